"""Tracks: pairwise matches joined into multi-view observations of one ground point, and their
sub-pixel registration.

A *track* is an ``(k, 2)`` int64 array of ``(view, feature)`` rows, one per view, sorted by view:
the same ground point seen as keypoint ``feature`` of each listed ``view``. ``Observations`` is
the flat form the triangulation and the bundle adjustment use. :func:`register_observations`
registers each track's observations to its first one by Lucas-Kanade after warping the views
onto each other with the cameras' ground-plane homography, and :func:`best_registered` keeps,
of each pair of views, those whose windows match best. Measured against a synthetic town's
truth (1000 px views, 15 px windows): 0.09 px median where the window lies on one surface, 0.5
px where it straddles surfaces metres apart (most SIFT keypoints lie on building edges), 0.11 px
in the quarter of lowest residuals and 1.4 px in the highest; SIFT keypoints at half resolution
are off by 0.8 px (median).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.sparse.features import _to_u8
from satsweep.sparse.subpixel import refine_translations
from satsweep.threads import map_in_threads


# -- tracks --------------------------------------------------------------------------------------
def connected_labels(n_nodes: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Connected components of the undirected graph with edges ``src[k] - dst[k]`` over nodes
    0 .. n_nodes - 1: a label per node, 0 .. n_components - 1, numbered in the order of each
    component's smallest node (as scipy.sparse.csgraph.connected_components numbers them).

    Each round hooks every edge's larger root under the smaller one and then jumps pointers to
    the roots, until no edge joins two roots.
    """
    parent = np.arange(n_nodes)
    src, dst = np.asarray(src, np.int64), np.asarray(dst, np.int64)
    while True:
        a, b = parent[src], parent[dst]
        low, high = np.minimum(a, b), np.maximum(a, b)
        joined = low != high
        if not joined.any():
            break
        np.minimum.at(parent, high[joined], low[joined])
        while True:  # pointer jumping: every node to its root
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up
    return np.unique(parent, return_inverse=True)[1].reshape(-1)


def build_tracks(
    n_views: int, pair_matches: Mapping[tuple[int, int], tuple[np.ndarray, np.ndarray]]
) -> list[np.ndarray]:
    """Chain pairwise matches into tracks (connected components, i.e. union-find).

    ``pair_matches[(i, j)] = (idx_i, idx_j)``: feature ``idx_i[k]`` of view ``i`` matches feature
    ``idx_j[k]`` of view ``j``. Every (view, feature) is a node and every match an edge; each
    connected component with at least two nodes is a track. A component holding two features of
    one view is inconsistent (some match in it is wrong) and is dropped whole. Tracks are
    ``(k, 2)`` int64 arrays of ``(view, feature)`` sorted by view, in a deterministic order.
    """
    counts = np.zeros(n_views, dtype=np.int64)
    for (i, j), (a, b) in pair_matches.items():
        if not (0 <= i < n_views and 0 <= j < n_views) or i == j:
            raise CameraError(f"build_tracks: pair ({i}, {j}) is not a pair of views 0..{n_views - 1}")
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        if len(a) != len(b):
            raise CameraError(f"build_tracks: pair ({i}, {j}) has {len(a)} and {len(b)} indices")
        if len(a):
            counts[i] = max(counts[i], int(a.max()) + 1)
            counts[j] = max(counts[j], int(b.max()) + 1)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    n_nodes = int(offsets[-1])
    src = [offsets[i] + np.asarray(a, np.int64) for (i, _), (a, _b) in pair_matches.items()]
    dst = [offsets[j] + np.asarray(b, np.int64) for (_, j), (_a, b) in pair_matches.items()]
    if n_nodes == 0 or not src:
        return []
    src, dst = np.concatenate(src), np.concatenate(dst)
    if len(src) == 0:
        return []
    labels = connected_labels(n_nodes, src, dst)
    node_view = np.repeat(np.arange(n_views), counts)
    node_feature = np.arange(n_nodes) - offsets[node_view]
    # Group nodes by label (stable: nodes in view order within a component).
    order = np.argsort(labels, kind="stable")
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    sizes = np.diff(np.r_[starts, len(lab)])
    views_sorted = node_view[order]
    # A component is consistent when its views are all distinct (nodes are sorted by view).
    same_view = np.zeros(len(order), dtype=bool)
    same_view[1:] = (lab[1:] == lab[:-1]) & (views_sorted[1:] == views_sorted[:-1])
    bad = np.zeros(len(starts), dtype=bool)
    np.logical_or.at(bad, np.searchsorted(starts, np.flatnonzero(same_view), side="right") - 1, True)
    tracks = []
    for s, k, b in zip(starts, sizes, bad):
        if k < 2 or b:
            continue
        nodes = order[s:s + k]
        tracks.append(np.column_stack([node_view[nodes], node_feature[nodes]]))
    return tracks


@dataclasses.dataclass(frozen=True, eq=False)
class Observations:
    """Tracks flattened for vectorised maths: observation ``k`` is pixel ``xy[k]`` of point
    ``point[k]`` in view ``view[k]`` (int64, int64, float64 (M, 2))."""

    point: np.ndarray
    view: np.ndarray
    xy: np.ndarray
    n_points: int

    def subset(self, keep: np.ndarray) -> "Observations":
        """Keep observations ``keep`` (bool mask); points left with fewer than 2 are dropped and
        the remaining points renumbered 0..n-1 in their previous order."""
        return self.take(self.subset_index(keep))

    def take(self, rows: np.ndarray) -> "Observations":
        """The observations ``rows`` (indices, in order; each point keeping two or more, as
        :meth:`subset_index` gives them), points renumbered 0..n-1 in their previous order."""
        alive = np.zeros(self.n_points, dtype=bool)
        alive[self.point[rows]] = True
        new_index = np.cumsum(alive) - 1
        return Observations(point=new_index[self.point[rows]], view=self.view[rows],
                            xy=self.xy[rows], n_points=int(alive.sum()))

    def subset_index(self, keep: np.ndarray) -> np.ndarray:
        """The indices of the observations that :meth:`subset` keeps (to carry other per-
        observation arrays along)."""
        kept = np.flatnonzero(keep)
        count = np.bincount(self.point[kept], minlength=self.n_points)
        return kept[count[self.point[kept]] >= 2]


