"""Tests of satsweep.sparse: SIFT keypoints, matching and verification, tracks, triangulation.

References: exact synthetic ground truth (blob centres, pinhole cameras and points), the ray-plane
back-projection of satsweep.geometry.camera for epipolar lines, a plain-Python union-find for tracks and
scipy's least_squares for the nonlinear triangulation.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from satsweep.errors import OptionsError
from satsweep.sparse import features as sparse
from satsweep.sparse import matching, options, triangulation
from satsweep.sparse import tracks as sparse_tracks
from tests.synthetic_cameras import project, scene_points, three_cameras

# Gaussian blobs are located by SIFT's quadratic interpolation of the DoG extremum: measured
# errors about 0.01 px, also at half resolution (mapped back); a quarter-pixel convention slip
# would show as 0.25 px, a slip of the resampling's pixel centres as 0.5 px.
BLOB_TOL_PX = 0.05
# Noise-free triangulation: float64 rounding of pixels ~500 px through cameras ~700 km away
# (measured ~1e-7 m); 1e-4 m is still 1000x below anything that matters (GSD 0.5 m).
EXACT_POINT_TOL_M = 1e-4
EXACT_PIXEL_TOL_PX = 1e-6
# Two minimisers of the same reprojection error (ours and scipy's) agree to their convergence
# tolerances; points differ by micrometres (measured ~1e-7 m).
REFINE_TOL_M = 1e-4
# Pixel noise of the synthetic observations (a typical SIFT localisation error).
NOISE_PX = 0.3
# Verification must keep nearly every true match: with 0.3 px noise, a 1.5 px threshold on the
# epipolar distance loses a match with probability ~1e-6; 98 % recall leaves room for the
# random sampling of RANSAC on 400 matches.
MIN_RECALL = 0.98
# A kept match must be consistent with the true geometry: within the verification threshold
# plus the wobble of the estimated offset or affine model (a few tenths of a pixel).
CONSISTENCY_MARGIN_PX = 0.5
# Lucas-Kanade registration of a smooth 8-bit texture: measured errors 0.010 px median, 0.043 px
# at most over 39 points; the keypoints it starts from are 0.4-1.2 px off, and a registration
# that ignored the views' rotation (20 degrees) does not converge to within a pixel.
REGISTRATION_TOL_PX = 0.1
# Grey-level residual (of 255) of those registrations: the 8-bit quantisation and the two
# resamplings of a smooth texture leave about one level (measured at most 1.2).
REGISTERED_RESIDUAL_MAX = 2.0



# -- options -----------------------------------------------------------------------------------
@pytest.mark.parametrize("field,value", [("ratio", 1.5), ("ransac_threshold_px", 0.0),
                                         ("min_matches", 2), ("max_features", 0),
                                         ("contrast_threshold", -1.0), ("geometric_model", "homography")])
def test_options_name_the_bad_field(field, value):
    with pytest.raises(OptionsError, match=field):
        options.SparseOptions(**{field: value})


# -- features ----------------------------------------------------------------------------------
@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_keypoints_follow_the_pixel_centre_convention(scale):
    """Blobs centred at known sub-pixel positions are found there (pixel (0,0) = first centre),
    also when SIFT runs on the image resampled by half and its keypoints are mapped back."""
    rows, cols = np.mgrid[0:200, 0:200].astype(np.float64)
    centres = np.array([[40.3, 50.8], [120.0, 45.25], [60.7, 150.1], [150.45, 139.6]])  # (col, row)
    image = np.zeros((200, 200))
    for cx, cy in centres:
        image += np.exp(-((cols - cx) ** 2 + (rows - cy) ** 2) / (2 * 3.0 ** 2))
    xy, desc = sparse.detect_features(image, max_features=100, contrast_threshold=0.01,
                                      scale=scale)
    assert desc.shape == (len(xy), 128) and desc.dtype == np.float32
    for c in centres:
        d = np.hypot(*(xy - c).T)
        assert d.min() < BLOB_TOL_PX, (c, xy[np.argmin(d)])


def test_small_views_keep_full_resolution_features():
    o = options.SparseOptions(feature_scale=0.5, feature_scale_min_px=512)
    assert sparse.feature_scale_for((511, 2000), o) == 1.0
    assert sparse.feature_scale_for((512, 600), o) == 0.5
    assert sparse.feature_scale_for((300, 300), o.replace(feature_scale_min_px=0)) == 0.5


def test_blank_image_has_no_features():
    xy, desc = sparse.detect_features(np.zeros((64, 80), np.float32), max_features=100)
    assert xy.shape == (0, 2) and desc.shape == (0, 128)


def test_max_features_caps_the_keypoints():
    rng = np.random.default_rng(0)
    image = rng.random((200, 200))
    xy, _ = sparse.detect_features(image, max_features=50)
    # OpenCV keeps ties at the cut-off and splits multi-orientation keypoints: a few extra.
    assert 40 <= len(xy) <= 60


class _PlaneCamera:
    """A camera whose ground plane u = 0 maps to pixels by the 3x3 ``H`` (columns e, n, 1)."""

    def __init__(self, H):
        self.P = np.column_stack([H[:, 0], H[:, 1], np.zeros(3), H[:, 2]])


def test_refinement_registers_tie_points_across_rotated_views():
    """View 1 is view 0 rotated by 20 degrees, scaled by 1.03 and moved, as its camera says,
    plus a pointing error the camera does not know; observations of view 1 given 0.4-1.2 px off
    come back to the exact transform of view 0's points; one given 5 px off is dropped."""
    import cv2

    rng = np.random.default_rng(7)
    texture = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 2.0)
    image0 = (texture - texture.min()) / np.ptp(texture)
    a = np.deg2rad(20.0)
    A = 1.03 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H1 = np.eye(3)
    H1[:2, :2], H1[:2, 2] = A, [60.0, -40.0]
    pointing = np.array([0.37, -0.21])  # the view-1 error the cameras do not know
    M = np.hstack([A, (H1[:2, 2] + pointing)[:, None]])  # view 0 pixels -> view 1 pixels
    image1 = cv2.warpAffine(image0, M, (300, 300), flags=cv2.INTER_CUBIC)
    cams = [_PlaneCamera(np.eye(3)), _PlaneCamera(H1)]

    xy0 = rng.uniform(100.0, 200.0, (40, 2))
    truth = xy0 @ A.T + M[:, 2]
    angle = rng.uniform(0.0, 2 * np.pi, 40)
    off = rng.uniform(0.4, 1.2, 40)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    off[5] = [5.0, 0.0]  # a wrong match
    obs = sparse_tracks.Observations(point=np.repeat(np.arange(40), 2), view=np.tile([0, 1], 40),
                              xy=np.stack([xy0, truth + off], axis=1).reshape(-1, 2), n_points=40)
    refined, dropped = sparse_tracks.refine_observations(obs, [image0, image1], cams, window_px=15,
                                                  max_shift_px=2.0)
    assert dropped == 1 and refined.n_points == 39
    again, residual, _ = sparse_tracks.register_observations(obs, [image0, image1], cams,
                                                             window_px=15, max_shift_px=2.0)
    np.testing.assert_array_equal(again.xy, refined.xy)
    # first observations have none; the others that of a smooth texture quantised to 8 bits and
    # resampled twice (measured at most 1.2 grey levels of 255)
    assert (residual[0::2] == 0).all() and residual[1::2].max() < REGISTERED_RESIDUAL_MAX
    keep = np.arange(40) != 5
    np.testing.assert_array_equal(refined.xy[0::2], xy0[keep])  # first observations stay
    err = np.hypot(*(refined.xy[1::2] - truth[keep]).T)
    assert err.max() < REGISTRATION_TOL_PX, err.max()


