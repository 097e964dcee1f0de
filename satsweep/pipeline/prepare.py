"""Prepare the views of an area: crops, cameras, pointing correction, skew correction.

This is the front half of every reconstruction, and a stage of its own for the ``satsweep
cameras`` command, the tests and the tools (``prepare_views`` runs it whole). Its steps, each
timed as a stage of the run's report when one is given:

  views    each image cropped to the footprint of the AOI cube, tonemapped
           (``satsweep.io.views``, ``satsweep.io.images.tonemap``)
  cameras  the perspective approximation of every RPC over the cube (``satsweep.geometry.camera``)
  adjust   the principal points moved by the sparse stage's pointing corrections
           (``satsweep.sparse.stage``, run by ``pipeline.altitude.tie_and_range`` before the
           crops), per ``[reconstruct] adjust``; an ``Adjustment`` says what was done
  skew     the images sheared so that K has no skew (``satsweep.geometry.skew``)

The images handed to the sweep are the tonemapped crops; the orthophoto's are the crops' own
values (sensor units, the same in every tile), sheared alike.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from satsweep.errors import CameraError

if TYPE_CHECKING:  # pragma: no cover
    import os

    from satsweep.config import PipelineConfig
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.geometry.aoi import AOI
    from satsweep.geometry.camera import CameraSet
    from satsweep.io.sources import ImageSource
    from satsweep.io.views import View
    from satsweep.pipeline.report import RunReport
    from satsweep.sparse.bundle import BundleReport
    from satsweep.sparse.stage import SparseResult


log = logging.getLogger(__name__)


def _stage(report: "RunReport | None", name: str):
    """The report's timer of stage ``name``, or nothing without a report."""
    return report.stage(name) if report is not None else contextlib.nullcontext()


def _log(report: "RunReport | None", message: str) -> None:
    if report is not None:
        report.log(message)


def _warn(report: "RunReport | None", message: str) -> None:
    """A warning in the run's report; without one, a logged warning."""
    if report is not None:
        report.warn(message)
    else:
        log.warning("%s", message)


@dataclasses.dataclass(frozen=True)
class Adjustment:
    """What the pointing-correction step did with an area's views.

    ``bundle``: the adjustment's own report when it ran; else ``skipped`` says why (and
    ``borrowed_shift_px`` holds the other tiles' corrections applied instead, if any), or
    ``postponed`` says why the area waits for other tiles' corrections.
    """

    bundle: "BundleReport | None" = None
    skipped: str | None = None
    borrowed_shift_px: tuple[tuple[float, float], ...] | None = None
    postponed: str | None = None
    sparse_shifts: tuple[tuple[str, tuple[float, float]], ...] | None = None  # per view, its
    # image (the path as given) and the sparse stage's correction applied
    # (satsweep.sparse.stage): by path, not file name, so that two views of one file name in
    # different folders keep their own

    @property
    def own_shifts(self) -> list[list[float]] | None:
        """Per view (dcx, dcy) px of this area's own adjustment; None without one."""
        if self.sparse_shifts is not None:
            return [list(s) for _, s in self.sparse_shifts]
        if self.bundle is None:
            return None
        return [list(s) for s in self.bundle.principal_point_shift_px]

    def named_sparse_shifts(self) -> list[tuple[str, tuple[float, float]]]:
        """``sparse_shifts`` by the views' ``report_names`` (for the report and the log)."""
        from satsweep.io.sources import report_names

        shifts = self.sparse_shifts or ()
        return list(zip(report_names([p for p, _ in shifts]), (s for _, s in shifts)))

    def to_report(self) -> dict[str, Any]:
        if self.sparse_shifts is not None:
            return {"method": "sparse stage (report: sparse)",
                    "principal_point_shift_px": {n: list(s)
                                                 for n, s in self.named_sparse_shifts()}}
        if self.bundle is not None:
            return self.bundle.to_dict()
        if self.postponed is not None:
            return {"postponed": self.postponed}
        out: dict[str, Any] = {"skipped": self.skipped}
        if self.borrowed_shift_px is not None:
            out["borrowed_principal_point_shift_px"] = [list(s) for s in self.borrowed_shift_px]
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class PreparedViews:
    """An area's views ready for the sweep: crops, images, cameras and how they were adjusted."""

    views: list["View"]  # the crops (raw pixels, RPCs of the crops)
    images: list[np.ndarray]  # float32, tonemapped to about [0, 1], sheared like the cameras
    ortho_images: list[np.ndarray] | None  # the crops' own values, sheared alike (None: none)
    cameras: "CameraSet"  # adjusted (per ``adjustment``) and skew-corrected (per the options)
    adjustment: Adjustment
    valid: list[np.ndarray | None] = dataclasses.field(default_factory=list)  # per view, the
    # pixels of ``images`` that hold data (None: all), sheared like them

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]


