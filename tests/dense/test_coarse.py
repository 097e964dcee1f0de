"""Coarse-to-fine plane windows (satsweep/dense/coarse.py): the half-resolution images and
homographies against exact pixel-centre truths, and the windows' planes against the coarse map
they are built from."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.dense import coarse
from satsweep.dense.planes import translation_homographies


def test_downsample2_puts_a_half_resolution_pixel_at_its_footprint_centre():
    """A linear ramp is its own 2x2 mean: the half-resolution pixel (i, j) must hold the ramp's
    value at full-resolution (2j + 0.5, 2i + 0.5); an odd last row and column are left out."""
    h, w = 9, 12
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ramp = (0.3 * x - 0.7 * y + 2.0).astype(np.float32)
    half = coarse.downsample2(ramp)
    assert half.shape == (4, 6)
    yc, xc = np.mgrid[0:4, 0:6].astype(np.float64)
    np.testing.assert_allclose(half, 0.3 * (2 * xc + 0.5) - 0.7 * (2 * yc + 0.5) + 2.0,
                               atol=1e-5)


def test_half_resolution_homographies_halve_a_translation():
    """A source shifted by t pixels at full resolution is shifted by t / 2 between the
    half-resolution images (the footprint centres move with it)."""
    shifts = np.array([[1.3, -0.6], [-2.2, 0.4]])
    heights = np.array([0.0, 1.0, 5.0])
    full = translation_homographies(shifts, heights)
    half = coarse.half_resolution_homographies(full)
    np.testing.assert_allclose(half, translation_homographies(shifts / 2, heights), atol=1e-12)


def test_upsample_index_gives_each_pixel_its_half_resolution_pixel():
    c = np.arange(12, dtype=np.float64).reshape(3, 4)
    up = coarse.upsample_index(c, (7, 8))
    assert up.shape == (7, 8)
    assert up[0, 0] == up[1, 1] == 0 and up[5, 7] == 11 and up[6, 7] == 11  # odd last row
    assert up[2, 3] == c[1, 1]


def _step_map(shape=(96, 128), low=10.0, high=40.0, step_x=70):
    idx = np.full(shape, low)
    idx[:, step_x:] = high
    return idx


def test_plane_windows_cover_the_coarse_planes_of_each_block():
    """Two plateaus (planes 10 and 40) meeting at column 70, blocks of 32 px, halo 4, margin 3:
    blocks away from the step sweep 7 planes around their plateau; the block across it sweeps
    from 7 to 43; the volume holds the widest window's labels."""
    idx = _step_map()
    n = 64
    win = coarse.plane_windows(idx, n, block=32, halo=4, margin=3, max_fraction=0.9)
    assert win is not None and win.first.shape == (3, 4)
    assert win.n_planes == 37  # the widest window: 37 planes across the step
    np.testing.assert_array_equal(win.first[:, 0], 7)
    np.testing.assert_array_equal(win.count[:, 0], 7)
    np.testing.assert_array_equal(win.first[:, 2], 7)  # columns 64..95 hold the step
    np.testing.assert_array_equal(win.count[:, 2], 37)
    np.testing.assert_array_equal(win.first[:, 3], 37)
    np.testing.assert_array_equal(win.count[:, 3], 7)
    assert np.all(win.count <= win.n_planes) and np.all(win.first + win.count <= n)
    win.check(idx.shape, n)
    # the halo widens a block next to the step: with 8 px, columns 32..63 see plane 40 too
    wide = coarse.plane_windows(idx, n, block=32, halo=8, margin=3, max_fraction=0.9)
    np.testing.assert_array_equal(wide.count[:, 1], 37)


