"""OpenCL plane sweep: census matching cost, multi-view aggregation, guided filtering and
winner-take-all height maps for one reference view.

Conventions: images are 2-D float32 arrays, tonemapped to about [0, 1], row-major; pixel (0, 0)
is the centre of the first pixel. A plane is ``u = h`` in the ENU frame of the scene (``h`` in
metres); for each plane and source a 3x3 homography (float64 on the host) maps homogeneous
reference pixels ``(x, y, 1)`` to source pixels. Kernels run in float32; the homographies are
re-expressed in tile-local reference coordinates on the host (float64) before the cast, so the
float32 coordinates on the device stay small.

Pipeline per reference tile (kernels/*.cl, one file per stage):

1. ``census.cl``: census codes of the reference tile (window ``census_window``, 64-bit codes);
2. ``sweep.cl``: per plane, each source warped into the reference by the plane's homography, the
   Hamming distance between census codes (of the warped source image, or of the source sampled
   at the warped position) plus, by default, a truncated absolute intensity difference
   (AD-census; ``ad_weight``) and optionally a gradient term (``grad_weight``), then the mean of
   the ``k`` lowest costs over the sources that see the pixel (robust to occlusion); a pixel that
   no source sees gets the worst cost;
3. ``guided_filter.cl``: every cost slice filtered by the guided filter (He et al.) with the
   reference image as guide, or by a box filter, from O(1)-per-pixel box sums;
4. ``wta.cl``: streaming argmin over the planes with a parabola through the best plane and its
   neighbours, a confidence (margin to the second-best local minimum) and a validity mask.

``PlaneSweep`` has one method per operation: ``height_map`` (the winner-take-all ``HeightMap``;
the cost volume never leaves the device and never exists whole), ``cost_volume`` and
``cost_volume_on_device`` (the filtered cost of every plane as a ``CostVolume``, which the MRF
refinements take: on the host, plane-major, or on the device in SGM's layout), and
``height_map_with_cost_volume`` (both from one sweep); the volume methods may sweep each block
of the reference over its own window of planes (``PlaneWindows``, coarse-to-fine). Planes are
processed in batches, and the reference image in tiles (with the filter's margin), so that a
memory budget holds. Images are uploaded once per run; the source census codes
(``sampled_codes`` mode) are computed once on the device. The device buffers of a run and of a
tile are listed once, each under the name of the kernel argument it is passed as
(``run_buffers``, ``tile_buffers``): ``plan_tiles`` sums that table to fit the budget, and the
sweep allocates it for each tile, releasing every buffer when the tile (or the run) ends,
normally or by an error (``satsweep.opencl.buffers``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from typing import Callable, Literal, Sequence

import numpy as np

from satsweep.dense.planes import ellipsoid_heights, plane_heights, view_homographies
from satsweep.dense.volume import CostVolume
from satsweep.errors import DeviceError, InputError
from satsweep.opencl.buffers import BufferSpec, DeviceMemory, largest_bytes, total_bytes
from satsweep.opencl.constants import (
    GF_COLS_VEC,
    SWEEP_BAND_PLANES,
    SWEEP_VEC,
    WTA_NSTATE,
    WTA_VEC,
)
from satsweep.opencl.device import Device
from satsweep.opencl.device import launch as _launch  # (tests patch sweep's _launch)
from satsweep.options import Options

# Smallest tile interior side (pixels) worth processing before the plane batch is reduced instead.
_MIN_TILE_SIDE = 64
# Planes warped per launch by the split census kernels (their warped-source buffer holds this
# many planes of every source over the tile plus the census margin), at least; a small tile
# (a coarse-to-fine block) warps more planes per launch, up to _WARP_CHUNK_POSITIONS positions
# (5 bytes each: about 5 MiB, the buffer stays in cache between the two launches), so that it
# needs fewer launches.
SPLIT_WARP_PLANES = 8
_WARP_CHUNK_POSITIONS = 1 << 20
# Fixed allowance (bytes) for the driver's bookkeeping, added to the buffers of the run and to
# those of each tile in the memory plan.
_SMALL_BUFFERS_BYTES = 1 << 16


@dataclasses.dataclass(frozen=True)
class SweepOptions(Options):
    """Options of the OpenCL plane sweep."""

    step_px: float = 0.5  # plane spacing: one step moves a pixel by at most this (px) in the
    # widest-baseline source
    ad_weight: float = 8.0  # census bits the truncated intensity difference adds (AD-census);
    # 0: census alone (for views whose radiometry differs)
    search: Literal["full", "coarse_to_fine"] = "coarse_to_fine"  # with SGM: a half-resolution
    # pass first gives each block of the reference a window of planes; full: every plane
    memory_fraction: float = 0.5  # device memory budget, a fraction of its global memory
    memory_budget_bytes: int | None = None  # device memory budget (bytes); overrides the fraction
    census_window: tuple[int, int] = (5, 5)  # census window (rows, columns): odd sides, at most
    # 64 neighbours
    cost_mode: Literal["warped_census", "sampled_codes"] = "warped_census"  # census of the
    # bilinearly warped source, or the source's own codes at the nearest warped pixel
    ad_truncation: float = 0.15  # intensity difference (image in [0, 1]) at which AD saturates
    grad_weight: float = 0.0  # census bits the truncated gradient difference adds; 0: none
    consensus_grad_weight: float | None = 8.0  # ... in an area whose DSM is the consensus of
    # the reference views' height maps ([dsm] fusion), where the costs hold intensities
    # (cost_mode "warped_census", a census window of 3 x 3 or more); None: grad_weight
    grad_truncation: float = 0.1  # gradient difference at which the gradient term saturates
    census_ring_weight: float = 0.0  # extra weight of the census bits that compare the centre
    # with its 8 nearest neighbours (the 3 x 3 ring): the census term is (bits + w ring bits)
    # n / (n + w n_ring), so it still spans 0..n bits (n: the window's bits); 0: plain census
    consensus_census_ring_weight: float | None = 2.0  # ... in an area whose DSM is the consensus
    # of the reference views' height maps ([dsm] fusion); None: census_ring_weight
    dense_consensus_census_ring_weight: float | None = 8.0  # ... there, for a reference of
    # pixels finer than the DSM's cells (pipeline.sweeps.reference_options); None: as the
    # area's. On the issue-form 0.3 m stacks (19 views, 8 references) 2 -> 8, DFC MAE m: seeds
    # 11 13 and held-out 14-18 1.090 1.080 0.764 1.029 1.162 0.454 0.826 -> 1.075 1.089 0.758
    # 0.979 1.160 0.437 0.830, seeds 7 and 12 0.788 0.749 -> 0.780 0.736 (lower on 7 of 9);
    # 4: 1.084 / 1.156 on seeds 11 / 16. At 0.5 m pixels 8 lost (v10 seeds 0-5: 93.75 ->
    # 93.72% within 1 m, DFC MAE 0.583 -> 0.589 m): such references keep the area's weight.
    census_mask_threshold: float = 0.0  # edge-aware census: only the comparisons whose
    # neighbour lies within this of the centre's intensity in the reference (image in [0, 1])
    # count, scaled to span 0..n bits (a pixel like fewer than CENSUS_MASK_MIN_BITS of its
    # window keeps every bit): the comparisons across a roof's edge no longer pull the ground
    # beside it to the roof's height; needs cost_mode "warped_census" and a census window of at
    # most 32 bits (5 x 5); 0: every bit
    consensus_census_mask_threshold: float | None = 0.12  # ... in an area whose DSM is the
    # consensus of the reference views' height maps (where the census allows it); None:
    # census_mask_threshold. Issue-form 0.3 m stacks (19 views), DFC MAE m, seeds 11-16: 1.082
    # 0.687 1.098 0.839 1.063 0.809 -> 1.039 0.630 1.022 0.817 0.879 0.763; v10 0.5 m stacks
    # (seeds 0-5) 0.485 0.841 0.454 0.476 0.818 0.367 -> 0.468 0.721 0.448 0.467 0.783 0.370
    # (docs/measurements.md); 0.04 / 0.08 / 0.10 / 0.15 / 0.20 on seeds 11 and 15: 1.112 /
    # 1.060 / 1.053 / 1.039 / 1.053 and 0.873 / 0.896 / 0.858 / 0.893 / 0.953. Pairs of one
    # date (tools/bench_e2e.py, median fusion) lost a little with it: there it stays 0
    prefilter_sigma_px: float = 0.0  # Gaussian blur (px) of the images before the census; 0: none
    n_best_sources: int | None = None  # cost = mean of the k lowest source costs; None: half the
    # sources, rounded up
    cost_filter: Literal["guided", "box", "none"] = "guided"  # filter of each cost slice
    gf_radius: int = 5  # guided filter radius (px) of the winner-take-all path (--mrf none)
    gf_eps: float = 1e-4  # guided filter regularisation (guide units squared, guide in [0, 1])
    box_radius: int = 2  # box filter radius (px) for cost_filter = "box"
    subplane: bool = True  # parabola refinement between planes
    reject_range_edges: bool = True  # a best plane at an end of the height range is invalid
    lr_check: bool = False  # sweep again with the first source as reference and keep agreements
    lr_tolerance_planes: float = 1.0  # largest plane difference (planes) the check accepts
    max_planes_per_batch: int = 32  # planes filtered together (memory grows with it)
    census_kernel: Literal["split", "staged"] = "split"  # warp then census in two launches, or
    # both in one work-group kernel (the same costs, bit for bit)
    work_group: tuple[int, int] = (16, 16)  # work-group size (x, y) of the staged census kernel
    coarse_plane_stride: int = 4  # coarse_to_fine: the half-resolution pass sweeps every this
    # many planes
    window_block_px: int = 64  # coarse_to_fine: side (px) of the blocks that share a window
    # (8 or more: each block a tile of its own); 1: each pixel its own window, in tiles as
    # without windows
    window_halo_px: int = 8  # coarse_to_fine: pixels around a block whose coarse heights its
    # window also spans
    window_margin_planes: int = 4  # coarse_to_fine: planes added below and above each window
    window_max_fraction: float = 0.6  # coarse_to_fine: sweep every plane when the windows would
    # hold more than this fraction of them
    window_bands: bool = True  # coarse_to_fine, windows of one pixel: each pixel sweeps only
    # the bands of BAND_PLANES planes that hold a coarse height within its halo (with the
    # margin), not every plane between the lowest and the highest of them: beside a roof the
    # ground's planes and the roof's, not the facade's. 19-view 0.3 m stacks of 1700 px (seed
    # 22), RPCs over the scene's heights / over 1000 m: 126.5 / 143.6 -> 111.0 / 124.0 s, DFC MAE
    # 0.941 / 0.979 -> 0.951 / 1.005 m (docs/measurements.md, fifty-first session); False: the
    # whole window
    window_band_halo_px: int = 4  # coarse_to_fine, windows of one pixel with bands: pixels
    # around each pixel whose coarse heights its bands hold (at most window_halo_px, which its
    # window spans). 8 (the window's) before: the 1700 px stack with RPCs over 1000 m, two
    # pairs one run after the other, 127.4 / 127.4 -> 121.4 / 116.5 s (sweep 70.7 / 71.0 ->
    # 62.9 / 59.5 s), DFC MAE 1.005 -> 0.997 m; ten issue-form runs (seeds 11-17 with RPCs over
    # 1000 m, 11-13 with the scenes' heights) +0.003 m on average, each within 0.05 m; 2 px:
    # seed 11 1.054 -> 1.161 m (docs/measurements.md, fifty-second session)
    window_pixel_fallback: bool = False  # coarse_to_fine: where the blocks' windows would hold
    # more than window_max_fraction, each pixel its own window if those hold no more, before
    # every plane
    dense_consensus_window_pixel_fallback: bool | None = True  # ... for a reference of pixels
    # finer than the DSM's cells in a consensus area (as dense_consensus_census_ring_weight):
    # at 0.3 m every 64 px block of a city holds a roof and the ground, and such references
    # take the most time. 19-view 0.3 m stacks of 1700 px: 151 / 178 -> 105 / 119 s, DFC MAE
    # 0.791 / 0.919 -> 0.824 / 0.867 m; of 850 px (seeds 11-16): mean 0.963 -> 0.972 m. On
    # 0.5 m stacks (not dense) it costs 0.0-0.4 points within 1 m for no time (v10 seeds 0-5).
    # None: as the area's

    ADVANCED = ("census_window", "cost_mode", "ad_truncation", "grad_weight",
                "consensus_grad_weight", "grad_truncation", "census_ring_weight",
                "consensus_census_ring_weight", "dense_consensus_census_ring_weight",
                "census_mask_threshold", "consensus_census_mask_threshold",
                "prefilter_sigma_px", "n_best_sources", "cost_filter", "gf_radius", "gf_eps",
                "box_radius", "subplane", "reject_range_edges", "lr_check", "lr_tolerance_planes",
                "max_planes_per_batch", "census_kernel", "work_group", "coarse_plane_stride",
                "window_block_px", "window_halo_px", "window_margin_planes",
                "window_max_fraction", "window_bands", "window_band_halo_px",
                "window_pixel_fallback",
                "dense_consensus_window_pixel_fallback")

    def check(self) -> None:
        rows, cols = self.census_window
        self._require(rows >= 1 and cols >= 1 and rows % 2 == 1 and cols % 2 == 1,
                      "census_window", "both sizes must be odd and positive")
        self._require(2 <= rows * cols <= 65, "census_window",
                      "the window must hold between 1 and 64 neighbours (64-bit codes)")
        for term, weight, trunc in (("the AD term", "ad_weight", "ad_truncation"),
                                    ("the gradient term", "grad_weight", "grad_truncation")):
            w = getattr(self, weight)
            self._require(math.isfinite(w) and 0 <= w <= 64, weight, "must be in [0, 64] census bits")
            self._require(w == 0 or self.cost_mode == "warped_census", weight,
                          f"{term} needs cost_mode = 'warped_census' (sampled_codes has no "
                          f"intensities): set {weight} = 0")
            t = getattr(self, trunc)
            self._require(math.isfinite(t) and t > 0, trunc, "must be > 0 (intensity units)")
        self._require(self.grad_weight == 0 or min(self.census_window) >= 3, "grad_weight",
                      "the gradient term needs a census window of at least 3x3: set grad_weight = 0")
        w = self.consensus_grad_weight
        self._require(w is None or (math.isfinite(w) and 0 <= w <= 64), "consensus_grad_weight",
                      "must be in [0, 64] census bits (or None)")
        self._require(math.isfinite(self.census_ring_weight) and 0 <= self.census_ring_weight <= 64,
                      "census_ring_weight", "must be in [0, 64] (a ring bit weighs 1 + this)")
        for name in ("consensus_census_ring_weight", "dense_consensus_census_ring_weight"):
            w = getattr(self, name)
            self._require(w is None or (math.isfinite(w) and 0 <= w <= 64), name,
                          "must be in [0, 64] (or None)")
        t = self.census_mask_threshold
        self._require(math.isfinite(t) and 0 <= t <= 1, "census_mask_threshold",
                      "must be in [0, 1] (intensity, image in [0, 1])")
        self._require(t == 0 or self.census_can_mask,
                      "census_mask_threshold", "needs cost_mode = 'warped_census' and a census "
                      "window of at most 32 bits (e.g. 5 x 5): set census_mask_threshold = 0")
        t = self.consensus_census_mask_threshold
        self._require(t is None or (math.isfinite(t) and 0 <= t <= 1),
                      "consensus_census_mask_threshold", "must be in [0, 1] (or None)")
        self._require(math.isfinite(self.prefilter_sigma_px) and 0 <= self.prefilter_sigma_px <= 5,
                      "prefilter_sigma_px", "must be in [0, 5] pixels")
        self._require(math.isfinite(self.step_px) and self.step_px > 0, "step_px", "must be > 0")
        self._require(self.n_best_sources is None or self.n_best_sources >= 1, "n_best_sources",
                      "must be >= 1 (or None)")
        self._require(0 <= self.gf_radius <= 64, "gf_radius", "must be in [0, 64]")
        self._require(math.isfinite(self.gf_eps) and self.gf_eps > 0, "gf_eps", "must be > 0")
        self._require(0 <= self.box_radius <= 64, "box_radius", "must be in [0, 64]")
        self._require(math.isfinite(self.lr_tolerance_planes) and self.lr_tolerance_planes >= 0,
                      "lr_tolerance_planes", "must be >= 0")
        self._require(0 < self.memory_fraction <= 1, "memory_fraction", "must be in (0, 1]")
        self._require(self.memory_budget_bytes is None or self.memory_budget_bytes > 0,
                      "memory_budget_bytes", "must be > 0 (or None)")
        self._require(1 <= self.max_planes_per_batch <= 4096, "max_planes_per_batch",
                      "must be in [1, 4096]")
        wx, wy = self.work_group
        self._require(1 <= wx <= 256 and 1 <= wy <= 256 and wx * wy <= 1024, "work_group",
                      "sizes must be in [1, 256] with a product <= 1024")
        self._require(self.window_block_px == 1 or 8 <= self.window_block_px <= 4096,
                      "window_block_px", "must be 1 (each pixel its own window) or in [8, 4096] "
                      "pixels")
        self._require(1 <= self.coarse_plane_stride <= 64, "coarse_plane_stride",
                      "must be in [1, 64] planes")
        self._require(0 <= self.window_halo_px <= 256, "window_halo_px",
                      "must be in [0, 256] pixels")
        self._require(0 <= self.window_band_halo_px <= 256, "window_band_halo_px",
                      "must be in [0, 256] pixels")
        self._require(0 <= self.window_margin_planes <= 256, "window_margin_planes",
                      "must be in [0, 256] planes")
        self._require(math.isfinite(self.window_max_fraction) and 0 < self.window_max_fraction <= 1,
                      "window_max_fraction", "must be in (0, 1]")

    @property
    def census_radii(self) -> tuple[int, int]:
        """(rx, ry): census window half-width and half-height in pixels."""
        return self.census_window[1] // 2, self.census_window[0] // 2

    @property
    def census_bits(self) -> int:
        """Bits per census code (window area minus the centre)."""
        return self.census_window[0] * self.census_window[1] - 1

    @property
    def census_can_mask(self) -> bool:
        """Whether the census can take ``census_mask_threshold``: the warped census (the mask is
        the reference's, for sweep.cl's warped-census kernels) with codes of at most 32 bits
        (census.cl keeps the mask in the high word)."""
        return self.cost_mode == "warped_census" and self.census_bits <= 32

    @property
    def census_ring(self) -> int:
        """The census code's bits that compare the centre with its 8 nearest neighbours (a mask:
        the code holds the window's comparisons in raster order, the first in its highest bit)."""
        rx, ry = self.census_radii
        order = [(dy, dx) for dy in range(-ry, ry + 1) for dx in range(-rx, rx + 1)
                 if (dy, dx) != (0, 0)]
        n = len(order)
        return sum(1 << (n - 1 - k) for k, (dy, dx) in enumerate(order)
                   if abs(dy) <= 1 and abs(dx) <= 1)

    @property
    def census_scale(self) -> float:
        """The factor n / (n + w n_ring) of the census term under ``census_ring_weight`` = w."""
        n, ring = self.census_bits, bin(self.census_ring).count("1")
        return n / (n + self.census_ring_weight * ring)

    @property
    def max_cost(self) -> float:
        """The largest cost of one source at one pixel and plane: census bits plus the AD and
        gradient terms (also the cost of a pixel that no source sees)."""
        return float(self.census_bits) + self.ad_weight + self.grad_weight

    @property
    def filter_radius(self) -> int:
        """Radius of the box sums used by the chosen cost filter (0 for none)."""
        return {"guided": self.gf_radius, "box": self.box_radius, "none": 0}[self.cost_filter]

    @property
    def slice_filter(self) -> Literal["guided", "box", "none"]:
        """The filter the sweep runs on each cost slice: ``cost_filter``, or "none" where its
        radius is 0 (a guided or box filter of radius 0 gives every cost back unchanged, so it
        is not run: SGM's sweep, ``MRFOptions.sgm_sweep_gf_radius``)."""
        return self.cost_filter if self.filter_radius > 0 else "none"

    @property
    def tile_margin(self) -> int:
        """Margin (pixels) around a tile so that its interior equals a whole-image computation.

        The guided filter applies two box filters in sequence (2 r), a box filter one (r). The
        census needs none: the sweep kernel clamps census neighbours to the reference image, not
        to the tile, and the reference codes of a tile are computed from the whole image.
        """
        return {"guided": 2 * self.gf_radius, "box": self.box_radius, "none": 0}[self.cost_filter]

    def for_consensus(self) -> "SweepOptions":
        """The options of an area whose DSM is a consensus of many height maps: the gradient
        term weighs ``consensus_grad_weight`` where the costs can hold it (see its comment), the
        census's 3 x 3 ring ``consensus_census_ring_weight``, the census's mask
        ``consensus_census_mask_threshold`` where the census allows one (see its comment)."""
        changes: dict = {}
        w = self.consensus_grad_weight
        if w is not None and self.cost_mode == "warped_census" and min(self.census_window) >= 3:
            changes["grad_weight"] = float(w)
        if self.consensus_census_ring_weight is not None:
            changes["census_ring_weight"] = float(self.consensus_census_ring_weight)
        t = self.consensus_census_mask_threshold
        if t is not None and self.census_can_mask:
            changes["census_mask_threshold"] = float(t)
        return self.replace(**changes) if changes else self

    def for_dense_pixels(self) -> "SweepOptions":
        """The options (an area's, after ``for_consensus``) of a reference whose pixels are
        finer than the DSM's cells: the census's 3 x 3 ring weighs
        ``dense_consensus_census_ring_weight``, and windows of one pixel follow blocks as
        ``dense_consensus_window_pixel_fallback`` says (each when set)."""
        changes: dict = {}
        if self.dense_consensus_census_ring_weight is not None:
            changes["census_ring_weight"] = float(self.dense_consensus_census_ring_weight)
        if self.dense_consensus_window_pixel_fallback is not None:
            changes["window_pixel_fallback"] = bool(self.dense_consensus_window_pixel_fallback)
        return self.replace(**changes) if changes else self

    def best_k(self, n_sources: int) -> int:
        """The number of lowest source costs averaged per pixel for ``n_sources`` sources."""
        k = (n_sources + 1) // 2 if self.n_best_sources is None else self.n_best_sources
        return max(1, min(k, n_sources))