# lucas_kanade_in_patches against OpenCV's Lucas-Kanade on the whole images: away from the
# images' borders the patches hold every pixel it reads, so a window ends where it ends on the
# whole images up to float32's rounding of its positions (the patches give them in smaller
# coordinates), which can end its iterations a step earlier or later: within a few of
# Lucas-Kanade's last steps (below _LK_EPS_PX, 0.001 px; measured 0.0006 px at most here, 0.0035
# px on a smaller texture of the same kind).
PATCH_LK_TOL_PX = 10 * sparse_tracks._LK_EPS_PX


def _patch_lk_case(n_points=20, seed=3):
    """A smooth 8-bit texture (head, 1000 x 960 px) and the view it becomes under a homography
    (other; head's pixels -> other's: rotated 20 degrees about the centre, scaled, moved and
    tilted), and ``n_points`` points."""
    import cv2

    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((960, 1000)).astype(np.float32), (0, 0), 2.0)
    head = np.clip((texture - texture.min()) / np.ptp(texture) * 255, 0, 255).astype(np.uint8)
    a = np.deg2rad(20.0)
    to_origin, rotate, back = np.eye(3), np.eye(3), np.eye(3)
    to_origin[:2, 2] = [-500.0, -480.0]
    rotate[:2, :2] = 1.03 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    back[:2, 2], back[2, :2] = [503.3, 477.6], [6e-6, -3e-6]
    H = back @ rotate @ to_origin
    other = cv2.warpPerspective(head, H, (1000, 960), flags=cv2.INTER_CUBIC)
    xy = np.c_[rng.uniform(0.0, 999.0, n_points), rng.uniform(0.0, 959.0, n_points)]
    return head, other, H, xy, rng


