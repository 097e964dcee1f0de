"""DSM stage: height maps to points, grids, rasterisation, fusion, hole filling, GeoTIFF output."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from satsweep.errors import CameraError, OptionsError
from satsweep.geometry.aoi import AOI
from satsweep.geometry.geodesy import ENUFrame, lonlat_to_utm
from satsweep.products import fusion as dsm
from satsweep.products import grid as dsm_grid
from satsweep.products import ortho
from satsweep.products import points as dsm_points

# Points recovered from a height map must match the exact ray/plane intersection to this (m):
# float64 keeps ~1e-9 m at the 600 km camera distance; ENU -> geodetic -> ENU adds ~1e-9 m.
POINT_TOL_M = 1e-6
# Fused heights are rounded to float32: at 2400 m its spacing is 2.4e-4 m.
FLOAT32_HEIGHT_TOL_M = 5e-4

FRAME = ENUFrame(lon0=55.65, lat0=-21.23, alt0=2340.0)  # La Reunion, as the real pair


def _satellite_camera(width: int = 64, height: int = 48, *, off_nadir_deg: float = 10.0,
                      azimuth_rad: float = 0.3):
    """A pinhole 600 km up, ``off_nadir_deg`` off nadir looking at the ENU origin, ~0.5 m pixels.

    Returns (P, K, R, C): P = K R [I | -C], R ENU -> camera (x along columns, y along rows).
    """
    off = math.radians(off_nadir_deg)
    C = np.array([600e3 * math.tan(off) * math.sin(azimuth_rad),
                  -600e3 * math.tan(off) * math.cos(azimuth_rad), 600e3])
    forward = -C / np.linalg.norm(C)
    north = np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, north)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    f = np.linalg.norm(C) / 0.5
    K = np.array([[f, 3.0, width / 2 + 7.3], [0.0, f * 1.0002, height / 2 - 4.1], [0.0, 0.0, 1.0]])
    P = K @ R @ np.hstack([np.eye(3), -C[:, None]])
    return P, K, R, C


def _ray_plane(K, R, C, col, row, u):
    """Exact ground point: the ray of pixel (col, row) through the camera centre, cut at height u."""
    d = (R.T @ np.linalg.solve(K, np.stack([col, row, np.ones_like(col)])))  # ENU directions
    lam = (u - C[2]) / d[2]
    return C[0] + lam * d[0], C[1] + lam * d[1]


def test_height_map_to_points_recovers_exact_enu_points():
    P, K, R, C = _satellite_camera()
    h, w = 48, 64
    rng = np.random.default_rng(0)
    height = (rng.uniform(-20.0, 40.0, (h, w))).astype(np.float32)
    valid = rng.random((h, w)) > 0.2
    height[5, 7] = np.nan
    valid[5, 7] = True  # a NaN height is skipped even when flagged valid
    colors = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    conf = rng.random((h, w)).astype(np.float32)
    pts = dsm_points.height_map_to_points(height, valid, P * -3.7, FRAME, colors=colors, confidence=conf)
    rows, cols = np.nonzero(valid & np.isfinite(height))
    assert len(pts) == rows.size
    e_ref, n_ref = _ray_plane(K, R, C, cols.astype(float), rows.astype(float), height[rows, cols].astype(float))
    e, n, u = FRAME.from_geodetic(lon=pts.lon, lat=pts.lat, alt=pts.alt)
    np.testing.assert_allclose(e, e_ref, rtol=0, atol=POINT_TOL_M)
    np.testing.assert_allclose(n, n_ref, rtol=0, atol=POINT_TOL_M)
    np.testing.assert_allclose(u, height[rows, cols], rtol=0, atol=POINT_TOL_M)
    # And the points project back onto their pixels.
    q = P @ np.stack([e, n, u, np.ones_like(e)])
    np.testing.assert_allclose(q[0] / q[2], cols, atol=1e-6)
    np.testing.assert_allclose(q[1] / q[2], rows, atol=1e-6)
    np.testing.assert_array_equal(pts.colors, colors[rows, cols])
    np.testing.assert_array_equal(pts.confidence, conf[rows, cols])


def test_subsamples_cover_the_pixel_footprint():
    P, K, R, C = _satellite_camera()
    height = np.full((3, 4), 12.5, np.float32)
    valid = np.zeros((3, 4), bool)
    valid[1, 2] = True
    grey = np.full((3, 4), 77, np.uint8)
    pts = dsm_points.height_map_to_points(height, valid, P, FRAME, colors=grey, subsamples=2)
    assert len(pts) == 4
    offs = np.array([-0.25, 0.25])
    dy, dx = np.meshgrid(offs, offs, indexing="ij")
    e_ref, n_ref = _ray_plane(K, R, C, 2 + dx.ravel(), 1 + dy.ravel(), np.full(4, 12.5))
    e, n, u = FRAME.from_geodetic(lon=pts.lon, lat=pts.lat, alt=pts.alt)
    np.testing.assert_allclose(e, e_ref, atol=POINT_TOL_M)
    np.testing.assert_allclose(n, n_ref, atol=POINT_TOL_M)
    assert np.all(pts.colors == 77) and pts.colors.shape == (4, 3)


# A slanted plane u = a + b e + c n (m): the surface the cross-check tests see.
PLANE = (5.0, 0.02, -0.01)
# Tolerance of the cross-check in those tests (m), and the error injected into one view (m).
CHECK_TOL_M = 1.0
INJECTED_ERROR_M = 3.0


def _plane_height_map(K, R, C, shape):
    """Exact ENU height of the plane PLANE seen at every pixel (ray-plane intersection)."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    d = R.T @ np.linalg.solve(K, np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)]))
    a, b, c = PLANE
    lam = (a + b * C[0] + c * C[1] - C[2]) / (d[2] - b * d[0] - c * d[1])
    return (C[2] + lam * d[2]).reshape(shape)


def _views_of_the_plane(n: int, shape=(48, 64)):
    cams = [_satellite_camera(shape[1], shape[0], off_nadir_deg=off, azimuth_rad=az)
            for off, az in ((10.0, 0.3), (6.0, 2.4), (12.0, 4.2))[:n]]
    return [P for P, *_ in cams], [_plane_height_map(K, R, C, shape) for _, K, R, C in cams], cams


def _seen_by(cam_from, cam_to, height, shape):
    """Pixels of one view whose plane point falls inside another view (exact geometry)."""
    _, K, R, C = cam_from
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    e, n = _ray_plane(K, R, C, cols.ravel(), rows.ravel(), height.ravel())
    P = cam_to[0]
    q = P @ np.stack([e, n, height.ravel(), np.ones(e.size)])
    col, row = np.floor(q[0] / q[2] + 0.5), np.floor(q[1] / q[2] + 0.5)
    return ((col >= 0) & (col < shape[1]) & (row >= 0) & (row < shape[0])).reshape(shape)


def test_cross_check_keeps_consistent_maps_and_rejects_an_injected_error():
    shape = (48, 64)
    Ps, maps, cams = _views_of_the_plane(2, shape)
    seen = [_seen_by(cams[0], cams[1], maps[0], shape), _seen_by(cams[1], cams[0], maps[1], shape)]
    assert all(0.5 < s.mean() < 1.0 for s in seen)  # the views overlap, not completely
    keep = dsm.cross_check_heights(maps, Ps, tolerance_m=CHECK_TOL_M)
    for k in range(2):
        np.testing.assert_array_equal(keep[k], seen[k])
    bad = [m.copy() for m in maps]
    bad[0][10:30, 20:40] += INJECTED_ERROR_M
    bad[0][0, 0] = np.nan  # unknown pixels are never kept
    keep = dsm.cross_check_heights(bad, Ps, tolerance_m=CHECK_TOL_M)
    assert not keep[0][10:30, 20:40].any() and not keep[0][0, 0]
    # The caller's ENU points of the known pixels, when given, give the same masks.
    points = [dsm_points.height_map_to_enu(m, np.isfinite(m), P) for m, P in zip(bad, Ps)]
    given = dsm.cross_check_heights(bad, Ps, tolerance_m=CHECK_TOL_M, points=points)
    for k in range(2):
        np.testing.assert_array_equal(given[k], keep[k])
    outside = seen[0].copy()
    outside[10:30, 20:40] = False
    outside[0, 0] = False
    np.testing.assert_array_equal(keep[0][outside], True)
    # View 1's pixels that see the corrupted block disagree with it; the others are kept.
    assert (keep[1] <= seen[1]).all() and 0.5 * seen[1].mean() < keep[1].mean() < seen[1].mean()


def test_cross_check_with_three_views_needs_one_or_all_agreeing():
    shape = (48, 64)
    Ps, maps, cams = _views_of_the_plane(3, shape)
    bad = [m.copy() for m in maps]
    bad[0] += INJECTED_ERROR_M  # view 0 is wrong everywhere
    one = dsm.cross_check_heights(bad, Ps, tolerance_m=CHECK_TOL_M, min_agreeing=1)
    both = dsm.cross_check_heights(bad, Ps, tolerance_m=CHECK_TOL_M, min_agreeing=2)
    assert not one[0].any() and not both[0].any()
    seen12 = _seen_by(cams[1], cams[2], maps[1], shape)
    np.testing.assert_array_equal(one[1], seen12)  # view 2 confirms what view 0 cannot
    assert not both[1].any()  # view 0 never agrees
    # A single view cannot be checked: its known pixels are returned.
    single = dsm.cross_check_heights([maps[0]], [Ps[0]], tolerance_m=CHECK_TOL_M)
    assert single[0].all()
    with pytest.raises(OptionsError, match="tolerance_m"):
        dsm.cross_check_heights(maps, Ps, tolerance_m=0.0)
    with pytest.raises(OptionsError, match="min_agreeing"):
        dsm.cross_check_heights(maps, Ps, tolerance_m=1.0, min_agreeing=0)


def test_height_map_to_enu_matches_the_points_and_names_their_pixels():
    P, K, R, C = _satellite_camera()
    rng = np.random.default_rng(3)
    height = rng.uniform(-5.0, 30.0, (48, 64))
    valid = rng.random((48, 64)) > 0.3
    for s in (1, 2):
        e, n, u, pixel = dsm_points.height_map_to_enu(height, valid, P, subsamples=s)
        pts = dsm_points.height_map_to_points(height, valid, P, FRAME, subsamples=s)
        lon, lat, alt = FRAME.to_geodetic(e=e, n=n, u=u)
        np.testing.assert_allclose(lon, pts.lon, rtol=0, atol=1e-12)
        np.testing.assert_allclose(lat, pts.lat, rtol=0, atol=1e-12)
        np.testing.assert_allclose(alt, pts.alt, rtol=0, atol=POINT_TOL_M)
        rows, cols = np.divmod(pixel, 64)
        assert valid[rows, cols].all() and len(e) == s * s * valid.sum()
        np.testing.assert_array_equal(u, height[rows, cols])


def _map_for(P, height, valid):
    """An ENUToMap over a height map's points (with room for their footprints)."""
    from satsweep.geometry.geodesy import utm_epsg

    e, n, u, _ = dsm_points.height_map_to_enu(height, valid, P)
    return dsm_points.ENUToMap.fit(FRAME, utm_epsg(lon=FRAME.lon0, lat=FRAME.lat0),
                            e_range=(e.min() - 5, e.max() + 5), n_range=(n.min() - 5, n.max() + 5),
                            u_range=(u.min(), u.max()))


