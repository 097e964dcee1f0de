"""Bundle adjustment of principal points: the correction of RPC pointing errors.

Vendor RPCs carry pointing errors of a few pixels (tens on some views of real stacks), which
over a small AOI amount to an image-space translation per view. Following VisSat (Zhang et al.
2019), the correction is done the vision way: SIFT features are matched across views
(:mod:`satsweep.sparse`), chained into tracks and triangulated with the approximated perspective
cameras, and a bundle adjustment then moves only the principal point ``(cx, cy)`` of every
camera (and the 3-D points); focal lengths, skew, rotation and centre stay fixed.

Two stages (the sparse stage, :mod:`satsweep.sparse.stage`, runs both):

- :func:`adjust_coarse`: pointing errors of any size from the raw keypoints. No threshold
  assumes the cameras are within a few pixels: rounds of robust solves whose loss scale and
  rejection threshold start from the median error and shrink with it, on a sample of the
  tracks; the result is put in the gauge of smallest corrections (:func:`robust_gauge`).
- :func:`adjust_observations`: the fine adjustment, from cameras corrected by the coarse
  shifts, on tie points registered to a fraction of a pixel; its anchors are the triangulation
  with those cameras, so that the regulariser below pulls the points by centimetres, not by
  the metres that tens of pixels of pointing error would move them.

:func:`shift_uncertainty` then says how firmly the tie points fix each shift.

Objective of each solve (robust Levenberg-Marquardt, the points eliminated per point)::

    sum_obs  rho(|| proj(P_v, X_p) + s_v - x_obs ||^2)  +  lambda * sum_p || X_p - Xhat_p ||^2

where ``s_v`` is the shift (px) of view v's principal point (moving ``cx, cy`` by ``s`` moves every
projection by exactly ``s``, as ``K[2] = (0, 0, 1)``), ``X_p`` a point in ENU metres and ``Xhat_p``
its triangulation with the starting cameras; ``lambda`` (default 0.01 px^2/m^2) anchors the
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
own parallax direction, by ``parallax_v`` (px/m) times the offset. So only the shifts modulo
``{-A_v dX}`` are measured; with no pointing error they are zero. The coarse stage picks the
member whose shifts are smallest over the views (a robust fit of ``dX``: most views' RPCs are
taken as right on average), and the fine stage's anchor ``lambda`` keeps it (its points stay at
their triangulation with the coarsely corrected cameras). With pointing errors of tens of
pixels, the recovered scene may thus lie tens of metres from the true one (the synthetic stacks
of tools/bench_ba.py, biases up to 50 px: dX of 13-76 m, mostly in height); everything derived
from the corrected cameras (tie points, altitude range, DSM) lies in that same frame.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Literal, Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.options import Options
from satsweep.sparse.matching import fundamental_from_cameras, match_pair
from satsweep.sparse.options import SparseOptions
from satsweep.sparse.tracks import Observations
from satsweep.sparse.triangulation import (
    SYM3,
    base_to_height,
    jacobian_entries,
    observation_entries,
    point_covariances,
    project_entries,
    projection_jacobian,
    projection_stack,
    sum_by,
    sym3_apply,
    sym3_inverse,
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
    "adjust_coarse",
    "robust_gauge",
    "in_gauge",
    "shift_uncertainty",
    "ShiftUncertainty",
    "TooFewObservations",
    "track_median_errors",
]


@dataclasses.dataclass(frozen=True)
class BundleOptions(Options):
    """Options of the principal-point bundle adjustment."""

    regulariser: float = 0.01  # weight (px^2 per m^2) of each point's anchor to its
    # pre-adjustment triangulation; fixes the gauge, > 0
    loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "soft_l1"  # robust loss of
    # each residual
    loss_scale_px: float = 0.3  # residual (px) where the robust loss leaves its quadratic zone
    # (tie points between dates lie 0.2-0.3 px off, within a date 0.06: at 1 px they pulled
    # the corrections of multi-date stacks by 0.1-0.3 px)
    extended_loss_scale_px: float = 0.1  # ... in the sparse stage's fine adjustment once its
    # tracks are extended to every view (SparseOptions.extend_points_per_view, 3 views or more):
    # with many more tie points between dates, the tighter loss leaves out those that moving
    # shadows bias (tools/bench_multidate.py v10 seeds 0-5, worst correction 0.150 -> 0.128 px
    # on average; without the extension 0.1 did not help: 0.209 -> 0.216 px)
    extended_loss: Literal["linear", "huber", "soft_l1", "cauchy", "arctan"] = "cauchy"  # ... and
    # the loss there: tie points between dates that a moving shadow or the sun's shading biases
    # pull each date's views one way by 0.1-0.3 px, coherently; a loss whose pull fades with the
    # residual (Cauchy) lets the unbiased majority set the shifts where soft_l1's keeps pulling.
    # Worst view after the gauge, pipeline crops, mean over seeds: v10 multi-date seeds 0-5 0.127
    # -> 0.088 px, issue-form 0.3 m stacks (seeds 11-16, 19 views) 0.074 -> 0.056 px
    # (docs/measurements.md, twenty-seventh session)
    initial_threshold_px: float = 10.0  # tracks leaving an observation farther (px) before the
    # adjustment are dropped
    coarse_threshold_px: float = 4.0  # observations farther (px) after the first solve go
    fine_threshold_px: float = 2.0  # observations farther (px) after the second solve go
    min_observations: int = 20  # observations each view must keep
    max_evaluations: int = 200  # cost evaluations allowed to each solve
    max_shift_sigma_px: float = 0.3  # a view whose correction is more uncertain (px, 1 sigma) is
    # dropped by the sparse stage
    anchor_min_bh: float = 0.01  # points whose views' effective base-to-height ratio
    # (triangulation.base_to_height) is lower have no anchor: triangulated along nearly one line
    # of sight, an anchor holds the two views' relative correction along their small parallax
    # where the anchors' cameras put it (bench_multidate one view per date seed 39, 3 views of
    # which two 0.004 rad apart, 40 of 112 points: 0.275 px off after the gauge, 0.019 without
    # their anchors; as 8-bit RGB at 33.45 S 1.272 -> 0.032 px). The other points fix the gauge
    fixed_views: tuple[str, ...] = ()  # views whose RPCs are trusted (file names as given, or
    # paths): their corrections are held at zero and the others are corrected to agree with
    # them (ASP's fixed cameras, S2P's reference image); (): the gauge of smallest corrections
    surface_ties: Literal["auto", "on", "off"] = "auto"  # once a first DSM is made, the
    # corrections refined on tie points of its surface (satsweep.sparse.surface_ties) and the
    # dense stages run again with them, for 3 views or more; auto: where the sparse stage left
    # a view's correction uncertain by more than surface_ties_sigma_px (few tie points: small
    # stacks of other dates), since it doubles the dense stages' time
    surface_ties_sigma_px: float = 0.035  # surface_ties = auto refines the corrections where
    # one is uncertain by more than this (px, one sigma, the sparse stage's correction_sigma_px).
    # Measured: the runs of tools/bench_multidate.py's families left over 0.05 px after the
    # gauge report
    # 0.040-0.110 px (13 of 328 runs; 3 with the refinement); the issue-form stacks of 19 views
    # of 850 px 0.011-0.017 px, the 1700 px one 0.024-0.030 px (85 s a run: refined, it would
    # sweep twice, past issue 26's 2 minutes), 10 views in passes under 0.02 px. At 0.02 px
    # (before the halves' spread): as many runs over 0.05 px as at 0.035, each family's mean
    # worst view 0.001-0.002 px lower (docs/measurements.md, sixty-seventh session)
    surface_ties_points: int = 1000  # cells of the DSM, on a regular stride, projected and
    # registered into every view

    ADVANCED = ("loss", "loss_scale_px", "extended_loss_scale_px", "extended_loss",
                "initial_threshold_px",
                "coarse_threshold_px", "fine_threshold_px", "min_observations", "max_evaluations",
                "max_shift_sigma_px", "anchor_min_bh", "surface_ties_sigma_px",
                "surface_ties_points")

    def check(self) -> None:
        self._require(math.isfinite(self.regulariser) and self.regulariser > 0.0, "regulariser",
                      "must be a positive number (it fixes the gauge of the adjustment)")
        self._require(math.isfinite(self.loss_scale_px) and self.loss_scale_px > 0.0,
                      "loss_scale_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.extended_loss_scale_px)
                      and self.extended_loss_scale_px > 0.0,
                      "extended_loss_scale_px", "must be a positive number of pixels")
        for name in ("initial_threshold_px", "coarse_threshold_px", "fine_threshold_px"):
            v = getattr(self, name)
            self._require(math.isfinite(v) and v > 0.0, name, "must be a positive number of pixels")
        self._require(self.fine_threshold_px <= self.coarse_threshold_px <= self.initial_threshold_px,
                      "coarse_threshold_px",
                      "thresholds must satisfy fine <= coarse <= initial")
        self._require(self.min_observations >= 3, "min_observations",
                      "must be at least 3 (2 shift parameters per view need redundancy)")
        self._require(self.max_evaluations >= 1, "max_evaluations", "must be at least 1")
        self._require(math.isfinite(self.max_shift_sigma_px) and self.max_shift_sigma_px > 0.0,
                      "max_shift_sigma_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.anchor_min_bh) and self.anchor_min_bh >= 0.0,
                      "anchor_min_bh", "must be a base-to-height ratio >= 0 (0: every point)")
        self._require(math.isfinite(self.surface_ties_sigma_px) and self.surface_ties_sigma_px >= 0.0,
                      "surface_ties_sigma_px", "must be a number of pixels >= 0")
        self._require(self.surface_ties_points >= 10, "surface_ties_points", "must be at least 10")
        self._require(all(isinstance(f, str) and f.strip() for f in self.fixed_views),
                      "fixed_views", "must be a list of file names")
        self._require(len(set(self.fixed_views)) == len(self.fixed_views), "fixed_views",
                      "names a view twice")


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
    reproj_before_px: tuple[float, float]  # (median, mean), raw keypoints and original cameras
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
    unanchored: int = 0  # points the last solve left without an anchor (anchor_min_bh)


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
# The solves of adjust_observations stop at these instead (relative decrease, step in px or m):
# on the synthetic stacks of tools/bench_ba.py the shifts agree with those of _LM_FTOL/_LM_XTOL
# to 1e-4 px, in 40% fewer evaluations (20 views: 0.97 s instead of 1.6 s).
_FINE_FTOL = 1e-8
_FINE_XTOL = 1e-5
# ... but the two solves whose only use is to find the observations to reject (farther than
# coarse_threshold_px, then fine_threshold_px) stop at these: a thousandth of a pixel changes no
# rejection at thresholds of pixels.
_SCREEN_FTOL = 1e-6
_SCREEN_XTOL = 1e-3
# A non-convex loss's last solve (from the screening solves' soft_l1 solution) stops after this
# many cost evaluations: its reweighted steps crawl (80-110 to _FINE_FTOL), while the shifts at
# 30 lie within 0.001 px of the converged ones on tools/bench_ba.py's 20 views and within 0.004
# / 0.005 px on the multi-date v10 seeds 0 / 5 (tools/bench_multidate.py's crops).
_NON_CONVEX_MAX_EVALUATIONS = 30
# Robust losses whose cost is not convex (several minima; their reweighted steps converge slowly).
_NON_CONVEX = ("cauchy", "arctan")


def _inverse_spd3(U: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Inverses (6 entries in SYM3 order, each (N,)) of symmetric positive-definite 3 x 3 blocks
    given by their 6 entries ``U``, by their adjugates. Raises LinAlgError, as ``np.linalg.inv``
    does, when a block is singular (a determinant that is not positive)."""
    det, adj = sym3_inverse(U)
    if not np.all(det > 0.0):
        raise np.linalg.LinAlgError("a point's 3 x 3 normal block is singular")
    return [a / det for a in adj]


