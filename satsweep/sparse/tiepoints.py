"""The altitude range of the sparse stage's adjusted tie points: the scene's heights when the
user gives none.

Without ``--alt-range`` or ``--dem``, the only prior on the scene's heights is the RPCs' height
offset +- scale, which spans kilometres (-20..2610 m for the Pleiades pair, whose ground lies
between about 2270 and 2376 m): thousands of planes. As S2P estimates its disparity range from
SIFT matches, satsweep bounds the heights of the sparse stage's tie points
(:mod:`satsweep.sparse.stage`: matched between the views cropped at that coarse range,
triangulated with the cameras the adjustment corrects): their reprojection errors weed out wrong
matches across views, and :func:`altitude_range_from_points` is robust to those left.

(Until then the 1% and 99% quantiles of every pair's matches triangulated with the raw RPCs
served: on issue 26's 19-view WorldView-3 stack, wrong matches among its 171 pairs spread those
altitudes from -491 to +586 m, and the quantiles swept -82..+46 m for a scene of -27..+30 m.)
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.sparse.triangulation import base_to_height

# Points above the supported top that are checked against the views, highest first.
MAX_CONFIRM_CANDIDATES = 16
# Fewest points of fewer than altitude_floor_views views that can set the floor (with the
# fraction altitude_floor_fewer_fraction of them; and the fewest of all points where too few
# are of that many views and all of them serve): wrong two-view matches agree in twos and
# threes by chance (a 5-view multi-date stack: two of 136 within 3 m of each other at 11 m, 89 m
# under the ground), a ground seen by two views at a time in dozens.
FEWER_VIEWS_MIN_SUPPORT = 5
# Tie points closer than this (m) to a point before them are one point to the range: SIFT gives a
# keypoint one descriptor per dominant orientation at the same position, and a match of such
# twins in two views makes two tracks that triangulate to one spot, so that one wrong match
# supported itself (a 5-view stack of one view per date, tools/bench_multidate.py --dates 20
# seed 33 at 33.45 S: its floor at 69.5 m, 30 m under the ground, held by two such twins).
DUPLICATE_POINT_M = 0.01
# TOP_VIEW_SETS_NOTE. Where TOP_VIEW_SETS_MIN_VIEWS views or more are tied, a top whose support
# comes from points of one set of views only (one pair), above the highest supported by two
# sets (two pairs, or a pair and a longer track), stands only where the views outside that set
# confirm it (the confirmation of the lone points above the top): the wrong matches of one pair
# on a repeated pattern share a height and a place. On ten views of one date each
# (tools/bench_multidate.py seed 39 --dates 10, 8-bit RGB at 33.45 S) points of one pair held a
# top at 379 m over a town whose roofs end at 158 m (range 95..379 m, 95..165 with the rule). A
# small stack's top roof is often held by one pair only, and the views of other dates do not
# confirm it: with the rule from 4 views, 5 views of v10 seed 4 lost theirs (range 96..165 ->
# 96..150 m for a truth of 99..152, DFC MAE 1.42 -> 3.20 m); hence 8. Two pairs with a view in
# common are one set for this (their wrong matches share that view's pattern): on a 19-view
# issue-form stack (seed 75) points of views 9-12 and 9-13, 10 m apart, held a top at 228 m
# over roofs that end at 160 m (range 95.6..243.0 m; 95.6..179.7 m when they count as one, the
# views denying the top). A track of three views or more and another set count as two.
TOP_VIEW_SETS_MIN_VIEWS = 8


def supported_extremes(alt: np.ndarray, support: int, window_m: float) -> tuple[float, float]:
    """The lowest and the highest altitudes at which ``support`` values lie within ``window_m``.

    ``lo`` is the lowest ``a`` with at least ``support`` altitudes in ``[a, a + window_m]``,
    ``hi`` the highest with as many in ``[a - window_m, a]``: a wrong match has a height of its
    own, while the ground and each roof hold several tie points at nearly the same height.
    Falls back to the extremes when no altitude has that support (fewer values than it)."""
    a = np.asarray(alt, np.float64)
    lo = lowest_supported(a, support, window_m)
    neg_hi = lowest_supported(-a, support, window_m)  # the highest, seen upside down
    return float(a.min() if lo is None else lo), float(a.max() if neg_hi is None else -neg_hi)


def lowest_supported(alt: np.ndarray, support: int, window_m: float) -> float | None:
    """The lowest altitude ``a`` with at least ``support`` values in ``[a, a + window_m]``, or
    None when no altitude has that support."""
    a = np.sort(np.asarray(alt, np.float64))
    above = np.searchsorted(a, a + window_m, side="right") - np.arange(len(a))
    ok = np.flatnonzero(above >= support)
    return float(a[ok[0]]) if ok.size else None


def highest_supported_near(alt: np.ndarray, xy: np.ndarray, support: int, window_m: float,
                           radius_m: float, *, view_members: np.ndarray | None = None,
                           min_view_sets: int = 1) -> float | None:
    """The highest altitude ``a`` of a point with at least ``support`` points (itself included)
    within ``window_m`` under it and within ``radius_m`` of it horizontally (``xy`` (N, 2)
    metres; ``radius_m`` 0: anywhere), or None when no point has that support. With
    ``min_view_sets`` 2 and ``view_members`` ((N, V) bool: the views that observe each point),
    those points must hold two sets of views that count as two: without a view in common, or
    different with one of them of three views or more (TOP_VIEW_SETS_NOTE)."""
    if min_view_sets not in (1, 2):
        raise ValueError(f"min_view_sets = {min_view_sets!r}: 1 or 2")
    if min_view_sets == 2 and view_members is None:
        raise ValueError("min_view_sets = 2 needs view_members")
    a = np.asarray(alt, np.float64)
    order = np.argsort(-a, kind="stable")
    a, xy = a[order], np.asarray(xy, np.float64)[order]
    members = None if min_view_sets == 1 else np.asarray(view_members, bool)[order]
    # points k..end[k]-1 lie within window_m under point k (sorted by decreasing altitude)
    end = np.searchsorted(-a, -(a - window_m), side="right")
    for k in np.flatnonzero(end - np.arange(len(a)) >= support):
        near = np.arange(k, end[k])
        if radius_m > 0.0:
            near = near[np.hypot(*(xy[near] - xy[k]).T) <= radius_m]
        if len(near) < support:
            continue
        if members is None:
            return float(a[k])
        m = members[near].astype(np.int32)
        shared, views = m @ m.T, m.sum(axis=1)
        longer = np.maximum(views[:, None], views[None, :])
        if ((shared == 0) | ((shared < longer) & (longer >= 3))).any():
            return float(a[k])
    return None


def view_members(obs, n_points: int) -> np.ndarray:
    """(n_points, V) bool: which of the V views (those ``obs`` names) observe each point."""
    out = np.zeros((n_points, int(np.max(obs.view)) + 1 if len(obs.view) else 0), dtype=bool)
    out[np.asarray(obs.point), np.asarray(obs.view)] = True
    return out


def _near_aoi(points: np.ndarray, frame, aoi: AOI, margin_m: float) -> np.ndarray:
    """Which ENU ``points`` lie within ``margin_m`` of the AOI (its ENU bounding box, grown)."""
    lon, lat = aoi.boundary()
    e, n, _ = frame.from_geodetic(lon=lon, lat=lat, alt=np.zeros(lon.shape))
    return ((points[:, 0] >= e.min() - margin_m) & (points[:, 0] <= e.max() + margin_m)
            & (points[:, 1] >= n.min() - margin_m) & (points[:, 1] <= n.max() + margin_m))


def _duplicates(points: np.ndarray) -> np.ndarray:
    """Mask of the points within DUPLICATE_POINT_M (per ENU axis) of a point before them."""
    dup = np.zeros(len(points), dtype=bool)
    if len(points) < 2:
        return dup
    finite = np.isfinite(points).all(axis=1)
    keys = np.round(np.asarray(points, np.float64)[finite] / DUPLICATE_POINT_M).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    rows = np.flatnonzero(finite)
    dup[rows] = True
    dup[rows[first]] = False
    return dup


def altitude_range_from_points(points: np.ndarray, obs, point_error: np.ndarray, frame, aoi: AOI,
                               options, *, within: AltitudeRange | None = None,
                               confirm: Callable[[int, float], bool] | None = None,
                               point_covariances: np.ndarray | None = None
                               ) -> tuple[AltitudeRange | None, dict]:
    """The altitude range of adjusted tie points (the sparse stage's), and a record of it.

    ``points`` (N, 3): ENU points (m) of ``frame``; ``obs``: their observations (to count the
    views of each); ``point_error`` (N,): each point's largest reprojection error (px) with the
    corrected cameras; ``options``: SparseOptions; ``point_covariances`` (N, 3, 3): each point's
    for 1 px of error (:func:`satsweep.sparse.triangulation.point_covariances`), None when not
    known. The points used lie inside the AOI grown by ``altitude_aoi_margin_m`` with every
    error within ``altitude_max_error_px`` and an effective base-to-height ratio
    (:func:`satsweep.sparse.triangulation.base_to_height`) of ``altitude_min_bh`` at least. The
    range runs from the lowest altitude of the points seen by ``altitude_floor_views`` views or more (all
    points when fewer than ``altitude_min_points`` are, with FEWER_VIEWS_MIN_SUPPORT of them
    agreeing at least; or that of the points of fewer views,
    when it lies more than ``altitude_margin_below_m`` lower and ``altitude_floor_fewer_fraction``
    of them, and FEWER_VIEWS_MIN_SUPPORT at least, share it within ``altitude_support_m``) to
    the highest of all, each the lowest
    or highest altitude supported by ``altitude_support`` points (or
    ``altitude_support_fraction`` of them) within ``altitude_support_m``
    (:func:`supported_extremes`), the highest's within ``altitude_support_radius_m`` of it
    horizontally too (:func:`highest_supported_near`: the points of one roof; two-view wrong
    matches share a height by chance anywhere: a 20-view stack's two at 163 and 161 m, 45 m
    apart, over a town whose top is at 126 m); ``confirm(i, below_m)``, when given, is asked
    about the points above that top, highest first (at most ``MAX_CONFIRM_CANDIDATES``), with
    ``below_m`` their height above the floor, and the first it accepts raises the top to its
    altitude (the sparse stage asks the views, :mod:`satsweep.sparse.verify`, down to the
    floor); both ends widened by ``altitude_margin_below_m`` and
    ``altitude_margin_above_m``, the margins kept ``within`` the prior range when they overlap
    it (an extreme past the prior is kept: :func:`_within_prior`).

    Why the two ends differ: a wrong match that two views accept anywhere along its epipolar
    line gets a height of its own, and more views bring more of them (a 20-view synthetic stack:
    points of two views down to 32 m below the ground, those of three views or more within 8 m
    of it); the ground is seen everywhere, by many views. The highest roofs are seen by few
    views (plain roofs have no features: only their corners, against the ground below), and on
    3-view stacks no point of three views comes within 5-44 m of the highest roof, while points
    of two views come within 1-13 m. Returns (None, record with a "reason") when fewer than
    ``altitude_min_points`` are usable.
    """
    o = options
    n_views = np.bincount(obs.point, minlength=len(points)) if len(points) else np.zeros(0, int)
    if len(points):
        alt = frame.to_geodetic(e=points[:, 0], n=points[:, 1], u=points[:, 2])[2]
        inside = _near_aoi(points, frame, aoi, o.altitude_aoi_margin_m) & np.isfinite(alt)
    else:
        alt = np.zeros(0)
        inside = np.zeros(0, dtype=bool)
    use = inside & (point_error <= o.altitude_max_error_px)
    vague = np.zeros(len(points), dtype=bool)
    if point_covariances is not None:
        vague = use & ~(base_to_height(point_covariances) >= o.altitude_min_bh)
        use &= ~vague
    twins = use & _duplicates(points)
    use &= ~twins
    floor = use & (n_views >= o.altitude_floor_views)
    all_points = bool(floor.sum() < o.altitude_min_points)
    if all_points:
        floor = use
    record: dict = {"source": "tie points", "tie_points": int(use.sum()),
                    "tie_points_for_the_lowest": int(floor.sum()),
                    "tie_points_near_aoi": int(inside.sum()),
                    "duplicate_tie_points": int(twins.sum()),
                    "vague_tie_points": int(vague.sum()),
                    "min_bh": o.altitude_min_bh,
                    "aoi_margin_m": o.altitude_aoi_margin_m,
                    "views_per_tie_point": {str(k): int(c) for k, c in
                                            enumerate(np.bincount(n_views[use])) if c},
                    "max_error_px": o.altitude_max_error_px}
    if use.sum() < o.altitude_min_points:
        record["reason"] = (f"only {int(use.sum())} adjusted tie points within "
                            f"{o.altitude_aoi_margin_m:g} m of the AOI (at least "
                            f"{o.altitude_min_points} are needed to bound its heights)")
        return None, record
    a = alt[use]

    def support(n: int) -> int:
        return max(o.altitude_support, math.ceil(o.altitude_support_fraction * n))

    floor_need = support(int(floor.sum()))
    lo = supported_extremes(alt[floor], floor_need, o.altitude_support_m)[0]
    if all_points:
        # Mostly points of fewer views then, whose wrong matches agree in twos by chance (8-bit
        # RGB at 33.45 S, one view per date seed 35 at 5 views: 11 of 91 points of three views,
        # two of two views at 7 m held a floor 91 m under the ground): a floor more than
        # altitude_support_m under the lowest that FEWER_VIEWS_MIN_SUPPORT of them hold is that.
        held = lowest_supported(alt[floor], max(floor_need, FEWER_VIEWS_MIN_SUPPORT),
                                o.altitude_support_m)
        if held is not None and lo < held - o.altitude_support_m:
            lo = held
    fewer = use & ~floor
    if fewer.any() and o.altitude_floor_fewer_fraction > 0.0:
        # A ground that few views tie (each date's texture differs: one view per date) leaves
        # the points of many views on the roofs; the points of fewer views then show it where a
        # good share of them agree on its height (wrong matches scatter theirs), below what the
        # margin adds to the floor of the points of many views.
        need = max(FEWER_VIEWS_MIN_SUPPORT,
                   math.ceil(o.altitude_floor_fewer_fraction * fewer.sum()))
        low = lowest_supported(alt[fewer], need, o.altitude_support_m)
        if low is not None and low < lo - o.altitude_margin_below_m:
            record["floor_from_fewer_views"] = {"altitude_m": low, "points": int(fewer.sum()),
                                                "support": need}
            lo = low
    # TOP_VIEW_SETS_NOTE: a top held by points of one set of views only (wrong matches of one
    # pair on a repeated pattern share a height and a place), over that of two sets, needs the
    # views' confirmation where the stack has TOP_VIEW_SETS_MIN_VIEWS views or more.
    tied_views = len(np.unique(obs.view[use[obs.point]])) if len(obs.view) else 0
    min_sets = 2 if tied_views >= TOP_VIEW_SETS_MIN_VIEWS else 1
    # (the views of each point are looked up only where two sets are asked for)
    members = view_members(obs, len(points))[use] if min_sets > 1 else None
    xy_use = points[use][:, :2]

    def top(need_sets: int) -> float | None:
        return highest_supported_near(a, xy_use, support(a.size), o.altitude_support_m,
                                      o.altitude_support_radius_m, view_members=members,
                                      min_view_sets=need_sets)

    hi = top(1)
    if min_sets > 1 and hi is not None:
        two = top(min_sets)
        if two is not None and two < hi:
            # a top held by one set of views stands where the views outside it confirm it
            # (satsweep.sparse.verify; without them, as before)
            i = int(np.flatnonzero(use & (alt == hi))[0])
            held = confirm is None or confirm(i, float(hi - lo))
            record["one_view_set_top"] = {"altitude_m": hi, "confirmed": bool(held)}
            if not held:
                hi = two
    hi = float(a.max()) if hi is None else hi
    record["supported_extremes_m"] = [lo, hi]
    if confirm is not None:
        # The points above the supported top, highest first: the first that other views
        # confirm raises it (a lone tower's roof; satsweep.sparse.verify).
        above = np.flatnonzero(use & (alt > hi + o.altitude_support_m))
        above = above[np.argsort(-alt[above])][:MAX_CONFIRM_CANDIDATES]
        tried = 0
        for tried, i in enumerate(above, start=1):
            if confirm(int(i), float(alt[i] - lo)):
                hi = float(alt[i])
                record["confirmed_top_m"] = hi
                break
        record["unsupported_points_tried"] = tried
    lo, hi = _within_prior(lo, hi, o.altitude_margin_below_m, o.altitude_margin_above_m, within)
    record.update({"min": lo, "max": hi,
                   "tie_point_altitudes_m": [float(x) for x in np.quantile(a, [0.0, 0.5, 1.0])]})
    return AltitudeRange(lo, hi), record


def _within_prior(lo: float, hi: float, below_m: float, above_m: float,
                  prior: AltitudeRange | None) -> tuple[float, float]:
    """The supported extremes ``lo``, ``hi`` widened by the margins, the margins cut at the
    ``prior`` (the RPCs' range) when the range overlaps it, the extremes themselves never: the
    prior holds the scene in the RPCs' frame, while the corrected cameras put it where the
    adjustment's gauge does, metres away when one view of a pair is a pixel or two off along the
    epipolar lines (a same-date pair of the v20 multi-date stacks, seed 1, views 7-8: supported
    ground at 89 m, the prior's floor at 95 m, and more than half of the sweep's pixels at that
    floor). Past the prior the margin is not added: on 5-view multi-date stacks the supported
    floor lies a few metres under the ground (two-view points), and a deeper range lets shadows
    match below it."""
    out_lo, out_hi = lo - below_m, hi + above_m
    if prior is None or not max(out_lo, prior.min) < min(out_hi, prior.max):
        return out_lo, out_hi
    return max(out_lo, min(prior.min, lo)), min(out_hi, max(prior.max, hi))