@pytest.mark.parametrize("subsamples", [2, 3])
def test_footprint_splats_match_the_exact_sub_samples(subsamples):
    # A 2000 x 1500 px view, 25 degrees off nadir, heights over 150 m: the Jacobian moves each
    # sub-sample from its centre as solving and mapping it exactly would, within SPLAT_TOL_M.
    P, *_ = _satellite_camera(2000, 1500, off_nadir_deg=25.0)
    rng = np.random.default_rng(7)
    height = rng.uniform(-50.0, 100.0, (1500, 2000))
    valid = rng.random(height.shape) > 0.995
    valid[[0, 0, -1, -1], [0, -1, 0, -1]] = True  # the corners
    to_map = _map_for(P, height, valid)
    centres = dsm_points.height_map_to_enu(height, valid, P)
    (x, y, z, pixel), (sx, sy, sz, spix) = dsm_points.map_view_points(centres, height, valid, P, to_map,
                                                               subsamples=subsamples)
    e, n, u, ref_pix = dsm_points.height_map_to_enu(height, valid, P, subsamples=subsamples)
    rx, ry, rz = dsm_points._exact_enu_to_map(FRAME, to_map.epsg, e, n, u)
    np.testing.assert_array_equal(spix, ref_pix)
    assert dsm_points.footprint_jacobian(P, to_map, col=pixel % 2000, row=pixel // 2000, u=z) is not None
    for got, ref in ((sx, rx), (sy, ry), (sz, rz)):
        np.testing.assert_allclose(got, ref, rtol=0, atol=dsm_points.SPLAT_TOL_M)
    # The centres are the exact points themselves.
    ce, cn, cu, _ = centres
    cx, cy, cz = dsm_points._exact_enu_to_map(FRAME, to_map.epsg, ce, cn, cu)
    np.testing.assert_allclose(x, cx, rtol=0, atol=1e-5)
    np.testing.assert_allclose(z, cz, rtol=0, atol=1e-5)


def test_footprint_jacobian_refuses_a_varying_footprint():
    # A camera 6 km up (not a satellite): footprints change by far more than SPLAT_TOL_M across the
    # view, so the sub-samples are solved one by one, and still match the exact points.
    P, K, R, C = _satellite_camera(400, 300, off_nadir_deg=40.0)
    C, K = C / 100.0, np.diag([0.01, 0.01, 1.0]) @ K  # still about 0.5 m pixels
    P = K @ R @ np.hstack([np.eye(3), -C[:, None]])
    rng = np.random.default_rng(8)
    height = rng.uniform(-50.0, 100.0, (300, 400))
    valid = rng.random(height.shape) > 0.9
    to_map = _map_for(P, height, valid)
    centres = dsm_points.height_map_to_enu(height, valid, P)
    e, n, u, pixel = centres
    assert dsm_points.footprint_jacobian(P, to_map, col=pixel % 400, row=pixel // 400, u=u) is None
    _, (sx, sy, sz, spix) = dsm_points.map_view_points(centres, height, valid, P, to_map, subsamples=2)
    e2, n2, u2, ref_pix = dsm_points.height_map_to_enu(height, valid, P, subsamples=2)
    rx, ry, rz = to_map(e=e2, n=n2, u=u2)
    np.testing.assert_array_equal(spix, ref_pix)
    np.testing.assert_array_equal(sx, rx)
    np.testing.assert_array_equal(sz, rz)


def test_rasterise_max_cells_shares_the_cells_of_rasterise_max():
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=100.0, y_max=50.0, resolution=0.5, width=30, height=20)
    rng = np.random.default_rng(9)
    x, y = rng.uniform(95.0, 120.0, 4000), rng.uniform(35.0, 55.0, 4000)
    x[:10] = 100.0 + 0.5 * np.arange(10)  # on cell boundaries
    z = rng.normal(size=4000)
    z[20] = np.nan
    cells = dsm.flat_cells(x, y, grid)
    inside = (x >= 100.0) & (x < 115.0) & (y > 40.0) & (y <= 50.0)
    np.testing.assert_array_equal(cells >= 0, inside)
    ref = np.full(grid.shape, np.nan, np.float32)
    for xi, yi, zi in zip(x, y, z):  # the documented rule, point by point
        i, j = math.floor((50.0 - yi) / 0.5), math.floor((xi - 100.0) / 0.5)
        if 0 <= i < 20 and 0 <= j < 30 and np.isfinite(zi):
            ref[i, j] = zi if np.isnan(ref[i, j]) else max(ref[i, j], np.float32(zi))
    np.testing.assert_array_equal(dsm.rasterise_max_cells(cells, z, grid), ref)
    np.testing.assert_array_equal(dsm.rasterise_max(x, y, z, grid), ref)


@pytest.mark.parametrize("quantile", [0.0, 0.5, 0.75, dsm.VIEW_RASTER_QUANTILE, 1.0])
def test_rasterise_quantile_cells_matches_a_python_loop(quantile):
    """Per cell the round(quantile (n - 1))-th of its n values in ascending order (halves
    rounded up), points outside the grid and NaN values ignored, NaN where a cell holds none;
    quantile 1 is rasterise_max_cells."""
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=100.0, y_max=50.0, resolution=0.5, width=30, height=20)
    rng = np.random.default_rng(11)
    x, y = rng.uniform(95.0, 120.0, 4000), rng.uniform(35.0, 55.0, 4000)
    z = rng.normal(size=4000)
    z[::97] = np.nan
    z[100:110] = z[110:120]  # ties
    cells = dsm.flat_cells(x, y, grid)
    per_cell: dict[int, list[float]] = {}
    for c, v in zip(cells, z):
        if c >= 0 and np.isfinite(v):
            per_cell.setdefault(int(c), []).append(float(v))
    ref = np.full(grid.width * grid.height, np.nan)
    for c, vals in per_cell.items():
        ref[c] = sorted(vals)[math.floor(quantile * (len(vals) - 1) + 0.5)]
    got = dsm.rasterise_quantile_cells(cells, z, grid, quantile)
    assert got.dtype == np.float32 and got.shape == grid.shape
    np.testing.assert_array_equal(got, ref.reshape(grid.shape).astype(np.float32))
    assert np.isnan(got).any() and max(len(v) for v in per_cell.values()) >= 4
    if quantile == 1.0:
        np.testing.assert_array_equal(got, dsm.rasterise_max_cells(cells, z, grid))
    with pytest.raises(ValueError):
        dsm.rasterise_quantile_cells(cells[:-1], z, grid, quantile)
    with pytest.raises(ValueError):
        dsm.rasterise_quantile_cells(cells, z, grid, 1.5)


@pytest.mark.parametrize("quantile", [0.0, 0.75, 1.0])
def test_rasterise_quantile_cells_values_closer_than_float32(quantile):
    """Heights closer together than float32 resolves (ellipsoidal heights of a few thousand
    metres differing by micrometres, both signs, zeros of both signs): each cell the float32 of
    the float64 value a python loop picks."""
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=100.0, y_max=50.0, resolution=0.5, width=8, height=6)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(100.0, 104.0, 3000), rng.uniform(47.0, 50.0, 3000)
    base = rng.choice([2340.0, -31.5, 0.0, 1e-30, -1e-30], size=3000)
    z = base + rng.integers(-3, 4, 3000) * 1e-6 * (base != 0.0)
    z[::50] = -0.0
    cells = dsm.flat_cells(x, y, grid)
    per_cell: dict[int, list[float]] = {}
    for c, v in zip(cells, z):
        if c >= 0:
            per_cell.setdefault(int(c), []).append(float(v))
    ref = np.full(grid.width * grid.height, np.nan)
    for c, vals in per_cell.items():
        ref[c] = sorted(vals)[math.floor(quantile * (len(vals) - 1) + 0.5)]
    got = dsm.rasterise_quantile_cells(cells, z, grid, quantile)
    np.testing.assert_array_equal(got, ref.reshape(grid.shape).astype(np.float32))
    assert len(per_cell) == grid.width * grid.height


def test_view_raster_rule_follows_the_pixels_per_cell():
    """auto: the quantile where a view puts DENSE_CENTRES_PER_CELL pixel centres or more
    in the cells it fills (a 0.3 m view on 0.5 m cells), the highest point where fewer (0.5 m)."""
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=0.0, y_max=50.0, resolution=0.5, width=100, height=100)

    def centres(gsd):  # pixel centres of a nadir view of ground sample distance gsd (m)
        g = np.arange(0.5 * gsd, 50.0, gsd)
        x, y = np.meshgrid(g, 50.0 - g)
        return dsm.flat_cells(x.ravel(), y.ravel(), grid)

    fine, coarse = centres(0.3), centres(0.5)
    assert dsm.centres_per_cell(fine) == pytest.approx((0.5 / 0.3) ** 2, rel=0.05)
    assert dsm.centres_per_cell(coarse) == pytest.approx(1.0)
    assert dsm.centres_per_cell(np.array([-1, -1])) == 0.0
    auto = dsm.DSMOptions()
    assert auto.view_raster == "auto"
    assert auto.view_raster_for(fine) == "quantile"
    assert auto.view_raster_for(coarse) == "max"
    assert dsm.DSMOptions(view_raster="max").view_raster_for(fine) == "max"
    assert dsm.DSMOptions(view_raster="quantile").view_raster_for(coarse) == "quantile"
    with pytest.raises(OptionsError, match="view_raster"):
        dsm.DSMOptions(view_raster="median")


# The polynomial ENU -> UTM map must reproduce pyproj to this (m) over an AOI-sized box.
ENU_MAP_CHECK_TOL_M = 1e-6


def test_enu_to_map_reproduces_the_exact_transform():
    from satsweep.geometry.geodesy import lonlat_to_utm, utm_epsg

    epsg = utm_epsg(lon=FRAME.lon0, lat=FRAME.lat0)
    m = dsm_points.ENUToMap.fit(FRAME, epsg, e_range=(-400.0, 300.0), n_range=(-250.0, 350.0),
                         u_range=(-20.0, 150.0))
    assert m.accurate and m.max_error_m < ENU_MAP_CHECK_TOL_M
    rng = np.random.default_rng(5)
    e, n, u = rng.uniform(-400, 300, 5000), rng.uniform(-250, 350, 5000), rng.uniform(-20, 150, 5000)
    x, y, z = m(e=e, n=n, u=u)
    lon, lat, alt = FRAME.to_geodetic(e=e, n=n, u=u)
    xr, yr = lonlat_to_utm(lon=lon, lat=lat, epsg=epsg)
    np.testing.assert_allclose(x, xr, rtol=0, atol=ENU_MAP_CHECK_TOL_M)
    np.testing.assert_allclose(y, yr, rtol=0, atol=ENU_MAP_CHECK_TOL_M)
    np.testing.assert_allclose(z, alt, rtol=0, atol=ENU_MAP_CHECK_TOL_M)
    # Over a 600 km box the polynomials are not accurate: the exact transform is used instead.
    far = dsm_points.ENUToMap.fit(FRAME, epsg, e_range=(-3e5, 3e5), n_range=(-3e5, 3e5), u_range=(0, 100))
    assert not far.accurate
    x, y, z = far(e=e * 500, n=n * 500, u=u)
    lon, lat, alt = FRAME.to_geodetic(e=e * 500, n=n * 500, u=u)
    xr, yr = lonlat_to_utm(lon=lon, lat=lat, epsg=epsg)
    np.testing.assert_array_equal(x, xr)
    np.testing.assert_array_equal(z, alt)


def test_degenerate_or_bad_camera():
    with pytest.raises(CameraError):
        dsm_points.height_map_to_points(np.zeros((2, 2)), np.ones((2, 2), bool), np.zeros((3, 3)), FRAME)
    # A camera whose rays are horizontal (looking along north) cannot meet a plane u = const.
    P = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 1.0, 0, 0]])
    e, n = dsm_points.solve_ground_en(P, col=[0.5], row=[0.0], u=[0.0])
    assert np.isnan(e).all() and np.isnan(n).all()


def test_points_concatenate_keeps_common_attributes():
    a = dsm_points.Points(lon=np.zeros(2), lat=np.zeros(2), alt=np.ones(2), colors=np.zeros((2, 3), np.uint8))
    b = dsm_points.Points(lon=np.ones(3), lat=np.ones(3), alt=np.ones(3))
    c = dsm_points.Points.concatenate([a, b])
    assert len(c) == 5 and c.colors is None
    assert len(dsm_points.Points.concatenate([])) == 0


def test_dsm_grid_for_aoi_covers_the_aoi_and_snaps_to_the_resolution():
    aoi = AOI(lon_min=55.640, lat_min=-21.240, lon_max=55.660, lat_max=-21.220)
    grid = dsm_grid.dsm_grid_for_aoi(aoi, 0.5)
    assert grid.epsg == 32740  # zone 40 south
    t = np.linspace(0, 1, 2001)
    lons = np.concatenate([55.640 + 0.02 * t, np.full_like(t, 55.66), 55.640 + 0.02 * t, np.full_like(t, 55.64)])
    lats = np.concatenate([np.full_like(t, -21.24), -21.24 + 0.02 * t, np.full_like(t, -21.22), -21.24 + 0.02 * t])
    x, y = lonlat_to_utm(lon=lons, lat=lats, epsg=32740)
    # Snapped outward to multiples of the cell size, with less than one cell of slack.
    for edge in (grid.x_min, grid.y_max, grid.x_max, grid.y_min):
        assert math.isclose(edge / 0.5, round(edge / 0.5), abs_tol=1e-6)
    assert grid.x_min <= x.min() < grid.x_min + 0.5
    assert grid.x_max - 0.5 < x.max() <= grid.x_max
    assert grid.y_min <= y.min() < grid.y_min + 0.5
    assert grid.y_max - 0.5 < y.max() <= grid.y_max
    assert (grid.width, grid.height) == (round((grid.x_max - grid.x_min) / 0.5), round((grid.y_max - grid.y_min) / 0.5))
    # An explicit EPSG is honoured; a bad resolution is an OptionsError.
    assert dsm_grid.dsm_grid_for_aoi(aoi, 2.0, epsg=32640).epsg == 32640
    with pytest.raises(OptionsError, match="resolution"):
        dsm_grid.dsm_grid_for_aoi(aoi, 0.0)


