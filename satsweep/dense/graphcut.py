"""Graph-cut refinement: alpha-expansion (Boykov, Veksler and Zabih 2001) with PyMaxflow on the
host.

Each expansion move minimises the energy of :mod:`satsweep.dense.mrf` exactly (truncated linear
smoothness is a metric: Kolmogorov and Zabih 2004). The cost is bounded by solving
coarse-to-fine, restricting each pixel to a window of labels around the coarser solution, and by
tiling with overlap.
"""

from __future__ import annotations

import time

import numpy as np

from satsweep.dense.mrf import (
    MRFOptions,
    MRFResult,
    _check_guide,
    _check_heights,
    _check_scale,
    _check_visible,
    _energy,
    _finish,
    _host_volume,
    _parabola_offset,
    _sanitised,
    edge_weights,
)
from satsweep.dense.volume import CostVolume
from satsweep.errors import InputError


class _ExpansionGrid:
    """Alpha-expansion on one tile: data costs (L, n), 4-connected edges with weights.

    Edge ids: horizontal edge (p, p+1) has id p, vertical edge (p, p+w) has id n + p (weights of
    non-existent edges at the right and bottom borders are 0 and they are never used).
    """

    def __init__(self, data: np.ndarray, wh: np.ndarray, wv: np.ndarray, truncation: int):
        self.n_labels, self.h, self.w = data.shape
        self.n = self.h * self.w
        self.data = data.reshape(self.n_labels, self.n)
        n, w = self.n, self.w
        pid = np.arange(n)
        px, py = pid % w, pid // w
        self.has_right, self.has_down = px < w - 1, py < self.h - 1
        self.has_left, self.has_up = px > 0, py > 0
        wgt = np.zeros(2 * n)
        wgt[:n].reshape(self.h, w)[:, :-1] = wh
        wgt[n:].reshape(self.h, w)[:-1, :] = wv
        self.weight = wgt
        self.p = np.concatenate([pid, pid])
        self.q = np.concatenate([np.minimum(pid + 1, n - 1), np.minimum(pid + w, n - 1)])
        self.truncation = truncation
        self.is_free = np.zeros(n, bool)
        self.local = np.zeros(n, np.int64)

    def _v(self, a: np.ndarray, b) -> np.ndarray:
        return np.minimum(np.abs(a - b), self.truncation)

    def move(self, labels: np.ndarray, alpha: int, free: np.ndarray) -> int:
        """Optimal expansion of ``alpha`` over the pixels ``free`` (flat ids); others keep their
        labels. Updates ``labels`` in place; returns how many pixels switched."""
        import maxflow  # noqa: PLC0415

        k = free.size
        if k == 0:
            return 0
        n, w = self.n, self.w
        isf, loc = self.is_free, self.local
        isf[free] = True
        loc[free] = np.arange(k)
        # Each edge touching a free pixel once: its own right/down edges, and its left/up edges
        # when that neighbour is not free (otherwise the neighbour owns the edge).
        left, up = free - 1, free - w
        eids = np.concatenate([
            free[self.has_right[free]],
            n + free[self.has_down[free]],
            left[self.has_left[free] & ~isf[np.maximum(left, 0)]],
            n + up[self.has_up[free] & ~isf[np.maximum(up, 0)]],
        ])
        p, q, wt = self.p[eids], self.q[eids], self.weight[eids]
        lp, lq = labels[p], labels[q]
        e_a = wt * self._v(lp, lq)       # A = E(0, 0): both keep their labels
        e_b = wt * self._v(lp, alpha)    # B = E(0, 1): q takes alpha
        e_c = wt * self._v(lq, alpha)    # C = E(1, 0): p takes alpha; D = E(1, 1) = 0
        fp, fq = isf[p], isf[q]
        both, only_p = fp & fq, fp & ~fq
        lp_loc, lq_loc = loc[p], loc[q]
        lab_f = labels[free]
        # Unary terms (u0: keep, u1: take alpha). Both free: E = A + (C - A) xp - C xq
        # + (B + C - A) (1 - xp) xq, and -C xq = C (1 - xq) - C; only p free: A or C; only q
        # free: A or B. Each edge adds to one u0 and one u1 entry.
        idx0 = np.where(only_p, lp_loc, lq_loc)
        val0 = np.where(both, e_c, e_a)
        idx1 = np.where(fp, lp_loc, lq_loc)
        val1 = np.where(both, e_c - e_a, np.where(only_p, e_c, e_b))
        u0 = self.data[lab_f, free] + np.bincount(idx0, val0, minlength=k)
        u1 = self.data[alpha, free] + np.bincount(idx1, val1, minlength=k)
        m = np.minimum(u0, u1)
        u0 -= m
        u1 -= m
        # Pairwise edge p -> q, cut when p keeps and q takes alpha: B + C - A >= 0 (truncated
        # linear is a metric); clipped against rounding.
        cap = np.maximum(e_b[both] + e_c[both] - e_a[both], 0.0)
        g = maxflow.Graph[float](k, int(both.sum()))
        nodes = g.add_nodes(k)
        if cap.size:
            g.add_edges(lp_loc[both], lq_loc[both], cap, np.zeros(cap.size))
        # A node in the sink segment (x = 1, takes alpha) cuts its source edge: capacity u1.
        g.add_grid_tedges(nodes, u1, u0)
        g.maxflow()
        switch = g.get_grid_segments(nodes) & (lab_f != alpha)
        labels[free[switch]] = alpha
        isf[free] = False
        return int(switch.sum())

    def solve(self, labels: np.ndarray, lo: np.ndarray, hi: np.ndarray, iterations: int) -> int:
        """Alpha-expansion sweeps with each pixel's label restricted to [lo, hi] (flat arrays).

        ``labels`` (flat, int64) must lie in the windows; updated in place. Alphas go from the
        lowest to the highest label any window allows; the sweeps stop early when one changes
        nothing. Returns the number of expansion moves made.
        """
        moves = 0
        alphas = range(int(lo.min()), int(hi.max()) + 1)
        for _ in range(iterations):
            changed = 0
            for alpha in alphas:
                free = np.flatnonzero((lo <= alpha) & (hi >= alpha))
                changed += self.move(labels, alpha, free)
                moves += 1
            if changed == 0:
                break
        return moves


