"""Tests of satsweep.geometry.camera: DLT, RQ conventions, RPC approximation, skew, plane plus parallax.

References: exact synthetic pinhole cameras (DLT, RQ, skew), the RPC itself at points off the
fitting grid (approximation error), and an independent float64 ray-plane intersection
(homographies).
"""

from __future__ import annotations

import functools
import math
import types

import numpy as np
import pytest

from satsweep.errors import CameraError, OptionsError
from satsweep.geometry import camera as cam
from satsweep.geometry import parallax
from satsweep.geometry import skew as skew_mod
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.geometry.geodesy import ENUFrame
from satsweep.geometry.rpc import RPCModel

# Exact data: the fit is limited by float64 rounding amplified by the conditioning of a
# satellite-like (nearly affine) camera, measured at about 1e-12; 1e-9 leaves a wide margin.
EXACT_REL_TOL = 1e-9
# The bound for the Pleiades pair over 300 m x 80 m (measured: about 0.021 px).
# A fit on 2000 of the 2e5 grid samples against the fit on all: both approximate the same RPC to
# about 0.04 px, so they may differ by a fraction of that.
FIT_SUBSET_TOL_PX = 0.01
PLEIADES_MAX_ERROR_PX = 0.05
# Skew correction is an exact algebraic identity on the cameras: float64 rounding of pixel
# coordinates of about 1e3 px is about 1e-13 px.
SKEW_PX_TOL = 1e-6
# float32 image values of about 1e4 carry a relative rounding of 6e-8 per operation; the four-tap
# interpolation sums four of them.
IMAGE_REL_TOL = 1e-5
# Float64 homographies against the float64 ray-plane truth: both limited by rounding of a camera
# 1500 km away (about 1e-9 px measured).
HOMOGRAPHY_F64_TOL_PX = 1e-6
# The bound for the reparametrised float32 homography (measured: about 5e-5 px) and the
# factor by which it must beat the textbook float32 formula (measured: about 3000).
REPARAM_F32_TOL_PX = 1e-3
REPARAM_GAIN_MIN = 10.0
# rho = zbar (u - d) / depth differs from u - d by the relative depth spread over the AOI, which is
# about (300 m tan(9 deg) + 80 m) / 1500 km ~ 1e-4; a 1e-3 relative bound leaves a margin.
RHO_REL_TOL = 1e-3
# Height from (pixel, rho) through P4^-1 in float64: rounding only.
HEIGHT_TOL_M = 1e-6
# Float64 identities between a few matrix products (K[R|t] = P, R R^T = I, scalings): rounding of
# about 1e-16 times the condition of a satellite camera's matrices (about 1e4 here).
ROUND_REL_TOL = 1e-12
# Pixel identities through a matrix 1500 km away (P4 vs P, identity homography): rounding.
ROUND_PX_TOL = 1e-9
# Camera centre and ray-plane points of the synthetic camera 700 km away: float64 rounding.
ROUND_M_TOL = 1e-6
# Depth along the optical axis vs distance to the centre for a 9-degree off-nadir view of a
# 300 m cube: cos of the angle off the axis (< 0.02 degrees) and the cube's depth spread.
DEPTH_VS_DISTANCE_REL = 2e-3
# The mean error over 5000 random points of the cube estimates the grid's mean error to within
# sampling noise of a few percent.
MEAN_ERROR_REL_TOL = 0.2
# A source column this far beyond the image edge is outside; closer ones are rounding of W.
EDGE_TOL_PX = 1e-6

PAIR_ALT_MIN, PAIR_ALT_MAX, PAIR_ALT_CENTRE = 2300.0, 2380.0, 2340.0  # metres, README of the pair
PAIR_AOI_HALF_SIZE_M = 150.0


