"""AOI parsing/validation and altitude ranges (user range, DEM, RPC guess)."""

from __future__ import annotations

import json
import logging
import math
import types

import numpy as np
import pyproj
import pytest
import rasterio
import tifffile

from satsweep.errors import AOIError, InputError, OptionsError
from satsweep.geometry import altitude
from satsweep.geometry import aoi as saoi
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.io.geotiff import write_geotiff

WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3
# Small boxes: the meridian-arc closed form M * dlat is exact to O(dlat^2) relative; 1e-6 covers it.
SIZE_REL_TOL = 1e-6
# A UTM box's lon/lat bounds from 32 samples per edge against 1001: the edges' curvature over
# 300 m is far below a micro-degree (0.1 m), and the bound is one.
UTM_BOX_TOLERANCE_DEG = 1e-6


# -- AOI ---------------------------------------------------------------------------------------
def test_aoi_properties():
    box = AOI(55.64, -21.24, 55.66, -21.22)
    assert box.center == pytest.approx((55.65, -21.23), abs=1e-12)
    assert box.corners() == ((55.64, -21.24), (55.66, -21.24), (55.66, -21.22), (55.64, -21.22))
    gj = box.to_geojson()
    assert gj["type"] == "Polygon"
    ring = gj["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 5
    # RFC 7946 exterior rings are counter-clockwise: positive shoelace area.
    xy = np.array(ring)
    assert np.sum(xy[:-1, 0] * xy[1:, 1] - xy[1:, 0] * xy[:-1, 1]) > 0
    assert json.loads(json.dumps(gj)) == gj
    inside = box.contains(lon=[55.65, 55.63, 55.66], lat=[-21.23, -21.23, -21.22])
    np.testing.assert_array_equal(inside, [True, False, True])
    assert box.utm_epsg() == 32740


def test_aoi_boundary_contains_corners_and_stays_on_edges():
    box = AOI(10.0, 20.0, 10.5, 20.25)
    lon, lat = box.boundary()
    pts = set(zip(lon.tolist(), lat.tolist()))
    assert all(c in pts for c in box.corners())
    on_edge = np.isclose(lon, 10.0) | np.isclose(lon, 10.5) | np.isclose(lat, 20.0) | np.isclose(lat, 20.25)
    assert on_edge.all() and len(lon) > 4


def test_aoi_size_in_metres():
    # On the equator the east-west line is the equator itself: width = a * dlon.
    box = AOI(10.0, -0.0005, 10.001, 0.0005)
    assert box.width_m == pytest.approx(WGS84_A * math.radians(0.001), rel=SIZE_REL_TOL)
    # North-south: meridian radius of curvature M at the centre latitude times dlat.
    box = AOI(55.64, -21.2305, 55.66, -21.2295)
    phi = math.radians(-21.23)
    m = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * math.sin(phi) ** 2) ** 1.5
    assert box.height_m == pytest.approx(m * math.radians(0.001), rel=SIZE_REL_TOL)


@pytest.mark.parametrize(
    "args, match",
    [
        ((10.0, 0.0, 9.0, 1.0), "lon_min"),
        ((0.0, 1.0, 1.0, 1.0), "lat_min"),
        ((-181.0, 0.0, 1.0, 1.0), "lon_min"),
        ((0.0, 0.0, 1.0, 90.5), "lat_max"),
        ((0.0, float("nan"), 1.0, 1.0), "lat_min"),
        (("a", 0.0, 1.0, 1.0), "lon_min"),
    ],
)
def test_aoi_validation(args, match):
    with pytest.raises(AOIError, match=match):
        AOI(*args)


def test_parse_aoi_numbers():
    assert parse("55.64, -21.24,55.66 ,-21.22") == AOI(55.64, -21.24, 55.66, -21.22)
    with pytest.raises(AOIError, match="LON_MIN,LAT_MIN,LON_MAX,LAT_MAX"):
        parse("55.64,-21.24,55.66")
    with pytest.raises(AOIError, match="LON_MIN"):
        parse("55.64,-21.24,x,-21.22")
    with pytest.raises(AOIError, match="lat_min"):
        parse("55.64,-21.22,55.66,-21.24")
    with pytest.raises(InputError, match="no such file"):
        parse("missing.geojson")


