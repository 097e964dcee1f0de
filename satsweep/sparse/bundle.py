"""Bundle adjustment of principal points: the correction of RPC pointing errors.

Vendor RPCs carry pointing errors of up to a few pixels, which over a small AOI amount to an
image-space translation per view. Following VisSat (Zhang et al. 2019), the correction is done
the vision way: SIFT features are matched across views (:mod:`satsweep.sparse`), chained into
tracks and triangulated with the approximated perspective cameras, and a bundle adjustment then
moves only the principal point ``(cx, cy)`` of every camera (and the 3-D points); focal lengths,
skew, rotation and centre stay fixed.

Objective (robust Levenberg-Marquardt, the points eliminated per point)::

    sum_obs  rho(|| proj(P_v, X_p) + s_v - x_obs ||^2)  +  lambda * sum_p || X_p - Xhat_p ||^2

where ``s_v`` is the shift (px) of view v's principal point (moving ``cx, cy`` by ``s`` moves every
projection by exactly ``s``, as ``K[2] = (0, 0, 1)``), ``X_p`` a point in ENU metres and ``Xhat_p``
its triangulation with the original cameras; ``lambda`` (default 0.01 px^2/m^2) anchors the
points, which fixes the gauge (see below). Observations are then rejected at a coarse and at a
fine reprojection threshold, the anchor points re-triangulated, and the problem solved again.

Sign convention and gauge
-------------------------
If the true image content of view v lies at (RPC projection + b_v), the adjusted principal point is
the original plus ``b_v`` and ``principal_point_shift_px`` (adjusted minus original) is ``b_v``, up
to the motion that no image measurement can see: moving the whole scene by a 3-D vector ``dX``
while shifting each view by ``-A_v dX`` (``A_v`` the 2x3 Jacobian of its projection) changes no
residual. The horizontal part of that motion shifts all views nearly alike (a translation common
to all views); its vertical part (a height offset of the whole scene) shifts each view along its
own parallax direction, by ``parallax_v`` (px/m) times the offset. The anchor ``lambda`` picks the
solution whose points stay at their first triangulation. So only the shifts modulo
``{-A_v dX}`` are measured; with no pointing error they are zero.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Any, Literal, Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.options import Options
from satsweep.sparse.features import detect_features, feature_scale_for
from satsweep.sparse.matching import fundamental_from_cameras, match_pair
from satsweep.sparse.options import SparseOptions
from satsweep.sparse.tracks import (
    Observations,
    build_tracks,
    connected_labels,
    observations_from_tracks,
    refine_observations,
)
from satsweep.sparse.triangulation import (
    projection_jacobian,
    projection_stack,
    triangulate_observations,
)

__all__ = [
    "BundleOptions",
    "BundleReport",
    "BundleSolution",
    "adjust_principal_points",
    "adjust_observations",
    "shift_principal_point",
    "gauge_jacobians",
]


@dataclasses.dataclass(frozen=True)
class BundleOptions(Options):
    """Options of the principal-point bundle adjustment."""

    # lambda: weight (px^2 per m^2) of the anchor ||X - Xhat||^2 of each point to its
    # pre-adjustment triangulation (VisSat's 0.01); it fixes the gauge and must be > 0.
    regulariser: float = 0.01
    # Robust loss applied to each residual (scipy.optimize.least_squares' names and definitions).
    # soft_l1 (the smooth pseudo-Huber) by default: with Huber's kink scipy's trust-region steps
    # crawled (measured: 200 function evaluations against 6 for soft_l1, same solution).
    loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "soft_l1"
    # Residual (px) at which the robust loss leaves its quadratic zone.
    loss_scale_px: float = 1.0
    # Before the adjustment, tracks whose triangulation leaves an observation further than this
    # (px) are dropped: a pointing error of a few px leaves pre-adjustment errors of that order.
    initial_threshold_px: float = 10.0
    # After the first solve, observations further than this (px) from their reprojection go.
    coarse_threshold_px: float = 4.0
    # After the second solve, observations further than this (px) go; a last solve follows.
    fine_threshold_px: float = 2.0
    # Each view must keep at least this many observations after outlier rejection.
    min_observations: int = 20
    # Cost evaluations allowed to each solve.
    max_evaluations: int = 200

    def check(self) -> None:
        self._require(math.isfinite(self.regulariser) and self.regulariser > 0.0, "regulariser",
                      "must be a positive number (it fixes the gauge of the adjustment)")
        self._require(math.isfinite(self.loss_scale_px) and self.loss_scale_px > 0.0,
                      "loss_scale_px", "must be a positive number of pixels")
        for name in ("initial_threshold_px", "coarse_threshold_px", "fine_threshold_px"):
            v = getattr(self, name)
            self._require(math.isfinite(v) and v > 0.0, name, "must be a positive number of pixels")
        self._require(self.fine_threshold_px <= self.coarse_threshold_px <= self.initial_threshold_px,
                      "coarse_threshold_px",
                      "thresholds must satisfy fine <= coarse <= initial")
        self._require(self.min_observations >= 3, "min_observations",
                      "must be at least 3 (2 shift parameters per view need redundancy)")
        self._require(self.max_evaluations >= 1, "max_evaluations", "must be at least 1")


# -- the report ----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class BundleReport:
    """What the adjustment did: counts, reprojection errors and the principal-point shifts.

    Reprojection errors (px) are distances between observations and reprojections, over the
    observations kept at the end: "before" with the original cameras and the points triangulated
    with them, "after" with the adjusted cameras and points. ``principal_point_shift_px[v]`` is
    the adjusted minus the original ``(cx, cy)`` of view v (see the module docstring for its sign
    and gauge).
    """

    names: tuple[str, ...]
    n_features: tuple[int, ...]  # SIFT keypoints per view
    n_matches: tuple[tuple[int, int, int], ...]  # (view i, view j, verified matches) per pair
    min_matches: int  # pairs with fewer verified matches were not used
    n_tracks: int  # tracks built from the matches (consistent components of the match graph)
    track_length_histogram: dict[int, int]  # views per track -> number of tracks
    n_refine_dropped: int  # observations the sub-pixel refinement dropped (failed or moved too far)
    n_points: int  # tracks kept in the final adjustment
    n_observations: tuple[int, ...]  # observations per view kept in the final adjustment
    reproj_before_px: tuple[float, float]  # (median, mean)
    reproj_after_px: tuple[float, float]  # (median, mean)
    principal_point_shift_px: tuple[tuple[float, float], ...]  # per view (dcx, dcy)
    regulariser: float
    solver_evaluations: tuple[int, ...]  # cost evaluations of each solve
    seconds: dict[str, float]  # wall time per stage

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the ``ba`` section of cameras.json)."""
        return {
            "views": list(self.names),
            "n_features": {n: k for n, k in zip(self.names, self.n_features)},
            "n_matches": [{"views": [self.names[i], self.names[j]], "matches": k,
                           "used": k >= self.min_matches} for i, j, k in self.n_matches],
            "n_tracks": self.n_tracks,
            "track_length_histogram": {str(k): v for k, v in sorted(self.track_length_histogram.items())},
            "n_refine_dropped": self.n_refine_dropped,
            "n_points": self.n_points,
            "n_observations": {n: k for n, k in zip(self.names, self.n_observations)},
            "reprojection_error_px": {
                "before": {"median": self.reproj_before_px[0], "mean": self.reproj_before_px[1]},
                "after": {"median": self.reproj_after_px[0], "mean": self.reproj_after_px[1]},
            },
            "principal_point_shift_px": {n: list(s) for n, s in zip(self.names, self.principal_point_shift_px)},
            "regulariser": self.regulariser,
            "solver_evaluations": list(self.solver_evaluations),
            "seconds": dict(self.seconds),
            "convention": "principal_point_shift_px = adjusted - original (cx, cy): the image content "
                          "was found at (projection + shift); defined up to the motion of the whole "
                          "scene, which shifts every view by the projection of one 3-D vector",
        }


