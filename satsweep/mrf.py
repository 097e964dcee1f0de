"""MRF refinement of plane-sweep height maps: semi-global matching (OpenCL) and graph cuts.

Winner-take-all over a filtered cost volume fails where the image has little texture (plain
roofs, roads, plazas): the cost curve is flat and its minimum is noise. Both methods here add a
smoothness prior in the plane index (the label) and trade speed for accuracy:

- ``sgm``: semi-global matching (Hirschmueller 2008) along 4 or 8 scanline directions on the
  device (``kernels/sgm.cl``), the path costs summed, then the sweep's streaming winner-take-all
  (``kernels/wta.cl``) on the aggregated volume. Fast: a few passes over the volume.
- ``graphcut``: alpha-expansion (Boykov, Veksler and Zabih 2001) with PyMaxflow on the host,
  minimising the energy below exactly per expansion move. Bounded in cost by solving
  coarse-to-fine and restricting each pixel to a window of labels around the coarser solution,
  and by tiling with overlap.

Conventions (shared by both; they are those of ``satsweep.sweep``):

- The cost volume is (L, H, W) float32, plane-major: ``cost[d, y, x]`` is the (filtered) matching
  cost of reference pixel (x, y) on plane d, lower is better, mostly in [0, cost_scale]. For the
  sweep's costs ``cost_scale`` is the number of census bits (``SweepOptions.census_bits``): the
  penalties are fractions of it. The sweep's AD and gradient terms can add up to ``ad_weight +
  grad_weight`` more (``SweepOptions.max_cost``, also the cost of a pixel that no source sees).
  Entries at or below
  ``SATSWEEP_INVALID / 2`` (the device-side invalid marker, -1e30) and NaN are read as
  ``cost_scale``.
- The label of a pixel is a plane index; the planes are at the equally spaced heights
  ``heights[L]`` (metres, ENU up), so a one-label change is one plane spacing.
- Penalties are given as fractions of ``cost_scale``, so that they do not depend on the census
  window size.
- ``guide`` is the reference image (H, W), tonemapped to about [0, 1]: smoothness is weaker across
  its edges (contrast-sensitive weights), where height discontinuities are likely.
- ``visible`` (optional) tells where a pixel is seen by at least one source: (H, W), or (L, H, W)
  per plane. A result pixel is valid when it is visible at its chosen plane and, with
  ``reject_range_edges``, its plane is neither the first nor the last, as in the sweep's WTA.

Results (``MRFResult``) carry the fields of ``sweep.SweepResult`` that describe pixels (height
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
import time
from typing import Literal

import numpy as np

from .device import Device
from .errors import DeviceError, InputError
from .options import Options
from .sweep import WTA_VEC

# The device-side invalid marker (kernels/common.h SATSWEEP_INVALID); costs at or below half of
# it are missing.
SATSWEEP_INVALID = -1.0e30
# Scanline directions (dx, dy) of SGM, in the order their path costs are added; 4 paths use the
# first four (horizontal and vertical), 8 paths all of them.
SGM_DIRECTIONS: tuple[tuple[int, int], ...] = (
    (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1))
# Most labels sgm.cl accepts (SGM_MAX_LABELS there): local memory holds one float per label.
SGM_MAX_LABELS = 1024
# Work-items per scanline on GPUs when sgm_work_group = 0 (a warp/wavefront shares a scanline).
_SGM_GPU_WORK_GROUP = 32
# One-work-item SGM (CPUs): scanlines per work-item of the vertical and diagonal directions, which
# then read neighbouring pixels each round (sgm.cl). Measured on PoCL, 770^2 x 136 labels, one
# accumulating path: vertical 0.143 s with 1, 0.117 s with 4, 0.066 s with 8, 0.087 s with 16;
# diagonal 0.106 / 0.068 / 0.073 / 0.088 s. Rows stay one per work-item: they are contiguous
# already (0.046 s with 1, 0.067 s with 8). Private arrays hold 2 x (3 labels + 4) floats per
# scanline, capped at SGM_PRIVATE_BYTES per work-item (fewer scanlines for many labels).
SGM_CPU_LINES = 8
SGM_PRIVATE_BYTES = 64 * 1024
# sgm.cl's SGM_SCAN_GUARD: +inf entries on each side of a step in sgm_scan's scratch.
_SGM_SCAN_GUARD = 8
# Floats of per-pixel state of wta.cl (WTA_NSTATE) and their order there.
_WTA_NSTATE = 8
_S_M1, _S_I1, _S_M1P, _S_M1N, _S_M2, _S_PREV, _S_PREV2, _S_MAX = range(_WTA_NSTATE)
# wta.cl's "infinite" cost (WTA_BIG).
_WTA_BIG = float(np.float32(3.0e38))


@dataclasses.dataclass(frozen=True)
class MRFOptions(Options):
    """Options of the MRF refinement of a sweep's cost volume (penalties in cost_scale units)."""

    method: Literal["none", "sgm", "graphcut"] = "sgm"  # none: the sweep's winner-take-all; sgm:
    # semi-global matching on the device; graphcut: alpha-expansion on the host (see README table)
    sgm_p1: float = 0.5  # SGM penalty of a one-plane height change (fraction of cost_scale);
    # tuned with tools/bench_e2e.py together with sgm_p2 and sgm_sweep_gf_radius
    # (docs/measurements.md: better on all 8 scenes of seeds 0-3 and against S2P than 0.4 / 1.0 /
    # radius 3, and 0.4 beat 0.15 before). Much more over-smooths: a path pays max(P1, P2') to
    # jump onto a weakly textured roof, whose census evidence is only ~0.02-0.03 cost_scale per
    # pixel, so roofs keep the ground's height (tests/test_mrf.py weak-texture roof: p1 0.6 /
    # p2 2.0 fails)
    sgm_p2: float = 1.25  # SGM penalty of a larger jump (fraction of cost_scale), before adaptation
    sgm_sweep_gf_radius: int | None = 2  # guided-filter radius of the sweep whose costs SGM
    # refines, in place of [sweep] gf_radius (None: that one). SGM aggregates along its paths,
    # so it wants less spatial filtering than the winner-take-all alone (whose best radius is 5)
    sgm_paths: Literal[4, 8] = 8  # number of scanline directions aggregated
    sgm_p2_sigma: float = 0.05  # guide intensity difference (image in [0, 1]) at which P2 is
    # halved: P2' = max(P1, P2 / (1 + |dI| / sigma)); 0 disables the adaptation
    sgm_work_group: int = 0  # work-items per scanline (power of two); 0: 1 on CPUs, 32 on GPUs
    sgm_scan: bool = True  # with one work-item per scanline (CPUs): all directions in two raster
    # scans run side by side (sgm.cl sgm_scan), each pixel's volumes read and written once per
    # scan instead of once per direction; the same path costs, summed in another order (label
    # windows of a coarse-to-fine search too). False: one sgm_path launch per direction
    sgm_subplane: Literal["equiangular", "parabola"] = "equiangular"  # sub-plane fit through the
    # aggregated costs of the best plane and its neighbours: SGM's sums are V-shaped near their
    # minimum (linear P1 penalties), which a symmetric V fits; tools/bench_e2e.py, 4 scenes:
    # median 0.210 -> 0.196 m, completeness unchanged, against the parabola
    gc_sweep_gf_radius: int | None = 3  # guided-filter radius of the sweep whose costs the graph
    # cut refines, in place of [sweep] gf_radius (None: that one). tools/bench_e2e.py, seeds 0-1:
    # radius 5 lowers the median (0.240 -> 0.219 m) but loses completeness (85.8 -> 84.5%; with
    # gc_smoothness 0.1 or 0.25 too), so the graph cut keeps the radius it was tuned with
    gc_smoothness: float = 0.15  # graph-cut weight of a one-plane change between 4-neighbours
    # (fraction of cost_scale), before the contrast weight
    gc_truncation_labels: int = 4  # smoothness is linear up to this many planes, then constant
    gc_edge_sigma: float = 0.1  # guide intensity scale of the contrast weight exp(-dI^2/(2 s^2));
    # 0: no contrast sensitivity
    gc_label_window: int = 3  # each pixel may take labels within +-window of the coarser level's
    # labels around it (the range of its 3x3 coarse neighbourhood), or of initial_labels
    gc_levels: int = 2  # coarse-to-fine levels below full resolution (each halves the image); the
    # coarsest level is solved over the full label range; 0: one level, window around the WTA
    gc_tile: int = 256  # graph-cut tile side (pixels) at full resolution
    gc_tile_overlap: int = 16  # pixels each tile extends past its kept part on every side
    gc_iterations: int = 2  # most sweeps over the labels (stops earlier when nothing changes)
    tile_px: int = 1024  # reconstruct sweeps and refines a reference in tiles of at most this
    # side (pixels), so that memory holds one tile's cost volume, not the whole image's; smaller
    # when the device's memory budget needs it (satsweep.pipeline.mrf_tile_side)
    tile_overlap_px: int = 64  # pixels each such tile is swept and refined past its kept part on
    # every side, so that SGM paths and graph-cut neighbourhoods reach into the neighbours

    def check(self) -> None:
        self._require(math.isfinite(self.sgm_p1) and self.sgm_p1 >= 0.0, "sgm_p1", "must be >= 0")
        self._require(math.isfinite(self.sgm_p2) and self.sgm_p2 >= self.sgm_p1, "sgm_p2",
                      "must be finite and >= sgm_p1")
        self._require(self.sgm_sweep_gf_radius is None or 0 <= self.sgm_sweep_gf_radius <= 64,
                      "sgm_sweep_gf_radius", "must be in [0, 64] (or None)")
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


