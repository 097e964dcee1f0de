"""PNG renderings: valid images of the expected layout, map pixels equal to the colour mapping."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from satsweep.products import quicklook as render


def _surface(rows: int, cols: int) -> np.ndarray:
    yy, xx = np.mgrid[0:rows, 0:cols]
    z = 100.0 + 0.05 * xx + 0.02 * yy
    z[rows // 4: rows // 2, cols // 4: cols // 2] += 12.0  # a building
    z[0:3, 0:5] = np.nan  # no data
    return z


def _reference_colors(a, vmin, vmax, cmap):
    """Colour mapping written out independently: 8-bit index, then OpenCV's table of the map."""
    idx = np.zeros(a.shape, np.uint8)
    fin = np.isfinite(a)
    idx[fin] = np.round(255 * np.clip((a[fin] - vmin) / (vmax - vmin), 0, 1)).astype(np.uint8)
    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cmap).reshape(256, 3)
    out = table[idx]
    out[~fin] = render.NAN_COLOR
    return out


def test_height_png_map_pixels_and_colour_bar(tmp_path):
    a = _surface(300, 260)  # longer side >= MIN_MAP_SIDE: drawn one pixel per cell
    path = tmp_path / "dsm.png"
    box = render.height_png(path, a, title="DSM", vmin=95.0, vmax=125.0)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None and img.dtype == np.uint8
    assert (box.height, box.width, box.scale) == (300, 260, 1.0)
    assert img.shape[0] >= render.TITLE_HEIGHT + 300 + render.FOOTER_HEIGHT
    assert img.shape[1] >= render.MARGIN + 260 + render.BAR_GAP + render.BAR_WIDTH
    region = img[box.top:box.top + box.height, box.left:box.left + box.width]
    np.testing.assert_array_equal(region, _reference_colors(a, 95.0, 125.0, cv2.COLORMAP_VIRIDIS))
    # Colour bar: top row is vmax's colour, bottom row vmin's (row centres within 1 index step).
    bar_x = box.left + box.width + render.BAR_GAP
    table = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cv2.COLORMAP_VIRIDIS).reshape(256, 3)
    top = img[box.top, bar_x + render.BAR_WIDTH // 2]
    bottom = img[box.top + max(300, render.MIN_BAR_HEIGHT) - 1, bar_x + render.BAR_WIDTH // 2]
    assert any(np.array_equal(top, table[k]) for k in (254, 255))
    assert any(np.array_equal(bottom, table[k]) for k in (0, 1))
    # Tick labels are drawn right of the bar: dark text pixels there.
    labels = img[box.top:box.top + 300, bar_x + render.BAR_WIDTH + render.TICK_LENGTH + 2:]
    assert np.count_nonzero(labels.max(axis=2) < 100) > 50


def test_small_map_is_enlarged_by_an_integer_factor(tmp_path):
    a = _surface(20, 30)
    path = tmp_path / "small.png"
    box = render.height_png(path, a, title="small", cmap=cv2.COLORMAP_TURBO)
    scale = render.MIN_MAP_SIDE // 30
    assert (box.scale, box.height, box.width) == (scale, 20 * scale, 30 * scale)
    img = cv2.imread(str(path))
    region = img[box.top:box.top + box.height, box.left:box.left + box.width]
    ref = _reference_colors(a, box.vmin, box.vmax, cv2.COLORMAP_TURBO)
    np.testing.assert_array_equal(region, np.repeat(np.repeat(ref, scale, axis=0), scale, axis=1))
    # Default range: the 2nd..98th percentiles of the finite values.
    lo, hi = np.percentile(a[np.isfinite(a)], [2, 98])
    assert math.isclose(box.vmin, lo) and math.isclose(box.vmax, hi)


def test_large_map_is_reduced(tmp_path):
    a = np.tile(np.linspace(0, 1, 2100), (30, 1))
    box = render.height_png(tmp_path / "wide.png", a, title="wide")
    assert box.width == render.MAX_MAP_SIDE and box.height == round(30 * render.MAX_MAP_SIDE / 2100)
    img = cv2.imread(str(tmp_path / "wide.png"))
    assert img.shape[1] > render.MAX_MAP_SIDE
    assert img.shape[0] >= render.TITLE_HEIGHT + render.MIN_BAR_HEIGHT  # bar keeps its height


def test_overlays_and_diverging_map(tmp_path):
    err = np.linspace(-2, 2, 300 * 300).reshape(300, 300)
    mask = np.zeros(err.shape, bool)
    mask[100:120, 50:60] = True
    box = render.height_png(tmp_path / "err.png", err, title="error", vmin=-2, vmax=2,
                            cmap=render.diverging_lut(), overlays=[(mask, (0, 0, 0), "black: missing")])
    img = cv2.imread(str(tmp_path / "err.png"))
    region = img[box.top:box.top + 300, box.left:box.left + 300]
    assert np.all(region[mask] == 0)
    lut = render.diverging_lut().reshape(256, 3)
    # Zero error maps to (near) white, the ends to saturated blue / red.
    assert lut[128].min() >= 250
    assert lut[0][0] > lut[0][2] and lut[255][2] > lut[255][0]
    np.testing.assert_array_equal(region[0, 0], lut[0])
    np.testing.assert_array_equal(region[-1, -1], lut[255])


def test_all_nan_map_is_still_rendered(tmp_path):
    a = np.full((40, 40), np.nan)
    render.height_png(tmp_path / "nan.png", a, title="empty")
    img = cv2.imread(str(tmp_path / "nan.png"))
    assert img is not None


def test_bad_range_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="vmin"):
        render.height_png(tmp_path / "x.png", np.zeros((4, 4)), title="t", vmin=1.0, vmax=1.0)
    assert not (tmp_path / "x.png").exists()


def test_histogram_counts_and_bars(tmp_path):
    rng = np.random.default_rng(3)
    v = np.concatenate([rng.normal(0, 0.5, 5000), [np.nan, np.inf, 50.0]])
    path = tmp_path / "hist.png"
    counts = render.histogram_png(path, v, bins=40, title="errors", value_range=(-2, 2), markers=(-1, 1))
    ref, _ = np.histogram(v[np.isfinite(v)], bins=40, range=(-2, 2))
    np.testing.assert_array_equal(counts, ref)
    img = cv2.imread(str(path))
    assert img.shape == (render.HIST_HEIGHT, render.HIST_WIDTH, 3)
    # The tallest bin is drawn as a bar-coloured column reaching the top of the plot area.
    k = int(np.argmax(ref))
    left, right = 70, render.HIST_WIDTH - 20
    x = left + int(round((k + 0.5) / 40 * (right - left)))
    column = img[:, x]
    bar = np.all(column == render.BAR_COLOR, axis=1)
    assert bar.sum() >= (render.HIST_HEIGHT - 60 - 50) - 2
    # The markers are red lines.
    assert np.any(np.all(img == render.MARKER_COLOR, axis=2))


@pytest.mark.parametrize("lo,hi", [(0.0, 10.0), (-2.0, 2.0), (2331.7, 2398.2), (0.013, 0.029), (5.0, 5.4)])
def test_nice_ticks(lo, hi):
    ticks = render.nice_ticks(lo, hi)
    assert ticks.size >= 2
    assert ticks.min() >= lo - 1e-9 and ticks.max() <= hi + 1e-9
    steps = np.diff(ticks)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)
    mantissa = steps[0] / 10 ** math.floor(math.log10(steps[0]) + 1e-9)
    assert any(math.isclose(mantissa, m, rel_tol=1e-9) for m in (1.0, 2.0, 2.5, 5.0))
    # Every tick is a whole multiple of the step.
    np.testing.assert_allclose(ticks / steps[0], np.round(ticks / steps[0]), atol=1e-6)