# -- the core adjustment -------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class BundleSolution:
    """Result of :func:`adjust_observations` on the observations it kept (``obs``)."""

    shifts: np.ndarray  # (V, 2) principal-point shifts, px
    points: np.ndarray  # (N, 3) adjusted ENU points, m
    anchors: np.ndarray  # (N, 3) pre-adjustment triangulation of the kept observations
    obs: Observations  # the observations kept after outlier rejection
    errors_before: np.ndarray  # (M,) px, original cameras and anchors
    errors_after: np.ndarray  # (M,) px, adjusted cameras and points
    evaluations: tuple[int, ...]


# The robust losses rho(z) of the squared scaled residual z = (f / loss_scale)^2 and their
# derivatives (scipy.optimize.least_squares' definitions): the cost is
# 0.5 * loss_scale^2 * sum rho(z), each residual weighted by rho'(z) in the normal equations.
_LOSSES = {
    "linear": (lambda z: z, lambda z: np.ones_like(z)),
    "huber": (lambda z: np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0),
              lambda z: np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))),
    "soft_l1": (lambda z: 2.0 * (np.sqrt(1.0 + z) - 1.0), lambda z: 1.0 / np.sqrt(1.0 + z)),
    "cauchy": (lambda z: np.log1p(z), lambda z: 1.0 / (1.0 + z)),
    "arctan": (lambda z: np.arctan(z), lambda z: 1.0 / (1.0 + z * z)),
}
# Levenberg-Marquardt: initial damping (a fraction of the normal matrix's diagonal), its factors
# after an accepted and a rejected step, and the stopping tests: relative cost decrease and the
# largest parameter step (px or m) below which the solve has converged.
_LM_DAMPING0 = 1e-4
_LM_DOWN, _LM_UP = 0.3, 10.0
_LM_FTOL = 1e-10
_LM_XTOL = 1e-8


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values`` (M, ...) into (n, ...) by ``index`` (M,) (bincount per component,
    several times faster than np.add.at)."""
    flat = values.reshape(len(index), -1)
    out = np.empty((n, flat.shape[1]))
    for c in range(flat.shape[1]):
        out[:, c] = np.bincount(index, weights=flat[:, c], minlength=n)
    return out.reshape((n,) + values.shape[1:])


def _normal_step(V: int, obs: Observations, J: np.ndarray, r: np.ndarray, a: np.ndarray,
                 wr: np.ndarray, wa: np.ndarray, sqrt_lambda: float, damping: float,
                 groups: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step (shifts (V, 2), points (N, 3)) of the weighted problem, the
    points eliminated per point (Schur complement): a 2V x 2V system for the V views' shifts."""
    N = obs.n_points
    lam = sqrt_lambda ** 2
    CA = wr[:, :, None] * J  # W_k A_k (M, 2, 3): the shift-point blocks of J^T W J
    U = _sum_by(obs.point, np.einsum("mai,maj->mij", J, CA), N)
    U[:, [0, 1, 2], [0, 1, 2]] += lam * wa
    gX = _sum_by(obs.point, np.einsum("mai,ma->mi", CA, r), N) + sqrt_lambda * wa * a
    S = _sum_by(obs.view, wr, V)
    gs = _sum_by(obs.view, wr * r, V)
    # Marquardt's damping: the diagonal scaled by (1 + damping).
    U[:, [0, 1, 2], [0, 1, 2]] *= 1.0 + damping
    S = S * (1.0 + damping)
    Uinv = np.linalg.inv(U)
    G = np.einsum("mai,mij->maj", CA, Uinv[obs.point])  # C_k U_p^-1 (M, 2, 3)
    Hs = np.zeros((V, V, 2, 2))
    Hs[np.arange(V), np.arange(V)] = np.einsum("va,ab->vab", S, np.eye(2))
    order, start, length = groups
    for i in range(int(length.max())):
        for j in range(int(length.max())):
            sel = length > max(i, j)
            k, kk = order[start[sel] + i], order[start[sel] + j]
            np.add.at(Hs, (obs.view[k], obs.view[kk]), -np.einsum("mai,mbi->mab", G[k], CA[kk]))
    bs = _sum_by(obs.view, np.einsum("mai,mi->ma", G, gX[obs.point]), V) - gs
    ds = np.linalg.solve(Hs.transpose(0, 2, 1, 3).reshape(2 * V, 2 * V), bs.ravel()).reshape(V, 2)
    rhs = -gX - _sum_by(obs.point, np.einsum("mai,ma->mi", CA, ds[obs.view]), N)
    dX = np.einsum("nij,nj->ni", Uinv, rhs)
    return ds, dX