def test_grid_cell_convention():
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=1000.0, y_max=5000.0, resolution=0.5, width=4, height=3)
    xs, ys = grid.cell_centers()
    np.testing.assert_array_equal(xs, [1000.25, 1000.75, 1001.25, 1001.75])
    np.testing.assert_array_equal(ys, [4999.75, 4999.25, 4998.75])
    i, j = grid.cell_of(x=xs, y=np.full(4, ys[2]))
    np.testing.assert_array_equal(i, [2, 2, 2, 2])
    np.testing.assert_array_equal(j, [0, 1, 2, 3])
    assert grid.geotransform == (1000.0, 0.5, 0.0, 5000.0, 0.0, -0.5)
    with pytest.raises(OptionsError):
        dsm_grid.DSMGrid(epsg=32740, x_min=0.0, y_max=0.0, resolution=0.5, width=0, height=3)


def test_rasterise_max_matches_a_python_loop():
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=340_000.0, y_max=7_650_000.0, resolution=0.5, width=23, height=17)
    rng = np.random.default_rng(1)
    n = 3000
    x = rng.uniform(grid.x_min - 1.0, grid.x_max + 1.0, n)
    y = rng.uniform(grid.y_min - 1.0, grid.y_max + 1.0, n)
    x[:40] = grid.x_min + 0.5 * rng.integers(0, 24, 40)  # exactly on cell boundaries
    y[:40] = grid.y_max - 0.5 * rng.integers(0, 18, 40)
    z = rng.normal(2340.0, 5.0, n)
    z[50:60] = np.nan
    got = dsm.rasterise_max(x, y, z, grid)
    ref = np.full((grid.height, grid.width), -np.inf)
    for xv, yv, zv in zip(x, y, z):
        if not math.isfinite(zv):
            continue
        j = math.floor((xv - grid.x_min) / grid.resolution)
        i = math.floor((grid.y_max - yv) / grid.resolution)
        if 0 <= i < grid.height and 0 <= j < grid.width and zv > ref[i, j]:
            ref[i, j] = zv
    ref[np.isinf(ref)] = np.nan
    assert got.dtype == np.float32 and got.shape == (17, 23)
    np.testing.assert_array_equal(got, ref.astype(np.float32))
    assert np.isnan(got).any() and np.isfinite(got).any()


def test_rasterise_points_goes_through_utm():
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=338_000.0, y_max=7_651_000.0, resolution=1.0, width=10, height=10)
    xs, ys = grid.cell_centers()
    from satsweep.geometry.geodesy import utm_to_lonlat

    lon, lat = utm_to_lonlat(x=xs[[1, 1, 8]], y=ys[[2, 2, 5]], epsg=32740)
    pts = dsm_points.Points(lon=lon, lat=lat, alt=np.array([10.0, 30.0, 20.0]))
    out = dsm.rasterise_points(pts, grid)
    assert out[2, 1] == 30.0 and out[5, 8] == 20.0
    assert np.count_nonzero(np.isfinite(out)) == 2


@pytest.mark.parametrize("block_values", [dsm.FUSE_BLOCK_VALUES, 5 * 40 * 7])
def test_fuse_dsms_discards_injected_outliers(block_values, monkeypatch):
    monkeypatch.setattr(dsm, "FUSE_BLOCK_VALUES", block_values)  # also in row blocks of 7 rows
    rng = np.random.default_rng(2)
    base = rng.uniform(2300, 2400, (30, 40))
    views = [base + rng.uniform(-0.2, 0.2, base.shape) for _ in range(5)]
    outlier = np.zeros((5, 30, 40), bool)
    outlier[0, :10] = True  # view 0 is 20 m too high on the first rows
    outlier[3, 5:15, 20:] = True  # view 3 is 15 m too low on a block
    views[0][outlier[0]] += 20.0
    views[3][outlier[3]] -= 15.0
    missing = np.zeros((5, 30, 40), bool)
    missing[1, 20:, :5] = True
    views[1][missing[1]] = np.nan
    fused, count = dsm.fuse_dsms(views, outlier_m=2.0)
    stack = np.stack(views)
    keep = ~outlier & ~missing
    ref = np.array([[np.median(stack[keep[:, i, j], i, j]) for j in range(40)] for i in range(30)])
    np.testing.assert_allclose(fused, ref, atol=FLOAT32_HEIGHT_TOL_M)
    np.testing.assert_array_equal(count, keep.sum(axis=0))
    assert fused.dtype == np.float32 and count.dtype == np.int32


def test_fuse_two_views_that_disagree_are_dropped_and_min_views():
    a = np.array([[10.0, 10.0, np.nan, np.nan]])
    b = np.array([[10.4, 20.0, 7.0, np.nan]])
    fused, count = dsm.fuse_dsms([a, b], outlier_m=1.0)
    np.testing.assert_allclose(fused[0, :3], [10.2, np.nan, 7.0], atol=FLOAT32_HEIGHT_TOL_M)
    assert np.isnan(fused[0, 3])
    np.testing.assert_array_equal(count, [[2, 0, 1, 0]])
    fused2, count2 = dsm.fuse_dsms([a, b], outlier_m=1.0, min_views=2)
    assert np.isnan(fused2[0, 2]) and count2[0, 2] == 0 and math.isclose(fused2[0, 0], 10.2, abs_tol=1e-4)
    with pytest.raises(OptionsError, match="outlier_m"):
        dsm.fuse_dsms([a], outlier_m=0.0)
    with pytest.raises(ValueError):
        dsm.fuse_dsms([a, np.zeros((2, 2))])


def _holes_dsm():
    rng = np.random.default_rng(4)
    d = rng.uniform(100, 110, (20, 20))
    d[5:7, 5:7] = np.nan  # 4-cell enclosed hole
    d[12:18, 10:15] = np.nan  # 30-cell enclosed hole: too large
    d[0:2, 15:18] = np.nan  # 6 cells touching the border: too large
    d[9, 2] = np.nan  # 1-cell hole
    d[19, 8:10] = np.nan  # 2 cells touching the border
    return d


def _rim_values(d, cells):
    """Valid 4-neighbours of a set of cells, by a plain loop."""
    out = []
    for i, j in cells:
        for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            a, b = i + di, j + dj
            if 0 <= a < d.shape[0] and 0 <= b < d.shape[1] and np.isfinite(d[a, b]):
                out.append(d[a, b])
    return np.array(out)


@pytest.mark.parametrize("method", ["min", "median"])
@pytest.mark.parametrize("border_holes", [True, False])
def test_fill_small_holes(method, border_holes):
    d = _holes_dsm()
    filled, n = dsm.fill_small_holes(d, max_hole_cells=4, method=method,
                                     border_holes=border_holes)
    assert n == (7 if border_holes else 5)
    pick = np.min if method == "min" else np.median
    holes = [[(5, 5), (5, 6), (6, 5), (6, 6)], [(9, 2)]]
    edge = [(19, 8), (19, 9)]  # its rim: the cells inside the raster
    for hole in holes + ([edge] if border_holes else []):
        rim = _rim_values(d, hole)
        for i, j in hole:
            assert math.isclose(filled[i, j], np.float32(pick(rim)), rel_tol=0, abs_tol=1e-4)
    if not border_holes:
        assert np.isnan(filled[19, 8:10]).all()
    assert np.isnan(filled[12:18, 10:15]).all() and np.isnan(filled[0:2, 15:18]).all()
    untouched = np.isfinite(d)
    np.testing.assert_array_equal(filled[untouched], d[untouched].astype(np.float32))
    same, zero = dsm.fill_small_holes(d, max_hole_cells=0)
    assert zero == 0 and np.count_nonzero(np.isnan(same)) == np.count_nonzero(np.isnan(d))


def _supported_min_reference(rim):
    """The lowest rim value with max(RIM_SUPPORT_CELLS, RIM_SUPPORT_SHARE of the rim) values
    within RIM_SUPPORT_M above it, by a plain loop; the minimum when none has."""
    need = max(dsm.RIM_SUPPORT_CELLS, math.ceil(dsm.RIM_SUPPORT_SHARE * len(rim)))
    ok = [v for v in rim if np.sum((rim >= v) & (rim <= v + dsm.RIM_SUPPORT_M)) >= need]
    return min(ok) if ok else rim.min()


@pytest.mark.parametrize("border_holes", [True, False])
def test_fill_small_holes_supported_min(border_holes):
    d = _holes_dsm()
    filled, n = dsm.fill_small_holes(d, max_hole_cells=4, method="supported_min",
                                     border_holes=border_holes)
    assert n == (7 if border_holes else 5)
    for hole in [[(5, 5), (5, 6), (6, 5), (6, 6)], [(9, 2)]]:
        want = _supported_min_reference(_rim_values(d, hole))
        for i, j in hole:
            assert math.isclose(filled[i, j], np.float32(want), rel_tol=0, abs_tol=1e-4)


def test_one_blunder_on_a_rim_does_not_set_the_hole():
    """A hole beside a wall (roof at 20 m on one side, ground at 10 m on the others) with one rim
    cell 30 m under the ground: "min" fills the hole with the blunder, "supported_min" with the
    ground; a rim whose values all lie apart falls back to its minimum."""
    d = np.full((12, 12), 10.0)
    d[:, 8:] = 20.0  # the roof
    d[3:9, 4:8] = np.nan  # the hole, against the wall
    d[2, 5] = -20.0  # one blunder on its rim
    plain, _ = dsm.fill_small_holes(d, max_hole_cells=100, method="min")
    robust, n = dsm.fill_small_holes(d, max_hole_cells=100, method="supported_min")
    assert n == 24 and np.all(plain[3:9, 4:8] == -20.0) and np.all(robust[3:9, 4:8] == 10.0)
    lone = np.array([[1.0, 5.0, 9.0], [13.0, np.nan, 17.0], [21.0, 25.0, 29.0]])
    single, _ = dsm.fill_small_holes(lone, max_hole_cells=1, method="supported_min")
    assert single[1, 1] == 5.0  # rim 5, 13, 17, 25: no two within 1 m: the minimum


def test_dsm_options_are_checked():
    assert dsm.DSMOptions().resolution == 0.5
    with pytest.raises(OptionsError, match="DSMOptions.resolution"):
        dsm.DSMOptions(resolution=-1.0)
    with pytest.raises(OptionsError, match="fill_method"):
        dsm.DSMOptions(fill_method="mean")
    with pytest.raises(OptionsError, match="DSMOptions.cross_check_m"):
        dsm.DSMOptions(cross_check_m=-1.0)
    with pytest.raises(OptionsError, match="DSMOptions.cross_check_views"):
        dsm.DSMOptions(cross_check_views=0)
    with pytest.raises(OptionsError, match="DSMOptions.visibility_far_m"):
        dsm.DSMOptions(visibility_far_m=float("nan"))
    with pytest.raises(OptionsError, match="DSMOptions.visibility_leaf_on_far_m"):
        dsm.DSMOptions(visibility_leaf_on_far_m=-1.0)
    with pytest.raises(OptionsError, match="DSMOptions.visibility_bare_far_m"):
        dsm.DSMOptions(visibility_bare_far_m=float("nan"))


def test_write_dsm_geotiff_is_read_by_rasterio_with_the_right_crs(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=338_000.0, y_max=7_651_000.0, resolution=0.5, width=7, height=5)
    a = np.arange(35, dtype=np.float32).reshape(5, 7)
    a[2, 3] = np.nan
    path = tmp_path / "dsm.tif"
    dsm_grid.write_dsm_geotiff(path, a, grid)
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32740
        assert src.transform.to_gdal() == grid.geotransform
        assert np.isnan(src.nodata) and src.dtypes[0] == "float32"
        np.testing.assert_array_equal(src.read(1), a)


