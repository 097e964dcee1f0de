"""Area of interest: a lon/lat box, from the command line or a GeoJSON file.

The AOI is a WGS84 lon/lat bounding box in degrees, given on the command line as
``LON_MIN,LAT_MIN,LON_MAX,LAT_MAX`` or as a GeoJSON file (RFC 7946: WGS84 lon/lat; the box of all
polygon coordinates is used; a file with the older ``crs`` member naming an EPSG code, as GDAL
and QGIS write for a projected layer, is mapped to lon/lat first). Boxes that cross the
antimeridian are not supported.

The altitude range swept over it is :mod:`satsweep.geometry.altitude`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from typing import Any

import numpy as np

from satsweep.errors import AOIError, InputError, OptionsError

log = logging.getLogger(__name__)

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

    def grown_to(self, side_m: float) -> "AOI":
        """The box about the same centre whose sides are at least ``side_m`` metres (each side
        as it is when already longer), within the valid latitudes and longitudes."""
        lon, lat = self.center
        half_lon, half_lat = 0.5 * (self.lon_max - self.lon_min), 0.5 * (self.lat_max - self.lat_min)
        grow_lon = max(1.0, float(side_m) / max(self.width_m, 1e-9))
        grow_lat = max(1.0, float(side_m) / max(self.height_m, 1e-9))
        if grow_lon == 1.0 and grow_lat == 1.0:
            return self
        lons = ((self.lon_min, self.lon_max) if grow_lon == 1.0 else
                (max(lon - grow_lon * half_lon, -180.0), min(lon + grow_lon * half_lon, 180.0)))
        lats = ((self.lat_min, self.lat_max) if grow_lat == 1.0 else
                (max(lat - grow_lat * half_lat, -90.0), min(lat + grow_lat * half_lat, 90.0)))
        return AOI(lons[0], lats[0], lons[1], lats[1])

    def utm_epsg(self) -> int:
        """EPSG code of the UTM zone of the box centre."""
        from satsweep.geometry.geodesy import utm_epsg

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
    GeometryCollection; the AOI is the bounding box of all polygon coordinates (in lon/lat: a
    GeoJSON 2008 ``crs`` member naming an EPSG code maps them there first, each edge sampled).
    Malformed GeoJSON raises InputError naming the file; a malformed number list raises
    AOIError.
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
    epsg = _geojson_crs_epsg(path, doc)
    positions: list[np.ndarray] = []
    _collect_polygons(path, doc, positions, where="top level")
    if not positions:
        raise InputError(path, "GeoJSON holds no Polygon or MultiPolygon coordinates")
    if epsg is not None:  # a projected CRS (GeoJSON 2008, as GDAL writes it): to lon/lat
        positions = [_ring_to_lonlat(path, ring, epsg) for ring in positions]
    if len(positions) > 1 or not _is_box(positions[0]):
        log.warning("%s: the AOI is the lon/lat bounding box of its %d polygon ring(s); the DSM "
                    "covers the whole box", path, len(positions))
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


def _is_box(ring: np.ndarray) -> bool:
    """Whether a polygon ring is its own lon/lat bounding box: its area (shoelace) is the box's."""
    x, y = ring[:, 0] - ring[:, 0].mean(), ring[:, 1] - ring[:, 1].mean()  # no cancellation
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    box = float(np.ptp(x) * np.ptp(y))
    return box > 0.0 and abs(area - box) <= 1e-9 * box


def _geojson_crs_epsg(path: str, doc: Any) -> int | None:
    """The EPSG code of the obsolete GeoJSON 2008 ``crs`` member (a named CRS, as GDAL writes
    for a layer that is not in WGS84: ``urn:ogc:def:crs:EPSG::32631`` or ``EPSG:32631``); None
    without one or for WGS84 lon/lat (RFC 7946's only CRS). InputError for any other form."""
    if not isinstance(doc, dict) or "crs" not in doc or doc["crs"] is None:
        return None
    crs = doc["crs"]
    name = crs.get("properties", {}).get("name", "") if isinstance(crs, dict) else ""
    if not isinstance(name, str):
        name = repr(name)
    upper = name.upper().strip()
    if "CRS84" in upper or upper.endswith(("EPSG::4326", "EPSG:4326")):
        return None
    code = upper.rsplit(":", 1)[-1] if "EPSG:" in upper else ""
    if not code.isdigit():
        raise InputError(
            path, f"GeoJSON declares crs {name or crs!r}: expected a named EPSG code "
                  "(urn:ogc:def:crs:EPSG::NNNN) or WGS84 lon/lat (RFC 7946)")
    return int(code)


# Points per edge of a polygon ring in a projected CRS when it is mapped to lon/lat: a straight
# edge there is a curve in lon/lat, whose bounding box its vertices alone may miss.
GEOJSON_EDGE_SAMPLES = 32


def _ring_to_lonlat(path: str, ring: np.ndarray, epsg: int) -> np.ndarray:
    """A polygon ring of a projected CRS (EPSG ``epsg``) as (n, 2) lon/lat, each edge sampled
    at GEOJSON_EDGE_SAMPLES points."""
    from satsweep.geometry.geodesy import crs_to_lonlat

    t = np.linspace(0.0, 1.0, GEOJSON_EDGE_SAMPLES, endpoint=False)
    a, b = ring, np.roll(ring, -1, axis=0)
    xy = (a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]).reshape(-1, 2)
    try:
        lon, lat = crs_to_lonlat(x=xy[:, 0], y=xy[:, 1], epsg=epsg)
    except OptionsError as exc:
        raise InputError(path, f"GeoJSON crs EPSG:{epsg}: {exc}") from None
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        raise InputError(path, f"GeoJSON coordinates do not map from EPSG:{epsg} to lon/lat "
                               "(outside the CRS's area?)")
    return np.stack([lon, lat], axis=1)


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
