"""The dense-matching driver of an area: every reference view swept against its sources over
the pixels that see the AOI, with the MRF refinement the options ask for.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from satsweep.config import PipelineConfig
from satsweep.dense.mrf import MRFOptions
from satsweep.dense.sweep import SweepOptions
from satsweep.dense.tiled import mrf_sweep_options, sweep_refine_tiled
from satsweep.errors import InputError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.pipeline.report import RunReport

# Pixels of context kept around the AOI's footprint in a reference view (``reference_window``):
# SGM's paths enter the AOI with some history. The sweep stage widens it to the cost filter's
# margin where that is larger (``SweepOptions.tile_margin``: 2 r = 10 px for the
# winner-take-all's radius 5), so that every AOI pixel is filtered over its whole window. The
# rest of the crop margin (``crop_margin_px``, which the sources need) lies outside the AOI at
# every height and is not swept.
REFERENCE_CONTEXT_PX = 8

# An area of at least this many reference views whose DSM is their consensus ([dsm] fusion) is
# swept under SGM with ``mrf.sgm_consensus_gf_radius``: the consensus of many height maps rejects
# each one's blunders, which the wider filter of a pair would have smoothed away, and the wider
# filter erodes crowns and roof edges. tools/bench_multidate.py (384 px, seeds 0-5; within 1 m
# % / DFC MAE m, means): 8 references 90.7 / 0.790 -> 91.9 / 0.725, 7 references 85.6 / 1.088
# -> 86.1 / 1.022, but 5 of 10 views (4-5 references) 68.4 -> 66.6% (docs/measurements.md).
# Any area fused by the consensus (4 references or more by default) sweeps with the gradient
# term (``sweep.consensus_grad_weight``, ``area_sweep_options``): seeds 0-5, 10 views of passes
# 92.18 / 0.734 -> 92.66 / 0.699, one view per date 87.26 / 1.493 -> 88.08 / 1.390, 5 views
# (seeds 0-2, 4-5) 82.94 / 1.317 -> 83.92 / 1.300; on 2-3 views (tools/bench_e2e.py, median
# fusion) it moved the medians by -0.003 to +0.012 m.
NARROW_FILTER_MIN_REFERENCES = 6
# In such an area a reference whose pixels are finer than the DSM's cells (at least
# DENSE_CENTRES_PER_CELL pixel centres per cell at its ground sample distance, as WorldView-3's
# 0.3 m on 0.5 m cells) sweeps with ``mrf.sgm_dense_consensus_gf_radius`` (0: no filter):
# each of its cells already pools about three pixels (a high quantile of their points,
# ``DSMOptions.view_raster``), and even a radius of 1 px averages a crown's costs over texture
# that each date redraws (the issue-form seed 11: crown cells within 1 m 30.2 -> 37.3%, their
# MAE 4.29 -> 3.50 m; the ground beside roofs, at the roof's height as often, 8.08 -> 7.23 m
# off on average: docs/measurements.md). Issue-form 0.3 m stacks (19 views, 8 references), DFC
# MAE m, radius 1 -> 0: seeds 11, 13 and held-out 14-18 1.216 1.131 0.961 1.252 1.339 0.459
# 0.892 -> 1.117 1.112 0.834 1.024 1.190 0.457 0.837 (mean 1.036 -> 0.939); seeds 7 and 12
# 0.874 -> 0.797 and 0.709 -> 0.745 (noisier flat areas). At 0.5 m pixels (one per cell) the
# radius of 1 stays: 0 lost there (v10 seeds 0-5, 93.27 -> 92.65% within 1 m).


def reference_window(camera, frame, aoi: AOI, alt_range: AltitudeRange, shape: tuple[int, int],
                     context_px: int = REFERENCE_CONTEXT_PX) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), end exclusive: the pixels of a reference image of ``shape`` that see the
    AOI cube (the AOI box x the altitude range), through ``camera`` (ENU -> pixels, the image's
    own, skew-corrected where the image is), grown by ``context_px`` and clipped to the image.
    The cube's box is the crop's (``views.projected_aoi_box``), grown by one more pixel for the
    edges' curvature between its samples. A point of the DSM lies inside the AOI, so only these
    pixels can contribute to it."""
    from satsweep.errors import AOIError  # noqa: PLC0415
    from satsweep.io.views import projected_aoi_box  # noqa: PLC0415

    P = np.asarray(camera.P, dtype=np.float64)

    def project(*, lon, lat, alt):
        lon, lat, alt = (np.ravel(a) for a in np.broadcast_arrays(lon, lat, alt))
        e, n, u = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
        x = P @ np.stack([e, n, u, np.ones_like(e)])
        x[:, x[2] <= 0] = np.nan  # behind the camera: projected_aoi_box refuses non-finite pixels
        return x[0] / x[2], x[1] / x[2]

    h, w = shape
    try:
        c0, r0, c1, r1 = projected_aoi_box(project, aoi, alt_range)
    except AOIError:
        return 0, 0, w, h  # the cube reaches behind the camera: keep everything
    grow = context_px + 1
    x0 = min(max(int(math.floor(c0)) - grow, 0), w - 1)
    y0 = min(max(int(math.floor(r0)) - grow, 0), h - 1)
    x1 = max(min(int(math.ceil(c1)) + grow + 1, w), x0 + 1)
    y1 = max(min(int(math.ceil(r1)) + grow + 1, h), y0 + 1)
    return x0, y0, x1, y1