@dataclasses.dataclass(frozen=True)
class WorkSplit:
    """How a sweep (or a sweep with its MRF, ``satsweep.dense.tiled``) split its work."""

    n_tiles: int = 1  # tiles of the reference swept one after the other
    n_batches: int = 1  # batches of planes, over all tiles
    peak_device_bytes: int = 0  # the most device memory its buffers held at once
    window_planes: int | None = None  # planes per window of a coarse-to-fine sweep (else None)
    window_share: float | None = None  # ... the share of its pixels' planes it swept (else None)


@dataclasses.dataclass
class HeightMap:
    """A height map of the reference view, arrays of the reference image's shape: the sweep's
    winner-take-all (``PlaneSweep.height_map``), or its MRF refinement (``sweep_refine_tiled``).

    height: plane parameter (metres, the ``h`` of the planes, float64) of the best plane with
        sub-plane refinement; NaN where invalid.
    plane_index: fractional index of the best plane (float32), defined everywhere.
    confidence: (second-lowest local minimum - best cost) / ``SweepOptions.max_cost`` (census
        bits plus the AD and gradient weights), in [0, 1] (float32).
    valid: True where the pixel is seen by a source at its best plane, the best plane is not at
        an end of the range (``reject_range_edges``) and, with ``lr_check``, where the check passed.
    cost_min: the best (filtered) cost, in census bits (plus the AD and gradient terms; float32).
    split: how the work was split (tiles, plane batches, device memory, plane windows).
    altitude: the heights above the WGS84 ellipsoid, where the sweep knew the scene's frame
        (``sweep_views`` with ``frame``); else None.
    """

    height: np.ndarray
    plane_index: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray
    cost_min: np.ndarray
    split: WorkSplit = WorkSplit()
    altitude: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class TilePlan:
    """How a sweep is split: interior tile size, planes per batch and the memory it needs."""

    tile_w: int  # interior width (pixels)
    tile_h: int  # interior height (pixels)
    margin: int  # filter margin around each interior (pixels)
    planes_per_batch: int
    resident_bytes: int  # images (and codes) kept for the whole run
    tile_bytes: int  # per-tile buffers at the planned size
    n_tiles: int

    @property
    def total_bytes(self) -> int:
        return self.resident_bytes + self.tile_bytes


