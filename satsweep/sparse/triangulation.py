"""Triangulation of observations with 3x4 cameras (linear, then Gauss-Newton), and the
projection helpers the bundle adjustment shares.

World points are in the cameras' ENU frame (metres); a camera is anything with a 3x4 ``P``
mapping homogeneous ENU points to homogeneous pixels.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from satsweep.sparse.tracks import Observations, observations_from_tracks

# Gauss-Newton iterations of the per-point triangulation refinement: the projection is near-affine
# over an AOI, so the linear solution is within millimetres of the optimum and 3 steps reach the
# float64 floor; 5 leave a margin for long, oblique tracks.
REFINE_ITERATIONS = 5
# The refinement stops early once no point moves by more than this (m) in a step: the steps
# shrink quadratically, so the next would move them by far less than a micrometre.
REFINE_STEP_TOL_M = 1e-6

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
    """Sum (M, ...) values into (n_points, ...) by point index (a bincount per component,
    several times faster than np.add.at)."""
    flat = values.reshape(len(point), int(np.prod(values.shape[1:], dtype=np.int64)))
    out = np.empty((n_points, flat.shape[1]), dtype=np.float64)
    for c in range(flat.shape[1]):
        out[:, c] = np.bincount(point, weights=flat[:, c], minlength=n_points)
    return out.reshape((n_points,) + values.shape[1:])


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
        step = _solve3(JtJ, Jtr)
        X = X - step
        with np.errstate(invalid="ignore"):
            if not np.nanmax(np.abs(step), initial=0.0) > REFINE_STEP_TOL_M:
                break
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