def test_value_at_highest_takes_each_cells_top_point():
    grid = dsm_grid.DSMGrid(epsg=32631, x_min=0.0, y_max=2.0, resolution=1.0, width=3, height=2)
    #                cell: 0    0    0    1    1     4      5    -1 (outside)  2
    cells = np.array([0, 0, 0, 1, 1, 4, 5, -1, 2])
    heights = np.array([10., 12., 11., 5., 5., np.nan, 7., 99., 3.])
    values = np.array([0.1, 0.2, 0.3, 0.4, 0.6, 0.9, np.nan, 0.8, 0.5])
    got = ortho.value_at_highest(cells, heights, values, grid)
    # cell 0: the point at 12 m; cell 1: two tops at 5 m, the larger value; cell 2: its one point;
    # cell 4: no height, cell 5: no value, cell 3: no point -> NaN
    expected = np.array([[0.2, 0.6, 0.5], [np.nan, np.nan, np.nan]], np.float32)
    np.testing.assert_array_equal(got, expected)
    assert got.dtype == np.float32
    with pytest.raises(ValueError, match="lengths differ"):
        ortho.value_at_highest(cells, heights[:-1], values, grid)


def test_values_at_highest_takes_each_value_sets_top_points():
    rng = np.random.default_rng(8)
    grid = dsm_grid.DSMGrid(epsg=32631, x_min=0.0, y_max=6.0, resolution=1.0, width=5, height=6)
    cells = rng.integers(-1, 30, 400)
    heights = rng.integers(0, 4, 400).astype(float)  # many ties for the highest
    heights[::17] = np.nan
    grey = rng.random(400)
    green = rng.random(400)
    green[::5] = np.nan  # another set of points: the cells' tops differ where it has no value
    got = ortho.values_at_highest(cells, heights, [grey, grey * 2.0, green], grid)
    for g, v in zip(got, (grey, grey * 2.0, green)):
        # The rule cell by cell: of the points with a height and a value, those at the highest
        # height, the largest value.
        expected = np.full(30, np.nan, np.float32)
        for c in range(30):
            at = (cells == c) & np.isfinite(heights) & np.isfinite(v)
            if at.any():
                top = heights[at] == heights[at].max()
                expected[c] = v[at][top].max()
        np.testing.assert_array_equal(g, expected.reshape(6, 5))
    assert ortho.values_at_highest(cells, heights, [], grid) == []


def test_match_radiometry_fits_gain_and_offset_robustly():
    from satsweep.products.ortho import RADIOMETRY_MIN_CELLS, match_radiometry

    rng = np.random.default_rng(4)
    ref = rng.gamma(4.0, 100.0, (60, 60))
    other = (ref - 30.0) / 1.7  # another gain and offset
    # 5% of the cells see something else (values of the same kind, unrelated).
    other[:3] = (rng.gamma(4.0, 100.0, (3, 60)) - 30.0) / 1.7
    ref[10, 0] = other[11, 1] = np.nan
    got = match_radiometry(ref, other)
    agree = np.isfinite(got) & np.isfinite(ref)
    agree[:3] = False
    # Those cells move the quartiles a little: measured 0.3% (median relative difference).
    assert np.median(np.abs(got - ref)[agree] / ref[agree]) < 0.02
    few = np.full_like(ref, np.nan)
    few.flat[:RADIOMETRY_MIN_CELLS - 1] = 1.0
    assert match_radiometry(ref, few) is few


def _consensus_reference(values: list[float], tolerance: float, min_views: int,
                         min_share: float = 0.0):
    """Plain-Python consensus of one cell: the largest group within a window of 2 * tolerance
    (the lowest on a tie), its median and size; none when it holds fewer than min_views values
    or than min_share of the cell's values."""
    v = sorted(x for x in values if np.isfinite(x))
    best = (0, None)
    for i, lo in enumerate(v):
        group = [x for x in v if lo <= x <= lo + 2 * tolerance]
        if len(group) > best[0]:
            best = (len(group), group)
    size, group = best
    if size < min_views or group is None or size < min_share * len(v):
        return np.nan, 0
    return float(np.median(group)), size


@pytest.mark.parametrize("seed, min_share", [(0, 0.0), (1, 0.0), (2, 0.0), (0, 0.5), (1, 0.5),
                                             (2, 0.7)])
def test_consensus_matches_a_plain_reference(seed, min_share):
    from satsweep.products.fusion import consensus_dsms

    rng = np.random.default_rng(seed)
    n, shape = 6, (7, 9)
    truth = rng.normal(100.0, 10.0, shape)
    dsms = []
    for _ in range(n):
        d = truth + rng.normal(0.0, 0.3, shape)
        blunders = rng.random(shape) < 0.25
        d[blunders] += rng.choice([-30.0, 15.0, 40.0], blunders.sum())
        d[rng.random(shape) < 0.2] = np.nan
        dsms.append(d.astype(np.float32))
    fused, count, members = consensus_dsms(dsms, tolerance_m=1.0, min_views=2,
                                           min_share=min_share)
    for i in range(shape[0]):
        for j in range(shape[1]):
            values = [float(d[i, j]) for d in dsms]
            expected, size = _consensus_reference(values, 1.0, 2, min_share)
            assert count[i, j] == size, (i, j, values)
            if size:
                assert fused[i, j] == pytest.approx(expected, abs=1e-4)
                in_group = [k for k, x in enumerate(values) if members[k, i, j]]
                assert len(in_group) == size
            else:
                assert np.isnan(fused[i, j])


def test_consensus_never_keeps_a_lone_view():
    from satsweep.products.fusion import consensus_dsms

    a = np.array([[10.0, 10.0], [np.nan, 50.0]], np.float32)
    b = np.array([[10.4, 30.0], [np.nan, np.nan]], np.float32)
    fused, count, _ = consensus_dsms([a, b], tolerance_m=1.0, min_views=2)
    assert fused[0, 0] == pytest.approx(10.2) and count[0, 0] == 2
    assert np.isnan(fused[0, 1]) and np.isnan(fused[1, 1]) and count[1, 1] == 0


def test_consensus_needs_half_of_the_cells_heights_with_min_share():
    """Two agreeing heights among four make a cell's height with min_share = 0.5, among five
    they do not (the others scatter: no height for that cell, and no member)."""
    from satsweep.products.fusion import consensus_dsms

    four = [np.full((1, 1), v, np.float32) for v in (10.0, 10.3, 25.0, 40.0)]
    fused, count, _ = consensus_dsms(four, tolerance_m=1.0, min_views=2, min_share=0.5)
    assert fused[0, 0] == pytest.approx(10.15) and count[0, 0] == 2
    five = four + [np.full((1, 1), 60.0, np.float32)]
    fused, count, members = consensus_dsms(five, tolerance_m=1.0, min_views=2, min_share=0.5)
    assert np.isnan(fused[0, 0]) and count[0, 0] == 0 and not members.any()
    fused, count, _ = consensus_dsms(five, tolerance_m=1.0, min_views=2)  # no such rule
    assert fused[0, 0] == pytest.approx(10.15) and count[0, 0] == 2
    with pytest.raises(OptionsError, match="min_share"):
        consensus_dsms(five, tolerance_m=1.0, min_views=2, min_share=1.5)


# -- thin raised cells that few views agree on --------------------------------------------------
# A 0.5 m grid over ground at 100 m: two towers (count 12 of 12) with an alley of 2 cells between
# them that the consensus put at a wall's height by THIN_ALLEY_COUNT views; a roof in a shadow,
# its cells alternately empty and agreed on by 2 views; a low wall and a high narrow roof.
THIN_VIEWS = 12
THIN_ALLEY_COUNT = 3


def _thin_scene():
    fused = np.full((90, 90), 100.0, np.float32)
    count = np.full(fused.shape, THIN_VIEWS, np.uint8)
    fused[10:60, 10:30] = 160.0  # tower
    fused[10:60, 32:50] = 160.0  # tower
    alley = np.zeros(fused.shape, bool)
    alley[10:60, 30:32] = True
    fused[alley] = 140.0
    count[alley] = THIN_ALLEY_COUNT
    roof = np.zeros(fused.shape, bool)
    roof[65:85, 10:30] = True  # 10 m x 10 m, speckled
    fused[roof] = 130.0
    count[roof] = 2
    speckle = roof & ((np.indices(fused.shape).sum(axis=0) % 2) == 0)
    fused[speckle] = np.nan
    count[speckle] = 0
    fused[65:85, 60:62] = 110.0  # a low wall (10 m: under THIN_RAISED_RISE_M)
    count[65:85, 60:62] = 2
    fused[10:60, 70:72] = 160.0  # a narrow high roof that many views agree on
    count[10:60, 70:72] = 6
    return fused, count, alley


def test_thin_raised_minority_takes_the_alley_only():
    """Of the scene above, only the alley's cells: the speckled roof with its empty cells holds
    squares of THIN_RAISED_SIDE_M, the wall rises less than THIN_RAISED_RISE_M, the narrow roof
    has more views than a quarter of 12."""
    fused, count, alley = _thin_scene()
    assert dsm.THIN_RAISED_RISE_M < 140.0 - 100.0 and 110.0 - 100.0 < dsm.THIN_RAISED_RISE_M
    assert dsm.THIN_RAISED_SIDE_M / 0.5 > 2  # wider than the alley, narrower than the roof
    thin = dsm.thin_raised_minority(fused, count, THIN_VIEWS, max_share=0.25, resolution_m=0.5)
    np.testing.assert_array_equal(thin, alley)


def test_thin_raised_minority_share_rounds_down():
    """A share of 0.2 of 12 views allows 2 (the alley's 3 agree: kept); 0 allows none; a share
    outside [0, 1] is refused."""
    fused, count, alley = _thin_scene()
    for share in (0.2, 0.0):
        thin = dsm.thin_raised_minority(fused, count, THIN_VIEWS, max_share=share,
                                        resolution_m=0.5)
        assert not thin.any()
    count[alley] = 2
    thin = dsm.thin_raised_minority(fused, count, THIN_VIEWS, max_share=0.2, resolution_m=0.5)
    np.testing.assert_array_equal(thin, alley)
    with pytest.raises(OptionsError, match="max_share"):
        dsm.thin_raised_minority(fused, count, THIN_VIEWS, max_share=1.5, resolution_m=0.5)


def test_thin_raised_minority_ground_is_local():
    """The ground is the lowest cell within THIN_RAISED_GROUND_M: the scene on a terrace 50 m up
    that runs on past it that far before the low ground gives the alley alone again (from the
    low ground, the terrace's low wall would rise 60 m)."""
    fused, count, alley = _thin_scene()
    far = int(dsm.THIN_RAISED_GROUND_M / 0.5) + 1
    w = fused.shape[1]
    lifted = np.full((fused.shape[0], w + far + 20), 100.0, np.float32)
    lifted[:, :w + far] = 150.0
    lifted[:, :w] = fused + 50.0
    lifted_count = np.full(lifted.shape, THIN_VIEWS, np.uint8)
    lifted_count[:, :w] = count
    want = np.zeros(lifted.shape, bool)
    want[:, :w] = alley
    thin = dsm.thin_raised_minority(lifted, lifted_count, THIN_VIEWS, max_share=0.25,
                                    resolution_m=0.5)
    np.testing.assert_array_equal(thin, want)


def _valley_scene(alley_cells: int, alley_count: int):
    """Two towers 60 m over the ground that 10 of 12 views agree on, an alley of
    ``alley_cells`` (0.5 m cells) between them at a tower's height that ``alley_count`` agree
    on, and beside them a roof 30 m up in a tower's shadow that 2 views agree on throughout."""
    fused = np.full((60, 80), 100.0, np.float32)
    count = np.full(fused.shape, THIN_VIEWS, np.uint8)
    fused[10:50, 10:30] = 160.0
    count[10:50, 10:30] = 10
    fused[10:50, 30 + alley_cells:50 + alley_cells] = 160.0
    count[10:50, 30 + alley_cells:50 + alley_cells] = 10
    alley = np.zeros(fused.shape, bool)
    alley[10:50, 30:30 + alley_cells] = True
    fused[alley] = 160.0
    count[alley] = alley_count
    fused[20:40, 60 + alley_cells - 5:75] = 130.0  # the roof in shadow
    count[20:40, 60 + alley_cells - 5:75] = 2
    return fused, count, alley


