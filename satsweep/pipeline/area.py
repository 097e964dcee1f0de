"""Every stage of one area (the AOI, or one tile of it), from its altitude range to its rasters.

``run_area`` returns what the scheduler needs to decide, as types rather than report entries:

- ``AreaResult``: the area's rasters, cameras, its own pointing corrections and the figures of
  each stage (``AreaRecord``, serialised into report.json only at the end of the run);
- ``Split``: its cameras are further from their RPCs than the tiling allows (cut it again);
- ``Wait``: its views match too poorly for their own bundle adjustment (retry it once other tiles
  have given their corrections).
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any, NamedTuple, Sequence

import numpy as np

from satsweep.errors import CameraError, SatsweepError
from satsweep.geometry.altitude import AltitudeRange, enu_height_range
from satsweep.io.metadata import with_computed_sun
from satsweep.io.sources import report_names
from satsweep.pipeline.altitude import (
    AltitudeChoice,
    TiedSources,
    choose_altitude_range,
    tie_and_range,
)
from satsweep.pipeline.forecast import program_forecast
from satsweep.pipeline.prepare import (
    Adjustment,
    correct_pointing,
    crop_views,
    fit_cameras,
    ortho_values,
    skew_correct_masks,
    skew_correct_views,
    vegetation_values,
)
from satsweep.pipeline.rasters import AreaRasters, area_rasters
from satsweep.pipeline.sweeps import ReferenceHeights, sweep_references

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.config import PipelineConfig
    from satsweep.dense.selection import Selection
    from satsweep.geometry.aoi import AOI
    from satsweep.geometry.camera import CameraSet
    from satsweep.io.sources import ImageSource
    from satsweep.opencl.device import Device
    from satsweep.pipeline.report import RunReport
    from satsweep.products.grid import DSMGrid
    from satsweep.sparse.stage import SparseResult


# With two views each is the other's only source: the appearance similarity decides nothing.
MIN_VIEWS_FOR_SIMILARITY = 3


@dataclasses.dataclass(frozen=True)
class RunContext:
    """What every area of a run shares: the device, the options, the user's altitude inputs and
    the report that times the stages and prints the progress."""

    device: "Device"
    config: "PipelineConfig"
    report: "RunReport"
    alt_range: AltitudeRange | None = None  # --alt-range
    dem: str | os.PathLike | None = None  # --dem


@dataclasses.dataclass(frozen=True, eq=False)
class AreaJob:
    """One area to reconstruct: its images, lon/lat box and DSM grid, and how to treat it."""

    sources: Sequence["ImageSource"]  # the images that see it
    aoi: "AOI"
    grid: "DSMGrid"
    split_above_px: float = 0.0  # Split when a camera is further than this from its RPC (0: never)
    borrowed_shifts: dict[str, Sequence[float]] | None = None  # per image path, other tiles'
    # pointing corrections (dcx, dcy) px
    may_wait: bool = False  # Wait (rather than skip) when the views cannot be adjusted

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.sources]


@dataclasses.dataclass(frozen=True, eq=False)
class AreaRecord:
    """The figures of an area's stages, for report.json."""

    altitude: AltitudeChoice
    crops: list[tuple[str, tuple[int, int, int, int]]]  # (image, (x0, y0, width, height))
    acquisitions: list[dict | None]  # per view, its acquisition metadata (None: none given)
    cameras: "CameraSet"
    adjustment: Adjustment
    sparse: dict | None  # the sparse stage's figures (pair graph, corrections, dropped views)
    selection: "Selection"
    sweeps: list[ReferenceHeights]
    rasters: AreaRasters
    vegetation_shares: list[float | None] = dataclasses.field(default_factory=list)  # per
    # view, the share of its crop's pixels holding data that show vegetation (None: no colour,
    # or not read: [dsm] green_crowns and [views] leaf_from_colour both off)

    @property
    def names(self) -> list[str]:
        """The file names of the area's images."""
        return [os.path.basename(path) for path, _ in self.crops]

    def to_report(self) -> dict[str, Any]:
        names = [name for name, _ in self.crops]
        return {
            "altitude_range": self.altitude.to_report(),
            "views": [{"image": path, "crop": list(box), "acquisition": acquisition,
                       "vegetation_share": share}
                      for (path, box), acquisition, share
                      in zip(self.crops, self.acquisitions,
                             self.vegetation_shares or [None] * len(self.crops))],
            "cameras": {"approx_error_px": {n: v.camera.error.to_dict()
                                            for n, v in zip(report_names(names),
                                                            self.cameras.views)},
                        "warnings": list(self.cameras.warnings)},
            "sparse": self.sparse,
            "ba": self.adjustment.to_report(),
            "view_selection": self.selection.to_dict(report_names(names)),
            "sweep": [s.to_report() for s in self.sweeps],
            "dsm": self.rasters.to_report(),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class AreaResult:
    """A reconstructed area: its rasters on its grid, its cameras, its own pointing corrections
    (per view (dcx, dcy) px; None without its own adjustment) and its figures."""

    rasters: AreaRasters
    cameras: "CameraSet"
    shifts: dict[str, list[float]] | None  # per image path, (dcx, dcy) px
    record: AreaRecord

    def without_arrays(self) -> "AreaResult":
        """A copy without the rasters, height maps and clouds (kept on disk or written by
        then): what a run holds of a finished area."""
        rasters = dataclasses.replace(self.rasters, dsm=None, confidence=None, ortho=None,
                                      count=None, clouds=[])
        sweeps = [dataclasses.replace(s, height=None, valid=None, confidence=None)
                  for s in self.record.sweeps]
        record = dataclasses.replace(self.record, sweeps=sweeps, rasters=rasters)
        return dataclasses.replace(self, rasters=rasters, record=record)


@dataclasses.dataclass(frozen=True)
class Split:
    """The area's cameras are up to ``max_error_px`` from their RPCs: cut it again."""

    max_error_px: float


@dataclasses.dataclass(frozen=True)
class Wait:
    """The area's views cannot be adjusted on their own: retry it with other tiles'
    corrections."""

    reason: str


def run_area(job: AreaJob, ctx: RunContext) -> AreaResult | Split | Wait:
    """Every stage from the altitude range to the DSM rasters, for one area on its grid."""
    config, rep = ctx.config, ctx.report
    r = config.reconstruct
    tied = tie_and_range(job.sources, job.aoi, alt_range=ctx.alt_range, dem=ctx.dem,
                         config=config, adjust=r.adjust != "off", report=rep)
    sparse, altitude = tied.sparse, tied.altitude
    if altitude.source == "tie points":  # (a doubt about it: warned by tie_and_range)
        rep.log(f"altitude range {altitude.range.min:.1f}..{altitude.range.max:.1f} m from "
                f"{sparse.altitude['tie_points']} adjusted tie points (give --alt-range or --dem, "
                "alt_range= or dem= in the API, to set it)")
    widened: list[dict[str, Any]] = []
    while True:
        dense = _dense_stages(job, ctx, tied, altitude.range)
        if isinstance(dense, (Split, Wait)):
            return dense
        wider = None
        if altitude.source == "tie points" and len(widened) < RANGE_WIDENINGS:
            wider = widened_range(altitude.range, dense.sweeps)
        if wider is None:
            break
        rng, end, side = wider.range, wider.end, ("floor", "top")[wider.end]
        widened.append({"end": side, "from_m": (altitude.range.min, altitude.range.max)[end],
                        "to_m": (rng.min, rng.max)[end],
                        "references_at_end": wider.hits, "references": len(dense.sweeps),
                        "rule": wider.rule(), "region_m2": wider.region_m2})
        rep.warn(f"altitude range {altitude.range.min:.0f}..{altitude.range.max:.0f} m (tie "
                 f"points): {wider.hits} of {len(dense.sweeps)} reference views matched "
                 f"{wider.describe()} at its {side}; swept again over "
                 f"{rng.min:.0f}..{rng.max:.0f} m")
        altitude = dataclasses.replace(altitude, range=rng,
                                       details={**altitude.details, "widened": list(widened)})
    _check_range_ends(dense.sweeps, altitude, job, ctx)
    rasters = _rasters(dense, job, ctx)
    refined = _surface_refined(job, ctx, tied, dense, rasters)
    if refined is not None:  # the dense stages again, with the refined corrections
        tied, sparse = refined, refined.sparse
        dense = _dense_stages(job, ctx, tied, altitude.range)
        if isinstance(dense, (Split, Wait)):
            return dense
        rasters = _rasters(dense, job, ctx)
    views = dense.views
    record = AreaRecord(altitude=altitude,
                        crops=[(v.path, (int(v.x0), int(v.y0), int(v.width), int(v.height)))
                               for v in views],
                        acquisitions=[None if a is None else a.to_dict()
                                      for a in dense.acquisitions],
                        cameras=dense.cameras, adjustment=dense.adjustment,
                        sparse=None if sparse is None else sparse.to_dict(),
                        selection=dense.selection, sweeps=dense.sweeps, rasters=rasters,
                        vegetation_shares=[vegetation_share(v) for v in views])
    own = dense.adjustment.own_shifts
    return AreaResult(rasters=rasters, cameras=dense.cameras,
                      shifts=None if own is None else {v.path: s for v, s in zip(views, own)},
                      record=record)


def _rasters(dense: "_Dense", job: AreaJob, ctx: RunContext) -> AreaRasters:
    """The "dsm" stage on an area's sweeps."""
    from satsweep.dense.similarity import acquisition_passes

    return area_rasters(dense.sweeps, dense.cameras, dense.images, job.grid, ctx.config,
                        ctx.report, ortho_images=dense.ortho_images,
                        leaf_season=dense.selection.leaf_season,
                        passes=acquisition_passes(dense.acquisitions),
                        vegetation_images=dense.vegetation_images)


def surface_ties_reason(sparse: "SparseResult | None", n_views: int,
                        config: "PipelineConfig") -> str | None:
    """Why the corrections are refined on a first DSM's surface (``[bundle] surface_ties``,
    :mod:`satsweep.sparse.surface_ties`), None when they are not: the sparse stage's
    corrections, of ``n_views`` views (MIN_VIEWS or more), with ``on``, or with ``auto`` where
    one of them is uncertain by more than ``surface_ties_sigma_px``."""
    from satsweep.sparse.surface_ties import MIN_VIEWS

    b = config.bundle
    if (sparse is None or b.surface_ties == "off" or config.reconstruct.adjust == "off"
            or n_views < MIN_VIEWS):
        return None
    if b.surface_ties == "on":
        return "[bundle] surface_ties = on"
    sigma = float(np.max(sparse.correction_sigma_px[list(sparse.kept)]))
    if sigma > b.surface_ties_sigma_px:
        return (f"the tie points left a correction uncertain by {sigma:.3f} px (more than "
                f"[bundle] surface_ties_sigma_px = {b.surface_ties_sigma_px:g})")
    return None


def _surface_refined(job: AreaJob, ctx: RunContext, tied: TiedSources, dense: "_Dense",
                     rasters: AreaRasters) -> TiedSources | None:
    """``tied`` with the sparse stage's corrections refined on the surface of ``rasters``' DSM
    (:func:`surface_ties_reason`), None where they are not refined. The shifts found in the
    skew-corrected pixels of ``dense`` are taken back to the crops' (the warp's linear part)
    and weighed against the sparse stage's corrections (``surface_ties.blended_shifts``); with
    fixed views, the motion no image sees is chosen to keep their corrections at zero. A
    view the surface does not tie (a CameraError of the adjustment) leaves the sparse stage's
    corrections as they are, with a warning."""
    from satsweep.sparse.bundle import in_gauge
    from satsweep.sparse.stage import SPARSE_THREADS_MAX
    from satsweep.sparse.surface_ties import blended_shifts, surface_points, surface_ties
    from satsweep.sparse.triangulation import projection_stack

    config, rep, sparse = ctx.config, ctx.report, tied.sparse
    views = list(dense.cameras.views)
    reason = surface_ties_reason(sparse, len(views), config)
    if reason is None:
        return None
    names = [v.name for v in dense.views]
    with rep.stage("surface ties"):
        points = surface_points(rasters.dsm, *job.grid.cell_centers(), job.grid.epsg,
                                dense.cameras.frame, config.bundle.surface_ties_points)
        try:
            ties = surface_ties([v.camera for v in views], dense.images, points,
                                sparse_options=config.sparse, bundle_options=config.bundle,
                                names=names, valid=dense.masks, threads=SPARSE_THREADS_MAX)
        except CameraError as exc:
            rep.warn(f"pointing corrections not refined on the DSM's surface: {exc}")
            return None
    warps = [np.eye(2) if v.warp is None else np.asarray(v.warp, np.float64)[:2, :2]
             for v in views]
    found = np.array([np.linalg.solve(w, s) for w, s in zip(warps, ties.shifts)])
    paths = [v.path for v in views]
    index = sparse.indices_of(paths)  # (every view here was kept by the sparse stage)
    shifts, weight = blended_shifts(found, np.hypot(ties.sigma, ties.spread),
                                    sparse.correction_sigma_px[index])
    held = [k for k, i in enumerate(index) if i in sparse.fixed_views]
    if held:
        before = np.array(sparse.corrections_for(paths))
        crop_P = projection_stack([v.camera for v in views])
        for k, v in enumerate(views):
            if v.warp is not None:
                crop_P[k] = np.linalg.solve(np.asarray(v.warp, np.float64), crop_P[k])
        total = in_gauge(crop_P, before + shifts, points.mean(axis=0), held)
        total[held] = np.where(np.abs(total[held]) < 1e-9, 0.0, total[held])  # rounding
        shifts = total - before
    keys = report_names(names)
    figures = {
        "reason": reason,
        "points": ties.points,
        "registered_points": ties.registered,
        "observations": dict(zip(keys, ties.observations)),
        # added to the sparse stage's corrections: the shifts found on the surface, weighed
        # against those corrections by their uncertainties (blended_shifts)
        "shift_px": {k: [float(x) for x in s] for k, s in zip(keys, shifts)},
        "surface_shift_px": {k: [float(x) for x in s] for k, s in zip(keys, found)},
        "surface_weight": {k: float(x) for k, x in zip(keys, weight)},
        "sigma_px": {k: float(x) for k, x in zip(keys, ties.sigma)},
        # half the largest difference between the shifts of two halves of the surface
        # (surface_ties.half_spread), added to sigma_px in quadrature for the weights
        "spread_px": {k: float(x) for k, x in zip(keys, ties.spread)},
        "reprojection_median_px": ties.reprojection_median_px,
        "seconds": ties.seconds,
    }
    rep.log(f"pointing refined on {ties.registered} points of the DSM's surface ({reason}): "
            f"largest change {float(np.abs(shifts).max(initial=0.0)):.3f} px; the dense stages "
            "run again")
    return dataclasses.replace(tied, sparse=sparse.with_surface_shifts(paths, shifts, figures))


def vegetation_share(view) -> float | None:
    """The share of a view's crop pixels holding data whose vegetation index reaches the
    crowns' rule's threshold (``images.VEGETATION_INDEX_MIN``), rounded to 1e-4; None for a
    view without a vegetation index."""
    from satsweep.io.images import VEGETATION_INDEX_MIN

    if view.vegetation is None:
        return None
    valid = np.ones(view.vegetation.shape, bool) if view.valid is None else view.valid
    if not valid.any():
        return None
    return round(float(np.mean(view.vegetation[valid] >= VEGETATION_INDEX_MIN)), 4)


@dataclasses.dataclass(frozen=True, eq=False)
class _Dense:
    """What the stages from the crops to the sweeps made of an area at one altitude range."""

    views: list[Any]
    images: list[np.ndarray]
    ortho_images: list[np.ndarray] | None
    vegetation_images: list[np.ndarray] | None  # per view, its vegetation index (None: not
    # every image has colour, or [dsm] green_crowns is off)
    cameras: "CameraSet"
    adjustment: Adjustment
    acquisitions: list[Any]
    selection: "Selection"
    sweeps: list[ReferenceHeights]
    masks: list[np.ndarray | None]  # per view, its pixels holding data (None: all), in the
    # pixels of ``images``


def _dense_stages(job: AreaJob, ctx: RunContext, tied: TiedSources,
                  alt: AltitudeRange) -> _Dense | Split | Wait:
    """Crops, cameras, pointing correction, view selection and sweeps over ``alt``."""
    config, rep = ctx.config, ctx.report
    sources = tied.sources
    # (an image that sees part of the AOI: the run warns once, from its areas' shares)
    views, images = crop_views(sources, job.aoi, alt, config, report=rep,
                               extra_margin_px=tied.correction_margin_px, warn_partial=False)
    kept = {v.path for v in views}  # the views holding data over the area
    sources = [src for src in sources if src.path in kept]
    names = [v.name for v in views]
    cameras = fit_cameras(views, job.aoi, alt, config, report=rep)
    worst = max(v.camera.error.max_px for v in cameras.views)
    if job.split_above_px > 0.0 and worst > job.split_above_px:
        return Split(max_error_px=float(worst))

    from satsweep.dense.similarity import known_similarity, leaf_season

    # The sun's angles where the metadata give a date-time without them (reported as computed).
    lon, lat = job.aoi.center
    acquisitions = [with_computed_sun(s.acquisition, lon=lon, lat=lat) for s in sources]
    seasons = [leaf_season(a, lat) for a in acquisitions]
    seasons_from = "metadata" if any(v is not None for v in seasons) else None
    if seasons_from is None and config.views.leaf_from_colour:
        from satsweep.dense.similarity import leaf_state_from_vegetation

        estimated = leaf_state_from_vegetation([v.vegetation for v in views],
                                               [v.valid for v in views])
        if estimated is not None:
            seasons, seasons_from = estimated, "colour"
    with_similarity = len(cameras.views) >= MIN_VIEWS_FOR_SIMILARITY
    known = known_source = None
    if with_similarity:
        matches = (None if tied.sparse is None
                   else tied.sparse.match_counts([v.path for v in views]))
        known, known_source = known_similarity(acquisitions, matches=matches)
    # The kernels the sweep stage will need, built in the background meanwhile (the selection
    # forecast from the similarity known so far: the metadata's, the tie points').
    ctx.device.prebuild(program_forecast(ctx.device, cameras,
                                         enu_height_range(cameras.frame, job.aoi, alt), config,
                                         similarity=known, similarity_source=known_source,
                                         leaf_season=seasons))
    borrowed = (None if job.borrowed_shifts is None
                else [job.borrowed_shifts[v.path] for v in views])
    cameras, adjustment = correct_pointing(cameras, views, tied.sparse, tied.untied, config,
                                           borrowed_shifts=borrowed, may_wait=job.may_wait,
                                           report=rep)
    if adjustment.postponed is not None:
        return Wait(adjustment.postponed)
    ortho_images = ortho_values(views) if config.reconstruct.write_ortho else None
    vegetation = vegetation_values(views) if config.dsm.green_crowns else None
    masks = [v.valid for v in views]
    if config.reconstruct.skew_correct:
        masks = skew_correct_masks(cameras, masks)
        cameras, images, ortho_images, vegetation = skew_correct_views(
            cameras, images, ortho_images, vegetation_images=vegetation, report=rep)

    from satsweep.dense.selection import select_views

    u_range = enu_height_range(cameras.frame, job.aoi, alt)
    mid = 0.5 * (u_range[0] + u_range[1])
    with rep.stage("select"):
        similarity = similarity_source = None
        if with_similarity:  # the forecast's similarity, the images measuring what it left
            from satsweep.dense.similarity import with_measured_similarity

            similarity, similarity_source = with_measured_similarity(
                known, known_source, images, cameras, job.aoi, mid)
        selection = select_views([v.camera for v in cameras.views], mid_height=mid,
                                 options=config.views, names=names, similarity=similarity,
                                 similarity_source=similarity_source, leaf_season=seasons,
                                 leaf_season_from=seasons_from)
        for w in selection.warnings:
            rep.warn(w)
    sweeps = sweep_references(ctx.device, cameras, images, selection, u_range, config, rep,
                              names, aoi=job.aoi, alt_range=alt, valid_masks=masks)
    return _Dense(views=list(views), images=list(images), ortho_images=ortho_images,
                  vegetation_images=vegetation,
                  cameras=cameras, adjustment=adjustment, acquisitions=acquisitions,
                  selection=selection, sweeps=list(sweeps), masks=list(masks))


# More pixels than this fraction of a reference's window at an end of the altitude range means
# the surface extends beyond it. Measured with ranges that hold the surface: at most 0.26% on
# tools/bench_e2e.py's four 512 px towns, 1.1% on the tests' 192 px town, 0.03% on the Pleiades
# pair (2260..2390 m); with ranges that cut its ground off (2290..2420, 2200..2330 m): 5.2-7.3%.
RANGE_END_WARN_FRACTION = 0.03
# With this many references or more, one alone over RANGE_END_WARN_FRACTION at an end is named as
# such: a cloud in one view of ten puts 9.2% of its pixels at the top, which no other reference
# sees (forty-second session, docs/measurements.md).
RANGE_END_LONE_MIN_REFERENCES = 3
# A range measured from tie points is widened at an end, and the area swept again, when at least
# RANGE_WIDEN_SHARE of the reference views (and two of them, or the one there is) each match
# more than RANGE_WIDEN_FRACTION of their pixels there: a surface that the tie points missed (a
# tower whose roof no tie point holds). A few references are more often views of other dates
# matching their shadows at the floor. The top by RANGE_WIDEN_M, the floor by
# RANGE_WIDEN_FLOOR_M, at most RANGE_WIDENINGS times in all.
# Measured (tools/bench_multidate.py, 384 px, and the 0.3 m issue-form stacks of
# docs/measurements.md): ranges that hold the truth put at most 0.6% of any reference's pixels
# at an end but one reference of 8 (3.4%, v20 seed 5), and on one view per date seed 9 four of 8
# (range 95..165 m, truth 99..153 m: widened to 60 m by the half span of then, the shadows went
# 10-40 m under the ground, DFC MAE 3.27 m against 1.21 with 95..165); v20 seed 4 at 10 views
# (range 95..150 m, truth 99..152 m) put 3.3-4.1% at the top in all 8 references. The floor's
# count leaves out a ground a coarse plane over the floor (pipeline.sweeps.RANGE_FLOOR_END_M;
# sixty-fifth session).
RANGE_WIDEN_SHARE = 0.75
RANGE_WIDEN_FRACTION = 0.02
RANGE_WIDEN_M = 20.0
RANGE_WIDENINGS = 2
# (The top moved by half the range's span where that was more, before the sixty-fifth session:
# a tower's roof that the tie points missed lay 17-19 m over the top on the three stacks these
# rules' comments name (v10 seed 0, 8-bit RGB at 33.45 S seed 41, 5 views of seed 5), which one
# step of 20 m reaches, while half a 65 m span gives the blunders at the top 13 m more to match
# in. 328 runs of 2 to 20 views before and after: 71 changed, 43 better, 28 worse, mean DFC MAE
# 3.065 -> 3.025 m over 309, every family's mean lower or the same, every range that held its
# truth still does; at 10 views three changed, 0.916 / 0.673 / 0.448 -> 0.914 / 0.719 / 0.420
# m; docs/measurements.md.)
# The floor moves down by this much. What it cuts off is the ground, which tie points hold almost
# everywhere: a floor from them misses it by metres (tools/bench_multidate.py, 5 views of one date
# each: seed 17's 3 views 0.3 m, seed 11's 5 m; a test's town cut 8 m over its ground), not by
# the tens of metres a tower's roof may stand over the top, while every metre under the ground
# lets shadows of other dates match there. It moved as the top does before (33 m for seed 17's
# range of 65 m); sixty-fifth session, 328 runs of 2 to 20 views before and after: 8 change,
# seed 17's 3 views (range 99.7..165 m, truth 99.4..124.6) DFC MAE 9.588 -> 5.457 m, 8-bit RGB
# at 33.45 S seed 35's 3 views 19.871 -> 5.421 m, the issue's form at 384 px seeds 54 and 60 (3
# views) 2.581 / 2.498 -> 1.773 / 2.292 m, one view per date seed 8's 5 of 10 views 2.805 ->
# 2.127 m, three same-date pairs 0.795 / 3.557 / 16.464 -> 0.751 / 2.932 / 16.498 m; every range
# that held its truth still does (docs/measurements.md).
RANGE_WIDEN_FLOOR_M = 10.0
# The top is also widened on less: RANGE_WIDEN_SHARE of the references each matching more than
# RANGE_WIDEN_TOP_FRACTION of their pixels there. Nothing puts pixels above the surface as cast
# shadows put them under the ground, and a small stack's tie points miss a tower's roof: 5 views
# of tools/bench_multidate.py's seed 5 (range 95..142 m, truth 99..159 m) put 0.8-2.5% of every
# reference's pixels at the top (two over RANGE_WIDEN_FRACTION: not widened, DFC MAE 1.80 m;
# widened to 165 m, 0.99 m). Ranges that hold the truth put at most 0.82% of a reference's
# pixels there, more than 0.75% in at most one reference of 8 (v10 seeds 0-9, the issue-form
# stacks 7, 11-13, 15, 16), but 3 views of seed 3 (95..133 m, truth 99..119) 0.2, 0.6 and 1.1%:
# half the references over 0.5% would widen that one wrongly (DFC MAE 2.15 -> 3.02 m), and 3
# views of seed 4 (95..142, truth 99..152: 0.2, 0.7, 1.8%) look the same, so they stay as they
# are. Not with fewer than RANGE_WIDEN_TOP_MIN_REFERENCES references: 2 references of 5 views of
# a 20-view scene (93..154 m, truth 99..152, the roof just under the top) both over 0.75%,
# widened to 184 m: DFC MAE 3.72 -> 5.20 m (docs/measurements.md, twenty-seventh session).
RANGE_WIDEN_TOP_FRACTION = 0.0075
RANGE_WIDEN_TOP_MIN_REFERENCES = 3
# The top is also widened where RANGE_WIDEN_SHARE of the references each match a connected
# region of at least RANGE_WIDEN_TOP_REGION_M2 there (ReferenceHeights.top_region_m2: a roof,
# which a 3 x 3 opening keeps, where the fractions above count scattered pixels too). A tower
# of 96 m2 at 158 m that the tie points missed (tools/bench_multidate.py seed 41, 10 views of
# 8-bit RGB at 33.45 S, range 95..139 m) gave the eight references regions of 38, 32, 18, 15,
# 13.5, 13, 9.7 and 3.5 m2 and fractions of 0.16-0.83%: widened to 161 m, DFC MAE 1.661 ->
# 0.447 m. Ranges that hold the truth (v10 seeds 0-7, d10 seeds 0-5, 8-bit RGB seeds 31-46 at
# 33.45 S, the issue-form stacks at 0.3 m) leave the sixth largest of eight regions at 5.2 m2
# at most (its largest 31.5 m2: blunders at the top in one or two references).
# Not with fewer than RANGE_WIDEN_TOP_REGION_MIN_REFERENCES references: 3 views of v10 seed 2
# (range 95..142 m, truth 99..123) put such a region in each of their 3 references, widened to
# 201 m: DFC MAE 2.54 -> 4.58 m.
RANGE_WIDEN_TOP_REGION_M2 = 10.0
RANGE_WIDEN_TOP_REGION_MIN_REFERENCES = 6
# The top is also widened where RANGE_WIDEN_TOP_SPOT_REFERENCES references put such a region at
# one place: centroids within RANGE_WIDEN_TOP_SPOT_M of one of them on the top plane
# (ReferenceHeights.top_regions), with RANGE_WIDEN_TOP_REGION_MIN_REFERENCES references or more.
# A tower's roof lies at the same place in every reference that sees it; blunders at the top
# (shadows, clouds, textureless roofs) lie where each reference's own matching fails. A tower of
# tools/bench_multidate.py's seed 0 (10 views at 0.5 m, truth 100..157 m) rests on one tie
# point of two views; a cloud over it in one of them (a held-out test, forty-second session)
# left the range at 95..139 m, DFC MAE 0.468 -> 1.488 m: four of eight references put a region
# of 10-50 m2 within 4 m of one place, the other rules' counts were 4 of 8 and fewer. Ranges
# that hold the truth (v10 seeds 0-5, 8-bit RGB seeds 31-46 at 33.45 S, ...) put one reference
# at most at any place; held-out seed 41 (range 95..139 m, truth 99..158) five.
RANGE_WIDEN_TOP_SPOT_REFERENCES = 3
RANGE_WIDEN_TOP_SPOT_M = 5.0
# The top is also widened where RANGE_WIDEN_TOP_ROOF_REFERENCES references put a region of
# RANGE_WIDEN_TOP_ROOF_M2 or more (a roof, not a blunder's speck) at one place (as above), with
# RANGE_WIDEN_TOP_MIN_REFERENCES references or more: a small stack's tower that its few tie
# points missed, seen from two references. 144 reconstructions of 3 and 5 views
# (tools/bench_multidate.py's scenes: one date at 384 and 512 px, v5, v10 seeds 0-9, one view
# per date, 20 views, 8-bit RGB at 33.45 S; forty-fourth session, docs/measurements.md): of the
# 103 with three references or more, 10 ranges miss the truth's top, 4 of them with two such
# regions at one place (169-312 m2 each; widened, all 4 hold it, within 1 m +0.3 to +3.0
# points, DFC MAE 1.86 / 2.11 / 5.75 / 2.39 -> 1.45 / 2.47 / 6.21 / 1.66 m), and no range that
# holds the truth has two. Two references alone had two (270 m2 each) 6 m above a truth their
# range held: not with fewer than three.
RANGE_WIDEN_TOP_ROOF_M2 = 50.0
RANGE_WIDEN_TOP_ROOF_REFERENCES = 2


class Widening(NamedTuple):
    """A widened altitude range (``widened_range``): the range, its end widened (0: floor, 1:
    top), how many references hit that end, the fraction of their pixels they passed (None: a
    region rule), the least area of their regions there (m2; None: a fraction rule) and the
    radius of the one place their regions share (m; None unless the rule asks for one)."""

    range: AltitudeRange
    end: int
    hits: int
    fraction: float | None
    region_m2: float | None
    spot_m: float | None

    def rule(self) -> str:
        """The rule's name in the report (``altitude_range.widened``)."""
        return ("fraction" if self.fraction is not None else
                "region" if self.spot_m is None else "region at one place")

    def describe(self) -> str:
        """What the references matched at the end, for the warning."""
        if self.fraction is not None:
            return f"more than {100 * self.fraction:g}% of their pixels"
        return (f"a region of {self.region_m2:g} m2 or more"
                + ("" if self.spot_m is None else f" within {self.spot_m:g} m of one place"))


def widened_range(rng: AltitudeRange, sweeps: Sequence[ReferenceHeights]) -> Widening | None:
    """The range widened at the end that the references hit, or None when no end is hit so:
    RANGE_WIDEN_SHARE of them, and two or the one there is, over RANGE_WIDEN_FRACTION; the top
    also, with RANGE_WIDEN_TOP_MIN_REFERENCES references or more, on the first of these that
    holds: as many over RANGE_WIDEN_TOP_FRACTION; with RANGE_WIDEN_TOP_REGION_MIN_REFERENCES or
    more, as many with a region of RANGE_WIDEN_TOP_REGION_M2 there, or
    RANGE_WIDEN_TOP_SPOT_REFERENCES of them with such a region at one place; or
    RANGE_WIDEN_TOP_ROOF_REFERENCES of them with a region of RANGE_WIDEN_TOP_ROOF_M2 at one
    place."""
    if not sweeps:
        return None
    need = max(min(2, len(sweeps)), int(np.ceil(RANGE_WIDEN_SHARE * len(sweeps))))

    def widened(end: int, hits: int, fraction=None, region_m2=None, spot_m=None) -> Widening:
        wider = (AltitudeRange(rng.min - RANGE_WIDEN_FLOOR_M, rng.max) if end == 0
                 else AltitudeRange(rng.min, rng.max + RANGE_WIDEN_M))
        return Widening(wider, end, int(hits), fraction, region_m2, spot_m)

    hits = [sum(s.at_range_ends[end] > RANGE_WIDEN_FRACTION for s in sweeps) for end in (0, 1)]
    end = int(np.argmax(hits))
    if hits[end] >= need:
        return widened(end, hits[end], fraction=RANGE_WIDEN_FRACTION)
    if len(sweeps) < RANGE_WIDEN_TOP_MIN_REFERENCES:
        return None
    top = sum(s.at_range_ends[1] > RANGE_WIDEN_TOP_FRACTION for s in sweeps)
    if top >= need:
        return widened(1, top, fraction=RANGE_WIDEN_TOP_FRACTION)
    if len(sweeps) >= RANGE_WIDEN_TOP_REGION_MIN_REFERENCES:
        on_roof = sum(s.top_region_m2 >= RANGE_WIDEN_TOP_REGION_M2 for s in sweeps)
        if on_roof >= need:
            return widened(1, on_roof, region_m2=RANGE_WIDEN_TOP_REGION_M2)
        at_one = top_spot_references(sweeps, RANGE_WIDEN_TOP_REGION_M2)
        if at_one >= RANGE_WIDEN_TOP_SPOT_REFERENCES:
            return widened(1, at_one, region_m2=RANGE_WIDEN_TOP_REGION_M2,
                           spot_m=RANGE_WIDEN_TOP_SPOT_M)
    at_one = top_spot_references(sweeps, RANGE_WIDEN_TOP_ROOF_M2)
    if at_one >= RANGE_WIDEN_TOP_ROOF_REFERENCES:
        return widened(1, at_one, region_m2=RANGE_WIDEN_TOP_ROOF_M2, spot_m=RANGE_WIDEN_TOP_SPOT_M)
    return None


def top_spot_references(sweeps: Sequence[ReferenceHeights], min_area_m2: float) -> int:
    """The most references with a region of ``min_area_m2`` or more at the top (``top_regions``)
    whose centroid lies within RANGE_WIDEN_TOP_SPOT_M of one such centroid."""
    spots = np.array([(k, e, n) for k, s in enumerate(sweeps)
                      for area_m2, e, n in s.top_regions
                      if area_m2 >= min_area_m2], dtype=np.float64).reshape(-1, 3)
    best = 0
    for _, e, n in spots:
        near = np.hypot(spots[:, 1] - e, spots[:, 2] - n) <= RANGE_WIDEN_TOP_SPOT_M
        best = max(best, len(np.unique(spots[near, 0])))
    return best


def _check_range_ends(sweeps: Sequence[ReferenceHeights], altitude: AltitudeChoice, job: AreaJob,
                      ctx: RunContext) -> None:
    """A doubtful warning when many pixels' best plane sits at an end of the altitude range
    (:func:`range_end_message`), with the range that tie points measure between the views when
    the range was given."""
    message = range_end_message(sweeps, altitude.range, altitude.source)
    if message is None:
        return
    measured = ""
    if altitude.source != "tie points":
        try:
            ties = choose_altitude_range(job.sources, job.aoi, alt_range=None, dem=None,
                                         config=ctx.config)  # at the RPCs' range, not the user's
            measured = (f"; tie points between the views put it within "
                        f"{ties.range.min:.0f}..{ties.range.max:.0f} m")
        except SatsweepError as exc:
            measured = f"; tie points could not measure it ({exc})"
    ctx.report.warn(message + measured, doubtful=True)


def range_end_message(sweeps: Sequence[ReferenceHeights], rng: AltitudeRange, source: str
                      ) -> str | None:
    """The warning of :func:`_check_range_ends` (None: no reference puts more than
    RANGE_END_WARN_FRACTION of its pixels at an end): the reference that puts most there, and,
    where it is the only one of RANGE_END_LONE_MIN_REFERENCES or more, that a cloud or shadows
    in that view would do so too."""
    worst = max(((s.at_range_ends[k], k, s.reference) for s in sweeps for k in (0, 1)),
                default=(0.0, 0, ""))
    fraction, end, reference = worst
    if fraction <= RANGE_END_WARN_FRACTION:
        return None
    side, bound = (("lower", rng.min), ("upper", rng.max))[end]
    where = ("below", "above")[end]
    message = (f"{100 * fraction:.1f}% of {reference}'s pixels matched best at the {side} end "
               f"({bound:.0f} m) of the altitude range {rng.min:.0f}..{rng.max:.0f} m ({source}): ")
    over = sum(s.at_range_ends[end] > RANGE_END_WARN_FRACTION for s in sweeps)
    if over == 1 and len(sweeps) >= RANGE_END_LONE_MIN_REFERENCES:
        what = ("a cloud over it or" if end == 1 else "shadows of its date or") + " a blunder"
        return message + (f"the surface may extend {where} it, but only this one of the "
                          f"{len(sweeps)} reference views says so ({what} of that view would)")
    return message + f"the surface probably extends {where} it"


def sources_seeing(sources: Sequence["ImageSource"], aoi: "AOI",
                   prior: AltitudeRange) -> list["ImageSource"]:
    """The sources whose footprint of the AOI cube (at the ``prior`` range) meets the image."""
    return [s for s in sources if s.sees(aoi, prior)]


def median_shifts(shifts: Sequence[Sequence[Sequence[float]]]) -> list[list[float]]:
    """Per view, the median (dcx, dcy) of several tiles' corrections."""
    return [np.median(np.array(s), axis=0).tolist() for s in shifts]