def test_pixel_windows_span_the_coarse_planes_around_each_pixel():
    """block = 1: each pixel's window spans the coarse planes within ``halo`` px of it (scipy's
    min / max filters as the reference) plus the margin: 7 planes on each plateau, 37 within 4 px
    of the step at column 70; fractional indices widen it to the planes around them."""
    from scipy import ndimage

    idx = _step_map()
    idx[10:20, 10:20] = 25.5
    n = 64
    win = coarse.plane_windows(idx, n, block=1, halo=4, margin=3, max_fraction=0.9)
    assert win is not None and win.block == 1 and win.first.shape == idx.shape
    lo = np.floor(ndimage.minimum_filter(idx, size=9, mode="nearest")) - 3
    hi = np.ceil(ndimage.maximum_filter(idx, size=9, mode="nearest")) + 3
    np.testing.assert_array_equal(win.first, lo)
    np.testing.assert_array_equal(win.count, hi - lo + 1)
    assert win.count[50, 0] == 7 and win.count[50, 66] == 37 and win.count[50, 74] == 7
    assert win.count[15, 15] == 26 - 25 + 7 and win.n_planes == 37
    win.check(idx.shape, n)


def test_plane_windows_fill_unknown_pixels_and_give_up_when_nothing_is_gained():
    idx = _step_map()
    holes = idx.copy()
    holes[:, 60:80] = np.nan  # the step unknown: filled from the nearest known pixels
    win = coarse.plane_windows(holes, 64, block=32, halo=4, margin=3, max_fraction=0.9)
    assert win is not None and win.count.max() == 37
    assert coarse.plane_windows(np.full((40, 40), np.nan), 64, block=32, halo=4, margin=3,
                                max_fraction=0.9) is None
    # the blocks would sweep more than a tenth of the planes on average: sweep all of them
    assert coarse.plane_windows(idx, 64, block=32, halo=4, margin=3, max_fraction=0.1) is None
    # ... more than a fifth (14.5 of 64 planes), windows of one pixel less (8.9): those, if asked
    kw = dict(block=32, halo=4, margin=3, max_fraction=0.2)
    assert coarse.plane_windows(idx, 64, **kw) is None
    pixels = coarse.plane_windows(idx, 64, pixel_fallback=True, **kw)
    assert pixels.block == 1
    np.testing.assert_array_equal(pixels.count, coarse.plane_windows(
        idx, 64, block=1, halo=4, margin=3, max_fraction=1.0).count)
    assert coarse.plane_windows(idx, 64, pixel_fallback=True, **{**kw, "max_fraction": 0.1}) \
        is None
    assert coarse.plane_windows(idx, 64, pixel_fallback=True, **{**kw, "max_fraction": 0.3}) \
        .block == 32  # the blocks first, where they do


# OpenCV's labelled distance transform (5x5 mask) finds a known pixel within 0.14 px of the
# nearest one's distance (measured); 0.25 px leaves room and still fails a wrong neighbour.
NEAREST_FILL_TOL_PX = 0.25


def test_fill_from_nearly_the_nearest_known_pixel():
    """coarse.fill_from_nearest against scipy's exact Euclidean nearest: each unknown pixel takes
    the value of a known pixel at most NEAREST_FILL_TOL_PX farther than the nearest one; known
    pixels keep theirs."""
    from scipy import ndimage

    rng = np.random.default_rng(2)
    known = rng.random((70, 90)) < 0.03
    ys, xs = np.nonzero(known)
    values = np.full(known.shape, np.nan)
    values[known] = np.arange(known.sum())  # each known pixel's value names it
    filled = coarse.fill_from_nearest(values, known).astype(int)
    rows, cols = np.mgrid[0:70, 0:90]
    picked = np.hypot(ys[filled] - rows, xs[filled] - cols)
    assert np.all(picked <= ndimage.distance_transform_edt(~known) + NEAREST_FILL_TOL_PX)
    np.testing.assert_array_equal(filled[known], values[known])


@pytest.mark.parametrize("shape, planes, worth", [((200, 300), 64, True), ((200, 300), 12, False),
                                                  ((20, 300), 64, False)])
def test_worth_a_coarse_pass(shape, planes, worth):
    assert coarse.worth_a_coarse_pass(shape, planes) is worth