def _valleys_by_loops(fused, count, n_views, min_share, resolution_m):
    """raised_count_valleys written cell by cell, as its docstring reads."""
    h, w = fused.shape
    radius = int(round(dsm.THIN_RAISED_GROUND_M / resolution_m))
    reach = max(1, int(round(dsm.VALLEY_REACH_M / resolution_m)))
    drop = max(1, math.ceil(min_share * n_views - 1e-9))
    raised = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            if np.isfinite(fused[y, x]):
                window = fused[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
                raised[y, x] = fused[y, x] - np.nanmin(window) > dsm.THIN_RAISED_RISE_M
    out = np.zeros((h, w), bool)
    for y, x in zip(*np.nonzero(raised)):
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            sides = []
            for sign in (1, -1):
                best = -1
                for k in range(1, reach + 1):
                    yy, xx = y + sign * dy * k, x + sign * dx * k
                    if 0 <= yy < h and 0 <= xx < w and raised[yy, xx]:
                        best = max(best, int(count[yy, xx]))
                sides.append(best)
            if min(sides) >= int(count[y, x]) + drop:
                out[y, x] = True
    return out


def test_raised_count_valleys_take_the_alley_not_the_shadowed_roof():
    """An alley 1.5 m across that 6 views agree on between towers that 10 do (a share of 0.33
    of 12 rounds up to 4 views): the alley goes, the roof in shadow that 2 views agree on
    everywhere stays (no valley: its neighbours agree as little), and so does an alley that 7
    agree on (3 under the towers) and one 10 m across (its middle is more than VALLEY_REACH_M
    from either tower)."""
    fused, count, alley = _valley_scene(3, 6)
    assert 3 * 0.5 <= dsm.VALLEY_REACH_M < 10.0 / 2
    got = dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=0.33, resolution_m=0.5)
    np.testing.assert_array_equal(got, alley)
    fused, count, alley = _valley_scene(3, 7)
    assert not dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=0.33,
                                        resolution_m=0.5).any()
    fused, count, alley = _valley_scene(20, 6)
    got = dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=0.33, resolution_m=0.5)
    reach = int(round(dsm.VALLEY_REACH_M / 0.5))
    assert not got[:, 30 + 20 - reach:30 + reach].any() and not got[~alley].any()


def test_raised_count_valleys_match_a_loop_reference():
    """Random consensus rasters (holes, low walls, towers, counts 1-12) against the rule written
    cell by cell, at two resolutions and three shares; 0 takes nothing, a share outside [0, 1]
    is refused."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        h, w = rng.integers(5, 40, size=2)
        fused = (100.0 + rng.choice([0.0, 8.0, 30.0, 60.0], size=(h, w))
                 + rng.normal(0.0, 1.0, size=(h, w))).astype(np.float32)
        fused[rng.random((h, w)) < 0.15] = np.nan
        count = rng.integers(1, THIN_VIEWS + 1, size=(h, w)).astype(np.uint8)
        for share, res in ((0.33, 0.5), (0.2, 0.5), (0.5, 1.0)):
            got = dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=share,
                                           resolution_m=res)
            want = _valleys_by_loops(fused, count, THIN_VIEWS, share, res)
            np.testing.assert_array_equal(got, want, err_msg=f"trial {trial}, share {share}")
    assert not dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=0.0,
                                        resolution_m=0.5).any()
    with pytest.raises(OptionsError, match="min_share"):
        dsm.raised_count_valleys(fused, count, THIN_VIEWS, min_share=-0.1, resolution_m=0.5)


def test_consensus_ties_go_to_the_lower_group():
    """Two equally large groups: the lower wins (a roof height smeared beside a building
    must not beat the ground on a tie)."""
    from satsweep.products.fusion import consensus_dsms

    dsms = [np.full((1, 1), v, np.float32) for v in (10.0, 10.2, 40.0, 40.3)]
    fused, count, _ = consensus_dsms(dsms, tolerance_m=1.0, min_views=2)
    assert fused[0, 0] == pytest.approx(10.1) and count[0, 0] == 2


def test_consensus_counts_a_pair_seen_both_ways_once():
    """Height maps A-against-B and B-against-A share their errors: with view_sets the
    agreeing group must draw on min_distinct_views distinct views."""
    from satsweep.products.fusion import consensus_dsms

    dsms = [np.full((1, 2), v, np.float32) for v in (10.0, 10.1, 10.2)]
    dsms[2][0, 1] = 50.0  # cell 1: only the first two height maps agree
    view_sets = [(0, 1), (1, 0), (2, 3)]
    fused, count, members = consensus_dsms(
        dsms, tolerance_m=1.0, min_views=2, view_sets=view_sets, min_distinct_views=3)
    assert fused[0, 0] == pytest.approx(10.1) and count[0, 0] == 3  # views 0..3 in all
    assert np.isnan(fused[0, 1]) and count[0, 1] == 0 and not members[:, 0, 1].any()
    fused, count, _ = consensus_dsms(dsms, tolerance_m=1.0, min_views=2)
    assert fused[0, 1] == pytest.approx(10.05) and count[0, 1] == 2


# -- free-space (visibility) check --------------------------------------------------------------
# A 2-D world (east, up; north is the row): ground u = 0, a block u = 10 m over 20 <= e < 30.
# Affine views: pixel column = e + a * u (a = tan of the incidence, its sign the side the
# satellite looks from), row = n, one pixel per metre.
_BLOCK = (20.0, 30.0, 10.0)


def _affine(a: float) -> np.ndarray:
    """The affine view as a 3x4 matrix, with a perspective term small enough (a camera 1000 km
    away) to give its rays a side to look from."""
    return np.array([[1.0, 0.0, a, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1e-6, 1.0]])


def _true_heights(a: float, width: int, rows: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The height each pixel sees (first hit from above along e = col - a u), and whether it sees
    a wall."""
    e0, e1, top = _BLOCK
    col = np.arange(width, dtype=np.float64) + 0.5
    h = np.zeros(width)
    wall = np.zeros(width, bool)
    e_top = col - a * top  # where the ray crosses the roof's height
    roof = (e_top >= e0) & (e_top < e1)
    h[roof] = top
    # Below the roof's height the ray meets the wall the satellite faces, else the ground.
    face = e0 if a > 0 else e1
    u_wall = (col - face) / a
    hits = ~roof & (u_wall > 0) & (u_wall < top)
    h[hits] = u_wall[hits]
    wall[hits] = True
    return np.tile(h, (rows, 1)), np.tile(wall, (rows, 1))


def test_visibility_check_drops_a_facade_matched_at_its_roof_height_only():
    width = 60
    slopes = (0.5, 0.4, -0.5)
    maps, walls = zip(*(_true_heights(a, width) for a in slopes))
    fattened = maps[0].copy()
    fattened[walls[0]] = _BLOCK[2]  # view 0's facade swept at the roof's height
    heights = [fattened, maps[1], maps[2]]
    kept = dsm.visibility_check_heights(heights, [_affine(a) for a in slopes], tolerance_m=2.0)
    # The facade's pixels within the tolerance of the roof's height are right to that tolerance.
    wrong = walls[0] & (maps[0] < _BLOCK[2] - 2.0)
    assert wrong.sum() >= 8
    assert not kept[0][wrong].any()
    for k, (h, mask) in enumerate(zip(maps, kept)):
        right = ~wrong if k == 0 else np.ones(h.shape, bool)
        assert mask[right].all(), k
    # A single view has nothing to check against: all its pixels are kept.
    assert dsm.visibility_check_heights([maps[0]], [_affine(0.5)], tolerance_m=2.0)[0].all()


_FACADE_SLOPES = (0.5, 0.4, 0.05)


def _two_facades_at_roof_height(width: int = 60):
    """Views 0 and 1 from one side (incidences 0.5 and 0.4) with their facades swept at the
    roof's height, view 2 near nadir (0.05): (true maps, wall masks, heights, projections)."""
    maps, walls = zip(*(_true_heights(a, width) for a in _FACADE_SLOPES))
    heights = [m.copy() for m in maps]
    for k in (0, 1):
        heights[k][walls[k]] = _BLOCK[2]
    return maps, walls, heights, [_affine(a) for a in _FACADE_SLOPES]


def test_visibility_check_drops_a_facade_two_views_agree_on_when_one_sees_far_past():
    """Views 0 and 1 look from the same side (incidences 0.5 and 0.4) and both sweep the facade at
    the roof's height; view 2 looks almost straight down (0.05). View 0's facade points 16-20 m
    east are agreed on by view 1 (its own facade puts roof points there) and seen past by view
    2, which sees the ground 10 m below: one against one, kept by the majority rule, dropped
    when a view seeing more than far_m past outweighs two that agree (far_m 5 m, not 15 m)."""
    width = 60
    slopes = _FACADE_SLOPES
    maps, walls, heights, projections = _two_facades_at_roof_height(width)
    e = np.arange(width) + 0.5 - slopes[0] * heights[0][0]  # where view 0 puts its pixels
    both = walls[0][0] & (e >= 16.0) & (maps[0][0] < _BLOCK[2] - 2.0)
    assert both.sum() == 3  # facade pixels 1-3 of 5 (heights 3, 5, 7 m)
    majority = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0)[0][0]
    assert majority[both].all()
    near = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, far_m=15.0)[0][0]
    assert near[both].all()  # the ground is only 10 m below
    far = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, far_m=5.0)
    assert not far[0][0][both].any()
    # What else goes: the facades below 8 m, and the roof's last pixel at its east edge in views
    # 0 and 1, whose point lands half a pixel from the edge and rounds onto the ground in view 2
    # (the price of the rule: a roof eroded by a pixel where a view sees the ground beside it).
    dropped = [set(np.flatnonzero(~mask[0]).tolist()) for mask in far]
    assert dropped == [{20, 21, 22, 23, 34}, {20, 21, 22, 33}, set()], dropped
    with pytest.raises(OptionsError, match="far_m"):
        dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, far_m=-1.0)


def test_trusted_views_see_far_past_from_their_own_depth():
    """The scene of the test above: views 0 and 1 sweep their facades at the roof's height, view
    2 (near nadir) sees the ground 10 m below view 0's facade points. With far_m 15 m they stay;
    when view 2 is trusted from 5 m on they go exactly as with far_m 5 m for every view; when
    only views 0 and 1 are trusted (they never see past those points) nothing changes."""
    _, _, heights, projections = _two_facades_at_roof_height()
    run = functools.partial(dsm.visibility_check_heights, heights, projections, tolerance_m=2.0)
    near = run(far_m=15.0)
    everyone = run(far_m=5.0)
    assert any((~m).sum() > (~n).sum() for m, n in zip(everyone, near))
    nadir = run(far_m=15.0, trusted_far_m=5.0, trusted_views=[False, False, True])
    for a, b in zip(nadir, everyone):
        np.testing.assert_array_equal(a, b)
    # Without far_m the trusted views' rule stands alone.
    alone = run(trusted_far_m=5.0, trusted_views=[False, False, True])
    for a, b in zip(alone, everyone):
        np.testing.assert_array_equal(a, b)
    for trusted in ([True, True, False], None):
        same = run(far_m=15.0, trusted_far_m=5.0, trusted_views=trusted)
        for a, b in zip(same, near):
            np.testing.assert_array_equal(a, b)
    # A trusted depth beyond far_m changes nothing (the nearer of the two counts).
    for a, b in zip(run(far_m=5.0, trusted_far_m=15.0, trusted_views=[True] * 3), everyone):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(OptionsError, match="trusted_far_m"):
        run(trusted_far_m=float("nan"), trusted_views=[True] * 3)
    with pytest.raises(ValueError, match="trusted_views"):
        run(trusted_far_m=5.0, trusted_views=[True, True])


