"""Geodesy: WGS84 geodetic <-> ECEF <-> local ENU, and UTM map coordinates.

Conventions used throughout satsweep:

- lon/lat in degrees (WGS84, EPSG:4326 axis order swapped to lon, lat), heights in metres above
  the WGS84 ellipsoid (ellipsoidal heights, as RPC models use), never above a geoid.
- ECEF is EPSG:4978 (WGS84 geocentric, metres).
- ENU is the local east/north/up frame tangent to the ellipsoid at an origin: an exact rotation of
  ECEF differences (no map projection, no flat-earth approximation).
- UTM is the plain zone of the point (6 degree zones, no Norway/Svalbard exceptions, as S2P and
  CARS do); EPSG 326zz north of the equator, 327zz south of it.

Every function takes keyword arguments, accepts scalars or arrays (broadcast together), works in
float64 and returns float64 arrays of the broadcast shape (0-d for scalar input). The conversions go
through pyproj with local data only (no grid downloads are involved in any of them).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from satsweep.errors import AOIError, OptionsError

# UTM is defined between these latitudes; beyond them UPS applies, which satsweep does not support.
UTM_LAT_MIN = -80.0
UTM_LAT_MAX = 84.0

# EPSG codes: WGS84 geographic 2D (lon/lat), geographic 3D (lon/lat/ellipsoidal height), geocentric.
EPSG_WGS84 = 4326
EPSG_WGS84_3D = 4979
EPSG_ECEF = 4978


@functools.lru_cache(maxsize=None)
def _transformer(src: int, dst: int):
    """A cached pyproj transformer between two EPSG codes with (lon, lat)/(x, y) axis order."""
    import pyproj

    try:
        return pyproj.Transformer.from_crs(src, dst, always_xy=True)
    except pyproj.exceptions.CRSError as exc:
        raise OptionsError(f"EPSG:{src} -> EPSG:{dst}: unknown coordinate reference system ({exc})") from None


def _f64(*arrays) -> list[np.ndarray]:
    """Broadcast the inputs together as float64 arrays."""
    return list(np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays)))


def _run(transformer, *arrays) -> tuple[np.ndarray, ...]:
    """Apply a pyproj transformer to broadcast float64 arrays, keeping the input shape."""
    args = _f64(*arrays)
    shape = args[0].shape
    flat = [np.ascontiguousarray(a).ravel() for a in args]
    out = transformer.transform(*flat, errcheck=False)
    return tuple(np.asarray(o, dtype=np.float64).reshape(shape) for o in out)


# -- geodetic <-> ECEF -------------------------------------------------------------------------
def geodetic_to_ecef(*, lon, lat, alt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS84 lon/lat (degrees) and ellipsoidal height (m) -> ECEF x, y, z (m, EPSG:4978)."""
    return _run(_transformer(EPSG_WGS84_3D, EPSG_ECEF), lon, lat, alt)


