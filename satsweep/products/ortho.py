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
    c = np.asarray(cells, np.int64).ravel()
    z = np.asarray(heights, np.float64).ravel()
    v = np.asarray(values, np.float64).ravel()
    if not (c.size == z.size == v.size):
        raise ValueError(f"value_at_highest: lengths differ ({c.size} cells, {z.size} heights, "
                         f"{v.size} values)")
    ok = np.isfinite(z) & np.isfinite(v) & (c >= 0)
    c, z, v = c[ok], z[ok], v[ok]
    top = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(top, c, z)
    highest = z == top[c]
    out = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(out, c[highest], v[highest])
    out[np.isneginf(out)] = np.nan
    return out.reshape(grid.shape).astype(np.float32)


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