@dataclasses.dataclass
class _Linearised:
    """The adjustment's residuals and Jacobians at one estimate, per observation as rows."""

    p: np.ndarray  # (12, M) each observation's camera (triangulation.observation_entries)
    col: np.ndarray  # (M,) projected column of the point, before the view's shift
    row: np.ndarray  # (M,) projected row
    w: np.ndarray  # (M,) depth
    rc: np.ndarray  # (M,) column residual (projection + shift - observation), px
    rr: np.ndarray  # (M,) row residual, px

    def jacobians(self) -> tuple[np.ndarray, np.ndarray]:
        return jacobian_entries(self.p, self.col, self.row, self.w)


class _FillIn:
    """Where the blocks of the Schur fill-in go (see :func:`_reduced_hessian`): the flat indices
    of entry (2 view + a, 3 point + i) of the two 2V x 3N matrices, and the matrices themselves,
    zero elsewhere. The same for every step of a solve (its observations do not change): made
    once, the matrices rewritten in place (a third of a step's time on 20 views)."""

    def __init__(self, V: int, obs: Observations):
        N = obs.n_points
        # a track sees each view once, so no two blocks share an entry
        base = (2 * obs.view) * (3 * N) + 3 * obs.point
        self.flat = np.concatenate([base + i for i in range(3)]
                                   + [base + 3 * N + i for i in range(3)])
        self.G = np.zeros((2 * V, 3 * N))
        self.C = np.zeros((2 * V, 3 * N))

    def product(self, g: Sequence[np.ndarray], c: Sequence[np.ndarray]) -> np.ndarray:
        """sum_p sum_(k, k' of p) G_k C_k'^T for the blocks ``g`` = (gu, gv), ``c`` = (cu, cv)."""
        self.G.reshape(-1)[self.flat] = np.concatenate([g[0].ravel(), g[1].ravel()])
        self.C.reshape(-1)[self.flat] = np.concatenate([c[0].ravel(), c[1].ravel()])
        return self.G @ self.C.T