def ecef_to_geodetic(*, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF x, y, z (m, EPSG:4978) -> WGS84 lon/lat (degrees) and ellipsoidal height (m).

    PROJ's inverse geocentric conversion is a single Bowring step whose error grows with height
    (about 1e-6 m at 9 km); one fixed-point step of the exact latitude equation
    ``tan(lat) = (z + e2 N sin(lat)) / p`` then brings it to float64 rounding (the step contracts
    the error by about e2 = 0.0067), and the height is taken along the ellipsoid normal.
    """
    x, y, z = _f64(x, y, z)
    lon, lat, _ = _run(_transformer(EPSG_ECEF, EPSG_WGS84_3D), x, y, z)
    a, e2 = _wgs84_a_e2()
    p = np.hypot(x, y)
    s = np.sin(np.radians(lat))
    n = a / np.sqrt(1.0 - e2 * s * s)
    phi = np.arctan2(z + e2 * n * s, p)
    s, c = np.sin(phi), np.cos(phi)
    # Distance along the normal through (p, z): exact for any latitude, poles included.
    alt = p * c + z * s - a * np.sqrt(1.0 - e2 * s * s)
    return lon, np.degrees(phi), alt


@functools.lru_cache(maxsize=None)
def _wgs84_a_e2() -> tuple[float, float]:
    """WGS84 semi-major axis (m) and first eccentricity squared, as PROJ defines them."""
    import pyproj

    ell = pyproj.CRS.from_epsg(EPSG_WGS84).ellipsoid
    f = 1.0 / ell.inverse_flattening
    return float(ell.semi_major_metre), f * (2.0 - f)


# -- local ENU frame ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ENUFrame:
    """Local east/north/up frame (metres) with its origin at (lon0, lat0, alt0).

    ``enu = R @ (ecef - ecef(origin))`` with the standard rotation
    ``R = [[-sin(lon), cos(lon), 0], [-sin(lat)cos(lon), -sin(lat)sin(lon), cos(lat)],
    [cos(lat)cos(lon), cos(lat)sin(lon), sin(lat)]]`` (geodetic lon/lat of the origin), so the
    frame is exact at any distance: "up" is the ellipsoid normal at the origin only.
    """

    lon0: float  # origin longitude, degrees
    lat0: float  # origin latitude, degrees
    alt0: float  # origin height above the WGS84 ellipsoid, metres

    def __post_init__(self) -> None:
        for name in ("lon0", "lat0", "alt0"):
            if not math.isfinite(getattr(self, name)):
                raise AOIError(f"ENUFrame.{name} = {getattr(self, name)!r}: must be finite")
        if not -90.0 <= self.lat0 <= 90.0:
            raise AOIError(f"ENUFrame.lat0 = {self.lat0!r}: must lie in [-90, 90] degrees")

    @functools.cached_property
    def rotation(self) -> np.ndarray:
        """3x3 matrix taking ECEF differences to (east, north, up)."""
        lon, lat = math.radians(self.lon0), math.radians(self.lat0)
        so, co, sa, ca = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
        return np.array(
            [[-so, co, 0.0], [-sa * co, -sa * so, ca], [ca * co, ca * so, sa]], dtype=np.float64
        )

    @functools.cached_property
    def origin_ecef(self) -> np.ndarray:
        """ECEF coordinates (m) of the origin, shape (3,)."""
        return np.array([float(v) for v in geodetic_to_ecef(lon=self.lon0, lat=self.lat0, alt=self.alt0)])

    def from_ecef(self, *, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ECEF x, y, z (m) -> east, north, up (m) in this frame."""
        x, y, z = _f64(x, y, z)
        o, r = self.origin_ecef, self.rotation
        dx, dy, dz = x - o[0], y - o[1], z - o[2]
        return tuple(r[i, 0] * dx + r[i, 1] * dy + r[i, 2] * dz for i in range(3))

    def to_ecef(self, *, e, n, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East, north, up (m) in this frame -> ECEF x, y, z (m)."""
        e, n, u = _f64(e, n, u)
        o, r = self.origin_ecef, self.rotation
        # R is orthonormal: its inverse is its transpose.
        return tuple(o[i] + r[0, i] * e + r[1, i] * n + r[2, i] * u for i in range(3))

    def from_geodetic(self, *, lon, lat, alt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """WGS84 lon/lat (degrees), ellipsoidal height (m) -> east, north, up (m)."""
        x, y, z = geodetic_to_ecef(lon=lon, lat=lat, alt=alt)
        return self.from_ecef(x=x, y=y, z=z)

    def to_geodetic(self, *, e, n, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East, north, up (m) -> WGS84 lon/lat (degrees), ellipsoidal height (m)."""
        x, y, z = self.to_ecef(e=e, n=n, u=u)
        return ecef_to_geodetic(x=x, y=y, z=z)


# -- UTM ---------------------------------------------------------------------------------------
def utm_zone(*, lon: float) -> int:
    """UTM zone number 1..60 of a longitude in degrees (180 E falls in zone 1, like 180 W)."""
    lon = float(lon)
    if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise AOIError(f"lon = {lon!r}: must lie in [-180, 180] degrees")
    return int(math.floor((lon + 180.0) / 6.0)) % 60 + 1


def utm_epsg(*, lon: float, lat: float) -> int:
    """EPSG code of the WGS84 UTM zone holding the point: 32600 + zone north, 32700 + zone south.

    The equator (lat = 0) counts as north. Raises AOIError beyond UTM's latitudes (80 S .. 84 N).
    """
    lat = float(lat)
    if not (math.isfinite(lat) and UTM_LAT_MIN <= lat <= UTM_LAT_MAX):
        raise AOIError(
            f"lat = {lat!r}: outside UTM's range {UTM_LAT_MIN:g}..{UTM_LAT_MAX:g} degrees "
            "(polar stereographic grids are not supported)"
        )
    return (32600 if lat >= 0.0 else 32700) + utm_zone(lon=lon)


def lonlat_to_utm(*, lon, lat, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 lon/lat (degrees) -> easting, northing (m) in the UTM (or other projected) ``epsg``."""
    return lonlat_to_crs(lon=lon, lat=lat, epsg=epsg)


def utm_to_lonlat(*, x, y, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """Easting, northing (m) in the UTM (or other projected) ``epsg`` -> WGS84 lon/lat (degrees)."""
    return crs_to_lonlat(x=x, y=y, epsg=epsg)


def lonlat_to_crs(*, lon, lat, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 lon/lat (degrees) -> (x, y) in any EPSG CRS, x first (lon first for geographic)."""
    return _run(_transformer(EPSG_WGS84, int(epsg)), lon, lat)


def crs_to_lonlat(*, x, y, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) in any EPSG CRS, x first (lon first for geographic) -> WGS84 lon/lat (degrees)."""
    return _run(_transformer(int(epsg), EPSG_WGS84), x, y)