@pytest.mark.parametrize("band_halo", [None, 1, 0, 5])
def test_pixel_bands_hold_the_coarse_planes_within_the_halo(band_halo):
    """block = 1: bit k of a pixel's bands is set exactly when some coarse index i within
    the bands' halo of it (``band_halo``, at most and by default the window's ``halo``; the
    image's pixels only) has floor(i) - margin .. ceil(i) + margin (within the planes) meet
    planes [4 k, 4 k + 4) (brute force); every band set meets the pixel's window, and a step's
    two plateaus leave the planes between them out."""
    from satsweep.dense.sweep import BAND_PLANES

    rng = np.random.default_rng(3)
    idx = rng.integers(0, 12, (17, 23)).astype(np.float64) * 4.0
    idx[5:9, 3:20] += rng.uniform(0.0, 1.0, (4, 17))  # fractional indices
    idx[:, 15:] += 70.0  # a step: no index between ~48 and 70 next to it
    n, window_halo, margin = 130, 2, 3
    halo = window_halo if band_halo is None else min(band_halo, window_halo)
    win = coarse.plane_windows(idx, n, block=1, halo=window_halo, margin=margin,
                               max_fraction=1.0, bands=True, band_halo=band_halo)
    assert win is not None and win.bands is not None
    lo = np.clip(np.floor(idx) - margin, 0, n - 1) // BAND_PLANES
    hi = np.clip(np.ceil(idx) + margin, 0, n - 1) // BAND_PLANES
    h, w = idx.shape
    for y in range(h):
        for x in range(w):
            ys, xs = slice(max(y - halo, 0), y + halo + 1), slice(max(x - halo, 0), x + halo + 1)
            want = set()
            for a, b in zip(lo[ys, xs].ravel(), hi[ys, xs].ravel()):
                want.update(range(int(a), int(b) + 1))
            got = {k for k in range(-(-n // BAND_PLANES))
                   if (int(win.bands[k >> 5, y, x]) >> (k & 31)) & 1}
            assert got == want, (y, x)
            first, count = int(win.first[y, x]), int(win.count[y, x])
            assert all(first < BAND_PLANES * (k + 1) and BAND_PLANES * k < first + count
                       for k in got)
    # next to the step a window spans both plateaus, its bands the planes near each only
    k_mid = 60 // BAND_PLANES
    assert win.first[10, 14] < 60 < win.first[10, 14] + win.count[10, 14]
    assert not (int(win.bands[k_mid >> 5, 10, 14]) >> (k_mid & 31)) & 1


@pytest.mark.parametrize("shape, radius", [((3, 2), 6), ((9, 14), 4), ((1, 30), 3)])
def test_band_sets_by_brute_force(shape, radius):
    """``_bands`` (runs of bits per word, ORed over the square) against each pixel's set of
    bands built by brute force: images narrower than the square, three words of bands (300
    planes), indices below and above the planes (clipped)."""
    from satsweep.dense.sweep import BAND_PLANES, band_words

    rng = np.random.default_rng(11)
    n, margin = 300, 2
    idx = rng.uniform(-5.0, n + 5.0, shape)
    idx[0, 0] = 31.0 * BAND_PLANES  # a run that ends at a word's last bit
    got = coarse._bands(idx, n, radius, margin)
    assert got.shape == (band_words(n),) + shape == (3,) + shape and got.dtype == np.uint32
    lo = np.clip(np.floor(idx) - margin, 0, n - 1) // BAND_PLANES
    hi = np.clip(np.ceil(idx) + margin, 0, n - 1) // BAND_PLANES
    h, w = shape
    for y in range(h):
        for x in range(w):
            ys = slice(max(y - radius, 0), y + radius + 1)
            xs = slice(max(x - radius, 0), x + radius + 1)
            want = set()
            for a, b in zip(lo[ys, xs].ravel(), hi[ys, xs].ravel()):
                want.update(range(int(a), int(b) + 1))
            have = {k for k in range(32 * got.shape[0])
                    if (int(got[k >> 5, y, x]) >> (k & 31)) & 1}
            assert have == want, (y, x)
