"""MRF refinement of plane-sweep height maps: the options, the conventions and ``refine``.

Winner-take-all over a filtered cost volume fails where the image has little texture (plain
roofs, roads, plazas): the cost curve is flat and its minimum is noise. Both methods here add a
smoothness prior in the plane index (the label) and trade speed for accuracy:

- ``sgm`` (:mod:`satsweep.dense.sgm`): semi-global matching (Hirschmueller 2008) along 4 or 8 scanline directions on the
  device (``kernels/sgm.cl``), the path costs summed, then the sweep's streaming winner-take-all
  (``kernels/wta.cl``) on the aggregated volume. Fast: a few passes over the volume.
- ``graphcut`` (:mod:`satsweep.dense.graphcut`): alpha-expansion (Boykov, Veksler and Zabih 2001) with PyMaxflow on the host,
  minimising the energy below exactly per expansion move. Bounded in cost by solving
  coarse-to-fine and restricting each pixel to a window of labels around the coarser solution,
  and by tiling with overlap.

Both take the cost volume as a ``CostVolume`` (:mod:`satsweep.dense.volume`), the one type the
sweep makes: SGM any of them (on the host or the device, plane-major, pixel-major or ragged, with
or without plane windows), the graph cut a host, plane-major one over every plane.

Conventions (shared by both; they are those of ``satsweep.dense.sweep``):

- The cost volume: ``cost[d, y, x]`` (plane-major) is the (filtered) matching
  cost of reference pixel (x, y) on plane d, lower is better, mostly in [0, cost_scale]. For the
  sweep's costs ``cost_scale`` is the number of census bits (``SweepOptions.census_bits``): the
  penalties are fractions of it. The sweep's AD and gradient terms can add up to ``ad_weight +
  grad_weight`` more (``SweepOptions.max_cost``, also the cost of a pixel that no source sees).
  Entries at or below
  ``SATSWEEP_INVALID / 2`` (the device-side invalid marker, -1e30) and NaN are read as
  ``cost_scale``.
- The label of a pixel is a plane index; the planes are at the equally spaced heights
  ``heights[L]`` (metres, ENU up), so a one-label change is one plane spacing. With plane
  windows (``CostVolume.label_base``), label d of pixel p is plane label_base[p] + d and
  ``heights`` holds every plane.
- Penalties are given as fractions of ``cost_scale``, so that they do not depend on the census
  window size.
- ``guide`` is the reference image (H, W), tonemapped to about [0, 1]: smoothness is weaker across
  its edges (contrast-sensitive weights), where height discontinuities are likely.
- ``visible`` (optional) tells where a pixel is seen by at least one source: (H, W), or (L, H, W)
  per plane. A result pixel is valid when it is visible at its chosen plane and, with
  ``reject_range_edges``, its plane is neither the first nor the last, as in the sweep's WTA.

Results (``MRFResult``) carry the fields of ``sweep.HeightMap`` that describe pixels (height
with NaN where invalid, fractional plane index, confidence in [0, 1], validity) plus the integer
labels, so a pipeline can take either.

Energy minimised by the graph cut (``mrf_energy`` computes it):

    E(l) = sum_p D(p, l_p) + sum_{p~q, 4-connected} w_pq min(|l_p - l_q|, T)
    w_pq = gc_smoothness * cost_scale * exp(-(I_p - I_q)^2 / (2 gc_edge_sigma^2))

D is the cost volume; truncated linear smoothness is a metric, so each expansion move is an exact
minimum cut (Kolmogorov and Zabih 2004).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from satsweep.dense.volume import CostVolume
from satsweep.errors import DeviceError, InputError
from satsweep.opencl.constants import SATSWEEP_INVALID
from satsweep.opencl.device import Device
from satsweep.options import Options


@dataclasses.dataclass(frozen=True)
class MRFOptions(Options):
    """Options of the MRF refinement of a sweep's cost volume (penalties in cost_scale units)."""

    method: Literal["none", "sgm", "graphcut"] = "sgm"  # none: the sweep's winner-take-all;
    # sgm: semi-global matching on the device; graphcut: alpha-expansion on the host
    tile_px: int = 1024  # a reference is swept and refined in tiles of at most this side (px)
    sgm_p1: float = 0.5  # SGM penalty of a one-plane height change (fraction of cost_scale)
    sgm_p2: float = 1.25  # SGM penalty of a larger jump (fraction of cost_scale), before adaptation
    sgm_sweep_gf_radius: int | None = 2  # guided-filter radius (px) of the sweep under SGM; None:
    # [sweep] gf_radius
    sgm_consensus_gf_radius: int | None = 1  # ... in an area whose DSM is the consensus of many
    # reference views' height maps ([dsm] fusion; 6 or more): it rejects each map's blunders,
    # and a wider filter erodes crowns and roof edges; None: sgm_sweep_gf_radius
    sgm_dense_consensus_gf_radius: int | None = 0  # ... for a reference of such an area whose
    # pixels are finer than the DSM's cells (2 pixels per cell or more, as 0.3 m pixels on 0.5 m
    # cells: each cell already pools several pixels); 0: no filter; None: sgm_consensus_gf_radius
    median_radius_m: float = 0.0  # an edge-aware weighted median of each height map, the
    # reference image as guide (satsweep.dense.median): its window's radius (m); 0: none
    consensus_median_radius_m: float = 1.2  # ... in an area whose DSM is the consensus of many
    # reference views' height maps under SGM (as sgm_consensus_gf_radius): it removes the height
    # noise of flat areas that the consensus keeps; 0: median_radius_m
    median_sigma: float = 0.04  # guide difference (image in [0, 1]) at which a neighbour's weight
    # in the median falls by exp(-1/2)
    sgm_paths: Literal[4, 8] = 8  # scanline directions aggregated
    sgm_p2_sigma: float = 0.05  # guide difference (image in [0, 1]) that halves P2; 0: no adaptation
    sgm_work_group: int = 0  # work-items per scanline (power of two); 0: 1 on CPUs, 32 on GPUs
    sgm_scan: bool = True  # one work-item per scanline: all directions in two raster scans rather
    # than a launch per direction
    sgm_subplane: Literal["equiangular", "parabola"] = "equiangular"  # sub-plane fit through the
    # aggregated costs around the best plane
    gc_sweep_gf_radius: int | None = 3  # guided-filter radius (px) of the sweep under the graph
    # cut; None: [sweep] gf_radius
    gc_smoothness: float = 0.15  # graph-cut weight of a one-plane change between neighbours
    # (fraction of cost_scale)
    gc_truncation_labels: int = 4  # planes beyond which the graph cut's smoothness stays constant
    gc_edge_sigma: float = 0.1  # guide scale of the contrast weight exp(-dI^2 / 2 s^2); 0: none
    gc_label_window: int = 3  # labels (planes) each pixel may move from the coarser level's
    gc_levels: int = 2  # coarse-to-fine levels below full resolution
    gc_tile: int = 256  # graph-cut tile side (px) at full resolution
    gc_tile_overlap: int = 16  # pixels each graph-cut tile extends past its kept part
    gc_iterations: int = 2  # most sweeps over the labels
    tile_overlap_px: int = 32  # pixels each reference tile is swept and refined past its kept part
    # (references wider than tile_px only). 64 -> 32 on the 19-view 1700 px stacks: 104.9 /
    # 124.1 -> 94.9 / 117.8 s, DFC MAE 0.8238 / 0.8668 -> 0.8233 / 0.8663 m; a 1470 x 1452
    # reference's SGM map differs from one untiled by > 0.5 m at 0.116% -> 0.139% of its
    # pixels (16: 0.204%)

    ADVANCED = ("sgm_p1", "sgm_p2", "sgm_sweep_gf_radius", "sgm_consensus_gf_radius",
                "sgm_dense_consensus_gf_radius",
                "median_radius_m", "consensus_median_radius_m", "median_sigma",
                "sgm_paths", "sgm_p2_sigma", "sgm_work_group", "sgm_scan", "sgm_subplane",
                "gc_sweep_gf_radius", "gc_smoothness", "gc_truncation_labels", "gc_edge_sigma",
                "gc_label_window", "gc_levels", "gc_tile", "gc_tile_overlap", "gc_iterations",
                "tile_overlap_px")

    def for_consensus(self) -> "MRFOptions":
        """The options of an area whose DSM is a consensus of many height maps: under SGM, the
        sweep filters with ``sgm_consensus_gf_radius`` and the height maps take the median of
        ``consensus_median_radius_m`` (each when set)."""
        if self.method != "sgm":
            return self
        changes: dict = {}
        if self.sgm_consensus_gf_radius is not None:
            changes["sgm_sweep_gf_radius"] = self.sgm_consensus_gf_radius
        if self.consensus_median_radius_m > 0.0:
            changes["median_radius_m"] = self.consensus_median_radius_m
        return self.replace(**changes) if changes else self

    def for_dense_pixels(self) -> "MRFOptions":
        """The options (already ``for_consensus``) of a reference whose pixels are finer than
        the DSM's cells: under SGM, the sweep filters with ``sgm_dense_consensus_gf_radius``
        when that is set."""
        if self.method != "sgm" or self.sgm_dense_consensus_gf_radius is None:
            return self
        return self.replace(sgm_sweep_gf_radius=self.sgm_dense_consensus_gf_radius)

    def check(self) -> None:
        self._require(math.isfinite(self.sgm_p1) and self.sgm_p1 >= 0.0, "sgm_p1", "must be >= 0")
        self._require(math.isfinite(self.sgm_p2) and self.sgm_p2 >= self.sgm_p1, "sgm_p2",
                      "must be finite and >= sgm_p1")
        self._require(self.sgm_sweep_gf_radius is None or 0 <= self.sgm_sweep_gf_radius <= 64,
                      "sgm_sweep_gf_radius", "must be in [0, 64] (or None)")
        self._require(self.sgm_consensus_gf_radius is None
                      or 0 <= self.sgm_consensus_gf_radius <= 64,
                      "sgm_consensus_gf_radius", "must be in [0, 64] (or None)")
        self._require(self.sgm_dense_consensus_gf_radius is None
                      or 0 <= self.sgm_dense_consensus_gf_radius <= 64,
                      "sgm_dense_consensus_gf_radius", "must be in [0, 64] (or None)")
        for name in ("median_radius_m", "consensus_median_radius_m"):
            value = getattr(self, name)
            self._require(math.isfinite(value) and 0.0 <= value <= 100.0, name,
                          "must be in [0, 100] metres (0: none)")
        self._require(math.isfinite(self.median_sigma) and self.median_sigma > 0.0,
                      "median_sigma", "must be > 0")
        self._require(self.gc_sweep_gf_radius is None or 0 <= self.gc_sweep_gf_radius <= 64,
                      "gc_sweep_gf_radius", "must be in [0, 64] (or None)")
        self._require(math.isfinite(self.sgm_p2_sigma) and self.sgm_p2_sigma >= 0.0,
                      "sgm_p2_sigma", "must be >= 0 (0 disables the adaptation)")
        wg = self.sgm_work_group
        self._require(wg == 0 or (1 <= wg <= 1024 and wg & (wg - 1) == 0), "sgm_work_group",
                      "must be 0 (automatic) or a power of two up to 1024")
        self._require(math.isfinite(self.gc_smoothness) and self.gc_smoothness >= 0.0,
                      "gc_smoothness", "must be >= 0")
        self._require(self.gc_truncation_labels >= 1, "gc_truncation_labels", "must be >= 1")
        self._require(self.tile_px >= 64, "tile_px", "must be >= 64 pixels")
        self._require(0 <= self.tile_overlap_px <= 1024, "tile_overlap_px",
                      "must be in [0, 1024] pixels")
        self._require(math.isfinite(self.gc_edge_sigma) and self.gc_edge_sigma >= 0.0,
                      "gc_edge_sigma", "must be >= 0 (0: no contrast sensitivity)")
        self._require(self.gc_label_window >= 1, "gc_label_window", "must be >= 1")
        self._require(0 <= self.gc_levels <= 6, "gc_levels", "must be in [0, 6]")
        self._require(self.gc_tile >= 16, "gc_tile", "must be >= 16 pixels")
        self._require(0 <= self.gc_tile_overlap <= self.gc_tile // 2, "gc_tile_overlap",
                      "must be in [0, gc_tile / 2]")
        self._require(1 <= self.gc_iterations <= 100, "gc_iterations", "must be in [1, 100]")