def observations_from_tracks(tracks: Sequence[np.ndarray], xys: Sequence[np.ndarray]) -> Observations:
    """Flatten tracks (see :func:`build_tracks`) with the keypoints ``xys[view]`` (N_v, 2)."""
    if len(tracks) == 0:
        return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), 0)
    lengths = np.array([len(t) for t in tracks], dtype=np.int64)
    flat = np.concatenate([np.asarray(t, np.int64) for t in tracks])
    point = np.repeat(np.arange(len(tracks)), lengths)
    xy = np.empty((len(flat), 2), dtype=np.float64)
    for v in np.unique(flat[:, 0]):
        sel = flat[:, 0] == v
        xy[sel] = np.asarray(xys[v], np.float64)[flat[sel, 1]]
    return Observations(point=point, view=flat[:, 0].copy(), xy=xy, n_points=len(tracks))


def _scrambled(points: np.ndarray) -> np.ndarray:
    """A multiplicative hash of point numbers: a fixed order unrelated to the image position."""
    return (np.asarray(points).astype(np.uint64) * np.uint64(2654435761)) % np.uint64(2**32)


def thin_points(obs: Observations, per_view: int) -> Observations:
    """The tie points of ``obs`` that give every view at least ``per_view`` observations (all of
    its own when it has fewer), with every observation of each point kept.

    Each view ranks its points longest track first (ties in a fixed pseudo-random order, so
    that no part of the image is preferred), and a point is kept when it is among the first
    ``per_view`` of any of its views. A view's principal point has two unknowns: a few hundred
    observations fix it to hundredths of a pixel, while a stack of many views gathers long
    tracks, thousands of observations per view, that the registration and the fine adjustment
    would pay for (see SparseOptions.fine_points_per_view). ``per_view`` 0: every point.
    """
    if per_view <= 0 or obs.xy.shape[0] == 0:
        return obs
    return obs.subset(thin_mask(obs, per_view))


def thin_mask(obs: Observations, per_view: int) -> np.ndarray:
    """The observations (bool, per observation) that :func:`thin_points` keeps: whole tracks,
    each of two observations or more."""
    if per_view <= 0 or obs.xy.shape[0] == 0:
        return np.ones(obs.xy.shape[0], dtype=bool)
    length = np.bincount(obs.point, minlength=obs.n_points)
    order = np.lexsort((_scrambled(obs.point), -length[obs.point], obs.view))  # by view, best first
    view_sorted = obs.view[order]
    start = np.searchsorted(view_sorted, view_sorted, side="left")
    rank = np.arange(len(order)) - start
    chosen = np.zeros(obs.n_points, dtype=bool)
    chosen[obs.point[order[rank < per_view]]] = True
    return chosen[obs.point]


def extend_tracks(obs: Observations, P: np.ndarray, shapes: Sequence[tuple[int, int]], *,
                  margin_px: float, per_view: int) -> Observations:
    """``obs`` with each point also observed, at its projection, in the views that do not see
    it yet: observations for :func:`register_observations` to move onto the image (it starts
    there, as from a keypoint) or drop. ``P`` (V, 3, 4): the views' cameras, as corrected as
    known (the points are triangulated with them); ``shapes``: their images' (height, width).

    A tie point matched in one date's views is where the matching of another date's failed
    (shadows, seasons, radiometry: SIFT matches between dates are few), yet its patch is seen
    there; registered from the track's first observation, it ties the dates on many more
    points. Only projections at least ``margin_px`` inside the image and in front of the camera
    count; each view gains at most ``per_view`` observations (the points in a fixed pseudo-random
    order, the one :func:`thin_points` breaks its ties with), so the count stays linear in the
    views.
    Observations keep their order per point, the new ones after the point's own.
    """
    from satsweep.sparse.triangulation import project, triangulate_observations

    V = len(shapes)
    if obs.xy.shape[0] == 0 or V < 3 or per_view <= 0:
        return obs
    X, _, _ = triangulate_observations(obs, P)
    n = obs.n_points
    seen = np.zeros((n, V), dtype=bool)
    seen[obs.point, obs.view] = True
    ok_point = np.all(np.isfinite(X), axis=1)
    pt, vw = np.nonzero(~seen & ok_point[:, None])
    if len(pt) == 0:
        return obs
    xy, depth = project(P, vw, X[pt])
    h = np.array([s[0] for s in shapes], np.float64)[vw]
    w = np.array([s[1] for s in shapes], np.float64)[vw]
    inside = (depth > 0) & np.all(np.isfinite(xy), axis=1)
    inside &= (xy[:, 0] >= margin_px) & (xy[:, 0] <= w - 1 - margin_px)
    inside &= (xy[:, 1] >= margin_px) & (xy[:, 1] <= h - 1 - margin_px)
    pt, vw, xy = pt[inside], vw[inside], xy[inside]
    order = np.lexsort((_scrambled(pt), vw))
    start = np.searchsorted(vw[order], vw[order], side="left")
    keep = order[(np.arange(len(order)) - start) < per_view]
    pt, vw, xy = pt[keep], vw[keep], xy[keep]
    point = np.r_[obs.point, pt]
    view = np.r_[obs.view, vw]
    allxy = np.r_[obs.xy, xy]
    grouped = np.argsort(point, kind="stable")  # the point's own observations first
    return Observations(point=point[grouped], view=view[grouped], xy=allxy[grouped], n_points=n)


# Lucas-Kanade of refine_observations: pyramid levels above full resolution (each halves the
# image; 1 lets a window converge from a keypoint ~2 px off), iterations and the step (px) below
# which it stops.
_LK_LEVELS = 1
_LK_ITERATIONS = 30
_LK_EPS_PX = 1e-3
# Lucas-Kanade runs on patches of the two images around the windows rather than on the whole
# images (lucas_kanade_in_patches): a patch holds every pixel that Lucas-Kanade reads for a
# window that ends within _LK_MOTION_PX (or 3 x the registration's shift limit, if more) of
# where it started, so those windows register as on the whole images; those that move farther
# are dropped by the shift limit anyway (a kept window ends within the limit of its keypoint,
# and starts there or within the limit of it, in view v's pixels, which the warp scales). The
# patches' corners lie on even pixels, so the pyramid's level above (_LK_LEVELS = 1) holds the
# same values as the whole image's.
_LK_MOTION_PX = 12
# The patches take the place of the whole images where they hold at most this share of an
# image's pixels: a patch costs several times a whole image's pixel (a warp and a copy each,
# from Python), and single-threaded on the captured registrations of the 1700 px and the 850 px
# issue-form stacks (docs/measurements.md, fifty-third session) the warps and Lucas-Kanade took
# 14.8 -> 5.6 s and 4.6 -> 3.6 s with 0.2 (the best choice each: 5.1 s and 3.5 s).
_PATCH_SHARE_MAX = 0.2