def _placed(result, window: tuple[int, int, int, int], shape: tuple[int, int]):
    """The per-pixel maps of a sweep of the reference window ``window``, placed in full-size maps
    of ``shape`` (no height, invalid, zero confidence outside the window)."""
    x0, y0, x1, y1 = window
    height = np.full(shape, np.nan)
    valid = np.zeros(shape, bool)
    confidence = np.zeros(shape, np.float32)
    height[y0:y1, x0:x1] = result.height
    valid[y0:y1, x0:x1] = result.valid
    confidence[y0:y1, x0:x1] = result.confidence
    return height, valid, confidence


# A pixel whose best plane is within this many planes of an end of the range "sits at the end":
# the surface there may lie beyond the range.
RANGE_END_PLANES = 1
# ... and, at the floor, within this many metres of the lowest plane too. A range measured from
# tie points has its floor sparse.altitude_margin_below_m (2 m) under the lowest supported tie
# point, so the ground that the ties hold lies a metre or two over it: one plane up where a
# reference's planes are coarse (a small base-to-height ratio), where counting that plane counts
# the ground. tools/bench_multidate.py's 5 views of one date each, seed 3 (384 px at 0.5 m, range
# 98.3..165 m, truth 99..160 m): planes 1.7-1.9 m apart in three references put 8.4-15% of their
# pixels within a plane of the floor, 4.8-10.7% on the plane over the lowest, where the ground 1-3
# m over the floor lies; the floor was widened to 65 m and shadows matched under the ground, DFC
# MAE 6.758 m; counting the lowest plane alone there (2.0-4.4%), 2.239 m.
# Over the 212 runs of 2 to 20 views of docs/measurements.md's sixty-fifth session it changes 7:
# five stacks of 3-5 views of one date each, DFC MAE 6.758 / 5.863 / 3.568 / 3.932 / 4.545 ->
# 2.239 / 2.257 / 1.424 / 2.601 / 6.200 m (the last, planes 2.8-3.7 m apart, a ground cut 5 m
# under its floor no longer found), and two same-date pairs whose ranges miss the truth either
# way; no run of 10 or 20 views. The top's margin is 15 m: a plane's width there counts no
# surface the ties hold.
RANGE_FLOOR_END_M = 1.0


def range_end_fractions(index: np.ndarray, data: np.ndarray, heights: Sequence[float]
                        ) -> tuple[float, float, np.ndarray]:
    """The fractions of the ``data`` pixels (bool, matched on data) whose best plane ``index``
    sits at the floor (within RANGE_END_PLANES planes and RANGE_FLOOR_END_M metres of the lowest
    of ``heights``, the planes' heights in ascending order) and at the top (within
    RANGE_END_PLANES planes of the highest), and the mask of the pixels at the top."""
    heights = np.asarray(heights, dtype=np.float64)
    # planes over the lowest that still count (ascending heights: those within the metres)
    floor_planes = int(np.sum(heights[1:RANGE_END_PLANES + 1] - heights[0] <= RANGE_FLOOR_END_M))
    index = np.asarray(index)
    at_top = (index >= len(heights) - 1 - RANGE_END_PLANES) & data
    on_data = max(int(data.sum()), 1)
    return (float(np.sum((index <= floor_planes) & data)) / on_data,
            float(np.sum(at_top)) / on_data, at_top)