def test_bare_views_see_far_past_the_points_that_are_not_green():
    """The scene above. View 2 (near nadir) counted as a bare view from 5 m on drops what it
    drops when trusted from 5 m on, where no point is green; every point green, or no green
    flags for a view (None), keeps that view's points as with far_m 15 m; view 0's facade points
    marked green stay, and everything else goes as before."""
    from satsweep.products.points import height_map_to_enu

    _, walls, heights, projections = _two_facades_at_roof_height()
    points = [height_map_to_enu(h, np.isfinite(h), P) for h, P in zip(heights, projections)]
    run = functools.partial(dsm.visibility_check_heights, heights, projections, tolerance_m=2.0,
                            far_m=15.0, points=points)
    near = run()
    everyone = run(trusted_far_m=5.0, trusted_views=[False, False, True])
    assert any((~m).sum() > (~n).sum() for m, n in zip(everyone, near))
    bare = functools.partial(run, bare_far_m=5.0, bare_views=[False, False, True])
    never_green = [np.zeros(p[2].shape, bool) for p in points]
    for a, b in zip(bare(green=never_green), everyone):
        np.testing.assert_array_equal(a, b)
    for green in ([np.ones(p[2].shape, bool) for p in points], [None] * 3):
        for a, b in zip(bare(green=green), near):
            np.testing.assert_array_equal(a, b)
    # View 0's facade points green: they go as with far_m 15 m alone (the three that rule
    # keeps stay), the rest of every view as without green.
    facade = walls[0].ravel()[points[0][3]]
    green = [facade, never_green[1], never_green[2]]
    out = bare(green=green)
    assert (near[0][0] & ~everyone[0][0] & walls[0][0]).sum() == 3  # per row
    np.testing.assert_array_equal(out[0], np.where(walls[0], near[0], everyone[0]))
    for a, b in zip(out[1:], everyone[1:]):
        np.testing.assert_array_equal(a, b)
    # Views that are not bare, or a depth of 0, change nothing.
    for kwargs in ({"bare_views": [True, True, False]}, {"bare_far_m": 0.0}):
        for a, b in zip(bare(green=never_green, **kwargs), near):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(OptionsError, match="bare_far_m"):
        bare(bare_far_m=float("nan"), green=never_green)
    with pytest.raises(ValueError, match="bare_views"):
        bare(bare_views=[True, True], green=never_green)
    with pytest.raises(ValueError, match="green"):
        bare(green=None)
    with pytest.raises(ValueError, match="green flags"):
        bare(green=[never_green[0][:-1], None, None])


def test_fine_pixels_are_two_footprints_per_cell():
    from satsweep.products.fusion import fine_pixels

    assert fine_pixels(0.3, 0.5)  # WorldView-3 on 0.5 m cells: 2.8 footprints per cell
    assert not fine_pixels(0.5, 0.5) and not fine_pixels(0.7, 0.5)
    assert fine_pixels(0.5 / np.sqrt(2.0) - 1e-9, 0.5) and not fine_pixels(0.36, 0.5)
    with pytest.raises(ValueError, match="gsd_m"):
        fine_pixels(0.0, 0.5)


_ERODED_SLOPES = (0.1, -0.1, 0.05)


def _eroded_rim_scene(width: int = 60):
    """The slack test's three near-nadir views: views 1 and 2 erode the block by a pixel on each
    side. Returns (heights, projections, view 0's rim columns, per view j in (1, 2) the columns
    where view 0's rim points land: on its ground)."""
    slopes = _ERODED_SLOPES
    heights = [_true_heights(a, width)[0] for a in slopes]
    roof0 = np.flatnonzero(heights[0][0] == _BLOCK[2])
    rim0 = [roof0[0], roof0[-1]]
    landing = {}
    for j in (1, 2):  # where view 0's rim points land in view j (pixel centres at integers)
        west, east = np.floor(np.array(rim0) - (slopes[0] - slopes[j]) * _BLOCK[2]
                              + 0.5).astype(int)
        roof = np.flatnonzero(heights[j][0] == _BLOCK[2])
        # Eroded: the block's pixels up to those see the ground, the next ones hold its height.
        heights[j][:, roof[0]:west + 1] = 0.0
        heights[j][:, east:roof[-1] + 1] = 0.0
        assert heights[j][0, west + 1] == heights[j][0, east - 1] == _BLOCK[2]
        landing[j] = [west, east]
        assert (heights[j][:, landing[j]] == 0.0).all()
    return heights, [_affine(a) for a in slopes], rim0, landing


def test_unconfident_pixels_of_voter_views_do_not_see_past():
    """View 0's rim points land on pixels that views 1 and 2 put on the ground: two views see
    past, none agrees, and the rim is dropped. Where those ground heights are unconfident
    (two near-equal minima) in views marked as voters, they no longer count as seeing past (or
    far past), and the rim stays; one confident view seeing past still drops it."""
    heights, projections, rim0, landing = _eroded_rim_scene()
    sure = [np.ones(h.shape) for h in heights]
    unsure = [c.copy() for c in sure]
    for j in (1, 2):
        unsure[j][:, landing[j]] = 0.01
    run = functools.partial(dsm.visibility_check_heights, heights, projections, tolerance_m=2.0)
    assert not run()[0][:, rim0].any()
    voters = [True, True, True]
    kept = run(confidences=unsure, voter_min_confidence=0.02, voter_views=voters)
    assert kept[0][:, rim0].all()
    # The far rule counts the same voters: nothing sees far past the rim either.
    far = run(confidences=unsure, voter_min_confidence=0.02, voter_views=voters, far_m=5.0)
    assert far[0][:, rim0].all()
    # The rest is as without the rule: the rim is all that changes in view 0.
    strict = run()
    assert (kept[0] == (strict[0] | _columns(kept[0].shape, rim0))).all()
    # One view still confident on its ground there sees past: dropped.
    one = [unsure[0], unsure[1], sure[2]]
    assert not run(confidences=one, voter_min_confidence=0.02,
                   voter_views=voters)[0][:, rim0].any()
    # Views not marked, a threshold of 0, or confidences under it nowhere: as before.
    for kwargs in (dict(voter_views=[True, False, False]), dict(voter_views=None),
                   dict(voter_views=voters, voter_min_confidence=0.0),
                   dict(voter_views=voters, voter_min_confidence=0.005)):
        kwargs.setdefault("voter_min_confidence", 0.02)
        assert not run(confidences=unsure, **kwargs)[0][:, rim0].any(), kwargs
    # A voter view without confidences never sees past.
    none = run(confidences=[None, None, None], voter_min_confidence=0.02, voter_views=voters)
    assert none[0][:, rim0].all()
    with pytest.raises(OptionsError, match="voter_min_confidence"):
        run(voter_min_confidence=1.5)
    with pytest.raises(ValueError, match="voter_views"):
        run(confidences=unsure, voter_min_confidence=0.02, voter_views=[True, True])


def _columns(shape, cols) -> np.ndarray:
    out = np.zeros(shape, bool)
    out[:, cols] = True
    return out


def test_visibility_slack_keeps_a_rim_that_other_views_erode_by_a_pixel():
    """Three near-nadir views of the block; views 1 and 2 erode it by a pixel on each side (their
    edge pixels see the ground), view 0 does not. Its edge pixels then land on the others'
    eroded pixels: two views see past, none agrees, and the strict check drops the rim. With a
    one-pixel slack each of them has the block's height a pixel away, so the rim stays, when
    view 0 matched it confidently; an unconfident rim (a facade's pattern) keeps the strict
    test, and the far rule, which reads the nearest pixel, still applies."""
    heights, projections, rim0, _ = _eroded_rim_scene()
    truth = [_true_heights(a, heights[0].shape[1])[0] for a in _ERODED_SLOPES]
    sure = [np.ones(h.shape) for h in heights]
    strict = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0)
    assert not strict[0][:, rim0].any()
    slack = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=1,
                                         confidences=sure, slack_min_confidence=0.3)
    assert slack[0][:, rim0].all()
    # The slack only keeps more, and only true points of the block (views 1 and 2 see past
    # each other's edge pixels too, eroded differently; view 1's last facade pixel).
    for k in range(3):
        assert (slack[k] | ~strict[k]).all(), k
        rescued = slack[k] & ~strict[k]
        assert (heights[k][rescued] == truth[k][rescued]).all(), k
        assert (heights[k][rescued] > 0.0).all(), k
    # Unconfident pixels (view 0's rim under 0.3), or views without confidences: strict.
    unsure = [c.copy() for c in sure]
    unsure[0][:, rim0] = 0.1
    low = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=1,
                                       confidences=unsure, slack_min_confidence=0.3)
    assert not low[0][:, rim0].any()
    none = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=1,
                                        confidences=[None, *sure[1:]],
                                        slack_min_confidence=0.3)
    assert not none[0][:, rim0].any()
    # The far rule reads the nearest pixel: two views 10 m past outweigh none agreeing.
    far = dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, far_m=5.0,
                                       slack_px=1, confidences=sure, slack_min_confidence=0.3)
    assert not far[0][:, rim0].any()
    with pytest.raises(OptionsError, match="slack_px"):
        dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=-1)
    with pytest.raises(OptionsError, match="slack_min_confidence"):
        dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=1,
                                     slack_min_confidence=1.5)
    with pytest.raises(ValueError, match="confidence maps"):
        dsm.visibility_check_heights(heights, projections, tolerance_m=2.0, slack_px=1,
                                     confidences=sure[:2])


@pytest.mark.parametrize("with_voters", [False, True])
@pytest.mark.parametrize("block", [dsm.SEEN_BLOCK, 7])
def test_seen_by_others_counts_match_a_plain_loop(block, with_voters, monkeypatch):
    """The counts behind the cross- and free-space checks (agree, past with and without the
    slack, far), against a loop over every point and every other view: maps of several sizes
    with unknown pixels, views shifted so that some points fall outside the others' maps; the
    points in one block and in blocks of 7 (a last one shorter)."""
    monkeypatch.setattr(dsm, "SEEN_BLOCK", block)
    rng = np.random.default_rng(5)
    shapes = [(9, 12), (11, 10), (8, 14)]
    heights = []
    for shape in shapes:
        h = rng.choice([0.0, 3.0, 10.0], size=shape) + rng.normal(0.0, 0.5, shape)
        h[rng.random(shape) < 0.15] = np.nan
        heights.append(h)
    projections = [np.array([[1.0, 0.05 * k, 0.3 * k - 0.2, 1.5 * k - 1.0],
                             [-0.03 * k, 1.0, 0.1 * k, 2.0 - k],
                             [0.0, 0.0, 1e-6, 1.0]]) for k in range(3)]
    slack = [rng.random(shape) < 0.5 for shape in shapes]
    slack[1] = None
    far_from = [4.0, None, 6.0]
    tol, slack_px = 1.0, 1
    # Per view, the pixels that may see past (voters; None: all).
    voters = [None, None, None]
    if with_voters:
        voters = [rng.random(int(np.prod(shape))) < 0.6 for shape in shapes]
        voters[1] = None
    got = dsm._heights_seen_by_others(
        heights, projections, tol, None, "test", far_from=far_from, slack_px=slack_px,
        slack=slack, voters=voters if with_voters else None,
        reduce=lambda known, agree, past, far: (known, agree, past, far))
    highest = [dsm._highest_within(h, slack_px) for h in heights]
    for k, (h, P) in enumerate(zip(heights, projections)):
        known, agree, past, far = got[k]
        np.testing.assert_array_equal(known, np.isfinite(h))
        want = np.zeros((3,) + h.shape, np.int64)
        for r, c in zip(*np.nonzero(np.isfinite(h))):
            u = h[r, c]
            e, n = dsm_points.solve_ground_en(P, col=float(c), row=float(r), u=u)
            for j, (hj, Pj) in enumerate(zip(heights, projections)):
                if j == k:
                    continue
                q = Pj @ np.array([float(e), float(n), u, 1.0])
                ic, ir = math.floor(q[0] / q[2] + 0.5), math.floor(q[1] / q[2] + 0.5)
                if not (0 <= ic < hj.shape[1] and 0 <= ir < hj.shape[0]):
                    continue
                other = hj[ir, ic]
                below = highest[j][ir, ic] if slack[k] is not None and slack[k][r, c] else other
                vote = voters[j] is None or bool(voters[j][ir * hj.shape[1] + ic])
                want[0, r, c] += abs(other - u) <= tol
                want[1, r, c] += vote and below < u - tol
                want[2, r, c] += vote and far_from[j] is not None and other < u - far_from[j]
        assert want.sum() > 0 and (want[0] < 2).any()
        np.testing.assert_array_equal(agree, want[0])
        np.testing.assert_array_equal(past, want[1])
        np.testing.assert_array_equal(far, want[2])


def test_visibility_slack_options_are_checked():
    with pytest.raises(OptionsError, match="DSMOptions.visibility_slack_px"):
        dsm.DSMOptions(visibility_slack_px=-1)
    with pytest.raises(OptionsError, match="DSMOptions.visibility_slack_confidence"):
        dsm.DSMOptions(visibility_slack_confidence=float("nan"))
    with pytest.raises(OptionsError, match="DSMOptions.visibility_voter_confidence"):
        dsm.DSMOptions(visibility_voter_confidence=-0.1)


