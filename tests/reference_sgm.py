"""Numpy reference of kernels/sgm.cl (test-only): semi-global aggregation in float32.

It computes the recurrence documented in sgm.cl with the same float32 operations in the same
order, but organised differently (column by column or row by row, all scanlines at once, instead
of one scanline per work-group), so that an indexing or boundary mistake in either shows up:

    Lr(p, d) = C(p, d) + (min(Lr(p-r, d), Lr(p-r, d-1) + P1, Lr(p-r, d+1) + P1, m + P2') - m)
    m        = min_k Lr(p-r, k)
    P2'      = max(P1, P2 / (1 + |I(p) - I(p-r)| * inv_sigma))

with Lr(p, d) = C(p, d) where p-r lies outside the image. With label bases (``label_base``), label d of
pixel p is plane base[p] + d and Lr(p-r, .) is read at d + base[p] - base[p-r] (+inf outside its
window), as documented in sgm.cl; with label counts (``label_count``), pixel p has only labels
d < count[p]: the others are +inf here, so that they never win a minimum and read as outside
the window (the kernel leaves them alone; compare labels below the counts only). Cost entries at
or below
SATSWEEP_INVALID / 2 are replaced by ``missing_cost``. The aggregated volume is the sum of the
Lr over the paths, added in the order of ``SGM_DIRECTIONS[:n_paths]`` starting from the first.
"""

from __future__ import annotations

import numpy as np

from satsweep.dense.sgm import SGM_DIRECTIONS
from satsweep.opencl.constants import SATSWEEP_INVALID

F32 = np.float32


def _sanitise(cost: np.ndarray, missing_cost: float) -> np.ndarray:
    c = np.asarray(cost, dtype=F32)
    return np.where(c > F32(0.5 * SATSWEEP_INVALID), c, F32(missing_cost)).astype(F32)


def _shifted(prev: np.ndarray, delta: np.ndarray, offset: int) -> np.ndarray:
    """prev[d + delta + offset] per column (delta (n,)), +inf outside [0, L)."""
    n_labels = prev.shape[0]
    j = np.arange(n_labels)[:, None] + delta[None, :] + offset
    inside = (j >= 0) & (j < n_labels)
    out = np.take_along_axis(prev, np.clip(j, 0, n_labels - 1), axis=0)
    return np.where(inside, out, F32(np.inf)).astype(F32)


def _step(c: np.ndarray, prev: np.ndarray, gcur: np.ndarray, gprev: np.ndarray,
          p1: np.float32, p2: np.float32, inv_sigma: np.float32,
          delta: np.ndarray | None = None) -> np.ndarray:
    """One step of the recurrence for a batch: c, prev (L, n); gcur, gprev (n,); delta (n,) the
    base differences base[p] - base[p-r] (None: all 0)."""
    p2a = np.maximum(p1, p2 / (F32(1.0) + np.abs(gcur - gprev) * inv_sigma)).astype(F32)
    m = prev.min(axis=0)
    if delta is None:
        delta = np.zeros(prev.shape[1], np.int64)
    best = np.minimum(_shifted(prev, delta, 0), m + p2a)
    best = np.minimum(best, _shifted(prev, delta, -1) + p1)
    best = np.minimum(best, _shifted(prev, delta, 1) + p1)
    return (c + (best - m)).astype(F32)


def path_cost(cost: np.ndarray, guide: np.ndarray, dx: int, dy: int, *, p1: float, p2: float,
              inv_sigma: float, missing_cost: float,
              label_base: np.ndarray | None = None,
              label_count: np.ndarray | None = None) -> np.ndarray:
    """Lr for the single direction r = (dx, dy): (L, H, W) float32."""
    c = _sanitise(cost, missing_cost)
    if label_count is not None:
        beyond = np.arange(c.shape[0])[:, None, None] >= np.asarray(label_count)[None]
        c = np.where(beyond, F32(np.inf), c).astype(F32)
    base = np.zeros(c.shape[1:], np.int64) if label_base is None \
        else np.asarray(label_base, np.int64)
    g = np.asarray(guide, dtype=F32)
    p1f, p2f, isf = F32(p1), F32(p2), F32(inv_sigma)
    n_labels, h, w = c.shape
    out = np.empty_like(c)
    if dx != 0:
        xs = range(w) if dx > 0 else range(w - 1, -1, -1)
        for i, x in enumerate(xs):
            if i == 0:
                out[:, :, x] = c[:, :, x]
                continue
            xp = x - dx
            ys = np.arange(h)
            yp = ys - dy
            inside = (yp >= 0) & (yp < h)
            out[:, ~inside, x] = c[:, ~inside, x]
            yi, ypi = ys[inside], yp[inside]
            out[:, yi, x] = _step(c[:, yi, x], out[:, ypi, xp], g[yi, x], g[ypi, xp], p1f, p2f, isf,
                                  base[yi, x] - base[ypi, xp])
    else:
        ys = range(h) if dy > 0 else range(h - 1, -1, -1)
        for i, y in enumerate(ys):
            if i == 0:
                out[:, y, :] = c[:, y, :]
                continue
            out[:, y, :] = _step(c[:, y, :], out[:, y - dy, :], g[y, :], g[y - dy, :],
                                 p1f, p2f, isf, base[y, :] - base[y - dy, :])
    return out


def aggregate(cost: np.ndarray, guide: np.ndarray, *, n_paths: int, p1: float, p2: float,
              inv_sigma: float, missing_cost: float,
              label_base: np.ndarray | None = None,
              label_count: np.ndarray | None = None) -> np.ndarray:
    """Sum of the path costs over the first ``n_paths`` directions, in float32, in order."""
    total = None
    for dx, dy in SGM_DIRECTIONS[:n_paths]:
        lr = path_cost(cost, guide, dx, dy, p1=p1, p2=p2, inv_sigma=inv_sigma,
                       missing_cost=missing_cost, label_base=label_base,
                       label_count=label_count)
        total = lr if total is None else (total + lr).astype(F32)
    return total
