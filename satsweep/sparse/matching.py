"""Pairwise matching of SIFT descriptors and its geometric verification.

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

from typing import Any

import numpy as np

from satsweep.sparse.options import SparseOptions

# A 4-point affine-fundamental sample is degenerate (its points nearly on a 2-plane of the
# 4-D joint space, e.g. collinear in one image) when its two smallest singular values are within
# this ratio: the fitted hyperplane is then arbitrary and the sample is skipped.
_DEGENERATE_SAMPLE_RATIO = 1e-6
# Candidate offsets tried by the one-parameter epipolar RANSAC (a random subset of the matches).
_OFFSET_CANDIDATES = 400


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
        D = a[s:s + _KNN_BLOCK] @ b.T  # in place from here: no temporaries of the block's size
        D *= -2.0
        D += nb[None, :]
        D += na[s:s + _KNN_BLOCK, None]
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
                               rng: np.random.Generator, threshold: float) -> np.ndarray:
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
    thr = threshold

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
    threshold_px: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Verified matches between two views: ``(idx1, idx2)`` int64 arrays of feature indices.

    Ratio test and mutual check, then geometric verification: with ``fundamental`` (3x3, from
    :func:`fundamental_from_cameras`, ``x2^T F x1 = 0``) the camera epipolar geometry up to one
    unknown offset (the pointing error, of any size: the offset is found by RANSAC, not assumed
    small); without it RANSAC of an affine fundamental matrix (which absorbs any translation).
    ``threshold_px``: the inlier threshold, default ``options.ransac_threshold_px`` (the sparse
    stage widens it by the cameras' own approximation errors).
    """
    xy1 = np.asarray(xy1, dtype=np.float64)
    xy2 = np.asarray(xy2, dtype=np.float64)
    i1, i2 = _tentative_matches(np.asarray(desc1, np.float32), np.asarray(desc2, np.float32), options)
    rng = np.random.default_rng(options.seed)
    threshold = options.ransac_threshold_px if threshold_px is None else float(threshold_px)
    if fundamental is not None:
        d = _epipolar_distance(np.asarray(fundamental, np.float64), xy1[i1], xy2[i2])
        keep = _verify_offset(d, threshold, rng)
    else:
        keep = _affine_fundamental_ransac(xy1[i1], xy2[i2], options, rng, threshold)
    return i1[keep], i2[keep]