@dataclasses.dataclass(frozen=True, eq=False)
class ReferenceHeights:
    """One reference view's height map over its whole crop, and how it was made."""

    index: int  # the reference's view index
    height: np.ndarray  # (H, W) ENU up (m) of the surface at each pixel; NaN outside the window
    valid: np.ndarray  # (H, W) bool
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    reference: str  # file names, for the report
    sources: tuple[str, ...]
    source_indices: tuple[int, ...]  # the sources' view indices
    planes: int  # planes swept
    plane_step_m: float | None
    window: tuple[int, int, int, int]  # the swept pixels (x0, y0, x1, y1), ends excluded
    valid_fraction: float  # over the window
    tiles: int  # tiles of the sweep (of the MRF, with one)
    window_planes: int | None  # with coarse-to-fine windows: the most planes of a tile
    window_share: float | None  # ... the share of the tiles' pixels' planes swept
    mrf: dict | None  # the MRF's method, seconds, tiles and valid fraction; None without one
    at_range_ends: tuple[float, float]  # fractions of the window's pixels matched on data whose
    # best plane is within RANGE_END_PLANES of the lowest / the highest plane
    median_radius_px: int | None = None  # the weighted median's window radius; None: no median
    top_region_m2: float = 0.0  # ground area (m2, at the reference's ground sample distance)
    # of the largest connected region of pixels at the top end (top_region_m2)
    top_regions: tuple[tuple[float, float, float], ...] = ()  # its TOP_REGIONS_KEPT largest
    # such regions, largest first: (area m2, east m, north m of the centroid at the top plane)

    def to_report(self) -> dict:
        return {"reference": self.reference, "sources": list(self.sources),
                "planes": self.planes, "plane_step_m": self.plane_step_m,
                "window": [int(v) for v in self.window], "valid_fraction": self.valid_fraction,
                "tiles": self.tiles, "window_planes": self.window_planes,
                "window_share": self.window_share, "mrf": self.mrf,
                "at_range_ends": list(self.at_range_ends),
                "median_radius_px": self.median_radius_px,
                "top_region_m2": self.top_region_m2,
                "top_regions": [[round(v, 2) if math.isfinite(v) else None for v in r]
                                for r in self.top_regions]}


# The largest regions at the range's top that a reference keeps, with where they lie
# (ReferenceHeights.top_regions): the range is widened where several references put one at the
# same place (satsweep.pipeline.area.RANGE_WIDEN_TOP_SPOT_REFERENCES).
TOP_REGIONS_KEPT = 8