def crop_views(sources: Sequence["ImageSource"], aoi: "AOI", alt_range: "AltitudeRange",
               config: "PipelineConfig", *, report: "RunReport | None" = None,
               extra_margin_px: int = 0,
               warn_partial: bool = True) -> tuple[list["View"], list[np.ndarray]]:
    """The "views" step: each image's crop of the AOI cube (``[reconstruct] crop_margin_px``
    around it) and the crop tonemapped (its no-data pixels flat, ``View.valid``). A view with
    less than ``MIN_VALID_FRACTION`` of its crop holding data is left out with a warning naming
    it; InputError when fewer than two views remain. ``warn_partial``: warn about an image that
    sees only part of ``aoi`` (off in a reconstruction, which warns once per image from the
    shares its areas measure on their DSMs, ``satsweep.pipeline.scheduler``)."""
    from satsweep.errors import InputError
    from satsweep.io.images import tonemap
    from satsweep.io.views import load_views

    with _stage(report, "views"):
        views = load_views(sources, aoi, alt_range,
                           margin_px=config.reconstruct.crop_margin_px + int(extra_margin_px),
                           warn_partial=warn_partial,
                           vegetation=config.dsm.green_crowns or config.views.leaf_from_colour)
        kept = []
        for v in views:
            fraction = 1.0 if v.valid is None else float(np.mean(v.valid))
            if fraction < MIN_VALID_FRACTION:
                _warn(report, f"{v.path}: only {100 * fraction:.0f}% of the pixels that see the "
                              "AOI hold data (no-data value, NaN, zero fill or its mask): left "
                              "out")
                continue
            kept.append(v)
        if len(kept) < 2:
            raise InputError(None, "fewer than two images hold data over the AOI ("
                                   + ", ".join(v.name for v in views) + ")")
        images = [tonemap(v.image, valid=v.valid) for v in kept]
    return kept, images


def fit_cameras(views: Sequence["View"], aoi: "AOI", alt_range: "AltitudeRange",
                config: "PipelineConfig", *, report: "RunReport | None" = None) -> "CameraSet":
    """The "cameras" step: every view's perspective approximation over the AOI cube."""
    from satsweep.geometry.camera import build_cameras

    with _stage(report, "cameras"):
        cameras = build_cameras(views, aoi, alt_range, config.camera)
        for w in cameras.warnings:
            _warn(report, w)
    return cameras


def correct_pointing(cameras: "CameraSet", views: Sequence["View"], sparse: "SparseResult | None",
                     untied: CameraError | None, config: "PipelineConfig", *,
                     borrowed_shifts: Sequence[Sequence[float]] | None = None,
                     may_wait: bool = False, report: "RunReport | None" = None
                     ) -> tuple["CameraSet", Adjustment]:
    """The "adjust" step, per ``[reconstruct] adjust``: the principal points moved by the sparse
    stage's corrections (``sparse``, from ``pipeline.altitude.tie_and_range``; the ``views``
    cropped with room for them); when it could not tie the views (``untied``), the rules of
    :func:`unadjusted`."""
    if config.reconstruct.adjust == "off":
        return cameras, Adjustment(skipped="reconstruct.adjust = off")
    if sparse is not None:
        from satsweep.sparse.bundle import shift_principal_points

        shifts = sparse.corrections_for([v.path for v in views])
        return (shift_principal_points(cameras, shifts),
                Adjustment(sparse_shifts=tuple((v.path, s) for v, s in zip(views, shifts))))
    return unadjusted(cameras, untied, config, borrowed_shifts=borrowed_shifts,
                      may_wait=may_wait, report=report)