def _reduced_hessian(V: int, obs: Observations, ju: np.ndarray, jv: np.ndarray, wc: np.ndarray,
                     wr: np.ndarray, point_diag: np.ndarray, damping: float,
                     fill: _FillIn | None = None) -> tuple:
    """The shifts' normal matrix with the points eliminated (Schur complement), (2V, 2V), row
    and column ``2 v + a`` for view v's column (a = 0) and row (a = 1) shift.

    ``ju``, ``jv`` (3, M): d(column)/d(point) and d(row)/d(point) per observation; ``wc``, ``wr``
    (M,): weights of the column and row residuals; ``point_diag`` (N, 3): added to each point's
    3 x 3 block (the anchors' weight); ``damping``: Marquardt's, the diagonals scaled by
    (1 + damping); ``fill``: the fill-in's layout for ``obs`` (made here when None). Also returns
    the points' inverse blocks ``Uinv`` (6 entries in SYM3 order,
    each (N,)), ``cu``, ``cv`` = W_k A_k (each (3, M)) and ``gu``, ``gv`` = C_k U_p^-1.

    The fill-in ``sum_p sum_(k, k' of p) G_k CA_k'^T`` is one dense product of two 2V x 3N
    matrices holding the blocks ``G_k`` and ``CA_k`` (view rows, point columns): O(V^2 N)
    arithmetic in BLAS, where summing the blocks pair by pair costs the square of each track's
    length (20 views: 4 times faster).
    """
    N = obs.n_points
    cu, cv = wc * ju, wr * jv  # W_k A_k: the shift-point blocks of J^T W J
    U = [sum_by(obs.point, ju[i] * cu[j] + jv[i] * cv[j], N) for i, j in SYM3]
    for k, i in ((0, 0), (3, 1), (5, 2)):  # the diagonal, then Marquardt's damping
        U[k] = (U[k] + point_diag[:, i]) * (1.0 + damping)
    S = np.stack([sum_by(obs.view, wc, V), sum_by(obs.view, wr, V)], axis=1).ravel()
    S *= 1.0 + damping
    Uinv = _inverse_spd3(U)
    Ui = [u[obs.point] for u in Uinv]
    gu = sym3_apply(Ui, cu).T  # C_k U_p^-1, each (3, M) (U_p^-1 is symmetric)
    gv = sym3_apply(Ui, cv).T
    H = -(fill if fill is not None else _FillIn(V, obs)).product((gu, gv), (cu, cv))
    H[np.arange(2 * V), np.arange(2 * V)] += S
    return H, Uinv, cu, cv, gu, gv