def _opened_regions(at_top: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel counts (n,) and centroids (n, 2) (col, row) of the 8-connected regions of
    ``at_top`` that a 3 x 3 opening keeps (pixels at the range's top scattered by noise fall
    away; a roof stays)."""
    import cv2  # noqa: PLC0415

    mask = cv2.morphologyEx(np.asarray(at_top, dtype=np.uint8), cv2.MORPH_OPEN,
                            np.ones((3, 3), np.uint8))
    if not mask.any():
        return np.zeros(0), np.zeros((0, 2))
    _n, _labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    return stats[1:, cv2.CC_STAT_AREA].astype(np.float64), centroids[1:]


def top_regions(at_top: np.ndarray, gsd_m: float, P: np.ndarray, top_u: float,
                offset: tuple[int, int] = (0, 0)) -> tuple[tuple[float, float, float], ...]:
    """The ``TOP_REGIONS_KEPT`` largest 8-connected regions of ``at_top`` pixels that a 3 x 3
    opening keeps (pixels at the range's top scattered by noise fall away; a roof stays; the
    first one's area is ``ReferenceHeights.top_region_m2``), largest first, as (area m2, east
    m, north m): each centroid's ENU point on the
    top plane ``u = top_u`` seen by the reference camera ``P`` (3 x 4, ENU -> pixels of the
    image whose pixel ``offset`` (col, row) is ``at_top``'s first)."""
    from satsweep.products.points import solve_ground_en  # noqa: PLC0415

    pixels, centroids = _opened_regions(at_top)
    order = np.argsort(-pixels, kind="stable")[:TOP_REGIONS_KEPT]
    if not len(order):
        return ()
    e, n = solve_ground_en(P, col=centroids[order, 0] + offset[0],
                           row=centroids[order, 1] + offset[1], u=np.full(len(order), top_u))
    # (a ray parallel to the plane gives NaN: that region is at no place, but keeps its area)
    return tuple((float(pixels[k]) * gsd_m * gsd_m, float(ek), float(nk))
                 for k, ek, nk in zip(order, e, n))


def area_mrf_options(config: PipelineConfig, n_references: int) -> MRFOptions:
    """The MRF options of an area of ``n_references`` reference views: ``mrf.for_consensus()``
    where at least ``NARROW_FILTER_MIN_REFERENCES`` height maps make a consensus, else as given."""
    if (n_references >= NARROW_FILTER_MIN_REFERENCES
            and config.dsm.fusion_for(n_references) == "consensus"):
        return config.mrf.for_consensus()
    return config.mrf


def reference_options(config: PipelineConfig, area_sweep: SweepOptions, area_mrf: MRFOptions,
                      n_references: int, gsd_m: float) -> tuple[SweepOptions, MRFOptions]:
    """The (sweep, MRF) options of one reference of an area of ``n_references`` (``area_sweep``,
    ``area_mrf``: ``area_sweep_options``, ``area_mrf_options``) whose pixels are ``gsd_m``
    metres on the ground. Where those pixels are finer than the DSM's cells (at least
    DENSE_CENTRES_PER_CELL pixel centres per cell): the sweep's ``for_dense_pixels`` where the
    area's maps make a consensus (``SweepOptions.dense_consensus_census_ring_weight``), the
    MRF's ``for_dense_pixels`` where the area also narrows the filter; else the area's. The
    sweep stage and the program forecast both take them from here, so they agree."""
    from satsweep.products.fusion import DENSE_CENTRES_PER_CELL  # noqa: PLC0415

    if not (math.isfinite(gsd_m) and gsd_m > 0.0):
        raise InputError(None, f"a reference's ground sample distance {gsd_m!r} m must be > 0")
    dense = (config.dsm.resolution / gsd_m) ** 2 >= DENSE_CENTRES_PER_CELL
    consensus = config.dsm.fusion_for(n_references) == "consensus"
    narrow = n_references >= NARROW_FILTER_MIN_REFERENCES and consensus
    sweep = area_sweep.for_dense_pixels() if dense and consensus else area_sweep
    mrf = area_mrf.for_dense_pixels() if dense and narrow else area_mrf
    return sweep, mrf


def reference_gsd(camera_P: np.ndarray, u_range: tuple[float, float]) -> float:
    """A reference's ground sample distance (m) at the AOI's centre, mid-range (the sweep
    stage's and the program forecast's, for ``reference_options``)."""
    from satsweep.geometry.camera import ground_sample_distance  # noqa: PLC0415

    return ground_sample_distance(camera_P, (0.0, 0.0, 0.5 * (u_range[0] + u_range[1])))


def area_sweep_options(config: PipelineConfig, n_references: int) -> SweepOptions:
    """The sweep options of an area of ``n_references`` reference views: ``sweep.for_consensus()``
    where their height maps make a consensus ([dsm] fusion), else as given."""
    if config.dsm.fusion_for(n_references) == "consensus":
        return config.sweep.for_consensus()
    return config.sweep


def sweep_references(device, cameras, images, selection, u_range, config: PipelineConfig,
                     rep: RunReport, names, *, aoi: AOI, alt_range: AltitudeRange,
                     valid_masks: Sequence[np.ndarray | None] | None = None
                     ) -> list[ReferenceHeights]:
    """Sweep every reference view against its sources; MRF refinement per the options.

    Each reference is swept over its ``reference_window`` only (the pixels that see the AOI cube,
    with some context), not over the crop's whole margin; the plane spacing is that of the whole
    image. Without an MRF, the sweep's winner-take-all (its own tiling keeps the cost volume on
    the device). With one, ``sweep_refine_tiled``, timed as the "sweep" stage, whose refinement
    time is then moved to the "mrf" stage and also given in the view's entry with its tile count.

    ``valid_masks`` (per view, the pixels that hold data; None: all) make a reference pixel
    invalid where its matching window reads no-data pixels, or where at its plane no source
    window holds data (``_no_data_check``). With ``median_radius_m`` in the area's MRF options
    (``area_mrf_options``: a consensus of many maps), each map then takes the weighted median of
    that radius (``satsweep.dense.median``; timed as the "mrf" stage). A reference of finer
    pixels than the DSM's cells may filter its costs less and weigh its census's 3 x 3 ring
    more (``reference_options``).
    """
    from satsweep.dense.planes import plane_heights, view_homographies
    from satsweep.dense.sweep import PlaneSweep

    out = []
    progress = rep.progress("sweep", len(selection.references))
    with_mrf = config.mrf.method != "none"
    area_mrf = area_mrf_options(config, len(selection.references))
    area_sweep = area_sweep_options(config, len(selection.references))
    for k, r in enumerate(selection.references):
        srcs = list(selection.sources[r])
        ref_proj = cameras.views[r].projection
        src_projs = [cameras.views[s].projection for s in srcs]
        shape = images[r].shape
        gsd = reference_gsd(cameras.views[r].camera.P, u_range)
        sweep, mrf = reference_options(config, area_sweep, area_mrf, len(selection.references),
                                       gsd)
        swept = mrf_sweep_options(sweep, mrf)  # the sweep options as run
        window = reference_window(cameras.views[r].camera, cameras.frame, aoi, alt_range, shape,
                                  context_px=max(REFERENCE_CONTEXT_PX, swept.tile_margin))
        x0, y0, x1, y1 = window
        mrf_info = None
        with rep.stage("sweep"):
            heights = plane_heights(ref_proj, src_projs, u_range, sweep.step_px,
                                    ref_shape=shape)
            shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
            hom = view_homographies(ref_proj, src_projs, heights) @ shift
            ref_image = images[r][y0:y1, x0:x1]  # a view: the sweep makes its own copy
            src_images = [images[s] for s in srcs]
            if with_mrf:
                _check_sgm_labels(heights, config)
                result, seconds = sweep_refine_tiled(
                    device, ref_image, src_images, hom, heights, sweep, mrf,
                    progress=rep.progress("sweep tiles", 1).callback(names[r]))
            else:
                result = PlaneSweep(device, sweep).height_map(ref_image, src_images, hom,
                                                               heights)
        if with_mrf:
            rep.move_time("sweep", "mrf", seconds)
            mrf_info = {"method": mrf.method, "seconds": seconds,
                        "sweep_gf_radius": int(swept.gf_radius),
                        "sweep_grad_weight": float(swept.grad_weight),
                        "sweep_census_ring_weight": float(swept.census_ring_weight),
                        "sweep_census_mask_threshold": float(swept.census_mask_threshold),
                        "tiles": int(result.split.n_tiles),
                        "valid_fraction": float(np.mean(result.valid))}
        progress.update(k + 1, names[r])
        masks = valid_masks if valid_masks is not None else [None] * len(images)
        data = np.ones(np.shape(result.plane_index), dtype=bool)  # pixels matched on data
        if masks[r] is not None or any(masks[s] is not None for s in srcs):
            data = _no_data_check(result, hom, [masks[s] for s in srcs], masks[r], window,
                                  [images[s].shape for s in srcs], swept.census_radii)
        height, valid, confidence = _placed(result, window, shape)
        median_px = None
        if mrf.median_radius_m > 0.0:
            from satsweep.dense.median import (
                MEDIAN_MAX_RADIUS_PX,
                radius_px,
                wanted_radius_px,
                weighted_median,
            )

            with rep.stage("mrf"):
                median_px = radius_px(mrf.median_radius_m, gsd)
                wanted_px = wanted_radius_px(mrf.median_radius_m, gsd)
                if wanted_px > median_px:
                    rep.warn(f"{names[r]}: the height map's weighted median of radius "
                             f"{mrf.median_radius_m:g} m ([mrf] median_radius_m or "
                             f"consensus_median_radius_m) would be "
                             f"{wanted_px} px at {gsd:.2f} m per pixel; "
                             f"the kernel's window reaches {MEDIAN_MAX_RADIUS_PX} px: "
                             f"{median_px * gsd:.2f} m used")
                height[y0:y1, x0:x1] = weighted_median(
                    device, height[y0:y1, x0:x1], valid[y0:y1, x0:x1], ref_image,
                    radius=median_px, sigma=mrf.median_sigma)
        # The ends' shares and regions count the pixels matched on data only: a no-data part
        # of a view (an image's edge) leaves its pixels' planes anywhere, ends included.
        at_floor, at_top_fraction, at_top = range_end_fractions(result.plane_index, data,
                                                                heights)
        ends = (at_floor, at_top_fraction)
        # (the largest region's area is top_region_m2: one opening of the mask serves both)
        regions = top_regions(at_top, gsd, cameras.views[r].camera.P, float(heights[-1]),
                              (x0, y0))
        out.append(ReferenceHeights(
            index=r, height=height, valid=valid, confidence=confidence, reference=names[r],
            sources=tuple(names[s] for s in srcs), source_indices=tuple(int(s) for s in srcs),
            planes=int(len(heights)),
            plane_step_m=float(abs(heights[1] - heights[0])) if len(heights) > 1 else None,
            window=tuple(int(v) for v in window), valid_fraction=float(np.mean(result.valid)),
            tiles=int(result.split.n_tiles), window_planes=result.split.window_planes,
            window_share=result.split.window_share,
            mrf=mrf_info, median_radius_px=median_px,
            at_range_ends=ends,
            top_region_m2=regions[0][0] if regions else 0.0, top_regions=regions))
    return out


def _check_sgm_labels(heights: np.ndarray, config: PipelineConfig) -> None:
    """Refuse, before sweeping, an altitude range with more planes than SGM handles."""
    from satsweep.dense.sgm import SGM_MAX_LABELS

    if config.mrf.method == "sgm" and heights.size > SGM_MAX_LABELS:
        raise InputError(None, f"the altitude range spans {abs(heights[-1] - heights[0]):.0f} m: "
                               f"{heights.size} planes at [sweep] step_px = "
                               f"{config.sweep.step_px:g}, more than SGM's {SGM_MAX_LABELS}; "
                               "give a tighter altitude range (--alt-range, alt_range=) or "
                               "a DEM (--dem, dem=), a larger step_px, or no MRF (--mrf none)")


def _window_data(mask: np.ndarray | None, shape: tuple[int, int],
                 radii: tuple[int, int]) -> np.ndarray:
    """The pixels whose matching window (``radii`` = (rx, ry)) holds data only."""
    import cv2

    if mask is None:
        return np.ones(shape, bool)
    rx, ry = radii
    kernel = np.ones((2 * ry + 1, 2 * rx + 1), np.uint8)
    bad = cv2.dilate((~mask).astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT,
                     borderValue=0)
    return bad == 0


def _no_data_check(result, hom: np.ndarray, src_masks: Sequence[np.ndarray | None],
                   ref_mask: np.ndarray | None, window: tuple[int, int, int, int],
                   src_shapes: Sequence[tuple[int, int]], radii: tuple[int, int]) -> np.ndarray:
    """No-data pixels never make a height: a reference pixel whose census window reads one is
    invalid, and so is one that, at its chosen plane, no source sees at a pixel whose window
    holds data (the kernels saw the fill values there as an image). Returns the pixels that
    pass (bool, the window's shape), valid or not for other reasons."""
    from satsweep.dense.planes import seen_with_data

    x0, y0, x1, y1 = window
    keep = _window_data(ref_mask, ref_mask.shape if ref_mask is not None else (1, 1),
                        radii)[y0:y1, x0:x1] if ref_mask is not None else True
    n = hom.shape[0]
    labels = np.clip(np.rint(np.nan_to_num(result.plane_index)), 0, n - 1).astype(np.int64)
    masks = [_window_data(m, shape, radii) for m, shape in zip(src_masks, src_shapes)]
    keep = keep & seen_with_data(hom, labels, masks)
    result.valid &= keep
    result.height[~result.valid] = np.nan
    return np.broadcast_to(keep, labels.shape).copy()
