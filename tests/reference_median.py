"""Numpy reference of kernels/median.cl (test-only): the weighted median of
satsweep.dense.median in float64, with how close each pixel's choice lies to a tie."""

from __future__ import annotations

import numpy as np

from satsweep.dense.median import _check


def weighted_median_reference(height: np.ndarray, valid: np.ndarray, guide: np.ndarray, *,
                              radius: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """``satsweep.dense.median.weighted_median`` in numpy (float64), and per pixel how far the running sum of the
    weights at the chosen height and at the one before lie from half the total (a fraction of
    the total; where it is tiny, float32 sums may pick the neighbouring height)."""
    height = np.asarray(height, np.float64)
    valid = np.asarray(valid, bool)
    guide = np.asarray(guide, np.float64)
    _check(height, valid, guide, radius, sigma)
    r = radius
    H, W = height.shape
    hp = np.pad(np.where(valid, height, np.nan), r, constant_values=np.nan)
    gp = np.pad(guide, r, mode="edge")
    hs, ws = [], []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            hh = hp[r + dy:r + dy + H, r + dx:r + dx + W]
            gg = gp[r + dy:r + dy + H, r + dx:r + dx + W]
            wq = np.exp(-((gg - guide) ** 2) / (2.0 * sigma * sigma)
                        - (dx * dx + dy * dy) / (2.0 * r * r))
            ok = np.isfinite(hh)
            hs.append(np.where(ok, hh, np.inf))
            ws.append(np.where(ok, wq, 0.0))
    hs, ws = np.stack(hs, -1), np.stack(ws, -1)
    order = np.argsort(hs, axis=-1, kind="stable")
    hs, ws = np.take_along_axis(hs, order, -1), np.take_along_axis(ws, order, -1)
    run = np.cumsum(ws, -1)
    total = run[..., -1:]
    k = np.argmax(run >= 0.5 * total, axis=-1)[..., None]
    out = np.where(valid, np.take_along_axis(hs, k, -1)[..., 0], height)
    with np.errstate(invalid="ignore", divide="ignore"):
        above = (np.take_along_axis(run, k, -1) - 0.5 * total) / total
        below = (0.5 * total - np.take_along_axis(run, np.maximum(k - 1, 0), -1)) / total
        below = np.where(k > 0, below, np.inf)
    margin = np.where(valid, np.minimum(above, below)[..., 0], np.inf)
    return out, margin