def _whole_image_lk(head, other, H, centre, start, window_px):
    """OpenCV's Lucas-Kanade on head and the whole of other warped into head's pixels."""
    import cv2

    h, w = head.shape
    warped = cv2.warpPerspective(other, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        head, warped, centre.astype(np.float32).reshape(-1, 1, 2),
        start.astype(np.float32).reshape(-1, 1, 2), winSize=(window_px, window_px),
        maxLevel=sparse_tracks._LK_LEVELS, criteria=_LK_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    return found.reshape(-1, 2).astype(np.float64), status.ravel() == 1


_LK_CRITERIA = (3, sparse_tracks._LK_ITERATIONS, sparse_tracks._LK_EPS_PX)  # COUNT | EPS


@pytest.mark.parametrize("n_points,per_observation,on_patches", [(20, False, True),
                                                                 (20, True, True),
                                                                 (150, False, False)])
def test_lucas_kanade_in_patches_matches_the_whole_images(monkeypatch, n_points, per_observation,
                                                          on_patches):
    """Windows at 4 offsets from each point (or each observation its own 4 offsets), their
    starts 0-1.2 px off: away from the borders, every window that converges on the whole images
    within _LK_MOTION_PX of its start converges on the patches too, to the same place, and most
    of them to their true places (the warped texture is head itself). 150 points' patches would
    hold more than _PATCH_SHARE_MAX of the image's pixels: those run on the whole images."""
    import cv2

    head, other, H, xy, rng = _patch_lk_case(n_points)
    offsets = np.array([[0.0, 0.0], [6.0, 0.0], [-6.0, 6.0], [8.0, 8.0]])[:, None, :]
    if per_observation:
        offsets = offsets + rng.integers(-3, 4, (4, len(xy), 2))
    centre = xy[None] + offsets  # (k, n, 2)
    start = centre + rng.uniform(-1.2, 1.2, centre.shape)
    window = 13
    warps = []  # the sizes warped: the patches or the whole image

    def warp(image, M, size, **kwargs):
        warps.append(tuple(size))
        return warp_perspective(image, M, size, **kwargs)

    warp_perspective = cv2.warpPerspective
    monkeypatch.setattr(cv2, "warpPerspective", warp)
    found, status = sparse_tracks.lucas_kanade_in_patches(head, other, H, centre, start, window,
                                                          _LK_CRITERIA)
    monkeypatch.undo()
    assert ((1000, 960) not in warps) == on_patches
    whole, whole_status = _whole_image_lk(head, other, H, centre, start, window)
    c, s = centre.reshape(-1, 2), start.reshape(-1, 2)
    margin = sparse_tracks._lk_reach_px(window) + sparse_tracks._LK_MOTION_PX
    inner = ((c >= margin) & (c < np.array([1000, 960]) - margin)).all(axis=1)
    converged = whole_status & (np.hypot(*(whole - s).T) < sparse_tracks._LK_MOTION_PX) & inner
    assert converged.sum() > 0.5 * len(c)  # the interior's windows are most of them
    assert status[converged].all()
    np.testing.assert_allclose(found[converged], whole[converged], atol=PATCH_LK_TOL_PX)
    # And they are where the texture is: Lucas-Kanade alone (before the sub-pixel step) leaves
    # most within a tenth of a pixel of it (a few of these windows find another minimum).
    err = np.hypot(*(found[converged] - c[converged]).T)
    assert np.median(err) < REGISTRATION_TOL_PX, np.median(err)


def test_lucas_kanade_in_patches_fails_windows_outside_the_image():
    """A window centred more than OpenCV's bound outside the image (its top-left corner more
    than a window out) fails as it does on the whole images, and so does one whose start is not
    finite; the others of the call are unaffected."""
    head, other, H, xy, _ = _patch_lk_case()
    centre = np.array([[[150.2, 160.7], [-9.0, 100.0], [120.0, 970.0], [100.0, 100.0]]])
    start = centre + 0.4
    start[0, 3] = np.nan
    found, status = sparse_tracks.lucas_kanade_in_patches(head, other, H, centre, start, 13,
                                                          _LK_CRITERIA)
    whole, whole_status = _whole_image_lk(head, other, H, centre[:, :3], start[:, :3], 13)
    np.testing.assert_array_equal(status, [True, False, False, False])
    np.testing.assert_array_equal(whole_status, [True, False, False])
    np.testing.assert_allclose(found[0], whole[0], atol=PATCH_LK_TOL_PX)
    assert np.isnan(found[3]).all()


def _step(seed=3):
    """Two surfaces whose parallax differs, meeting at column 100 of view 0: view k sees the
    left one moved by STEP_LEFT_MOVES[k] and the right one (raised: its edge moves with it) by
    STEP_RIGHT_MOVES[k], which the cameras (the identity) do not know."""
    import cv2

    rng = np.random.default_rng(seed)

    def texture():
        t = cv2.GaussianBlur(rng.random((200, 200)).astype(np.float32), (0, 0), 1.5)
        return (t - t.min()) / np.ptp(t)

    left, right = texture(), texture()
    cols = np.arange(200)[None, :]

    def moved(image, move):
        return cv2.warpAffine(image, np.hstack([np.eye(2), np.asarray(move)[:, None]]),
                              (200, 200), flags=cv2.INTER_CUBIC)

    images = [np.where(cols < 100 + r[0], moved(left, m), moved(right, r))
              for m, r in zip(STEP_LEFT_MOVES, STEP_RIGHT_MOVES)]
    return images, [_PlaneCamera(np.eye(3)) for _ in images]


# The step's two surfaces' moves from view 0 to views 0, 1, 2 (px): 1.3 px apart along the
# rows in view 1, 1.2 px in view 2, as two surfaces a few metres apart in pairs of
# base-to-height 0.2-0.3 at 0.5 m pixels.
STEP_LEFT_MOVES = np.array([[0.0, 0.0], [0.3, 0.2], [-0.4, 0.1]])
STEP_RIGHT_MOVES = np.array([[0.0, 0.0], [1.6, -0.1], [-1.6, 0.3]])


def _step_tracks(n_views: int):
    """Tracks of ``n_views`` views over the step: 13 on the edge (column 99.6), 13 inside the
    left surface, each view's observation 0.5 px off its point's."""
    rows = np.linspace(40.0, 160.0, 13)
    xy0 = np.vstack([np.column_stack([np.full(13, 99.6), rows]),
                     np.column_stack([np.full(13, 50.0), rows])])
    n = len(xy0)
    xy = np.stack([xy0 + (0.0 if k == 0 else 0.5) for k in range(n_views)], axis=1)
    return sparse_tracks.Observations(point=np.repeat(np.arange(n), n_views),
                                      view=np.tile(np.arange(n_views), n),
                                      xy=xy.reshape(-1, 2), n_points=n)


@pytest.mark.parametrize("beside_px, probes, finalists",
                         [(0.0, 5, 2), (6.0, 5, 2), (6.0, 1, 2), (6.0, 1, 1)])
def test_a_tie_point_on_an_edge_is_registered_by_a_window_beside_it(beside_px, probes,
                                                                    finalists, monkeypatch):
    """Tracks of three views on the edge between two surfaces: the centred window straddles
    both and registers neither surface's move; windows 6 px beside lie over one, and each track
    takes one of the two surfaces' moves in both other views. Points inside the left surface
    get its move either way. With one probe per track (BESIDE_PROBES), the windows are compared
    on one other view and the third is registered by the BESIDE_FINALISTS best of them (one:
    by the best alone): each track on one surface in both views all the same."""
    monkeypatch.setattr(sparse_tracks, "BESIDE_PROBES", probes)
    monkeypatch.setattr(sparse_tracks, "BESIDE_FINALISTS", finalists)
    images, cams = _step()
    obs = _step_tracks(3)
    choice = {}
    got, _, dropped = sparse_tracks.register_observations(
        obs, images, cams, window_px=9, max_shift_px=3.0, beside_px=beside_px, choice=choice)
    assert dropped == 0
    xy = got.xy.reshape(-1, 3, 2)
    for k in (1, 2):
        move = xy[:, k] - xy[:, 0]
        off_left = np.hypot(*(move - STEP_LEFT_MOVES[k]).T)
        off_right = np.hypot(*(move - STEP_RIGHT_MOVES[k]).T)
        assert off_left[13:].max() < REGISTRATION_TOL_PX, (k, off_left[13:])
        nearest = np.minimum(off_left, off_right)[:13]
        if beside_px:
            assert nearest.max() < REGISTRATION_TOL_PX, (k, nearest)
        else:  # the centred window: a compromise, far from both on most of the edge's points
            assert np.median(nearest) > 3 * REGISTRATION_TOL_PX, (k, nearest)
    if beside_px:
        left = np.hypot(*(xy[:13, 1] - xy[:13, 0] - STEP_LEFT_MOVES[1]).T) < REGISTRATION_TOL_PX
        left2 = np.hypot(*(xy[:13, 2] - xy[:13, 0] - STEP_LEFT_MOVES[2]).T) < REGISTRATION_TOL_PX
        np.testing.assert_array_equal(left, left2)  # each track: one surface in every view
        assert choice["beside_points"] >= 13 and choice["points"] == obs.n_points
    else:
        assert choice["beside_points"] is None


def test_tracks_of_two_views_keep_the_centred_window():
    """BESIDE_MIN_VIEWS: a track of two views keeps its centred window's registration."""
    assert sparse_tracks.BESIDE_MIN_VIEWS == 3
    images, cams = _step()
    obs = _step_tracks(2)
    centred, _, _ = sparse_tracks.register_observations(obs, images[:2], cams[:2], window_px=9,
                                                        max_shift_px=3.0)
    choice = {}
    beside, _, _ = sparse_tracks.register_observations(obs, images[:2], cams[:2], window_px=9,
                                                       max_shift_px=3.0, beside_px=6.0,
                                                       choice=choice)
    np.testing.assert_array_equal(beside.xy, centred.xy)
    assert choice["beside_points"] == 0


def _two_dates(brighter, xy0, seed=7):
    """View 0 (a blurred noise texture) and view 1: view 0 moved by a known sub-pixel translation
    (the cameras know its integer part), its grey levels 0.5 + 0.4 x view 0's (another date:
    brighter, less contrast) where ``brighter`` (a function of the column) is true; the pair's
    observations at view 0's ``xy0``. Returns images, cameras, observations and the move."""
    import cv2

    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 2.0)
    image0 = (texture - texture.min()) / np.ptp(texture)
    move = np.array([3.3, -2.6])  # view 0 pixels -> view 1 pixels; the cameras know 3, -2
    image1 = np.clip(cv2.warpAffine(image0, np.hstack([np.eye(2), move[:, None]]), (300, 300),
                                    flags=cv2.INTER_CUBIC), 0.0, 1.0)
    other = brighter(np.arange(300))[None, :]
    image1 = np.where(other, 0.5 + 0.4 * image1, image1)
    H1 = np.eye(3)
    H1[:2, 2] = [3.0, -2.0]
    cams = [_PlaneCamera(np.eye(3)), _PlaneCamera(H1)]
    n = len(xy0)
    obs = sparse_tracks.Observations(point=np.repeat(np.arange(n), 2), view=np.tile([0, 1], n),
                                     xy=np.stack([xy0, xy0 + H1[:2, 2]], axis=1).reshape(-1, 2),
                                     n_points=n)
    return [image0, image1], cams, obs, move