# -- synthetic cameras ---------------------------------------------------------------------------
def _look_at(center: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Rotation ENU -> camera (x right, y down, z forward) looking from center at target."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.stack([x, y, z])


def _satellite_camera(*, skew: float = 0.012) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Pleiades-like pinhole camera 700 km away, 9 degrees off nadir, with skew. (K, R, t)."""
    f = 1.4e6
    K = np.array([[f, skew * f, 512.3], [0.0, 1.02 * f, 480.7], [0.0, 0.0, 1.0]])
    centre = np.array([0.12 * 7e5, -0.08 * 7e5, 7e5])
    R = _look_at(centre, np.zeros(3), roll=0.3)
    return K, R, -R @ centre


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    xh = np.hstack([X, np.ones((X.shape[0], 1))]) @ P.T
    return xh[:, :2] / xh[:, 2:]


def _cube_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform([-150.0, -150.0, 0.0], [150.0, 150.0, 80.0], size=(n, 3))


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def test_dlt_recovers_exact_synthetic_camera():
    K, R, t = _satellite_camera()
    P = K @ np.hstack([R, t[:, None]])
    X = _cube_points(np.random.default_rng(1), 2000)
    fitted = cam.normalized_dlt(X, _project(P, X))
    # P up to scale (and sign).
    scale = fitted.ravel() @ P.ravel() / (fitted.ravel() @ fitted.ravel())
    assert _rel(scale * fitted, P) < EXACT_REL_TOL
    P2, K2, R2, t2 = cam.decompose_projection(fitted)
    assert _rel(P2, P) < EXACT_REL_TOL
    assert _rel(K2, K) < EXACT_REL_TOL
    assert abs(K2[0, 1] - K[0, 1]) / K[0, 1] < EXACT_REL_TOL  # the skew is kept, not just K's scale
    assert np.max(np.abs(R2 - R)) < EXACT_REL_TOL
    assert _rel(t2, t) < EXACT_REL_TOL


def test_refinement_converges_back_to_the_exact_camera():
    K, R, t = _satellite_camera()
    P = K @ np.hstack([R, t[:, None]])
    X = _cube_points(np.random.default_rng(2), 2000)
    x = _project(P, X)
    start = P * (1.0 + 1e-4 * np.random.default_rng(3).standard_normal(P.shape))
    assert np.max(np.abs(_project(start, X) - x)) > 0.05  # well above the RPC fitting error
    refined = cam.refine_projection(start, X, x)
    assert _rel(cam.decompose_projection(refined)[0], P) < EXACT_REL_TOL


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_rq_conventions(seed, sign):
    rng = np.random.default_rng(seed)
    P = sign * rng.standard_normal((3, 4)) * rng.uniform(0.1, 1e3)
    P2, K, R, t = cam.decompose_projection(P)
    assert K[0, 0] > 0 and K[1, 1] > 0
    assert K[2, 2] == 1.0
    assert np.allclose(np.tril(K, -1), 0.0, atol=0.0)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=ROUND_REL_TOL)
    assert np.allclose(R @ R.T, np.eye(3), atol=ROUND_REL_TOL, rtol=0)
    assert _rel(K @ np.hstack([R, t[:, None]]), P2) < ROUND_REL_TOL
    # P2 is the input up to a (possibly negative) scale
    ratio = P2 / P
    assert np.allclose(ratio, ratio[0, 0], rtol=ROUND_REL_TOL, atol=0)


@pytest.mark.parametrize("seed", range(4))
def test_rq3_against_scipy(seed):
    """camera._rq3 (numpy QR of the reversed transpose) against scipy.linalg.rq: the same
    factors up to the signs of R's columns / Q's rows, and R Q the input."""
    from scipy.linalg import rq

    A = np.random.default_rng(seed).standard_normal((3, 3)) * 100.0
    R, Q = cam._rq3(A)
    R_ref, Q_ref = rq(A)
    d = np.sign(np.diag(R)) * np.sign(np.diag(R_ref))
    assert np.allclose(np.tril(R, -1), 0.0, atol=0.0)
    assert _rel(R @ Q, A) < ROUND_REL_TOL
    assert _rel(R * d[None, :], R_ref) < ROUND_REL_TOL
    assert _rel(d[:, None] * Q, Q_ref) < ROUND_REL_TOL


def test_camera_accessors_match_the_synthetic_geometry():
    K, R, t = _satellite_camera()
    c = cam.PerspectiveCamera.from_projection(K @ np.hstack([R, t[:, None]]), width=1024, height=1024)
    centre = -R.T @ t
    assert np.allclose(c.center, centre, rtol=0, atol=ROUND_M_TOL)
    X = _cube_points(np.random.default_rng(4), 50)
    col, row = c.project(X[:, 0], X[:, 1], X[:, 2])
    assert np.allclose(np.linalg.norm(X - centre, axis=1), c.depth(*X.T), rtol=DEPTH_VS_DISTANCE_REL)
    e, n = c.backproject(col, row, u=X[:, 2])
    assert np.allclose(e, X[:, 0], atol=ROUND_M_TOL) and np.allclose(n, X[:, 1], atol=ROUND_M_TOL)


def test_options_are_checked():
    with pytest.raises(OptionsError, match="grid_size"):
        cam.CameraOptions(grid_size=(100, 1, 20))
    with pytest.raises(OptionsError, match="plane_margin_m"):
        cam.CameraOptions(plane_margin_m=-5.0)
    with pytest.raises(OptionsError, match="warn_error_px"):
        cam.CameraOptions(warn_error_px=0.0)


# -- the real Pleiades pair ----------------------------------------------------------------------
@pytest.fixture
def pair(pleiades_pair):
    """RPCs, shapes, AOI, altitude range, frame and default-grid cameras of the Pleiades pair."""
    return _pair(pleiades_pair)


@functools.lru_cache(maxsize=None)
def _pair(d):
    """Computed once per session (the default grid takes about a second per view)."""
    rpcs = [RPCModel.from_image(d / f"img_0{i}.tif") for i in (1, 2)]
    shapes = [(1024, 1024), (1102, 1031)]  # (rows, cols), README of the pair
    lon, lat = rpcs[0].localization(col=(shapes[0][1] - 1) / 2, row=(shapes[0][0] - 1) / 2,
                                    alt=PAIR_ALT_CENTRE)
    local = ENUFrame(lon0=float(lon), lat0=float(lat), alt0=PAIR_ALT_CENTRE)
    h = PAIR_AOI_HALF_SIZE_M
    lons, lats, _ = local.to_geodetic(e=np.array([-h, h]), n=np.array([-h, h]), u=0.0)
    aoi = AOI(lons[0], lats[0], lons[1], lats[1])
    alt = AltitudeRange(PAIR_ALT_MIN, PAIR_ALT_MAX)
    frame = cam.frame_for(aoi, alt)
    cams = [cam.approximate_camera(r, frame, aoi, alt, s, name=f"img_0{i + 1}")
            for i, (r, s) in enumerate(zip(rpcs, shapes))]
    grid = cam.aoi_grid(frame, aoi, alt, (10, 10, 5))
    d_plane = float(grid.u.min()) - cam.CameraOptions().plane_margin_m
    projs = [parallax.reparametrise(c, d=d_plane, zbar=float(np.mean(c.depth(grid.e, grid.n, grid.u))))
             for c in cams]
    return types.SimpleNamespace(rpcs=rpcs, shapes=shapes, aoi=aoi, alt=alt, frame=frame, cams=cams,
                                 projs=projs, d=d_plane)


def test_pleiades_approximation_error(pair):
    for c in pair.cams:
        e = c.error
        print(f"approx error: mean {e.mean_px:.4f} median {e.median_px:.4f} max {e.max_px:.4f} px, "
              f"back-projection max {e.backprojection_max_m:.4f} m")
        assert e.n_points == 100 * 100 * 20  # the AOI lies well inside both crops
        assert e.max_px <= PLEIADES_MAX_ERROR_PX
        assert 0.0 < e.median_px <= e.max_px and e.mean_px <= e.max_px
        assert c.K[0, 0] > 0 and c.K[1, 1] > 0 and np.linalg.det(c.R) == pytest.approx(1.0, abs=ROUND_REL_TOL)


def test_fit_on_a_sample_subset_matches_the_whole_grid(pair):
    """The default fit uses a random subset of the grid samples (CameraOptions.fit_samples) but
    reports its errors over all of them; it projects like the fit on every sample to within
    FIT_SUBSET_TOL_PX over the cube."""
    rpc, shape = pair.rpcs[0], pair.shapes[0]
    whole = cam.approximate_camera(rpc, pair.frame, pair.aoi, pair.alt, shape,
                                   cam.CameraOptions(fit_samples=100 * 100 * 20))
    subset = cam.approximate_camera(rpc, pair.frame, pair.aoi, pair.alt, shape,
                                    cam.CameraOptions(fit_samples=2000))
    assert subset.error.n_points == whole.error.n_points == 100 * 100 * 20
    grid = cam.aoi_grid(pair.frame, pair.aoi, pair.alt, (15, 15, 6))
    a = np.stack(whole.project(grid.e, grid.n, grid.u))
    b = np.stack(subset.project(grid.e, grid.n, grid.u))
    assert np.max(np.abs(a - b)) < FIT_SUBSET_TOL_PX
    assert subset.error.max_px <= PLEIADES_MAX_ERROR_PX
    with pytest.raises(OptionsError, match="fit_samples"):
        cam.CameraOptions(fit_samples=3)


def test_pleiades_approximation_off_the_grid(pair):
    """Against the RPC at random points of the cube that are not grid samples."""
    rng = np.random.default_rng(5)
    n = 5000
    lon = rng.uniform(pair.aoi.lon_min, pair.aoi.lon_max, n)
    lat = rng.uniform(pair.aoi.lat_min, pair.aoi.lat_max, n)
    alt = rng.uniform(pair.alt.min, pair.alt.max, n)
    e, nn, u = pair.frame.from_geodetic(lon=lon, lat=lat, alt=alt)
    for rpc, c in zip(pair.rpcs, pair.cams):
        col, row = rpc.projection(lon=lon, lat=lat, alt=alt)
        pc, pr = c.project(e, nn, u)
        err = np.hypot(pc - col, pr - row)
        assert np.max(err) <= PLEIADES_MAX_ERROR_PX
        # the grid statistics describe the error everywhere in the cube
        assert np.mean(err) == pytest.approx(c.error.mean_px, rel=MEAN_ERROR_REL_TOL)


def test_camera_that_does_not_see_the_aoi_is_an_error(pair):
    far = pair.rpcs[0].cropped(x0=50_000, y0=0)
    with pytest.raises(CameraError, match="img_far.*does not see the AOI"):
        cam.approximate_camera(far, pair.frame, pair.aoi, pair.alt, pair.shapes[0],
                               cam.CameraOptions(grid_size=(5, 5, 3)), name="img_far")


def test_mirrored_image_is_an_error(pair):
    rpc, width = pair.rpcs[0], pair.shapes[0][1]

    class Mirrored:
        def projection(self, *, lon, lat, alt):
            col, row = rpc.projection(lon=lon, lat=lat, alt=alt)
            return width - 1 - col, row

    with pytest.raises(CameraError, match="mirrored"):
        cam.approximate_camera(Mirrored(), pair.frame, pair.aoi, pair.alt, pair.shapes[0],
                               cam.CameraOptions(grid_size=(5, 5, 3)))


# -- skew correction -----------------------------------------------------------------------------
def test_skew_correction_cameras(pair):
    c = pair.cams[0]
    assert abs(c.K[0, 1]) > 1e3  # the Pleiades approximation has a real skew (about 0.012 fy)
    image = np.zeros((c.height, c.width), np.uint16)
    _, c2, W = skew_mod.skew_correct(image, c)
    assert c2.K[0, 1] == 0.0 and c2.K[2, 2] == 1.0
    assert np.array_equal(c2.K[1], c.K[1]) and c2.K[0, 0] == c.K[0, 0]
    assert np.allclose(c2.K @ np.hstack([c2.R, c2.t[:, None]]), c2.P, rtol=ROUND_REL_TOL, atol=0)
    X = _cube_points(np.random.default_rng(6), 1000)
    col, row = c.project(*X.T)
    warped = W @ np.stack([col, row, np.ones_like(col)])
    col2, row2 = c2.project(*X.T)
    assert np.max(np.abs(col2 - warped[0] / warped[2])) < SKEW_PX_TOL
    assert np.max(np.abs(row2 - warped[1] / warped[2])) < SKEW_PX_TOL
    # every original pixel lands inside the corrected image
    corners = W @ np.array([[0, c.width - 1, 0, c.width - 1], [0, 0, c.height - 1, c.height - 1], [1, 1, 1, 1]])
    assert corners[0].min() >= 0.0 and corners[0].max() <= c2.width - 1


@pytest.mark.parametrize("skew", [0.012, -0.03])
def test_skew_correction_image(skew):
    """The warped image samples the original at W^-1 pixel: exact for a quadratic image (Keys)."""
    K, R, t = _satellite_camera(skew=skew)
    rows, cols = 200, 300
    c = cam.PerspectiveCamera.from_projection(K @ np.hstack([R, t[:, None]]), width=cols, height=rows)

    def quadratic(col, row):
        return 3e-2 * (col - 100.0) ** 2 + 7.0 * col - 2.0 * row + 1e3

    r, q = np.mgrid[0:rows, 0:cols].astype(np.float64)
    image = np.stack([quadratic(q, r), 2.0 * quadratic(q, r)], axis=2)  # two bands
    warped, c2, W = skew_mod.skew_correct(image, c)
    assert warped.shape == (rows, c2.width, 2) and warped.dtype == np.float32
    r2, q2 = np.mgrid[0:rows, 0:c2.width].astype(np.float64)
    src = np.linalg.solve(W, np.stack([q2.ravel(), r2.ravel(), np.ones(q2.size)]))
    src_col, src_row = src[0].reshape(q2.shape), src[1].reshape(q2.shape)
    interior = (src_col >= 1.0) & (src_col <= cols - 3.0)  # all four taps inside
    expect = quadratic(src_col, src_row)
    assert np.max(np.abs(warped[..., 0][interior] - expect[interior]) / np.abs(expect[interior])) < IMAGE_REL_TOL
    assert np.allclose(warped[..., 1][interior], 2.0 * warped[..., 0][interior], rtol=IMAGE_REL_TOL)
    outside = (src_col < -EDGE_TOL_PX) | (src_col > cols - 1 + EDGE_TOL_PX)
    assert np.all(np.isnan(warped[..., 0][outside])) and not np.any(np.isnan(warped[..., 0][~outside]))


def _shear_reference(image: np.ndarray, shift: np.ndarray, out_width: int) -> np.ndarray:
    """``shear_rows`` pixel by pixel in float64: Keys taps at floor(x) - 1 .. floor(x) + 2 of
    ``x = c + shift[r]``, each index clamped to the row, NaN where x lies outside [0, cols - 1]."""
    rows, cols = image.shape[:2]
    out = np.full((rows, out_width) + image.shape[2:], np.nan)
    for r in range(rows):
        for c in range(out_width):
            x = c + shift[r]
            if x < 0.0 or x > cols - 1:
                continue
            base = math.floor(x)
            w = skew_mod._keys_weights(np.array(x - base))
            taps = [image[r, min(max(base + k - 1, 0), cols - 1)].astype(np.float64) for k in range(4)]
            out[r, c] = sum(w[k] * taps[k] for k in range(4))
    return out


@pytest.mark.parametrize("bands", [0, 3])
def test_shear_rows_resamples_each_row_with_its_shift(bands):
    """Any shifts (a shear's runs of equal whole parts, one per row, beyond either edge)."""
    rng = np.random.default_rng(4)
    rows, cols, out_width = 40, 13, 17
    shape = (rows, cols, bands) if bands else (rows, cols)
    image = rng.integers(0, 4000, shape).astype(np.uint16)
    shift = np.concatenate([np.linspace(-2.3, 4.6, 15),  # a shear: runs of rows
                            rng.uniform(-25.0, 25.0, 16),  # a different window on every row
                            [-40.0, -19.5, -15.5, 12.25, 30.0, 11.999, -16.0, 0.0, 3.5]])  # edges
    got = skew_mod.shear_rows(image, shift, out_width)
    expect = _shear_reference(image, shift, out_width)
    assert got.shape == expect.shape and got.dtype == np.float32
    assert np.array_equal(np.isnan(got), np.isnan(expect))
    inside = ~np.isnan(expect)
    assert np.max(np.abs(got[inside] - expect[inside]) / np.abs(expect[inside]).clip(1.0)) < IMAGE_REL_TOL


# -- plane plus parallax -------------------------------------------------------------------------
def _ray_plane_truth(ref: cam.PerspectiveCamera, src: cam.PerspectiveCamera, col, row, h):
    """Float64 truth: intersect the reference pixel rays with u = h, project into the source."""
    centre = ref.center
    rays = ref.R.T @ np.linalg.solve(ref.K, np.stack([col, row, np.ones_like(col)]))
    lam = (h - centre[2]) / rays[2]
    X = centre[:, None] + lam * rays
    return src.project(X[0], X[1], X[2])


def _apply_h(H: np.ndarray, col, row):
    x = H @ np.stack([col, row, np.ones_like(col)])
    return x[0] / x[2], x[1] / x[2]


def _ref_pixels(shape) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = shape
    c, r = np.meshgrid(np.linspace(0, cols - 1, 33), np.linspace(0, rows - 1, 33))
    return c.ravel(), r.ravel()


def test_reparametrised_matrix(pair):
    c, p = pair.cams[0], pair.projs[0]
    assert np.max(np.abs(p.P4)) == 1.0
    X = _cube_points(np.random.default_rng(7), 500)
    v = p.P4 @ np.vstack([X.T, np.ones(len(X))])
    w = c.depth(*X.T)
    s = p.scale
    col, row = c.project(*X.T)
    assert np.allclose(v[2], s * w, rtol=ROUND_REL_TOL, atol=0)
    assert np.allclose(v[0] / v[2], col, rtol=0, atol=ROUND_PX_TOL)
    assert np.allclose(v[1] / v[2], row, rtol=0, atol=ROUND_PX_TOL)
    assert np.allclose(v[3], s * p.zbar * (X[:, 2] - p.d), rtol=ROUND_REL_TOL, atol=0)
    rho = v[3] / v[2]
    assert np.allclose(rho, X[:, 2] - p.d, rtol=RHO_REL_TOL, atol=0)  # ~ height above the plane
    assert np.all(rho > 0)  # the plane lies below the scene
    assert np.allclose(parallax.height_from_fourth(p, col, row, rho), X[:, 2], rtol=0, atol=HEIGHT_TOL_M)
    assert np.allclose(parallax.fourth_from_height(p, col, row, X[:, 2]), rho, rtol=ROUND_PX_TOL, atol=0)
    e, n, u = parallax.enu_from_fourth(p, col, row, rho)
    assert np.allclose(np.stack([e, n, u], axis=1), X, rtol=0, atol=HEIGHT_TOL_M)


def test_plane_homography_matches_ray_plane_truth(pair):
    (c1, c2), (p1, p2) = pair.cams, pair.projs
    col, row = _ref_pixels(pair.shapes[0])
    heights = np.array([0.0, 17.5, 80.0])  # bottom, inside, top of the altitude range (ENU up, m)
    Hs = parallax.plane_homography(p1, p2, heights)
    assert Hs.shape == (3, 3, 3) and Hs.dtype == np.float64
    for h, H in zip(heights, Hs):
        tc, tr = _ray_plane_truth(c1, c2, col, row, h)
        x, y = _apply_h(H, col, row)
        assert np.max(np.hypot(x - tc, y - tr)) < HOMOGRAPHY_F64_TOL_PX
        single = parallax.plane_homography(p1, p2, h)
        assert single.shape == (3, 3) and np.allclose(single, H, rtol=ROUND_REL_TOL, atol=0)
    # the plane through the reference view itself is the identity (up to scale)
    I = parallax.plane_homography(p1, p1, 40.0)
    assert np.allclose(I / I[2, 2], np.eye(3), rtol=0, atol=ROUND_PX_TOL)


def _textbook_homography(c1: cam.PerspectiveCamera, c2: cam.PerspectiveCamera, h: float, dtype) -> np.ndarray:
    """H = K2 (R + t n^T / d) K1^-1 with camera-centred plane n.X = d, all arithmetic in dtype."""
    K1, K2, R1, R2, t1, t2 = (np.asarray(a, dtype) for a in (c1.K, c2.K, c1.R, c2.R, c1.t, c2.t))
    R = R2 @ R1.T
    t = t2 - R @ t1
    n = R1 @ np.array([0.0, 0.0, 1.0], dtype)  # ENU up in camera-1 coordinates
    d = dtype(h) + n @ t1  # the ENU plane u = h is n.Xc = d in camera-1 coordinates
    return K2 @ (R + np.outer(t, n) / d) @ np.linalg.inv(K1), float(d)


def test_float32_precision_of_reparametrised_homography(pair):
    """Why the kernels get P4 matrices: float32 homographies from them stay at float32 pixel rounding."""
    (c1, c2), (p1, p2) = pair.cams, pair.projs
    col, row = _ref_pixels(pair.shapes[0])
    worst_reparam = worst_textbook = 0.0
    for h in (0.0, 40.0, 80.0):
        tc, tr = _ray_plane_truth(c1, c2, col, row, h)
        H32 = parallax.plane_homography(p1, p2, np.float32(h), dtype=np.float32)
        assert H32.dtype == np.float32
        x, y = _apply_h(H32.astype(np.float64), col, row)
        worst_reparam = max(worst_reparam, float(np.max(np.hypot(x - tc, y - tr))))
        T32, d_cam = _textbook_homography(c1, c2, h, np.float32)
        assert T32.dtype == np.float32
        x, y = _apply_h(T32.astype(np.float64), col, row)
        worst_textbook = max(worst_textbook, float(np.max(np.hypot(x - tc, y - tr))))
        # the textbook formula is right in float64: its float32 error is precision, not a bug
        T64, _ = _textbook_homography(c1, c2, h, np.float64)
        x, y = _apply_h(T64, col, row)
        assert np.max(np.hypot(x - tc, y - tr)) < HOMOGRAPHY_F64_TOL_PX
    report = (f"float32 homography error vs float64 truth: reparametrised {worst_reparam:.2e} px, "
              f"textbook {worst_textbook:.2e} px (camera-centred plane distance {abs(d_cam) / 1e3:.0f} km)")
    print(report)
    assert worst_reparam < REPARAM_F32_TOL_PX, report
    assert worst_reparam * REPARAM_GAIN_MIN < worst_textbook, report


# -- camera sets ---------------------------------------------------------------------------------
def test_build_cameras_and_json_round_trip(pair, tmp_path):
    views = [types.SimpleNamespace(path=f"/data/img_0{i + 1}.tif", image=np.zeros(s, np.uint16),
                                   rpc=r, x0=10 * i, y0=20 * i)
             for i, (r, s) in enumerate(zip(pair.rpcs, pair.shapes))]
    opts = cam.CameraOptions(grid_size=(20, 20, 5))
    cs = cam.build_cameras(views, pair.aoi, pair.alt, opts)
    assert cs.frame.alt0 == pair.alt.min
    assert (cs.frame.lon0, cs.frame.lat0) == pytest.approx(pair.aoi.center, abs=ROUND_REL_TOL)
    assert cs.utm_epsg == 32740  # La Reunion: UTM zone 40 south (README of the pair)
    assert cs.d < -opts.plane_margin_m + 1e-3 and not cs.warnings
    for v, ref in zip(cs.views, pair.cams):
        # same camera as the default grid to well within the approximation error
        X = _cube_points(np.random.default_rng(8), 200)
        assert np.max(np.abs(np.subtract(v.camera.project(*X.T), ref.project(*X.T)))) < 2 * PLEIADES_MAX_ERROR_PX  # both within the bound of the RPC
    back = cam.CameraSet.from_json(cs.to_json())
    assert back.frame == cs.frame and back.utm_epsg == cs.utm_epsg and back.aoi == cs.aoi
    for a, b in zip(back.views, cs.views):
        assert (a.path, a.x0, a.y0) == (b.path, b.x0, b.y0)
        for name in ("K", "R", "t", "P"):
            assert np.array_equal(getattr(a.camera, name), getattr(b.camera, name))
        assert np.array_equal(a.projection.P4, b.projection.P4)
        assert a.camera.error == b.camera.error
    # warnings when the error exceeds the (here tiny) warning level
    noisy = cam.build_cameras(views, pair.aoi, pair.alt, opts.replace(warn_error_px=1e-4))
    assert len(noisy.warnings) == 2 and "tile" in noisy.warnings[0]
    # skew-corrected set: K' skew-free, warp recorded, P4 rebuilt from the new P
    sk, images = skew_mod.skew_correct_set(cs, [v.image for v in views])
    assert all(v.camera.K[0, 1] == 0.0 and v.warp is not None for v in sk.views)
    assert [im.shape[1] for im in images] == [v.camera.width for v in sk.views]
    again = cam.CameraSet.from_json(sk.to_json())
    assert np.array_equal(again.views[0].warp, sk.views[0].warp)


def test_ground_sample_distance_of_an_affine_and_a_perspective_camera():
    from satsweep.geometry.camera import ground_sample_distance

    affine = np.array([[2.0, 0.0, 0.3, 10.0], [0.0, -2.0, 0.1, 5.0], [0.0, 0.0, 0.0, 1.0]])
    assert ground_sample_distance(affine, (0.0, 0.0, 7.0)) == pytest.approx(0.5, rel=1e-12)
    # a camera 1000 m up looking down, focal 2000 px: 0.5 m per pixel on the ground, 0.45 at 100 m
    K = np.array([[2000.0, 0.0, 500.0], [0.0, -2000.0, 500.0], [0.0, 0.0, 1.0]])
    Rt = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 1000.0]])
    assert ground_sample_distance(K @ Rt, (0.0, 0.0, 0.0)) == pytest.approx(0.5, rel=1e-12)
    assert ground_sample_distance(K @ Rt, (0.0, 0.0, 100.0)) == pytest.approx(0.45, rel=1e-12)