@dataclasses.dataclass
class MRFResult:
    """Per-pixel outputs of an MRF refinement, arrays of the reference image's shape.

    height: metres (the planes' heights interpolated at plane_index, float64); NaN where invalid.
    plane_index: fractional plane index (float32), defined everywhere: the label plus an offset
        in [-0.5, 0.5] fitted through the costs of the label and its neighbours (SGM:
        ``sgm_subplane``, on the aggregated costs; graph cut: a parabola through the data costs).
    labels: the integer label (plane index) chosen by the MRF (int32).
    confidence: in [0, 1] (float32): (second-lowest local minimum - value at the label) of the
        aggregated cost (SGM, divided by paths * cost_scale) or of the conditional energy of each
        pixel given its neighbours (graph cut, divided by cost_scale).
    valid: visible at the chosen plane and, with reject_range_edges, not at an end of the range.
    cost_min: aggregated cost (SGM) or data cost (graph cut) at the label (float32).
    seconds: wall time of the refinement; energy: the graph-cut energy E (NaN for SGM).
    """

    height: np.ndarray
    plane_index: np.ndarray
    labels: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray
    cost_min: np.ndarray
    seconds: float = 0.0
    energy: float = math.nan


# ---------------------------------------------------------------------------------------------
# input checks
# ---------------------------------------------------------------------------------------------
def _check_heights(heights, n_labels: int, *, banded: bool = False) -> np.ndarray:
    """The plane heights: one per label, or with label bands (``banded``) at least as many
    planes as the window of labels."""
    h = np.asarray(heights, dtype=np.float64).reshape(-1)
    if (h.size < n_labels) if banded else (h.size != n_labels):
        raise InputError(None, f"heights: {h.size} values for a cost volume of {n_labels} planes")
    if not np.isfinite(h).all():
        raise InputError(None, "heights: holds NaN or infinite values")
    if h.size > 1:
        d = np.diff(h)
        if not (np.all(d > 0) or np.all(d < 0)):
            raise InputError(None, "heights: must be strictly monotonic")
        if not np.allclose(d, d[0], rtol=1e-6, atol=0.0):
            raise InputError(None, "heights: the planes must be equally spaced (labels are "
                                   "plane indices and the smoothness counts planes)")
    return h