def test_registration_of_another_dates_pair_on_local_contrast():
    """A pair whose grey levels differ (another date) is registered wholly on both views' local
    contrast: Lucas-Kanade on the grey levels loses most tie points or leaves residuals of 36-50
    levels of 255, above _CONTRAST_PAIR_RESIDUAL; on local contrast every one comes back to the
    truth, whatever share best_registered will keep."""
    xy0 = np.random.default_rng(3).uniform(60.0, 240.0, (40, 2))
    images, cams, obs, move = _two_dates(lambda col: np.ones(col.shape, bool), xy0)
    for keep_fraction in (1.0, 0.1):
        registered, residual, dropped = sparse_tracks.register_observations(
            obs, images, cams, window_px=15, max_shift_px=2.0, keep_fraction=keep_fraction)
        assert registered.n_points == 40 and dropped == 0
        assert (residual[1::2] >= sparse_tracks.CONTRAST_RANK).all()
        err = np.hypot(*(registered.xy[1::2] - (registered.xy[0::2] + move)).T)
        assert err.max() < REGISTRATION_TOL_PX, err.max()


class _AffineCamera:
    """A satellite-like affine camera: pixels = A (e, n, u) + b (its P's last row 0 0 0 1)."""

    def __init__(self, A, b):
        self.A = np.asarray(A, np.float64)
        self.P = np.vstack([np.c_[self.A, b], [0.0, 0.0, 0.0, 1.0]])

    def project(self, X):
        return X @ self.A.T + self.P[:2, 3]


def test_across_spread_measures_the_scatter_across_epipolar_lines():
    """across_spread is the median absolute deviation of the tie points' offsets across the
    epipolar lines: heights (along the lines) and one shift of the whole view (the relative
    pointing) leave it at zero, offsets across them give their own MAD. The epipolar direction
    of the reference is derived here otherwise: the image in view v of the direction that view
    w's affine camera does not see (the null vector of its 2 x 3 block)."""
    w = _AffineCamera([[2.0, 0.0, 0.1], [0.0, 2.0, -0.2]], [500.0, 500.0])
    v = _AffineCamera([[2.0, 0.05, 0.6], [-0.05, 2.0, 0.3]], [480.0, 510.0])
    rng = np.random.default_rng(5)
    X = np.c_[rng.uniform(-100.0, 100.0, (9, 2)), rng.uniform(0.0, 40.0, 9)]
    ray = np.cross(w.A[0], w.A[1])
    t = v.A @ ray
    normal = np.array([-t[1], t[0]]) / np.hypot(*t)
    xy_w, xy_v = w.project(X), v.project(X) + [0.7, -0.4]
    assert sparse_tracks.across_spread(w, v, xy_w, xy_v) == pytest.approx(0.0, abs=1e-9)
    across = np.array([0.1, -0.1, 0.3, -0.3, 0.2, 0.0, 0.05, -0.25, 0.4])
    expected = np.median(np.abs(across - np.median(across)))
    moved = xy_v + across[:, None] * normal
    assert sparse_tracks.across_spread(w, v, xy_w, moved) == pytest.approx(expected, abs=1e-9)
    # the same offsets along the lines: heights, nothing to measure
    along = xy_v + across[:, None] * t / np.hypot(*t)
    assert sparse_tracks.across_spread(w, v, xy_w, along) == pytest.approx(0.0, abs=1e-9)
    # one viewpoint (no parallax): the whole 2-D offsets' spread around their median
    deviation = np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.2], [0.0, -0.2], [0.0, 0.0]])
    assert sparse_tracks.across_spread(w, w, xy_w[:5], xy_w[:5] + [0.7, -0.4] + deviation) \
        == pytest.approx(0.1, abs=1e-9)


def test_registration_failures_fall_back_to_local_contrast():
    """In a pair whose grey levels mostly agree (view 1's right part alone is of another date),
    the observations the grey levels lose are registered again on local contrast and ranked
    after every grey-level one, when best_registered would otherwise keep too few of the pair;
    not when the grey levels registered enough."""
    rng = np.random.default_rng(3)
    xy0 = np.concatenate([np.column_stack([rng.uniform(40.0, 120.0, 26), rng.uniform(40.0, 260.0, 26)]),
                          np.column_stack([rng.uniform(190.0, 260.0, 14), rng.uniform(40.0, 260.0, 14)])])
    images, cams, obs, move = _two_dates(lambda col: col >= 155, xy0)
    registered, residual, dropped = sparse_tracks.register_observations(
        obs, images, cams, window_px=15, max_shift_px=2.0)
    second = residual[1::2] >= sparse_tracks.CONTRAST_RANK
    assert registered.n_points == 40 and dropped == 0
    assert second[26:].sum() >= 10 and not second[:26].any(), second
    assert residual[1::2][~second].max() < residual[1::2][second].min()
    err = np.hypot(*(registered.xy[1::2] - (registered.xy[0::2] + move)).T)
    assert err[second].max() < REGISTRATION_TOL_PX, err[second].max()
    assert err[:26].max() < REGISTRATION_TOL_PX, err[:26].max()  # (one window of the right
    # part converges on the grey levels, 1.75 px off with a residual of 65 levels: ranked last
    # of the grey-level ones, it is left out by best_registered's usual fraction)
    fewer, residual, dropped = sparse_tracks.register_observations(
        obs, images, cams, window_px=15, max_shift_px=2.0, keep_fraction=0.1)
    assert fewer.n_points == 40 - second.sum() and dropped == second.sum()
    assert (residual < sparse_tracks.CONTRAST_RANK).all()


