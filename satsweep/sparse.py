"""Sparse reconstruction: SIFT features, verified pairwise matches, tracks, triangulation.

This is the front half of the pointing-error correction (:mod:`satsweep.bundle`): it finds the
same ground features in every view and triangulates them with the approximated perspective
cameras, the way a vision pipeline (COLMAP, VisSat) does.

Conventions
-----------
- Pixels are (col, row) = (x, y) of the image a camera refers to; pixel (0, 0) is the centre of the
  first pixel. OpenCV's SIFT is run with ``enable_precise_upscale`` so its keypoints follow the
  same convention (without it they are biased by a quarter pixel).
- World points are in the cameras' ENU frame (metres); a camera is anything with a 3x4 ``P``
  (:class:`satsweep.camera.PerspectiveCamera`) mapping homogeneous ENU points to homogeneous pixels.
- A *track* is an ``(k, 2)`` int64 array of ``(view, feature)`` rows, one per view, sorted by view:
  the same ground point seen as keypoint ``feature`` of each listed ``view``.

Features and their positions
----------------------------
SIFT runs on views of at least ``feature_scale_min_px`` resampled by ``feature_scale`` (half by
default: three times faster, and the descriptors match as well); the keypoints find the tie
points, not their sub-pixel positions. Those come from :func:`refine_observations`, which
registers each track's observations to its first one by Lucas-Kanade after warping the views
onto each other with the cameras' ground-plane homography: 0.01-0.05 px where SIFT keypoints are
good to ~0.3-0.5 px at full resolution.

Matching
--------
Descriptors are matched by brute force (L2) with Lowe's ratio test and a mutual-consistency check
(a match must be the nearest neighbour both ways). Geometric verification uses either

- the cameras (``fundamental`` given): the epipolar geometry of the approximated cameras is exact
  up to the pointing error, which moves every epipolar line of a pair by nearly the same amount
  over a small AOI (the geometry is near-affine); so the signed point-to-epipolar-line distances of
  the true matches cluster around one offset. A one-parameter RANSAC finds that offset and keeps
  the matches within ``ransac_threshold_px`` of it. Wrong matches that slide along their epipolar
  line pass this test; they triangulate to wrong heights and, for a pair, do not bias the
  adjustment (the along-epipolar direction is absorbed by the height).
- or no cameras: RANSAC of an affine fundamental matrix ``a x2 + b y2 + c x1 + d y1 + e = 0``
  (the model of affine cameras, near-exact for satellites over small areas), 4 matches per sample.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, Mapping, Sequence

import numpy as np

from .errors import CameraError
from .options import Options

__all__ = [
    "SparseOptions",
    "detect_features",
    "feature_scale_for",
    "match_pair",
    "fundamental_from_cameras",
    "build_tracks",
    "connected_labels",
    "Observations",
    "observations_from_tracks",
    "refine_observations",
    "projection_stack",
    "project",
    "projection_jacobian",
    "triangulate",
    "triangulate_observations",
]

# Gauss-Newton iterations of the per-point triangulation refinement: the projection is near-affine
# over an AOI, so the linear solution is within millimetres of the optimum and 3 steps reach the
# float64 floor; 5 leave a margin for long, oblique tracks.
REFINE_ITERATIONS = 5
# A 4-point affine-fundamental sample is degenerate (its points nearly on a 2-plane of the
# 4-D joint space, e.g. collinear in one image) when its two smallest singular values are within
# this ratio: the fitted hyperplane is then arbitrary and the sample is skipped.
_DEGENERATE_SAMPLE_RATIO = 1e-6
# Candidate offsets tried by the one-parameter epipolar RANSAC (a random subset of the matches).
_OFFSET_CANDIDATES = 400


@dataclasses.dataclass(frozen=True)
class SparseOptions(Options):
    """Options of feature detection, matching and triangulation."""

    # Keep at most this many SIFT keypoints per view (the strongest by local contrast). Only the
    # principal points are adjusted, so a few hundred matches per pair pin them: on the Pleiades
    # pair 3000 keypoints gave 890 verified matches and the same shifts as 6000 (1627 matches)
    # to 0.002 px, in 0.6 s of adjustment instead of 1.1-1.6 s; the 8 synthetic scenes of
    # tools/bench_e2e.py gave the same DSMs to 0.001 m; tools/bench_ba.py's 3 views: residual
    # pointing errors at most 0.074 px (0.070 px with 6000), 1.6 s instead of 3.0 s.
    max_features: int = 3000
    # SIFT runs on the views resampled by this factor (area average), its keypoints mapped back to
    # full-resolution pixels; the tie points then take their sub-pixel positions from
    # refine_window_px, not from SIFT. tools/bench_ba.py, 3 views of 1000 px, seeds 0 / 1: 0.5
    # gives features in 0.35 s instead of 0.95-1.0 s and pointing errors left after the gauge of
    # at most 0.062 / 0.065 px, against 0.074 / 0.110 px for full-resolution SIFT unrefined (0.5
    # unrefined: 0.43 / 0.42 px). 1: SIFT on the views as they are.
    feature_scale: float = 0.5
    # Views whose smaller side is below this (px) are searched at full resolution: small views
    # have few features to spare (a 256 px scene of tests/test_bundle.py kept 27 verified matches
    # on one pair at half resolution, where min_matches is 30).
    feature_scale_min_px: int = 512
    # Side (px) of the window over which each tie point of a track is registered to the track's
    # first view (Lucas-Kanade, translation only, after the other view is warped into the first
    # by the cameras' homography of the ground plane, so that rotation and scale between the
    # views do not bias it); 0 keeps the keypoints' own positions.
    refine_window_px: int = 15
    # A tie point that the refinement moves farther than this (px) from its keypoint is dropped
    # (the match or the registration is wrong): half-resolution keypoints are good to ~1 px.
    refine_max_shift_px: float = 2.0
    # SIFT contrast threshold (OpenCV units: Lowe's 0.03 is 0.09 here, as OpenCV divides by the 3
    # octave layers); lower than OpenCV's 0.04 because tonemapped satellite crops are low-contrast.
    contrast_threshold: float = 0.02
    # Lowe's ratio test: nearest / second-nearest descriptor distance must be below this.
    ratio: float = 0.8
    # Keep a match only when each feature is the other's nearest neighbour.
    mutual: bool = True
    # Geometric verification: "cameras" = epipolar geometry of the approximated cameras (with an
    # unknown common offset: the pointing error); "affine" = RANSAC of an affine fundamental matrix.
    geometric_model: Literal["cameras", "affine"] = "cameras"
    # Inlier threshold (px) of the geometric verification: point-to-epipolar-line distance in the
    # second image. SIFT keypoints are good to ~0.3-0.5 px; 1.5 px keeps them and rejects blunders.
    ransac_threshold_px: float = 1.5
    # RANSAC samples drawn for the affine fundamental matrix.
    ransac_iterations: int = 1000
    # A pair with fewer verified matches than this is not used (its matches are unreliable);
    # every view needs at least one such pair.
    min_matches: int = 30
    # Seed of the RANSAC sampling (results are deterministic for a given seed).
    seed: int = 0

    def check(self) -> None:
        self._require(self.max_features >= 8, "max_features", "must be at least 8")
        self._require(math.isfinite(self.feature_scale) and 0.1 <= self.feature_scale <= 1.0,
                      "feature_scale", "must be in [0.1, 1]")
        self._require(self.feature_scale_min_px >= 0, "feature_scale_min_px", "must be >= 0")
        self._require(self.refine_window_px == 0 or 5 <= self.refine_window_px <= 63,
                      "refine_window_px", "must be 0 (no refinement) or in [5, 63] pixels")
        self._require(math.isfinite(self.refine_max_shift_px) and self.refine_max_shift_px > 0.0,
                      "refine_max_shift_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.contrast_threshold) and self.contrast_threshold > 0.0,
                      "contrast_threshold", "must be a positive number")
        self._require(0.0 < self.ratio <= 1.0, "ratio", "must be in (0, 1]")
        self._require(math.isfinite(self.ransac_threshold_px) and self.ransac_threshold_px > 0.0,
                      "ransac_threshold_px", "must be a positive number of pixels")
        self._require(self.ransac_iterations >= 1, "ransac_iterations", "must be at least 1")
        self._require(self.min_matches >= 5, "min_matches",
                      "must be at least 5 (the affine model needs 4 matches plus redundancy)")
        self._require(self.seed >= 0, "seed", "must be >= 0")


# -- features ------------------------------------------------------------------------------------
def feature_scale_for(shape: tuple[int, ...], options: SparseOptions) -> float:
    """The resampling factor SIFT gets for an image of ``shape``: ``options.feature_scale``, or 1
    for views whose smaller side is below ``options.feature_scale_min_px``."""
    return 1.0 if min(shape[:2]) < options.feature_scale_min_px else options.feature_scale


def _to_u8(image: np.ndarray) -> np.ndarray:
    """A tonemapped image in [0, 1] (NaN: 0) quantised to 8 bits, as OpenCV's SIFT and
    Lucas-Kanade require."""
    return np.round(_unit(image) * 255.0).astype(np.uint8)


def _unit(image: np.ndarray) -> np.ndarray:
    """A tonemapped image as float64 in [0, 1], NaN as 0."""
    return np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0), 0.0, 1.0)


def detect_features(
    image: np.ndarray, *, max_features: int, contrast_threshold: float = 0.02, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of a tonemapped image.

    ``image``: 2-D float array with values in [0, 1] (``satsweep.imageio.tonemap``); it is
    quantised to 8 bits, which OpenCV's SIFT requires. Returns ``(xy, descriptors)``: ``xy`` is
    ``(N, 2)`` float64 (col, row) with pixel (0, 0) the centre of the first pixel, ``descriptors``
    ``(N, 128)`` float32. At most ``max_features`` keypoints (the strongest) are kept; keypoints
    that OpenCV duplicates for several orientations at one location are all kept (they describe
    different gradients, and the mutual check keeps at most one of them per match). With
    ``scale`` < 1 SIFT runs on the image resampled by that factor (area average) and ``xy`` is
    mapped back to the pixels of ``image``.
    """
    import cv2

    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2:
        raise CameraError(f"detect_features needs a 2-D image, got shape {a.shape}")
    if not 0.0 < scale <= 1.0:
        raise CameraError(f"detect_features: scale must be in (0, 1], got {scale}")
    fx = fy = 1.0
    if scale < 1.0:
        h, w = a.shape
        ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
        small = cv2.resize(_unit(a).astype(np.float32), (ws, hs), interpolation=cv2.INTER_AREA)
        u8 = _to_u8(small)
        fx, fy = ws / w, hs / h  # the scales cv2.resize applied per axis
    else:
        u8 = _to_u8(a)
    # Arguments: nfeatures, nOctaveLayers, contrastThreshold, edgeThreshold, sigma,
    # enable_precise_upscale (maps pixel x of the original to 2x of the upsampled octave: no
    # quarter-pixel bias of the keypoints).
    sift = cv2.SIFT_create(int(max_features), 3, float(contrast_threshold), 10.0, 1.6, True)
    keypoints, descriptors = sift.detectAndCompute(u8, None)
    if not keypoints:
        return np.zeros((0, 2), dtype=np.float64), np.zeros((0, 128), dtype=np.float32)
    xy = np.array([k.pt for k in keypoints], dtype=np.float64)
    if scale < 1.0:
        # cv2.resize puts the centre of resampled pixel i at (i + 0.5) / f - 0.5.
        xy = (xy + 0.5) / np.array([fx, fy]) - 0.5
    return xy, np.asarray(descriptors, dtype=np.float32)