def _solve(P: np.ndarray, obs: Observations, anchors: np.ndarray, shifts0: np.ndarray,
           points0: np.ndarray, options: BundleOptions) -> tuple[np.ndarray, np.ndarray, int]:
    """One robust Levenberg-Marquardt solve from (shifts0, points0); returns (shifts, points,
    cost evaluations). Each step weights the residuals by the loss's derivative (iteratively
    reweighted least squares, whose fixed point is the robust cost's stationary point) and
    eliminates the points (3 x 3 blocks) so that only the shifts' 2V x 2V system is solved."""
    rho, drho = _LOSSES[options.loss]
    sqrt_lambda = math.sqrt(options.regulariser)
    c2 = options.loss_scale_px ** 2
    order = np.argsort(obs.point, kind="stable")
    length = np.bincount(obs.point, minlength=obs.n_points)
    groups = (order, np.concatenate([[0], np.cumsum(length)[:-1]]), length)

    def evaluate(s, X):
        xy, _w, J = projection_jacobian(P, obs.view, X[obs.point])
        r = xy + s[obs.view] - obs.xy
        a = sqrt_lambda * (X - anchors)
        cost = 0.5 * c2 * (rho(r * r / c2).sum() + rho(a * a / c2).sum())
        return cost, r, a, J

    s, X = np.array(shifts0, np.float64), np.array(points0, np.float64)
    cost, r, a, J = evaluate(s, X)
    evaluations, damping = 1, _LM_DAMPING0
    while evaluations < options.max_evaluations:
        ds, dX = _normal_step(P.shape[0], obs, J, r, a, drho(r * r / c2), drho(a * a / c2), sqrt_lambda,
                              damping, groups)
        new = evaluate(s + ds, X + dX)
        evaluations += 1
        step = max(float(np.abs(ds).max(initial=0.0)), float(np.abs(dX).max(initial=0.0)))
        if np.isfinite(new[0]) and new[0] <= cost:  # else (too long a step): more damping
            decrease = cost - new[0]
            s, X = s + ds, X + dX
            cost, r, a, J = new
            damping *= _LM_DOWN
            if decrease <= _LM_FTOL * cost or step <= _LM_XTOL:
                break
        else:
            damping *= _LM_UP
            if step <= _LM_XTOL:
                break
    return s, X, evaluations