def test_registration_residuals_choose_the_best_registered():
    """register_observations reports each observation's window residual; best_registered keeps,
    per pair of views, the given fraction with the lowest residuals (and at least a floor)."""
    rng = np.random.default_rng(11)
    n = 40
    point = np.repeat(np.arange(n), 3)
    view = np.tile([0, 1, 2], n)
    obs = sparse_tracks.Observations(point=point, view=view, xy=rng.uniform(0, 100, (3 * n, 2)),
                                     n_points=n)
    residual = rng.random(3 * n)
    residual[view == 0] = 0.0
    best = sparse_tracks.best_registered(obs, residual, 0.25)
    for v in (1, 2):
        mine = residual[view == v]
        kept = np.isin(obs.xy[view == v][:, 0], best.xy[best.view == v][:, 0])
        assert kept.sum() == 10 and mine[kept].max() <= mine[~kept].min()
    assert best.n_points == len(np.unique(best.point)) and (np.bincount(best.point) >= 2).all()
    assert len(sparse_tracks.best_registered(obs, residual, 0.25, at_least=30).view) > len(best.view)
    assert sparse_tracks.best_registered(obs, residual, 1.0) is obs


def test_subset_index_follows_subset():
    rng = np.random.default_rng(12)
    obs = sparse_tracks.Observations(point=np.repeat(np.arange(30), 3), view=np.tile([0, 1, 2], 30),
                                     xy=rng.random((90, 2)), n_points=30)
    keep = rng.random(90) < 0.6
    sub = obs.subset(keep)
    index = obs.subset_index(keep)
    np.testing.assert_array_equal(sub.xy, obs.xy[index])
    np.testing.assert_array_equal(sub.view, obs.view[index])


def _random_tracks(rng, n_points, n_views):
    """Observations of tracks of 2..n_views distinct views each, grouped by point."""
    point, view = [], []
    for p in range(n_points):
        k = int(rng.integers(2, n_views + 1))
        vs = np.sort(rng.choice(n_views, size=k, replace=False))
        point += [p] * k
        view += vs.tolist()
    return sparse_tracks.Observations(point=np.array(point), view=np.array(view),
                                      xy=rng.random((len(view), 2)), n_points=n_points)


@pytest.mark.parametrize("per_view", [1, 7, 40, 1000])
def test_thin_points_against_a_loop_over_the_views(per_view):
    """Every view keeps at least min(per_view, its observations); a point kept keeps all its
    observations; each view's choice is its longest tracks (checked by a plain loop)."""
    rng = np.random.default_rng(3)
    obs = _random_tracks(rng, 300, 9)
    thin = sparse_tracks.thin_points(obs, per_view)
    length = np.bincount(obs.point)
    scramble = (np.arange(obs.n_points, dtype=np.uint64) * np.uint64(2654435761)) % np.uint64(2**32)
    wanted = set()
    for v in range(9):
        mine = sorted(obs.point[obs.view == v].tolist(), key=lambda p: (-length[p], scramble[p]))
        wanted.update(mine[:per_view])
    expected = obs.subset(np.isin(obs.point, sorted(wanted)))
    np.testing.assert_array_equal(sparse_tracks.thin_mask(obs, per_view),
                                  np.isin(obs.point, sorted(wanted)))
    np.testing.assert_array_equal(thin.view, expected.view)
    np.testing.assert_array_equal(thin.xy, expected.xy)
    np.testing.assert_array_equal(thin.point, expected.point)
    have, had = np.bincount(thin.view, minlength=9), np.bincount(obs.view, minlength=9)
    assert (have >= np.minimum(per_view, had)).all()
    # whole tracks: each kept point has as many observations as before
    kept_points = np.unique(obs.point[np.isin(obs.point, sorted(wanted))])
    np.testing.assert_array_equal(np.bincount(thin.point), length[kept_points])
    if per_view >= had.max():
        assert thin.view.shape == obs.view.shape


@pytest.mark.parametrize("per_track", [0, 1, 3, 8])
def test_beside_probes_against_a_loop_over_the_points(per_track):
    """Each track's first observation and up to per_track others, in the fixed pseudo-random
    order of (point, view) (checked by a plain loop)."""
    rng = np.random.default_rng(5)
    V = 9
    obs = _random_tracks(rng, 300, V)
    probe = sparse_tracks.beside_probes(obs.point, obs.view, per_track)
    expected = np.zeros(len(obs.view), bool)
    for p in range(obs.n_points):
        mine = np.flatnonzero(obs.point == p)
        others = sorted(mine[1:], key=lambda i: (int(p) * V + int(obs.view[i])) * 2654435761 % 2**32)
        expected[mine[:1]] = True
        expected[others[:per_track]] = True
    np.testing.assert_array_equal(probe, expected)
    per = np.bincount(obs.point[probe], minlength=obs.n_points)
    assert (per == np.minimum(np.bincount(obs.point, minlength=obs.n_points), per_track + 1)).all()


def test_thin_points_prefers_long_tracks_and_zero_keeps_all():
    rng = np.random.default_rng(4)
    obs = _random_tracks(rng, 200, 6)
    assert sparse_tracks.thin_points(obs, 0) is obs
    thin = sparse_tracks.thin_points(obs, 5)
    assert np.bincount(thin.point).mean() > np.bincount(obs.point).mean()
    with pytest.raises(OptionsError, match="fine_points_per_view"):
        options.SparseOptions(fine_points_per_view=-1)


def _pinhole(rng, k):
    """A 3x4 camera at about 600 km looking at the ENU origin from up to ~17 degrees off nadir."""
    tilt, az = rng.uniform(0.0, 0.3), rng.uniform(0.0, 2 * np.pi)
    d = np.array([np.sin(tilt) * np.sin(az), np.sin(tilt) * np.cos(az), np.cos(tilt)])
    C = 6.0e5 * d
    z = -d  # the optical axis, towards the origin
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: image x, image y, depth
    K = np.array([[1.2e6, 0.0, 100.0 + 10 * k], [0.0, 1.2e6, 90.0], [0.0, 0.0, 1.0]])
    return K @ np.hstack([R, -(R @ C)[:, None]])


