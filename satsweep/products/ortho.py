"""The true orthophoto: each cell's image value at its highest point, radiometrically matched
between views.
"""

from __future__ import annotations

import numpy as np

from satsweep.products.grid import DSMGrid


def value_at_highest(cells: np.ndarray, heights, values, grid: DSMGrid) -> np.ndarray:
    """Per grid cell, the ``values`` of its highest point (``rasterise_max_cells``' rule: the
    point that sets the cell's height): what a true orthophoto shows, the surface seen from
    above. (grid.height, grid.width) float32, NaN where no point fell; points without a finite
    height or value are ignored; of points tied for the highest, the largest value."""
    return values_at_highest(cells, heights, [values], grid)[0]


def values_at_highest(cells: np.ndarray, heights, value_sets, grid: DSMGrid) -> list[np.ndarray]:
    """:func:`value_at_highest` of each of ``value_sets`` (a sequence of per-point values) over
    the same points: the highest point per cell is found once for value sets that are finite on
    the same points."""
    c = np.asarray(cells, np.int64).ravel()
    z = np.asarray(heights, np.float64).ravel()
    sets = [np.asarray(v, np.float64).ravel() for v in value_sets]
    for v in sets:
        if not (c.size == z.size == v.size):
            raise ValueError(f"value_at_highest: lengths differ ({c.size} cells, {z.size} "
                             f"heights, {v.size} values)")
    ok = np.isfinite(z) & (c >= 0)
    outs = []
    last = None  # (points used, the cells of those that are their cell's highest, and which)
    for v in sets:
        use = ok & np.isfinite(v)
        if last is None or not np.array_equal(last[0], use):
            cu, zu = c[use], z[use]
            top = np.full(grid.width * grid.height, -np.inf)
            np.maximum.at(top, cu, zu)
            highest = zu == top[cu]
            last = (use, cu[highest], np.flatnonzero(use)[highest])
        _, cells_top, points_top = last
        out = np.full(grid.width * grid.height, -np.inf)
        np.maximum.at(out, cells_top, v[points_top])
        out[np.isneginf(out)] = np.nan
        outs.append(out.reshape(grid.shape).astype(np.float32))
    return outs


# Cells two views must share for match_radiometry to fit one to the other.
RADIOMETRY_MIN_CELLS = 100


def match_radiometry(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """``other`` with the gain and offset that bring it to ``reference``'s radiometry, fitted on
    the cells both have (finite): the gain matches their interquartile ranges, the offset their
    medians (robust to the cells where they see different things). ``other`` unchanged when
    they share fewer than ``RADIOMETRY_MIN_CELLS`` cells or ``other`` is flat there."""
    both = np.isfinite(reference) & np.isfinite(other)
    if np.count_nonzero(both) < RADIOMETRY_MIN_CELLS:
        return other
    r = np.asarray(reference, np.float64)[both]
    o = np.asarray(other, np.float64)[both]
    r25, r50, r75 = np.percentile(r, [25, 50, 75])
    o25, o50, o75 = np.percentile(o, [25, 50, 75])
    if not o75 > o25:
        return other
    gain = (r75 - r25) / (o75 - o25)
    return (gain * (np.asarray(other, np.float64) - o50) + r50).astype(np.float32)
