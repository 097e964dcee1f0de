"""Area of interest (a lon/lat box) and the altitude range that the sweep covers.

The AOI is a WGS84 lon/lat bounding box in degrees, given on the command line as
``LON_MIN,LAT_MIN,LON_MAX,LAT_MAX`` or as a GeoJSON file (RFC 7946: WGS84 lon/lat; the box of all
polygon coordinates is used). Boxes that cross the antimeridian are not supported.

The altitude range (metres above the WGS84 ellipsoid) bounds the heights the plane sweep tries.
``resolve_altitude_range`` takes, in this order: a range the user gives, a DEM the user gives
(heights over the AOI plus a margin), or a coarse guess from the RPC height offset/scale.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from typing import Any, Iterable, Sequence

import numpy as np

from .errors import AOIError, InputError, OptionsError

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

# Points per AOI side when its boundary is transformed to another CRS or projected into an image:
# RPC and map projections bend straight lon/lat edges slightly, so edges are sampled, not just
# their ends.
BOUNDARY_POINTS_PER_SIDE = 9

# A box wider than this in longitude is taken to be a polygon crossing the antimeridian.
ANTIMERIDIAN_SPAN_DEG = 180.0


@dataclasses.dataclass(frozen=True)
class AOI:
    """A WGS84 lon/lat box in degrees; validated on construction (AOIError)."""

    lon_min: float  # west edge, degrees in [-180, 180]
    lat_min: float  # south edge, degrees in [-90, 90]
    lon_max: float  # east edge, degrees, > lon_min
    lat_max: float  # north edge, degrees, > lat_min

    def __post_init__(self) -> None:
        for name in ("lon_min", "lat_min", "lon_max", "lat_max"):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise AOIError(f"AOI {name} = {value!r}: not a number") from None
            if not math.isfinite(value):
                raise AOIError(f"AOI {name} = {value!r}: must be finite")
            object.__setattr__(self, name, value)
        for name in ("lon_min", "lon_max"):
            if not -180.0 <= getattr(self, name) <= 180.0:
                raise AOIError(
                    f"AOI {name} = {getattr(self, name)!r}: longitude must lie in [-180, 180] degrees"
                )
        for name in ("lat_min", "lat_max"):
            if not -90.0 <= getattr(self, name) <= 90.0:
                raise AOIError(
                    f"AOI {name} = {getattr(self, name)!r}: latitude must lie in [-90, 90] degrees"
                )
        if not self.lon_min < self.lon_max:
            raise AOIError(
                f"AOI lon_min = {self.lon_min!r} >= lon_max = {self.lon_max!r}: "
                "expected LON_MIN,LAT_MIN,LON_MAX,LAT_MAX with min < max"
            )
        if not self.lat_min < self.lat_max:
            raise AOIError(
                f"AOI lat_min = {self.lat_min!r} >= lat_max = {self.lat_max!r}: "
                "expected LON_MIN,LAT_MIN,LON_MAX,LAT_MAX with min < max"
            )

    @property
    def center(self) -> tuple[float, float]:
        """(lon, lat) of the box centre, degrees."""
        return 0.5 * (self.lon_min + self.lon_max), 0.5 * (self.lat_min + self.lat_max)

    def corners(self) -> tuple[tuple[float, float], ...]:
        """The four (lon, lat) corners, counter-clockwise from the south-west: SW, SE, NE, NW."""
        return (
            (self.lon_min, self.lat_min),
            (self.lon_max, self.lat_min),
            (self.lon_max, self.lat_max),
            (self.lon_min, self.lat_max),
        )

    def boundary(self, points_per_side: int = BOUNDARY_POINTS_PER_SIDE) -> tuple[np.ndarray, np.ndarray]:
        """(lon, lat) arrays of points along the box edges, corners included, counter-clockwise."""
        t = np.linspace(0.0, 1.0, max(int(points_per_side), 2))[:-1]
        c = np.array(self.corners() + (self.corners()[0],), dtype=np.float64)
        pts = np.concatenate([c[i] + t[:, None] * (c[i + 1] - c[i]) for i in range(4)])
        return pts[:, 0], pts[:, 1]

    def to_geojson(self) -> dict[str, Any]:
        """The box as a GeoJSON Polygon (RFC 7946: closed counter-clockwise exterior ring)."""
        ring = [list(p) for p in self.corners()]
        return {"type": "Polygon", "coordinates": [ring + [ring[0]]]}

    def contains(self, *, lon, lat) -> np.ndarray:
        """Boolean mask of the points inside the box (edges included)."""
        lon, lat = np.asarray(lon, np.float64), np.asarray(lat, np.float64)
        return (lon >= self.lon_min) & (lon <= self.lon_max) & (lat >= self.lat_min) & (lat <= self.lat_max)

    @property
    def width_m(self) -> float:
        """East-west size in metres along the centre latitude (geodesic on WGS84)."""
        import pyproj

        lat = self.center[1]
        return float(pyproj.Geod(ellps="WGS84").line_length([self.lon_min, self.lon_max], [lat, lat]))

    @property
    def height_m(self) -> float:
        """North-south size in metres along the centre meridian (geodesic on WGS84)."""
        import pyproj

        lon = self.center[0]
        return float(pyproj.Geod(ellps="WGS84").line_length([lon, lon], [self.lat_min, self.lat_max]))

    def utm_epsg(self) -> int:
        """EPSG code of the UTM zone of the box centre."""
        from .geo import utm_epsg

        lon, lat = self.center
        return utm_epsg(lon=lon, lat=lat)

    def __str__(self) -> str:
        return f"{self.lon_min!r},{self.lat_min!r},{self.lon_max!r},{self.lat_max!r}"


# -- parsing -----------------------------------------------------------------------------------
_AOI_FORMS = "LON_MIN,LAT_MIN,LON_MAX,LAT_MAX (degrees) or a GeoJSON file"
_POLYGON_TYPES = ("Polygon", "MultiPolygon")


def parse_aoi(spec: str | os.PathLike) -> AOI:
    """Parse ``LON_MIN,LAT_MIN,LON_MAX,LAT_MAX`` or a GeoJSON file into an AOI.

    A GeoJSON file may hold a Polygon or MultiPolygon geometry, a Feature, a FeatureCollection or a
    GeometryCollection; the AOI is the bounding box of all polygon coordinates. Malformed GeoJSON
    raises InputError naming the file; a malformed number list raises AOIError.
    """
    text = os.fspath(spec)
    parts = [p.strip() for p in text.split(",")]
    if len(parts) == 4 and not os.path.exists(text):
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise AOIError(f"AOI {text!r}: expected {_AOI_FORMS}") from None
        return AOI(*values)
    if os.path.isfile(text):
        return _aoi_from_geojson(text)
    if "," in text:
        raise AOIError(f"AOI {text!r}: expected {_AOI_FORMS}")
    raise InputError(text, f"no such file (the AOI must be {_AOI_FORMS})")


def _aoi_from_geojson(path: str) -> AOI:
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except UnicodeDecodeError:
        raise InputError(path, "not a GeoJSON file (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise InputError(
            path, f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror})") from None
    _check_geojson_crs(path, doc)
    positions: list[np.ndarray] = []
    _collect_polygons(path, doc, positions, where="top level")
    if not positions:
        raise InputError(path, "GeoJSON holds no Polygon or MultiPolygon coordinates")
    xy = np.concatenate(positions)
    lon_min, lat_min = xy.min(axis=0)
    lon_max, lat_max = xy.max(axis=0)
    if lon_min < -180.0 or lon_max > 180.0 or lat_min < -90.0 or lat_max > 90.0:
        raise InputError(
            path, f"coordinates span x {lon_min:g}..{lon_max:g}, y {lat_min:g}..{lat_max:g}: not WGS84 "
                  "lon/lat degrees (RFC 7946 GeoJSON is lon/lat; reproject it, e.g. ogr2ogr -t_srs EPSG:4326)"
        )
    if lon_max - lon_min > ANTIMERIDIAN_SPAN_DEG:
        raise InputError(path, "the polygon spans more than 180 degrees of longitude (crossing the "
                               "antimeridian is not supported: split the AOI)")
    try:
        return AOI(lon_min, lat_min, lon_max, lat_max)
    except AOIError as exc:
        raise InputError(
            path, f"bad GeoJSON AOI: {exc} (RFC 7946 GeoJSON is WGS84 lon/lat degrees)"
        ) from None


def _check_geojson_crs(path: str, doc: Any) -> None:
    """Reject the obsolete GeoJSON 2008 ``crs`` member unless it names WGS84 lon/lat."""
    if not isinstance(doc, dict) or "crs" not in doc or doc["crs"] is None:
        return
    crs = doc["crs"]
    name = crs.get("properties", {}).get("name", "") if isinstance(crs, dict) else ""
    if not isinstance(name, str):
        name = repr(name)
    if not any(tag in name.upper() for tag in ("CRS84", "EPSG::4326", "EPSG:4326")):
        raise InputError(
            path, f"GeoJSON declares crs {name or crs!r}: coordinates must be WGS84 lon/lat (RFC 7946)"
        )


def _collect_polygons(path: str, obj: Any, out: list[np.ndarray], *, where: str) -> None:
    """Append (n, 2) lon/lat arrays of every polygon ring found in a GeoJSON object."""
    if not isinstance(obj, dict) or not isinstance(obj.get("type"), str):
        raise InputError(path, f"GeoJSON {where}: expected an object with a \"type\" member")
    kind = obj["type"]
    if kind == "FeatureCollection":
        features = obj.get("features")
        if not isinstance(features, list):
            raise InputError(path, "GeoJSON FeatureCollection: \"features\" must be a list")
        for i, feature in enumerate(features):
            _collect_polygons(path, feature, out, where=f"feature {i}")
    elif kind == "Feature":
        if "geometry" not in obj:
            raise InputError(path, f"GeoJSON {where}: Feature without a \"geometry\" member")
        if obj["geometry"] is not None:  # RFC 7946: unlocated features have a null geometry
            _collect_polygons(path, obj["geometry"], out, where=f"{where} geometry")
    elif kind == "GeometryCollection":
        geometries = obj.get("geometries")
        if not isinstance(geometries, list):
            raise InputError(path, f"GeoJSON {where}: \"geometries\" must be a list")
        for i, geometry in enumerate(geometries):
            _collect_polygons(path, geometry, out, where=f"{where} geometry {i}")
    elif kind in _POLYGON_TYPES:
        depth = 2 if kind == "Polygon" else 3
        _collect_positions(path, obj.get("coordinates"), depth, out, where=f"{where} {kind}")
    elif kind in ("Point", "MultiPoint", "LineString", "MultiLineString"):
        raise InputError(
            path, f"GeoJSON {where}: a {kind} does not bound an area (need Polygon or MultiPolygon)"
        )
    else:
        raise InputError(path, f"GeoJSON {where}: unknown type {kind!r}")


def _collect_positions(path: str, coords: Any, depth: int, out: list[np.ndarray], *, where: str) -> None:
    """Walk ``depth`` levels of nested lists down to rings of [lon, lat(, alt)] positions."""
    if not isinstance(coords, list):
        raise InputError(path, f"GeoJSON {where}: \"coordinates\" must be nested lists")
    if depth > 1:
        for c in coords:
            _collect_positions(path, c, depth - 1, out, where=where)
        return
    for position in coords:
        if (
            not isinstance(position, list)
            or len(position) < 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in position)
        ):
            raise InputError(path, f"GeoJSON {where}: bad position {position!r} (expected [lon, lat])")
    if coords:
        xy = np.array([p[:2] for p in coords], dtype=np.float64)
        if not np.isfinite(xy).all():
            raise InputError(path, f"GeoJSON {where}: non-finite coordinate")
        out.append(xy)


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
    from .geo import lonlat_to_crs
    from .imageio import read_geotiff

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
    reconstruction narrows it with tie points, ``satsweep.tiepoints``).
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
        "(pass --alt-range MIN,MAX or --dem FILE for a tighter, faster sweep)", rng, len(rpcs),
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
    raise OptionsError("no altitude range: pass --alt-range MIN,MAX, --dem FILE, or images with RPCs")