def _check_volume(cost_volume) -> np.ndarray:
    c = np.asarray(cost_volume)
    if c.ndim != 3 or min(c.shape) < 1:
        raise InputError(None, f"cost_volume: expected (planes, H, W), got shape {c.shape}")
    if not np.issubdtype(c.dtype, np.floating):
        raise InputError(None, f"cost_volume: expected floats, got dtype {c.dtype}")
    return c


def _check_visible(visible, shape: tuple[int, int, int]) -> np.ndarray | None:
    if visible is None:
        return None
    v = np.asarray(visible, dtype=bool)
    if v.shape != shape and v.shape != shape[1:]:
        raise InputError(None, f"visible: shape {v.shape}, expected {shape[1:]} or {shape}")
    return v


def _check_label_base(label_base, shape: tuple[int, int], n_labels: int,
                      n_planes: int | None, label_count=None) -> tuple[np.ndarray | None,
                                                                       np.ndarray | None]:
    """The (H, W) int32 first plane of each pixel's label window and its (H, W) int32 label
    count (None, None: no bands; a count of None: n_labels everywhere): label d < count[p] of
    pixel p stands for plane label_base[p] + d, which must lie in [0, n_planes)."""
    if label_base is None:
        if label_count is not None:
            raise InputError(None, "label_count: needs label_base (the windows' first planes)")
        return None, None
    b = np.asarray(label_base)
    if b.shape != shape or not np.issubdtype(b.dtype, np.integer):
        raise InputError(None, f"label_base: expected integers of shape {shape}, got "
                               f"{b.dtype} {b.shape}")
    if label_count is None:
        n = np.full(shape, n_labels, np.int32)
    else:
        n = np.asarray(label_count)
        if n.shape != shape or not np.issubdtype(n.dtype, np.integer):
            raise InputError(None, f"label_count: expected integers of shape {shape}, got "
                                   f"{n.dtype} {n.shape}")
        if n.size and (n.min() < 1 or n.max() > n_labels):
            raise InputError(None, f"label_count: counts {n.min()}..{n.max()} outside 1.."
                                   f"{n_labels} (the volume's labels per pixel)")
    if b.size and (b.min() < 0 or (n_planes is not None and (b + n).max() > n_planes)):
        raise InputError(None, f"label_base: windows of {n.min()}..{n.max()} labels from planes "
                               f"{b.min()}..{b.max()} leave the {n_planes} planes")
    return (np.ascontiguousarray(b, dtype=np.int32),
            None if label_count is None else np.ascontiguousarray(n, dtype=np.int32))


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
# semi-global matching (device)
# ---------------------------------------------------------------------------------------------
def sgm_work_group(device: Device, options: MRFOptions, n_labels: int) -> int:
    """Work-items per scanline: the option, or 1 on CPUs and 32 on GPUs, within device limits."""
    wg = options.sgm_work_group
    if wg == 0:
        wg = _SGM_GPU_WORK_GROUP if device.info.kind == "gpu" else 1
    max_wg = int(device.cl_device.max_work_group_size)
    while wg > 1 and wg > max_wg:
        wg //= 2
    local_bytes = 4 * (n_labels + wg)
    if local_bytes > int(device.cl_device.local_mem_size):
        raise DeviceError(f"{device.info.label}: SGM over {n_labels} planes needs "
                          f"{local_bytes} bytes of local memory, the device has "
                          f"{int(device.cl_device.local_mem_size)}")
    return wg


def sgm_program_requests(device: Device, options: MRFOptions,
                         n_labels: int) -> list[tuple[str, dict]]:
    """The (source, defines) of the programs that SGM over ``n_labels`` labels builds: sgm.cl,
    and wta.cl for the winner-take-all of the sums (``Device.prebuild`` takes this list)."""
    wg = sgm_work_group(device, options, n_labels)
    lines = sgm_lines_per_item(wg, n_labels)
    return [("sgm", {"SGM_NL": n_labels, "SGM_WG": wg, "SGM_LINES": lines}),
            ("wta", _WTA_PIXEL_MAJOR_DEFINES)]


# wta.cl's defines for wta_pixel_major: NSRC and the census radii matter only to wta_finalize,
# which SGM does not use.
_WTA_PIXEL_MAJOR_DEFINES = {"NSRC": 1, "CENSUS_RX": 1, "CENSUS_RY": 1, "WTA_VEC": WTA_VEC}