def test_step_edge_pixels_are_the_high_side_of_steps():
    """A 10 m box on flat ground, a 1 m kerb and an unknown pixel: the box's outer ring of
    pixels (each with a ground neighbour, diagonals included) and nothing else."""
    h = np.zeros((12, 12))
    h[3:9, 4:10] = 10.0  # the box
    h[:, 0] = 1.0  # a kerb under EDGE_STEP_M
    h[0, 11] = np.nan  # unknown: never an edge, and no neighbour of one
    edges = dsm.step_edge_pixels(h)
    ring = np.zeros_like(edges)
    ring[3:9, 4:10] = True
    ring[4:8, 5:9] = False
    assert np.array_equal(edges, ring)
    # A step of exactly the threshold is no step; a lower threshold finds the kerb.
    assert not dsm.step_edge_pixels(np.array([[0.0, dsm.EDGE_STEP_M]])).any()
    assert dsm.step_edge_pixels(h, step_m=0.5)[:, 0].all()


def test_dense_view_raster_takes_a_crowns_top_over_the_quantile():
    """Per cell the VIEW_RASTER_QUANTILE of its points (rasterise_quantile_cells), or the
    highest of its flagged points (a crown's) where that is higher: a rim cell with one crown
    point among seven ground points takes the crown's height, a cell whose flagged point lies
    below the quantile keeps the quantile, unflagged cells and no flags at all keep it."""
    grid = dsm_grid.DSMGrid(epsg=32740, x_min=100.0, y_max=50.0, resolution=0.5, width=30, height=20)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(100.0, 115.0, 3000), rng.uniform(40.0, 50.0, 3000)
    z = rng.normal(size=3000)
    z[::101] = np.nan
    top = rng.uniform(size=3000) < 0.1
    cells = dsm.flat_cells(x, y, grid)
    quartile = dsm.rasterise_quantile_cells(cells, z, grid)
    per_cell: dict[int, list[float]] = {}
    for c, v, t in zip(cells, z, top):
        if c >= 0 and np.isfinite(v) and t:
            per_cell.setdefault(int(c), []).append(float(v))
    ref = quartile.astype(np.float64).ravel()
    for c, vals in per_cell.items():
        ref[c] = max(ref[c], max(vals))
    got = dsm.rasterise_dense_view_cells(cells, z, grid, top=top)
    np.testing.assert_array_equal(got, ref.reshape(grid.shape).astype(np.float32))
    assert (got > quartile).any() and (got == quartile).sum() > got.size // 2
    np.testing.assert_array_equal(dsm.rasterise_dense_view_cells(cells, z, grid), quartile)
    # A rim cell: seven ground points at 0 m, one crown point at 6 m.
    rim = np.zeros(8)
    rim[3] = 6.0
    one = np.zeros(8, np.int64)
    flags = np.arange(8) == 3
    assert dsm.rasterise_dense_view_cells(one, rim, grid, top=flags).ravel()[0] == 6.0
    assert dsm.rasterise_dense_view_cells(one, rim, grid).ravel()[0] == 0.0
    with pytest.raises(ValueError, match="lengths differ"):
        dsm.rasterise_dense_view_cells(cells, z, grid, top=top[:-1])


def test_dropped_edge_pixels_keep_the_marked_ones():
    """A 10 m box on flat ground whose left half matched poorly: its poorly matched outer ring
    is dropped, unless marked kept (a crown's rim); well matched pixels never are."""
    h = np.zeros((12, 12))
    h[3:9, 4:10] = 10.0
    confidence = np.full(h.shape, 0.5)
    confidence[:, :7] = 0.05
    ring = dsm.step_edge_pixels(h)
    drop = dsm.dropped_edge_pixels(h, confidence, 0.15)
    np.testing.assert_array_equal(drop, ring & (confidence < 0.15))
    assert drop.any() and (ring & ~drop).any()
    keep = np.zeros(h.shape, bool)
    keep[3:9, 4:6] = True
    np.testing.assert_array_equal(dsm.dropped_edge_pixels(h, confidence, 0.15, keep=keep),
                                  ring & (confidence < 0.15) & ~keep)
    assert not dsm.dropped_edge_pixels(h, confidence, 0.0).any()


def test_small_raised_pixels_are_crowns_not_buildings():
    """A 0.5 m map of gently sloping ground (0.01 m per pixel): a 3 m crown (radius) 5 m above
    it, a 20 x 20 m block 10 m above it, a 30 m-deep blunder pixel and unknown pixels. The
    crown's pixels are small and raised; the block (400 m^2) is not, nor the ground around the
    blunder (the median ignores one pixel), nor the unknown ones; a 1.5 m hump is not raised."""
    gsd = 0.5
    rows, cols = np.mgrid[0:120, 0:160]
    ground = 0.01 * cols
    h = ground.copy()
    crown = (rows - 30) ** 2 + (cols - 30) ** 2 <= (3.0 / gsd) ** 2
    h[crown] += 5.0
    block = (rows >= 60) & (rows < 100) & (cols >= 80) & (cols < 120)
    h[block] += 10.0
    hump = (rows - 30) ** 2 + (cols - 120) ** 2 <= 16
    h[hump] += 1.5
    h[10, 100] = -30.0  # a blunder
    h[0:5, 0:5] = np.nan
    small = dsm.small_raised_pixels(h, gsd, 150.0)
    np.testing.assert_array_equal(small, crown)
    # The two steps apart: raised pixels of any area, then the small regions among them.
    raised = dsm.raised_pixels(h, gsd)
    np.testing.assert_array_equal(raised, crown | block)
    np.testing.assert_array_equal(dsm.small_regions(raised, gsd, 150.0), crown)
    assert not dsm.small_regions(raised, gsd, 0.0).any()
    # Larger areas take the block too; 0 m^2 none.
    assert np.array_equal(dsm.small_raised_pixels(h, gsd, 500.0), crown | block)
    assert not dsm.small_raised_pixels(h, gsd, 0.0).any()
    # The area is in square metres: at 0.25 m per pixel the same pixels cover a quarter.
    assert np.array_equal(dsm.small_raised_pixels(h, 0.25, 100.0), crown | block)
    with pytest.raises(ValueError, match="gsd_m"):
        dsm.small_raised_pixels(h, 0.0, 150.0)
    with pytest.raises(ValueError, match="gsd_m"):
        dsm.raised_pixels(h, float("nan"))


def test_green_raised_pixels_are_crowns_in_any_region():
    """A 0.5 m map of flat ground with a 20 x 20 m block 10 m above it, a 5.5 x 6.5 m crown 6 m
    above the ground against its west wall (one raised region of more than 400 m^2), a lone
    crown, lawns at ground level, and a 1 m strip of grass along the block's east wall matched
    at its roof's height; the vegetation index is 0.33 on the crowns and 0.17 on the grass (the
    synthetic scenes' colours), 0.02 elsewhere. The crowns' pixels are green and raised,
    whatever their region's area; the block is raised but not green, the lawns green but not
    raised, the strip narrower than GREEN_TOP_MIN_WIDTH_M, unknown pixels neither."""
    gsd = 0.5
    rows, cols = np.mgrid[0:120, 0:160]
    h = np.zeros(rows.shape)
    veg = np.full(rows.shape, 0.02, np.float32)
    block = (rows >= 60) & (rows < 100) & (cols >= 80) & (cols < 120)
    h[block] = 10.0
    against = (rows >= 74) & (rows < 87) & (cols >= 69) & (cols < 80)
    lone = (rows >= 20) & (rows < 33) & (cols >= 24) & (cols < 37)
    crowns = against | lone
    h[crowns] = 6.0
    veg[crowns] = 0.33
    lawn = (rows >= 10) & (rows < 50) & (cols >= 90) & (cols < 150)
    veg[lawn] = 0.17
    strip = (rows >= 60) & (rows < 100) & (cols >= 120) & (cols < 122)
    h[strip] = 10.0
    veg[strip] = 0.17
    h[0:3, 0:3] = np.nan
    veg[0:3, 0:3] = 0.33
    # The opening's square (odd pixels, 3 at least) is wider than the strip (2 pixels) and no
    # wider than the wide strip below (4).
    side = max(3, 2 * int(0.5 * dsm.GREEN_TOP_MIN_WIDTH_M / gsd) + 1)
    assert 2 < side <= 4
    green = dsm.green_raised_pixels(h, veg, gsd)
    np.testing.assert_array_equal(green, crowns)
    # The raised mask given (the small objects' rule has it) is the one used.
    np.testing.assert_array_equal(
        dsm.green_raised_pixels(h, veg, gsd, raised=dsm.raised_pixels(h, gsd)), crowns)
    np.testing.assert_array_equal(dsm.green_raised_pixels(h, veg, gsd, raised=lone), lone)
    with pytest.raises(ValueError, match="raised"):
        dsm.green_raised_pixels(h, veg, gsd, raised=lone[:-1])
    with pytest.raises(ValueError, match="raised"):  # checked whether or not any pixel is green
        dsm.green_raised_pixels(h, np.zeros_like(veg), gsd, raised=lone[:-1])
    # The small objects' rule (150 m^2) sees the lone crown only: the other joins the block.
    np.testing.assert_array_equal(dsm.small_raised_pixels(h, gsd, 150.0), lone)
    # The strip 2 m wide (4 pixels) counts.
    wide = (rows >= 60) & (rows < 100) & (cols >= 120) & (cols < 124)
    h[wide], veg[wide] = 10.0, 0.17
    np.testing.assert_array_equal(dsm.green_raised_pixels(h, veg, gsd), crowns | wide)
    # An index under the threshold everywhere: none.
    assert not dsm.green_raised_pixels(h, np.full(h.shape, 0.05, np.float32), gsd).any()
    with pytest.raises(ValueError, match="differ in shape"):
        dsm.green_raised_pixels(h, veg[:-1], gsd)


def test_spread_to_footprint_edges_moves_the_selected_pixels_sub_samples_only():
    """Pixels mapped by x = 2 col + 0.5 row, y = -3 row (a sheared footprint), z = the pixel's
    height: the selected pixel's 2 x 2 sub-samples end at +-0.49 px of its centre, the others'
    stay at +-0.25 px."""
    shape = (4, 5)
    height = np.arange(20, dtype=np.float64).reshape(shape)
    pixel = np.array([3, 7, 12])
    r, c = np.divmod(pixel, shape[1])

    def mapped(dc, dr):
        cc, rr = c[:, None] + dc[None, :], r[:, None] + dr[None, :]
        return ((2.0 * cc + 0.5 * rr).ravel(), (-3.0 * rr).ravel(),
                np.repeat(height.ravel()[pixel], dc.size))

    dx, dy = dsm_points._subsample_offsets(2)
    x, y, z = mapped(np.zeros(1), np.zeros(1))
    sx, sy, sz = mapped(dx, dy)
    spix = np.repeat(pixel, 4)
    selected = np.zeros(20, bool)
    selected[7] = True
    ox, oy, oz, opix = dsm_points.spread_to_footprint_edges(
        (x, y, z, pixel), (sx, sy, sz, spix), selected, 2, 0.49)
    ex, ey, ez = mapped(dx / 0.25 * 0.49, dy / 0.25 * 0.49)
    moved = spix == 7
    np.testing.assert_allclose(ox[moved], ex[moved], atol=1e-12)
    np.testing.assert_allclose(oy[moved], ey[moved], atol=1e-12)
    np.testing.assert_array_equal(oz, sz)
    np.testing.assert_array_equal(opix, spix)
    np.testing.assert_array_equal(ox[~moved], sx[~moved])
    np.testing.assert_array_equal(oy[~moved], sy[~moved])
    # One sub-sample per pixel: nothing to move.
    same = dsm_points.spread_to_footprint_edges((x, y, z, pixel), (x, y, z, pixel), selected, 1,
                                                0.49)
    np.testing.assert_array_equal(same[0], x)
    with pytest.raises(ValueError, match="edge_px"):
        dsm_points.spread_to_footprint_edges((x, y, z, pixel), (sx, sy, sz, spix), selected, 2,
                                             0.6)
    with pytest.raises(ValueError, match="no centre"):
        dsm_points.spread_to_footprint_edges((x[:1], y[:1], z[:1], pixel[:1]),
                                             (sx, sy, sz, spix), selected, 2, 0.49)


