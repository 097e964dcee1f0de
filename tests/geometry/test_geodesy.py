"""Geodesy: geodetic/ECEF/ENU/UTM conversions against closed forms and PROJ's own operations."""

from __future__ import annotations

import math

import numpy as np
import pyproj
import pytest

from satsweep.errors import AOIError
from satsweep.geometry import geodesy as geo

# Round trips must hold to a micrometre (what the brief requires; float64 allows ~1e-9 m at
# Earth-radius magnitudes, so this leaves three orders of magnitude for the algorithms).
ROUND_TRIP_TOL_M = 1e-6
# Closed-form ECEF from the ellipsoid formula vs PROJ: both exact up to float64 rounding of
# ~6.4e6 m values (about 1e-9 m), so a micrometre is generous.
CLOSED_FORM_TOL_M = 1e-6
# Our ENU rotation vs PROJ's +proj=topocentric: same exact maths, different code paths.
TOPOCENTRIC_TOL_M = 1e-6
# Metres per degree bound used to turn angle differences into distances (Earth's radius).
EARTH_RADIUS_M = 6.4e6

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def _angle_error_m(dlon_deg, dlat_deg, lat_deg):
    """Ground distance (upper bound) of small lon/lat differences, metres."""
    dlon = (np.asarray(dlon_deg) + 180.0) % 360.0 - 180.0
    return EARTH_RADIUS_M * np.radians(
        np.hypot(dlat_deg, dlon * np.cos(np.radians(lat_deg)))
    )


def _random_geodetic(rng, n):
    lon = rng.uniform(-180.0, 180.0, n)
    lat = rng.uniform(-90.0, 90.0, n)
    alt = rng.uniform(-500.0, 9000.0, n)
    # Include the awkward places: poles, equator, antimeridian.
    lat[:6] = [90.0, -90.0, 0.0, 89.999999, -89.999999, 1e-12]
    lon[:6] = [180.0, -180.0, 0.0, 179.999999, -179.999999, 0.0]
    return lon, lat, alt


def test_geodetic_ecef_round_trip():
    rng = np.random.default_rng(1)
    lon, lat, alt = _random_geodetic(rng, 20000)
    x, y, z = geo.geodetic_to_ecef(lon=lon, lat=lat, alt=alt)
    lon2, lat2, alt2 = geo.ecef_to_geodetic(x=x, y=y, z=z)
    assert np.abs(alt2 - alt).max() < ROUND_TRIP_TOL_M
    # Longitude is meaningless at the poles: compare positions there through ECEF instead.
    x2, y2, z2 = geo.geodetic_to_ecef(lon=lon2, lat=lat2, alt=alt2)
    assert np.sqrt((x2 - x) ** 2 + (y2 - y) ** 2 + (z2 - z) ** 2).max() < ROUND_TRIP_TOL_M
    assert _angle_error_m(lon2 - lon, lat2 - lat, lat).max() < ROUND_TRIP_TOL_M


def test_geodetic_to_ecef_matches_closed_form():
    rng = np.random.default_rng(2)
    lon, lat, alt = _random_geodetic(rng, 1000)
    phi, lam = np.radians(lat), np.radians(lon)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(phi) ** 2)
    expected = (
        (n + alt) * np.cos(phi) * np.cos(lam),
        (n + alt) * np.cos(phi) * np.sin(lam),
        (n * (1.0 - WGS84_E2) + alt) * np.sin(phi),
    )
    got = geo.geodetic_to_ecef(lon=lon, lat=lat, alt=alt)
    for g, e in zip(got, expected):
        assert np.abs(g - e).max() < CLOSED_FORM_TOL_M


def test_ecef_special_points():
    b = WGS84_A * (1.0 - WGS84_F)
    x, y, z = geo.geodetic_to_ecef(lon=0.0, lat=0.0, alt=0.0)
    assert abs(x - WGS84_A) < CLOSED_FORM_TOL_M and abs(y) < CLOSED_FORM_TOL_M and abs(z) < CLOSED_FORM_TOL_M
    lon, lat, alt = geo.ecef_to_geodetic(x=0.0, y=0.0, z=-(b + 1234.5))
    assert lat == pytest.approx(-90.0, abs=1e-12)
    assert abs(alt - 1234.5) < ROUND_TRIP_TOL_M