def parse(spec):
    return saoi.parse_aoi(spec)


def _polygon(lon0, lat0, lon1, lat1, z=None):
    ring = [[lon0, lat0], [lon1, lat0], [lon1, lat1], [lon0, lat1], [lon0, lat0]]
    if z is not None:
        ring = [p + [z] for p in ring]
    return {"type": "Polygon", "coordinates": [ring]}


@pytest.mark.parametrize(
    "doc",
    [
        _polygon(1.0, 2.0, 3.0, 4.0),
        _polygon(1.0, 2.0, 3.0, 4.0, z=100.0),
        {"type": "Feature", "properties": {}, "geometry": _polygon(1.0, 2.0, 3.0, 4.0)},
        {"type": "FeatureCollection", "features": [
            {"type": "Feature", "properties": None, "geometry": _polygon(1.0, 2.0, 2.0, 3.0)},
            {"type": "Feature", "properties": None, "geometry": None},
            {"type": "Feature", "properties": None, "geometry": _polygon(2.5, 3.5, 3.0, 4.0)},
        ]},
        {"type": "MultiPolygon", "coordinates": [_polygon(1.0, 2.0, 2.0, 3.0)["coordinates"],
                                                 _polygon(2.0, 3.0, 3.0, 4.0)["coordinates"]]},
        {"type": "GeometryCollection", "geometries": [_polygon(1.0, 3.0, 3.0, 4.0), _polygon(2.0, 2.0, 2.5, 2.5)]},
        {"type": "Feature", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}},
         "properties": {}, "geometry": _polygon(1.0, 2.0, 3.0, 4.0)},
    ],
    ids=["polygon", "polygon-3d", "feature", "collection", "multipolygon", "geometrycollection", "crs84"],
)
def test_parse_aoi_geojson_bounding_box(tmp_path, doc):
    path = tmp_path / "aoi.geojson"
    path.write_text(json.dumps(doc))
    assert parse(str(path)) == AOI(1.0, 2.0, 3.0, 4.0)


def test_parse_aoi_round_trips_to_geojson(tmp_path):
    box = AOI(55.64, -21.24, 55.66, -21.22)
    path = tmp_path / "aoi.json"
    path.write_text(json.dumps(box.to_geojson()))
    assert parse(path) == box


@pytest.mark.parametrize("name", ["urn:ogc:def:crs:EPSG::32740", "EPSG:32740"])
def test_parse_aoi_geojson_in_a_projected_crs(tmp_path, caplog, name):
    """A GeoJSON 2008 file whose ``crs`` names a UTM zone (as GDAL writes a projected layer):
    the AOI is the lon/lat bounding box of its polygon mapped by pyproj (each edge sampled
    densely here), and the run says the DSM covers that box."""
    import pyproj

    x0, y0, x1, y1 = 358000.0, 7651000.0, 358300.0, 7651300.0
    path = tmp_path / "utm.geojson"
    path.write_text(json.dumps({**_polygon(x0, y0, x1, y1),
                                "crs": {"type": "name", "properties": {"name": name}}}))
    t = np.linspace(0.0, 1.0, 1001)
    xs = np.concatenate([x0 + t * (x1 - x0), np.full_like(t, x1), x1 - t * (x1 - x0), np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + t * (y1 - y0), np.full_like(t, y1), y1 - t * (y1 - y0)])
    lon, lat = pyproj.Transformer.from_crs(32740, 4326, always_xy=True).transform(xs, ys)
    with caplog.at_level("WARNING", logger="satsweep"):
        aoi = parse(str(path))
    got = (aoi.lon_min, aoi.lat_min, aoi.lon_max, aoi.lat_max)
    np.testing.assert_allclose(got, (lon.min(), lat.min(), lon.max(), lat.max()),
                               rtol=0, atol=UTM_BOX_TOLERANCE_DEG)
    assert "bounding box" in caplog.text


