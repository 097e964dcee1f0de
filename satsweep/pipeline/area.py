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
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from satsweep.errors import SatsweepError
from satsweep.geometry.altitude import AltitudeRange, enu_height_range
from satsweep.io.metadata import with_computed_sun
from satsweep.pipeline.altitude import AltitudeChoice, choose_altitude_range, tie_and_range
from satsweep.pipeline.forecast import program_forecast
from satsweep.pipeline.prepare import (
    Adjustment,
    correct_pointing,
    crop_views,
    fit_cameras,
    ortho_values,
    skew_correct_masks,
    skew_correct_views,
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

    @property
    def names(self) -> list[str]:
        """The file names of the area's images."""
        return [os.path.basename(path) for path, _ in self.crops]

    def to_report(self) -> dict[str, Any]:
        names = [name for name, _ in self.crops]
        return {
            "altitude_range": self.altitude.to_report(),
            "views": [{"image": path, "crop": list(box), "acquisition": acquisition}
                      for (path, box), acquisition in zip(self.crops, self.acquisitions)],
            "cameras": {"approx_error_px": {os.path.basename(n): v.camera.error.to_dict()
                                            for n, v in zip(names, self.cameras.views)},
                        "warnings": list(self.cameras.warnings)},
            "sparse": self.sparse,
            "ba": self.adjustment.to_report(),
            "view_selection": self.selection.to_dict([os.path.basename(n) for n in names]),
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
    sparse, untied, altitude, sources = tied.sparse, tied.untied, tied.altitude, tied.sources
    if altitude.source == "tie points":
        if altitude.doubt:
            rep.warn(altitude.doubt, doubtful=True)
        rep.log(f"altitude range {altitude.range.min:.1f}..{altitude.range.max:.1f} m from "
                f"{sparse.altitude['tie_points']} adjusted tie points (give --alt-range or --dem, "
                "alt_range= or dem= in the API, to set it)")
    alt = altitude.range
    views, images = crop_views(sources, job.aoi, alt, config, report=rep,
                               extra_margin_px=tied.correction_margin_px)
    kept = {v.path for v in views}  # the views holding data over the area
    sources = [src for src in sources if src.path in kept]
    names = [v.name for v in views]
    cameras = fit_cameras(views, job.aoi, alt, config, report=rep)
    worst = max(v.camera.error.max_px for v in cameras.views)
    if job.split_above_px > 0.0 and worst > job.split_above_px:
        return Split(max_error_px=float(worst))

    # The kernels the sweep stage will need, built in the background meanwhile.
    ctx.device.prebuild(program_forecast(ctx.device, cameras,
                                         enu_height_range(cameras.frame, job.aoi, alt), config))
    borrowed = (None if job.borrowed_shifts is None
                else [job.borrowed_shifts[v.path] for v in views])
    cameras, adjustment = correct_pointing(cameras, views, sparse, untied, config,
                                           borrowed_shifts=borrowed, may_wait=job.may_wait,
                                           report=rep)
    if adjustment.postponed is not None:
        return Wait(adjustment.postponed)
    ortho_images = ortho_values(views) if config.reconstruct.write_ortho else None
    masks = [v.valid for v in views]
    if config.reconstruct.skew_correct:
        masks = skew_correct_masks(cameras, masks)
        cameras, images, ortho_images = skew_correct_views(cameras, images, ortho_images,
                                                           report=rep)

    from satsweep.dense.selection import select_views

    u_range = enu_height_range(cameras.frame, job.aoi, alt)
    mid = 0.5 * (u_range[0] + u_range[1])
    # The sun's angles where the metadata give a date-time without them (reported as computed).
    lon, lat = job.aoi.center
    acquisitions = [with_computed_sun(s.acquisition, lon=lon, lat=lat) for s in sources]
    with rep.stage("select"):
        similarity = similarity_source = None
        if len(cameras.views) >= MIN_VIEWS_FOR_SIMILARITY:
            from satsweep.dense.similarity import appearance_similarity

            similarity, similarity_source = appearance_similarity(
                acquisitions, images, cameras, job.aoi, mid,
                matches=None if sparse is None else sparse.match_counts([v.path for v in views]))
        selection = select_views([v.camera for v in cameras.views], mid_height=mid,
                                 options=config.views, names=names, similarity=similarity,
                                 similarity_source=similarity_source)
        for w in selection.warnings:
            rep.warn(w)
    sweeps = sweep_references(ctx.device, cameras, images, selection, u_range, config, rep,
                              names, aoi=job.aoi, alt_range=alt, valid_masks=masks)
    _check_range_ends(sweeps, altitude, job, ctx)
    rasters = area_rasters(sweeps, cameras, images, job.grid, config, rep,
                           ortho_images=ortho_images)
    record = AreaRecord(altitude=altitude,
                        crops=[(v.path, (int(v.x0), int(v.y0), int(v.width), int(v.height)))
                               for v in views],
                        acquisitions=[None if a is None else a.to_dict() for a in acquisitions],
                        cameras=cameras, adjustment=adjustment,
                        sparse=None if sparse is None else sparse.to_dict(), selection=selection,
                        sweeps=sweeps, rasters=rasters)
    own = adjustment.own_shifts
    return AreaResult(rasters=rasters, cameras=cameras,
                      shifts=None if own is None else {v.path: s for v, s in zip(views, own)},
                      record=record)


# More pixels than this fraction of a reference's window at an end of the altitude range means
# the surface extends beyond it. Measured with ranges that hold the surface: at most 0.26% on
# tools/bench_e2e.py's four 512 px towns, 1.1% on the tests' 192 px town, 0.03% on the Pleiades
# pair (2260..2390 m); with ranges that cut its ground off (2290..2420, 2200..2330 m): 5.2-7.3%.
RANGE_END_WARN_FRACTION = 0.03


def _check_range_ends(sweeps: Sequence[ReferenceHeights], altitude: AltitudeChoice, job: AreaJob,
                      ctx: RunContext) -> None:
    """A doubtful warning when many pixels' best plane sits at an end of the altitude range,
    with the range that tie points measure between the views when the range was given."""
    worst = max(((s.at_range_ends[k], k, s.reference) for s in sweeps for k in (0, 1)),
                default=(0.0, 0, ""))
    fraction, end, reference = worst
    if fraction <= RANGE_END_WARN_FRACTION:
        return
    rng = altitude.range
    side, bound = (("lower", rng.min), ("upper", rng.max))[end]
    where = ("below", "above")[end]
    measured = ""
    if altitude.source != "tie points":
        try:
            ties = choose_altitude_range(job.sources, job.aoi, alt_range=None, dem=None,
                                         config=ctx.config)  # at the RPCs' range, not the user's
            measured = (f"; tie points between the views put it within "
                        f"{ties.range.min:.0f}..{ties.range.max:.0f} m")
        except SatsweepError as exc:
            measured = f"; tie points could not measure it ({exc})"
    ctx.report.warn(f"{100 * fraction:.1f}% of {reference}'s pixels matched best at the {side} "
                    f"end ({bound:.0f} m) of the altitude range {rng.min:.0f}..{rng.max:.0f} m "
                    f"({altitude.source}): the surface probably extends {where} it{measured}",
                    doubtful=True)


def sources_seeing(sources: Sequence["ImageSource"], aoi: "AOI",
                   prior: AltitudeRange) -> list["ImageSource"]:
    """The sources whose footprint of the AOI cube (at the ``prior`` range) meets the image."""
    return [s for s in sources if s.sees(aoi, prior)]


def median_shifts(shifts: Sequence[Sequence[Sequence[float]]]) -> list[list[float]]:
    """Per view, the median (dcx, dcy) of several tiles' corrections."""
    return [np.median(np.array(s), axis=0).tolist() for s in shifts]