def _lk_reach_px(window_px: int) -> int:
    """Pixels (full resolution) around a window's centre that pyramidal Lucas-Kanade reads: at
    each level half the window, one more for bilinear sampling and one for the derivatives,
    scaled to full resolution, and two per level for the pyramid's 5-tap filter."""
    scale = 2 ** _LK_LEVELS
    return scale * (window_px // 2 + 2) + 2 * (scale - 1)


def _patch(source: np.ndarray, x0: int, y0: int, side: int, shape: tuple[int, int],
           homography: np.ndarray | None = None) -> np.ndarray:
    """The ``side`` x ``side`` patch at (x0, y0) of an image of ``shape`` (h, w): ``source``
    itself (``homography`` None) or ``source`` warped into that image's pixels (bilinear, by the
    homography from its pixels to ``source``'s, as ``cv2.warpPerspective`` with
    ``WARP_INVERSE_MAP``), its pixels outside the image reflected as Lucas-Kanade's pyramid
    reflects them (BORDER_REFLECT_101)."""
    import cv2

    h, w = shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + side, w), min(y0 + side, h)
    if cx1 <= cx0 or cy1 <= cy0:  # wholly outside the image: Lucas-Kanade fails there
        return np.zeros((side, side), np.uint8)
    if homography is None:
        inner = source[cy0:cy1, cx0:cx1]
    else:
        shift = np.array([[1.0, 0.0, cx0], [0.0, 1.0, cy0], [0.0, 0.0, 1.0]])
        inner = cv2.warpPerspective(source, homography @ shift, (cx1 - cx0, cy1 - cy0),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    if (cx0, cy0, cx1, cy1) == (x0, y0, x0 + side, y0 + side):
        return inner
    return cv2.copyMakeBorder(np.ascontiguousarray(inner), cy0 - y0, y0 + side - cy1,
                              cx0 - x0, x0 + side - cx1, cv2.BORDER_REFLECT_101)


def lucas_kanade_in_patches(head_u8: np.ndarray, other_u8: np.ndarray, homography: np.ndarray,
                            centre: np.ndarray, start: np.ndarray, window_px: int,
                            criteria: tuple, motion_px: float = _LK_MOTION_PX
                            ) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's pyramidal Lucas-Kanade (translation, ``window_px`` windows, _LK_LEVELS) of
    ``head_u8``'s windows at ``centre`` (k, n, 2: window j of observation i, head's pixels) in
    ``other_u8`` warped into head's pixels by ``homography`` (head's pixels -> other's),
    starting from ``start`` (k, n, 2, the warped image's pixels): as on the whole images
    (``cv2.calcOpticalFlowPyrLK`` of ``head_u8`` and the whole warp), but each observation's k
    windows on patches of both images that cover them (to ``motion_px`` from their starts),
    laid side by side in one image each (on the whole images where the patches would hold more
    than _PATCH_SHARE_MAX of an image's pixels). On 19 views of 1700 px, a pair's patches hold
    about a tenth of an image's pixels. Returns (found (k n, 2) float64 in the warped image's
    pixels, status (k n,) bool)."""
    import cv2

    k, n = centre.shape[:2]
    found = np.full((k * n, 2), np.nan)
    status = np.zeros(k * n, bool)
    good = np.isfinite(centre).all(axis=(0, 2)) & np.isfinite(start).all(axis=(0, 2))
    if not good.any():
        return found, status
    obs = np.flatnonzero(good)
    reach = _lk_reach_px(window_px)
    # Each observation's patch corners (even pixels) in head's image and in the warped one.
    head_lo = 2 * np.floor((centre[:, obs].min(axis=0) - reach) / 2).astype(np.int64)
    head_hi = np.ceil(centre[:, obs].max(axis=0) + reach).astype(np.int64)
    warp_lo = 2 * np.floor((start[:, obs].min(axis=0) - reach - motion_px) / 2).astype(np.int64)
    warp_hi = np.ceil(start[:, obs].max(axis=0) + reach + motion_px).astype(np.int64)
    side = int(max((head_hi - head_lo).max(), (warp_hi - warp_lo).max()))
    side += side % 2 + 2  # even, and one more pixel each side
    shape = head_u8.shape
    index = (np.arange(k)[:, None] * n + obs[None]).ravel()  # the windows' rows in found
    lk = dict(winSize=(window_px, window_px), maxLevel=_LK_LEVELS, criteria=criteria,
              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    if len(obs) * side * side > _PATCH_SHARE_MAX * shape[0] * shape[1]:  # on the whole images
        warped = cv2.warpPerspective(other_u8, homography, shape[::-1],
                                     flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        got, ok, _ = cv2.calcOpticalFlowPyrLK(
            head_u8, warped, centre[:, obs].astype(np.float32).reshape(-1, 1, 2),
            start[:, obs].astype(np.float32).reshape(-1, 1, 2), **lk)
        found[index], status[index] = got.reshape(-1, 2), ok.ravel() == 1
        return found, status
    cols = int(np.ceil(np.sqrt(len(obs))))
    rows = -(-len(obs) // cols)
    slot = side * np.c_[np.arange(len(obs)) % cols, np.arange(len(obs)) // cols]  # (m, 2) x, y
    head_tiles = np.zeros((rows * side, cols * side), np.uint8)
    warp_tiles = np.zeros_like(head_tiles)
    for m in range(len(obs)):
        (sx, sy), (hx, hy), (wx, wy) = slot[m], head_lo[m], warp_lo[m]
        head_tiles[sy:sy + side, sx:sx + side] = _patch(head_u8, int(hx), int(hy), side, shape)
        warp_tiles[sy:sy + side, sx:sx + side] = _patch(other_u8, int(wx), int(wy), side, shape,
                                                        homography)
    prev = (centre[:, obs] - head_lo[None] + slot[None]).astype(np.float32).reshape(-1, 1, 2)
    init = (start[:, obs] - warp_lo[None] + slot[None]).astype(np.float32).reshape(-1, 1, 2)
    got, ok, _ = cv2.calcOpticalFlowPyrLK(head_tiles, warp_tiles, prev, init, **lk)
    found[index] = (got.reshape(k, -1, 2).astype(np.float64) - slot[None]
                    + warp_lo[None]).reshape(-1, 2)
    # OpenCV fails a window whose top-left corner lies more than a window outside the image or
    # past its far edges (both images have head's size): the same bounds here, where the
    # patches would go on over their neighbours.
    half = 0.5 * (window_px - 1)
    bounds = np.array(shape[::-1], np.float64)

    def within(xy: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return np.all((xy >= half - window_px) & (xy < bounds + half), axis=-1)

    status[index] = ((ok.ravel() == 1) & within(centre[:, obs].reshape(-1, 2))
                     & within(found[index]))
    return found, status


# Lucas-Kanade assumes the two windows' grey levels equal; views of other dates differ in gain,
# offset and gamma (and SIFT does not mind), and a translation then absorbs part of the
# difference: registered on the grey levels, the tie points between dates of the multi-date
# scenes (tools/bench_multidate.py, 10 views) lie 0.23 px from their true places (median),
# those within a date 0.06 px. Such pairs are registered on both images' local contrast: each
# pixel's difference to the Gaussian mean of scale _CONTRAST_SIGMA_PX around it over the local
# standard deviation plus _CONTRAST_FLOOR (8-bit grey levels: flat areas stay flat, not
# amplified noise), mapped to 8 bits as 128 + _CONTRAST_GAIN x that. Not everywhere: on views
# of one date it registers less precisely (tools/bench_ba.py, 50 px biases, 3/5/10 views:
# corrections within 0.054-0.061 px of the truth, against 0.027-0.036 on the grey levels, at a
# scale of 3 px). Its residuals are ranked after every grey-level one (+ CONTRAST_RANK) in
# best_registered. Two scales: (_CONTRAST_SIGMA_PX, _CONTRAST_GAIN) and (_FINE_CONTRAST_SIGMA_PX,
# _FINE_CONTRAST_GAIN); the pairs registered wholly on contrast are registered at both, and when
# in most of them the fine scale's ties agree better with one relative pointing of the two views
# (across_spread), every pair on contrast takes the fine scale, else the other.
_CONTRAST_SIGMA_PX = 3.0
_CONTRAST_FLOOR = 2.0
_CONTRAST_GAIN = 40.0
# At a pixel's scale the transform keeps each pixel's pattern against its nearest neighbours, as
# a census does; the wider one reaches across the edges between surfaces that the sun lights
# differently from date to date (roof faces, shadows: what biases the ties between dates), and
# what lies beyond such an edge pulls the registration. The fine scale is noisier, though: where
# the views' grey levels differ for other reasons (the real Pleiades pair of one pass, on the
# tests' AOI, goes wholly onto contrast) its ties scatter more (that pair, every tie forced onto
# contrast: 0.106 against 0.087 px mean reprojection error after the adjustment; forced, the
# one-date stacks of tools/bench_ba.py likewise 0.048-0.063 against 0.041-0.058 px), and there
# the fine scale's spread is 1.08-1.39 times the other's (three AOIs), on the synthetic
# multi-date stacks a median of 0.76-0.86 times. A choice per pair by the same measure lost most
# of the gain (10-view stacks 0.075 px against 0.066): the spread is noisy per pair and misses a
# bias shared by a pair's ties, so the stack decides. The gain maps the usual +-3 deviations
# onto 68..188 rather than clipping them. Worst view's correction against the truth after the
# gauge (tools/bench_multidate.py's measure, mean over seeds), 3 px only -> this choice:
# 10-view multi-date stacks seeds 0-5 0.088 -> 0.066 px, held-out seeds 6-9 0.042 -> 0.038,
# 5 views 0.047 -> 0.037, 20 views 0.066 -> 0.055, the 0.3 m stacks of 19 views (seeds 11-16)
# 0.056 -> 0.039 (docs/measurements.md, twenty-ninth session).
_FINE_CONTRAST_SIGMA_PX = 1.0
_FINE_CONTRAST_GAIN = 20.0
CONTRAST_RANK = 256.0
# A pair of views is registered wholly on local contrast when the median residual of its
# grey-level registrations (mean absolute difference of the windows, 8-bit levels) exceeds this:
# 3.2-13.4 (median 4.7) in the multi-date scenes' pairs of one date, 1.4-32 (median 12) between
# dates, in 16 and in 8 bits. With it, the 10-view stacks' pointing errors (seeds 0-5) come
# within 0.06 px of those that the true dates would give.
_CONTRAST_PAIR_RESIDUAL = 8.0
# Otherwise the observations that fail on the grey levels are registered again on contrast,
# in pairs where at least this share failed: 37-80% of a cross-date pair's tie points on the
# multi-date scenes, 3% of a same-date pair's (whose few failures, made again, cost a third of
# the registration's time on 20 views and tied nothing).
_CONTRAST_PAIR_FAILED = 0.2


def local_contrast_u8(grey_u8: np.ndarray, sigma_px: float = _CONTRAST_SIGMA_PX,
                      gain: float = _CONTRAST_GAIN) -> np.ndarray:
    """An 8-bit grey image (``_to_u8`` of a tonemapped one) as 8-bit local contrast at the scale
    ``sigma_px`` (see _CONTRAST_SIGMA_PX): gain, offset and any monotonic grey-level change that
    is locally affine leave it unchanged."""
    import cv2

    x = grey_u8.astype(np.float32)
    d = x - cv2.GaussianBlur(x, (0, 0), sigma_px)
    s = cv2.sqrt(cv2.GaussianBlur(cv2.multiply(d, d), (0, 0), sigma_px)) + _CONTRAST_FLOOR
    # (OpenCV's arithmetic: a third of numpy's time on 1000 px views; convertScaleAbs rounds and
    # saturates at 255, the max at 0.)
    return cv2.convertScaleAbs(cv2.max(cv2.divide(d, s, scale=gain) + 128.0, 0.0))


# across_spread: the epipolar line of a point of view w in view v through the points of its ray
# at the ENU heights 0 and _ACROSS_PROBE_M (the cameras' pinhole lines are straight: any two
# heights give the same line); a pair compares its two registrations on at least _ACROSS_MIN_TIES
# tie points that both registered (else it keeps the coarser scale's).
_ACROSS_PROBE_M = 100.0
_ACROSS_MIN_TIES = 8
# Rays whose two points lie closer than this (px) in the other view: no parallax between the
# views (one viewpoint, or cameras that ignore height), where every tie point should move alike.
_NO_PARALLAX_PX = 1e-6
# A spread below this (px) counts as this much in the two scales' ratio (ties that agree exactly).
_SPREAD_FLOOR_PX = 1e-6


def across_spread(camera_w: Any, camera_v: Any, xy_w: np.ndarray, xy_v: np.ndarray) -> float:
    """How well the tie points ``xy_w`` (view w) -> ``xy_v`` (view v) agree with one relative
    pointing of the two views: the median absolute deviation (px) of their offsets across the
    epipolar lines, in view v, of the rays of ``xy_w`` (cameras with a 3x4 ``P``, ENU ->
    pixels). Heights move a tie point along its line; a pointing error moves every tie point
    across by about the same amount; what varies across is the registration's error."""
    Pw, Pv = np.asarray(camera_w.P, np.float64), np.asarray(camera_v.P, np.float64)
    ends = []
    for u in (0.0, _ACROSS_PROBE_M):
        Hw, Hv = Pw[:, [0, 1, 3]].copy(), Pv[:, [0, 1, 3]].copy()
        Hw[:, 2] += u * Pw[:, 2]
        Hv[:, 2] += u * Pv[:, 2]
        ground = np.linalg.solve(Hw, np.c_[xy_w, np.ones(len(xy_w))].T)  # (e, n, 1) per point
        q = Hv @ ground
        ends.append((q[:2] / q[2]).T)
    d = xy_v - ends[0]
    direction = ends[1] - ends[0]
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    if not np.all(length > _NO_PARALLAX_PX):  # views without parallax: the whole offset
        return float(np.median(np.hypot(*(d - np.median(d, axis=0)).T)))
    direction /= length
    across = direction[:, 0] * d[:, 1] - direction[:, 1] * d[:, 0]
    return float(np.median(np.abs(across - np.median(across))))


_CENTRED = np.zeros((1, 2))  # the centred window's offset (register_observations)


def register_observations(obs: Observations, images: Sequence[np.ndarray], cameras: Sequence[Any], *,
                          window_px: int, max_shift_px: float, keep_fraction: float = 1.0,
                          at_least: int = 0, threads: int = 1, beside_px: float = 0.0,
                          choice: dict | None = None) -> tuple[Observations, np.ndarray, int]:
    """Register each track's observations to its first one, to a fraction of a pixel.

    SIFT places a keypoint to ~0.3-0.5 px (~1 px at half resolution), and those errors reach the
    principal points. Here observation k of view v, in a track whose first observation f is in
    view w, is moved to where the ``window_px`` window of view w around f lies in view v:
    view v's image is first warped into view w's pixels by the homography the cameras induce
    through the ENU frame's plane u = 0 (rotation, scale and shear between the views removed;
    what remains near a tie point is a translation: its parallax and the pointing errors), then
    OpenCV's pyramidal Lucas-Kanade (translation only; on patches of the two images around the
    windows, :func:`lucas_kanade_in_patches`) starts from k's keypoint mapped into the warped
    image; its result is then registered again to a fraction of a pixel on the two
    images themselves (:func:`satsweep.sparse.subpixel.refine_translations`: Lanczos samples
    where the homography maps the window, no 8-bit warp, whose interpolation errors would not
    average out over a pair's tie points), and mapped back into view v. First observations
    keep their positions (the tie point is wherever f is). ``images``: the views' tonemapped
    images in [0, 1], in the pixels of ``cameras`` (anything with a 3x4 ``P``). Observations
    that fail (no convergence, outside the image) or move farther than ``max_shift_px`` from
    their keypoint are dropped, then points seen by fewer than two views. A pair of views
    (view of the first observations, other view) whose grey-level registrations leave a median
    residual above _CONTRAST_PAIR_RESIDUAL is registered again wholly on the images' local
    contrast
    (:func:`local_contrast_u8`: views of other dates differ in gain, offset and gamma, which
    biases a registration of the grey levels), and its observations that fail there are
    dropped. In the other pairs, what fails on the grey levels is registered again on local
    contrast where fewer registered than :func:`best_registered` with ``keep_fraction`` and
    ``at_least`` would keep (elsewhere it would keep none of them: they rank after) and at least
    _CONTRAST_PAIR_FAILED of the pair failed. The contrast's scale (_CONTRAST_SIGMA_PX or
    _FINE_CONTRAST_SIGMA_PX) is the one under which the pairs wholly on contrast agree better
    with one relative pointing each (:func:`across_spread`, median over those pairs). The pairs
    run in up to ``threads`` threads (the same result as one).

    With ``beside_px`` > 0, every track is then registered again by the windows centred
    ``beside_px`` and 4/3 of it beside its point (BESIDE_DIRECTIONS x BESIDE_RINGS: the 4 sides
    and the 4 corners, each observation on the images its centred window used), and takes the
    window (centred or beside) whose residuals summed over the track's observations are least
    (compared first over its first observation and BESIDE_PROBES others, :func:`beside_probes`;
    the BESIDE_FINALISTS best there then over all of them).
    A tie point on an
    edge between two surfaces whose parallax differs (where SIFT puts most keypoints) has a
    centred window over both, and no translation registers both (a compromise, off by tenths
    of a pixel along the pair's epipolar lines); a window beside it lies over one, whose plane
    through the point's pixel is a 3-D point that every view sees consistently (planes map by
    homographies). ``choice``, a dict, receives ``contrast_sigma_px`` (the scale taken; None
    when no pair needed contrast), ``fine_spread_ratio`` (the median ratio, None when no pair
    compared), ``beside_px``, ``beside_points`` (tracks that took a window beside, None when
    none was tried) and ``points``. Returns the observations, the
    residual of each (mean absolute difference of the two windows' grey levels, in 8-bit units,
    after the registration, or of their local contrast plus CONTRAST_RANK; 0 for first
    observations)
    and the number of observations dropped.
    """
    import cv2

    if obs.xy.shape[0] == 0:
        return obs, np.zeros(0), 0
    first = np.r_[True, obs.point[1:] != obs.point[:-1]]
    if not np.array_equal(obs.point, np.sort(obs.point, kind="stable")):
        raise CameraError("refine_observations: observations must be grouped by point")
    head = np.flatnonzero(first)[np.cumsum(first) - 1]  # each observation's first observation
    head_view = obs.view[head]
    planes = [np.asarray(c.P, np.float64)[:, [0, 1, 3]] for c in cameras]  # ENU (e, n, 1) at u = 0
    xy = obs.xy.copy()
    residual = np.full(len(xy), np.inf)
    residual[first] = 0.0
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, _LK_ITERATIONS, _LK_EPS_PX)
    floats: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def as_float(image: np.ndarray) -> np.ndarray:
        """``image`` as float32 for the sub-pixel step, converted once per registration: a
        view's image serves every pair and pass it is in (on 19 views of 1700 px, converting
        it on every call took 2.9 of the registration's 16 s). Threads may both convert it:
        the same values either way."""
        held = floats.get(id(image))
        if held is None or held[0] is not image:
            held = floats[id(image)] = (image, np.asarray(image, np.float32))
        return held[1]

    def register(head_u8: np.ndarray, other_u8: np.ndarray, H: np.ndarray, sel: np.ndarray,
                 rank: float, out_xy: np.ndarray, out_residual: np.ndarray,
                 offsets: np.ndarray = _CENTRED, from_xy: np.ndarray | None = None) -> None:
        """Observations ``sel`` (of one view, their tracks' first in the view of ``head_u8``)
        registered on these images, by the windows centred ``offsets[k]`` pixels (of the
        warped images) from their points (``offsets`` (k, 2); or (k, every observation, 2):
        each observation its own): ``out_xy[k]`` and ``out_residual[k]`` (+ ``rank``)
        where it succeeds. LK starts from ``from_xy`` (view v's pixels; default: the
        keypoints)."""
        begin = obs.xy[sel] if from_xy is None else from_xy[sel]
        start = cv2.perspectiveTransform(begin.reshape(-1, 1, 2), np.linalg.inv(H))[:, 0]
        # Every offset's windows in one call, on patches of the two images around them.
        d = np.asarray(offsets, np.float64)
        d = d[:, None, :] if d.ndim == 2 else d[:, sel, :]  # (k, 1 or n, 2)
        centre = obs.xy[head[sel]][None] + d  # (k, n, 2), head's pixels
        found, lk = lucas_kanade_in_patches(head_u8, other_u8, H, centre, start[None] + d,
                                            window_px, criteria,
                                            max(_LK_MOTION_PX, 3.0 * max_shift_px))
        centre = centre.reshape(-1, 2)
        # Each window LK registered is registered again to a fraction of a pixel on the images
        # themselves (satsweep.sparse.subpixel: no 8-bit warp, one Lanczos interpolation): its
        # position and residual replace LK's, and a window that fails there fails.
        q, sub_residual, sub_ok = refine_translations(as_float(head_u8), as_float(other_u8), H,
                                                      centre[lk], found[lk], window_px)
        err = np.full(len(found), np.inf)
        err[np.flatnonzero(lk)[sub_ok]] = sub_residual[sub_ok]
        found[lk] = q
        found = found.reshape(len(d), -1, 2) - d
        back = cv2.perspectiveTransform(found.reshape(-1, 1, 2), H).reshape(len(d), -1, 2)
        shift = np.hypot(back[..., 0] - obs.xy[sel, 0], back[..., 1] - obs.xy[sel, 1])
        err = err.reshape(len(d), -1)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(shift) & (shift <= max_shift_px) & np.isfinite(err)
        for k in range(len(d)):
            out_xy[k, sel[ok[k]]] = back[k, ok[k]]
            out_residual[k, sel[ok[k]]] = rank + err[k, ok[k]]

    grey = map_in_threads(_to_u8, images, max_threads=threads, name="register")
    pairs = []  # (view of the first observations, other view, their observations)
    for w in np.unique(head_view):
        for v in np.unique(obs.view[(head_view == w) & ~first]):
            sel = np.flatnonzero((head_view == w) & (obs.view == v) & ~first)
            pairs.append((int(w), int(v), sel))
    # view w pixels -> view v pixels
    homography = {(w, v): planes[v] @ np.linalg.inv(planes[w]) for w, v, _ in pairs}

    def on(images_u8, rank, out_xy=xy, out_residual=residual):  # a pair's registration on these
        return lambda job: register(images_u8[job[0]], images_u8[job[1]], homography[job[:2]],
                                    job[2], rank, out_xy[None], out_residual[None])

    # The pairs' observations are disjoint and each registration reads only the keypoints: the
    # pairs run in any order, in threads, and give what one loop over them gives.
    map_in_threads(on(grey, 0.0), pairs, max_threads=threads, name="register")
    whole, again = [], []
    for w, v, pair in pairs:
        done = np.isfinite(residual[pair])
        if not done.any() or np.median(residual[pair[done]]) > _CONTRAST_PAIR_RESIDUAL:
            # the two views' grey levels differ: the whole pair on contrast
            xy[pair], residual[pair] = obs.xy[pair], np.inf
            whole.append((w, v, pair))
        else:
            failed = pair[~done]
            wanted = max(int(np.ceil(keep_fraction * len(pair))), at_least)
            if (len(failed) and len(pair) - len(failed) < wanted
                    and len(failed) >= _CONTRAST_PAIR_FAILED * len(pair)):
                again.append((w, v, failed))

    made: dict = {}  # (sigma_px, gain) -> {view: its local contrast}

    def contrast_of(jobs, sigma_px, gain):  # only the views that need it, each made once
        views = made.setdefault((sigma_px, gain), {})
        needed = sorted({k for w, v, _ in jobs for k in (w, v)} - set(views))
        views.update(zip(needed, map_in_threads(lambda k: local_contrast_u8(grey[k], sigma_px, gain),
                                                needed, max_threads=threads, name="register")))
        return views

    # The pairs wholly on contrast at both scales; the stack takes the fine one for every pair
    # on contrast where its ties agree better with one relative pointing in most such pairs.
    scale = (_CONTRAST_SIGMA_PX, _CONTRAST_GAIN)
    ratios: list[float] = []  # per pair compared: the fine scale's spread over the other's
    if whole:
        map_in_threads(on(contrast_of(whole, *scale), CONTRAST_RANK), whole, max_threads=threads,
                       name="register")
        fine_xy, fine_residual = obs.xy.copy(), np.full(len(xy), np.inf)
        map_in_threads(on(contrast_of(whole, _FINE_CONTRAST_SIGMA_PX, _FINE_CONTRAST_GAIN),
                          CONTRAST_RANK, fine_xy, fine_residual), whole, max_threads=threads,
                       name="register")
        for w, v, pair in whole:
            both = pair[np.isfinite(residual[pair]) & np.isfinite(fine_residual[pair])]
            if len(both) >= _ACROSS_MIN_TIES:
                coarse = across_spread(cameras[w], cameras[v], obs.xy[head[both]], xy[both])
                fine = across_spread(cameras[w], cameras[v], obs.xy[head[both]], fine_xy[both])
                ratios.append(fine / max(coarse, _SPREAD_FLOOR_PX))
        if ratios and np.median(ratios) < 1.0:
            scale = (_FINE_CONTRAST_SIGMA_PX, _FINE_CONTRAST_GAIN)
            for w, v, pair in whole:
                xy[pair], residual[pair] = fine_xy[pair], fine_residual[pair]
    if again:
        map_in_threads(on(contrast_of(again, *scale), CONTRAST_RANK), again, max_threads=threads,
                       name="register")
    window = None
    if beside_px > 0.0:
        xy, residual, window = _beside_windows(
            obs, first, pairs, xy, residual, register, grey,
            lambda jobs: contrast_of(jobs, *scale), homography,
            np.concatenate([np.asarray(BESIDE_DIRECTIONS, np.float64) * ring * beside_px
                            for ring in BESIDE_RINGS]), threads,
            {(w, v) for w, v, _ in whole})
    if choice is not None:
        choice.update(contrast_sigma_px=float(scale[0]) if whole or again else None,
                      fine_spread_ratio=float(np.median(ratios)) if ratios else None,
                      beside_px=float(beside_px),
                      beside_points=None if window is None else int(np.sum(window > 0)),
                      points=int(obs.n_points))
    keep = np.isfinite(residual)
    registered = Observations(point=obs.point, view=obs.view, xy=xy, n_points=obs.n_points)
    index = registered.subset_index(keep)
    return registered.subset(keep), residual[index], int((~keep).sum())