@pytest.mark.parametrize(
    "text, match",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "type"),
        (json.dumps({"type": "Point", "coordinates": [1.0, 2.0]}), "Point does not bound an area"),
        (json.dumps({"type": "Polygon", "coordinates": [[[1.0], [2.0, 3.0]]]}), "bad position"),
        (json.dumps({"type": "Polygon", "coordinates": [[["1", 2.0]]]}), "bad position"),
        (json.dumps({"type": "Polygon", "coordinates": "x"}), "coordinates"),
        (json.dumps({"type": "FeatureCollection", "features": []}), "no Polygon"),
        (json.dumps({"type": "Circle"}), "unknown type"),
        (json.dumps(_polygon(359000.0, 7651000.0, 360000.0, 7652000.0)), "lon/lat"),
        (json.dumps(_polygon(-179.9, 0.0, 179.9, 1.0)), "antimeridian"),
        (json.dumps({**_polygon(1.0, 2.0, 3.0, 4.0),
                     "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC::X"}}}),
         "crs"),
        (json.dumps({**_polygon(1.0, 2.0, 3.0, 4.0),
                     "crs": {"type": "name", "properties": {"name": "EPSG:999999"}}}),
         "EPSG:999999"),
    ],
)
def test_parse_aoi_bad_geojson(tmp_path, text, match):
    path = tmp_path / "bad.geojson"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as exc:
        parse(str(path))
    assert exc.value.path == str(path)


# -- altitude ranges ---------------------------------------------------------------------------
def test_altitude_range_validation():
    r = AltitudeRange(2300, 2380)
    assert (r.min, r.max, r.span, r.mid) == (2300.0, 2380.0, 80.0, 2340.0)
    with pytest.raises(AOIError, match="inverted altitude range"):
        AltitudeRange(2380.0, 2300.0)
    with pytest.raises(AOIError, match="inverted altitude range"):
        AltitudeRange(100.0, 100.0)
    with pytest.raises(AOIError, match="max"):
        AltitudeRange(0.0, float("inf"))
    with pytest.raises(AOIError, match="metres"):
        AltitudeRange(0.0, 29000.0)  # Everest in feet


def test_parse_altitude_range():
    assert altitude.parse_altitude_range("2300, 2380") == AltitudeRange(2300.0, 2380.0)
    for bad in ("2300", "a,b", "1,2,3"):
        with pytest.raises(AOIError, match="MIN,MAX"):
            altitude.parse_altitude_range(bad)


# A synthetic DEM with an exact answer: background 1000 m, inside the AOI a 1500 m peak, a -200 m
# pit and nodata cells, and outside the AOI (beyond the one-cell neighbour ring) a 9000 m spike
# that must not be seen.
DEM_MARGIN_M = 25.0


def _dem_case(tmp_path, *, epsg, nodata, dtype):
    box = AOI(55.645, -21.235, 55.655, -21.225)
    if epsg == 4326:
        res = 0.0005
        x0, y1 = 55.635, -21.215
    else:
        res = 30.0
        x_c, y_c = pyproj.Transformer.from_crs(4326, epsg, always_xy=True).transform(55.65, -21.23)
        x0, y1 = round(x_c) - 1500.0, round(y_c) + 1500.0
    dem = np.full((100, 100), 1000.0)
    to_dem = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)

    def cell(lon, lat):
        x, y = to_dem.transform(lon, lat)
        return int((y1 - y) / res), int((x - x0) / res)

    dem[cell(55.650, -21.230)] = 1500.0
    dem[cell(55.648, -21.232)] = -200.0
    dem[cell(55.652, -21.228)] = nodata
    r, c = cell(55.640, -21.240)  # far outside the AOI
    dem[r, c] = 9000.0
    path = tmp_path / f"dem_{epsg}.tif"
    write_geotiff(path, dem, epsg=epsg, x_min=x0, y_max=y1, resolution=res, nodata=nodata, dtype=dtype)
    return path, box