def test_extend_tracks_adds_each_point_in_the_views_that_miss_it():
    """Points observed (exactly) in some of 5 views get an observation at their projection in
    each other view where it lies margin_px inside the image, at most per_view per view (the
    fixed pseudo-random order), after their own; checked by a plain loop."""
    from satsweep.sparse.triangulation import project

    rng = np.random.default_rng(7)
    V, N, shape, margin = 5, 60, (200, 220), 11.0
    P = np.stack([_pinhole(rng, k) for k in range(V)])
    X = np.c_[rng.uniform(-40, 40, (N, 2)), rng.uniform(0, 30, N)]
    point, view = [], []
    for p in range(N):
        for v in sorted(rng.choice(V, size=rng.integers(2, 4), replace=False)):
            point.append(p)
            view.append(v)
    point, view = np.array(point), np.array(view)
    xy, _ = project(P, view, X[point])
    obs = sparse_tracks.Observations(point=point, view=view, xy=xy, n_points=N)
    for per_view in (1000, 4):
        ext = sparse_tracks.extend_tracks(obs, P, [shape] * V, margin_px=margin, per_view=per_view)
        scramble = (np.arange(N, dtype=np.uint64) * np.uint64(2654435761)) % np.uint64(2**32)
        wanted = set()
        for v in range(V):
            cand = []
            for p in range(N):
                if v in view[point == p]:
                    continue
                (c, r), = project(P, np.array([v]), X[p][None])[0]
                if margin <= c <= shape[1] - 1 - margin and margin <= r <= shape[0] - 1 - margin:
                    cand.append(p)
            wanted.update((p, v) for p in sorted(cand, key=lambda p: scramble[p])[:per_view])
        new = ext.view.shape[0] - obs.view.shape[0]
        assert new == len(wanted) > 0
        for p in range(N):
            mine = np.flatnonzero(ext.point == p)
            k = int(np.sum(point == p))
            np.testing.assert_array_equal(ext.view[mine[:k]], view[point == p])  # own ones first
            np.testing.assert_array_equal(ext.xy[mine[:k]], xy[point == p])
            added = ext.view[mine[k:]]
            assert {(p, int(v)) for v in added} == {w for w in wanted if w[0] == p}
            # at the projection (the points are triangulated back from exact observations)
            at = project(P, added, np.tile(X[p], (len(added), 1)))[0]
            np.testing.assert_allclose(ext.xy[mine[k:]], at, atol=1e-6)
    assert sparse_tracks.extend_tracks(obs, P, [shape] * V, margin_px=margin, per_view=0) is obs
    with pytest.raises(OptionsError, match="extend_points_per_view"):
        options.SparseOptions(extend_points_per_view=-1)


# -- matching ----------------------------------------------------------------------------------
def test_ratio_test_and_mutual_check():
    """Ambiguous matches fail the ratio test; a one-way nearest neighbour fails the mutual check."""
    rng = np.random.default_rng(1)
    base = rng.normal(0.0, 50.0, size=(6, 128)).astype(np.float32)
    p, q, r = base[0], base[1], base[2]
    desc1 = np.stack([p, p + 5.0 * (q - p) / np.linalg.norm(q - p), r])  # feature 1 sits near p
    desc2 = np.stack([p + 0.5, base[3], r + 0.1, r - 0.1])  # r has two equal candidates
    opts = options.SparseOptions(min_matches=5)
    i1, i2 = matching._tentative_matches(desc1, desc2, opts)
    assert list(zip(i1, i2)) == [(0, 0)]  # 1 -> 0 is not mutual, 2 is ambiguous
    i1, i2 = matching._tentative_matches(desc1, desc2, opts.replace(mutual=False))
    assert list(zip(i1, i2)) == [(0, 0), (1, 0)]


def test_nearest_neighbours_against_brute_force(monkeypatch):
    """_nearest's blocked float32 search against a float64 brute force over several blocks."""
    monkeypatch.setattr(matching, "_KNN_BLOCK", 7)
    rng = np.random.default_rng(3)
    desc1 = rng.normal(0.0, 40.0, size=(30, 128)).astype(np.float32)
    desc2 = rng.normal(0.0, 40.0, size=(23, 128)).astype(np.float32)
    idx12, d12, idx21 = matching._nearest(desc1, desc2)
    D = np.linalg.norm(desc1[:, None, :].astype(np.float64) - desc2[None, :, :], axis=2)
    order = np.argsort(D, axis=1)[:, :2]
    np.testing.assert_array_equal(idx12, order)
    np.testing.assert_allclose(d12, np.take_along_axis(D, order, axis=1), rtol=1e-5)
    np.testing.assert_array_equal(idx21, D.argmin(axis=0))


def _epipolar_truth(cam1, cam2, xy1, xy2, b1, b2) -> np.ndarray:
    """Distance (px) of xy2 to the true epipolar line of xy1: back-project xy1 - b1 onto two
    horizontal planes with camera 1 (satsweep.geometry.camera's ray-plane intersection), project both
    points with camera 2, add b2."""
    ends = []
    for u in (-100.0, 200.0):
        e, n = cam1.backproject(xy1[:, 0] - b1[0], xy1[:, 1] - b1[1], u=u)
        ends.append(project(cam2, np.column_stack([e, n, np.full_like(e, u)])) + b2)
    a, b = ends
    d = b - a
    return np.abs(d[:, 0] * (xy2[:, 1] - a[:, 1]) - d[:, 1] * (xy2[:, 0] - a[:, 0])) / np.hypot(*d.T)


@pytest.mark.parametrize("model,pointing_px", [("cameras", 1.0), ("affine", 1.0), ("cameras", 40.0)])
def test_verification_keeps_true_matches_and_drops_blunders(model, pointing_px):
    """Pointing errors of a pixel or of tens of pixels: the cameras' verification finds the
    pair's offset whatever its size. (The affine model absorbs any translation too, but its
    band, fitted near the matches, is not within 0.5 px of the true epipolar lines hundreds of
    pixels along them, where some blunders of this test fall.)"""
    rng = np.random.default_rng(2)
    cams = three_cameras()
    cam1, cam2 = cams[0], cams[2]
    n = 400
    X = scene_points(rng, n)
    b1, b2 = pointing_px * np.array([0.8, -1.2]), pointing_px * np.array([-1.5, 0.6])  # px
    xy1 = project(cam1, X) + b1 + rng.normal(0.0, NOISE_PX, (n, 2))
    xy2 = project(cam2, X) + b2 + rng.normal(0.0, NOISE_PX, (n, 2))
    wrong = rng.random(n) < 0.25
    xy2[wrong] = rng.uniform(0.0, 1000.0, (int(wrong.sum()), 2))
    desc = rng.normal(0.0, 50.0, (n, 128)).astype(np.float32)  # distinct: identity matching
    opts = options.SparseOptions(geometric_model=model)
    F = matching.fundamental_from_cameras(cam1, cam2) if model == "cameras" else None
    i1, i2 = matching.match_pair(desc, desc + 0.5, xy1, xy2, opts, fundamental=F)
    assert np.array_equal(i1, i2)
    kept = np.zeros(n, bool)
    kept[i1] = True
    recall = kept[~wrong].mean()
    assert recall >= MIN_RECALL
    truth = _epipolar_truth(cam1, cam2, xy1[kept], xy2[kept], b1, b2)
    assert truth.max() < opts.ransac_threshold_px + CONSISTENCY_MARGIN_PX
    # Blunders dropped: those kept are only the few that fell on their epipolar line by chance.
    assert kept[wrong].sum() <= 0.05 * wrong.sum()