# -- matching ------------------------------------------------------------------------------------
# Query rows per block of the descriptor distance matrix (bounds its memory to ~25 MB per block
# for 6000 features).
_KNN_BLOCK = 1024


def _nearest(desc1: np.ndarray, desc2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brute-force L2 neighbours both ways from one distance matrix.

    Returns ``idx12`` (N1, 2) and ``dist12`` (N1, 2): the two nearest features of image 2 for each
    feature of image 1 (closest first), and ``idx21`` (N2,): the nearest feature of image 1 for
    each feature of image 2. Squared distances are ``|a|^2 + |b|^2 - 2 a.b`` in float32 (SIFT
    descriptors have norms of about 512: the rounding, ~0.03 in squared distance, is far below
    the gaps the ratio test looks at), computed block by block.
    """
    n1, n2 = len(desc1), len(desc2)
    a = np.ascontiguousarray(desc1, dtype=np.float32)
    b = np.ascontiguousarray(desc2, dtype=np.float32)
    na, nb = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    idx12 = np.empty((n1, 2), dtype=np.int64)
    d12 = np.empty((n1, 2), dtype=np.float64)
    best21 = np.full(n2, np.inf, dtype=np.float32)
    idx21 = np.zeros(n2, dtype=np.int64)
    cols = np.arange(n2)
    for s in range(0, n1, _KNN_BLOCK):
        D = na[s:s + _KNN_BLOCK, None] + nb[None, :] - 2.0 * (a[s:s + _KNN_BLOCK] @ b.T)
        rows = D.argmin(axis=0)
        dmin = D[rows, cols]
        better = dmin < best21
        best21[better] = dmin[better]
        idx21[better] = rows[better] + s
        # The two nearest per row: two argmins, the first one's entry masked in between (3-5x
        # faster than an argpartition of the block on 3000 x 3000 descriptors).
        r = np.arange(len(D))
        first = D.argmin(axis=1)
        d_first = D[r, first]
        D[r, first] = np.inf
        second = D.argmin(axis=1)
        idx12[s:s + _KNN_BLOCK] = np.column_stack([first, second])
        d12[s:s + _KNN_BLOCK] = np.sqrt(np.maximum(np.column_stack([d_first, D[r, second]]), 0.0))
    return idx12, d12, idx21


def _tentative_matches(desc1: np.ndarray, desc2: np.ndarray, options: SparseOptions) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test (and optionally mutual) nearest-neighbour matches, as index arrays."""
    empty = np.zeros(0, dtype=np.int64)
    if len(desc1) < 2 or len(desc2) < 2:
        return empty, empty
    idx12, d12, idx21 = _nearest(desc1, desc2)
    ok = d12[:, 0] < options.ratio * d12[:, 1]
    if options.mutual:
        ok &= idx21[idx12[:, 0]] == np.arange(len(desc1))
    i1 = np.flatnonzero(ok)
    return i1, idx12[i1, 0]


def fundamental_from_cameras(camera1: Any, camera2: Any) -> np.ndarray:
    """Fundamental matrix ``F`` (unit Frobenius norm) with ``x2^T F x1 = 0`` for the two cameras.

    Built as ``F = [e2]_x H`` with ``H`` the homography induced by the ENU plane ``u = 0`` (it
    avoids the pseudo-inverse of a 3x4 matrix whose centre is ~700 km away) and ``e2`` the image
    in camera 2 of camera 1's centre. Pixels follow each camera's convention.
    """
    P1, P2 = np.asarray(camera1.P, np.float64), np.asarray(camera2.P, np.float64)
    G1 = P1[:, [0, 1, 3]]  # plane u = 0 (e, n, 1) -> image 1
    G2 = P2[:, [0, 1, 3]]
    H = G2 @ np.linalg.inv(G1)
    M = P1[:, :3]
    C1 = np.append(-np.linalg.solve(M, P1[:, 3]), 1.0)
    e2 = P2 @ C1
    e2 /= np.linalg.norm(e2)
    ex = np.array([[0.0, -e2[2], e2[1]], [e2[2], 0.0, -e2[0]], [-e2[1], e2[0], 0.0]])
    F = ex @ H
    return F / np.linalg.norm(F)


def _epipolar_distance(F: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Signed distance (px) of each ``xy2`` to the epipolar line ``F x1`` in image 2."""
    x1 = np.column_stack([xy1, np.ones(len(xy1))])
    lines = x1 @ F.T
    return (np.einsum("ij,ij->i", lines[:, :2], xy2) + lines[:, 2]) / np.hypot(lines[:, 0], lines[:, 1])


def _verify_offset(d: np.ndarray, threshold: float, rng: np.random.Generator) -> np.ndarray:
    """Inliers of a one-parameter RANSAC: the offset ``c`` with most ``|d - c| < threshold``."""
    if len(d) == 0:
        return np.zeros(0, dtype=bool)
    cand = d if len(d) <= _OFFSET_CANDIDATES else rng.choice(d, _OFFSET_CANDIDATES, replace=False)
    counts = (np.abs(d[None, :] - cand[:, None]) < threshold).sum(axis=1)
    c = cand[np.argmax(counts)]
    inl = np.abs(d - c) < threshold
    # Re-centre on the inliers' median and select again (the best candidate is one noisy sample).
    c = np.median(d[inl])
    return np.abs(d - c) < threshold


def _affine_fundamental_ransac(xy1: np.ndarray, xy2: np.ndarray, options: SparseOptions,
                               rng: np.random.Generator) -> np.ndarray:
    """Inlier mask of the best affine fundamental matrix found by RANSAC (4-match samples).

    The model is a hyperplane ``n . (q - q0) = 0`` of the joint space ``q = (x2, y2, x1, y1)``;
    a match's residual is its distance to the epipolar line in image 2,
    ``|n . (q - q0)| / |(n0, n1)|``. The best sample's inliers are refitted by total least squares.
    """
    n = len(xy1)
    if n < 4:
        return np.zeros(n, dtype=bool)
    q = np.column_stack([xy2, xy1])
    q = q - q.mean(axis=0)
    thr = options.ransac_threshold_px

    def residual(normal: np.ndarray, q0: np.ndarray) -> np.ndarray:
        # normal (..., 4), q0 (..., 4) -> (..., n)
        r = np.abs(np.einsum("...k,nk->...n", normal, q) - np.einsum("...k,...k->...", normal, q0)[..., None])
        return r / np.maximum(np.hypot(normal[..., 0], normal[..., 1]), 1e-12)[..., None]

    samples = rng.integers(0, n, size=(options.ransac_iterations, 4))
    pts = q[samples]  # (T, 4, 4)
    q0 = pts.mean(axis=1)
    _, s, vt = np.linalg.svd(pts - q0[:, None, :])
    normals = vt[:, -1, :]
    good = s[:, 2] > _DEGENERATE_SAMPLE_RATIO * np.maximum(s[:, 0], 1e-300)
    best, best_count = None, -1
    for start in range(0, len(normals), 250):  # bounded (250, n) residual blocks
        sl = slice(start, start + 250)
        counts = (residual(normals[sl], q0[sl]) < thr).sum(axis=1)
        counts[~good[sl]] = -1
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best, best_count = start + k, int(counts[k])
    if best is None or best_count < 4:
        return np.zeros(n, dtype=bool)
    inl = residual(normals[best], q0[best]) < thr
    for _ in range(2):  # total-least-squares refit on the inliers, then reselect
        sub = q[inl]
        c = sub.mean(axis=0)
        normal = np.linalg.svd(sub - c)[2][-1]
        new = residual(normal, c) < thr
        if new.sum() < inl.sum():
            break
        inl = new
    return inl


def match_pair(
    desc1: np.ndarray,
    desc2: np.ndarray,
    xy1: np.ndarray,
    xy2: np.ndarray,
    options: SparseOptions = SparseOptions(),
    *,
    fundamental: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Verified matches between two views: ``(idx1, idx2)`` int64 arrays of feature indices.

    Ratio test and mutual check, then geometric verification: with ``fundamental`` (3x3, from
    :func:`fundamental_from_cameras`, ``x2^T F x1 = 0``) the camera epipolar geometry up to one
    unknown offset (the pointing error); without it RANSAC of an affine fundamental matrix.
    """
    xy1 = np.asarray(xy1, dtype=np.float64)
    xy2 = np.asarray(xy2, dtype=np.float64)
    i1, i2 = _tentative_matches(np.asarray(desc1, np.float32), np.asarray(desc2, np.float32), options)
    rng = np.random.default_rng(options.seed)
    if fundamental is not None:
        d = _epipolar_distance(np.asarray(fundamental, np.float64), xy1[i1], xy2[i2])
        keep = _verify_offset(d, options.ransac_threshold_px, rng)
    else:
        keep = _affine_fundamental_ransac(xy1[i1], xy2[i2], options, rng)
    return i1[keep], i2[keep]


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
        point, view, xy = self.point[keep], self.view[keep], self.xy[keep]
        count = np.bincount(point, minlength=self.n_points)
        alive = count >= 2
        sel = alive[point]
        new_index = np.cumsum(alive) - 1
        return Observations(point=new_index[point[sel]], view=view[sel], xy=xy[sel],
                            n_points=int(alive.sum()))


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


# Lucas-Kanade of refine_observations: pyramid levels above full resolution (each halves the
# image; 1 lets a window converge from a keypoint ~2 px off), iterations and the step (px) below
# which it stops.
_LK_LEVELS = 1
_LK_ITERATIONS = 30
_LK_EPS_PX = 1e-3


def refine_observations(obs: Observations, images: Sequence[np.ndarray], cameras: Sequence[Any], *,
                        window_px: int, max_shift_px: float) -> tuple[Observations, int]:
    """Register each track's observations to its first one, to a fraction of a pixel.

    SIFT places a keypoint to ~0.3-0.5 px (~1 px at half resolution), and those errors reach the
    principal points. Here observation k of view v, in a track whose first observation f is in
    view w, is moved to where the ``window_px`` window of view w around f lies in view v:
    view v's image is first warped into view w's pixels by the homography the cameras induce
    through the ENU frame's plane u = 0 (rotation, scale and shear between the views removed;
    what remains near a tie point is a translation: its parallax and the pointing errors), then
    OpenCV's pyramidal Lucas-Kanade (translation only) starts from k's keypoint mapped into the
    warped image, and its result is mapped back into view v. First observations keep their
    positions (the tie point is wherever f is). ``images``: the views' tonemapped images in
    [0, 1], in the pixels of ``cameras`` (anything with a 3x4 ``P``). Observations that fail (no
    convergence, outside the image) or move farther than ``max_shift_px`` from their keypoint
    are dropped, and then points seen by fewer than two views. Returns the observations and the
    number dropped.
    """
    import cv2

    if obs.xy.shape[0] == 0:
        return obs, 0
    first = np.r_[True, obs.point[1:] != obs.point[:-1]]
    if not np.array_equal(obs.point, np.sort(obs.point, kind="stable")):
        raise CameraError("refine_observations: observations must be grouped by point")
    head = np.flatnonzero(first)[np.cumsum(first) - 1]  # each observation's first observation
    head_view = obs.view[head]
    u8 = [_to_u8(im) for im in images]
    planes = [np.asarray(c.P, np.float64)[:, [0, 1, 3]] for c in cameras]  # ENU (e, n, 1) at u = 0
    xy = obs.xy.copy()
    keep = np.ones(len(xy), dtype=bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, _LK_ITERATIONS, _LK_EPS_PX)
    for w in np.unique(head_view):
        for v in np.unique(obs.view[(head_view == w) & ~first]):
            sel = np.flatnonzero((head_view == w) & (obs.view == v) & ~first)
            H = planes[v] @ np.linalg.inv(planes[w])  # view w pixels -> view v pixels
            h, wd = u8[w].shape
            warped = cv2.warpPerspective(u8[v], H, (wd, h),
                                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            start = cv2.perspectiveTransform(obs.xy[sel].reshape(-1, 1, 2), np.linalg.inv(H))
            found, status, _err = cv2.calcOpticalFlowPyrLK(
                u8[w], warped, obs.xy[head[sel]].astype(np.float32).reshape(-1, 1, 2),
                start.astype(np.float32), winSize=(window_px, window_px), maxLevel=_LK_LEVELS,
                criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            back = cv2.perspectiveTransform(found.astype(np.float64), H).reshape(-1, 2)
            shift = np.hypot(*(back - obs.xy[sel]).T)
            ok = (status.ravel() == 1) & np.isfinite(shift) & (shift <= max_shift_px)
            xy[sel[ok]] = back[ok]
            keep[sel[~ok]] = False
    refined = Observations(point=obs.point, view=obs.view, xy=xy, n_points=obs.n_points)
    return refined.subset(keep), int((~keep).sum())

# -- projection and triangulation ----------------------------------------------------------------
def projection_stack(cameras: Sequence[Any]) -> np.ndarray:
    """The cameras' 3x4 matrices as a (V, 3, 4) float64 array."""
    return np.stack([np.asarray(c.P, dtype=np.float64) for c in cameras])


def project(P: np.ndarray, view: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) and depths (M,) of ENU points ``X`` (M, 3) in views ``view`` (M,) of ``P``."""
    Pv = P[view]
    h = np.einsum("mij,mj->mi", Pv[:, :, :3], X) + Pv[:, :, 3]
    return h[:, :2] / h[:, 2:3], h[:, 2]


def projection_jacobian(P: np.ndarray, view: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (M, 2), depths (M,) and d(pixel)/d(X) (M, 2, 3) of points ``X`` in views ``view``."""
    Pv = P[view]
    h = np.einsum("mij,mj->mi", Pv[:, :, :3], X) + Pv[:, :, 3]
    w = h[:, 2]
    xy = h[:, :2] / w[:, None]
    J = (Pv[:, :2, :3] - xy[:, :, None] * Pv[:, 2:3, :3]) / w[:, None, None]
    return xy, w, J


def _sum_by_point(values: np.ndarray, point: np.ndarray, n_points: int) -> np.ndarray:
    """Sum (M, ...) values into (n_points, ...) by point index."""
    out = np.zeros((n_points,) + values.shape[1:], dtype=np.float64)
    np.add.at(out, point, values)
    return out


def triangulate_observations(obs: Observations, P: np.ndarray, *,
                             iterations: int = REFINE_ITERATIONS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Multi-view triangulation: linear (DLT) then Gauss-Newton on the reprojection error.

    ``P`` (V, 3, 4) are the cameras. Each observation contributes the two linear equations
    ``col * P[2] - P[0]`` and ``row * P[2] - P[1]`` (applied to ``(X, 1)``), each scaled to a unit
    gradient so that all views weigh alike; the 3x3 normal equations are solved per point. The
    refinement then minimises the sum of squared pixel errors. Returns the points (N, 3) ENU m,
    the per-observation errors (M,) px and a per-point flag (N,) that is True when the point is in
    front of every camera that sees it (positive depth, ``K[2,2] = 1`` and ``det R = +1``).
    Points whose normal equations are singular (all rays parallel) are NaN with errors inf.
    """
    n = obs.n_points
    Pv = P[obs.view]
    rows = np.concatenate([obs.xy[:, 0:1] * Pv[:, 2] - Pv[:, 0], obs.xy[:, 1:2] * Pv[:, 2] - Pv[:, 1]])
    rows /= np.linalg.norm(rows[:, :3], axis=1, keepdims=True)
    pts = np.concatenate([obs.point, obs.point])
    A = _sum_by_point(rows[:, :3, None] * rows[:, None, :3], pts, n)
    b = _sum_by_point(-rows[:, :3] * rows[:, 3:4], pts, n)
    X = _solve3(A, b)
    for _ in range(max(0, int(iterations))):
        xy, _w, J = projection_jacobian(P, obs.view, X[obs.point])
        r = xy - obs.xy
        JtJ = _sum_by_point(np.einsum("mki,mkj->mij", J, J), obs.point, n)
        Jtr = _sum_by_point(np.einsum("mki,mk->mi", J, r), obs.point, n)
        X = X - _solve3(JtJ, Jtr)
    xy, w = project(P, obs.view, X[obs.point])
    err = np.hypot(*(xy - obs.xy).T)
    err[~np.isfinite(err)] = np.inf
    front = np.ones(n, dtype=bool)
    np.logical_and.at(front, obs.point, w > 0)
    front &= np.all(np.isfinite(X), axis=1)
    return X, err, front


def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched solve of (N, 3, 3) x = (N, 3); singular systems give NaN rows."""
    out = np.full(b.shape, np.nan)
    det = np.linalg.det(A)
    scale = np.einsum("nii->n", A) ** 3
    ok = np.abs(det) > 1e-12 * np.abs(scale)
    if ok.any():
        out[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return out


def triangulate(tracks: Sequence[np.ndarray], cameras: Sequence[Any],
                xys: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate tracks with the cameras: ENU points (N, 3) m and reprojection errors (N,) px.

    ``xys[v]`` are view ``v``'s keypoints (col, row). A point's error is the largest pixel distance
    between its observations and its reprojections; it is ``inf`` for a point behind a camera
    (negative depth) or whose rays are parallel, so that any threshold rejects it.
    """
    obs = observations_from_tracks(tracks, xys)
    X, err, front = triangulate_observations(obs, projection_stack(cameras))
    worst = np.full(obs.n_points, -np.inf)
    np.maximum.at(worst, obs.point, err)
    worst[~front] = np.inf
    return X, worst