def _check_guide(guide, shape: tuple[int, int]) -> np.ndarray:
    g = np.asarray(guide)
    if g.shape != shape:
        raise InputError(None, f"guide: shape {g.shape}, expected {shape} (the cost volume's H, W)")
    g = np.ascontiguousarray(g, dtype=np.float32)
    if not np.isfinite(g).all():
        raise InputError(None, "guide: holds NaN or infinite values")
    return g


def _host_volume(volume: CostVolume, method: str) -> np.ndarray:
    """The (L, H, W) array of a host, plane-major volume over every plane, which ``method``
    requires (InputError for any other)."""
    if not isinstance(volume, CostVolume):
        raise InputError(None, f"cost_volume: expected a CostVolume, got {type(volume).__name__}")
    if volume.on_device or volume.layout != "plane_major":
        raise InputError(None, f"cost_volume: {method} takes a plane-major host volume, not a "
                               f"{volume.layout} {'device' if volume.on_device else 'host'} one")
    if volume.label_base is not None:
        raise InputError(None, f"label_base: {method} takes no label bands (SGM does)")
    return volume.data


def _check_visible(visible, shape: tuple[int, int, int]) -> np.ndarray | None:
    if visible is None:
        return None
    v = np.asarray(visible, dtype=bool)
    if v.shape != shape and v.shape != shape[1:]:
        raise InputError(None, f"visible: shape {v.shape}, expected {shape[1:]} or {shape}")
    return v


