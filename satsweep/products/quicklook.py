"""PNG renderings for people: height and error maps with a colour bar, and histograms.

Drawn with OpenCV only (``cv2.applyColorMap``, ``cv2.putText``); no matplotlib. Layout of a map
image (pixels): a title band of ``TITLE_HEIGHT`` on top, the map at ``(top=TITLE_HEIGHT,
left=MARGIN)``, enlarged by an integer factor (nearest neighbour) when its longer side is below
``MIN_MAP_SIDE`` or reduced when above ``MAX_MAP_SIDE``, and a vertical colour bar with tick
labels and the unit on its right. NaN cells are drawn in ``NAN_COLOR`` (grey, outside every colour
map used here) and their count is written under the map. Every PNG is written to a temporary name
and renamed.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Sequence

import numpy as np

from satsweep.io.atomic import atomic_output

# Layout constants (pixels).
TITLE_HEIGHT = 46  # band above the map holding the title and the unit of the colour bar
MARGIN = 12  # blank border left of the map and below everything
FOOTER_HEIGHT = 26  # band under the map holding the no-data legend
BAR_GAP = 16  # space between the map and the colour bar
BAR_WIDTH = 22  # colour bar width
TICK_LENGTH = 5  # tick marks beside the colour bar
MIN_BAR_HEIGHT = 200  # the colour bar keeps this height even beside a flat map
MIN_MAP_SIDE = 256  # smaller maps are enlarged by an integer factor so text stays readable
MAX_MAP_SIDE = 2048  # larger maps are reduced to this longer side (area averaging of colours)
HIST_WIDTH, HIST_HEIGHT = 720, 420  # histogram image size

# Colours (BGR).
NAN_COLOR = (128, 128, 128)  # no data
BACKGROUND = (255, 255, 255)
INK = (0, 0, 0)
MARKER_COLOR = (0, 0, 200)  # vertical marker lines in histograms (red)
BAR_COLOR = (160, 110, 40)  # histogram bars (steel blue)

FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.45
TITLE_SCALE = 0.55

# Robust default display range of a map: these percentiles of its finite values.
DEFAULT_LOW_PERCENTILE = 2.0
DEFAULT_HIGH_PERCENTILE = 98.0


def diverging_lut() -> np.ndarray:
    """A 256-entry blue-white-red BGR colour map (256, 1, 3) uint8 for signed errors.

    Index 0 is dark blue (most negative), 128 white (zero), 255 dark red (most positive); the
    lightness falls linearly away from the centre, so equal |error| reads as equal strength.
    """
    t = np.linspace(-1.0, 1.0, 256)
    a = np.abs(t)
    # Blue side: white -> (200, 60, 20) BGR; red side: white -> (30, 40, 190) BGR.
    neg = np.array([200.0, 60.0, 20.0])
    pos = np.array([30.0, 40.0, 190.0])
    end = np.where(t[:, None] < 0, neg[None, :], pos[None, :])
    lut = 255.0 * (1.0 - a[:, None]) + end * a[:, None]
    return np.round(lut).astype(np.uint8).reshape(256, 1, 3)


def _default_cmap() -> int:
    import cv2

    return cv2.COLORMAP_VIRIDIS


def colorize(
    array: np.ndarray,
    *,
    vmin: float,
    vmax: float,
    cmap: int | np.ndarray | None = None,
    nan_color: tuple[int, int, int] = NAN_COLOR,
) -> np.ndarray:
    """Map a 2D array to a BGR uint8 image: ``round(255 * clip((v - vmin) / (vmax - vmin)))``.

    ``cmap``: an OpenCV ``COLORMAP_*`` constant (default viridis) or a (256, 1, 3) uint8 BGR
    look-up table such as ``diverging_lut()``. Non-finite cells get ``nan_color``.
    """
    import cv2

    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"colorize needs a 2D array, got shape {a.shape}")
    if not (math.isfinite(vmin) and math.isfinite(vmax) and vmax > vmin):
        raise ValueError(f"colorize needs finite vmin < vmax, got {vmin!r}, {vmax!r}")
    finite = np.isfinite(a)
    t = np.clip((np.where(finite, a, vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    index = np.round(t * 255.0).astype(np.uint8)
    cmap = _default_cmap() if cmap is None else cmap
    if isinstance(cmap, np.ndarray):
        lut = np.asarray(cmap, dtype=np.uint8).reshape(256, 1, 3)
        out = cv2.applyColorMap(index, lut)
    else:
        out = cv2.applyColorMap(index, int(cmap))
    out[~finite] = nan_color
    return out


def display_range(array: np.ndarray, *, symmetric: bool = False) -> tuple[float, float]:
    """Default colour range: the 2nd..98th percentiles of the finite values (never empty).

    ``symmetric`` gives ``(-m, m)`` with m the 98th percentile of |value| (for signed errors).
    """
    a = np.asarray(array, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return (-1.0, 1.0) if symmetric else (0.0, 1.0)
    if symmetric:
        m = float(np.percentile(np.abs(a), DEFAULT_HIGH_PERCENTILE))
        m = m if m > 0.0 else 1.0
        return -m, m
    lo, hi = (float(v) for v in np.percentile(a, [DEFAULT_LOW_PERCENTILE, DEFAULT_HIGH_PERCENTILE]))
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def nice_ticks(vmin: float, vmax: float, *, target: int = 5) -> np.ndarray:
    """Round tick values (multiples of 1, 2, 2.5 or 5 times a power of ten) inside [vmin, vmax].

    Falls back to the two ends when fewer than two round values fit.
    """
    span = vmax - vmin
    if not span > 0.0:
        return np.array([vmin])
    rough = span / max(target - 1, 1)
    mag = 10.0 ** math.floor(math.log10(rough))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= rough * (1.0 - 1e-9))
    k = np.arange(math.ceil(vmin / step - 1e-9), math.floor(vmax / step + 1e-9) + 1)
    ticks = k * step
    if ticks.size < 2:
        return np.array([vmin, vmax])
    return ticks


def _tick_text(value: float, step: float) -> str:
    """A tick label with as many decimals as the tick step needs."""
    decimals = 0 if step >= 1.0 else int(math.ceil(-math.log10(step) - 1e-9))
    if decimals and abs(step * 10 ** decimals - round(step * 10 ** decimals)) > 1e-6:
        decimals += 1
    text = f"{value:.{decimals}f}"
    return "0" if text.strip("-0.") == "" else text


def _text_size(text: str, scale: float) -> tuple[int, int]:
    import cv2

    (w, h), baseline = cv2.getTextSize(text, FONT, scale, 1)
    return w, h + baseline


def _put(img: np.ndarray, text: str, x: int, y: int, *, scale: float = FONT_SCALE, color=INK) -> None:
    """Draw text with its baseline at y."""
    import cv2

    cv2.putText(img, text, (int(x), int(y)), FONT, scale, color, 1, cv2.LINE_AA)


def _wrap(parts: Sequence[str], width: int) -> list[str]:
    """Join legend parts with '; ' into lines no wider than ``width`` pixels where possible."""
    lines: list[str] = []
    for part in parts:
        if lines and _text_size(lines[-1] + "; " + part, FONT_SCALE)[0] <= width:
            lines[-1] += "; " + part
        else:
            lines.append(part)
    return lines


def _write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - only for invalid images, which the callers never build
        raise ValueError(f"{os.fspath(path)}: PNG encoding failed")
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())


@dataclasses.dataclass(frozen=True)
class MapBox:
    """Where the map lies in a rendered PNG, and the colour range used (for tests and tools)."""

    top: int  # first row of the map
    left: int  # first column of the map
    height: int  # map rows in the PNG
    width: int  # map columns in the PNG
    scale: float  # PNG pixels per array cell
    vmin: float  # value at the bottom of the colour bar
    vmax: float  # value at the top of the colour bar


def _map_scale(shape: tuple[int, int]) -> float:
    """Integer enlargement for small maps, reduction factor for huge ones, 1 otherwise."""
    side = max(shape)
    if side < MIN_MAP_SIDE:
        return float(max(1, MIN_MAP_SIDE // side))
    if side > MAX_MAP_SIDE:
        return MAX_MAP_SIDE / side
    return 1.0


def height_png(
    path: str | os.PathLike,
    array: np.ndarray,
    *,
    title: str,
    units: str = "m",
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: int | np.ndarray | None = None,
    overlays: Sequence[tuple[np.ndarray, tuple[int, int, int], str]] = (),
) -> MapBox:
    """Write a 2D array (a DSM, an error map) as a colour PNG with a labelled colour bar.

    ``vmin``/``vmax`` default to the 2nd/98th percentiles of the finite values; values beyond are
    clipped to the end colours. ``cmap``: OpenCV ``COLORMAP_*`` constant (default viridis) or a
    (256, 1, 3) BGR table (``diverging_lut()`` for signed errors). NaN cells are grey. The map is
    drawn north up, one PNG pixel per cell unless the size limits apply (see the module
    docstring). ``overlays``: (mask, BGR colour, legend label) triples painted over the map in
    order, e.g. cells where a prediction is missing; each is counted in the legend line. Returns
    where the map lies in the image.
    """
    import cv2

    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2 or 0 in a.shape:
        raise ValueError(f"height_png needs a non-empty 2D array, got shape {a.shape}")
    lo, hi = display_range(a)
    lo = lo if vmin is None else float(vmin)
    hi = hi if vmax is None else float(vmax)
    if not hi > lo:
        raise ValueError(f"height_png: vmin {lo!r} must be below vmax {hi!r}")
    colored = colorize(a, vmin=lo, vmax=hi, cmap=cmap)
    legend_parts = [f"{a.shape[1]}x{a.shape[0]} cells", f"grey: no data ({int(np.count_nonzero(~np.isfinite(a)))})"]
    for mask, color, label in overlays:
        m = np.asarray(mask, dtype=bool)
        if m.shape != a.shape:
            raise ValueError(f"height_png: overlay {label!r} has shape {m.shape}, the map {a.shape}")
        colored[m] = color
        legend_parts.append(f"{label} ({int(np.count_nonzero(m))})")
    scale = _map_scale(a.shape)
    if scale != 1.0:
        size = (max(1, round(a.shape[1] * scale)), max(1, round(a.shape[0] * scale)))
        interp = cv2.INTER_NEAREST if scale > 1.0 else cv2.INTER_AREA
        colored = cv2.resize(colored, size, interpolation=interp)
    mh, mw = colored.shape[:2]

    ticks = nice_ticks(lo, hi)
    step = float(ticks[1] - ticks[0]) if ticks.size > 1 else 1.0
    labels = [_tick_text(float(t), step) for t in ticks]
    label_w = max(_text_size(s, FONT_SCALE)[0] for s in labels + [units])
    bar_h = max(mh, MIN_BAR_HEIGHT)
    bar_x = MARGIN + mw + BAR_GAP
    width = bar_x + BAR_WIDTH + TICK_LENGTH + 4 + label_w + MARGIN
    width = max(width, _text_size(title, TITLE_SCALE)[0] + 2 * MARGIN)
    legend_parts.append(f"colours clipped to [{lo:.4g}, {hi:.4g}] {units}")
    legend_lines = _wrap(legend_parts, width - 2 * MARGIN)
    width = max([width] + [_text_size(line, FONT_SCALE)[0] + 2 * MARGIN for line in legend_lines])
    body_h = max(mh, bar_h)
    height = TITLE_HEIGHT + body_h + FOOTER_HEIGHT * len(legend_lines) + MARGIN
    img = np.full((height, width, 3), BACKGROUND, dtype=np.uint8)

    _put(img, title, MARGIN, 22, scale=TITLE_SCALE)
    img[TITLE_HEIGHT:TITLE_HEIGHT + mh, MARGIN:MARGIN + mw] = colored
    cv2.rectangle(img, (MARGIN - 1, TITLE_HEIGHT - 1), (MARGIN + mw, TITLE_HEIGHT + mh), INK, 1)

    # Colour bar: top row = hi, bottom row = lo, sampled at row centres.
    rows = hi - (np.arange(bar_h) + 0.5) / bar_h * (hi - lo)
    bar = colorize(np.repeat(rows[:, None], BAR_WIDTH, axis=1), vmin=lo, vmax=hi, cmap=cmap)
    top = TITLE_HEIGHT
    img[top:top + bar_h, bar_x:bar_x + BAR_WIDTH] = bar
    cv2.rectangle(img, (bar_x - 1, top - 1), (bar_x + BAR_WIDTH, top + bar_h), INK, 1)
    text_h = _text_size("0", FONT_SCALE)[1]
    for value, label in zip(ticks, labels):
        y = top + int(round((hi - value) / (hi - lo) * (bar_h - 1)))
        cv2.line(img, (bar_x + BAR_WIDTH, y), (bar_x + BAR_WIDTH + TICK_LENGTH, y), INK, 1)
        baseline = min(max(y + text_h // 2 - 2, top + text_h - 4), top + bar_h + text_h // 2)
        _put(img, label, bar_x + BAR_WIDTH + TICK_LENGTH + 4, baseline)
    _put(img, units, bar_x, top - 10)

    for k, line in enumerate(legend_lines):
        _put(img, line, MARGIN, TITLE_HEIGHT + body_h + FOOTER_HEIGHT * (k + 1) - 8)
    _write_png(path, img)
    return MapBox(top=TITLE_HEIGHT, left=MARGIN, height=mh, width=mw, scale=scale, vmin=lo, vmax=hi)


def histogram_png(
    path: str | os.PathLike,
    values: np.ndarray,
    *,
    bins: int,
    title: str,
    units: str = "m",
    value_range: tuple[float, float] | None = None,
    markers: Sequence[float] = (),
) -> np.ndarray:
    """Write a histogram of the finite ``values`` as a ``HIST_WIDTH`` x ``HIST_HEIGHT`` PNG.

    ``value_range`` defaults to the 1st..99th percentiles; values outside it are not binned but
    their counts are printed. ``markers``: x positions drawn as red vertical lines (e.g. the
    +-1 m threshold). Returns the bin counts (``np.histogram`` over the range).
    """
    import cv2

    if not (isinstance(bins, int) and bins >= 1):
        raise ValueError(f"histogram_png: bins = {bins!r} must be a positive integer")
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if value_range is None:
        if v.size:
            lo, hi = (float(x) for x in np.percentile(v, [1.0, 99.0]))
        else:
            lo, hi = 0.0, 1.0
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
    else:
        lo, hi = (float(x) for x in value_range)
        if not hi > lo:
            raise ValueError(f"histogram_png: value_range {value_range!r} must be increasing")
    counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
    below = int(np.count_nonzero(v < lo))
    above = int(np.count_nonzero(v > hi))

    img = np.full((HIST_HEIGHT, HIST_WIDTH, 3), BACKGROUND, dtype=np.uint8)
    left, right, top, bottom = 70, HIST_WIDTH - 20, 50, HIST_HEIGHT - 60
    plot_w, plot_h = right - left, bottom - top
    _put(img, title, MARGIN, 24, scale=TITLE_SCALE)
    cmax = int(counts.max()) if counts.size and counts.max() > 0 else 1

    def x_of(value: float) -> int:
        return left + int(round((value - lo) / (hi - lo) * plot_w))

    for k, c in enumerate(counts):
        if c == 0:
            continue
        x0, x1 = x_of(edges[k]), max(x_of(edges[k + 1]) - 1, x_of(edges[k]))
        y0 = bottom - int(round(c / cmax * plot_h))
        cv2.rectangle(img, (x0, y0), (x1, bottom), BAR_COLOR, -1)
    for m in markers:
        if lo <= m <= hi:
            cv2.line(img, (x_of(m), top), (x_of(m), bottom), MARKER_COLOR, 1)
    cv2.line(img, (left, bottom), (right, bottom), INK, 1)
    cv2.line(img, (left, top), (left, bottom), INK, 1)

    ticks = nice_ticks(lo, hi, target=7)
    step = float(ticks[1] - ticks[0]) if ticks.size > 1 else 1.0
    for t in ticks:
        x = x_of(float(t))
        cv2.line(img, (x, bottom), (x, bottom + TICK_LENGTH), INK, 1)
        label = _tick_text(float(t), step)
        w, h = _text_size(label, FONT_SCALE)
        _put(img, label, x - w // 2, bottom + TICK_LENGTH + h)
    for count, y in ((0, bottom), (cmax, top)):
        label = str(count)
        w, h = _text_size(label, FONT_SCALE)
        cv2.line(img, (left - TICK_LENGTH, y), (left, y), INK, 1)
        _put(img, label, left - TICK_LENGTH - 4 - w, y + h // 2 - 2)
    median = f"{np.median(v):.3g}" if v.size else "n/a"
    footer = f"x axis: {units}; {v.size} values, median {median}; {below} below and {above} above the range"
    _put(img, footer, left, HIST_HEIGHT - 14)
    _write_png(path, img)
    return counts