# The windows beside a tie point (register_observations' ``beside_px``): the 4 sides and the 4
# corners, on two rings, at ``beside_px`` and 4/3 of it (6 and 8 px by default). One ring of 6
# px left the worst view of v10 seed 5 / one view per date seed 5 at 0.050 / 0.075 px, one of
# 8 px at 0.059 / 0.043, both 0.046 / 0.048 (docs/measurements.md, forty-third session).
BESIDE_DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))
BESIDE_RINGS = (1.0, 4.0 / 3.0)
# An observation that a window loses weighs this in its track's sum of residuals (more than
# any residual: a window that loses an observation the others keep is not taken for it).
_BESIDE_LOST = 1000.0
# Tracks of fewer views keep the centred window: two views' one residual picks among the nine
# windows by chance as much as by surface (tools/bench_e2e.py's two views, 0.196 m / 89.6%
# within 1 m: 0.200 m / 88.8% with their tracks too; the multi-date stacks' tracks reach most
# views, and the v10 pointing is the same either way).
BESIDE_MIN_VIEWS = 3


# A track's window (centred or beside) is first compared on at most BESIDE_PROBES of its
# observations besides the first (its probes, in a fixed pseudo-random order of views: no date
# preferred); the BESIDE_FINALISTS windows of the least sums there are registered on its other
# observations too, and the least sum over all of them wins. Sixteen windows on every
# observation made the registration grow as views x track length, with the square of the
# views. tools/bench_ba.py --views 5 20 --seeds 0 --bias 50 --mode sparse (1000 px): 20 views
# over 5 from 4.85 to 3.32 (the registration 20 views 2.5 s against 4.6 s before). Worst view
# after the gauge, sparse stage alone (docs/measurements.md, forty-seventh session): 10-view
# stacks seeds 0-5 mean 0.0232 -> 0.0229 px, one view per date, 10 views, 0.0287 -> 0.0285,
# 33.45 S stacks 0.0276 -> 0.0272, 20 views 0.0303 / 0.0238 -> 0.0331 / 0.0237; stacks of 6
# views or fewer as before (every observation a probe). The probes' choice alone (no
# finalists) left one view per date, 10 views, seeds 0 and 5 at 0.052 and 0.054 px.
BESIDE_PROBES = 5
BESIDE_FINALISTS = 2