def _check_windows(volume: CostVolume, n_planes: int) -> tuple[np.ndarray | None,
                                                                 np.ndarray | None]:
    """The volume's (label_base, label_count) (None, None: no bands; a count of None: all its
    labels), each pixel's window inside the ``n_planes`` planes (InputError otherwise)."""
    b, n = volume.label_base, volume.label_count
    if b is None:
        return None, None
    count = np.full(b.shape, volume.n_labels) if n is None else n
    if b.size and (b + count).max() > n_planes:
        raise InputError(None, f"label_base: windows of {count.min()}..{count.max()} labels from "
                               f"planes {b.min()}..{b.max()} leave the {n_planes} planes")
    return b, n


def _check_scale(cost_scale: float) -> float:
    s = float(cost_scale)
    if not (math.isfinite(s) and s > 0.0):
        raise InputError(None, f"cost_scale = {cost_scale!r}: must be > 0 (the worst cost)")
    return s


def _sanitised(cost: np.ndarray, cost_scale: float) -> np.ndarray:
    """float32 copy-if-needed of the volume with invalid markers replaced by cost_scale."""
    c = np.asarray(cost, dtype=np.float32)
    bad = ~(c > np.float32(0.5 * SATSWEEP_INVALID))
    if bad.any():
        c = np.where(bad, np.float32(cost_scale), c)
    return c