def unadjusted(cameras: "CameraSet", exc: CameraError, config: "PipelineConfig", *,
               borrowed_shifts: Sequence[Sequence[float]] | None = None, may_wait: bool = False,
               report: "RunReport | None" = None) -> tuple["CameraSet", Adjustment]:
    """What to do when the views could not be tied (``exc``): the other tiles' corrections
    (``borrowed_shifts``), else wait for them (``may_wait``), else skip the adjustment with 2
    views under ``adjust = auto``; raise ``exc`` otherwise."""
    from satsweep.sparse import bundle

    why = f"not enough matches for the adjustment: {exc}"
    if borrowed_shifts is not None:
        _warn(report, f"bundle adjustment of this tile impossible ({exc}); the other tiles' "
                      "pointing corrections are used")
        shifts = tuple(tuple(float(v) for v in s) for s in borrowed_shifts)
        return (bundle.shift_principal_points(cameras, borrowed_shifts),
                Adjustment(skipped=why, borrowed_shift_px=shifts))
    if may_wait:
        _log(report, f"bundle adjustment of this tile impossible ({exc}): it waits for the "
                     "other tiles' pointing corrections")
        return cameras, Adjustment(postponed=why)
    if config.reconstruct.adjust == "on" or len(cameras.views) >= 3:
        raise exc
    _warn(report, f"bundle adjustment skipped: {exc}")
    return cameras, Adjustment(skipped=why)


def tie_sources(sources: Sequence["ImageSource"], aoi: "AOI", prior: "AltitudeRange",
                config: "PipelineConfig", *, report: "RunReport | None" = None):
    """The "sparse" step (``satsweep.sparse.stage.sparse_stage``): the images cropped at the
    ``prior`` altitude range (the user's, a DEM's or the RPCs' wide one), their pointing
    corrections, the views that can be tied and the altitude range of the tie points. CameraError
    when fewer than two views can be tied."""
    from satsweep.io.images import tonemap
    from satsweep.io.views import load_views
    from satsweep.sparse.stage import sparse_stage

    with _stage(report, "sparse"):
        # A small AOI is tied over a larger box about it ([sparse] min_extent_m). Over the RPCs'
        # kilometres of heights the footprints overflow the images: no warning.
        tie_aoi = aoi.grown_to(config.sparse.min_extent_m)
        views = load_views(sources, tie_aoi, prior, margin_px=config.reconstruct.crop_margin_px,
                           warn_partial=False)
        # (The fixed views were checked against the whole input: check_fixed_views.)
        result = sparse_stage(views, aoi, prior, config.sparse, config.bundle,
                              images=[tonemap(v.image, valid=v.valid) for v in views],
                              fixed_absent_ok=True, tie_aoi=tie_aoi)
    for line in result.warnings:
        _warn(report, line)
    return result


# A view whose crop holds data over less than this fraction of its pixels is left out.
MIN_VALID_FRACTION = 0.2
# A sheared pixel holds data when its interpolated mask is at least this: every pixel it reads
# does (1 - 1e-6: float32 rounding of weights summing to one).
MASK_INTERPOLATED_MIN = 1.0 - 1e-6


def _fill_nan(image: np.ndarray) -> np.ndarray:
    """Skew correction leaves NaN where the sheared image has no source pixel: use 0 there (those
    pixels are in the crop margin, outside the AOI footprint)."""
    out = np.asarray(image, dtype=np.float32)
    return np.where(np.isfinite(out), out, np.float32(0.0)).astype(np.float32)