def beside_probes(point_index: np.ndarray, view: np.ndarray, per_track: int) -> np.ndarray:
    """Per observation (grouped by point, each track's first observation first), whether it is
    one of its track's probes: the first and up to ``per_track`` others, in a fixed pseudo-
    random order of (point, view)."""
    n = len(point_index)
    if n == 0:
        return np.zeros(0, bool)
    first = np.r_[True, point_index[1:] != point_index[:-1]]
    n_views = int(np.max(view)) + 1
    key = _scrambled(np.asarray(point_index, np.int64) * n_views + view)
    key[first] = 0  # the first observation leads its track
    order = np.lexsort((~first, key, point_index))
    start = np.searchsorted(point_index[order], point_index[order], side="left")
    probe = np.zeros(n, bool)
    probe[order[(np.arange(n) - start) <= per_track]] = True
    return probe


def _beside_windows(obs: Observations, first: np.ndarray, pairs, xy: np.ndarray,
                    residual: np.ndarray, register, grey, contrast_of, homography,
                    offsets: np.ndarray, threads: int, on_contrast: set
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every track registered again by the windows centred ``offsets`` (k, 2) beside its
    point, each observation on the images its centred window used (grey levels, or local
    contrast for those ranked after CONTRAST_RANK; one the centred window lost, its pair's), and
    each track of BESIDE_MIN_VIEWS views or more given the window (centred or beside) of the
    least sum of residuals over its observations: the windows are compared over its probes
    (:func:`beside_probes`), and the BESIDE_FINALISTS best there are registered on its other
    observations too and compared over all of them. Returns (xy, residual, the window's index
    per point: 0 centred)."""
    n = len(obs.xy)
    point_index = np.cumsum(first) - 1
    n_points = int(point_index[-1]) + 1
    views_per_point = np.bincount(point_index, minlength=n_points)
    long_enough = views_per_point[point_index] >= BESIDE_MIN_VIEWS
    probe = beside_probes(point_index, obs.view, BESIDE_PROBES)
    out_xy = np.repeat(xy[None], len(offsets), axis=0)
    out_residual = np.full((len(offsets), n), np.inf)
    out_residual[:, first] = 0.0

    def jobs_of(mask):  # per pair, its observations in mask on grey levels and on contrast
        grey_jobs, contrast_jobs = [], []
        for w, v, pair in pairs:
            pair = pair[mask[pair]]
            on_grey = np.where(np.isfinite(residual[pair]), residual[pair] < CONTRAST_RANK,
                               (w, v) not in on_contrast)
            if on_grey.any():
                grey_jobs.append((w, v, pair[on_grey]))
            if (~on_grey).any():
                contrast_jobs.append((w, v, pair[~on_grey]))
        return grey_jobs, contrast_jobs

    def run_all(mask, offs, o_xy, o_residual):  # LK starts from where the centred window ended
        grey_jobs, contrast_jobs = jobs_of(mask)

        def run(images_u8, rank):
            return lambda job: register(images_u8[job[0]], images_u8[job[1]],
                                        homography[job[:2]], job[2], rank, o_xy, o_residual,
                                        offsets=offs, from_xy=xy)

        map_in_threads(run(grey, 0.0), grey_jobs, max_threads=threads, name="register")
        if contrast_jobs:
            map_in_threads(run(contrast_of(contrast_jobs), CONTRAST_RANK), contrast_jobs,
                           max_threads=threads, name="register")

    run_all(long_enough & probe, offsets, out_xy, out_residual)
    every_xy = np.concatenate([xy[None], out_xy])
    every_residual = np.concatenate([residual[None], out_residual])
    cost = np.zeros((len(every_residual), n_points))
    for k, res in enumerate(every_residual):
        np.add.at(cost[k], point_index[probe], np.where(np.isfinite(res), res, _BESIDE_LOST)[probe])
    cost[1:, views_per_point < BESIDE_MIN_VIEWS] = np.inf
    # The windows of the BESIDE_FINALISTS least sums over the probes are registered on the
    # track's other observations too (every finalist in one pass: each pair's images warped
    # once), and the least sum over all its observations wins.
    finalists = np.argsort(cost, axis=0, kind="stable")[:BESIDE_FINALISTS]  # (m, points)
    window = finalists[:, point_index]  # (m, n): each observation's finalists
    rows = np.arange(n)
    cand_xy, cand_residual = every_xy[window, rows], every_residual[window, rows]
    need = (~probe & long_enough)[None] & (window > 0)
    if need.any():
        per_obs = np.zeros((len(finalists), n, 2))
        per_obs[need] = offsets[window[need] - 1]
        rest_xy = np.repeat(xy[None], len(finalists), axis=0)
        rest_residual = np.full((len(finalists), n), np.inf)
        run_all(need.any(axis=0), per_obs, rest_xy, rest_residual)
        cand_xy[need], cand_residual[need] = rest_xy[need], rest_residual[need]
    total = np.zeros((len(finalists), n_points))
    for m in range(len(finalists)):
        np.add.at(total[m], point_index,
                  np.where(np.isfinite(cand_residual[m]), cand_residual[m], _BESIDE_LOST))
    total[~np.isfinite(np.take_along_axis(cost, finalists, axis=0))] = np.inf
    pick = np.argmin(total, axis=0)  # ties: the better over the probes
    best = finalists[pick, np.arange(n_points)]
    return cand_xy[pick[point_index], rows], cand_residual[pick[point_index], rows], best


def best_registered(obs: Observations, residual: np.ndarray, keep_fraction: float,
                    at_least: int = 0) -> Observations:
    """Of each pair (view of the tracks' first observations, other view), the ``keep_fraction``
    observations with the lowest registration residuals (:func:`register_observations`), and
    at least the ``at_least`` lowest (all when fewer); then points seen by fewer than two views
    are dropped.

    The windows that match worst straddle surfaces at different heights (building edges, where
    SIFT puts most of its keypoints): no translation registers both surfaces, and the
    compromise is off by tenths of a pixel (see the ``refine_keep_fraction`` option)."""
    if keep_fraction >= 1.0 or obs.xy.shape[0] == 0:
        return obs
    first = np.r_[True, obs.point[1:] != obs.point[:-1]]
    head_view = obs.view[np.flatnonzero(first)[np.cumsum(first) - 1]]
    keep = first.copy()
    for w in np.unique(head_view):
        for v in np.unique(obs.view[(head_view == w) & ~first]):
            sel = np.flatnonzero((head_view == w) & (obs.view == v) & ~first)
            n = max(int(np.ceil(keep_fraction * len(sel))), at_least)
            keep[sel[np.argsort(residual[sel], kind="stable")[:n]]] = True
    return obs.subset(keep)


def refine_observations(obs: Observations, images: Sequence[np.ndarray], cameras: Sequence[Any], *,
                        window_px: int, max_shift_px: float,
                        keep_fraction: float = 1.0) -> tuple[Observations, int]:
    """:func:`register_observations`, then :func:`best_registered` with ``keep_fraction``.
    Returns the observations and the number dropped by the registration (not counting those
    ``keep_fraction`` leaves out)."""
    registered, residual, dropped = register_observations(
        obs, images, cameras, window_px=window_px, max_shift_px=max_shift_px,
        keep_fraction=keep_fraction)
    return best_registered(registered, residual, keep_fraction), dropped