@pytest.mark.parametrize(
    "epsg, nodata, dtype",
    [(32740, float("nan"), np.float32), (4326, -32768.0, np.int16), (32740, -9999.0, np.float32)],
    ids=["utm-nan", "geographic-int16", "utm-9999"],
)
def test_altitude_range_from_dem_synthetic(tmp_path, epsg, nodata, dtype):
    path, box = _dem_case(tmp_path, epsg=epsg, nodata=nodata, dtype=dtype)
    got = altitude.altitude_range_from_dem(path, box, margin_m=DEM_MARGIN_M)
    assert got == AltitudeRange(-200.0 - DEM_MARGIN_M, 1500.0 + DEM_MARGIN_M)


def test_altitude_range_from_dem_errors(tmp_path):
    path, _ = _dem_case(tmp_path, epsg=32740, nodata=float("nan"), dtype=np.float32)
    with pytest.raises(InputError, match="does not cover") as exc:
        altitude.altitude_range_from_dem(path, AOI(56.0, -21.0, 56.01, -20.99))
    assert exc.value.path == str(path)
    holes = tmp_path / "holes.tif"
    write_geotiff(holes, np.full((50, 50), np.nan), epsg=4326, x_min=55.6, y_max=-21.2, resolution=0.002)
    with pytest.raises(InputError, match="no valid height"):
        altitude.altitude_range_from_dem(holes, AOI(55.64, -21.24, 55.66, -21.22))
    with pytest.raises(OptionsError, match="margin"):
        altitude.altitude_range_from_dem(path, AOI(55.645, -21.235, 55.655, -21.225), margin_m=-1.0)


def test_altitude_range_from_geoid_dem_widens_margin(tmp_path, caplog):
    # A DEM declaring EGM96 geoid heights (VerticalCSTypeGeoKey 4096 = 5773), as SRTM products do.
    path = tmp_path / "srtm.tif"
    keys = (1, 1, 0, 4, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326, 4096, 0, 1, 5773)
    tifffile.imwrite(path, np.full((20, 20), 700, np.int16), metadata=None, extratags=[
        (33550, "d", 3, (0.01, 0.01, 0.0), True),
        (33922, "d", 6, (0.0, 0.0, 0.0, 55.55, -21.13, 0.0), True),
        (34735, "H", len(keys), keys, True),
    ])
    with caplog.at_level(logging.WARNING, logger="satsweep.geometry.altitude"):
        got = altitude.altitude_range_from_dem(path, AOI(55.64, -21.24, 55.66, -21.22), margin_m=10.0)
    margin = 10.0 + altitude.GEOID_UNDULATION_BOUND_M
    assert got == AltitudeRange(700.0 - margin, 700.0 + margin)
    assert "5773" in caplog.text


def test_altitude_range_from_real_dsm(pleiades_pair):
    # Oracle: rasterio's cell centres -> lon/lat with pyproj; cells whose centre is in the AOI give
    # the inner range, cells within two cells of it the outer range that ours must stay inside.
    path = pleiades_pair / "s2p_dsm.tif"
    with rasterio.open(path) as ds:
        z = ds.read(1).astype(np.float64)
        rows, cols = np.mgrid[0:ds.height, 0:ds.width]
        x, y = ds.xy(rows.ravel(), cols.ravel())
        res = ds.transform.a
        epsg = ds.crs.to_epsg()
    x, y, z = np.asarray(x), np.asarray(y), z.ravel()
    to_utm = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    # A box of about 110 x 110 m around the DSM's centre.
    c_lon, c_lat = pyproj.Transformer.from_crs(epsg, 4326, always_xy=True).transform(x.mean(), y.mean())
    box = AOI(c_lon - 0.0005, c_lat - 0.0005, c_lon + 0.0005, c_lat + 0.0005)
    bx, by = to_utm.transform([box.lon_min, box.lon_max, box.lon_max, box.lon_min],
                              [box.lat_min, box.lat_min, box.lat_max, box.lat_max])
    lon, lat = pyproj.Transformer.from_crs(epsg, 4326, always_xy=True).transform(x, y)
    inner = box.contains(lon=lon, lat=lat) & np.isfinite(z)
    grow = 2 * res
    outer = ((x > min(bx) - grow) & (x < max(bx) + grow) & (y > min(by) - grow) & (y < max(by) + grow)
             & np.isfinite(z))
    assert inner.sum() > 1000
    got = altitude.altitude_range_from_dem(path, box, margin_m=0.0)
    assert z[outer].min() <= got.min <= z[inner].min()
    assert z[inner].max() <= got.max <= z[outer].max()