def sgm_lines_per_item(work_group: int, n_labels: int) -> int:
    """Most scanlines one work-item of sgm_path steps together (sgm.cl's SGM_LINES): 1 with a
    work-group per scanline, else ``SGM_CPU_LINES`` within ``SGM_PRIVATE_BYTES`` of private
    arrays."""
    if work_group > 1:
        return 1
    per_line = 2 * 4 * (3 * n_labels + 4)
    return max(1, min(SGM_CPU_LINES, SGM_PRIVATE_BYTES // per_line))


def _check_device_array(device: Device, arr, layout: str, instead: str) -> None:
    """A device volume must be a C-contiguous 3-D float32 pyopencl Array of this device's context
    without offset (``layout`` and ``instead`` complete the messages)."""
    if arr.dtype != np.float32 or arr.ndim != 3 or not arr.flags.c_contiguous:
        raise InputError(None, f"cost_volume: device array must be C-contiguous float32 "
                               f"{layout}, got {arr.dtype} {arr.shape}")
    if arr.context != device.context:
        raise InputError(None, "cost_volume: device array lives in another OpenCL context")
    if arr.offset != 0:
        raise InputError(None, f"cost_volume: device array is a view with an offset; pass a "
                               f"{instead}")


def _as_device_volume(device: Device, cost_volume, shape):
    """(buffer, (L, H, W), owned) for a numpy volume, a pyopencl Array or a Buffer; owned: the
    buffer was uploaded here (from a numpy volume) and may be released after use."""
    import pyopencl as cl  # noqa: PLC0415
    import pyopencl.array as cla  # noqa: PLC0415

    if isinstance(cost_volume, cla.Array):
        _check_device_array(device, cost_volume, "(planes, H, W)", "copy or its buffer with shape=")
        return cost_volume.data, tuple(int(s) for s in cost_volume.shape), False
    if isinstance(cost_volume, cl.Buffer):
        if shape is None or len(shape) != 3:
            raise InputError(None, "cost_volume: a pyopencl Buffer needs shape=(planes, H, W)")
        shape = tuple(int(s) for s in shape)
        if cost_volume.size < 4 * shape[0] * shape[1] * shape[2]:
            raise InputError(None, f"cost_volume: buffer of {cost_volume.size} bytes is smaller "
                                   f"than float32 {shape}")
        return cost_volume, shape, False
    c = np.ascontiguousarray(_check_volume(cost_volume), dtype=np.float32)
    buf = cl.Buffer(device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=c)
    return buf, c.shape, True


def _pixel_major_volume(device: Device, cost_volume) -> tuple[int, int, int]:
    """(L, H, W) of a PIXEL-MAJOR (H, W, L) device volume, checked as ``_as_device_volume``
    checks a plane-major one."""
    import pyopencl.array as cla  # noqa: PLC0415

    if not isinstance(cost_volume, cla.Array):
        raise InputError(None, "cost_volume: a pixel-major volume must be a C-contiguous float32 "
                               "pyopencl Array (H, W, L) without offset")
    _check_device_array(device, cost_volume, "(H, W, L)", "copy")
    h, w, n_labels = (int(s) for s in cost_volume.shape)
    if min(h, w, n_labels) < 1:
        raise InputError(None, f"cost_volume: expected (H, W, L), got shape {cost_volume.shape}")
    return n_labels, h, w


def _volume_shape(cost_volume, shape) -> tuple[int, int, int]:
    """(L, H, W) of a host volume, a pyopencl Array, or a Buffer with its ``shape``."""
    import pyopencl as cl  # noqa: PLC0415
    import pyopencl.array as cla  # noqa: PLC0415

    if isinstance(cost_volume, cla.Array):
        dims = tuple(int(s) for s in cost_volume.shape)
    elif isinstance(cost_volume, cl.Buffer):
        if shape is None or len(shape) != 3:
            raise InputError(None, "cost_volume: a pyopencl Buffer needs shape=(planes, H, W)")
        dims = tuple(int(s) for s in shape)
    else:
        dims = _check_volume(cost_volume).shape
    if len(dims) != 3 or min(dims) < 1:
        raise InputError(None, f"cost_volume: expected (planes, H, W), got shape {dims}")
    return dims  # type: ignore[return-value]


def _ragged_dims(device: Device, cost_volume, label_count, label_offset,
                 capacity) -> tuple[int, int, int]:
    """(L, H, W) of a RAGGED pixel-major device volume: a 1-D float32 ``pyopencl.array.Array``
    whose pixel p holds its label_count[p] labels from label_offset[p] on; L, the labels SGM is
    built for, is ``capacity``, at least the largest count (``sgm_refine`` gives the planes the
    windows are drawn from, so that SGM's program is the full search's, which the pipeline
    builds ahead)."""
    import pyopencl.array as cla  # noqa: PLC0415

    if label_count is None:
        raise InputError(None, "label_offset: needs label_count (a ragged volume's labels)")
    if not isinstance(cost_volume, cla.Array) or cost_volume.ndim != 1 \
            or cost_volume.dtype != np.float32 or cost_volume.offset != 0 \
            or cost_volume.context != device.context:
        raise InputError(None, "cost_volume: a ragged volume (label_offset) must be a 1-D float32 "
                               "pyopencl Array of this device's context without offset")
    n = np.asarray(label_count)
    o = np.asarray(label_offset)
    if n.ndim != 2 or o.shape != n.shape or o.dtype != np.uint64 \
            or not np.issubdtype(n.dtype, np.integer):
        raise InputError(None, f"label_offset: expected uint64 of the label counts' shape "
                               f"{n.shape}, got {o.dtype} {o.shape}")
    if n.size and (n.min() < 1 or int((o + n.astype(np.uint64)).max()) > cost_volume.size):
        raise InputError(None, f"label_offset: pixels' labels reach past the volume's "
                               f"{cost_volume.size} floats")
    if capacity is None or not int(n.max()) <= capacity <= SGM_MAX_LABELS:
        raise InputError(None, f"label_count: counts up to {int(n.max())} outside the "
                               f"{capacity} labels SGM is built for (at most {SGM_MAX_LABELS})")
    return int(capacity), n.shape[0], n.shape[1]


def sgm_scan_scratch_floats(width: int, n_labels: int) -> int:
    """Floats of sgm_scan's scratch for both scans (sgm.cl's 2 x SGM_SCAN_SCRATCH(w))."""
    return 2 * ((6 * width + 2) * (n_labels + 2 * _SGM_SCAN_GUARD) + 6 * width)


def _check_sgm_size(device: Device, dims: tuple[int, int, int]) -> None:
    """The label count fits sgm.cl and one volume fits a device allocation."""
    n_labels, h, w = dims
    if n_labels > SGM_MAX_LABELS:
        raise InputError(None, f"cost_volume: {n_labels} planes, SGM supports at most "
                               f"{SGM_MAX_LABELS}")
    nbytes = 4 * n_labels * h * w
    if nbytes > device.max_alloc_bytes:
        raise DeviceError(f"{device.info.label}: an SGM volume of {nbytes / 2**20:.0f} MiB "
                          f"({n_labels} planes x {h} x {w}) exceeds the largest allocation "
                          f"({device.max_alloc_bytes / 2**20:.0f} MiB): refine smaller tiles")


def sgm_aggregate(device: Device, cost_volume, guide, options: MRFOptions, *,
                  cost_scale: float = 1.0, shape: tuple[int, int, int] | None = None,
                  pixel_major: bool = False, label_base=None, label_count=None):
    """Sum of the SGM path costs over ``options.sgm_paths`` directions, on the device.

    ``cost_volume``: (L, H, W) float32 as a numpy array, a ``pyopencl.array.Array`` in the
    device's context, or a ``pyopencl.Buffer`` (then ``shape`` is required). Invalid entries
    (<= SATSWEEP_INVALID / 2, or NaN) count as ``cost_scale``. P1 = sgm_p1 * cost_scale,
    P2 = sgm_p2 * cost_scale, adapted to the guide as documented in kernels/sgm.cl. The volume
    is turned pixel-major on the device, aggregated, and turned back; at most three volumes are
    held at once. With ``pixel_major``, ``cost_volume`` is already in SGM's layout, a
    ``pyopencl.array.Array`` (H, W, L) (as ``PlaneSweep.run(volume_on_device=True)`` leaves
    it), whose entries are all valid costs, and it is aggregated as it is. ``label_base``
    ((H, W) integers, optional): label d of pixel p is plane label_base[p] + d (label bands of a
    coarse-to-fine search, kernels/sgm.cl). ``label_count`` ((H, W) integers in 1..L, with
    ``label_base``): pixel p has only labels d < label_count[p]; its other labels are neither
    read nor written (their sums are undefined). Returns a ``pyopencl.array.Array`` (L, H, W)
    float32 on the device.
    """
    import pyopencl.array as cla  # noqa: PLC0415

    agg_pm, prg, _ = _sgm_aggregate_pixel_major(device, cost_volume, guide, options,
                                                cost_scale=cost_scale, shape=shape,
                                                pixel_major=pixel_major, label_base=label_base,
                                                label_count=label_count)
    h, w, n_labels = agg_pm.shape
    queue = device.queue
    agg = cla.empty(queue, (n_labels, h, w), np.float32)
    device.kernel(prg, "sgm_to_plane_major")(queue, (h * w,), None, agg_pm.data, agg.data,
                                             np.int32(h * w))
    queue.finish()
    agg_pm.data.release()
    return agg


def _sgm_aggregate_pixel_major(device: Device, cost_volume, guide, options: MRFOptions, *,
                               cost_scale: float, shape: tuple[int, int, int] | None,
                               pixel_major: bool = False, label_base=None, label_count=None,
                               label_offset=None, label_capacity: int | None = None):
    """``sgm_aggregate`` without the final transposition: ((H, W, L) device array, program,
    bands), or for a ragged volume (``label_offset``) a 1-D device array laid out like it;
    bands: the (count, offset) device arrays of a banded volume (each pixel's labels and where
    they start; the regular layout's when the caller gave none), else None. ``label_capacity``:
    the labels SGM is built for over a ragged volume (``_ragged_dims``)."""
    import pyopencl.array as cla  # noqa: PLC0415

    scale = _check_scale(cost_scale)
    ragged = label_offset is not None
    if ragged and not pixel_major:
        raise InputError(None, "label_offset: a ragged volume is a pixel-major device volume "
                               "(pixel_major = True)")
    n_labels, h, w = _ragged_dims(device, cost_volume, label_count, label_offset,
                                  label_capacity) if ragged \
        else _pixel_major_volume(device, cost_volume) if pixel_major \
        else _volume_shape(cost_volume, shape)
    g = _check_guide(guide, (h, w))
    base, count = _check_label_base(label_base, (h, w), n_labels, None, label_count)
    if ragged and base is None:
        raise InputError(None, "label_offset: needs label_base (the windows' first planes)")
    if not ragged:
        _check_sgm_size(device, (n_labels, h, w))
    source, defines = sgm_program_requests(device, options, n_labels)[0]
    wg, max_lines = defines["SGM_WG"], defines["SGM_LINES"]
    prg = device.build(source, defines)
    queue = device.queue
    guide_d = cla.to_device(queue, g)
    # The kernel reads base and count only when banded; one-entry buffers stand in otherwise.
    base_d = cla.to_device(queue, base if base is not None else np.zeros(1, np.int32))
    if base is not None and count is None:
        count = np.full((h, w), n_labels, np.int32)
    count_d = cla.to_device(queue, count if count is not None else np.zeros(1, np.int32))
    if base is not None and not ragged:  # the regular layout: pixel p's labels from p L on
        label_offset = np.arange(h * w, dtype=np.uint64).reshape(h, w) * np.uint64(n_labels)
    offset_d = cla.to_device(queue, np.ascontiguousarray(label_offset, dtype=np.uint64)
                             if base is not None else np.zeros(1, np.uint64))
    n_pix = h * w
    i32, f32 = np.int32, np.float32
    if pixel_major:
        cost_pm = cost_volume  # the caller's, in SGM's layout already
    else:
        # Pixel-major copy of the costs (invalid entries replaced), aggregated in that layout.
        buf, _, owned = _as_device_volume(device, cost_volume, shape)
        cost_pm = cla.empty(queue, (h, w, n_labels), np.float32)
        device.kernel(prg, "sgm_to_pixel_major")(queue, (n_pix,), None, buf, cost_pm.data,
                                                 i32(n_pix), f32(scale))
        if owned:
            buf.release()  # the uploaded host volume is no longer needed on the device
    agg_pm = cla.empty(queue, cost_volume.shape if ragged else (h, w, n_labels), np.float32)
    inv_sigma = 0.0 if options.sgm_p2_sigma == 0.0 else 1.0 / options.sgm_p2_sigma
    if options.sgm_scan and wg == 1:
        _sgm_scans(device, prg, cost_pm, guide_d, agg_pm, (h, w, n_labels), options, scale,
                   inv_sigma, (base_d, count_d, offset_d, base is not None))
    else:
        kernel = device.kernel(prg, "sgm_path")
        for i, (dx, dy) in enumerate(SGM_DIRECTIONS[:options.sgm_paths]):
            n_lines = h if dy == 0 else (w if dx == 0 else w + h - 1)
            lines = 1 if dy == 0 else max_lines  # scanlines per work-item (1 when wg > 1)
            kernel(queue, (-(-n_lines // lines) * wg,), (wg,), cost_pm.data, guide_d.data,
                   agg_pm.data, i32(w), i32(h), i32(dx), i32(dy), f32(options.sgm_p1 * scale),
                   f32(options.sgm_p2 * scale), f32(inv_sigma), i32(1 if i > 0 else 0),
                   base_d.data, count_d.data, offset_d.data, i32(0 if base is None else 1),
                   i32(lines))
        queue.finish()
    if not pixel_major:
        cost_pm.data.release()
    return agg_pm, prg, ((count_d, offset_d) if base is not None else None)


def _sgm_scans(device: Device, prg, cost_pm, guide_d, agg_pm, dims: tuple[int, int, int],
               options: MRFOptions, scale: float, inv_sigma: float, bands) -> None:
    """agg_pm = the sum of the SGM path costs by sgm.cl's two raster scans (sgm_scan, its two
    phases) over dims = (H, W, L); bands = (base, count, offset, banded) as sgm_scan takes
    them."""
    base_d, count_d, offset_d, banded = bands
    import pyopencl.array as cla  # noqa: PLC0415

    h, w, n_labels = dims
    queue = device.queue
    scratch = cla.empty(queue, (sgm_scan_scratch_floats(w, n_labels),), np.float32)
    try:
        kernel = device.kernel(prg, "sgm_scan")
        for phase in (0, 1):
            kernel(queue, (2,), (1,), cost_pm.data, guide_d.data, agg_pm.data, scratch.data,
                   np.int32(w), np.int32(h), np.float32(options.sgm_p1 * scale),
                   np.float32(options.sgm_p2 * scale), np.float32(inv_sigma),
                   np.int32(options.sgm_paths), np.int32(phase), base_d.data, count_d.data,
                   offset_d.data, np.int32(1 if banded else 0))
        queue.finish()
    finally:
        scratch.data.release()


def _wta_state(device: Device, agg_pm, dims: tuple[int, int, int], bands=None) -> np.ndarray:
    """wta.cl's winner-take-all state (8, H, W) of a whole PIXEL-MAJOR device volume of dims
    (H, W, L), in one pass (``wta_pixel_major``: the same state as streaming the planes through
    ``wta_update``, without turning the volume plane-major first); with ``bands`` (the (count,
    offset) device arrays of ``_sgm_aggregate_pixel_major``), each pixel's state after its
    count planes from its offset on."""
    import pyopencl.array as cla  # noqa: PLC0415

    h, w, n_labels = dims
    prg = device.build("wta", _WTA_PIXEL_MAJOR_DEFINES)
    queue = device.queue
    state = cla.empty(queue, (_WTA_NSTATE, h, w), np.float32)
    counted = bands is not None
    count_d, offset_d = bands if counted else (cla.to_device(queue, np.zeros(1, np.int32)),
                                               cla.to_device(queue, np.zeros(1, np.uint64)))
    device.kernel(prg, "wta_pixel_major")(queue, (-(-h * w // WTA_VEC),), None, agg_pm.data,
                                          np.int32(h * w), np.int32(n_labels), count_d.data,
                                          offset_d.data, np.int32(1 if counted else 0),
                                          state.data)
    return state.get()


def sgm_refine(device: Device, cost_volume, guide, heights, options: MRFOptions, *,
               cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
               shape: tuple[int, int, int] | None = None,
               pixel_major: bool = False, label_base=None, label_count=None,
               label_offset=None) -> MRFResult:
    """SGM aggregation, then winner-take-all with sub-plane refinement and confidence.

    The argmin, the parabola and the second local minimum are those of the sweep's WTA
    (wta.cl, run on the aggregated volume); the confidence margin is divided by
    ``sgm_paths * cost_scale`` since each path adds about one cost. See ``sgm_aggregate`` for the
    inputs (``pixel_major``, ``label_base``, ``label_count``) and ``MRFResult`` for the outputs;
    with ``label_base``, ``heights`` holds every plane and ``visible`` must be 2-D, and the range
    edges are each pixel's window's (its first and its label_count-th label). ``label_offset``
    ((H, W) uint64, with pixel_major, label_base and label_count): the volume is RAGGED, a 1-D
    device array in which pixel p's label_count[p] labels start at label_offset[p] (as
    ``PlaneSweep.run`` leaves a coarse-to-fine volume: each pixel holds just its window).
    """
    t0 = time.perf_counter()
    ragged = label_offset is not None
    # SGM over a ragged volume is built for every plane, as over the full search's volume.
    capacity = np.size(heights) if ragged else None
    dims = _ragged_dims(device, cost_volume, label_count, label_offset, capacity) \
        if ragged else _pixel_major_volume(device, cost_volume) if pixel_major \
        else _volume_shape(cost_volume, shape)
    n_labels = dims[0]
    hts = _check_heights(heights, n_labels, banded=label_base is not None)
    base, count = _check_label_base(label_base, dims[1:], n_labels, hts.size, label_count)
    vis = _check_visible(visible, dims)
    if base is not None and vis is not None and vis.ndim == 3:
        raise InputError(None, "visible: with label_base, give one mask per pixel (H, W)")
    agg_pm, _, bands = _sgm_aggregate_pixel_major(device, cost_volume, guide, options,
                                                  cost_scale=cost_scale, shape=shape,
                                                  pixel_major=pixel_major, label_base=base,
                                                  label_count=count, label_offset=label_offset,
                                                  label_capacity=capacity)
    try:
        s = _wta_state(device, agg_pm, (dims[1], dims[2], n_labels), bands).astype(np.float64)
    finally:
        agg_pm.data.release()
    # Finish as wta_finalize does: the last plane is tested as a local minimum against +inf.
    n_last = n_labels if count is None else count  # labels per pixel
    m1, i1, m1p, m1n, m2 = s[_S_M1], s[_S_I1], s[_S_M1P], s[_S_M1N], s[_S_M2]
    last, before = s[_S_PREV], s[_S_PREV2]
    is_min = (last < before) & (last <= _WTA_BIG)
    better = is_min & (last < m1)
    m2 = np.where(better, m1, np.where(is_min & (last < m2), last, m2))
    m1 = np.where(better, last, m1)
    m1p = np.where(better, before, m1p)
    m1n = np.where(better, _WTA_BIG, m1n)
    i1 = np.where(better, n_last - 1, i1).astype(np.int64)
    fit = _equiangular_offset if options.sgm_subplane == "equiangular" else _parabola_offset
    offset = fit(m1p, m1, m1n, (i1 > 0) & (i1 < n_last - 1))
    c2 = np.where(m2 < _WTA_BIG, m2, s[_S_MAX])
    conf = (c2 - m1) / (options.sgm_paths * _check_scale(cost_scale))
    return _finish(i1, offset, conf, m1, hts, vis, reject_range_edges,
                   time.perf_counter() - t0, label_base=base, n_labels=n_last)


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


def mrf_energy(cost_volume, guide, labels, options: MRFOptions, *,
               cost_scale: float = 1.0) -> float:
    """The graph-cut energy E(labels) (see the module docstring), in cost units (float64)."""
    c = _sanitised(_check_volume(cost_volume), _check_scale(cost_scale))
    lab = np.asarray(labels, dtype=np.intp)
    if lab.shape != c.shape[1:]:
        raise InputError(None, f"labels: shape {lab.shape}, expected {c.shape[1:]}")
    wh, wv = edge_weights(_check_guide(guide, c.shape[1:]), options, cost_scale)
    t = options.gc_truncation_labels
    data = np.take_along_axis(c, lab[None], axis=0)[0].astype(np.float64).sum()
    sh = np.minimum(np.abs(np.diff(lab, axis=1)), t)
    sv = np.minimum(np.abs(np.diff(lab, axis=0)), t)
    return float(data + (wh * sh).sum() + (wv * sv).sum())


class _ExpansionGrid:
    """Alpha-expansion on one tile: data costs (L, n), 4-connected edges with weights.

    Edge ids: horizontal edge (p, p+1) has id p, vertical edge (p, p+w) has id n + p (weights of
    non-existent edges at the right and bottom borders are 0 and they are never used).
    """

    def __init__(self, data: np.ndarray, wh: np.ndarray, wv: np.ndarray, truncation: int):
        self.n_labels, self.h, self.w = data.shape
        self.n = self.h * self.w
        self.data = data.reshape(self.n_labels, self.n)
        n, w = self.n, self.w
        pid = np.arange(n)
        px, py = pid % w, pid // w
        self.has_right, self.has_down = px < w - 1, py < self.h - 1
        self.has_left, self.has_up = px > 0, py > 0
        wgt = np.zeros(2 * n)
        wgt[:n].reshape(self.h, w)[:, :-1] = wh
        wgt[n:].reshape(self.h, w)[:-1, :] = wv
        self.weight = wgt
        self.p = np.concatenate([pid, pid])
        self.q = np.concatenate([np.minimum(pid + 1, n - 1), np.minimum(pid + w, n - 1)])
        self.truncation = truncation
        self.is_free = np.zeros(n, bool)
        self.local = np.zeros(n, np.int64)

    def _v(self, a: np.ndarray, b) -> np.ndarray:
        return np.minimum(np.abs(a - b), self.truncation)

    def move(self, labels: np.ndarray, alpha: int, free: np.ndarray) -> int:
        """Optimal expansion of ``alpha`` over the pixels ``free`` (flat ids); others keep their
        labels. Updates ``labels`` in place; returns how many pixels switched."""
        import maxflow  # noqa: PLC0415

        k = free.size
        if k == 0:
            return 0
        n, w = self.n, self.w
        isf, loc = self.is_free, self.local
        isf[free] = True
        loc[free] = np.arange(k)
        # Each edge touching a free pixel once: its own right/down edges, and its left/up edges
        # when that neighbour is not free (otherwise the neighbour owns the edge).
        left, up = free - 1, free - w
        eids = np.concatenate([
            free[self.has_right[free]],
            n + free[self.has_down[free]],
            left[self.has_left[free] & ~isf[np.maximum(left, 0)]],
            n + up[self.has_up[free] & ~isf[np.maximum(up, 0)]],
        ])
        p, q, wt = self.p[eids], self.q[eids], self.weight[eids]
        lp, lq = labels[p], labels[q]
        e_a = wt * self._v(lp, lq)       # A = E(0, 0): both keep their labels
        e_b = wt * self._v(lp, alpha)    # B = E(0, 1): q takes alpha
        e_c = wt * self._v(lq, alpha)    # C = E(1, 0): p takes alpha; D = E(1, 1) = 0
        fp, fq = isf[p], isf[q]
        both, only_p = fp & fq, fp & ~fq
        lp_loc, lq_loc = loc[p], loc[q]
        lab_f = labels[free]
        # Unary terms (u0: keep, u1: take alpha). Both free: E = A + (C - A) xp - C xq
        # + (B + C - A) (1 - xp) xq, and -C xq = C (1 - xq) - C; only p free: A or C; only q
        # free: A or B. Each edge adds to one u0 and one u1 entry.
        idx0 = np.where(only_p, lp_loc, lq_loc)
        val0 = np.where(both, e_c, e_a)
        idx1 = np.where(fp, lp_loc, lq_loc)
        val1 = np.where(both, e_c - e_a, np.where(only_p, e_c, e_b))
        u0 = self.data[lab_f, free] + np.bincount(idx0, val0, minlength=k)
        u1 = self.data[alpha, free] + np.bincount(idx1, val1, minlength=k)
        m = np.minimum(u0, u1)
        u0 -= m
        u1 -= m
        # Pairwise edge p -> q, cut when p keeps and q takes alpha: B + C - A >= 0 (truncated
        # linear is a metric); clipped against rounding.
        cap = np.maximum(e_b[both] + e_c[both] - e_a[both], 0.0)
        g = maxflow.Graph[float](k, int(both.sum()))
        nodes = g.add_nodes(k)
        if cap.size:
            g.add_edges(lp_loc[both], lq_loc[both], cap, np.zeros(cap.size))
        # A node in the sink segment (x = 1, takes alpha) cuts its source edge: capacity u1.
        g.add_grid_tedges(nodes, u1, u0)
        g.maxflow()
        switch = g.get_grid_segments(nodes) & (lab_f != alpha)
        labels[free[switch]] = alpha
        isf[free] = False
        return int(switch.sum())

    def solve(self, labels: np.ndarray, lo: np.ndarray, hi: np.ndarray, iterations: int) -> int:
        """Alpha-expansion sweeps with each pixel's label restricted to [lo, hi] (flat arrays).

        ``labels`` (flat, int64) must lie in the windows; updated in place. Alphas go from the
        lowest to the highest label any window allows; the sweeps stop early when one changes
        nothing. Returns the number of expansion moves made.
        """
        moves = 0
        alphas = range(int(lo.min()), int(hi.max()) + 1)
        for _ in range(iterations):
            changed = 0
            for alpha in alphas:
                free = np.flatnonzero((lo <= alpha) & (hi >= alpha))
                changed += self.move(labels, alpha, free)
                moves += 1
            if changed == 0:
                break
        return moves


def _downsample2(a: np.ndarray) -> np.ndarray:
    """2x2 block means over the last two axes (odd sizes padded by edge replication)."""
    h, w = a.shape[-2:]
    pad = [(0, 0)] * (a.ndim - 2) + [(0, h % 2), (0, w % 2)]
    if h % 2 or w % 2:
        a = np.pad(a, pad, mode="edge")
    return 0.25 * (a[..., 0::2, 0::2] + a[..., 1::2, 0::2] + a[..., 0::2, 1::2]
                   + a[..., 1::2, 1::2])


def _upsample2(labels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return np.repeat(np.repeat(labels, 2, axis=0), 2, axis=1)[:shape[0], :shape[1]]


def _coarse_weights(wh: np.ndarray, wv: np.ndarray, level: int,
                    shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Smoothness weights of the grid coarsened ``level`` times (blocks of s = 2^level pixels).

    A cut between two neighbouring blocks A and B stands for a fine cut that may run anywhere
    through A and B: for each of the s fine rows (columns) crossing them, the cheapest fine edge
    of that row within A and B, summed, divided by s^2 like the block-averaged data. With equal
    weights this is weight / s (the energy of a region keeps its balance between data and
    smoothness); across a strong edge of the guide anywhere inside A or B the coarse weight is
    low, so the coarse solution can follow edges that do not fall on block boundaries.
    ``shape`` is the coarse grid (rows, columns); the fine grid is padded by replication.
    """
    from numpy.lib.stride_tricks import sliding_window_view  # noqa: PLC0415

    s = 1 << level
    hc, wc = shape

    def per_axis(wgt: np.ndarray, n_blocks_across: int, n_blocks_along: int) -> np.ndarray:
        # wgt: (fine rows, fine edges along the row); rows are grouped by s, edges windowed.
        rows = n_blocks_along * s
        wgt = np.pad(wgt, ((0, max(rows - wgt.shape[0], 0)), (0, 0)), mode="edge")[:rows]
        width = (n_blocks_across + 1) * s - 1
        wgt = np.pad(wgt, ((0, 0), (0, max(width - wgt.shape[1], 0))), constant_values=np.inf)
        win = sliding_window_view(wgt, 2 * s - 1, axis=1)[:, 0:(n_blocks_across - 1) * s:s]
        best = win.min(axis=2)                                  # (rows, n_blocks_across - 1)
        return best.reshape(n_blocks_along, s, -1).sum(axis=1) / float(s * s)

    wh_c = per_axis(wh, wc, hc) if wc > 1 else np.zeros((hc, 0))
    wv_c = per_axis(wv.T, hc, wc).T if hc > 1 else np.zeros((0, wc))
    return wh_c, wv_c


def _solve_tiled(data: np.ndarray, wh: np.ndarray, wv: np.ndarray, init: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray, options: MRFOptions, tile: int) -> np.ndarray:
    """Alpha-expansion over tiles of ``tile`` pixels, each extended by the overlap on every side
    and solved independently from ``init`` with labels in [lo, hi]; the kept parts are joined."""
    n_labels, h, w = data.shape
    out = init.copy()
    ov = options.gc_tile_overlap
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            ya, xa = max(y0 - ov, 0), max(x0 - ov, 0)
            yb, xb = min(y1 + ov, h), min(x1 + ov, w)
            grid = _ExpansionGrid(np.ascontiguousarray(data[:, ya:yb, xa:xb]),
                                  wh[ya:yb, xa:xb - 1], wv[ya:yb - 1, xa:xb],
                                  options.gc_truncation_labels)
            lab = init[ya:yb, xa:xb].astype(np.int64).ravel()
            grid.solve(lab, lo[ya:yb, xa:xb].ravel(), hi[ya:yb, xa:xb].ravel(),
                       options.gc_iterations)
            out[y0:y1, x0:x1] = lab.reshape(yb - ya, xb - xa)[y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out


def _coarse_windows(coarse: np.ndarray, shape: tuple[int, int], window: int,
                    n_labels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial labels and label windows at a finer level from the coarser level's labels.

    Each fine pixel starts from its coarse pixel's label and may take labels from the lowest to
    the highest label of the 3x3 coarse neighbourhood, widened by ``window``: a fine pixel near a
    height discontinuity can take either side's height even where the coarse grid put the edge
    one coarse pixel off.
    """
    import cv2  # noqa: PLC0415

    kernel = np.ones((3, 3), np.uint8)  # 3x3 min / max, outside the image ignored
    c = np.asarray(coarse, np.float64)  # exact for labels; OpenCV morphology has no int64
    lo = cv2.erode(c, kernel, borderType=cv2.BORDER_REPLICATE).astype(coarse.dtype)
    hi = cv2.dilate(c, kernel, borderType=cv2.BORDER_REPLICATE).astype(coarse.dtype)
    return (_upsample2(coarse, shape), np.maximum(_upsample2(lo, shape) - window, 0),
            np.minimum(_upsample2(hi, shape) + window, n_labels - 1))


def _graphcut_confidence(data: np.ndarray, labels: np.ndarray, wh: np.ndarray, wv: np.ndarray,
                         truncation: int, cost_scale: float) -> np.ndarray:
    """Margin of the conditional energy E_p(k) = D(p, k) + sum_q w_pq V(k, l_q) at the label.

    Streams over k keeping three planes: (second-lowest local minimum of E_p other than at l_p,
    else max E_p) - E_p(l_p), divided by cost_scale. Local minima as in wta.cl (E_k < E_{k-1} and
    E_k <= E_{k+1}, the missing ends +inf).
    """
    n_labels, h, w = data.shape
    pads = []  # (neighbour labels, weights) for the 4 neighbours, weight 0 outside the image
    for axis, wgt in ((1, wh), (0, wv)):
        for side in (0, 1):
            nl = np.zeros((h, w), np.int64)
            ww = np.zeros((h, w))
            if axis == 1:
                if side == 0:
                    nl[:, :-1], ww[:, :-1] = labels[:, 1:], wgt
                else:
                    nl[:, 1:], ww[:, 1:] = labels[:, :-1], wgt
            else:
                if side == 0:
                    nl[:-1], ww[:-1] = labels[1:], wgt
                else:
                    nl[1:], ww[1:] = labels[:-1], wgt
            pads.append((nl, ww))

    def energy(k: int) -> np.ndarray:
        e = data[k].astype(np.float64)
        for nl, ww in pads:
            e += ww * np.minimum(np.abs(k - nl), truncation)
        return e

    inf = np.full((h, w), np.inf)
    at_label = np.zeros((h, w))
    other_min = np.full((h, w), np.inf)
    emax = np.full((h, w), -np.inf)
    prev2, prev = inf, energy(0)
    for k in range(n_labels):
        nxt = energy(k + 1) if k + 1 < n_labels else inf
        cur = prev
        emax = np.maximum(emax, cur)
        is_label = labels == k
        at_label[is_label] = cur[is_label]
        local_min = (cur < prev2) & (cur <= nxt) & ~is_label
        other_min = np.where(local_min, np.minimum(other_min, cur), other_min)
        prev2, prev = cur, nxt
    c2 = np.where(np.isfinite(other_min), other_min, emax)
    return (c2 - at_label) / cost_scale


def graphcut_refine(cost_volume, guide, heights, options: MRFOptions, *,
                    cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
                    initial_labels=None) -> MRFResult:
    """Alpha-expansion graph cut of the energy in the module docstring, bounded in cost.

    With ``gc_levels`` > 0 the volume is solved coarse-to-fine: halved ``gc_levels`` times (2x2
    means of the costs, smoothness weights from the full-resolution ones by ``_coarse_weights``
    so that a region's energy keeps its balance and the guide's edges are kept), the coarsest
    level over all labels starting from its winner-take-all,
    each finer level starting from the upsampled coarser labels within the windows of
    ``_coarse_windows``. With ``gc_levels`` = 0 one level is solved within +-gc_label_window of
    ``initial_labels`` (e.g. the sweep's WTA planes; by default the WTA of ``cost_volume``).
    ``initial_labels`` is not used when ``gc_levels`` > 0: where the WTA fails (weak texture) a
    window around it misses the true plane, which is why coarse-to-fine is the default.
    Each level is solved in tiles of ``gc_tile`` pixels (scaled with the level) extended by
    ``gc_tile_overlap`` on every side, each tile independently. The sub-plane offset is the
    parabola through the data costs around the label (the wta.cl rule).
    """
    t0 = time.perf_counter()
    scale = _check_scale(cost_scale)
    c = _sanitised(_check_volume(cost_volume), scale)
    n_labels, h, w = c.shape
    hts = _check_heights(heights, n_labels)
    g = _check_guide(guide, (h, w)).astype(np.float64)
    vis = _check_visible(visible, c.shape)
    window = options.gc_label_window
    wh, wv = edge_weights(g, options, scale)
    pyramid = [(c, wh, wv)]
    if options.gc_levels == 0:
        if initial_labels is None:
            labels = np.argmin(c, axis=0).astype(np.int64)
        else:
            init = np.asarray(initial_labels)
            if init.shape != (h, w) or not np.issubdtype(init.dtype, np.integer):
                raise InputError(None, f"initial_labels: expected integer labels of shape "
                                       f"{(h, w)}, got {init.dtype} {init.shape}")
            if init.min() < 0 or init.max() >= n_labels:
                raise InputError(None, f"initial_labels: values must be in [0, {n_labels - 1}]")
            labels = init.astype(np.int64)
        lo, hi = np.maximum(labels - window, 0), np.minimum(labels + window, n_labels - 1)
    else:
        for _ in range(options.gc_levels):
            if min(pyramid[-1][0].shape[1:]) < 8:
                break
            coarse = _downsample2(pyramid[-1][0])
            pyramid.append((coarse,) + _coarse_weights(wh, wv, len(pyramid), coarse.shape[1:]))
        labels = np.argmin(pyramid[-1][0], axis=0).astype(np.int64)
        lo, hi = np.zeros_like(labels), np.full_like(labels, n_labels - 1)

    for level in range(len(pyramid) - 1, -1, -1):
        data, lwh, lwv = pyramid[level]
        if labels.shape != data.shape[1:]:
            labels, lo, hi = _coarse_windows(labels, data.shape[1:], window, n_labels)
        labels = _solve_tiled(data, lwh, lwv, labels, lo, hi, options,
                              max(16, options.gc_tile >> level))

    lab = labels.astype(np.intp)
    c0 = np.take_along_axis(c, lab[None], axis=0)[0]
    cm = np.take_along_axis(c, np.maximum(lab - 1, 0)[None], axis=0)[0]
    cp = np.take_along_axis(c, np.minimum(lab + 1, n_labels - 1)[None], axis=0)[0]
    offset = _parabola_offset(cm, c0, cp, (lab > 0) & (lab < n_labels - 1))
    conf = _graphcut_confidence(c, labels, wh, wv, options.gc_truncation_labels, scale)
    energy = mrf_energy(c, g, labels, options, cost_scale=scale)
    return _finish(labels, offset, conf, c0, hts, vis, reject_range_edges,
                   time.perf_counter() - t0, energy)


def wta_labels(cost_volume) -> np.ndarray:
    """Winner-take-all labels (first argmin over planes) of a host cost volume, int32."""
    return np.argmin(_check_volume(cost_volume), axis=0).astype(np.int32)


def refine(device: Device | None, cost_volume, guide, heights, options: MRFOptions, *,
           cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
           initial_labels=None, pixel_major: bool = False,
           label_base=None, label_count=None, label_offset=None) -> MRFResult | None:
    """Dispatch on ``options.method``: None for ``none`` (keep the sweep's WTA), else the result.

    SGM needs ``device`` (and alone takes a ``pixel_major`` device volume, see
    ``sgm_aggregate``); the graph cut runs on the host and uses ``initial_labels`` only with
    ``gc_levels`` = 0 (see ``graphcut_refine``).
    """
    if options.method == "none":
        return None
    if options.method == "sgm":
        if device is None:
            raise DeviceError("MRF method sgm needs an OpenCL device")
        return sgm_refine(device, cost_volume, guide, heights, options, cost_scale=cost_scale,
                          visible=visible, reject_range_edges=reject_range_edges,
                          pixel_major=pixel_major, label_base=label_base,
                          label_count=label_count, label_offset=label_offset)
    if label_base is not None or label_count is not None or label_offset is not None:
        raise InputError(None, f"label_base: MRF method {options.method} takes no label bands "
                               "(SGM does)")
    if pixel_major:
        raise InputError(None, f"cost_volume: MRF method {options.method} takes a plane-major "
                               "host volume, not a pixel-major device volume")
    return graphcut_refine(cost_volume, guide, heights, options, cost_scale=cost_scale,
                           visible=visible, reject_range_edges=reject_range_edges,
                           initial_labels=initial_labels)


# ---------------------------------------------------------------------------------------------
# synthetic cost volumes with known truth (tests and benchmarks)
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SyntheticVolume:
    """A synthetic filtered cost volume with its true labels (see ``synthetic_roof_volume``)."""

    cost: np.ndarray  # (L, H, W) float32, in [0, cost_scale]
    guide: np.ndarray  # (H, W) float32 in [0, 1]
    heights: np.ndarray  # (L,) plane heights, metres
    truth_labels: np.ndarray  # (H, W) int64 true plane index
    roof: np.ndarray  # (H, W) bool, the weakly textured region
    cost_scale: float

    @property
    def truth_height(self) -> np.ndarray:
        return self.heights[self.truth_labels]


def synthetic_roof_volume(shape: tuple[int, int] = (64, 80), n_labels: int = 40, *,
                          seed: int = 0, cost_scale: float = 62.0, spacing_m: float = 0.5,
                          roof_contrast: float = 0.02, texture_contrast: float = 0.6,
                          noise: float = 0.05) -> SyntheticVolume:
    """A cost volume of a textured, gently undulating terrain with a large flat roof.

    The roof covers the central 60 % x 62 % of the image at a constant plane (70 % of the range);
    the terrain elsewhere varies smoothly over a quarter of the range. The cost of plane k at a
    pixel of true plane t is ``cost_scale * (0.5 - c/2 + c * min(|k - t| / 3, 1) + N(0, noise))``
    clipped to [0, cost_scale], with c = ``texture_contrast`` on the terrain and the much smaller
    ``roof_contrast`` on the roof, where the noise hides the minimum from a winner-take-all (as
    on a plain roof, whose census costs are nearly flat). The guide is uniform noise in [0, 1] on
    the terrain and nearly constant (0.6 +- 0.01) on the roof. Planes are ``spacing_m`` apart.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.3 * n_labels
    amp = 0.125 * n_labels
    truth = np.rint(base + amp * (0.55 * np.sin(xx / (0.11 * w)) + 0.45 * np.cos(yy / (0.17 * h))))
    truth = np.clip(truth, 1, n_labels - 2).astype(np.int64)
    roof = ((yy >= int(0.2 * h)) & (yy < int(0.8 * h)) & (xx >= int(0.2 * w))
            & (xx < int(0.82 * w)))
    truth[roof] = int(0.7 * n_labels)
    guide = rng.uniform(0.0, 1.0, (h, w))
    guide[roof] = 0.6 + rng.uniform(-0.01, 0.01, int(roof.sum()))
    k = np.arange(n_labels)[:, None, None]
    shape_k = np.minimum(np.abs(k - truth[None]) / 3.0, 1.0)
    contrast = np.where(roof, roof_contrast, texture_contrast)[None]
    cost = cost_scale * (0.5 - 0.5 * contrast + contrast * shape_k
                         + rng.normal(0.0, noise, (n_labels, h, w)))
    cost = np.clip(cost, 0.0, cost_scale).astype(np.float32)
    heights = 100.0 + spacing_m * np.arange(n_labels)
    return SyntheticVolume(cost=cost, guide=guide.astype(np.float32), heights=heights,
                           truth_labels=truth, roof=roof, cost_scale=float(cost_scale))