def _downsample2(a: np.ndarray) -> np.ndarray:
    """2x2 block means over the last two axes (odd sizes padded by edge replication)."""
    h, w = a.shape[-2:]
    pad = [(0, 0)] * (a.ndim - 2) + [(0, h % 2), (0, w % 2)]
    if h % 2 or w % 2:
        a = np.pad(a, pad, mode="edge")
    return 0.25 * (a[..., 0::2, 0::2] + a[..., 1::2, 0::2] + a[..., 0::2, 1::2]
                   + a[..., 1::2, 1::2])


def _upsample2(labels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return np.repeat(np.repeat(labels, 2, axis=0), 2, axis=1)[:shape[0], :shape[1]]


def _coarse_weights(wh: np.ndarray, wv: np.ndarray, level: int,
                    shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Smoothness weights of the grid coarsened ``level`` times (blocks of s = 2^level pixels).

    A cut between two neighbouring blocks A and B stands for a fine cut that may run anywhere
    through A and B: for each of the s fine rows (columns) crossing them, the cheapest fine edge
    of that row within A and B, summed, divided by s^2 like the block-averaged data. With equal
    weights this is weight / s (the energy of a region keeps its balance between data and
    smoothness); across a strong edge of the guide anywhere inside A or B the coarse weight is
    low, so the coarse solution can follow edges that do not fall on block boundaries.
    ``shape`` is the coarse grid (rows, columns); the fine grid is padded by replication.
    """
    from numpy.lib.stride_tricks import sliding_window_view  # noqa: PLC0415

    s = 1 << level
    hc, wc = shape

    def per_axis(wgt: np.ndarray, n_blocks_across: int, n_blocks_along: int) -> np.ndarray:
        # wgt: (fine rows, fine edges along the row); rows are grouped by s, edges windowed.
        rows = n_blocks_along * s
        wgt = np.pad(wgt, ((0, max(rows - wgt.shape[0], 0)), (0, 0)), mode="edge")[:rows]
        width = (n_blocks_across + 1) * s - 1
        wgt = np.pad(wgt, ((0, 0), (0, max(width - wgt.shape[1], 0))), constant_values=np.inf)
        win = sliding_window_view(wgt, 2 * s - 1, axis=1)[:, 0:(n_blocks_across - 1) * s:s]
        best = win.min(axis=2)                                  # (rows, n_blocks_across - 1)
        return best.reshape(n_blocks_along, s, -1).sum(axis=1) / float(s * s)

    wh_c = per_axis(wh, wc, hc) if wc > 1 else np.zeros((hc, 0))
    wv_c = per_axis(wv.T, hc, wc).T if hc > 1 else np.zeros((0, wc))
    return wh_c, wv_c


def _solve_tiled(data: np.ndarray, wh: np.ndarray, wv: np.ndarray, init: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray, options: MRFOptions, tile: int) -> np.ndarray:
    """Alpha-expansion over tiles of ``tile`` pixels, each extended by the overlap on every side
    and solved independently from ``init`` with labels in [lo, hi]; the kept parts are joined."""
    n_labels, h, w = data.shape
    out = init.copy()
    ov = options.gc_tile_overlap
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            ya, xa = max(y0 - ov, 0), max(x0 - ov, 0)
            yb, xb = min(y1 + ov, h), min(x1 + ov, w)
            grid = _ExpansionGrid(np.ascontiguousarray(data[:, ya:yb, xa:xb]),
                                  wh[ya:yb, xa:xb - 1], wv[ya:yb - 1, xa:xb],
                                  options.gc_truncation_labels)
            lab = init[ya:yb, xa:xb].astype(np.int64).ravel()
            grid.solve(lab, lo[ya:yb, xa:xb].ravel(), hi[ya:yb, xa:xb].ravel(),
                       options.gc_iterations)
            out[y0:y1, x0:x1] = lab.reshape(yb - ya, xb - xa)[y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out


def _coarse_windows(coarse: np.ndarray, shape: tuple[int, int], window: int,
                    n_labels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial labels and label windows at a finer level from the coarser level's labels.

    Each fine pixel starts from its coarse pixel's label and may take labels from the lowest to
    the highest label of the 3x3 coarse neighbourhood, widened by ``window``: a fine pixel near a
    height discontinuity can take either side's height even where the coarse grid put the edge
    one coarse pixel off.
    """
    import cv2  # noqa: PLC0415

    kernel = np.ones((3, 3), np.uint8)  # 3x3 min / max, outside the image ignored
    c = np.asarray(coarse, np.float64)  # exact for labels; OpenCV morphology has no int64
    lo = cv2.erode(c, kernel, borderType=cv2.BORDER_REPLICATE).astype(coarse.dtype)
    hi = cv2.dilate(c, kernel, borderType=cv2.BORDER_REPLICATE).astype(coarse.dtype)
    return (_upsample2(coarse, shape), np.maximum(_upsample2(lo, shape) - window, 0),
            np.minimum(_upsample2(hi, shape) + window, n_labels - 1))


def _graphcut_confidence(data: np.ndarray, labels: np.ndarray, wh: np.ndarray, wv: np.ndarray,
                         truncation: int, cost_scale: float) -> np.ndarray:
    """Margin of the conditional energy E_p(k) = D(p, k) + sum_q w_pq V(k, l_q) at the label.

    Streams over k keeping three planes: (second-lowest local minimum of E_p other than at l_p,
    else max E_p) - E_p(l_p), divided by cost_scale. Local minima as in wta.cl (E_k < E_{k-1} and
    E_k <= E_{k+1}, the missing ends +inf).
    """
    n_labels, h, w = data.shape
    pads = []  # (neighbour labels, weights) for the 4 neighbours, weight 0 outside the image
    for axis, wgt in ((1, wh), (0, wv)):
        for side in (0, 1):
            nl = np.zeros((h, w), np.int64)
            ww = np.zeros((h, w))
            if axis == 1:
                if side == 0:
                    nl[:, :-1], ww[:, :-1] = labels[:, 1:], wgt
                else:
                    nl[:, 1:], ww[:, 1:] = labels[:, :-1], wgt
            else:
                if side == 0:
                    nl[:-1], ww[:-1] = labels[1:], wgt
                else:
                    nl[1:], ww[1:] = labels[:-1], wgt
            pads.append((nl, ww))

    def energy(k: int) -> np.ndarray:
        e = data[k].astype(np.float64)
        for nl, ww in pads:
            e += ww * np.minimum(np.abs(k - nl), truncation)
        return e

    inf = np.full((h, w), np.inf)
    at_label = np.zeros((h, w))
    other_min = np.full((h, w), np.inf)
    emax = np.full((h, w), -np.inf)
    prev2, prev = inf, energy(0)
    for k in range(n_labels):
        nxt = energy(k + 1) if k + 1 < n_labels else inf
        cur = prev
        emax = np.maximum(emax, cur)
        is_label = labels == k
        at_label[is_label] = cur[is_label]
        local_min = (cur < prev2) & (cur <= nxt) & ~is_label
        other_min = np.where(local_min, np.minimum(other_min, cur), other_min)
        prev2, prev = cur, nxt
    c2 = np.where(np.isfinite(other_min), other_min, emax)
    return (c2 - at_label) / cost_scale


def graphcut_refine(volume: CostVolume, guide, heights, options: MRFOptions, *,
                    cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
                    initial_labels=None) -> MRFResult:
    """Alpha-expansion graph cut of the energy in the module docstring, bounded in cost, over a
    host, plane-major ``volume`` of every plane (InputError for any other).

    With ``gc_levels`` > 0 the volume is solved coarse-to-fine: halved ``gc_levels`` times (2x2
    means of the costs, smoothness weights from the full-resolution ones by ``_coarse_weights``
    so that a region's energy keeps its balance and the guide's edges are kept), the coarsest
    level over all labels starting from its winner-take-all,
    each finer level starting from the upsampled coarser labels within the windows of
    ``_coarse_windows``. With ``gc_levels`` = 0 one level is solved within +-gc_label_window of
    ``initial_labels`` (e.g. the sweep's WTA planes; by default the WTA of ``volume``).
    ``initial_labels`` is not used when ``gc_levels`` > 0: where the WTA fails (weak texture) a
    window around it misses the true plane, which is why coarse-to-fine is the default.
    Each level is solved in tiles of ``gc_tile`` pixels (scaled with the level) extended by
    ``gc_tile_overlap`` on every side, each tile independently. The sub-plane offset is the
    parabola through the data costs around the label (the wta.cl rule).
    """
    t0 = time.perf_counter()
    scale = _check_scale(cost_scale)
    c = _sanitised(_host_volume(volume, "the graph cut"), scale)
    n_labels, h, w = c.shape
    hts = _check_heights(heights, n_labels)
    g = _check_guide(guide, (h, w)).astype(np.float64)
    vis = _check_visible(visible, c.shape)
    window = options.gc_label_window
    wh, wv = edge_weights(g, options, scale)
    pyramid = [(c, wh, wv)]
    if options.gc_levels == 0:
        if initial_labels is None:
            labels = np.argmin(c, axis=0).astype(np.int64)
        else:
            init = np.asarray(initial_labels)
            if init.shape != (h, w) or not np.issubdtype(init.dtype, np.integer):
                raise InputError(None, f"initial_labels: expected integer labels of shape "
                                       f"{(h, w)}, got {init.dtype} {init.shape}")
            if init.min() < 0 or init.max() >= n_labels:
                raise InputError(None, f"initial_labels: values must be in [0, {n_labels - 1}]")
            labels = init.astype(np.int64)
        lo, hi = np.maximum(labels - window, 0), np.minimum(labels + window, n_labels - 1)
    else:
        for _ in range(options.gc_levels):
            if min(pyramid[-1][0].shape[1:]) < 8:
                break
            coarse = _downsample2(pyramid[-1][0])
            pyramid.append((coarse,) + _coarse_weights(wh, wv, len(pyramid), coarse.shape[1:]))
        labels = np.argmin(pyramid[-1][0], axis=0).astype(np.int64)
        lo, hi = np.zeros_like(labels), np.full_like(labels, n_labels - 1)

    for level in range(len(pyramid) - 1, -1, -1):
        data, lwh, lwv = pyramid[level]
        if labels.shape != data.shape[1:]:
            labels, lo, hi = _coarse_windows(labels, data.shape[1:], window, n_labels)
        labels = _solve_tiled(data, lwh, lwv, labels, lo, hi, options,
                              max(16, options.gc_tile >> level))

    lab = labels.astype(np.intp)
    c0 = np.take_along_axis(c, lab[None], axis=0)[0]
    cm = np.take_along_axis(c, np.maximum(lab - 1, 0)[None], axis=0)[0]
    cp = np.take_along_axis(c, np.minimum(lab + 1, n_labels - 1)[None], axis=0)[0]
    offset = _parabola_offset(cm, c0, cp, (lab > 0) & (lab < n_labels - 1))
    conf = _graphcut_confidence(c, labels, wh, wv, options.gc_truncation_labels, scale)
    energy = _energy(c, g, labels, options, scale)
    return _finish(labels, offset, conf, c0, hts, vis, reject_range_edges,
                   time.perf_counter() - t0, energy)