def test_fundamental_matrix_of_the_cameras():
    rng = np.random.default_rng(3)
    cams = three_cameras()
    X = scene_points(rng, 200)
    F = matching.fundamental_from_cameras(cams[0], cams[1])
    d = matching._epipolar_distance(F, project(cams[0], X), project(cams[1], X))
    assert np.abs(d).max() < EXACT_PIXEL_TOL_PX


def test_too_few_descriptors_give_no_matches():
    d = np.zeros((1, 128), np.float32)
    i1, i2 = matching.match_pair(d, d, np.zeros((1, 2)), np.zeros((1, 2)))
    assert len(i1) == 0 and len(i2) == 0


# -- tracks ------------------------------------------------------------------------------------
def _reference_tracks(n_views, pair_matches):
    """Plain union-find over (view, feature) nodes; components with a repeated view dropped."""
    parent: dict = {}

    def find(a):
        while parent.setdefault(a, a) != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for (i, j), (a, b) in pair_matches.items():
        for fa, fb in zip(a, b):
            ra, rb = find((i, int(fa))), find((j, int(fb)))
            if ra != rb:
                parent[ra] = rb
    groups: dict = {}
    for node in list(parent):
        groups.setdefault(find(node), []).append(node)
    out = set()
    for nodes in groups.values():
        views = [v for v, _ in nodes]
        if len(nodes) >= 2 and len(set(views)) == len(views):
            out.add(tuple(sorted(nodes)))
    return out


def test_tracks_chain_pairs_and_drop_inconsistent_components():
    pair_matches = {
        (0, 1): (np.array([0, 1, 5]), np.array([3, 4, 7])),
        (1, 2): (np.array([3, 4]), np.array([9, 2])),
        (0, 2): (np.array([1, 6]), np.array([2, 9])),  # 0:1-1:4-2:2 consistent; 0:6-2:9-1:3-0:0 not
    }
    tracks = sparse_tracks.build_tracks(3, pair_matches)
    got = {tuple(map(tuple, t)) for t in tracks}
    assert got == {((0, 1), (1, 4), (2, 2)), ((0, 5), (1, 7))}
    assert all(np.all(np.diff(t[:, 0]) > 0) for t in tracks)


@pytest.mark.parametrize("seed", range(5))
def test_connected_labels_against_scipy(seed):
    """sparse.connected_labels against scipy.sparse.csgraph.connected_components on random
    sparse graphs (chains, isolated nodes, repeated and self edges): the same labels."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(seed)
    n = 300
    src, dst = rng.integers(0, n, 200), rng.integers(0, n, 200)
    chain = np.arange(100, 160)  # a long chain: many hooking rounds
    src, dst = np.concatenate([src, chain[:-1], [5, 5]]), np.concatenate([dst, chain[1:], [5, 5]])
    _, ref = connected_components(coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n)),
                                  directed=False)
    np.testing.assert_array_equal(sparse_tracks.connected_labels(n, src, dst), ref)
    np.testing.assert_array_equal(sparse_tracks.connected_labels(4, np.zeros(0, int), np.zeros(0, int)),
                                  [0, 1, 2, 3])


def test_tracks_match_a_reference_union_find():
    rng = np.random.default_rng(4)
    V, nf = 4, 60
    pair_matches = {}
    for i in range(V):
        for j in range(i + 1, V):
            k = 40
            pair_matches[(i, j)] = (rng.choice(nf, k, replace=False), rng.choice(nf, k, replace=False))
    tracks = sparse_tracks.build_tracks(V, pair_matches)
    got = {tuple(map(tuple, t.tolist())) for t in tracks}
    assert got == _reference_tracks(V, pair_matches)
    assert len(got) == len(tracks)


# -- triangulation -----------------------------------------------------------------------------
def _observe(cams, X, rng=None, noise=0.0):
    xys = [project(c, X) + (rng.normal(0.0, noise, (len(X), 2)) if noise else 0.0) for c in cams]
    tracks = [np.array([[v, i] for v in range(len(cams))]) for i in range(len(X))]
    return tracks, xys


def test_triangulation_is_exact_on_noise_free_views():
    rng = np.random.default_rng(5)
    cams = three_cameras()
    X = scene_points(rng, 300)
    tracks, xys = _observe(cams, X)
    pts, err = triangulation.triangulate(tracks, cams, xys)
    assert np.abs(pts - X).max() < EXACT_POINT_TOL_M
    assert err.max() < EXACT_PIXEL_TOL_PX
    # Two-view tracks too.
    pts2, _ = triangulation.triangulate([t[[0, 2]] for t in tracks], cams, xys)
    assert np.abs(pts2 - X).max() < EXACT_POINT_TOL_M


def test_triangulation_minimises_the_reprojection_error():
    """Against scipy's least_squares on each point's pixel residuals."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(6)
    cams = three_cameras()
    X = scene_points(rng, 20)
    tracks, xys = _observe(cams, X, rng, noise=1.0)
    pts, err = triangulation.triangulate(tracks, cams, xys)
    for i in range(len(X)):
        def res(p):
            return np.concatenate([project(c, p[None])[0] - xys[v][i] for v, c in enumerate(cams)])
        ref = least_squares(res, X[i], xtol=1e-14, ftol=1e-14, gtol=1e-14).x
        assert np.abs(pts[i] - ref).max() < REFINE_TOL_M
        assert err[i] == pytest.approx(np.max(np.hypot(*res(ref).reshape(-1, 2).T)), abs=1e-6)


# The Monte Carlo estimate of a standard deviation from n samples is itself uncertain by about
# sigma / sqrt(2 n): 1.6% for 2000; five times that.
SIGMA_MC_SAMPLES = 2000
SIGMA_MC_REL_TOL = 0.08
# base_to_height against the angle between two lines of sight: equal for small angles, the
# ratio's 2 sin(b / 2) / cos(b / 2)-like terms leave under 1% at 0.2 rad.
BASE_TO_HEIGHT_REL_TOL = 0.01


def _centre(cam) -> np.ndarray:
    return -cam.R.T @ cam.t


