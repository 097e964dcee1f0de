"""The altitude range of a run or of one of its areas: one policy, used by every stage.

In this order: the range the user gives (``--alt-range``), else a DEM's heights over the area
plus a margin (``--dem``), else the sparse stage's tie points (as S2P takes its disparity range
from SIFT matches): matched between the views cropped at the RPCs' wide range, triangulated
with the cameras that the adjustment corrects, those that reproject within a pixel bounding the
heights (``satsweep.sparse.stage``, ``satsweep.sparse.tiepoints.altitude_range_from_points``).
``satsweep reconstruct`` and ``satsweep cameras`` get the same range from the same views.

``prior_altitude_range`` is the cheaper question of which images can see an area at all: the
user's range or the DEM's, else the RPCs' common height range (kilometres wide, so that no image
is left out for want of a range).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from typing import TYPE_CHECKING, Any, Sequence

from satsweep.errors import CameraError, InputError
from satsweep.geometry.altitude import (
    AltitudeRange,
    altitude_range_from_rpcs,
    resolve_altitude_range,
)

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.config import PipelineConfig
    from satsweep.geometry.aoi import AOI
    from satsweep.io.sources import ImageSource
    from satsweep.pipeline.report import RunReport
    from satsweep.sparse.stage import SparseResult

# A tie-point range that shares less than this fraction of its span with the RPCs' range: the
# corrected cameras put the scene where the RPCs do not (v20 multi-date stacks, same-date pairs
# one view of which is tens of pixels off: -65..-25 m, 148..184 m, 253..294 m against 95..165
# m, DSMs 11-51% within 1 m; pairs that hold the truth share 92% or more).
PRIOR_OVERLAP_MIN_FRACTION = 0.5
# Corrections (px) past which two views tied alone leave the scene's position in doubt: which of
# them is off, no measurement tells (a pointing error of either is a motion of the whole scene),
# and the adjustment puts the scene where the smaller correction does. 5 of 20 views of a v20
# multi-date stack (seed 0), three dropped: the two left were 31 and 42 px off, their
# corrections (-41.7, 0.1) and (0.1, 0.0) px, the DSM 30 m high, 31% of it within 1 m.
GAUGE_DOUBT_PX = 5.0
# What the user can do when no range can be measured.
_GIVE_A_RANGE = "give --alt-range MIN MAX or --dem FILE (alt_range= or dem= in the Python API)"


@dataclasses.dataclass(frozen=True)
class AltitudeChoice:
    """An area's altitude range and where it comes from."""

    range: AltitudeRange
    source: str  # "user", "dem" or "tie points"
    details: dict[str, Any] = dataclasses.field(default_factory=dict)  # the tie points' figures
    doubt: str | None = None  # a doubtful warning about the tie points' range (range_outside_prior)

    def to_report(self) -> dict[str, Any]:
        return {"min": self.range.min, "max": self.range.max, "source": self.source,
                **{k: v for k, v in self.details.items() if k not in ("min", "max", "source")}}


def prior_altitude_range(sources: Sequence["ImageSource"], aoi: "AOI", *,
                         alt_range: AltitudeRange | None,
                         dem: str | os.PathLike | None) -> AltitudeRange:
    """The user's range, else the DEM's over ``aoi``, else the RPCs' common range (the widest
    prior: for deciding which images see an area, not for sweeping)."""
    if alt_range is None and dem is None:
        return altitude_range_from_rpcs([s.rpc for s in sources], warn=False)
    return resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)


def choose_altitude_range(sources: Sequence["ImageSource"], aoi: "AOI", *,
                          alt_range: AltitudeRange | None, dem: str | os.PathLike | None,
                          config: "PipelineConfig",
                          report: "RunReport | None" = None) -> AltitudeChoice:
    """The altitude range to sweep over ``aoi``: the user's, else the DEM's, else the tie
    points' (see the module docstring: the sparse stage runs on the views cropped at the RPCs'
    range, timed in ``report`` when given; its doubts are the caller's to give, from
    ``AltitudeChoice.doubt``). InputError when none can be had."""
    if alt_range is not None or dem is not None:
        rng = resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)
        return AltitudeChoice(rng, "user" if alt_range is not None else "dem")
    return tie_and_range(sources, aoi, alt_range=None, dem=None, config=config, adjust=False,
                         report=report, warn_doubts=False).altitude


@dataclasses.dataclass(frozen=True, eq=False)
class TiedSources:
    """What :func:`tie_and_range` found: the sparse stage's result (None when it did not run, or
    ``untied`` when it could not tie the views although a range was given), the area's altitude
    range, and the sources the sparse stage kept (all of them when it did not run)."""

    sparse: "SparseResult | None"
    untied: CameraError | None
    altitude: AltitudeChoice
    sources: list["ImageSource"]

    @property
    def correction_margin_px(self) -> int:
        """Pixels the views' crops need beyond the AOI's footprint to hold its content once the
        sparse stage's corrections move them (its largest, rounded up; 0 when it did not run)."""
        return 0 if self.sparse is None else int(math.ceil(self.sparse.max_correction_px))