def _shifted(P: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Projection matrices (V, 3, 4) with the principal points moved by ``shifts`` (V, 2) px."""
    out = P.copy()
    out[:, :2, :] += shifts[:, :, None] * P[:, 2:3, :]
    return out


def _errors(P: np.ndarray, obs: Observations, X: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    xy, _w, _J = projection_jacobian(P, obs.view, X[obs.point])
    return np.hypot(*(xy + shifts[obs.view] - obs.xy).T)


def _check_coverage(obs: Observations, V: int, names: Sequence[str], minimum: int, stage: str) -> None:
    """Raise CameraError naming the views with fewer than ``minimum`` observations."""
    count = np.bincount(obs.view, minlength=V)
    poor = [f"{names[v]} ({count[v]})" for v in range(V) if count[v] < minimum]
    if poor:
        raise CameraError(
            f"cannot adjust the principal points: {stage}, too few tie points remain in "
            f"{', '.join(poor)} (need at least {minimum} per view); do the views see the same "
            "textured place?"
        )


def _anchors(P: np.ndarray, obs: Observations, threshold: float) -> tuple[Observations, np.ndarray]:
    """Triangulate with the original cameras, dropping points behind a camera or with an
    observation further than ``threshold`` px; repeated until every kept point passes."""
    while True:
        X, err, front = triangulate_observations(obs, P)
        worst = np.zeros(obs.n_points)
        np.maximum.at(worst, obs.point, err)
        good = front & (worst <= threshold)
        if good.all() or obs.n_points == 0:
            return obs, X
        obs = obs.subset(good[obs.point])


def adjust_observations(cameras: Sequence[Any], obs: Observations, options: BundleOptions = BundleOptions(),
                        *, names: Sequence[str] | None = None) -> BundleSolution:
    """Bundle-adjust principal points and points on given observations (tracks already built).

    ``cameras``: objects with a 3x4 ``P`` (ENU -> pixels). Steps: anchors = triangulation with the
    original cameras (tracks with errors above ``initial_threshold_px`` dropped); solve; drop
    observations above ``coarse_threshold_px``; re-anchor and solve; drop those above
    ``fine_threshold_px``; re-anchor and solve. Raises CameraError naming the views left with
    fewer than ``min_observations`` observations.
    """
    P = projection_stack(cameras)
    V = P.shape[0]
    names = [f"view {v}" for v in range(V)] if names is None else list(names)
    obs, anchors = _anchors(P, obs, options.initial_threshold_px)
    _check_coverage(obs, V, names, options.min_observations, "after triangulation")
    shifts, X = np.zeros((V, 2)), anchors.copy()
    evaluations = []
    for threshold in (options.coarse_threshold_px, options.fine_threshold_px):
        shifts, X, nfev = _solve(P, obs, anchors, shifts, X, options)
        evaluations.append(nfev)
        keep = _errors(P, obs, X, shifts) <= threshold
        obs = obs.subset(keep)
        _check_coverage(obs, V, names, options.min_observations,
                        f"after rejecting reprojection errors above {threshold:g} px")
        # Re-anchor: the pre-adjustment triangulation of what is left (outliers no longer pull);
        # restart the points from their triangulation with the adjusted cameras (points that lost
        # an outlier move by metres, which the joint solver would approach in many small steps).
        anchors = triangulate_observations(obs, P)[0]
        X = triangulate_observations(obs, _shifted(P, shifts))[0]
    shifts, X, nfev = _solve(P, obs, anchors, shifts, X, options)
    evaluations.append(nfev)
    before = _errors(P, obs, anchors, np.zeros((V, 2)))
    after = _errors(P, obs, X, shifts)
    return BundleSolution(shifts=shifts, points=X, anchors=anchors, obs=obs, errors_before=before,
                          errors_after=after, evaluations=tuple(evaluations))


# -- cameras -------------------------------------------------------------------------------------
def shift_principal_point(camera: Any, shift: Sequence[float]) -> Any:
    """A copy of a PerspectiveCamera with its principal point moved by ``shift`` = (dcx, dcy) px.

    ``K' = T K`` and ``P' = T P`` with ``T = [[1, 0, dcx], [0, 1, dcy], [0, 0, 1]]``: every
    projection moves by exactly ``(dcx, dcy)``; R, t and the rest of K are unchanged.
    """
    dx, dy = (float(v) for v in shift)
    T = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
    K = np.asarray(camera.K, np.float64)
    if not np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-12):
        raise CameraError(f"shift_principal_point: K[2] = {K[2].tolist()} is not (0, 0, 1)")
    return dataclasses.replace(camera, K=T @ K, P=T @ np.asarray(camera.P, np.float64))


def gauge_jacobians(cameras: Sequence[Any], point: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(V, 2, 3) Jacobians d(pixel)/d(ENU) of the cameras at ``point``: the unobservable motion.

    Shifts ``s_v`` and ``s_v - A_v dX`` fit the images equally well for any ``dX`` (m); compare
    recovered shifts with expected ones modulo this 3-parameter family.
    """
    P = projection_stack(cameras)
    X = np.tile(np.asarray(point, np.float64), (P.shape[0], 1))
    return projection_jacobian(P, np.arange(P.shape[0]), X)[2]


# -- the whole step ------------------------------------------------------------------------------
def _view_cameras(cameras: Any) -> tuple[list[Any], list[str] | None]:
    """Per-view PerspectiveCameras and names from a CameraSet or a sequence of cameras."""
    views = getattr(cameras, "views", None)
    if views is not None:
        return [v.camera for v in views], [os.path.basename(v.path) for v in views]
    return list(cameras), None


def _match_all(feats: list[tuple[np.ndarray, np.ndarray]], cams: list[Any],
               sparse_options: SparseOptions) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Verified matches of every pair of views."""
    out = {}
    V = len(feats)
    for i in range(V):
        for j in range(i + 1, V):
            F = (fundamental_from_cameras(cams[i], cams[j])
                 if sparse_options.geometric_model == "cameras" else None)
            out[(i, j)] = match_pair(feats[i][1], feats[j][1], feats[i][0], feats[j][0],
                                     sparse_options, fundamental=F)
    return out


def _check_connected(matches: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]], V: int,
                     names: Sequence[str], min_matches: int) -> None:
    """Raise CameraError when the pairs with enough matches do not link all the views."""
    good = [(i, j) for (i, j), (a, _b) in matches.items() if len(a) >= min_matches]
    ij = np.array(good, dtype=np.int64).reshape(-1, 2)
    labels = connected_labels(V, ij[:, 0], ij[:, 1])
    if labels.max() == 0:
        return
    # Name the views cut off from view 0's group and the best pair across the cut.
    apart = [v for v in range(V) if labels[v] != labels[0]]
    across = [(len(a), i, j) for (i, j), (a, _b) in matches.items() if (labels[i] == labels[0]) != (labels[j] == labels[0])]
    k, i, j = max(across)
    group = ", ".join(names[v] for v in apart)
    raise CameraError(
        f"cannot adjust the principal points: {group} share{'s' if len(apart) == 1 else ''} too few "
        f"verified matches with the other views (best pair: {names[i]} and {names[j]} with {k}; "
        f"need at least {min_matches}); do the views see the same place?"
    )


def adjust_principal_points(
    cameras: Any,
    images: Sequence[np.ndarray],
    options: BundleOptions = BundleOptions(),
    sparse_options: SparseOptions = SparseOptions(),
    names: Sequence[str] | None = None,
) -> tuple[Any, BundleReport]:
    """Correct the pointing errors of the views: features, matches, tracks, bundle adjustment.

    ``cameras``: a :class:`satsweep.camera.CameraSet` or a sequence of
    :class:`satsweep.camera.PerspectiveCamera`; ``images``: the views' tonemapped float32 images
    (``satsweep.imageio.tonemap``) in the pixels the cameras refer to (the AOI crops, or the
    skew-corrected images for skew-corrected cameras). Returns the adjusted cameras, of the same
    kind as given (a CameraSet gets its views' cameras and plane-plus-parallax projections
    replaced), and the report. ``names`` default to the image file names of a CameraSet, else
    "view 0", "view 1", ...

    Raises CameraError naming the views when the input is degenerate: a view with too few SIFT
    features (blank image), views without enough verified matches to the others (different
    places), or too few tie points left after outlier rejection.
    """
    cams, set_names = _view_cameras(cameras)
    V = len(cams)
    if names is None:
        names = set_names if set_names is not None else [f"view {v}" for v in range(V)]
    names = list(names)
    if V < 2:
        raise CameraError(f"cannot adjust the principal points of {V} view(s): need at least 2")
    if len(images) != V or len(names) != V:
        raise CameraError(f"adjust_principal_points: {len(images)} images and {len(names)} names "
                          f"for {V} cameras")
    for name, image, cam in zip(names, images, cams):
        if np.shape(image) != (cam.height, cam.width):
            raise CameraError(f"{name}: image of shape {np.shape(image)} but the camera is "
                              f"{cam.width}x{cam.height} px")
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    feats = [detect_features(im, max_features=sparse_options.max_features,
                             contrast_threshold=sparse_options.contrast_threshold,
                             scale=feature_scale_for(np.shape(im), sparse_options))
             for im in images]
    n_features = [len(xy) for xy, _ in feats]
    poor = [f"{n} ({k})" for n, k in zip(names, n_features) if k < sparse_options.min_matches]
    if poor:
        raise CameraError(
            f"cannot adjust the principal points: too few SIFT features in {', '.join(poor)} "
            f"(need at least {sparse_options.min_matches}); blank or featureless image?"
        )
    seconds["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matches = _match_all(feats, cams, sparse_options)
    _check_connected(matches, V, names, sparse_options.min_matches)
    used = {p: m for p, m in matches.items() if len(m[0]) >= sparse_options.min_matches}
    seconds["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    tracks = build_tracks(V, used)
    lengths = np.bincount([len(t) for t in tracks], minlength=V + 1) if tracks else np.zeros(V + 1, int)
    histogram = {int(k): int(c) for k, c in enumerate(lengths) if c > 0}
    obs = observations_from_tracks(tracks, [xy for xy, _ in feats])
    seconds["tracks"] = time.perf_counter() - t0

    n_refine_dropped = 0
    if sparse_options.refine_window_px:
        t0 = time.perf_counter()
        obs, n_refine_dropped = refine_observations(
            obs, images, cams, window_px=sparse_options.refine_window_px,
            max_shift_px=sparse_options.refine_max_shift_px)
        seconds["refinement"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    solution = adjust_observations(cams, obs, options, names=names)
    seconds["adjustment"] = time.perf_counter() - t0

    report = BundleReport(
        names=tuple(names),
        n_features=tuple(n_features),
        n_matches=tuple((i, j, len(m[0])) for (i, j), m in matches.items()),
        min_matches=sparse_options.min_matches,
        n_tracks=len(tracks),
        track_length_histogram=histogram,
        n_refine_dropped=n_refine_dropped,
        n_points=solution.obs.n_points,
        n_observations=tuple(int(c) for c in np.bincount(solution.obs.view, minlength=V)),
        reproj_before_px=(float(np.median(solution.errors_before)), float(np.mean(solution.errors_before))),
        reproj_after_px=(float(np.median(solution.errors_after)), float(np.mean(solution.errors_after))),
        principal_point_shift_px=tuple((float(s[0]), float(s[1])) for s in solution.shifts),
        regulariser=options.regulariser,
        solver_evaluations=solution.evaluations,
        seconds=seconds,
    )
    return shift_principal_points(cameras, solution.shifts), report


def shift_principal_points(cameras: Any, shifts: Sequence[Sequence[float]]) -> Any:
    """``cameras`` (a CameraSet or a sequence of PerspectiveCamera) with each view's principal
    point moved by its (dcx, dcy) of ``shifts`` (``shift_principal_point``); a CameraSet gets
    its views' cameras and plane-plus-parallax projections replaced."""
    cams, _ = _view_cameras(cameras)
    if len(shifts) != len(cams):
        raise CameraError(f"shift_principal_points: {len(shifts)} shifts for {len(cams)} views")
    adjusted = [shift_principal_point(c, s) for c, s in zip(cams, shifts)]
    views = getattr(cameras, "views", None)
    if views is None:
        return adjusted
    from satsweep.geometry.parallax import reparametrise

    new_views = tuple(
        dataclasses.replace(v, camera=c, projection=reparametrise(c, d=v.projection.d, zbar=v.projection.zbar))
        for v, c in zip(views, adjusted)
    )
    return dataclasses.replace(cameras, views=new_views)