def test_point_covariances_against_the_spread_of_noisy_triangulations():
    """Each point's covariance per pixel of error, against that of its triangulations from
    SIGMA_MC_SAMPLES draws of its views' pixels with 1 px of Gaussian noise on each coordinate
    (the diagonal, to the estimate's noise): a pair 0.2 apart and the triplet."""
    from tests.synthetic_cameras import satellite_camera

    rng = np.random.default_rng(9)
    X = np.array([[30.0, -50.0, 20.0], [-120.0, 80.0, 55.0]])
    for cams in ([satellite_camera(0.0, -0.1), satellite_camera(0.0, 0.1)], three_cameras()):
        P = triangulation.projection_stack(cams)
        V = len(cams)
        obs = sparse_tracks.Observations(np.repeat(np.arange(2), V), np.tile(np.arange(V), 2),
                                         np.zeros((2 * V, 2)), 2)
        cov = triangulation.point_covariances(P, obs, X)
        exact = triangulation.project(P, obs.view, X[obs.point])[0]
        points = np.empty((SIGMA_MC_SAMPLES, 2, 3))
        for k in range(SIGMA_MC_SAMPLES):
            noisy = dataclasses.replace(obs, xy=exact + rng.normal(0.0, 1.0, exact.shape))
            points[k] = triangulation.triangulate_observations(noisy, P)[0]
        np.testing.assert_allclose(np.sqrt(np.diagonal(cov, axis1=1, axis2=2)),
                                   points.std(axis=0), rtol=SIGMA_MC_REL_TOL)


@pytest.mark.parametrize("first,second", [((0.0, -0.1), (0.0, 0.1)),  # 0.2 rad, near nadir
                                          ((0.25, 0.05), (0.26, 0.05)),  # oblique, 0.009 rad
                                          ((-0.15, 0.0), (-0.1495, 0.001))])  # one orbit, twice
def test_base_to_height_is_the_angle_between_the_lines_of_sight(first, second):
    """Two views' effective base-to-height ratio at a point, against the angle between the rays
    from it to their centres, whatever their incidence: a height-only measure would take an
    oblique pair along nearly one line of sight (its uncertainty lies along that line, partly
    across the ground) for a good one. One view twice: 0."""
    from tests.synthetic_cameras import satellite_camera

    cams = [satellite_camera(*first), satellite_camera(*second)]
    P = triangulation.projection_stack(cams)
    X = np.array([[30.0, -50.0, 20.0]])
    obs = sparse_tracks.Observations(np.array([0, 0]), np.array([0, 1]), np.zeros((2, 2)), 1)
    rays = [_centre(c) - X[0] for c in cams]
    angle = np.arccos(np.dot(rays[0], rays[1]) / np.linalg.norm(rays[0]) / np.linalg.norm(rays[1]))
    b = triangulation.base_to_height(triangulation.point_covariances(P, obs, X))[0]
    assert b == pytest.approx(angle, rel=BASE_TO_HEIGHT_REL_TOL)
    one = triangulation.projection_stack([cams[0], cams[0]])
    cov = triangulation.point_covariances(one, obs, X)
    assert np.isinf(cov).all() and triangulation.base_to_height(cov)[0] == 0.0


def test_points_behind_the_cameras_are_rejected():
    rng = np.random.default_rng(7)
    cams = three_cameras()
    X = scene_points(rng, 5)
    X[2] = [0.0, 0.0, 2e6]  # above the satellites: negative depth in every view
    tracks, xys = _observe(cams, X)
    _, err = triangulation.triangulate(tracks, cams, xys)
    assert np.isinf(err[2]) and np.all(np.isfinite(np.delete(err, 2)))


def test_parallel_rays_give_no_point():
    """A track whose rays coincide (one pixel of one view, twice) has singular normal equations:
    its point is NaN, its errors inf, and it is not in front; the other points are unaffected."""
    rng = np.random.default_rng(8)
    cams = three_cameras()
    X = scene_points(rng, 4)
    xys = [project(c, X) for c in cams]
    view = np.array([0, 1, 2, 0, 1, 2, 1, 1, 0, 2])
    point = np.array([0, 0, 0, 1, 1, 2, 2, 3, 3, 3])
    xy = np.array([xys[v][p] for v, p in zip(view, point)])
    xy[6] = xy[5] = xys[1][2]
    view[5] = 1
    obs = sparse_tracks.Observations(point=point, view=view, xy=xy, n_points=4)
    P = triangulation.projection_stack(cams)
    pts, err, front = triangulation.triangulate_observations(obs, P)
    assert np.isnan(pts[2]).all() and np.isinf(err[5:7]).all() and not front[2]
    keep = point != 2
    assert np.abs(pts[[0, 1, 3]] - X[[0, 1, 3]]).max() < EXACT_POINT_TOL_M
    assert err[keep].max() < EXACT_PIXEL_TOL_PX and front[[0, 1, 3]].all()


class _Camera:
    def __init__(self, P):
        self.P = P


def _nadir_camera(focal_px: float, height_m: float = 6.0e5) -> _Camera:
    """A pinhole looking straight down from ``height_m`` over the ENU origin: its ground sample
    there is height / focal (m per pixel) exactly."""
    K = np.array([[focal_px, 0.0, 500.0], [0.0, focal_px, 400.0], [0.0, 0.0, 1.0]])
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # x east, y south, depth down
    C = np.array([0.0, 0.0, height_m])
    return _Camera(K @ np.hstack([R, -(R @ C)[:, None]]))


@pytest.mark.parametrize("gsd, window", [(0.5, 9), (0.45, 9), (0.3, 13), (0.2, 19), (0.01, 63)])
def test_registration_window_spans_refine_window_m_at_the_finest_gsd(gsd, window):
    """The window is refine_window_px (9), or the nearest odd count of pixels spanning
    refine_window_m (3.9 m) at the finest view's ground sample where that is more (at most
    63); the ground sample of a nadir pinhole is its height over its focal length."""
    from satsweep.geometry.camera import ground_sample_distance
    from satsweep.sparse.stage import registration_window_px

    cams = [_nadir_camera(6.0e5 / gsd), _nadir_camera(6.0e5 / (1.4 * gsd))]
    assert ground_sample_distance(cams[0].P, np.zeros(3)) == pytest.approx(gsd, rel=1e-9)
    o = options.SparseOptions()
    assert (o.refine_window_px, o.refine_window_m) == (9, 3.9)
    assert registration_window_px(cams, o) == window
    assert registration_window_px(cams, o.replace(refine_window_m=0.0)) == 9
    assert registration_window_px(cams, o.replace(refine_window_px=0, refine_beside_px=0.0)) == 0
    with pytest.raises(OptionsError, match="refine_window_m"):
        options.SparseOptions(refine_window_m=-1.0)