@dataclasses.dataclass(frozen=True, eq=False)
class PlaneWindows:
    """Which planes a coarse-to-fine sweep evaluates: square blocks of the reference, each with a
    window of consecutive planes (``satsweep.dense.coarse`` derives them from a coarse height map).
    Block (i, j) covers reference rows [i block, (i + 1) block) and columns [j block, (j + 1)
    block); it sweeps the ``count[i, j]`` planes from first[i, j] (``n_planes`` when count is
    None), which become its labels 0 .. count - 1. A cost volume of these windows holds
    ``n_planes`` labels per pixel (the most of any block; its ``label_base`` and
    ``label_count`` come from here): a block on gentle terrain sweeps fewer planes than one
    across a cliff, and SGM refines each pixel over its own count. With ``block`` = 1 each pixel
    has its own window: the sweep then keeps its usual tiles, each sweeping the planes of its
    pixels' windows, and the split kernels skip per group of pixels the planes that no window
    within reach holds (``group_windows``); such windows need a ragged device volume (SGM's).
    """

    block: int  # block side (pixels); the blocks start at the reference's pixel (0, 0)
    first: np.ndarray  # (ceil(H / block), ceil(W / block)) int: first plane of each block
    n_planes: int  # labels per pixel of the volume (the widest window)
    count: np.ndarray | None = None  # like first: planes of each block's window (None: n_planes)
    bands: np.ndarray | None = None  # block = 1 only: (words, H, W) uint32 bit sets, bit k:
    # the pixel sweeps planes [k BAND_PLANES, (k + 1) BAND_PLANES) of its window (the others
    # get the worst cost); None: every plane of its window

    def sweep_range(self, i: int, j: int) -> tuple[int, int]:
        """(first plane, planes) of block (i, j)."""
        return int(self.first[i, j]), self.n_planes if self.count is None else int(self.count[i, j])

    def check(self, shape: tuple[int, int], total_planes: int) -> None:
        """Raise InputError unless the windows fit a reference of ``shape`` and the planes."""
        h, w = shape
        want = (-(-h // self.block), -(-w // self.block)) if self.block >= 1 else None
        first = np.asarray(self.first)
        if want is None or first.shape != want or not np.issubdtype(first.dtype, np.integer):
            raise InputError(None, f"plane_windows: first must be integers of shape {want} for "
                                   f"blocks of {self.block} px over {w} x {h}, got "
                                   f"{first.dtype} {first.shape}")
        count = np.full(first.shape, self.n_planes) if self.count is None \
            else np.asarray(self.count)
        if count.shape != first.shape or not np.issubdtype(count.dtype, np.integer):
            raise InputError(None, f"plane_windows: count must be integers of shape {want}, got "
                                   f"{count.dtype} {count.shape}")
        if not 1 <= self.n_planes <= total_planes or first.min() < 0 or count.min() < 1 \
                or count.max() > self.n_planes or (first + count).max() > total_planes:
            raise InputError(None, f"plane_windows: windows of {count.min()}..{count.max()} "
                                   f"planes (at most {self.n_planes}) from planes "
                                   f"{first.min()}..{first.max()} leave the {total_planes} planes")
        if self.bands is not None:
            bands = np.asarray(self.bands)
            want_bands = (band_words(total_planes), h, w)
            if self.block != 1 or bands.dtype != np.uint32 or bands.shape != want_bands:
                raise InputError(None, f"plane_windows: bands must be uint32 of shape "
                                       f"{want_bands} with windows of one pixel, got "
                                       f"{bands.dtype} {bands.shape} (block {self.block})")

    def swept(self, shape: tuple[int, int], step: int = 1) -> np.ndarray:
        """(H, W) int: the planes each pixel sweeps: its window's, or those of its bands within
        its window (the bands between the window's first and last, whole, less the parts of
        those two outside it); with ``step``, of every step-th row and column only
        (ceil(H / step), ceil(W / step))."""
        count = self.counts(shape)[::step, ::step]
        if self.bands is None:
            return count
        first = self.per_pixel(shape)[::step, ::step]
        end = first + count
        k_first, k_last = first // BAND_PLANES, (end - 1) // BAND_PLANES
        bands = self.bands[:, ::step, ::step]
        held = np.zeros(bands.shape[1:], np.int32)
        for word in range(bands.shape[0]):
            lo = np.clip(k_first - 32 * word, 0, 32)
            hi = np.clip(k_last - 32 * word + 1, 0, 32)
            held += _popcount32(bands[word] & _BIT_RANGES[lo, hi])

        def bit(k: np.ndarray) -> np.ndarray:
            words = np.take_along_axis(bands, (k >> 5)[None].astype(np.intp), axis=0)[0]
            return ((words >> (k & 31).astype(np.uint32)) & np.uint32(1)).astype(np.int32)
        return (BAND_PLANES * held - bit(k_first) * (first - BAND_PLANES * k_first)
                - bit(k_last) * (BAND_PLANES * (k_last + 1) - end))

    def per_pixel(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) int32: the first plane of every pixel's window."""
        return self._expand(self.first, shape)

    def counts(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) int32: the planes of every pixel's window."""
        if self.count is None:
            return np.full(shape, self.n_planes, np.int32)
        return self._expand(self.count, shape)

    def _expand(self, per_block, shape: tuple[int, int]) -> np.ndarray:
        h, w = shape
        b = np.asarray(per_block, dtype=np.int32)
        return np.ascontiguousarray(np.repeat(np.repeat(b, self.block, axis=0), self.block,
                                              axis=1)[:h, :w])


# -- device buffers and memory planning ---------------------------------------------------------
# Floats after the last source image in the sweep's source buffer (src_img): sweep_warp loads
# each bilinear sample's left and right taps as one pair, also where the right tap is clamped
# onto the left at a source's last column (its weight 0), which reads one float past the
# source: past the last one, this pad.
SWEEP_SRC_PAD = 1


def source_layout(srcs: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """sweep.cl's ``src_size`` (width, height of each source, int32) and ``src_offset`` (the
    first element of each in the concatenated sources, int64)."""
    sizes = np.array([[s.shape[1], s.shape[0]] for s in srcs], dtype=np.int32).ravel()
    offsets = np.concatenate([[0], np.cumsum([s.size for s in srcs])[:-1]]).astype(np.int64)
    return sizes, offsets


def source_image(srcs: Sequence[np.ndarray], pad_value: float = 0.0) -> np.ndarray:
    """sweep.cl's ``src_img``: every source's rows concatenated (float32), then SWEEP_SRC_PAD
    floats of ``pad_value`` (0 in the sweep; read with weight 0 only)."""
    return np.concatenate([np.ravel(s) for s in srcs]
                          + [np.full(SWEEP_SRC_PAD, pad_value)]).astype(np.float32)


# The sweep's device buffers, each named after the kernel argument it is passed as. One table
# (BufferSpec: name, element type, length as a function of the sizes) serves both plan_tiles,
# which sums it, and the sweep, which allocates it (satsweep.opencl.buffers).
@dataclasses.dataclass(frozen=True)
class RunSizes:
    """The sizes of the buffers a sweep keeps for the whole run (``run_buffers``)."""

    ref_px: int  # pixels of the reference image
    src_px: int  # pixels of all the source images
    n_src: int
    volume_floats: int = 0  # floats of a cost volume kept on the device (0: none)


@dataclasses.dataclass(frozen=True)
class SourceSizes:
    """The size of one source image whose census codes the sweep computes (``code_buffers``)."""

    px: int


@dataclasses.dataclass(frozen=True)
class TileSizes:
    """The sizes of one tile's buffers (``tile_buffers``)."""

    tw: int  # tile width and height, margins included (pixels)
    th: int
    iw: int  # interior width and height (pixels)
    ih: int
    nb: int  # planes per batch
    n_planes: int  # planes the tile sweeps (its homographies)
    n_src: int
    band_words: int = 0  # words of each group's band set (``group_bands``; 0: none)


def run_buffers(options: SweepOptions, *, volume: bool = False) -> tuple[BufferSpec, ...]:
    """The buffers a sweep keeps for the whole run: the reference image, the sources' sizes and
    offsets, every source image (``warped_census``) or every source's census codes
    (``sampled_codes``), and with ``volume`` the cost volume it keeps on the device."""
    srcs = BufferSpec("src_code", np.uint64, lambda r: r.src_px) \
        if options.cost_mode == "sampled_codes" else \
        BufferSpec("src_img", np.float32, lambda r: r.src_px + SWEEP_SRC_PAD)
    specs = (BufferSpec("ref_img", np.float32, lambda r: r.ref_px),
             BufferSpec("src_size", np.int32, lambda r: 2 * r.n_src),
             BufferSpec("src_offset", np.int64, lambda r: r.n_src),
             srcs)
    if volume:
        specs += (BufferSpec("volume", np.float32, lambda r: r.volume_floats),)
    return specs


def code_buffers() -> tuple[BufferSpec, ...]:
    """The buffers of one source's census codes (``sampled_codes``), while they are computed:
    census_transform's image and codes (the codes are then copied into ``src_code``)."""
    return (BufferSpec("img", np.float32, lambda s: s.px),
            BufferSpec("codes", np.uint64, lambda s: s.px))


def tile_buffers(options: SweepOptions, *, wta: bool = True,
                 pixel_windows: bool = False) -> tuple[BufferSpec, ...]:
    """The buffers of one tile: its homographies, the reference codes, the cost of a batch of
    planes with the filter's temporaries (``cost``, ``sums``: see ``PlaneSweep._filter``), the
    guide fields (guided filter), the split census kernels' warped sources and their groups'
    plane windows (``warp_window``, ``cost_window``: kernels/sweep.cl), with ``wta`` the
    winner-take-all's state and per-pixel outputs (over the interior), and with
    ``pixel_windows`` each interior pixel's window in the ragged volume (volume_pixel_windows)."""
    area = lambda t: t.tw * t.th  # noqa: E731
    interior = lambda t: t.iw * t.ih  # noqa: E731
    specs = [BufferSpec("homography", np.float32, lambda t: 9 * t.n_planes * t.n_src),
             BufferSpec("ref_code", np.uint64, area)]
    if options.slice_filter == "guided":  # [p | I p] sums -> [a | b] -> q
        specs += [BufferSpec("cost", np.float32, lambda t: 2 * t.nb * area(t)),
                  BufferSpec("sums", np.float32, lambda t: 2 * t.nb * area(t)),
                  BufferSpec("guide_i", np.float32, area),
                  BufferSpec("guide_mean", np.float32, lambda t: 2 * area(t))]
    elif options.slice_filter == "box":
        specs += [BufferSpec("cost", np.float32, lambda t: t.nb * area(t)),
                  BufferSpec("sums", np.float32, lambda t: t.nb * area(t))]
    else:
        specs += [BufferSpec("cost", np.float32, lambda t: t.nb * area(t))]
    if _split_census(options):
        positions = lambda t: _warped_positions(options, (t.tw, t.th), t.nb, t.n_src)  # noqa: E731
        specs += [BufferSpec("warped", np.float32, positions),
                  BufferSpec("seen", np.uint8, positions),
                  BufferSpec("warp_window", np.int32,
                             lambda t: 2 * _group_count(options, (t.tw, t.th), padded=True)),
                  BufferSpec("cost_window", np.int32,
                             lambda t: 2 * _group_count(options, (t.tw, t.th), padded=False)),
                  BufferSpec("warp_bands", np.uint32, lambda t: t.band_words * _group_count(
                      options, (t.tw, t.th), padded=True)),
                  BufferSpec("cost_bands", np.uint32, lambda t: t.band_words * _group_count(
                      options, (t.tw, t.th), padded=False))]
    if pixel_windows:
        specs += [BufferSpec("label_first", np.int32, interior),
                  BufferSpec("label_count", np.int32, interior),
                  BufferSpec("label_offset", np.uint64, interior)]
    if wta:
        specs += [BufferSpec("state", np.float32, lambda t: WTA_NSTATE * interior(t)),
                  BufferSpec("plane_index", np.float32, interior),
                  BufferSpec("confidence", np.float32, interior),
                  BufferSpec("best_cost", np.float32, interior),
                  BufferSpec("valid", np.uint8, interior)]
    return tuple(specs)


def _tile_bytes(options: SweepOptions, sizes: TileSizes) -> int:
    """Device bytes of one tile in the plan: its buffers WITH the winner-take-all's, whether or
    not the sweep runs it, so that a sweep without it (SGM's) is split as the sweep with it is
    (the tiles change the filters' float32 sums), plus the driver's allowance."""
    return max(total_bytes(tile_buffers(options), sizes),
               total_bytes(tile_buffers(options, wta=False, pixel_windows=True), sizes)) \
        + _SMALL_BUFFERS_BYTES


def _split_census(options: SweepOptions) -> bool:
    return options.cost_mode == "warped_census" and options.census_kernel == "split"


def _warp_plane_positions(options: SweepOptions, tile_dims: tuple[int, int], n_src: int) -> int:
    """Positions the split kernels warp per plane of a tile: every source over the tile plus the
    census margin."""
    rx, ry = options.census_radii
    return n_src * (tile_dims[0] + 2 * rx) * (tile_dims[1] + 2 * ry)


def _group_count(options: SweepOptions, tile_dims: tuple[int, int], *, padded: bool) -> int:
    """Groups of SWEEP_VEC positions per plane of the split kernels over a tile of ``tile_dims``:
    sweep_warp's (``padded``: the tile plus the census margin) or sweep_warped_cost's."""
    rx, ry = options.census_radii if padded else (0, 0)
    return _ceil_div(tile_dims[0] + 2 * rx, SWEEP_VEC) * (tile_dims[1] + 2 * ry)


def group_windows(options: SweepOptions, first: np.ndarray,
                  end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The split kernels' plane windows (``warp_window``, ``cost_window``) of a tile whose pixel
    (y, x) needs the filtered costs of planes [first, end) (tile-local plane indices, (th, tw)
    integer arrays). A pixel's raw cost of a plane is needed where a pixel within the cost
    filter's reach (``tile_margin``) needs that plane; a group of sweep_warped_cost's pixels
    computes the union of what its pixels need (and writes the worst cost for the other
    planes, which the filter may read); a group of sweep_warp's positions warps the union of
    what the groups whose census reads one of its positions compute, so that every computed
    cost reads warped sources of its own plane. Each as a flat int32 array of (first, end)
    pairs in the kernels' group order."""
    rx, ry = options.census_radii
    reach = options.tile_margin
    first = np.asarray(first, dtype=np.int64)
    end = np.asarray(end, dtype=np.int64)
    th, tw = first.shape
    cost_lo, cost_hi = _window_union(first, end, reach, reach)
    cost = _grouped(cost_lo, cost_hi)
    # Each pixel computes what its group computes; a warped position (py, px) is read by the
    # census of the tile pixels within the radii of tile pixel (py - ry, px - rx).
    pairs = cost.reshape(th, -1, 2)
    lo = np.repeat(pairs[:, :, 0], SWEEP_VEC, axis=1)[:, :tw]
    hi = np.repeat(pairs[:, :, 1], SWEEP_VEC, axis=1)[:, :tw]
    lo = np.pad(lo, ((ry, ry), (rx, rx)), constant_values=_EMPTY_FIRST)
    hi = np.pad(hi, ((ry, ry), (rx, rx)), constant_values=_EMPTY_END)
    return _grouped(*_window_union(lo, hi, ry, rx)), cost


def every_plane_windows(options: SweepOptions, tile_dims: tuple[int, int],
                        n_planes: int) -> tuple[np.ndarray, np.ndarray]:
    """``group_windows`` of a tile of ``tile_dims`` whose every pixel needs all ``n_planes``
    planes (a sweep without windows), without computing it."""
    return tuple(np.tile(np.array([0, n_planes], np.int32),
                         _group_count(options, tile_dims, padded=padded))
                 for padded in (True, False))


# Planes per bit of the windows' band sets (PlaneWindows.bands), as kernels/sweep.cl reads them.
BAND_PLANES = SWEEP_BAND_PLANES


def _popcount32(x: np.ndarray) -> np.ndarray:
    """Set bits of each uint32 of ``x``, int32 (a 16-bit table: numpy before 2.0 has no
    bitwise_count)."""
    return (_POPCOUNT16[x & np.uint32(0xFFFF)] + _POPCOUNT16[x >> np.uint32(16)]).astype(np.int32)


# Set bits of every 16-bit value; and the 32-bit masks of bits [lo, hi) (zero where hi <= lo).
_POPCOUNT16 = np.unpackbits(np.arange(1 << 16, dtype=">u2").view(np.uint8)).reshape(
    -1, 16).sum(axis=1).astype(np.uint8)
_BIT_RANGES = np.array([[((1 << hi) - (1 << lo)) if hi > lo else 0 for hi in range(33)]
                        for lo in range(33)], np.uint64).astype(np.uint32)


def band_words(n_planes: int) -> int:
    """32-bit words of a band set over ``n_planes`` planes."""
    return _ceil_div(_ceil_div(n_planes, BAND_PLANES), 32)


def group_bands(options: SweepOptions, bands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The split kernels' band sets (``warp_bands``, ``cost_bands``) of a tile whose pixel
    (y, x) needs the planes of the bands ``bands[:, y, x]`` ((words, th, tw) uint32 bit sets),
    as ``group_windows`` unions windows: over the cost filter's reach, then over each group of
    SWEEP_VEC pixels of a row; a warp group over the cost groups whose census reads one of its
    positions. Each a flat uint32 array, ``words`` per group in the kernels' group order."""
    rx, ry = options.census_radii
    reach = options.tile_margin
    tw = bands.shape[2]
    cost = _grouped_or(_or_within(bands, reach, reach))  # (words, th, groups)
    pixels = np.repeat(cost, SWEEP_VEC, axis=2)[:, :, :tw]
    warp = _grouped_or(_or_within(np.pad(pixels, ((0, 0), (ry, ry), (rx, rx))), ry, rx))
    return tuple(np.ascontiguousarray(a.transpose(1, 2, 0).ravel(), dtype=np.uint32)
                 for a in (warp, cost))


def _or_within(sets: np.ndarray, ry: int, rx: int) -> np.ndarray:
    """Per pixel of (words, rows, cols) bit sets, the union of the sets of the pixels within
    ``ry`` rows and ``rx`` columns of it (outside the arrays: none)."""
    cols = sets.copy()
    for d in range(1, rx + 1):
        cols[:, :, d:] |= sets[:, :, :-d]
        cols[:, :, :-d] |= sets[:, :, d:]
    out = cols.copy()
    for d in range(1, ry + 1):
        out[:, d:, :] |= cols[:, :-d, :]
        out[:, :-d, :] |= cols[:, d:, :]
    return out


def _grouped_or(sets: np.ndarray) -> np.ndarray:
    """(words, rows, groups): the union of the sets of each group of SWEEP_VEC pixels of a row
    of (words, rows, cols) bit sets."""
    words, rows, w = sets.shape
    padded = np.pad(sets, ((0, 0), (0, 0), (0, _ceil_div(w, SWEEP_VEC) * SWEEP_VEC - w)))
    return np.bitwise_or.reduce(padded.reshape(words, rows, -1, SWEEP_VEC), axis=3)


# An empty window of planes: the identities of the min of firsts and the max of ends (the
# first exact in float32, which the unions are computed in, and in int32).
_EMPTY_FIRST, _EMPTY_END = 2**30, 0


def _window_union(first: np.ndarray, end: np.ndarray, ry: int,
                  rx: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the union (min of firsts, max of ends) of the windows of the pixels within
    ``ry`` rows and ``rx`` columns of it (outside the arrays: none): OpenCV's erosion and
    dilation in float32, exact for plane indices below 2^24."""
    import cv2  # noqa: PLC0415

    kernel = np.ones((2 * ry + 1, 2 * rx + 1), np.uint8)
    lo = cv2.erode(np.asarray(first, np.float32), kernel, borderType=cv2.BORDER_CONSTANT,
                   borderValue=float(_EMPTY_FIRST))
    hi = cv2.dilate(np.asarray(end, np.float32), kernel, borderType=cv2.BORDER_CONSTANT,
                    borderValue=float(_EMPTY_END))
    return lo.astype(np.int64), hi.astype(np.int64)


def _grouped(first: np.ndarray, end: np.ndarray) -> np.ndarray:
    """The union of the windows of each group of SWEEP_VEC pixels of a row, as a flat int32
    array of (first, end) pairs, row by row."""
    rows, w = first.shape
    n = _ceil_div(w, SWEEP_VEC) * SWEEP_VEC - w
    lo = np.pad(first, ((0, 0), (0, n)), constant_values=_EMPTY_FIRST)
    hi = np.pad(end, ((0, 0), (0, n)), constant_values=_EMPTY_END)
    return np.ascontiguousarray(np.stack([lo.reshape(rows, -1, SWEEP_VEC).min(axis=2),
                                          hi.reshape(rows, -1, SWEEP_VEC).max(axis=2)],
                                         axis=-1).ravel(), dtype=np.int32)


def _warp_chunk(options: SweepOptions, tile_dims: tuple[int, int], nb: int, n_src: int) -> int:
    """Planes per launch of the split kernels for a tile of ``tile_dims`` in batches of nb planes:
    SPLIT_WARP_PLANES, or more on a tile small enough (_WARP_CHUNK_POSITIONS); at most nb."""
    per_plane = _warp_plane_positions(options, tile_dims, n_src)
    return max(1, min(nb, max(SPLIT_WARP_PLANES, _WARP_CHUNK_POSITIONS // per_plane)))


def _warped_positions(options: SweepOptions, tile_dims: tuple[int, int], nb: int, n_src: int) -> int:
    """Positions of the split kernels' warped sources for a tile (0 for the other kernels)."""
    if not _split_census(options):
        return 0
    return _warp_chunk(options, tile_dims, nb, n_src) * _warp_plane_positions(options, tile_dims,
                                                                              n_src)


def _resident_bytes(options: SweepOptions, ref_shape: tuple[int, int],
                    src_shapes: Sequence[tuple[int, int]], volume_floats: int = 0) -> int:
    """Device bytes kept for the whole run: ``run_buffers``, in ``sampled_codes`` mode one
    source's ``code_buffers`` while its codes are computed (the largest source's), and the
    driver's allowance."""
    run = total_bytes(run_buffers(options, volume=volume_floats > 0),
                      _run_sizes(ref_shape, src_shapes, volume_floats))
    if options.cost_mode == "sampled_codes":
        run += total_bytes(code_buffers(), SourceSizes(max(h * w for h, w in src_shapes)))
    return run + _SMALL_BUFFERS_BYTES


def _run_sizes(ref_shape: tuple[int, int], src_shapes: Sequence[tuple[int, int]],
               volume_floats: int = 0) -> RunSizes:
    return RunSizes(ref_px=ref_shape[0] * ref_shape[1],
                    src_px=sum(h * w for h, w in src_shapes), n_src=len(src_shapes),
                    volume_floats=volume_floats)


def plan_tiles(options: SweepOptions, ref_shape: tuple[int, int],
               src_shapes: Sequence[tuple[int, int]], n_planes: int, budget_bytes: int,
               max_alloc_bytes: int | None = None, volume_floats: int = 0) -> TilePlan:
    """Split a sweep into tiles and plane batches that fit ``budget_bytes`` of device memory.

    The run's buffers stay resident (``run_buffers``: the images, and a cost volume of
    ``volume_floats`` kept on the device); each tile holds ``tile_buffers``: its reference
    codes, guide fields, the cost of one batch of planes with the filter's temporaries, and the
    winner-take-all's state and outputs of its interior. The plane batch is kept as large as
    allowed (up to ``max_planes_per_batch``) while tiles are at least ``_MIN_TILE_SIDE`` pixels;
    then the batch shrinks. No buffer may exceed ``max_alloc_bytes``. Raises DeviceError when
    even one plane of a minimal tile does not fit.
    """
    h_img, w_img = ref_shape
    m = options.tile_margin
    resident = _resident_bytes(options, ref_shape, src_shapes, volume_floats)
    free = budget_bytes - resident
    n_src = len(src_shapes)
    if free <= 0:
        what = "images themselves" + (" and the kept cost volume" if volume_floats else "")
        raise DeviceError(f"memory budget of {budget_bytes / 2**20:.0f} MiB is smaller than the "
                          f"{what} ({resident / 2**20:.0f} MiB): raise "
                          "SweepOptions.memory_budget_bytes or memory_fraction")
    if max_alloc_bytes is not None:
        run_sizes = _run_sizes(ref_shape, src_shapes, volume_floats)
        for spec in run_buffers(options, volume=volume_floats > 0):
            if spec.nbytes(run_sizes) > max_alloc_bytes:
                raise DeviceError(f"the sweep's buffer {spec.name} of "
                                  f"{spec.nbytes(run_sizes) / 2**20:.0f} MiB ({n_src} source "
                                  f"images) exceeds the device's largest allocation "
                                  f"({max_alloc_bytes / 2**20:.0f} MiB): use fewer or smaller "
                                  "images")

    def sizes(tw: int, th: int, nb: int) -> TileSizes:
        """The tile of interior tw x th (margins added, clipped to the image), batches of nb."""
        return TileSizes(tw=min(tw + 2 * m, w_img), th=min(th + 2 * m, h_img), iw=tw, ih=th,
                         nb=nb, n_planes=n_planes, n_src=n_src,
                         band_words=band_words(n_planes) if options.window_bands else 0)

    def fits(tw: int, th: int, nb: int) -> bool:
        t = sizes(tw, th, nb)
        if _tile_bytes(options, t) > free:
            return False
        return max_alloc_bytes is None \
            or largest_bytes(tile_buffers(options), t) <= max_alloc_bytes

    nb = max(1, min(n_planes, options.max_planes_per_batch))
    min_side = min(_MIN_TILE_SIDE, w_img, h_img)
    while True:
        if fits(w_img, h_img, nb):
            tw, th = w_img, h_img
            break
        side = _largest_square(lambda s: fits(min(s, w_img), min(s, h_img), nb), max(w_img, h_img))
        if side >= min_side or nb == 1:
            if side < 1:
                raise DeviceError(
                    f"memory budget of {budget_bytes / 2**20:.0f} MiB cannot hold one plane of a "
                    f"1-pixel tile after {resident / 2**20:.0f} MiB of images: raise "
                    "SweepOptions.memory_budget_bytes or memory_fraction")
            th = min(side, h_img)
            # Widen the tile while it fits (useful for wide, short images).
            tw = min(side, w_img)
            tw = _largest_square(lambda s: fits(s, th, nb), w_img) if tw < w_img else tw
            break
        nb = max(1, nb // 2)
    n_tiles = math.ceil(w_img / tw) * math.ceil(h_img / th)
    return TilePlan(tile_w=tw, tile_h=th, margin=m, planes_per_batch=nb, resident_bytes=resident,
                    tile_bytes=_tile_bytes(options, sizes(tw, th, nb)), n_tiles=n_tiles)


def _largest_square(ok: Callable[[int], bool], upper: int) -> int:
    """Largest s in [0, upper] with ok(s) (ok monotone decreasing); 0 if none."""
    lo, hi = 0, upper
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo


# Edge-aware census (SweepOptions.census_mask_threshold): a pixel whose mask keeps bits weighing
# less than this (of the census term's 0..n, e.g. 24 for 5 x 5) is unlike most of its window (a
# point, a thin line) and keeps every bit. Issue-form seeds 11 / 15 at a threshold of 0.12, DFC
# MAE m: 6 bits 1.041 / 0.895, 12 bits 1.039 / 0.879, 16 bits 1.070 / 0.994.
CENSUS_MASK_MIN_BITS = 12.0


def census_mask_defines(options: SweepOptions) -> dict:
    """The census and sweep kernels' -D constants of the edge-aware census (none without one):
    CENSUS_MASK_THRESHOLD and CENSUS_MASK_MIN_BITS."""
    if options.census_mask_threshold == 0.0:
        return {}
    return {"CENSUS_MASK_THRESHOLD": float(options.census_mask_threshold),
            "CENSUS_MASK_MIN_BITS": CENSUS_MASK_MIN_BITS}


def census_ring_defines(options: SweepOptions) -> dict:
    """The sweep kernels' -D constants of the census ring's weight (none without one, or where
    the ring is the whole window, whose term it would not change): CENSUS_RING_WEIGHT, the
    ring's mask of the 64-bit code (CENSUS_RING) and of its low and high 32-bit words
    (CENSUS_RING_LO, CENSUS_RING_HI: sweep_warped_cost's vectors), and CENSUS_SCALE."""
    ring = options.census_ring
    if options.census_ring_weight == 0.0 or ring == (1 << options.census_bits) - 1:
        return {}
    return {"CENSUS_RING_WEIGHT": float(options.census_ring_weight),
            "CENSUS_RING": f"0x{ring:x}UL", "CENSUS_RING_LO": f"0x{ring & 0xFFFFFFFF:x}u",
            "CENSUS_RING_HI": f"0x{ring >> 32:x}u", "CENSUS_SCALE": options.census_scale}


# -- the processing class -----------------------------------------------------------------------
def _round_up(n: int, m: int) -> int:
    return ((n + m - 1) // m) * m




def _check_image(name: str, img) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(None, f"{name}: expected a 2-D image, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise InputError(None, f"{name}: expected a numeric image, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.isfinite(a).all():
        raise InputError(None, f"{name}: holds NaN or infinite values (fill no-data first)")
    return a


def prefilter(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` (float32) blurred by a Gaussian of ``sigma_px`` pixels, edges replicated."""
    import cv2  # noqa: PLC0415

    return cv2.GaussianBlur(image, (0, 0), sigmaX=float(sigma_px), sigmaY=float(sigma_px),
                            borderType=cv2.BORDER_REPLICATE)


class PlaneSweep:
    """The plane-sweep engine on one device: builds the kernels once, sweeps reference views.

    Its entry points (``height_map``, ``cost_volume``, ``cost_volume_on_device``,
    ``height_map_with_cost_volume``) take float32 images (tonemapped, about [0, 1]),
    homographies (n_planes, n_src, 3, 3) float64 mapping reference pixels to source pixels for
    each plane, and the plane heights.
    """

    def __init__(self, device: Device, options: SweepOptions | None = None, *,
                 profile: bool = False):
        self.device = device
        self.options = options if options is not None else SweepOptions()
        # With profile, the queue is drained around each stage and its wall time (s) summed
        # into stage_seconds ("census", "sweep", "filter", "wta"); slower, for benchmarks.
        self.profile = profile
        self.stage_seconds: dict[str, float] = {}
        # How the last sweep split its work (None before the first).
        self.last_split: WorkSplit | None = None

    @contextlib.contextmanager
    def _stage(self, name: str):
        """Account the wall time of the enclosed kernel launches to ``name`` when profiling."""
        if not self.profile:
            yield
            return
        self.device.queue.finish()
        t0 = time.perf_counter()
        yield
        self.device.queue.finish()
        self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - t0

    # -- programs -------------------------------------------------------------------------------
    def program_requests(self, n_src: int, *, wta: bool = True) -> list[tuple[str, dict | None]]:
        """The (source, defines) of the programs that a sweep of ``n_src`` sources builds:
        census, sweep, the cost filter (None for cost_filter = "none") and, with ``wta``, the
        winner-take-all (else None: a volume-only sweep, ``cost_volume``, never launches it)."""
        o = self.options
        rx, ry = o.census_radii
        sweep_defs = {"CENSUS_RX": rx, "CENSUS_RY": ry, "NSRC": n_src, "NBEST": o.best_k(n_src),
                      "AD_WEIGHT": float(o.ad_weight), "AD_TRUNC": float(o.ad_truncation),
                      "GRAD_WEIGHT": float(o.grad_weight), "GRAD_TRUNC": float(o.grad_truncation)}
        sweep_defs.update(census_ring_defines(o))
        sweep_defs.update(census_mask_defines(o))
        if o.cost_mode == "warped_census" and o.census_kernel == "staged":
            sweep_defs.update({"WG_X": o.work_group[0], "WG_Y": o.work_group[1]})
        wta_defs = {"NSRC": n_src, "CENSUS_RX": rx, "CENSUS_RY": ry, "AD_WEIGHT": float(o.ad_weight),
                    "GRAD_WEIGHT": float(o.grad_weight)}
        census_defs = {"CENSUS_RX": rx, "CENSUS_RY": ry, **census_mask_defines(o)}
        return [("census", census_defs), ("sweep", sweep_defs),
                self._filter_request(), ("wta", wta_defs) if wta else None]

    def _programs(self, n_src: int, *, wta: bool = True):
        """The built programs of ``program_requests`` (None where it has None)."""
        return tuple(None if r is None else self.device.build(*r)
                     for r in self.program_requests(n_src, wta=wta))

    def _filter_request(self) -> tuple[str, dict] | None:
        """The cost-filter program's (source, defines) for the options (None for "none")."""
        o = self.options
        if o.slice_filter == "none":
            return None
        r = o.filter_radius
        defs = {"BOX_R": r, "BOX_CHUNK": box_chunk(r)}
        if o.slice_filter == "guided":
            defs["GF_EPS"] = float(o.gf_eps)
        return "guided_filter", defs

    def _filter_program(self):
        """The cost-filter program for the options (None for cost_filter = "none")."""
        request = self._filter_request()
        return None if request is None else self.device.build(*request)

    def budget_bytes(self) -> int:
        """The device memory budget of a run (bytes)."""
        o = self.options
        if o.memory_budget_bytes is not None:
            return int(o.memory_budget_bytes)
        return int(o.memory_fraction * self.device.global_mem_bytes)

    # -- public entry points --------------------------------------------------------------------
    # Each sweeps ``ref_image`` against ``src_images`` (float32, tonemapped to about [0, 1]) over
    # the planes ``heights`` ((n_planes,) strictly monotonic, metres) with ``homographies``
    # ((n_planes, n_src, 3, 3) float64, plane p and source s mapping homogeneous reference
    # pixels to source pixels). ``windows``: sweep each block of the reference over its own
    # window of the planes only (coarse-to-fine): the volume's label d of pixel p then stands
    # for plane ``label_base[p] + d``, d < ``label_count[p]``, and a height map's plane indices
    # and heights are still absolute, a best plane at either end of its window invalid with
    # ``reject_range_edges``. The options' ``lr_check`` is a check of height maps: the volume
    # methods have none to check. After each, ``last_split`` tells how the work was split.
    def height_map(self, ref_image, src_images: Sequence, homographies, heights) -> HeightMap:
        """The winner-take-all height map (and, with ``lr_check``, the left-right check); the
        cost volume never exists whole."""
        ref, srcs, hom, hts = self._inputs(ref_image, src_images, homographies, heights, None)
        result, _ = self._sweep(ref, srcs, hom, hts, wta=True)
        if self.options.lr_check:
            self._lr_check(result, ref, srcs, hom, hts)
        return result

    def cost_volume(self, ref_image, src_images: Sequence, homographies, heights, *,
                    windows: PlaneWindows | None = None) -> CostVolume:
        """The filtered cost of every plane, on the host: a plane-major ``CostVolume`` (L, H, W)
        float32 in census bits (with ``windows``, L = ``windows.n_planes``; a pixel's labels past
        its window's count hold the worst cost, ``SweepOptions.max_cost``)."""
        ref, srcs, hom, hts = self._inputs(ref_image, src_images, homographies, heights, windows)
        return self._sweep(ref, srcs, hom, hts, keep="host", windows=windows, wta=False)[1]

    def cost_volume_on_device(self, ref_image, src_images: Sequence, homographies, heights, *,
                              windows: PlaneWindows | None = None) -> CostVolume:
        """The filtered cost of every plane, kept on the device (counted in the memory budget)
        in SGM's layout, so that SGM needs no copy of its own: a pixel-major ``CostVolume`` (H,
        W, L), or with windows of their own counts a ragged one (each pixel just its window's
        labels). The caller releases it (``CostVolume.release`` or a ``with`` block)."""
        ref, srcs, hom, hts = self._inputs(ref_image, src_images, homographies, heights, windows)
        return self._sweep(ref, srcs, hom, hts, keep="device", windows=windows, wta=False)[1]

    def height_map_with_cost_volume(self, ref_image, src_images: Sequence, homographies, heights,
                                    *, windows: PlaneWindows | None = None,
                                    on_device: bool = False) -> tuple[HeightMap, CostVolume]:
        """Both, from one sweep: the winner-take-all height map (with ``lr_check``, checked;
        not with ``windows`` then) and the cost volume (``cost_volume_on_device``'s with
        ``on_device``, else ``cost_volume``'s). For an MRF that starts from the winner-take-all
        or a left-right check of it."""
        ref, srcs, hom, hts = self._inputs(ref_image, src_images, homographies, heights, windows)
        if windows is not None and self.options.lr_check:
            raise InputError(None, "plane_windows: the left-right check sweeps every plane; "
                                   "set lr_check = false for a coarse-to-fine sweep")
        result, volume = self._sweep(ref, srcs, hom, hts, keep="device" if on_device else "host",
                                     windows=windows, wta=True)
        if self.options.lr_check:
            try:
                self._lr_check(result, ref, srcs, hom, hts)
            except BaseException:
                volume.release()  # the caller never gets it
                raise
        return result, volume

    def _inputs(self, ref_image, src_images, homographies, heights,
                windows: PlaneWindows | None):
        """The checked inputs as the sweep takes them (prefiltered when the options say so):
        (ref, srcs, hom, hts); InputError naming the bad one."""
        ref = _check_image("ref_image", ref_image)
        srcs = [_check_image(f"src_images[{i}]", s) for i, s in enumerate(src_images)]
        if not srcs:
            raise InputError(None, "src_images: at least one source view is needed")
        if len(srcs) > 32:
            raise InputError(None, f"src_images: {len(srcs)} sources, at most 32 are supported")
        hom = np.asarray(homographies, dtype=np.float64)
        hts = np.asarray(heights, dtype=np.float64).reshape(-1)
        if hom.ndim != 4 or hom.shape[1:] != (len(srcs), 3, 3) or hom.shape[0] != hts.size:
            raise InputError(None, f"homographies: shape {hom.shape}, expected "
                                   f"({hts.size}, {len(srcs)}, 3, 3) for {hts.size} heights")
        if hts.size < 1 or not np.isfinite(hts).all() or not np.isfinite(hom).all():
            raise InputError(None, "heights/homographies: need at least one plane, finite values")
        if hts.size > 1:
            d = np.diff(hts)
            if not ((d > 0).all() or (d < 0).all()):
                raise InputError(None, "heights: must be strictly monotonic")
        if windows is not None:
            windows.check(ref.shape, hts.size)
        if self.options.prefilter_sigma_px > 0:
            ref = prefilter(ref, self.options.prefilter_sigma_px)
            srcs = [prefilter(s, self.options.prefilter_sigma_px) for s in srcs]
        return ref, srcs, hom, hts

    def filter_volume(self, cost, guide) -> np.ndarray:
        """The configured cost filter applied to host slices (n, h, w) with a 2-D guide.

        Runs the same kernels as the sweep on one whole-image tile; for tests and inspection.
        """
        import pyopencl as cl  # noqa: PLC0415

        o = self.options
        vol = np.ascontiguousarray(cost, dtype=np.float32)
        g = _check_image("guide", guide)
        if vol.ndim != 3 or vol.shape[1:] != g.shape:
            raise InputError(None, f"cost: shape {vol.shape} does not match guide {g.shape}")
        nb, th, tw = vol.shape
        filt = self._filter_program()
        tile = _Tile(0, 0, tw, th, 0, 0, tw, th)
        sizes = TileSizes(tw=tw, th=th, iw=tw, ih=th, nb=nb, n_planes=0, n_src=0)
        # The filter's buffers of a tile, and the guide image in place of the reference's.
        specs = tuple(spec for spec in tile_buffers(o, wta=False)
                      if spec.name in ("cost", "sums", "guide_i", "guide_mean"))
        guided = o.slice_filter == "guided"
        if guided:
            specs += (BufferSpec("ref_img", np.float32, lambda t: t.tw * t.th),)
        with DeviceMemory(self.device.context).allocate(
                specs, sizes, host={"ref_img": g} if guided else None) as b:
            cl.enqueue_copy(self.device.queue, b["cost"], vol)
            if guided:
                self._guide_stats(filt, tile, b["ref_img"], tw, b["guide_i"], b["guide_mean"],
                                  b["sums"])
            self._filter(filt, tile, nb, b["cost"], b.get("sums"), b.get("guide_i"),
                         b.get("guide_mean"))
            out = np.empty_like(vol)
            cl.enqueue_copy(self.device.queue, out, b["cost"])
            self.device.queue.finish()
        return out

    # -- implementation -------------------------------------------------------------------------
    def _sweep(self, ref: np.ndarray, srcs: list[np.ndarray], hom: np.ndarray,
               hts: np.ndarray, *, keep: Literal["host", "device"] | None = None,
               windows: PlaneWindows | None = None,
               wta: bool = True) -> tuple[HeightMap | None, CostVolume | None]:
        """The sweep behind the entry points, of checked inputs: (the winner-take-all height map
        if ``wta``, else None; the cost volume kept on the host or the device as ``keep`` says,
        else None); sets ``last_split``."""
        import pyopencl as cl  # noqa: PLC0415
        import pyopencl.array as cla  # noqa: PLC0415

        o = self.options
        queue = self.device.queue
        n_src, n_total = len(srcs), hts.size
        # With windows, every tile (one block) sweeps n_planes planes of its own.
        n_planes = n_total if windows is None else windows.n_planes
        h_img, w_img = ref.shape
        census_prg, sweep_prg, filt_prg, wta_prg = self._programs(n_src, wta=wta)
        keep_volume, on_device = keep is not None, keep == "device"
        # A device volume of windows with their own counts is RAGGED: each block's pixels hold
        # just their window's labels, block after block (label_offset: where each pixel's start).
        ragged = on_device and windows is not None and windows.count is not None
        # Windows of one pixel each: tiles as without windows, each sweeping the planes of its
        # pixels' windows, the split kernels skipping the planes out of each group's windows.
        pixel = windows is not None and windows.block == 1
        if pixel and (not ragged or wta):
            raise InputError(None, "plane_windows: windows of one pixel are swept into a device "
                                   "cost volume, without winner-take-all (SGM's sweep)")
        if pixel:
            n_planes = n_total
        label_offset = block_start = None
        if ragged:
            label_offset, block_start = _ragged_layout(windows, ref.shape)
            volume_floats = int(block_start[-1])
        else:
            volume_floats = n_planes * h_img * w_img
        run_sizes = _run_sizes(ref.shape, [s.shape for s in srcs],
                               volume_floats if on_device else 0)
        volume_bytes = 4 * volume_floats
        if on_device and volume_bytes > self.device.max_alloc_bytes:
            raise DeviceError(f"{self.device.info.label}: a cost volume of "
                              f"{volume_bytes / 2**20:.0f} MiB ({n_planes} planes x {h_img} x "
                              f"{w_img}) exceeds the largest allocation "
                              f"({self.device.max_alloc_bytes / 2**20:.0f} MiB): sweep smaller tiles")
        plan = plan_tiles(o, ref.shape, [s.shape for s in srcs], n_planes, self.budget_bytes(),
                          self.device.max_alloc_bytes, volume_floats=run_sizes.volume_floats)
        tile_w, tile_h = plan.tile_w, plan.tile_h
        if windows is not None and not pixel:
            if min(tile_w, w_img) < min(windows.block, w_img) \
                    or min(tile_h, h_img) < min(windows.block, h_img):
                raise DeviceError(f"memory budget of {self.budget_bytes() / 2**20:.0f} MiB holds "
                                  f"tiles of {tile_w} x {tile_h} px, smaller than the plane "
                                  f"windows' {windows.block} px blocks: use smaller blocks")
            tile_w = tile_h = windows.block
        mem = DeviceMemory(self.device.context)
        i32 = np.int32

        # Resident data: the reference image and every source (or its codes), uploaded once,
        # and the device volume; all released at the end, but for the volume handed out.
        sizes, offsets = source_layout(srcs)
        host = {"ref_img": ref, "src_size": sizes, "src_offset": offsets}
        if o.cost_mode != "sampled_codes":
            host["src_img"] = source_image(srcs)
        census_k = self.device.kernel(census_prg, "census_transform")
        # The winner-take-all's per-pixel maps (index, confidence, cost, validity), if asked for.
        outs = (np.zeros((h_img, w_img), np.float32), np.zeros((h_img, w_img), np.float32),
                np.zeros((h_img, w_img), np.float32), np.zeros((h_img, w_img), np.uint8)) \
            if wta else None
        # A host volume's labels past a block's window get the worst cost (a device volume with
        # counts is ragged and has none).
        padded = windows is not None and windows.count is not None \
            and bool(np.any(np.asarray(windows.count) < n_planes))
        n_batches = n_tiles = 0
        with mem.allocate(run_buffers(o, volume=on_device), run_sizes, host=host) as res:
            if o.cost_mode == "sampled_codes":
                # Each source's codes computed on the device once, into one concatenated buffer.
                for img, off in zip(srcs, offsets):
                    h_s, w_s = img.shape
                    with mem.allocate(code_buffers(), SourceSizes(img.size),
                                      host={"img": img}) as tmp:
                        _launch(census_k, queue, (w_s, h_s), tmp["img"], i32(w_s), i32(h_s),
                                i32(0), i32(0), i32(w_s), i32(h_s), tmp["codes"])
                        cl.enqueue_copy(queue, res["src_code"], tmp["codes"],
                                        dst_offset=8 * int(off), byte_count=8 * img.size)
                        queue.finish()
                src_buf = res["src_code"]
                sweep_k = self.device.kernel(sweep_prg, "sweep_code_cost")
            else:
                src_buf = res["src_img"]
                kern = self.device.kernel
                sweep_k = (kern(sweep_prg, "sweep_warp"), kern(sweep_prg, "sweep_warped_cost")) \
                    if _split_census(o) else kern(sweep_prg, "sweep_census_cost")
            volume = volume_k = None
            if on_device:
                volume = res["volume"]
                volume_k = self.device.kernel(sweep_prg, "volume_pixel_windows" if pixel
                                              else "volume_pixel_major")
            elif keep_volume:
                volume = np.full((n_planes, h_img, w_img), o.max_cost, np.float32) if padded \
                    else np.empty((n_planes, h_img, w_img), np.float32)
            m = plan.margin
            for ix0, iy0, ix1, iy1, tx0, ty0, tx1, ty1 in tile_grid(w_img, h_img, tile_w, tile_h,
                                                                    m):
                tile = _Tile(tx0, ty0, tx1 - tx0, ty1 - ty0, ix0 - tx0, iy0 - ty0, ix1 - ix0,
                             iy1 - iy0)
                first, count = 0, n_planes
                # where the tile's interior goes in a device volume: (row width, origin x,
                # origin y, labels per pixel, start)
                place = (w_img, ix0, iy0, n_planes, 0)
                pixel_windows = None
                if pixel:
                    # The tile sweeps planes [first, first + count): its pixels' windows.
                    f = np.asarray(windows.first[ty0:ty1, tx0:tx1], dtype=np.int64)
                    e = f + np.asarray(windows.count[ty0:ty1, tx0:tx1], dtype=np.int64)
                    first = int(f.min())
                    count = int(e.max()) - first
                    inner = (slice(iy0, iy1), slice(ix0, ix1))
                    pixel_windows = (f - first, e - first, windows.first[inner] - first,
                                     windows.count[inner], label_offset[inner],
                                     None if windows.bands is None
                                     else windows.bands[:, ty0:ty1, tx0:tx1], first)
                elif windows is not None:
                    bi, bj = iy0 // tile_h, ix0 // tile_w
                    first, count = windows.sweep_range(bi, bj)
                    if ragged:
                        place = (ix1 - ix0, 0, 0, count,
                                 int(block_start[bi * windows.first.shape[1] + bj]))
                n_batches += self._sweep_tile(
                    tile, plan.planes_per_batch, hom[first:first + count], count, mem, res,
                    src_buf, census_k, sweep_k, filt_prg, wta_prg, (w_img, h_img), outs,
                    (ix0, iy0), volume, volume_k, place, pixel_windows)
                if wta:
                    outs[0][iy0:iy1, ix0:ix1] += first  # the swept plane index -> the plane's
                n_tiles += 1
            if on_device:
                volume = cla.Array(queue, (volume_floats,) if ragged else (h_img, w_img, n_planes),
                                   np.float32, data=res.detach("volume"))
        self.last_split = WorkSplit(n_tiles=n_tiles, n_batches=n_batches,
                                    peak_device_bytes=mem.peak)
        kept = None
        if keep_volume:
            base = None if windows is None else windows.per_pixel(ref.shape)
            count = None if windows is None else windows.counts(ref.shape)
            kept = CostVolume(volume, "ragged" if ragged else "pixel_major" if on_device
                              else "plane_major", label_base=base, label_count=count,
                              label_offset=label_offset)
        if not wta:
            return None, kept
        index, out_conf, out_cost, out_valid = outs
        if not o.subplane:
            index = np.rint(index).astype(np.float32)
        valid = out_valid.astype(bool)
        height = np.interp(index.astype(np.float64), np.arange(n_total), hts) if n_total > 1 \
            else np.full(index.shape, hts[0])
        height[~valid] = np.nan
        return HeightMap(height=height, plane_index=index, confidence=out_conf, valid=valid,
                         cost_min=out_cost, split=self.last_split), kept

    def _sweep_tile(self, tile, nb_max, hom, n_planes, mem, res, src_buf, census_k, sweep_k,
                    filt_prg, wta_prg, ref_size, outs, interior_origin, volume=None,
                    volume_k=None, place=None, pixel_windows=None) -> int:
        """Sweep one tile over the n_planes planes of ``hom``, its buffers (``tile_buffers``)
        allocated from ``mem`` for the tile alone; ``res``: the run's buffers (``run_buffers``),
        src_buf the sources' images or codes among them. A kept volume receives the planes as
        each pixel's labels 0 .. n_planes - 1: a host volume at the interior's origin, a device
        volume as ``place`` = (out_w, ox, oy, labels per pixel, start) says (volume_pixel_major).
        With ``pixel_windows`` = (first, end of every tile pixel's window; first, count and
        volume offset of every interior pixel's, plane indices of ``hom``; the tile pixels'
        band sets or None, the plane of ``hom[0]`` among the bands'), a pixel computes the planes
        of its window (and of its bands) only and a ragged device volume receives them
        (volume_pixel_windows). outs = None: no winner-take-all (the volume only)."""
        import pyopencl as cl  # noqa: PLC0415

        o = self.options
        queue = self.device.queue
        i32 = np.int32
        w_img, h_img = ref_size
        tw, th = tile.tw, tile.th
        n_src = hom.shape[1]
        iw, ih = tile.iw, tile.ih
        wta = outs is not None

        # Homographies in tile-local reference coordinates: H @ T(tx0, ty0), normalised, float32.
        shift = np.eye(3)
        shift[0, 2], shift[1, 2] = tile.tx0, tile.ty0
        local = hom @ shift
        local = local / local[:, :, 2:3, 2:3]
        hom_f32 = np.ascontiguousarray(local.reshape(n_planes, n_src, 9), dtype=np.float32)
        # A tile's band sets (windows of one pixel with bands): the kernels skip the planes of
        # a group's window outside its bands; they take global plane indices (band_base: the
        # tile's first plane).
        # (The band buffers are as large as plan_tiles counts them whether or not they are used.)
        bands = pixel_windows[5] if pixel_windows is not None else None
        n_words = int(bands.shape[0]) if bands is not None and _split_census(o) else 0
        band_base = int(pixel_windows[6]) if n_words else 0
        sizes = TileSizes(tw=tw, th=th, iw=iw, ih=ih, nb=nb_max, n_planes=n_planes, n_src=n_src,
                          band_words=n_words or (band_words(n_planes) if o.window_bands else 0))
        host = {"homography": hom_f32}
        if _split_census(o):
            if pixel_windows is None:
                host["warp_window"], host["cost_window"] = every_plane_windows(o, (tw, th),
                                                                               n_planes)
            else:
                host["warp_window"], host["cost_window"] = group_windows(o, *pixel_windows[:2])
            if n_words:
                host["warp_bands"], host["cost_bands"] = group_bands(o, bands)
        if pixel_windows is not None:
            host["label_first"], host["label_count"], host["label_offset"] = (
                np.ascontiguousarray(a, dtype=t)
                for a, t in zip(pixel_windows[2:5], (np.int32, np.int32, np.uint64)))
        with mem.allocate(tile_buffers(o, wta=wta, pixel_windows=pixel_windows is not None),
                          sizes, host=host) as b:
            hom_buf, code_buf, ref_buf = b["homography"], b["ref_code"], res["ref_img"]
            off_buf, size_buf = res["src_offset"], res["src_size"]
            with self._stage("census"):
                _launch(census_k, queue, (tw, th), ref_buf, i32(w_img), i32(h_img),
                        i32(tile.tx0), i32(tile.ty0), i32(tw), i32(th), code_buf)

            vol_a, vol_b = b["cost"], b.get("sums")
            guide_i, guide_mean = b.get("guide_i"), b.get("guide_mean")
            if o.slice_filter == "guided":
                with self._stage("filter"):
                    self._guide_stats(filt_prg, tile, ref_buf, w_img, guide_i, guide_mean, vol_b)

            state = b.get("state")
            if wta:
                wta_update = self.device.kernel(wta_prg, "wta_update")
                _launch(self.device.kernel(wta_prg, "wta_init"), queue, (iw, ih), state,
                        i32(iw), i32(ih))

            warped, seen = b.get("warped"), b.get("seen")
            if _split_census(o):
                rx, ry = o.census_radii
                pw, ph = tw + 2 * rx, th + 2 * ry
                chunk = _warp_chunk(o, (tw, th), nb_max, n_src)

            # The cost of a batch lands in vol_a (first nb planes); the filters use vol_b (and the
            # rest of vol_a) as temporaries and leave the filtered cost in vol_a. Without
            # winner-take-all, the guided filter's last pass writes the interior straight into the
            # pixel-major volume instead (no plane-major q, no copy).
            ix0, iy0 = interior_origin
            fused = (volume is not None and not isinstance(volume, np.ndarray) and not wta
                     and o.slice_filter == "guided" and pixel_windows is None)
            wgx, wgy = o.work_group
            n_batches = 0
            for p0 in range(0, n_planes, nb_max):
                nb = min(nb_max, n_planes - p0)
                with self._stage("sweep"):
                    if warped is not None:
                        warp_k, cost_k = sweep_k
                        for c0 in range(0, nb, chunk):
                            nc = min(chunk, nb - c0)
                            _launch(warp_k, queue, (_ceil_div(pw, SWEEP_VEC), ph, nc * n_src),
                                    src_buf, off_buf, size_buf,
                                    hom_buf, i32(tw), i32(th), i32(tile.tx0), i32(tile.ty0),
                                    i32(w_img), i32(h_img), i32(p0 + c0), b["warp_window"],
                                    b["warp_bands"], i32(n_words), i32(band_base), warped, seen)
                            _launch(cost_k, queue, (_ceil_div(tw, SWEEP_VEC), th, nc), warped,
                                    seen, code_buf, ref_buf, i32(tw), i32(th), i32(tile.tx0),
                                    i32(tile.ty0), i32(w_img), i32(h_img), i32(c0), i32(p0 + c0),
                                    b["cost_window"], b["cost_bands"], i32(n_words),
                                    i32(band_base), vol_a)
                    elif o.cost_mode == "warped_census":
                        sweep_k(queue, (_round_up(tw, wgx), _round_up(th, wgy), nb), (wgx, wgy, 1),
                                src_buf, off_buf, size_buf, hom_buf, code_buf, ref_buf, i32(tw),
                                i32(th), i32(tile.tx0), i32(tile.ty0), i32(w_img), i32(h_img),
                                i32(p0), vol_a)
                    else:
                        _launch(sweep_k, queue, (tw, th, nb), src_buf, off_buf, size_buf, hom_buf,
                                code_buf, i32(tw), i32(th), i32(p0), vol_a)
                to_volume = (volume, *place, p0) if fused else None
                with self._stage("filter"):
                    self._filter(filt_prg, tile, nb, vol_a, vol_b, guide_i, guide_mean, to_volume)
                if isinstance(volume, np.ndarray):  # MRF path: the filtered interior to the host
                    batch = np.empty((nb, th, tw), np.float32)
                    cl.enqueue_copy(queue, batch, vol_a)
                    volume[p0:p0 + nb, iy0:iy0 + tile.ih, ix0:ix0 + tile.iw] = \
                        batch[:, tile.my:tile.my + tile.ih, tile.mx:tile.mx + tile.iw]
                elif pixel_windows is not None:  # MRF path: each pixel's window, ragged
                    with self._stage("copy"):
                        _launch(volume_k, queue, (iw, ih), vol_a, i32(tw), i32(th), i32(tile.mx),
                                i32(tile.my), i32(iw), i32(ih), i32(nb), i32(p0),
                                b["label_first"], b["label_count"], b["label_offset"], volume)
                elif volume is not None and not fused:  # MRF path: the interior, pixel-major
                    with self._stage("copy"):
                        out_w, ox, oy, n_labels, start = place
                        _launch(volume_k, queue, (iw, ih), vol_a,
                                i32(tw), i32(th), i32(tile.mx), i32(tile.my), i32(iw), i32(ih),
                                i32(nb), volume, i32(out_w), i32(ox), i32(oy), i32(n_labels),
                                i32(p0), np.uint64(start))
                if wta:
                    with self._stage("wta"):
                        _launch(wta_update, queue, (_ceil_div(iw, WTA_VEC), ih), vol_a, i32(tw),
                                i32(th), i32(tile.mx), i32(tile.my), i32(iw), i32(ih), i32(nb),
                                i32(p0), state)
                n_batches += 1

            if wta:
                with self._stage("wta"):
                    _launch(self.device.kernel(wta_prg, "wta_finalize"), queue, (iw, ih), state,
                            i32(iw), i32(ih), i32(n_planes), i32(tile.mx), i32(tile.my),
                            hom_buf, size_buf, i32(1 if o.reject_range_edges else 0),
                            b["plane_index"], b["confidence"], b["best_cost"], b["valid"])
                for name, host, dtype in zip(("plane_index", "confidence", "best_cost", "valid"),
                                             outs, (np.float32, np.float32, np.float32, np.uint8)):
                    tmp = np.empty((ih, iw), dtype)
                    cl.enqueue_copy(queue, tmp, b[name])
                    host[iy0:iy0 + ih, ix0:ix0 + iw] = tmp
            queue.finish()
        return n_batches

    def _guide_stats(self, prg, tile, ref_buf, w_img, guide_i, guide_mean, scratch) -> None:
        """guide_i = I and guide_mean = [box mean of I | box mean of I^2] over the tile."""
        queue = self.device.queue
        kern = self.device.kernel
        i32 = np.int32
        tw, th = tile.tw, tile.th
        chunk = box_chunk(self.options.filter_radius)
        _launch(kern(prg, "gf_guide_fields"), queue, (tw, th), ref_buf, i32(w_img),
                i32(tile.tx0), i32(tile.ty0), i32(tw), i32(th), guide_i, guide_mean)
        _launch(kern(prg, "box_cols_sum"), queue,
                (_ceil_div(tw, GF_COLS_VEC), _ceil_div(th, chunk), 2),
                guide_mean, scratch, i32(tw), i32(th))
        _launch(kern(prg, "box_rows_mean"), queue, (_ceil_div(tw, chunk), th, 2),
                scratch, guide_mean, i32(tw), i32(th))

    def _filter(self, prg, tile, nb, vol_a, vol_b, guide_i, guide_mean, to_volume=None) -> None:
        """Filter the nb cost planes at the start of vol_a in place (through vol_b).

        With ``to_volume`` = (volume, out_w, ox, oy, n_planes, start, plane0) (guided filter
        only), the tile's interior goes straight into the pixel-major ``volume`` instead, at
        (ox, oy) of rows of out_w pixels from float ``start`` on, and labels plane0 .. plane0 +
        nb - 1 (gf_rows_q_pixel_major; vol_a is left holding the [a | b] coefficients).
        """
        o = self.options
        if o.slice_filter == "none":
            return
        queue = self.device.queue
        kern = self.device.kernel
        i32 = np.int32
        tw, th = tile.tw, tile.th
        chunk = box_chunk(o.filter_radius)
        ncx, ncy = _ceil_div(tw, chunk), _ceil_div(th, chunk)
        ncv = _ceil_div(tw, GF_COLS_VEC)  # column kernels: GF_COLS_VEC columns per work-item
        if o.slice_filter == "box":
            _launch(kern(prg, "box_cols_sum"), queue, (ncv, ncy, nb), vol_a, vol_b, i32(tw),
                    i32(th))
            _launch(kern(prg, "box_rows_mean"), queue, (ncx, th, nb), vol_b, vol_a, i32(tw),
                    i32(th))
            return
        # Guided: p = vol_a[0:nb] -> vol_b = [colsum p | colsum I p] -> vol_a = [a | b]
        # -> vol_b = [colsum a | colsum b] -> vol_a[0:nb] = q.
        _launch(kern(prg, "gf_cols_p"), queue, (ncv, ncy, nb), vol_a, guide_i, vol_b,
                i32(tw), i32(th), i32(nb))
        _launch(kern(prg, "gf_rows_ab"), queue, (ncx, th, nb), vol_b, guide_mean, vol_a,
                i32(tw), i32(th), i32(nb))
        _launch(kern(prg, "box_cols_sum"), queue, (ncv, ncy, 2 * nb), vol_a, vol_b,
                i32(tw), i32(th))
        if to_volume is None:
            _launch(kern(prg, "gf_rows_q"), queue, (ncx, th, nb), vol_b, guide_i, vol_a,
                    i32(tw), i32(th), i32(nb))
            return
        volume, out_w, ox, oy, n_planes, start, plane0 = to_volume
        _launch(kern(prg, "gf_rows_q_pixel_major"), queue, (ncx, tile.ih), vol_b, guide_i,
                i32(tw), i32(th), i32(nb), i32(tile.mx), i32(tile.my), i32(tile.iw),
                i32(tile.ih), volume, i32(out_w),
                i32(ox), i32(oy), i32(n_planes), i32(plane0), np.uint64(start))

    def _lr_check(self, result: HeightMap, ref: np.ndarray, srcs: list[np.ndarray],
                  hom: np.ndarray, hts: np.ndarray) -> None:
        """Sweep again with the first source as reference and keep pixels that agree.

        The swapped sweep uses the homographies source 0 -> reference (inverse) and source 0 ->
        source j (H_j H_0^-1). A reference pixel with fractional plane index f maps to source 0
        by interpolating the maps of the planes around f; it passes when source 0's nearest
        pixel is valid with |f - f_0| <= lr_tolerance_planes.
        """
        ok = self.lr_mask(result.plane_index, result.valid, ref, srcs, hom, hts)
        result.valid &= ok
        result.height[~result.valid] = np.nan

    def lr_mask(self, plane_index: np.ndarray, valid: np.ndarray, ref: np.ndarray,
                srcs: list[np.ndarray], hom: np.ndarray, hts: np.ndarray) -> np.ndarray:
        """Pixels of a (whole-reference) winner-take-all map that pass the left-right check.

        The first source is swept as the reference (winner-take-all, no check) against the
        reference and the other sources; see ``_lr_check`` and ``lr_consistent``.
        """
        inv0 = np.linalg.inv(hom[:, 0])
        swapped = [inv0] + [hom[:, j] @ inv0 for j in range(1, len(srcs))]
        back = PlaneSweep(self.device, self.options.replace(lr_check=False))
        other, _ = back._sweep(srcs[0], [ref] + list(srcs[1:]), np.stack(swapped, axis=1), hts)
        return lr_consistent(plane_index, valid, other.plane_index, other.valid, hom[:, 0],
                             self.options.lr_tolerance_planes)


@dataclasses.dataclass(frozen=True)
class _Tile:
    tx0: int  # tile origin in the reference image (margin included)
    ty0: int
    tw: int  # tile size (margin included)
    th: int
    mx: int  # interior origin inside the tile
    my: int
    iw: int  # interior size
    ih: int


def _ragged_layout(windows: PlaneWindows, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The layout of a ragged pixel-major volume over plane windows: block after block (row-major
    over the blocks), each block's pixels row by row, each pixel its block's count of labels.
    Returns ((H, W) uint64 start of each pixel's labels, in floats; block starts, one per block
    plus the total, in the same units)."""
    h, w = shape
    b = windows.block
    nby, nbx = np.asarray(windows.first).shape
    rows = np.minimum(b, h - b * np.arange(nby))   # pixel rows of each block row
    cols = np.minimum(b, w - b * np.arange(nbx))   # pixel columns of each block column
    count = np.asarray(windows.count, dtype=np.uint64)
    size = rows[:, None].astype(np.uint64) * cols[None, :].astype(np.uint64) * count
    block_start = np.concatenate([[0], np.cumsum(size.ravel())]).astype(np.uint64)
    # pixel (y, x) of block (i, j): start + ((y - i b) cols[j] + (x - j b)) count[i, j]
    y, x = np.arange(h), np.arange(w)
    bi, bj = y // b, x // b
    local = ((y - bi * b)[:, None] * cols[bj][None, :] + (x - bj * b)[None, :]).astype(np.uint64)
    offset = block_start[:-1].reshape(nby, nbx)[bi[:, None], bj[None, :]] \
        + local * count[bi[:, None], bj[None, :]]
    return np.ascontiguousarray(offset, dtype=np.uint64), block_start


def tile_grid(width: int, height: int, tile_w: int, tile_h: int, margin: int):
    """Tiles covering a width x height image, row by row: (interior x0, y0, x1, y1, tile x0, y0,
    x1, y1), ends exclusive, interiors tile_w x tile_h (less at the right and bottom), each tile
    its interior plus ``margin`` pixels on every side, clipped to the image."""
    for y0 in range(0, height, tile_h):
        for x0 in range(0, width, tile_w):
            x1, y1 = min(x0 + tile_w, width), min(y0 + tile_h, height)
            yield (x0, y0, x1, y1, max(x0 - margin, 0), max(y0 - margin, 0),
                   min(x1 + margin, width), min(y1 + margin, height))


def _ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def box_chunk(radius: int) -> int:
    """Samples per work-item of the sliding box sums: at least the window (O(1) per pixel)."""
    return max(32, 2 * radius + 1)


def lr_consistent(index_ref: np.ndarray, valid_ref: np.ndarray, index_src: np.ndarray,
                  valid_src: np.ndarray, hom_ref_to_src: np.ndarray, tolerance_planes: float,
                  rows_per_block: int = 256) -> np.ndarray:
    """Left-right consistency of two plane-index maps (float64 host computation).

    hom_ref_to_src: (n_planes, 3, 3). Each valid reference pixel is mapped to the source with the
    homography linearly interpolated (in image position) between the planes around its
    fractional index; the source's nearest pixel must be valid with an index within
    ``tolerance_planes``. Rows are processed in blocks to bound host memory.
    """
    h_img, w_img = index_ref.shape
    hs, ws = index_src.shape
    n_planes = hom_ref_to_src.shape[0]
    out = np.zeros((h_img, w_img), bool)
    for y0 in range(0, h_img, rows_per_block):
        ys, xs = np.nonzero(valid_ref[y0:y0 + rows_per_block])
        ys = ys + y0
        f = index_ref[ys, xs].astype(np.float64)
        i0 = np.clip(np.floor(f).astype(np.int64), 0, max(n_planes - 2, 0))
        t = f - i0
        pts = np.stack([xs, ys, np.ones(xs.size)], axis=1)[:, :, None].astype(np.float64)

        def project(i):
            q = (hom_ref_to_src[i] @ pts)[:, :, 0]
            return q[:, :2] / q[:, 2:3]

        uv = project(i0)
        if n_planes > 1:
            uv = (1.0 - t)[:, None] * uv + t[:, None] * project(i0 + 1)
        iu, iv = np.floor(uv[:, 0] + 0.5).astype(np.int64), np.floor(uv[:, 1] + 0.5).astype(np.int64)
        inside = (iu >= 0) & (iu < ws) & (iv >= 0) & (iv < hs)
        good = np.zeros(xs.size, bool)
        k = np.nonzero(inside)[0]
        good[k] = valid_src[iv[k], iu[k]] & (np.abs(f[k] - index_src[iv[k], iu[k]]) <= tolerance_planes)
        out[ys, xs] = good
    return out


def sweep_views(device: Device, ref_image, src_images: Sequence, ref_proj, src_projs: Sequence, *,
                heights=None, alt_range: tuple[float, float] | None = None,
                options: SweepOptions | None = None,
                frame=None) -> tuple[HeightMap, np.ndarray]:
    """The winner-take-all height map of a sweep with projections from
    ``satsweep.geometry.camera`` (homographies by ``view_homographies``).

    Either ``heights`` (ENU up, metres) or ``alt_range`` (then spaced by ``plane_heights``) is
    given. With ``frame`` (the ``ENUFrame`` of the projections) ``HeightMap.altitude`` holds the
    heights above the ellipsoid (``ellipsoid_heights``). Returns the height map and the plane
    heights.
    """
    opts = options if options is not None else SweepOptions()
    if len(src_projs) != len(src_images):
        raise InputError(None, f"src_projs: {len(src_projs)} projections for "
                               f"{len(src_images)} source images")
    if heights is None:
        if alt_range is None:
            raise InputError(None, "sweep_views: give heights or alt_range")
        heights = plane_heights(ref_proj, src_projs, alt_range, opts.step_px,
                                ref_shape=np.asarray(ref_image).shape)
    heights = np.asarray(heights, dtype=np.float64)
    hom = view_homographies(ref_proj, src_projs, heights)
    result = PlaneSweep(device, opts).height_map(ref_image, src_images, hom, heights)
    if frame is not None:
        result.altitude = ellipsoid_heights(result.height, ref_proj, frame)
    return result, heights