def skew_correct_views(cameras: "CameraSet", images: Sequence[np.ndarray],
                       ortho_images: Sequence[np.ndarray] | None = None, *,
                       vegetation_images: Sequence[np.ndarray] | None = None,
                       report: "RunReport | None" = None):
    """The "skew" step: (cameras without skew, images sheared alike with 0 where no pixel maps,
    ortho images and vegetation images sheared alike, NaN where no pixel maps (None stays
    None))."""
    from satsweep.geometry.skew import skew_correct_set

    with _stage(report, "skew"):
        corrected, sheared = skew_correct_set(cameras, images)
        sheared = [_fill_nan(im) for im in sheared]
        if ortho_images is not None:
            _, ortho_images = skew_correct_set(cameras, ortho_images)
        if vegetation_images is not None:
            _, vegetation_images = skew_correct_set(cameras, vegetation_images)
    return corrected, sheared, ortho_images, vegetation_images


def skew_correct_masks(cameras: "CameraSet", masks: Sequence[np.ndarray | None]
                       ) -> list[np.ndarray | None]:
    """The views' data masks sheared like their images (``skew_correct_views``): a pixel holds
    data where every source pixel its interpolation reads does; outside the sheared image (the
    crop margin) it counts as data, as the images' zero fill there always did."""
    from satsweep.geometry.skew import skew_correct_set

    if all(m is None for m in masks):
        return list(masks)
    planes = [np.ones((v.camera.height, v.camera.width), np.float32) if m is None
              else m.astype(np.float32) for m, v in zip(masks, cameras.views)]
    _, sheared = skew_correct_set(cameras, planes)
    return [None if m is None else np.where(np.isfinite(s), s >= MASK_INTERPOLATED_MIN, True)
            for m, s in zip(masks, sheared)]


def check_fixed_views(sources: Sequence["ImageSource"], config: "PipelineConfig") -> None:
    """OptionsError naming a ``[bundle] fixed_views`` entry that names none of the run's
    images (or several): checked once on the whole input, since a tile's sparse stage sees only
    the images that see it."""
    from satsweep.sparse.stage import fixed_view_indices

    fixed_view_indices(config.bundle.fixed_views, [s.path for s in sources],
                       [s.name for s in sources])


def open_run_sources(paths: Sequence["ImageSource | str | os.PathLike"],
                     config: "PipelineConfig", *,
                     rpc_dir: "str | os.PathLike | None" = None,
                     mask_dir: "str | os.PathLike | None" = None) -> list["ImageSource"]:
    """The run's images opened (``satsweep.io.sources.open_sources``: each with its RPC, from
    ``rpc_dir`` where given, and its mask, from ``mask_dir`` where it has one there) and
    ``[bundle] fixed_views`` checked against all of them (``check_fixed_views``): what every
    entry point does first."""
    from satsweep.io.sources import open_sources

    sources = open_sources(paths, rpc_dir=rpc_dir, mask_dir=mask_dir)
    check_fixed_views(sources, config)
    return sources


