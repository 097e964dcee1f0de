"""The altitude range of a run or of one of its areas: one policy, used by every stage.

In this order: the range the user gives (``--alt-range``), else a DEM's heights over the area
plus a margin (``--dem``), else SIFT tie points between the views triangulated with their RPCs
(``satsweep.sparse.tiepoints``, as S2P takes its disparity range from SIFT matches).

``prior_altitude_range`` is the cheaper question of which images can see an area at all: the
user's range or the DEM's, else the RPCs' common height range (kilometres wide, so that no image
is left out for want of a range).
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any, Sequence

from satsweep.geometry.altitude import (
    AltitudeRange,
    altitude_range_from_rpcs,
    resolve_altitude_range,
)

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.config import PipelineConfig
    from satsweep.geometry.aoi import AOI
    from satsweep.io.sources import ImageSource


@dataclasses.dataclass(frozen=True)
class AltitudeChoice:
    """An area's altitude range and where it comes from."""

    range: AltitudeRange
    source: str  # "user", "dem" or "tie points"
    details: dict[str, Any] = dataclasses.field(default_factory=dict)  # the tie points' figures

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
                          config: "PipelineConfig") -> AltitudeChoice:
    """The altitude range to sweep over ``aoi``: the user's, else the DEM's, else the tie
    points' (see the module docstring)."""
    if alt_range is not None or dem is not None:
        rng = resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)
        return AltitudeChoice(rng, "user" if alt_range is not None else "dem")
    from satsweep.sparse.tiepoints import altitude_range_for_images

    r = config.reconstruct
    rng, record = altitude_range_for_images(
        sources, aoi, config.sparse, quantile=r.tie_altitude_quantile,
        margin_m=r.tie_altitude_margin_m, crop_margin_px=r.crop_margin_px)
    return AltitudeChoice(rng, "tie points", record)