def _fake_rpc(off, scale):
    return types.SimpleNamespace(alt_offset=off, alt_scale=scale)


def test_altitude_range_from_rpcs(caplog):
    with caplog.at_level(logging.WARNING, logger="satsweep.geometry.altitude"):
        got = altitude.altitude_range_from_rpcs([_fake_rpc(1295.0, 1315.0), _fake_rpc(1000.0, 500.0)])
    assert got == AltitudeRange(1000.0 - 500.0, 1000.0 + 500.0)  # heights valid for both
    assert "coarse" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="satsweep.geometry.altitude"):
        quiet = altitude.altitude_range_from_rpcs([_fake_rpc(1000.0, 500.0)], warn=False)
    assert quiet == AltitudeRange(500.0, 1500.0) and not caplog.text
    disjoint = altitude.altitude_range_from_rpcs([_fake_rpc(100.0, 50.0), _fake_rpc(500.0, 50.0)])
    assert disjoint == AltitudeRange(50.0, 550.0)  # no common heights: their union
    with pytest.raises(OptionsError):
        altitude.altitude_range_from_rpcs([])


def test_resolve_altitude_range_priority(tmp_path, caplog):
    path, box = _dem_case(tmp_path, epsg=32740, nodata=float("nan"), dtype=np.float32)
    rpcs = [_fake_rpc(1295.0, 1315.0)]
    given = AltitudeRange(10.0, 20.0)
    assert altitude.resolve_altitude_range(alt_range=given, dem=path, rpcs=rpcs, aoi=box) == given
    assert altitude.resolve_altitude_range(alt_range=(10, 20)) == given
    from_dem = altitude.resolve_altitude_range(dem=path, rpcs=rpcs, aoi=box, dem_margin_m=DEM_MARGIN_M)
    assert from_dem == AltitudeRange(-200.0 - DEM_MARGIN_M, 1500.0 + DEM_MARGIN_M)
    with caplog.at_level(logging.WARNING, logger="satsweep.geometry.altitude"):
        assert altitude.resolve_altitude_range(rpcs=rpcs, aoi=box) == AltitudeRange(-20.0, 2610.0)
    with pytest.raises(OptionsError, match="AOI"):
        altitude.resolve_altitude_range(dem=path)
    with pytest.raises(OptionsError, match="--alt-range"):
        altitude.resolve_altitude_range(aoi=box)
    with pytest.raises(AOIError, match="inverted"):
        altitude.resolve_altitude_range(alt_range=(20.0, 10.0))


def test_geojson_aoi_that_is_not_one_box_says_the_bounding_box_is_used(tmp_path, caplog):
    multi = {"type": "MultiPolygon", "coordinates": [_polygon(1.0, 2.0, 2.0, 3.0)["coordinates"],
                                                     _polygon(2.0, 3.0, 3.0, 4.0)["coordinates"]]}
    triangle = {"type": "Polygon", "coordinates": [[[1.0, 2.0], [3.0, 2.0], [2.0, 4.0],
                                                    [1.0, 2.0]]]}
    for doc, rings in ((multi, 2), (triangle, 1)):
        path = tmp_path / f"aoi_{rings}.geojson"
        path.write_text(json.dumps(doc))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="satsweep.geometry.aoi"):
            parse(str(path))
        assert any("bounding box of its" in r.getMessage() and str(path) in r.getMessage()
                   for r in caplog.records), doc
    path = tmp_path / "box.geojson"
    path.write_text(json.dumps(_polygon(1.0, 2.0, 3.0, 4.0)))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="satsweep.geometry.aoi"):
        parse(str(path))
    assert not caplog.records
