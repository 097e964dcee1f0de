"""The altitude range (metres above the WGS84 ellipsoid) that bounds the heights the plane sweep
tries, and its span in a local ENU frame.

``resolve_altitude_range`` takes, in this order: a range the user gives, a DEM the user gives
(heights over the AOI plus a margin), or a coarse guess from the RPC height offset/scale.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from typing import Any, Iterable, Sequence

import numpy as np

from satsweep.errors import AOIError, InputError, OptionsError
from satsweep.geometry.aoi import AOI

log = logging.getLogger(__name__)


# Plausible heights above the WGS84 ellipsoid for ground on Earth (Dead Sea shore about -410 m,
# Everest about 8820 m); a range beyond these is a unit or sign mistake (feet, depths).
ALT_PLAUSIBLE_MIN_M = -1000.0
ALT_PLAUSIBLE_MAX_M = 12000.0

# Margin added around a DEM's heights: global DEMs (SRTM, Copernicus) have vertical errors of
# about 5-16 m and model bare earth or canopy tops, so buildings and trees stand above them.
DEFAULT_DEM_MARGIN_M = 50.0

# Bound on |geoid undulation| on Earth (EGM2008: -107 .. +86 m): the extra margin applied when a
# DEM declares geoid (not ellipsoidal) heights, which satsweep cannot convert without geoid grids.
GEOID_UNDULATION_BOUND_M = 110.0


# -- altitude range ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class AltitudeRange:
    """Heights swept, in metres above the WGS84 ellipsoid; validated on construction (AOIError)."""

    min: float  # lowest height, metres above the ellipsoid
    max: float  # highest height, metres above the ellipsoid, > min

    def __post_init__(self) -> None:
        for name in ("min", "max"):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise AOIError(f"altitude range {name} = {value!r}: not a number") from None
            if not math.isfinite(value):
                raise AOIError(f"altitude range {name} = {value!r}: must be finite")
            if not ALT_PLAUSIBLE_MIN_M <= value <= ALT_PLAUSIBLE_MAX_M:
                raise AOIError(
                    f"altitude range {name} = {value!r} m: outside "
                    f"{ALT_PLAUSIBLE_MIN_M:g}..{ALT_PLAUSIBLE_MAX_M:g} m above the WGS84 ellipsoid "
                    "(metres expected)"
                )
            object.__setattr__(self, name, value)
        if not self.min < self.max:
            raise AOIError(
                f"inverted altitude range: min = {self.min!r} m >= max = {self.max!r} m (need min < max)"
            )

    @property
    def span(self) -> float:
        """max - min, metres."""
        return self.max - self.min

    @property
    def mid(self) -> float:
        """Middle height, metres above the ellipsoid."""
        return 0.5 * (self.min + self.max)

    def __str__(self) -> str:
        return f"{self.min:g}..{self.max:g} m"


def parse_altitude_range(spec: str) -> AltitudeRange:
    """Parse ``MIN,MAX`` (metres above the WGS84 ellipsoid) into an AltitudeRange."""
    parts = [p.strip() for p in str(spec).split(",")]
    try:
        if len(parts) != 2:
            raise ValueError
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise AOIError(
            f"altitude range {spec!r}: expected MIN,MAX in metres above the WGS84 ellipsoid"
        ) from None
    return AltitudeRange(lo, hi)


def altitude_range_from_dem(
    path: str | os.PathLike, aoi: AOI, margin_m: float = DEFAULT_DEM_MARGIN_M
) -> AltitudeRange:
    """Height range of a DEM GeoTIFF over the AOI, widened by ``margin_m`` on both sides.

    The DEM may be in any EPSG CRS that read_geotiff supports (geographic EPSG:4326 or UTM, among
    others). Cells overlapping the AOI box, plus one ring of neighbours, are used; nodata and NaN
    cells are ignored. Heights must be above the WGS84 ellipsoid: when the file declares a vertical
    CRS (a geoid, e.g. EGM96 for SRTM), the margin is widened by the geoid undulation bound and a
    warning says so. Raises InputError naming the DEM when it does not cover the whole AOI or has
    no valid height there.
    """
    from satsweep.geometry.geodesy import lonlat_to_crs
    from satsweep.io.geotiff import read_geotiff

    path = os.fspath(path)
    if not (math.isfinite(margin_m) and margin_m >= 0.0):
        raise OptionsError(f"DEM margin_m = {margin_m!r}: must be finite and >= 0")
    dem, info = read_geotiff(path)
    lon, lat = aoi.boundary()
    x, y = lonlat_to_crs(lon=lon, lat=lat, epsg=info.epsg)
    col, row = info.xy_to_pixel(x=x, y=y)
    height, width = dem.shape
    # Pixel (0, 0) is the centre of the first cell: the raster spans -0.5 .. size - 0.5.
    if not (np.isfinite(col).all() and np.isfinite(row).all()) or (
        col.min() < -0.5 or row.min() < -0.5 or col.max() > width - 0.5 or row.max() > height - 0.5
    ):
        raise InputError(path, f"the DEM (EPSG:{info.epsg}) does not cover the whole AOI {aoi}")
    c0, r0 = max(int(np.floor(col.min())), 0), max(int(np.floor(row.min())), 0)
    c1, r1 = min(int(np.ceil(col.max())) + 1, width), min(int(np.ceil(row.max())) + 1, height)
    window = np.asarray(dem[r0:r1, c0:c1], dtype=np.float64)
    valid = window[~info.is_nodata(window) & np.isfinite(window)]
    if valid.size == 0:
        raise InputError(path, f"the DEM has no valid height over the AOI {aoi} (all nodata)")
    margin = float(margin_m)
    if info.vertical_epsg is not None:
        margin += GEOID_UNDULATION_BOUND_M
        log.warning(
            "%s: DEM heights are in vertical CRS EPSG:%d, not above the WGS84 ellipsoid; widening the "
            "altitude margin by %g m to cover the geoid undulation", path, info.vertical_epsg,
            GEOID_UNDULATION_BOUND_M,
        )
    return AltitudeRange(float(valid.min()) - margin, float(valid.max()) + margin)


def altitude_range_from_rpcs(rpcs: Iterable[Any], *, warn: bool = True) -> AltitudeRange:
    """Coarse height range from RPC height offsets/scales: ``offset +- scale``.

    Uses the heights valid for every RPC (their intersection), or all of them (the union) when they
    do not overlap. Logs a warning unless ``warn`` is False: this range is usually far wider than
    the scene's relief, which slows the sweep; give --alt-range or --dem for a tight one (the
    reconstruction narrows it with tie points, ``satsweep.sparse.tiepoints``).
    """
    rpcs = list(rpcs)
    if not rpcs:
        raise OptionsError("no RPC to guess the altitude range from")
    lows = np.array([float(r.alt_offset) - abs(float(r.alt_scale)) for r in rpcs])
    highs = np.array([float(r.alt_offset) + abs(float(r.alt_scale)) for r in rpcs])
    lo, hi = lows.max(), highs.min()
    if not lo < hi:
        lo, hi = lows.min(), highs.max()
    lo, hi = max(lo, ALT_PLAUSIBLE_MIN_M), min(hi, ALT_PLAUSIBLE_MAX_M)
    rng = AltitudeRange(lo, hi)
    if not warn:
        return rng
    log.warning(
        "altitude range %s guessed from the RPC height offset/scale of %d image(s): this is coarse "
        "(give --alt-range MIN MAX or --dem FILE, alt_range= or dem= in the Python API, for a "
        "tighter, faster sweep)", rng, len(rpcs),
    )
    return rng


def resolve_altitude_range(
    *,
    alt_range: AltitudeRange | Sequence[float] | None = None,
    dem: str | os.PathLike | None = None,
    rpcs: Iterable[Any] | None = None,
    aoi: AOI | None = None,
    dem_margin_m: float = DEFAULT_DEM_MARGIN_M,
) -> AltitudeRange:
    """The altitude range to sweep: the user's range, else a DEM's over the AOI, else the RPCs'."""
    if alt_range is not None:
        if isinstance(alt_range, AltitudeRange):
            return alt_range
        values = list(alt_range)
        if len(values) != 2:
            raise AOIError(f"altitude range {alt_range!r}: expected (min, max) in metres")
        return AltitudeRange(*values)
    if dem is not None:
        if aoi is None:
            raise OptionsError(
                f"{os.fspath(dem)}: a DEM gives an altitude range only over an AOI (none given)"
            )
        return altitude_range_from_dem(dem, aoi, dem_margin_m)
    rpcs = list(rpcs) if rpcs is not None else []
    if rpcs:
        return altitude_range_from_rpcs(rpcs)
    raise OptionsError("no altitude range: give --alt-range MIN MAX or --dem FILE (alt_range= or "
                       "dem= in the Python API), or images with RPCs")


def enu_height_range(frame, aoi: AOI, alt_range: AltitudeRange) -> tuple[float, float]:
    """ENU ``u`` range spanned by the AOI cube (the AOI box x the altitude range).

    Earth curvature makes a constant altitude sag below u = alt - alt0 away from the origin
    (about 7 mm at 300 m), so the range is taken over the box's corners and edge midpoints."""
    lons = np.array([aoi.lon_min, aoi.lon_max, aoi.lon_min, aoi.lon_max, aoi.center[0]])
    lats = np.array([aoi.lat_min, aoi.lat_min, aoi.lat_max, aoi.lat_max, aoi.center[1]])
    lo = frame.from_geodetic(lon=lons, lat=lats, alt=np.full(5, alt_range.min))[2]
    hi = frame.from_geodetic(lon=lons, lat=lats, alt=np.full(5, alt_range.max))[2]
    return float(np.min(lo)), float(np.max(hi))
