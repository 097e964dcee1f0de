"""satsweep.sparse.subpixel: windows registered against an analytic texture's exact truth."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.sparse import subpixel

# A band-limited texture (24 plane waves up to 0.22 cycles per pixel) drawn exactly at every
# pixel of both views, the second through a known homography: the truth of each window is known
# to the bit, without resampling either image.
_SIZE = 200
_WINDOW = 9
# Mean error over 400 windows, each axis (px): measured at most 0.0013 for translations with
# fractions of 0, 1/4, 1/2 and 3/4 px; the registration before it (8-bit bilinear warp, then
# OpenCV's Lucas-Kanade) errs by up to 0.020 px on the same windows: what does not average out
# over a pair's tie points.
BIAS_TOL_PX = 0.004
# Median error of one window (px): measured 0.012-0.018 (Lanczos interpolation of waves up to
# 0.22 cycles per pixel, positions to 1/32 px; OpenCV's bicubic leaves 0.04); it averages out
# over the windows.
MEDIAN_TOL_PX = 0.03


def _texture(seed: int = 5):
    rng = np.random.default_rng(seed)
    freq = rng.uniform(-0.22, 0.22, (24, 2))
    amp = rng.uniform(0.5, 1.0, 24)
    phase = rng.uniform(0.0, 2.0 * np.pi, 24)

    def f(x, y):
        wave = np.cos(2.0 * np.pi * (freq[:, 0, None, None] * x + freq[:, 1, None, None] * y)
                      + phase[:, None, None])
        return 128.0 + 12.0 * np.tensordot(amp, wave, axes=1)
    return f


def _views(H: np.ndarray):
    """(head, other): other(H p) = head(p) exactly, for every pixel p of head."""
    f = _texture()
    yy, xx = np.mgrid[0:_SIZE, 0:_SIZE].astype(np.float64)
    Hi = np.linalg.inv(H)
    s = Hi[2, 0] * xx + Hi[2, 1] * yy + Hi[2, 2]
    other = f((Hi[0, 0] * xx + Hi[0, 1] * yy + Hi[0, 2]) / s,
              (Hi[1, 0] * xx + Hi[1, 1] * yy + Hi[1, 2]) / s)
    return f(xx, yy), other


def _points(n=400, seed=1):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(40.0, 160.0, (n, 2))
    return pts, pts + rng.normal(0.0, 0.1, pts.shape)  # where Lucas-Kanade would leave them


@pytest.mark.parametrize("shift", [(3.0, -2.0), (3.25, -2.5), (3.5, -2.75), (3.75, -2.25)])
def test_translations_are_registered_without_bias(shift):
    """A window at p in the first view lies at p in the second's frame (q = p): over 400 windows
    at random sub-pixel places the mean error stays under BIAS_TOL_PX whatever the fraction of
    the views' offset, and each window's under MEDIAN_TOL_PX at the median."""
    H = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]], [0.0, 0.0, 1.0]])
    head, other = _views(H)
    pts, start = _points()
    q, residual, ok = subpixel.refine_translations(head, other, H, pts, start, _WINDOW)
    assert ok.all()
    err = q - pts
    assert np.abs(err.mean(axis=0)).max() < BIAS_TOL_PX, err.mean(axis=0)
    assert np.median(np.hypot(*err.T)) < MEDIAN_TOL_PX
    assert np.isfinite(residual).all() and np.median(residual) < 1.0  # of 12-grey-level waves


def test_a_rotated_scaled_perspective_view_is_registered_through_its_homography():
    """The windows' samples follow the homography's local affine map (10 degrees, 2% scale,
    perspective terms): the same accuracy as a translation."""
    a = np.deg2rad(10.0)
    H = np.array([[1.02 * np.cos(a), -1.02 * np.sin(a), 30.3],
                  [1.02 * np.sin(a), 1.02 * np.cos(a), -20.6], [2e-5, -1e-5, 1.0]])
    head, other = _views(H)
    pts, start = _points(seed=2)
    q, _, ok = subpixel.refine_translations(head, other, H, pts, start, _WINDOW)
    assert ok.all()
    err = q - pts
    assert np.abs(err.mean(axis=0)).max() < BIAS_TOL_PX
    assert np.median(np.hypot(*err.T)) < MEDIAN_TOL_PX
    # the homography's inverse in its place registers nothing (the test can fail)
    q_bad, _, ok_bad = subpixel.refine_translations(head, other, np.linalg.inv(H), pts, start,
                                                    _WINDOW)
    assert not ok_bad.all() or np.median(np.hypot(*(q_bad - pts).T)) > 10 * MEDIAN_TOL_PX


def test_windows_without_texture_or_too_far_fail():
    H = np.eye(3)
    head, other = _views(H)
    head[80:120, 80:120] = 100.0  # a flat patch: no gradients to register
    pts = np.array([[100.0, 100.0], [60.0, 60.0], [140.0, 60.0]])
    start = pts.copy()
    start[2] += [2.0, 0.0]  # two pixels off: farther than SUBPIXEL_MAX_MOVE_PX from there
    _, _, ok = subpixel.refine_translations(head, other, H, pts, start, _WINDOW)
    np.testing.assert_array_equal(ok, [False, True, False])
    q, residual, ok = subpixel.refine_translations(head, other, H, np.zeros((0, 2)),
                                                   np.zeros((0, 2)), _WINDOW)
    assert q.shape == (0, 2) and residual.shape == (0,) and ok.shape == (0,)


def test_sampling_in_parts_gives_the_same_values(monkeypatch):
    """Images and window sets beyond OpenCV remap's limits are sampled in parts, each from a
    crop of the image: the same values as at once, bit for bit."""
    rng = np.random.default_rng(3)
    image = rng.uniform(0.0, 255.0, (120, 150)).astype(np.float32)
    x = rng.uniform(-2.0, 152.0, (300, 7)).astype(np.float32)  # some beyond the edges
    y = rng.uniform(-2.0, 122.0, (300, 7)).astype(np.float32)
    whole = subpixel.sample_lanczos(image, x, y)
    monkeypatch.setattr(subpixel, "_REMAP_LIMIT", 40)
    parts = subpixel.sample_lanczos(image, x, y)
    np.testing.assert_array_equal(parts, whole)
    import cv2

    direct = cv2.remap(image, x, y, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_array_equal(whole, direct)