# ---------------------------------------------------------------------------------------------
# shared finalisation (labels -> heights, validity)
# ---------------------------------------------------------------------------------------------
def _parabola_offset(cm: np.ndarray, c0: np.ndarray, cp: np.ndarray,
                     interior: np.ndarray) -> np.ndarray:
    """Vertex offset of the parabola through (-1, cm), (0, c0), (1, cp), in [-0.5, 0.5].

    The rule of wta.cl: 0 where the label is at an end of the range (``interior`` False) or the
    curvature is not positive.
    """
    cm, c0, cp = (np.asarray(a, dtype=np.float64) for a in (cm, c0, cp))
    denom = cm - 2.0 * c0 + cp
    ok = interior & (denom > 0.0)
    off = np.zeros(c0.shape)
    off[ok] = np.clip(0.5 * (cm[ok] - cp[ok]) / denom[ok], -0.5, 0.5)
    return off


def _equiangular_offset(cm: np.ndarray, c0: np.ndarray, cp: np.ndarray,
                        interior: np.ndarray) -> np.ndarray:
    """Vertex offset of the symmetric V (two lines of opposite slopes) through (-1, cm), (0, c0),
    (1, cp), c0 the smallest, in [-0.5, 0.5]: 0.5 (cm - cp) / (max(cm, cp) - c0).

    0 where the label is at an end of the range (``interior`` False), where c0 is not the smallest
    of the three, or where the three are equal.
    """
    cm, c0, cp = (np.asarray(a, dtype=np.float64) for a in (cm, c0, cp))
    rise = np.maximum(cm, cp) - c0
    ok = interior & (c0 <= cm) & (c0 <= cp) & (rise > 0.0)
    off = np.zeros(c0.shape)
    off[ok] = np.clip(0.5 * (cm[ok] - cp[ok]) / rise[ok], -0.5, 0.5)
    return off


def _finish(labels: np.ndarray, offset: np.ndarray, confidence: np.ndarray, cost_min: np.ndarray,
            heights: np.ndarray, visible: np.ndarray | None, reject_range_edges: bool,
            seconds: float, energy: float = math.nan, *, label_base: np.ndarray | None = None,
            n_labels: int | None = None) -> MRFResult:
    """Labels (and offsets) -> plane indices and heights. With ``label_base``, label d of a pixel
    is plane label_base + d of ``heights``, its window holds ``n_labels`` labels (an int, or one
    per pixel), and the range edges that ``reject_range_edges`` refuses are the window's (a
    minimum there may lie outside it)."""
    if n_labels is None:
        n_labels = heights.size
    window = labels.astype(np.int64)
    if label_base is not None:
        labels = window + label_base
    index = (labels + offset).astype(np.float32)
    if visible is None:
        valid = np.ones(labels.shape, bool)
    elif visible.ndim == 2:
        valid = visible.copy()
    else:
        valid = np.take_along_axis(visible, labels[None].astype(np.intp), axis=0)[0]
    if reject_range_edges:
        valid &= (window > 0) & (window < n_labels - 1)
    if heights.size > 1:
        height = np.interp(index.astype(np.float64), np.arange(heights.size), heights)
    else:
        height = np.full(labels.shape, heights[0])
    height[~valid] = np.nan
    return MRFResult(height=height, plane_index=index, labels=labels.astype(np.int32),
                     confidence=np.clip(confidence, 0.0, 1.0).astype(np.float32), valid=valid,
                     cost_min=np.asarray(cost_min, dtype=np.float32), seconds=seconds,
                     energy=energy)