def tie_and_range(sources: Sequence["ImageSource"], aoi: "AOI", *,
                  alt_range: AltitudeRange | None, dem: str | os.PathLike | None,
                  config: "PipelineConfig", adjust: bool,
                  report: "RunReport | None" = None, warn_doubts: bool = True) -> TiedSources:
    """The sparse stage where the run needs it, and the altitude range: ``reconstruct``,
    ``satsweep cameras`` and ``prepare_views`` start here. Without a range (``alt_range``,
    ``dem``) the sparse stage runs over the RPCs' range and gives it (InputError when it
    cannot); with one, it runs over that range only when the pointing is to be corrected
    (``adjust``). With ``warn_doubts``, what puts the result in doubt (a tie-point range
    outside the RPCs', two views tied alone far off) is a doubtful warning in ``report``, or a
    logged one without a report."""
    given = alt_range is not None or dem is not None
    sources = list(sources)
    sparse, untied = None, None
    if not given or adjust:
        from satsweep.pipeline.prepare import tie_sources

        prior = prior_altitude_range(sources, aoi, alt_range=alt_range, dem=dem)
        try:
            sparse = tie_sources(sources, aoi, prior, config, report=report)
        except CameraError as exc:
            if not given:
                raise untied_error(exc) from None
            untied = exc
        else:
            kept = set(sparse.kept_paths)
            sources = [src for src in sources if src.path in kept]
            if warn_doubts:
                _warn_doubt(report, pointing_gauge_doubt(sparse))
    if given:
        altitude = choose_altitude_range(sources, aoi, alt_range=alt_range, dem=dem,
                                         config=config)
    else:
        altitude = tie_point_altitude(sparse, prior)
        if warn_doubts:
            _warn_doubt(report, altitude.doubt)
    return TiedSources(sparse=sparse, untied=untied, altitude=altitude, sources=sources)


def _warn_doubt(report: "RunReport | None", doubt: str | None) -> None:
    """A doubtful warning in the run's report; without one (``satsweep cameras``), a logged
    warning; nothing for None."""
    if doubt is None:
        return
    if report is not None:
        report.warn(doubt, doubtful=True)
    else:
        log.warning("%s", doubt)


def pointing_gauge_doubt(sparse: "SparseResult") -> str | None:
    """A warning when only two views are tied and their corrections reach GAUGE_DOUBT_PX, else
    None. Moving the whole scene by ``dX`` while shifting each view by ``-A_v dX`` changes no
    tie point (:mod:`satsweep.sparse.bundle`); with two views every member of that family fits,
    so the scene may lie where either view's RPC is right: the motion named is the smallest that
    takes the larger correction to zero (``A_v`` at the tie points' median)."""
    import numpy as np

    from satsweep.sparse.bundle import gauge_jacobians

    kept = list(sparse.tied.kept)
    if len(kept) != 2:
        return None
    s = np.asarray(sparse.corrections_px, np.float64)[kept]
    worst = int(np.argmax(np.abs(s).max(axis=1)))
    if not float(np.abs(s[worst]).max()) > GAUGE_DOUBT_PX:
        return None
    points = np.asarray(sparse.tied.points, np.float64)
    centre = np.median(points, axis=0) if len(points) else np.zeros(3)
    A = gauge_jacobians([sparse.tied.cameras[v] for v in kept], centre)
    move = float(np.linalg.norm(np.linalg.pinv(A[worst]) @ s[worst]))
    names = [os.path.basename(sparse.paths[v]) for v in kept]
    return (f"only two views are tied ({names[0]}, {names[1]}) and {names[worst]}'s pointing "
            f"correction is {s[worst, 0]:+.1f}, {s[worst, 1]:+.1f} px: two views cannot tell which "
            "of them is off (either's error is a motion of the whole scene), so the scene and its "
            f"DSM may lie {move:.0f} m or more from the ground the RPCs see (had {names[worst]}'s "
            "RPC been right); give more views of the place, or RPCs corrected against ground "
            "control")


def untied_error(exc: CameraError) -> InputError:
    """The error of a run without a range whose views the sparse stage cannot tie (``exc``)."""
    return InputError(None, f"no altitude range given and the views cannot be tied to find one "
                            f"({exc}): {_GIVE_A_RANGE}")


def tie_point_altitude(sparse: "SparseResult", prior: AltitudeRange) -> AltitudeChoice:
    """The sparse stage's altitude range as an area's, with its record, and a doubt when it lies
    mostly outside ``prior`` (the RPCs' range: :func:`range_outside_prior`). InputError when
    its tie points bound none."""
    if sparse.altitude_range is None:
        raise InputError(None, f"no altitude range given and {sparse.altitude['reason']}: "
                               f"{_GIVE_A_RANGE}")
    return AltitudeChoice(sparse.altitude_range, "tie points", sparse.altitude,
                          doubt=range_outside_prior(sparse.altitude_range, prior,
                                                    len(sparse.kept_paths)))


def range_outside_prior(rng: AltitudeRange, prior: AltitudeRange, n_views: int) -> str | None:
    """A warning when the tie points' altitude range lies mostly outside the RPCs' (``prior``),
    else None: the adjustment's unobservable motion has moved the whole scene, which with two
    views (or views along one line) a pointing error along the epipolar lines does."""
    overlap = max(0.0, min(rng.max, prior.max) - max(rng.min, prior.min))
    span = max(rng.max - rng.min, 1e-9)
    if overlap >= PRIOR_OVERLAP_MIN_FRACTION * span:
        return None
    why = ("with two views a pointing error along the epipolar lines is a height offset of the "
           "whole scene" if n_views == 2 else "their pointing errors moved the whole scene")
    return (f"the {n_views} views' adjusted tie points lie at {rng.min:.0f}..{rng.max:.0f} m, "
            f"mostly outside the RPCs' altitude range {prior.min:.0f}..{prior.max:.0f} m ({why}): "
            "the DSM's heights and position may be off by metres to tens of metres; give "
            "--alt-range or --dem, or more views")