def test_shapes_broadcast_and_dtype():
    lon = np.full((3, 4), 55.65)
    lat = np.linspace(-21.3, -21.2, 4)
    x, y, z = geo.geodetic_to_ecef(lon=lon, lat=lat, alt=2340)
    assert x.shape == y.shape == z.shape == (3, 4)
    assert x.dtype == np.float64
    e, n, u = geo.ENUFrame(55.65, -21.25, 2340.0).from_geodetic(lon=lon, lat=lat, alt=2340)
    assert e.shape == (3, 4)
    ux, uy = geo.lonlat_to_utm(lon=lon, lat=lat, epsg=32740)
    assert ux.shape == (3, 4)


ENU_ORIGINS = [(55.65, -21.23, 2340.0), (-122.4, 37.8, -30.0), (0.0, 0.0, 0.0), (179.99, 71.0, 8000.0)]


@pytest.mark.parametrize("origin", ENU_ORIGINS)
def test_enu_round_trip(origin):
    frame = geo.ENUFrame(*origin)
    rng = np.random.default_rng(3)
    e = rng.uniform(-5000.0, 5000.0, 5000)
    n = rng.uniform(-5000.0, 5000.0, 5000)
    # Altitudes -500..9000 m above the ellipsoid: up is measured from the origin's height.
    u = rng.uniform(-500.0, 9000.0, 5000) - origin[2]
    lon, lat, alt = frame.to_geodetic(e=e, n=n, u=u)
    e2, n2, u2 = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
    err = np.sqrt((e2 - e) ** 2 + (n2 - n) ** 2 + (u2 - u) ** 2)
    assert err.max() < ROUND_TRIP_TOL_M


@pytest.mark.parametrize("origin", ENU_ORIGINS)
def test_enu_matches_proj_topocentric(origin):
    lon0, lat0, alt0 = origin
    proj = pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lon_0={lon0!r} +lat_0={lat0!r} +h_0={alt0!r}"
    )
    rng = np.random.default_rng(4)
    lon = lon0 + rng.uniform(-0.05, 0.05, 500)
    lat = np.clip(lat0 + rng.uniform(-0.05, 0.05, 500), -90.0, 90.0)
    alt = rng.uniform(-500.0, 9000.0, 500)
    expected = proj.transform(lon, lat, alt)
    got = geo.ENUFrame(lon0, lat0, alt0).from_geodetic(lon=lon, lat=lat, alt=alt)
    for g, x in zip(got, expected):
        assert np.abs(g - np.asarray(x)).max() < TOPOCENTRIC_TOL_M


def test_enu_hand_cases():
    # At (lon0, lat0) = (0, 0): east is +y, north is +z, up is +x of ECEF.
    frame = geo.ENUFrame(0.0, 0.0, 0.0)
    e, n, u = frame.from_ecef(x=WGS84_A + 10.0, y=20.0, z=30.0)
    assert (float(e), float(n), float(u)) == pytest.approx((20.0, 30.0, 10.0), abs=CLOSED_FORM_TOL_M)
    # At lon0 = 90 E on the equator, east is -x of ECEF.
    frame = geo.ENUFrame(90.0, 0.0, 0.0)
    e, n, u = frame.from_ecef(x=-7.0, y=WGS84_A, z=0.0)
    assert (float(e), float(n), float(u)) == pytest.approx((7.0, 0.0, 0.0), abs=CLOSED_FORM_TOL_M)
    # The origin maps to zero, and straight up stays straight up.
    frame = geo.ENUFrame(55.65, -21.23, 2340.0)
    e, n, u = frame.from_geodetic(lon=55.65, lat=-21.23, alt=[2340.0, 3340.0])
    np.testing.assert_allclose(e, 0.0, atol=CLOSED_FORM_TOL_M)
    np.testing.assert_allclose(n, 0.0, atol=CLOSED_FORM_TOL_M)
    np.testing.assert_allclose(u, [0.0, 1000.0], atol=CLOSED_FORM_TOL_M)
    r = frame.rotation
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-15)


def test_enu_rejects_bad_origin():
    with pytest.raises(AOIError, match="lat0"):
        geo.ENUFrame(0.0, 91.0, 0.0)
    with pytest.raises(AOIError, match="alt0"):
        geo.ENUFrame(0.0, 0.0, float("nan"))