# ---------------------------------------------------------------------------------------------
# graph cut (host, PyMaxflow)
# ---------------------------------------------------------------------------------------------
def edge_weights(guide: np.ndarray, options: MRFOptions,
                 cost_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Contrast-sensitive smoothness weights of the 4-connected grid (float64).

    Returns (horizontal (H, W-1) between (x, y) and (x+1, y), vertical (H-1, W) between (x, y)
    and (x, y+1)): ``gc_smoothness * cost_scale * exp(-dI^2 / (2 gc_edge_sigma^2))``.
    """
    g = np.asarray(guide, dtype=np.float64)
    lam = options.gc_smoothness * cost_scale
    dh, dv = np.diff(g, axis=1), np.diff(g, axis=0)
    if options.gc_edge_sigma == 0.0:
        return np.full(dh.shape, lam), np.full(dv.shape, lam)
    k = 1.0 / (2.0 * options.gc_edge_sigma ** 2)
    return lam * np.exp(-k * dh * dh), lam * np.exp(-k * dv * dv)


def mrf_energy(volume: CostVolume, guide, labels, options: MRFOptions, *,
               cost_scale: float = 1.0) -> float:
    """The graph-cut energy E(labels) (see the module docstring) of a host, plane-major volume,
    in cost units (float64)."""
    scale = _check_scale(cost_scale)
    return _energy(_sanitised(_host_volume(volume, "the energy"), scale), guide, labels, options,
                   scale)


def _energy(c: np.ndarray, guide, labels, options: MRFOptions, cost_scale: float) -> float:
    """mrf_energy of the sanitised (L, H, W) costs ``c``."""
    lab = np.asarray(labels, dtype=np.intp)
    if lab.shape != c.shape[1:]:
        raise InputError(None, f"labels: shape {lab.shape}, expected {c.shape[1:]}")
    wh, wv = edge_weights(_check_guide(guide, c.shape[1:]), options, cost_scale)
    t = options.gc_truncation_labels
    data = np.take_along_axis(c, lab[None], axis=0)[0].astype(np.float64).sum()
    sh = np.minimum(np.abs(np.diff(lab, axis=1)), t)
    sv = np.minimum(np.abs(np.diff(lab, axis=0)), t)
    return float(data + (wh * sh).sum() + (wv * sv).sum())


def wta_labels(volume: CostVolume) -> np.ndarray:
    """Winner-take-all labels (first argmin over planes) of a host, plane-major volume, int32."""
    return np.argmin(_host_volume(volume, "wta_labels"), axis=0).astype(np.int32)


def refine(device: Device | None, volume: CostVolume, guide, heights, options: MRFOptions, *,
           cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
           initial_labels=None) -> MRFResult | None:
    """Dispatch on ``options.method``: None for ``none`` (keep the sweep's WTA), else the result.

    SGM needs ``device`` and takes any ``CostVolume``; the graph cut runs on the host over a
    host, plane-major volume without plane windows, and uses ``initial_labels`` only with
    ``gc_levels`` = 0 (see ``graphcut_refine``).
    """
    from satsweep.dense.graphcut import graphcut_refine  # noqa: PLC0415 (they import this module)
    from satsweep.dense.sgm import sgm_refine  # noqa: PLC0415

    if options.method == "none":
        return None
    if options.method == "sgm":
        if device is None:
            raise DeviceError("MRF method sgm needs an OpenCL device")
        return sgm_refine(device, volume, guide, heights, options, cost_scale=cost_scale,
                          visible=visible, reject_range_edges=reject_range_edges)
    return graphcut_refine(volume, guide, heights, options, cost_scale=cost_scale,
                           visible=visible, reject_range_edges=reject_range_edges,
                           initial_labels=initial_labels)
