"""Bundle adjustment of principal points: the correction of RPC pointing errors.

Vendor RPCs carry pointing errors of up to a few pixels, which over a small AOI amount to an
image-space translation per view. Following VisSat (Zhang et al. 2019), the correction is done
the vision way: SIFT features are matched across views (:mod:`satsweep.sparse`), chained into
tracks and triangulated with the approximated perspective cameras, and a bundle adjustment then
moves only the principal point ``(cx, cy)`` of every camera (and the 3-D points); focal lengths,
skew, rotation and centre stay fixed.

Objective (scipy ``least_squares``, sparse Jacobian, robust loss)::

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

from .errors import CameraError
from .options import Options
from .sparse import (
    Observations,
    SparseOptions,
    build_tracks,
    detect_features,
    feature_scale_for,
    fundamental_from_cameras,
    match_pair,
    observations_from_tracks,
    refine_observations,
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
    # Robust loss of scipy.optimize.least_squares applied to the residuals. soft_l1 (the smooth
    # pseudo-Huber) by default: with Huber's kink scipy's trust-region steps crawl (measured: 200
    # function evaluations against 6 for soft_l1 on the same problem, same solution).
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
    # Function evaluations allowed to each least_squares solve.
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
    solver_evaluations: tuple[int, ...]  # function evaluations of each least_squares solve
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


def _residuals(params: np.ndarray, P: np.ndarray, obs: Observations, anchors: np.ndarray,
               sqrt_lambda: float) -> np.ndarray:
    V = P.shape[0]
    s = params[:2 * V].reshape(V, 2)
    X = params[2 * V:].reshape(-1, 3)
    xy, _w, _J = projection_jacobian(P, obs.view, X[obs.point])
    r_obs = xy + s[obs.view] - obs.xy
    return np.concatenate([r_obs.ravel(), sqrt_lambda * (X - anchors).ravel()])


def _jacobian_structure(V: int, obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Row and column indices of the non-zeros: shift block (2M), point block (6M), anchors (3N)."""
    M, N = len(obs.point), obs.n_points
    k = np.arange(M)
    # d r_obs[k, a] / d s[view, a]: one entry per residual.
    rows_s = (2 * k[:, None] + np.arange(2)).ravel()
    cols_s = (2 * obs.view[:, None] + np.arange(2)).ravel()
    # d r_obs[k, a] / d X[point, b]: a 2x3 block per observation.
    rows_x = np.broadcast_to((2 * k)[:, None, None] + np.arange(2)[None, :, None], (M, 2, 3)).ravel()
    cols_x = np.broadcast_to(2 * V + 3 * obs.point[:, None, None] + np.arange(3)[None, None, :], (M, 2, 3)).ravel()
    rows_a = 2 * M + np.arange(3 * N)
    cols_a = 2 * V + np.arange(3 * N)
    return (np.concatenate([rows_s, rows_x, rows_a]), np.concatenate([cols_s, cols_x, cols_a]),
            np.array([2 * M, 6 * M, 3 * N]), np.array([2 * M + 3 * N, 2 * V + 3 * N]))


def _solve(P: np.ndarray, obs: Observations, anchors: np.ndarray, shifts0: np.ndarray,
           points0: np.ndarray, options: BundleOptions) -> tuple[np.ndarray, np.ndarray, int]:
    """One least_squares solve from (shifts0, points0); returns (shifts, points, evaluations)."""
    from scipy.optimize import least_squares
    from scipy.sparse import csr_matrix

    V = P.shape[0]
    sqrt_lambda = math.sqrt(options.regulariser)
    rows, cols, sizes, shape = _jacobian_structure(V, obs)
    n_s, n_x, n_a = (int(v) for v in sizes)
    anchor_values = np.full(n_a, sqrt_lambda)
    shift_values = np.ones(n_s)

    def fun(params):
        return _residuals(params, P, obs, anchors, sqrt_lambda)

    def jac(params):
        X = params[2 * V:].reshape(-1, 3)
        _xy, _w, J = projection_jacobian(P, obs.view, X[obs.point])
        data = np.concatenate([shift_values, J.ravel(), anchor_values])
        return csr_matrix((data, (rows, cols)), shape=tuple(int(v) for v in shape))

    x0 = np.concatenate([shifts0.ravel(), points0.ravel()])
    res = least_squares(fun, x0, jac=jac, method="trf", tr_solver="lsmr", x_scale="jac",
                        loss=options.loss, f_scale=options.loss_scale_px,
                        max_nfev=options.max_evaluations)
    if not np.all(np.isfinite(res.x)):
        raise CameraError("the bundle adjustment diverged (non-finite parameters)")
    return res.x[:2 * V].reshape(V, 2), res.x[2 * V:].reshape(-1, 3), int(res.nfev)


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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    good = [(i, j) for (i, j), (a, _b) in matches.items() if len(a) >= min_matches]
    if good:
        ij = np.array(good)
        graph = coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(V, V))
    else:
        graph = coo_matrix((V, V))
    n_comp, labels = connected_components(graph, directed=False)
    if n_comp == 1:
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

    adjusted = [shift_principal_point(c, s) for c, s in zip(cams, solution.shifts)]
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
    views = getattr(cameras, "views", None)
    if views is None:
        return adjusted, report
    from .camera import reparametrise

    new_views = tuple(
        dataclasses.replace(v, camera=c, projection=reparametrise(c, d=v.projection.d, zbar=v.projection.zbar))
        for v, c in zip(views, adjusted)
    )
    return dataclasses.replace(cameras, views=new_views), report