def _normal_step(V: int, obs: Observations, lin: _Linearised, a: np.ndarray, wc: np.ndarray,
                 wr: np.ndarray, wa: np.ndarray, sqrt_lambda: float, damping: float,
                 fill: _FillIn | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step (shifts (V, 2), points (N, 3)) of the weighted problem, the
    points eliminated per point (Schur complement): a 2V x 2V system for the V views' shifts."""
    N = obs.n_points
    ju, jv = lin.jacobians()
    H, Uinv, cu, cv, gu, gv = _reduced_hessian(V, obs, ju, jv, wc, wr, sqrt_lambda ** 2 * wa,
                                               damping, fill)
    gX = [sum_by(obs.point, cu[i] * lin.rc + cv[i] * lin.rr, N) + sqrt_lambda * wa[:, i] * a[:, i]
          for i in range(3)]
    gXk = [g[obs.point] for g in gX]
    bs = np.stack([sum_by(obs.view, g[0] * gXk[0] + g[1] * gXk[1] + g[2] * gXk[2] - wt * r, V)
                   for g, wt, r in ((gu, wc, lin.rc), (gv, wr, lin.rr))], axis=1)
    ds = np.linalg.solve(H, bs.ravel()).reshape(V, 2)
    dsc, dsr = ds[obs.view, 0], ds[obs.view, 1]
    rhs = [-gX[i] - sum_by(obs.point, cu[i] * dsc + cv[i] * dsr, N) for i in range(3)]
    return ds, sym3_apply(Uinv, rhs)


def _linearise(p: np.ndarray, obs: Observations, X: np.ndarray, s: np.ndarray) -> _Linearised:
    col, row, w = project_entries(p, X[obs.point])
    return _Linearised(p, col, row, w, col + s[obs.view, 0] - obs.xy[:, 0],
                       row + s[obs.view, 1] - obs.xy[:, 1])


def _solve(P: np.ndarray, obs: Observations, anchors: np.ndarray, shifts0: np.ndarray,
           points0: np.ndarray, options: BundleOptions, *, ftol: float = _LM_FTOL,
           xtol: float = _LM_XTOL, anchored: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray, int]:
    """One robust Levenberg-Marquardt solve from (shifts0, points0); returns (shifts, points,
    cost evaluations). Each step weights the residuals by the loss's derivative (iteratively
    reweighted least squares, whose fixed point is the robust cost's stationary point) and
    eliminates the points (3 x 3 blocks) so that only the shifts' 2V x 2V system is solved.
    ``anchored`` (N,) bool: the points held by their anchors (None: all)."""
    rho, drho = _LOSSES[options.loss]
    sqrt_lambda = math.sqrt(options.regulariser)
    c2 = options.loss_scale_px ** 2
    p = observation_entries(P, obs.view)
    fill = _FillIn(P.shape[0], obs)
    held = np.ones((obs.n_points, 1)) if anchored is None else \
        np.asarray(anchored, np.float64).reshape(-1, 1)

    def evaluate(s, X):
        lin = _linearise(p, obs, X, s)
        a = sqrt_lambda * held * (X - anchors)
        cost = 0.5 * c2 * (rho(lin.rc * lin.rc / c2).sum() + rho(lin.rr * lin.rr / c2).sum()
                           + rho(a * a / c2).sum())
        return cost, lin, a

    s, X = np.array(shifts0, np.float64), np.array(points0, np.float64)
    cost, lin, a = evaluate(s, X)
    evaluations, damping = 1, _LM_DAMPING0
    while evaluations < options.max_evaluations:
        ds, dX = _normal_step(P.shape[0], obs, lin, a, drho(lin.rc * lin.rc / c2),
                              drho(lin.rr * lin.rr / c2), held * drho(a * a / c2), sqrt_lambda,
                              damping, fill)
        new = evaluate(s + ds, X + dX)
        evaluations += 1
        step = max(float(np.abs(ds).max(initial=0.0)), float(np.abs(dX).max(initial=0.0)))
        if np.isfinite(new[0]) and new[0] <= cost:  # else (too long a step): more damping
            decrease = cost - new[0]
            s, X = s + ds, X + dX
            cost, lin, a = new
            damping *= _LM_DOWN
            if decrease <= ftol * cost or step <= xtol:
                break
        else:
            damping *= _LM_UP
            if step <= xtol:
                break
    return s, X, evaluations


def _shifted(P: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Projection matrices (V, 3, 4) with the principal points moved by ``shifts`` (V, 2) px."""
    out = P.copy()
    out[:, :2, :] += shifts[:, :, None] * P[:, 2:3, :]
    return out


def _errors(P: np.ndarray, obs: Observations, X: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    lin = _linearise(observation_entries(P, obs.view), obs, X, shifts)
    return np.hypot(lin.rc, lin.rr)


class TooFewObservations(CameraError):
    """Views left with too few observations by the adjustment (``views``: their indices, and
    ``counts``: their observations), so that the sparse stage can drop them and go on."""

    def __init__(self, message: str, views: Sequence[int], counts: Sequence[int]):
        super().__init__(message)
        self.views = tuple(int(v) for v in views)
        self.counts = tuple(int(c) for c in counts)


def _check_coverage(obs: Observations, V: int, names: Sequence[str], minimum: int, stage: str) -> None:
    """Raise TooFewObservations naming the views with fewer than ``minimum`` observations."""
    count = np.bincount(obs.view, minlength=V)
    poor = [v for v in range(V) if count[v] < minimum]
    if poor:
        raise TooFewObservations(
            f"cannot adjust the principal points: {stage}, too few tie points remain in "
            f"{', '.join(f'{names[v]} ({count[v]})' for v in poor)} (need at least {minimum} "
            "per view); do the views see the same textured place?",
            poor, [count[v] for v in poor])


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


def _anchored(P: np.ndarray, obs: Observations, anchors: np.ndarray,
              options: BundleOptions) -> np.ndarray | None:
    """(N,) bool: the points that keep their anchors, those whose views' effective
    base-to-height ratio at the anchor is ``options.anchor_min_bh`` or more; None (all) where
    none would be (views along one line of sight: the gauge needs anchors) or the bound is 0."""
    if options.anchor_min_bh <= 0.0 or obs.n_points == 0:
        return None
    keep = base_to_height(point_covariances(P, obs, anchors)) >= options.anchor_min_bh
    return keep if keep.any() else None


def adjust_observations(cameras: Sequence[Any], obs: Observations, options: BundleOptions = BundleOptions(),
                        *, names: Sequence[str] | None = None) -> BundleSolution:
    """Bundle-adjust principal points and points on given observations (tracks already built).

    ``cameras``: objects with a 3x4 ``P`` (ENU -> pixels). Steps: anchors = triangulation with the
    original cameras (tracks with errors above ``initial_threshold_px`` dropped); solve; drop
    observations above ``coarse_threshold_px``; re-anchor and solve; drop those above
    ``fine_threshold_px``; re-anchor and solve (with a non-convex ``loss``, the two screening
    solves take soft_l1 and the last one at most _NON_CONVEX_MAX_EVALUATIONS evaluations).
    Points whose views' effective base-to-height ratio is under ``anchor_min_bh`` have no anchor
    (:func:`_anchored`).
    Raises CameraError naming the views left with
    fewer than ``min_observations`` observations.
    """
    P = projection_stack(cameras)
    V = P.shape[0]
    names = [f"view {v}" for v in range(V)] if names is None else list(names)
    obs, anchors = _anchors(P, obs, options.initial_threshold_px)
    _check_coverage(obs, V, names, options.min_observations, "after triangulation")
    shifts, X = np.zeros((V, 2)), anchors.copy()
    evaluations = []
    # The screening solves only sort the observations by their errors: a non-convex loss there
    # converges slowly (its reweighted steps crawl) for no better screen, so they take soft_l1
    # and the last solve starts from their solution.
    screen = options.replace(loss="soft_l1") if options.loss in _NON_CONVEX else options
    for threshold in (options.coarse_threshold_px, options.fine_threshold_px):
        shifts, X, nfev = _solve(P, obs, anchors, shifts, X, screen, ftol=_SCREEN_FTOL,
                                 xtol=_SCREEN_XTOL, anchored=_anchored(P, obs, anchors, options))
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
    final = options
    if options.loss in _NON_CONVEX:
        final = options.replace(max_evaluations=min(options.max_evaluations,
                                                    _NON_CONVEX_MAX_EVALUATIONS))
    anchored = _anchored(P, obs, anchors, options)
    shifts, X, nfev = _solve(P, obs, anchors, shifts, X, final, ftol=_FINE_FTOL,
                             xtol=_FINE_XTOL, anchored=anchored)
    evaluations.append(nfev)
    before = _errors(P, obs, anchors, np.zeros((V, 2)))
    after = _errors(P, obs, X, shifts)
    return BundleSolution(shifts=shifts, points=X, anchors=anchors, obs=obs, errors_before=before,
                          errors_after=after, evaluations=tuple(evaluations),
                          unanchored=0 if anchored is None else int((~anchored).sum()))


def track_median_errors(solution: BundleSolution) -> np.ndarray:
    """(N,) per point of ``solution``: the median of its observations' reprojection errors after
    the adjustment (``errors_after``, px; the mean of the two middle ones for an even count)."""
    point, err = solution.obs.point, np.asarray(solution.errors_after, np.float64)
    n = int(solution.obs.n_points)
    if err.shape != point.shape:
        raise ValueError(f"track_median_errors: {err.size} errors for {point.size} observations")
    if n == 0:
        return np.zeros(0)
    order = np.lexsort((err, point))  # by point, then by error
    count = np.bincount(point, minlength=n)
    start = np.r_[0, np.cumsum(count)[:-1]]
    lo, hi = start + (count - 1) // 2, start + count // 2
    ranked = err[order]
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, 0.5 * (ranked[np.minimum(lo, err.size - 1)]
                                          + ranked[np.minimum(hi, err.size - 1)]), np.nan)


# -- the coarse adjustment: pointing errors of any size -------------------------------------------
# Weight (px^2 per m^2) of the anchors in the coarse solves. It only keeps the normal equations
# regular along the gauge (the coarse shifts are then moved to the gauge of the smallest
# corrections, robust_gauge); at 1e-6 a point 100 m from its anchor costs 0.01 px^2, so it does
# not pull the shifts (the fine stage's 0.01 would pull them by tenths of a pixel when the
# pointing errors are tens of pixels and the anchors tens of metres off).
_COARSE_REGULARISER = 1e-6
# Each coarse round drops the observations further than this many times the round's median
# error (and at most coarse_threshold_px is kept at the end): true matches' errors follow a
# Rayleigh-like law whose 4 x median lies at 4.7 standard deviations.
_COARSE_REJECT = 4.0
# Coarse rounds at most: each one solves, rejects and shrinks the robust loss's scale; from
# pointing errors of 50 px the synthetic stacks settle in 3-5.
_COARSE_ROUNDS = 10
# The coarse solves stop at steps below this (px and m) or relative decreases of the cost below
# _COARSE_FTOL: their shifts only start the fine adjustment, which re-anchors and solves again
# (the iteratively reweighted steps of a robust loss converge linearly: to the fine
# adjustment's 1e-8 they took 25-30 evaluations per round on 10 views, 6-9 to this).
_COARSE_XTOL = 1e-3
_COARSE_FTOL = 1e-6
# Tie points per view that the coarse solves use (a seeded random sample, see _sample_points).
_COARSE_POINTS_PER_VIEW = 300
_COARSE_SEED = 0
# The gauge of smallest corrections: a robust fit of the unobservable motion to the shifts, with
# this scale (px), Huber's weights first (convex: a start that does not depend on the outliers),
# then Cauchy's (a view tens of pixels off among views a pixel or two off then weighs ~1e-3 of
# the others in where the scene is put, where Huber's would still move it by a fraction of a px).
_GAUGE_SCALE_PX = 1.0
_GAUGE_ITERATIONS = 30
# Cauchy's cost has a basin per group of views that some motion makes agree; from Huber's start
# it can settle in one where a single view is left uncorrected (10 views of a multi-date stack,
# four of the seven kept with pointing errors of 36-51 px: the scene moved by 21 m). So the
# motions that zero each pair of views' shifts are tried too: those under which the most views
# lie within _GAUGE_CONSENSUS_PX (the best _GAUGE_STARTS, and Huber's) start a Cauchy fit each,
# and the fit of least Cauchy cost is taken.
_GAUGE_CONSENSUS_PX = 3.0
_GAUGE_STARTS = 8
# Singular values of the fixed views' stacked Jacobians under this fraction of the largest are
# taken as zero: the motions along them are left to the other views (one fixed view leaves the
# motion along its line of sight).
_FIXED_RANK_TOL = 1e-6
# GAUGE_ALTITUDE_PRIOR_NOTE. Two motions can leave the views' shifts alike: in a stack of three
# views of which one is tens of pixels off, the motions that zero two views' shifts each leave one
# view tens of pixels off, and Cauchy's costs of those differ by a few tenths (bench_multidate
# one view per date seeds 18, 39 and 40, 3 views: one wrong choice put the scene 30-60 m under
# the RPCs' altitude range, and the DSMs 4.5-36 m off). What the images cannot tell, the prior
# range can (the RPCs' own, a DEM's or the user's: the scene lies within it): each fitted start's
# cost adds log(1 + (d / _GAUGE_OUTSIDE_SCALE_M)^2), d the distance (m) by which it puts the
# scene's median tie point outside that range (0 inside; ``altitude_prior``). A scene
# _GAUGE_OUTSIDE_SCALE_M outside weighs as much as one view 1 px off; one 15 m outside as a view
# 3 px off, so that agreeing views still outweigh a range a little off (a DEM's, say).
_GAUGE_OUTSIDE_SCALE_M = 5.0


def robust_gauge(P: np.ndarray, shifts: np.ndarray, point: np.ndarray,
                 fixed: Sequence[int] = (),
                 altitude_prior: tuple[float, float] | None = None) -> np.ndarray:
    """The unobservable motion ``dX`` (m) that makes the shifts ``shifts - A_v dX`` smallest
    (a robust fit of ``A_v dX`` to ``shifts``, ``A_v`` the Jacobians at ``point``, ENU m).

    A bundle adjustment fixes the scene only up to a 3-D motion (module docstring); this picks
    the solution whose corrections are smallest over the views: the RPCs of most views are
    taken as right on average, which is all a stack without ground control can say. The fit
    minimises Cauchy's cost (scale _GAUGE_SCALE_PX) from several starts (Huber's fit, and the
    motions that zero the shifts of the pairs of views most others agree with) and keeps the
    least costly: the largest group of views whose RPCs agree wins.

    ``fixed``: views whose RPCs are trusted (``BundleOptions.fixed_views``): the motion zeroes
    their shifts (least squares over them), and only what they leave free (the motion along the
    line of sight of a single fixed view) is fitted to the others as above.

    ``altitude_prior``: ``(lo, hi)``, the prior range's ends less the scene's height (its median
    tie point's up, m): the fitted starts' costs add ``log(1 + (d / _GAUGE_OUTSIDE_SCALE_M)^2)``,
    ``d`` the distance of ``dX_up`` outside ``[lo, hi]`` (where the images leave two choices
    alike, the one that keeps the scene in the range: GAUGE_ALTITUDE_PRIOR_NOTE). Not used with
    fixed views.
    """
    return _gauge_motion(_jacobians_at(P, point), np.asarray(shifts, np.float64), fixed,
                         altitude_prior)


def _jacobians_at(P: np.ndarray, point: Sequence[float]) -> np.ndarray:
    """(V, 2, 3) Jacobians of the cameras ``P`` (V, 3, 4) at one ENU ``point``."""
    V = P.shape[0]
    return projection_jacobian(P, np.arange(V), np.tile(np.asarray(point, np.float64), (V, 1)))[2]


def _gauge_motion(A: np.ndarray, shifts: np.ndarray, fixed: Sequence[int],
                  altitude_prior: tuple[float, float] | None = None) -> np.ndarray:
    """:func:`robust_gauge` on the Jacobians ``A`` (V, 2, 3) at its point."""
    V = A.shape[0]
    fixed = sorted(set(int(v) for v in fixed))
    if not fixed:
        return _robust_motion(A, shifts, altitude_prior)
    Af = A[fixed].reshape(-1, 3)
    x0 = np.linalg.lstsq(Af, shifts[fixed].ravel(), rcond=None)[0]
    _, sv, vt = np.linalg.svd(Af)
    rank = int(np.sum(sv > _FIXED_RANK_TOL * sv[0]))
    free = vt[rank:].T  # (3, r): the motions that leave the fixed views' shifts as they are
    others = [v for v in range(V) if v not in fixed]
    if free.shape[1] == 0 or not others:
        return x0
    t = _robust_motion(A[others] @ free, shifts[others] - A[others] @ x0)
    return x0 + free @ t


def in_gauge(P: np.ndarray, shifts: np.ndarray, point: np.ndarray,
             fixed: Sequence[int] = (),
             altitude_prior: tuple[float, float] | None = None) -> np.ndarray:
    """``shifts`` moved by the motion :func:`robust_gauge` picks: ``shifts - A_v dX`` (the
    residuals, to first order, are those of the original shifts)."""
    A = _jacobians_at(P, point)
    shifts = np.asarray(shifts, np.float64)
    return shifts - A @ _gauge_motion(A, shifts, fixed, altitude_prior)


def _robust_motion(A: np.ndarray, shifts: np.ndarray,
                   altitude_prior: tuple[float, float] | None = None) -> np.ndarray:
    """The parameters ``t`` (r,) of the motion that makes ``shifts - A @ t`` smallest in
    Cauchy's cost (``A`` (V, 2, r), ``shifts`` (V, 2)): :func:`robust_gauge`'s fit;
    ``altitude_prior`` (r = 3 only) as there."""
    V, r = A.shape[0], A.shape[2]
    M, b = A.reshape(-1, r), shifts.ravel()

    def reweighted(dX: np.ndarray, weights: str) -> np.ndarray:
        for _ in range(_GAUGE_ITERATIONS):
            norm = np.hypot(*(shifts - A @ dX).T) / _GAUGE_SCALE_PX
            if weights == "huber":
                w = np.where(norm <= 1.0, 1.0, 1.0 / np.maximum(norm, 1e-300))
            else:
                w = 1.0 / (1.0 + norm * norm)
            ww = np.repeat(np.sqrt(w), 2)
            new = np.linalg.lstsq(M * ww[:, None], b * ww, rcond=None)[0]
            step = float(np.abs(new - dX).max())
            dX = new
            if step < 1e-9:
                break
        return dX

    def cost(dX: np.ndarray) -> float:
        norm = np.hypot(*(shifts - A @ dX).T) / _GAUGE_SCALE_PX
        total = float(np.log1p(norm * norm).sum())
        if altitude_prior is not None:
            lo, hi = altitude_prior
            d = max(lo - dX[2], dX[2] - hi, 0.0) / _GAUGE_OUTSIDE_SCALE_M
            total += math.log1p(d * d)
        return total

    starts = [reweighted(np.linalg.lstsq(M, b, rcond=None)[0], "huber")]
    if V >= 3:
        v, w = np.triu_indices(V, 1)
        Mp = np.concatenate([A[v], A[w]], axis=1)  # (pairs, 4, r)
        bp = np.concatenate([shifts[v], shifts[w]], axis=1)  # (pairs, 4)
        MtM = np.einsum("pki,pkj->pij", Mp, Mp)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = np.linalg.cond(MtM) < 1e12  # two views of one pass see the motion alike
        if ok.any():
            rhs = np.einsum("pki,pk->pi", Mp[ok], bp[ok])
            fits = np.linalg.solve(MtM[ok], rhs[..., None])[..., 0]
            off = np.hypot(*(shifts[None] - np.einsum("vai,pi->pva", A, fits)).transpose(2, 0, 1))
            agree = (off <= _GAUGE_CONSENSUS_PX).sum(axis=1)
            order = np.lexsort((off.sum(axis=1), -agree))[:_GAUGE_STARTS]
            starts += [fits[k] for k in order]
    fitted = [reweighted(start, "cauchy") for start in starts]
    return min(fitted, key=cost)


def _scene_height(P: np.ndarray, obs: Observations, X: np.ndarray) -> float:
    """The median up (m) of the points ``X``, each weighed by how well its views fix its height
    (``1 / variance_up``, :func:`point_covariances`): two views along nearly one line of sight
    triangulate their wrong and right matches alike hundreds of metres off (bench_multidate one
    view per date seed 39, 3 views: 84 of 142 tie points of such a pair, 166 m per pixel)."""
    w = 1.0 / point_covariances(P, obs, X)[:, 2, 2]
    if not np.any(w > 0.0):
        return float(np.median(X[:, 2]))
    order = np.argsort(X[:, 2])
    cum = np.cumsum(w[order])
    return float(X[order[np.searchsorted(cum, 0.5 * cum[-1])], 2])


def _sample_points(obs: Observations, per_view: int, seed: int) -> np.ndarray:
    """(N,) bool: a random sample of the points holding, for each view, ``per_view`` of the
    points it sees (all of them when it sees fewer): every view stays tied, and the sample's
    size grows with the number of views, not with the tracks' lengths."""
    key = np.random.default_rng(seed).random(obs.n_points)
    pick = np.zeros(obs.n_points, dtype=bool)
    for v in np.unique(obs.view):
        mine = np.unique(obs.point[obs.view == v])
        pick[mine[np.argsort(key[mine])[:per_view]]] = True
    return pick


def adjust_coarse(cameras: Sequence[Any], obs: Observations,
                  options: BundleOptions = BundleOptions(), *,
                  fixed: Sequence[int] = (),
                  prior_range_up: tuple[float, float] | None = None) -> BundleSolution:
    """Principal-point shifts of any size (tens of pixels) from raw tie points, robustly.

    Nothing here assumes the cameras are within a few pixels: the tracks are triangulated with
    the original cameras (a pointing error moves those points by metres, and leaves errors of
    the order of the pointing errors), then rounds of robust Levenberg-Marquardt solves (soft L1
    loss whose scale starts at the median error and shrinks with it), each followed by the
    rejection of observations further than ``_COARSE_REJECT`` times the median error, until the
    threshold reaches ``options.coarse_threshold_px`` (one last solve follows). The solves run
    on a sample of the tracks (``_COARSE_POINTS_PER_VIEW`` per view: the shifts need a few
    hundred tie points per view, and long tracks cost the square of their length). The anchors
    weigh almost nothing (``_COARSE_REGULARISER``); the shifts are put in the gauge of smallest
    corrections (:func:`robust_gauge`; ``fixed``: the views whose shifts it holds at zero;
    ``prior_range_up``: the ends of the prior altitude range as up coordinates of the cameras'
    frame, which choose between motions the images leave alike: GAUGE_ALTITUDE_PRIOR_NOTE).
    Every track is then triangulated with the corrected
    cameras, and its observations further than ``coarse_threshold_px`` are dropped: the
    solution's ``obs`` are those kept, its points their triangulation. The fine adjustment
    (:func:`adjust_observations`) follows, from cameras corrected by these shifts. Views left
    with fewer than ``options.min_observations`` observations are not an error here: the caller
    reads ``obs`` and drops them.
    """
    P = projection_stack(cameras)
    V = P.shape[0]
    full, _ = _anchors(P, obs, math.inf)
    shifts = np.zeros((V, 2))
    if full.n_points == 0:
        empty = np.zeros(0)
        return BundleSolution(shifts=shifts, points=np.zeros((0, 3)), anchors=np.zeros((0, 3)),
                              obs=full, errors_before=empty, errors_after=empty, evaluations=())
    sub = full.subset(_sample_points(full, _COARSE_POINTS_PER_VIEW, _COARSE_SEED)[full.point])
    anchors = triangulate_observations(sub, P)[0]
    X = anchors.copy()
    floor = options.coarse_threshold_px
    scale = max(options.loss_scale_px, float(np.median(_errors(P, sub, X, shifts))))
    evaluations = []
    final = False
    for _ in range(_COARSE_ROUNDS):
        o = options.replace(regulariser=_COARSE_REGULARISER, loss="soft_l1",
                            loss_scale_px=scale)
        shifts, X, nfev = _solve(P, sub, anchors, shifts, X, o, ftol=_COARSE_FTOL, xtol=_COARSE_XTOL)
        evaluations.append(nfev)
        if final:
            break
        err = _errors(P, sub, X, shifts)
        median = float(np.median(err))
        threshold = max(floor, _COARSE_REJECT * median)
        sub = sub.subset(err <= threshold)
        if sub.n_points == 0:
            break
        anchors = triangulate_observations(sub, P)[0]
        X = triangulate_observations(sub, _shifted(P, shifts))[0]
        final = threshold <= floor
        scale = max(options.loss_scale_px, min(scale, median))
    if sub.n_points:
        prior = None
        if prior_range_up is not None:
            height = _scene_height(_shifted(P, shifts), sub, X)
            prior = tuple(float(u) - height for u in prior_range_up)
        shifts = in_gauge(P, shifts, X.mean(axis=0), fixed, prior)
    # Every track, with the corrected cameras: the observations within the threshold.
    X = triangulate_observations(full, _shifted(P, shifts))[0]
    full = full.subset(_errors(P, full, X, shifts) <= floor)
    X = triangulate_observations(full, _shifted(P, shifts))[0]
    anchors = triangulate_observations(full, P)[0]
    before = _errors(P, full, anchors, np.zeros((V, 2)))
    after = _errors(P, full, X, shifts)
    return BundleSolution(shifts=shifts, points=X, anchors=anchors, obs=full, errors_before=before,
                          errors_after=after, evaluations=tuple(evaluations))


@dataclasses.dataclass(frozen=True)
class ShiftUncertainty:
    """How well the tie points fix the shifts (:func:`shift_uncertainty`), px one sigma."""

    sigma: np.ndarray  # (V,) per view, along its worst direction (inf without observations)
    worst_sigma: float  # along the least determined direction of all the shifts
    worst_view: int  # the view that carries most of that direction


def shift_uncertainty(cameras: Sequence[Any], obs: Observations, points: np.ndarray,
                      shifts: np.ndarray) -> ShiftUncertainty:
    """The uncertainty (px, one sigma) of the shifts that the tie points leave.

    From the adjustment's normal equations with the points eliminated (the shifts' 2V x 2V
    information), the unobservable motion taken out (the directions ``-A_v dX`` of all views
    together, ``A_v`` at the points' centroid: the covariance is that of the gauge of smallest
    shifts) and the observation noise estimated from the residuals. A view tied by enough
    tracks is known to a few hundredths of a pixel. One tied only by two-view tracks with a
    single other view is not tied along that pair's epipolar lines (that component is the height
    of the pair's points): the least determined direction of the shifts is then that view's
    shift along those lines, with a large sigma, and ``worst_view`` names it. Views without
    observations get inf.
    """
    P = projection_stack(cameras)
    V = P.shape[0]
    lin = _linearise(observation_entries(P, obs.view), obs, points, shifts)
    dof = 2 * len(lin.rc) - 3 * obs.n_points - (2 * V - 3)
    squares = float((lin.rc ** 2).sum() + (lin.rr ** 2).sum())
    sigma0 = math.sqrt(squares / dof) if dof > 0 else math.inf
    # A tiny weight per point (1e-9 px^2/m^2) keeps the 3 x 3 blocks of degenerate tracks regular.
    ones = np.ones(len(lin.rc))
    H = _reduced_hessian(V, obs, *lin.jacobians(), ones, ones, np.full((obs.n_points, 3), 1e-9),
                         0.0)[0]
    A = projection_jacobian(P, np.arange(V), np.tile(points.mean(axis=0), (V, 1)))[2]
    Q = np.linalg.svd(A.reshape(-1, 3), full_matrices=True)[0][:, 3:]  # complement of the gauge
    lam, U = np.linalg.eigh(Q.T @ H @ Q)
    lam = np.maximum(lam, 1e-300)
    W = Q @ U  # (2V, 2V - 3): the observable directions, least determined first
    C = (W / lam) @ W.T
    sigma = np.full(V, np.inf)
    for v in np.flatnonzero(np.bincount(obs.view, minlength=V) > 0):
        block = C[2 * v:2 * v + 2, 2 * v:2 * v + 2]
        sigma[v] = sigma0 * math.sqrt(max(float(np.linalg.eigvalsh(block).max()), 0.0))
    worst = W[:, 0].reshape(V, 2)
    return ShiftUncertainty(sigma=sigma, worst_sigma=sigma0 / math.sqrt(float(lam[0])),
                            worst_view=int(np.argmax((worst * worst).sum(axis=1))))


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
    return _jacobians_at(projection_stack(cameras), point)


# -- the whole step ------------------------------------------------------------------------------
def _view_cameras(cameras: Any) -> tuple[list[Any], list[str] | None]:
    """Per-view PerspectiveCameras and names from a CameraSet or a sequence of cameras."""
    views = getattr(cameras, "views", None)
    if views is not None:
        return [v.camera for v in views], [os.path.basename(v.path) for v in views]
    return list(cameras), None


def _match_all(feats: list[tuple[np.ndarray, np.ndarray]], cams: list[Any],
               sparse_options: SparseOptions) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Verified matches of every pair of views (a reference for the pair graph's choice)."""
    out = {}
    V = len(feats)
    for i in range(V):
        for j in range(i + 1, V):
            F = (fundamental_from_cameras(cams[i], cams[j])
                 if sparse_options.geometric_model == "cameras" else None)
            out[(i, j)] = match_pair(feats[i][1], feats[j][1], feats[i][0], feats[j][0],
                                     sparse_options, fundamental=F)
    return out


def adjust_principal_points(
    cameras: Any,
    images: Sequence[np.ndarray],
    options: BundleOptions = BundleOptions(),
    sparse_options: SparseOptions = SparseOptions(),
    names: Sequence[str] | None = None,
) -> tuple[Any, BundleReport]:
    """Correct the pointing errors of the views: features, pair graph, matches, tracks, coarse
    then fine bundle adjustment (:func:`satsweep.sparse.stage.tie_views`; the sparse stage does
    the same over crops of a prior range and also gives the altitude range).

    ``cameras``: a :class:`satsweep.camera.CameraSet` or a sequence of
    :class:`satsweep.camera.PerspectiveCamera`; ``images``: the views' tonemapped float32 images
    (``satsweep.imageio.tonemap``) in the pixels the cameras refer to (the AOI crops, or the
    skew-corrected images for skew-corrected cameras). Returns the adjusted cameras, of the same
    kind as given (a CameraSet gets its views' cameras and plane-plus-parallax projections
    replaced), and the report. ``names`` default to the image file names of a CameraSet, else
    "view 0", "view 1", ...

    Every view must be tied: raises CameraError naming each view that cannot be, and why (too
    few SIFT features: a blank image; too few verified matches with the others: another place;
    too few tie points after outlier rejection; a correction the tie points do not fix).
    """
    from satsweep.sparse.graph import aoi_samples
    from satsweep.sparse.stage import tie_views

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
    samples = None
    if getattr(cameras, "views", None) is not None:
        alt = cameras.alt_range
        samples = aoi_samples(cameras.frame, cameras.aoi, (alt.min, alt.mid, alt.max))
    tied = tie_views(images, cams, names, sparse_options, options, samples=samples)
    if tied.dropped:
        raise CameraError("cannot adjust the principal points: "
                          + "; ".join(d.message() for d in tied.dropped))
    if len(tied.kept) != V:  # pragma: no cover - tie_views drops with a reason
        raise CameraError("cannot adjust the principal points: the views could not be tied")
    fine = tied.fine
    report = BundleReport(
        names=tuple(names),
        n_features=tied.n_features,
        n_matches=tuple((i, j, k) for (i, j), k in tied.matches.items()),
        min_matches=sparse_options.min_matches,
        n_tracks=tied.n_tracks,
        track_length_histogram=tied.track_length_histogram,
        n_refine_dropped=tied.n_refine_dropped,
        n_points=fine.obs.n_points,
        n_observations=tuple(int(c) for c in np.bincount(fine.obs.view, minlength=V)),
        reproj_before_px=(float(np.median(tied.errors_before)), float(np.mean(tied.errors_before))),
        reproj_after_px=(float(np.median(fine.errors_after)), float(np.mean(fine.errors_after))),
        principal_point_shift_px=tuple((float(a), float(b)) for a, b in tied.shifts),
        regulariser=options.regulariser,
        solver_evaluations=tied.coarse.evaluations + fine.evaluations,
        seconds=dict(tied.seconds),
    )
    return shift_principal_points(cameras, tied.shifts), report


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