def _pyproj_utm_epsg(lon, lat):
    """Independent oracle: the WGS84 UTM CRSs whose EPSG area of use holds the point."""
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    infos = query_utm_crs_info(
        datum_name="WGS 84",
        area_of_interest=AreaOfInterest(lon, lat, lon, lat),
    )
    return {int(i.code) for i in infos if i.code.startswith(("326", "327"))}


def test_utm_epsg_matches_proj_areas_of_use():
    rng = np.random.default_rng(5)
    lons = rng.uniform(-179.9, 179.9, 10)
    lats = rng.uniform(-79.9, 83.9, 10)
    checked = 0
    for lon, lat in zip(lons, lats):
        # Stay off zone and hemisphere borders, where two zones' areas of use touch.
        if abs((lon + 180.0) % 6.0 - 3.0) > 2.9 or abs(lat) < 0.1:
            continue
        assert geo.utm_epsg(lon=lon, lat=lat) in _pyproj_utm_epsg(lon, lat)
        checked += 1
    assert checked >= 5


@pytest.mark.parametrize(
    "lon, lat, epsg",
    [
        (55.65, -21.23, 32740),  # La Reunion, the shared Pleiades pair
        (2.35, 48.85, 32631),  # Paris
        (-180.0, 10.0, 32601),
        (180.0, 10.0, 32601),  # 180 E is the same meridian as 180 W
        (6.0, 0.0, 32632),  # zone borders belong to the eastern zone; the equator is north
        (-0.000001, -0.000001, 32730),
    ],
)
def test_utm_epsg_hand_cases(lon, lat, epsg):
    assert geo.utm_epsg(lon=lon, lat=lat) == epsg


@pytest.mark.parametrize("lon, lat", [(0.0, 85.0), (0.0, -80.5), (181.0, 0.0), (float("nan"), 0.0)])
def test_utm_epsg_rejects_out_of_range(lon, lat):
    with pytest.raises(AOIError):
        geo.utm_epsg(lon=lon, lat=lat)


# UTM northing on the central meridian is k0 times the meridian arc: compared with pyproj.Geod
# (Karney's geodesics, a different algorithm than the transverse Mercator series) to a millimetre.
UTM_TOL_M = 1e-3


def test_utm_against_meridian_arc_and_round_trip():
    geod = pyproj.Geod(ellps="WGS84")
    lats = np.array([0.0, 10.0, 45.0, 70.0])
    x, y = geo.lonlat_to_utm(lon=57.0, lat=lats, epsg=32640)  # 57 E: central meridian of zone 40
    arcs = np.array([geod.line_length([57.0, 57.0], [0.0, la]) for la in lats])
    np.testing.assert_allclose(x, 500000.0, atol=UTM_TOL_M)
    np.testing.assert_allclose(y, 0.9996 * arcs, atol=UTM_TOL_M)
    # Southern zones add a false northing of 10 000 km.
    xs, ys = geo.lonlat_to_utm(lon=57.0, lat=-lats[1:], epsg=32740)
    np.testing.assert_allclose(ys, 10_000_000.0 - 0.9996 * arcs[1:], atol=UTM_TOL_M)
    rng = np.random.default_rng(6)
    lon = rng.uniform(52.0, 60.0, 1000)
    lat = rng.uniform(-30.0, -10.0, 1000)
    ux, uy = geo.lonlat_to_utm(lon=lon, lat=lat, epsg=32740)
    lon2, lat2 = geo.utm_to_lonlat(x=ux, y=uy, epsg=32740)
    assert _angle_error_m(lon2 - lon, lat2 - lat, lat).max() < ROUND_TRIP_TOL_M


def test_unknown_epsg_is_an_options_error():
    from satsweep.errors import OptionsError

    with pytest.raises(OptionsError, match="EPSG:1"):
        geo.lonlat_to_utm(lon=0.0, lat=0.0, epsg=1)


def test_geodetic_scalars_give_floats_usable_as_numbers():
    x, y, z = geo.geodetic_to_ecef(lon=10.0, lat=20.0, alt=30.0)
    assert math.isfinite(float(x)) and np.ndim(x) == 0
