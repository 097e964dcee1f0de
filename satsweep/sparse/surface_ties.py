"""Pointing corrections refined on tie points of the reconstructed surface.

The sparse stage ties the views on SIFT matches. Between views of different dates those are few
(shadows, seasons and radiometry change the descriptors): a stack of three views of three dates
keeps 50-80 observations per view, and its corrections are then uncertain by 0.04-0.11 px (the
stage's ``correction_sigma_px``), left 0.05-0.11 px off after the gauge on the one-per-date stacks
of ``tools/bench_multidate.py``. Once a first DSM exists, every textured cell of it is a tie
point whose place is known in every view: the Ames Stereo Pipeline's "matches from disparity"
for its bundle adjustment, done here on the fused surface. Each cell of a regular sample of the
DSM's consensus (holes left out) is projected into every view with the corrected cameras, its
observations registered to its first one by the sparse stage's own registration
(:func:`satsweep.sparse.tracks.register_observations`: the ground-plane homography, Lucas-Kanade,
the Lanczos sub-pixel step, local contrast between dates, windows beside edges), the best
registered kept (:func:`satsweep.sparse.tracks.best_registered`) and the principal points
adjusted on them alone (:func:`satsweep.sparse.bundle.adjust_observations`, the loss of the
sparse stage's extended ties). The anchors hold the points where the first DSM put them, so the
scene does not move: the shifts found are what the corrections lacked. Each view's shift is
weighed against its sparse correction by their uncertainties (:func:`blended_shifts`; the
surface's with SURFACE_BIAS_PX and :func:`half_spread` added), and the dense stages run again
with the result
(:func:`satsweep.pipeline.area.run_area`).

The first observation of each point cycles over the views, so that no view's pixels set every
track. Measured on ``tools/bench_multidate.py``'s nine families (328 runs; docs/measurements.md,
sixty-seventh session): the worst view after the gauge over 0.05 px on 13 runs before, 3 after
(two views tied of three, which the refinement leaves; 0.113 -> 0.057 and 0.080 -> 0.052 px);
30 refined runs more than 0.01 px better, 3 worse (to 0.014-0.030 px); the families' mean DFC
MAE within -0.029 / +0.030 m, every range as it was.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.sparse.bundle import BundleOptions, adjust_observations, shift_uncertainty
from satsweep.sparse.options import SparseOptions
from satsweep.sparse.tracks import Observations, best_registered, register_observations
from satsweep.sparse.triangulation import project, projection_stack

# Fewest views the refinement runs on: with two, a correction along the pair's epipolar lines is
# a height of the scene (part of the motion no image sees), and the pairs of one pass keep
# their sparse stage's corrections (tools/bench_e2e.py's figures as they were).
MIN_VIEWS = 3
# The surface's shifts are not as certain as their residuals say: registrations between dates
# keep a bias of a few hundredths of a pixel per pair of views (moved shadows and shading; the
# twenty-eighth session measured 0.025-0.041 px on tie points within 0.3 px of the truth,
# docs/measurements.md), which hundreds of tie points do not average out. Each view's shift is
# weighed against the sparse stage's correction by their inverse variances (blended_shifts),
# the surface's with this bias added in quadrature. Measured on the 20 one-per-date runs the
# refinement changed most (sixty-seventh session): the worst view after the gauge over the 20
# at most 0.068 px with the surface alone (three over 0.05), 0.053 / 0.046 / 0.052 px with 0 /
# 0.02 / 0.03 px here (one, none, one over 0.05); the sparse stage's alone 0.113 (twelve over).
SURFACE_BIAS_PX = 0.02
# HALF_SPREAD_NOTE. A bias of the registrations that differs from place to place shows where
# the shifts are adjusted on two halves of the surface apart (half_spread); half their
# difference is added to the surface's uncertainty in quadrature before the blend. The 0.3 m,
# 8-bit stack of one view per date, seed 56 at 5 views (the sixty-seventh session's one
# regression): halves 0.07-0.27 px apart (0.27 and 0.16 px in the two views the surface moved
# wrongly), its residuals' sigma 0.015 px; one view per date seed 8 at 3 views, whose surface
# was right: 0.01-0.06 px apart.
# Fewest registered observations per view the adjustment needs ([bundle] min_observations is
# the sparse stage's; the surface gives hundreds per view or none where a view sees no texture).
MIN_OBSERVATIONS = 50


@dataclasses.dataclass(frozen=True)
class SurfaceTies:
    """What :func:`surface_ties` found: per view the shift (px, in the pixels of the cameras it
    was given) to add to its correction and the shift's uncertainty (px, one sigma), with the
    counts and the time."""

    shifts: np.ndarray  # (V, 2) (dcx, dcy) px
    sigma: np.ndarray  # (V,) px, from the residuals
    spread: np.ndarray  # (V,) px, half the largest difference between the shifts of two halves
    # of the surface (half_spread)
    points: int  # surface points projected into the views
    registered: int  # points that kept two or more registered observations
    observations: tuple[int, ...]  # per view, observations the adjustment kept
    reprojection_median_px: float  # after the adjustment
    seconds: float


def surface_points(dsm: np.ndarray, x_centres: np.ndarray, y_centres: np.ndarray, epsg: int,
                   frame: Any, count: int) -> np.ndarray:
    """ENU points (N, 3) of ``frame`` of about ``count`` cells of ``dsm`` (heights above the
    ellipsoid, NaN where none) on a regular stride over its grid, whose column and row centres
    (map metres, CRS ``epsg``) are ``x_centres`` and ``y_centres``. Only cells with a height."""
    from satsweep.geometry.geodesy import crs_to_lonlat

    dsm = np.asarray(dsm)
    finite = np.isfinite(dsm)
    n = int(finite.sum())
    if n == 0 or count <= 0:
        return np.zeros((0, 3))
    stride = max(1, int(round(math.sqrt(n / count))))
    rows, cols = np.nonzero(finite[::stride, ::stride])
    rows, cols = rows * stride, cols * stride
    lon, lat = crs_to_lonlat(x=np.asarray(x_centres)[cols], y=np.asarray(y_centres)[rows],
                             epsg=epsg)
    e, nn, u = frame.from_geodetic(lon=lon, lat=lat, alt=dsm[rows, cols].astype(np.float64))
    return np.column_stack([e, nn, u])


def surface_observations(P: np.ndarray, shapes: Sequence[tuple[int, int]], points: np.ndarray,
                         margin_px: float, valid: Sequence[np.ndarray | None] | None = None
                         ) -> Observations:
    """Each of ``points`` (N, 3) observed at its projection in every view of ``P`` (V, 3, 4) that
    holds it at least ``margin_px`` inside its image (``shapes``: (height, width)), in front of
    the camera, on a pixel that holds data (``valid``: per view a bool mask or None); point k's
    observations start with view k mod V (the view its others register to) and go round. Points
    seen by fewer than two views are left out."""
    V, N = P.shape[0], len(points)
    if N == 0 or V == 0:
        return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), 0)
    point = np.repeat(np.arange(N), V)
    view = (point + np.tile(np.arange(V), N)) % V  # point k: views k, k+1, ... mod V
    xy, depth = project(P, view, points[point])
    inside = depth > 0
    for v in range(V):
        sel = view == v
        h, w = shapes[v]
        x, y = xy[sel, 0], xy[sel, 1]
        ok = ((x >= margin_px) & (x <= w - 1 - margin_px) & (y >= margin_px)
              & (y <= h - 1 - margin_px))
        mask = None if valid is None else valid[v]
        if mask is not None:
            r = np.clip(np.rint(y), 0, h - 1).astype(np.int64)
            c = np.clip(np.rint(x), 0, w - 1).astype(np.int64)
            ok &= mask[r, c]
        inside[sel] &= ok
    return Observations(point, view, xy, N).subset(inside)


def surface_ties(cameras: Sequence[Any], images: Sequence[np.ndarray], points: np.ndarray, *,
                 sparse_options: SparseOptions = SparseOptions(),
                 bundle_options: BundleOptions = BundleOptions(),
                 names: Sequence[str] | None = None,
                 valid: Sequence[np.ndarray | None] | None = None,
                 threads: int = 1) -> SurfaceTies:
    """The principal-point shifts that tie the views on ``points`` (ENU, in the cameras' frame:
    :func:`surface_points`), module docstring. ``cameras``: objects with a 3x4 ``P`` in the
    pixels of ``images`` (tonemapped, in [0, 1]), as corrected as known; ``valid``: per view the
    pixels holding data (None: all). The registration takes ``sparse_options``' window,
    largest move, kept share and windows beside; the adjustment ``bundle_options`` with its
    extended loss. Raises CameraError when a view keeps fewer than MIN_OBSERVATIONS."""
    from satsweep.sparse.stage import registration_window_px

    t0 = time.perf_counter()
    V = len(cameras)
    if len(images) != V:
        raise CameraError(f"surface_ties: {V} cameras, {len(images)} images")
    if V < MIN_VIEWS:
        raise CameraError(f"surface_ties: {V} views (needs {MIN_VIEWS} or more)")
    names = [f"view {v}" for v in range(V)] if names is None else list(names)
    o = sparse_options
    window_px = registration_window_px(cameras, o)
    P = projection_stack(cameras)
    obs = surface_observations(P, [np.shape(im) for im in images], np.asarray(points, np.float64),
                               window_px + o.refine_max_shift_px + 1.0, valid)
    registered, residual, _ = register_observations(
        obs, images, cameras, window_px=window_px, max_shift_px=o.refine_max_shift_px,
        keep_fraction=o.refine_keep_fraction, threads=threads, beside_px=o.refine_beside_px)
    kept = best_registered(registered, residual, o.refine_keep_fraction)
    options = bundle_options.replace(loss=bundle_options.extended_loss,
                                     loss_scale_px=bundle_options.extended_loss_scale_px,
                                     min_observations=MIN_OBSERVATIONS)
    solution = adjust_observations(cameras, kept, options, names=names)
    certainty = shift_uncertainty(cameras, solution.obs, solution.points, solution.shifts)
    return SurfaceTies(shifts=solution.shifts, sigma=np.asarray(certainty.sigma, np.float64),
                       spread=half_spread(cameras, solution, options, names),
                       points=len(points), registered=int(kept.n_points),
                       observations=tuple(int(k) for k in np.bincount(solution.obs.view,
                                                                      minlength=V)),
                       reprojection_median_px=float(np.median(solution.errors_after)),
                       seconds=time.perf_counter() - t0)


def half_spread(cameras: Sequence[Any], solution: Any, options: BundleOptions,
                names: Sequence[str]) -> np.ndarray:
    """Per view (V,), half the largest difference (px) between its shifts adjusted on the
    points west and east of the points' median, or south and north of it (``solution``: the
    adjustment on all of them, :func:`satsweep.sparse.bundle.adjust_observations`; a split
    whose half leaves a view too few observations counts for nothing). What the residuals do not
    show: a surface whose registrations between dates are biased, differently in different
    places (moved shadows, a view's own shading), gives halves that disagree by tenths of a
    pixel where their residuals fix each to hundredths (HALF_SPREAD_NOTE)."""
    V = len(cameras)
    spread = np.zeros(V)
    X = solution.points[solution.obs.point]
    for axis in (0, 1):  # east, north
        first = X[:, axis] <= np.median(solution.points[:, axis])
        try:
            a = adjust_observations(cameras, solution.obs.subset(first), options, names=names)
            b = adjust_observations(cameras, solution.obs.subset(~first), options, names=names)
        except CameraError:
            continue
        spread = np.maximum(spread, np.hypot(*(a.shifts - b.shifts).T) / 2.0)
    return spread


def blended_shifts(shifts: np.ndarray, surface_sigma: np.ndarray, sparse_sigma: np.ndarray,
                   bias_px: float = SURFACE_BIAS_PX) -> tuple[np.ndarray, np.ndarray]:
    """The shifts (V, 2) to add to the sparse stage's corrections: each view's surface ``shifts``
    weighed against its sparse correction (which the shift moves away from) by their inverse
    variances, the surface's ``surface_sigma`` with ``bias_px`` added in quadrature, the sparse
    stage's ``sparse_sigma`` (px, one sigma per view; inf for an unknown one: the surface's
    shift whole). Returns the shifts and each view's weight of the surface (0..1)."""
    sparse_var = np.asarray(sparse_sigma, np.float64) ** 2
    surface_var = np.asarray(surface_sigma, np.float64) ** 2 + float(bias_px) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.where(np.isinf(sparse_var), 1.0, sparse_var / (sparse_var + surface_var))
    weight = np.where(np.isfinite(weight), weight, 0.0)
    return np.asarray(shifts, np.float64) * weight[:, None], weight