def sources_seeing_the_aoi(sources: Sequence["ImageSource"], aoi: "AOI",
                           config: "PipelineConfig", *, alt_range: "AltitudeRange | None" = None,
                           dem: "str | os.PathLike | None" = None,
                           report: "RunReport | None" = None
                           ) -> tuple[list["ImageSource"], list[dict]]:
    """The sources whose image sees the AOI cube at its own RPC's heights (offset +- scale: the
    widest it could see it at) or, for one that does not, at those and the range that
    ``alt_range`` or ``dem`` gives (resolved only then: an RPC whose heights miss the scene's
    is no sign of another place), and a record per source left out (image, reason). A view of
    another place (its RPC puts the AOI outside its pixels) is left out with a warning naming
    it, as the sparse stage leaves out a view it cannot tie; checked before anything else, so
    that its RPC's heights do not narrow the others' common range. Raises that image's AOIError
    when it is a ``[bundle] fixed_views`` image (the user trusts it) or fewer than two images
    remain."""
    from satsweep.errors import AOIError
    from satsweep.geometry.altitude import (
        AltitudeRange,
        altitude_range_from_rpcs,
        resolve_altitude_range,
    )
    from satsweep.sparse.stage import fixed_view_indices

    fixed, _ = fixed_view_indices(config.bundle.fixed_views, [s.path for s in sources],
                                  [s.name for s in sources])
    given: list[AltitudeRange] = []  # the user's or the DEM's range, once resolved

    def sees(source: "ImageSource") -> None:  # AOIError where it does not
        own = altitude_range_from_rpcs([source.rpc], warn=False)
        try:
            source.footprint(aoi, own, warn_partial=False)
        except AOIError:
            if alt_range is None and dem is None:
                raise
            if not given:
                given.append(resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi))
            # both: the cube's box spans every height between
            source.footprint(aoi, AltitudeRange(min(own.min, given[0].min),
                                                max(own.max, given[0].max)), warn_partial=False)

    kept, elsewhere = [], []
    for k, source in enumerate(sources):
        try:
            sees(source)
        except AOIError as exc:
            if k in fixed:
                raise
            elsewhere.append((source, exc))
            continue
        kept.append(source)
    if elsewhere and len(kept) < 2:
        raise elsewhere[0][1]
    for _, exc in elsewhere:
        _warn(report, f"{exc}: left out")
    return kept, [{"image": source.path, "reason": str(exc)} for source, exc in elsewhere]


def ortho_values(views: Sequence["View"]) -> list[np.ndarray]:
    """The orthophoto's grey levels: the crops' own values (sensor units, the same for every
    tile, where each tile's tonemap stretches its own crop)."""
    return [np.asarray(v.image, np.float32) for v in views]


def vegetation_values(views: Sequence["View"]) -> list[np.ndarray] | None:
    """Each view's vegetation index (``View.vegetation``) where every view has one (colour
    images); None otherwise: a stack that mixes panchromatic and colour images tells leaves in
    some views only, and the crowns' rule (``[dsm] green_crowns``) compares views."""
    if not views or any(v.vegetation is None for v in views):
        return None
    return [np.asarray(v.vegetation, np.float32) for v in views]


def prepare_views(sources: Sequence["ImageSource | str"], aoi: "AOI",
                  alt_range: "AltitudeRange", config: "PipelineConfig | None" = None, *,
                  report: "RunReport | None" = None) -> PreparedViews:
    """Every step in order, as a reconstruction takes them over ``alt_range``: the images of
    other places left out (``sources_seeing_the_aoi``, with a warning), the sparse stage
    (per ``[reconstruct] adjust``; the views it cannot tie left out with a warning), crops,
    cameras, their pointing correction (``correct_pointing``, without waiting), the skew
    correction per ``[reconstruct] skew_correct``. ``sources``: ``ImageSource`` objects or image
    paths."""
    from satsweep.config import PipelineConfig
    from satsweep.pipeline.altitude import tie_and_range

    config = config if config is not None else PipelineConfig()
    sources = open_run_sources(sources, config)
    sources, _ = sources_seeing_the_aoi(sources, aoi, config, alt_range=alt_range,
                                        report=report)
    tied = tie_and_range(sources, aoi, alt_range=alt_range, dem=None,
                         config=config, adjust=config.reconstruct.adjust != "off",
                         report=report)
    views, images = crop_views(tied.sources, aoi, alt_range, config, report=report,
                               extra_margin_px=tied.correction_margin_px)
    cameras = fit_cameras(views, aoi, alt_range, config, report=report)
    cameras, adjustment = correct_pointing(cameras, views, tied.sparse, tied.untied, config,
                                           report=report)
    ortho = ortho_values(views) if config.reconstruct.write_ortho else None
    masks = [v.valid for v in views]
    if config.reconstruct.skew_correct:
        masks = skew_correct_masks(cameras, masks)
        cameras, images, ortho, _ = skew_correct_views(cameras, images, ortho, report=report)
    return PreparedViews(views=views, images=list(images), ortho_images=ortho, cameras=cameras,
                         adjustment=adjustment, valid=masks)