@pytest.mark.parametrize("radius", [1, 3, 8])
def test_extreme_within_matches_scipy(radius):
    """fusion._max_within / _min_within (OpenCV, float64) against scipy.ndimage's maximum and
    minimum filters with a constant outside, on values with infinities: exactly equal."""
    ndimage = pytest.importorskip("scipy.ndimage")
    rng = np.random.default_rng(radius)
    a = rng.normal(100.0, 20.0, size=(37, 23))
    a[rng.uniform(size=a.shape) < 0.1] = np.inf
    a[rng.uniform(size=a.shape) < 0.1] = -np.inf
    size = 2 * radius + 1
    for ours, fill, ref in ((dsm._max_within, -np.inf, ndimage.maximum_filter),
                            (dsm._min_within, np.inf, ndimage.minimum_filter)):
        expected = ref(a, size=size, mode="constant", cval=fill)
        np.testing.assert_array_equal(ours(a, radius), expected)


def test_dsm_rules_run_without_scipy():
    """SciPy is a test dependency only: the free-space check with its slack, the step edges and
    the small objects run in a process where importing it fails."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['scipy'] = None; sys.modules['scipy.ndimage'] = None\n"
        "import numpy as np\n"
        "from satsweep.products import fusion as f\n"
        "h = np.zeros((40, 40)); h[10:14, 10:14] = 6.0\n"
        "P = np.array([[1.0, 0, 0.1, 0], [0, 1.0, 0, 0], [0, 0, 1e-6, 1.0]])\n"
        "f.visibility_check_heights([h, h], [P, P], tolerance_m=1.0, slack_px=1,\n"
        "                           confidences=[np.ones_like(h)] * 2, slack_min_confidence=0.3)\n"
        "assert f.step_edge_pixels(h).sum() == 12\n"
        "assert f.small_raised_pixels(h, 0.5, 150.0).sum() == 16\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_small_object_area_is_checked():
    with pytest.raises(OptionsError, match="DSMOptions.small_object_area_m2"):
        dsm.DSMOptions(small_object_area_m2=-1.0)
    with pytest.raises(OptionsError, match="DSMOptions.small_object_area_m2"):
        dsm.DSMOptions(small_object_area_m2=float("inf"))


def test_edge_min_confidence_is_checked():
    with pytest.raises(OptionsError, match="edge_min_confidence"):
        dsm.DSMOptions(edge_min_confidence=1.5)
    assert dsm.DSMOptions(edge_min_confidence=0.0).edge_min_confidence == 0.0


def test_vertical_offsets_of_rasters_against_a_plain_loop():
    """Each raster's offset to the reference: the median of their differences over the cells
    where the reference is flat (a building's walls and a NaN's neighbours are not) and the two
    agree within COREGISTER_WINDOW_M (a blunder 5 m off counts for nothing); a raster with
    fewer such cells than COREGISTER_MIN_CELLS keeps offset 0."""
    from satsweep.products.fusion import (COREGISTER_FLAT_M, COREGISTER_MIN_CELLS,
                                          COREGISTER_WINDOW_M, vertical_offsets)

    rng = np.random.default_rng(5)
    ref = np.full((60, 70), 100.0)
    ref[20:40, 25:50] = 112.0  # a building: its walls are steps
    ref[5, 5] = np.nan
    ref += rng.normal(0.0, 0.01, ref.shape)
    shifts = [0.0, 0.23, -0.41]
    dsms = [ref + s + rng.normal(0.0, 0.05, ref.shape) for s in shifts]
    dsms[1][0:10, :] += 5.0  # blunders
    sparse = np.full_like(ref, np.nan)
    sparse[:5, :10] = ref[:5, :10] + 0.3  # 49 flat cells (one next to the NaN), too few
    got = vertical_offsets(dsms + [sparse], ref)
    gy, gx = np.gradient(ref)
    flat = np.hypot(gx, gy) < COREGISTER_FLAT_M
    for k, d in enumerate(dsms + [sparse]):
        e = d - ref
        ok = flat & (np.abs(e) < COREGISTER_WINDOW_M)
        want = float(np.median(e[ok])) if ok.sum() >= COREGISTER_MIN_CELLS else 0.0
        assert got[k] == pytest.approx(want, abs=1e-12)
    np.testing.assert_allclose(got[:3], shifts, atol=0.01)
    assert got[3] == 0.0
    assert not flat[5, 6] and not flat[19, 30]  # beside the NaN, on a wall


def test_leaf_on_crown_tops_raise_crowns_only():
    """0.5 m cells of flat ground at 0 m: the consensus (``fused``) has a crown at the ground's
    height (the leafless dates' view) and a 20 x 20 m block at 10 m. Three views of dates in
    leaf: two of different passes see the crown 6 m up (within the tolerance of each other),
    and all three see the block 3 m above the consensus. The crown's cells take the pair's mean;
    the block (not a small raised object) and the ground keep the consensus. A pair of one pass,
    a pair that disagrees, a rise under LEAF_TOP_RISE_M and views without a known pass raise
    nothing."""
    rows, cols = np.mgrid[0:100, 0:120]
    crown = (rows - 25) ** 2 + (cols - 25) ** 2 <= 6 ** 2  # 3 m radius
    block = (rows >= 50) & (rows < 90) & (cols >= 60) & (cols < 100)
    fused = np.where(block, 10.0, 0.0).astype(np.float32)
    fused[0, 0] = np.nan  # an empty cell stays empty
    a = np.where(crown, 6.2, 0.0) + np.where(block, 3.0, 0.0) + fused
    b = np.where(crown, 5.8, 0.0) + np.where(block, 3.0, 0.0) + fused
    c = np.where(crown, np.nan, 0.0) + np.where(block, 3.0, 0.0) + fused
    kw = dict(tolerance_m=1.0, resolution_m=0.5, max_area_m2=150.0)
    out, raised = dsm.leaf_on_crown_tops(fused, [a, b, c], [0, 1, 2], **kw)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(raised, crown)
    np.testing.assert_allclose(out[crown], 6.0, atol=1e-6)
    np.testing.assert_array_equal(out[~crown], fused[~crown])
    # One pass: one measurement, nothing raised; nor without a known pass.
    assert not dsm.leaf_on_crown_tops(fused, [a, b], [0] * 2, **kw)[1].any()
    assert not dsm.leaf_on_crown_tops(fused, [a, b], [None, 1], **kw)[1].any()
    # Views that disagree by more than the tolerance.
    far = np.where(crown, 9.0, 0.0) + fused
    assert not dsm.leaf_on_crown_tops(fused, [a, far], [0, 1],
                                      **kw)[1].any()
    # A rise of less than LEAF_TOP_RISE_M: the consensus holds the crown already.
    low = fused + np.where(crown, 0.9 * dsm.LEAF_TOP_RISE_M, 0.0)
    assert not dsm.leaf_on_crown_tops(fused, [low, low], [0, 1],
                                      **kw)[1].any()
    # No small raised object without an area.
    assert not dsm.leaf_on_crown_tops(fused, [a, b], [0, 1],
                                      tolerance_m=1.0, resolution_m=0.5,
                                      max_area_m2=0.0)[1].any()


def test_crown_hole_tops_fill_empty_crown_cells_only():
    """0.5 m cells of flat ground at 0 m and a 20 x 20 m block at 10 m; the consensus left a
    crown's cells empty, and a strip of ground beside the block. Two views of different passes
    agree on the crown 6 m up; on the strip they agree on the block's height (its roof seen
    beside its wall). The crown's empty cells take the pair's mean; the strip (part of the
    block's large region) and every known cell keep the consensus, to be filled as before.
    One pass, views without a known pass, or views that disagree fill nothing."""
    rows, cols = np.mgrid[0:100, 0:120]
    crown = (rows - 25) ** 2 + (cols - 25) ** 2 <= 6 ** 2
    block = (rows >= 50) & (rows < 90) & (cols >= 60) & (cols < 100)
    strip = (rows >= 50) & (rows < 90) & (cols >= 100) & (cols < 104)
    truth = np.where(block, 10.0, 0.0) + np.where(crown, 6.0, 0.0)
    fused = np.where(crown | strip, np.nan, truth).astype(np.float32)
    a = truth + np.where(crown, 0.2, 0.0) + np.where(strip, 10.0, 0.0)
    b = truth - np.where(crown, 0.2, 0.0) + np.where(strip, 10.0, 0.0)
    kw = dict(tolerance_m=1.0, resolution_m=0.5, max_area_m2=150.0)
    out, filled = dsm.crown_hole_tops(fused, [a, b], [0, 1], **kw)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(filled, crown)
    np.testing.assert_allclose(out[crown], 6.0, atol=1e-6)
    np.testing.assert_array_equal(out[~crown], fused[~crown])  # NaN where it was empty
    for passes in ([0] * 2, [None, 1]):
        assert not dsm.crown_hole_tops(fused, [a, b], passes, **kw)[1].any()
    far = truth + np.where(crown, 3.0, 0.0)
    assert not dsm.crown_hole_tops(fused, [a, far], [0, 1],
                                   **kw)[1].any()


def test_green_crown_tops_raise_crowns_the_green_views_see():
    """0.5 m cells of flat ground at 0 m: the consensus (``fused``) has a crown at 2 m (between
    the ground that leafless dates see and its top), a hole in the crown, and a 20 x 20 m block
    at 10 m. Views a and a2 see leaves on the crown at 7 and 6.5 m; view b sees the ground
    through it at 0 m (no leaves). Views c and c2 see a roof garden on the block 3 m above the
    consensus, a lawn at the ground's height, and grass in a strip beside the block at the
    roof's height (matched with the roof: one region with it in their rasters). The crown's
    cells (its hole too) take the highest green height, 7 m; every other cell keeps the
    consensus. One green view, views whose index is under VEGETATION_INDEX_MIN, or a rise under
    GREEN_TOP_RISE_M raise nothing."""
    assert dsm.GREEN_MIN_VIEWS == 2
    rows, cols = np.mgrid[0:100, 0:120]
    crown = (rows - 25) ** 2 + (cols - 25) ** 2 <= 6 ** 2  # 3 m radius
    hole = crown & (rows == 25) & (cols >= 24) & (cols <= 26)
    block = (rows >= 50) & (rows < 90) & (cols >= 60) & (cols < 100)
    strip = (rows >= 50) & (rows < 90) & (cols >= 100) & (cols < 104)
    lawn = (rows >= 50) & (rows < 90) & (cols >= 2) & (cols < 40)
    fused = (np.where(block, 10.0, 0.0) + np.where(crown, 2.0, 0.0)).astype(np.float32)
    fused[hole] = np.nan
    fused[0, 0] = np.nan  # an empty cell nobody sees green stays empty
    green, grey = dsm.VEGETATION_INDEX_MIN + 0.05, dsm.VEGETATION_INDEX_MIN - 0.05
    ground = np.where(block, 10.0, 0.0)
    a = np.where(crown, 7.0, ground)
    a2 = np.where(crown, 6.5, ground)
    va = np.where(crown, green, grey)
    b = ground
    vb = np.full(a.shape, grey)
    c = np.where(block | strip, 13.0, 0.0)
    vc = np.where(block | lawn | strip, green, grey)
    kw = dict(resolution_m=0.5, max_area_m2=150.0)
    out, raised = dsm.green_crown_tops(fused, [a, a2, b, c, c], [va, va, vb, vc, vc], **kw)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(raised, crown)
    np.testing.assert_array_equal(out[crown], 7.0)
    np.testing.assert_array_equal(out[~crown], fused[~crown])  # NaN where it was empty
    # One view seeing leaves: nothing; nor two that are not green enough.
    assert not dsm.green_crown_tops(fused, [a, b], [va, va], **kw)[1].any()
    assert not dsm.green_crown_tops(fused, [a, a2], [np.full(a.shape, grey)] * 2, **kw)[1].any()
    # Green but less than GREEN_TOP_RISE_M above the consensus (its empty cells are raised).
    low = np.where(crown, 2.0 + 0.9 * dsm.GREEN_TOP_RISE_M, 0.0)
    np.testing.assert_array_equal(dsm.green_crown_tops(fused, [low, low], [va, va], **kw)[1],
                                  hole)
    # No small raised object without an area.
    assert not dsm.green_crown_tops(fused, [a, a2], [va, va], resolution_m=0.5,
                                    max_area_m2=0.0)[1].any()
    with pytest.raises(ValueError, match="2 rasters but 1 vegetation"):
        dsm.green_crown_tops(fused, [a, a2], [va], **kw)
