"""The sparse stage: pointing corrections, the views that can be used, and the altitude range.

One pass over the views cropped at a prior altitude range (the user's, a DEM's, or the RPCs'
wide one) gives everything the dense stages need from tie points. An AOI smaller than
``min_extent_m`` is tied over the box of that side about it (``tie_aoi``: its cameras fitted
over the box, each view's SIFT budget grown with its crop, :func:`feature_budgets`), while the
pairs' overlaps and the altitude range stay the AOI's:

1. *Features*, once per view (SIFT, :mod:`satsweep.sparse.features`). A view with fewer than
   ``min_matches`` keypoints (blank, cloud, water) is dropped.
2. *Pair graph* (:mod:`satsweep.sparse.graph`): the candidate pairs (views that see a common
   part of the AOI), scored by overlap, base-to-height ratio and the matches of their strongest
   features; a spanning tree of the best pairs plus each view's ``pair_neighbours`` best ones
   are matched, not all V (V - 1) / 2 pairs. A view without candidates is dropped.
3. *Matching* of the selected pairs (:mod:`satsweep.sparse.matching`): ratio test, mutual
   check, and verification by the cameras' epipolar geometry up to one unknown offset per pair,
   found by RANSAC: a pointing error of any size is a translation of the whole image, which
   moves all of a pair's epipolar distances by nearly one offset. The threshold is widened by
   the two cameras' approximation errors (the cameras of a wide prior range are approximate).
   Views that the pairs with at least ``min_matches`` verified matches do not link to the
   largest group of views are matched with ``pair_repair`` more of their candidates. A group
   of such views (one date's acquisition, tied within itself) whose weaker pairs into the
   largest group (``_WEAK_PAIR_MIN`` matches or more each) hold three times ``min_matches``
   together is linked by them; the views still apart are dropped (another place, mostly cloud).
   A group held to the others by one such pair (a bridge) is matched with more candidates when
   its pairs into them are few, and adjusted on all of them, weak ones included.
4. *Tracks* (:mod:`satsweep.sparse.tracks`): the verified matches chained across views.
5. *Coarse correction* (:func:`satsweep.sparse.bundle.adjust_coarse`): a robust adjustment of
   one translation per view on the raw keypoints, with no assumption on the size of the
   pointing errors, put in the gauge of smallest corrections.
6. *Cameras for the fine adjustment*: the coarse tie points' altitudes bound the scene; the
   views' perspective cameras are fitted again over the AOI x that range (over the prior's
   kilometres an RPC is perspective to ~1 px only) and corrected by the coarse translations.
7. *Fine adjustment* (:func:`satsweep.sparse.bundle.adjust_observations`): of the coarse tie
   points, those that give each view ``fine_points_per_view`` observations, longest tracks
   first (:func:`satsweep.sparse.tracks.thin_points`: a stack of many views gathers long tracks
   and thousands of observations per view, which would make this step grow faster than the
   number of views), each also in the views that did not match it (at its projection, up to
   ``extend_points_per_view`` per view: SIFT matches few points between dates, whose patches are
   seen all the same; the tracks so extended thinned again to give each view at least that
   many observations, so that the registration's work too stays linear in the views),
   registered to a fraction of a pixel (Lucas-Kanade after a ground-plane warp; on local
   contrast in pairs of views whose grey levels differ, as another date's do; of each pair of
   views the best registered ``refine_keep_fraction``), then the principal-point bundle
   adjustment with the anchor regulariser (0.01 px^2/m^2) and a robust loss whose quadratic
   zone ends at 0.3 px (once the tracks are extended, a Cauchy loss from 0.1 px:
   ``extended_loss``, ``extended_loss_scale_px``), its
   anchors triangulated with the coarsely corrected cameras.
   A view left with fewer than ``min_observations`` observations, or carrying the least
   determined direction of the shifts when that is uncertain by more than
   ``max_shift_sigma_px`` (a view tied along one direction only), is dropped, and 7 runs again
   without it (and without the views it alone tied to the others), from the coarse solution
   restricted to the views left (4-6 run again only after a drop at step 5): no view is used
   with a correction that the tie points do not fix. When that direction is the motion of some views
   against the largest group of views tied in every direction by themselves (groups of
   different dates linked by a few tie points), those views are dropped together if that drops
   fewer than one view after another would.
8. *Altitude range* (:func:`satsweep.sparse.tiepoints.altitude_range_from_points`): every tie
   point the coarse adjustment kept, at its keypoints, triangulated with the corrected cameras;
   those inside the AOI whose reprojection errors are all within ``altitude_max_error_px``.
   The lowest end comes from the points of ``altitude_floor_views`` views or more, the highest
   from all, each an altitude that ``altitude_support`` points share within
   ``altitude_support_m`` (a wrong match has a height of its own), the highest's within
   ``altitude_support_radius_m`` of each other horizontally (one roof); the highest of the points
   above that top that views outside its track see where it lies raises it (a lone tower's
   roof, :mod:`satsweep.sparse.verify`); widened by the margins, which the prior range cuts
   (an end past the prior stays: the corrected cameras may put the scene there).

Corrections are translations in image pixels: a view's content of ground point X lies at
``RPC(X) + correction`` (the convention of the synthetic scenes' biases). A crop's pixels are the
full image's shifted by an integer offset, so the same translation moves the principal point of
any later crop's camera (:func:`satsweep.sparse.bundle.shift_principal_points`). They are known
up to the 3-D motion of the whole scene that no image measurement sees (see
:mod:`satsweep.sparse.bundle`); the stage reports them in the gauge of smallest corrections, and
the altitude range is that of the scene in the same gauge, i.e. where the corrected cameras put
it.

Figures (tools/bench_ba.py; synthetic stacks of 1000 px views with pointing errors drawn up to
50 px per axis, cropped at the RPCs' range widened by 300 m; 2 cores; seeds 0 and 1): the
worst correction within 0.022 px of the truth after the gauge on 3 views, 0.025 on 5, 0.018 on
10, 0.021 on 20; 0.50, 0.90, 1.74 and 3.44 s (20 views / 5 views: 3.8-3.85); every altitude
range held the truth. On the multi-date stacks of tools/bench_multidate.py (10 views of 384 px,
one to three per date, cropped at the RPCs' range as a reconstruction crops them) the tie points
between dates are less precise: 0.13 px for the worst view (mean over seeds 0-5; 0.21 before
the tracks were extended to every view), 0.045 px for the median one. The Pleiades pair (300 m
AOI, the RPCs' -20..2610 m): range 2261..2391 m from 959 tie points in 0.4 s (S2P's DSM spans
2274..2373 m).
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Sequence

import numpy as np

from satsweep.errors import CameraError, InputError, OptionsError
from satsweep.sparse.bundle import (
    BundleOptions,
    BundleSolution,
    TooFewObservations,
    adjust_coarse,
    adjust_observations,
    in_gauge,
    shift_principal_point,
    shift_uncertainty,
    track_median_errors,
)
from satsweep.sparse.features import detect_features, feature_scale_for
from satsweep.sparse.graph import PairGraph, aoi_samples, build_pair_graph, repair_pairs
from satsweep.sparse.matching import fundamental_from_cameras, match_pair
from satsweep.sparse.options import SparseOptions
from satsweep.sparse.tracks import (
    CONTRAST_RANK,
    Observations,
    best_registered,
    build_tracks,
    connected_labels,
    extend_tracks,
    observations_from_tracks,
    register_observations,
    thin_mask,
    thin_points,
)
from satsweep.sparse.triangulation import (point_covariances, project, projection_stack,
                                           triangulate_observations)
from satsweep.threads import map_in_threads

__all__ = ["DroppedView", "SparseResult", "TiedViews", "corrected_projections", "sparse_stage",
           "tie_point_confirmer", "tie_views"]

# The coarse tie points' altitudes bound the cube over which the fine cameras are fitted: their
# 1% and 99% quantiles widened by this margin (m). The coarse points carry the keypoints' noise
# and the prior cameras' approximation errors (metres of height); a cube too tall only costs
# approximation error (0.07 px over 300 m on the Pleiades pair, against 0.02 px over 80 m).
# FINE_CUBE_NOTE. Where fewer than [sparse] altitude_min_points of them lie in the tie box (a
# small AOI in crops that a wide prior makes whole images), all of them bound it: the prior's
# cameras, fitted over the RPCs' kilometre of heights, are the last resort only. Their frame's
# ground plane lies hundreds of metres under the scene, and the registration's warp through it
# moves each other view out of the first one's image: 3 views of one date each whose RPCs span
# 1000 m of heights as real ones do (`satsweep synth --rpc-height-scale 500`, the one-view-per-
# date scenes of tools/bench_multidate.py, seeds 3 and 4; 100 m AOI at 0.3 m: seed 74) had every
# view dropped; tied with all their tie points, 0.031 / 0.027 / 0.025 px off after the gauge.
_FINE_CUBE_QUANTILE = 0.01
_FINE_CUBE_MARGIN_M = 30.0
# Of each pair of views, the fine adjustment keeps at least this many of the best registered tie
# points (refine_keep_fraction of a few dozen would leave too few to tie small views).
_MIN_BEST_REGISTERED = 50
# Threads that tonemap the views and detect their features at once (each holds a view's image
# and its SIFT pyramid: more would cost memory on machines of many cores for little more speed).
# 20 views of 1000^2 px on 2 cores: tonemap 0.33 -> 0.17 s, features 1.7 -> 1.3 s, the same
# features. Matching stays sequential: its matrix products already use every core (threads made
# it 20% slower).
SPARSE_THREADS_MAX = 4
# A group of views tied among themselves by pairs of min_matches or more (one date's views) but
# by none to the largest group is linked to it by its weaker pairs into it: pairs of at least
# this many verified matches (each pair's offset then rests on several matches: on the 384 px
# multi-date crops those of 5-12 matches lie within 1 px of the true offset, those of 2-3 can
# be tens of pixels off), when together they hold at least _WEAK_LINK_FACTOR x min_matches
# (three pairs or more; what three pairs that link on their own would bring at the least: on
# v10 seed 5 with the range given, 30 matches in three pairs linked two views whose corrections
# came 0.49 px off and moved another view's from 0.34 to 0.64 px; the groups linked by 53-113
# matches in 6-15 pairs came within 0.1-0.38 px).
_WEAK_PAIR_MIN = 6
_WEAK_LINK_FACTOR = 3
# REPAIR_RATIO_NOTE. When the largest group holds at most half of the views (the others would
# be dropped), the pairs of fewer than min_matches into the views outside it are matched again
# with Lowe's ratio at ``repair_ratio`` (0.9), the larger verified set kept. Between dates whose
# suns differ by 30-45 degrees of elevation, on views seen from opposite sides, the ratio test
# at 0.8 leaves such a pair 2-11 matches (tools/bench_multidate.py seed 31, 384 px, 8-bit RGB at
# 33.45 S: the ten views fell into three dates' groups and six were dropped, 91.1% within 1 m);
# at 0.9 the same pairs verify 4-17, every view is tied and corrected within 0.062 px of its
# pointing error (94.5%). The verification by the cameras' epipolar geometry and the thresholds
# on the counts stay as they are. Where the largest group holds most views, only in stacks of
# REPAIR_ANY_MIN_VIEWS views or more: a view added so to 5-view subsets of v10 seeds 0 and 5 was
# tied right (0.086 and 0.226 px, as the others) but their DSMs were no better (DFC MAE 1.96 ->
# 2.75 and 1.03 -> 1.16 m), while 10 views of one date each at 33.45 S that dropped 1-4 views
# gained within 1 m (seeds 36, 40, 42: +2.7, +0.9, +0.3 points; DFC MAE -0.07, -0.15, +0.15 m;
# seed 36's 1812-cell hole between tall buildings gone).
REPAIR_ANY_MIN_VIEWS = 8
# TRACK_SCREEN_NOTE. Where the tracks were extended to every view (``extend_points_per_view``)
# and at least TRACK_SCREEN_MIN_VIEWS views are tied, the tie points whose observations' median
# reprojection error after the fine adjustment exceeds TRACK_SCREEN_MEDIAN_PX are left out and
# the fine adjustment runs again (``_screened``), where every view keeps [bundle]
# min_observations. The robust loss weighs each observation alone; a tie point registered on a
# facade (one side's views see it, each foreshortened its own way) or across a moving shadow is
# off in most of its views together, by a few tenths of a pixel, where the loss still lends it
# weight, and such points pull each date's views coherently. On the 1700 px stack of 19 dates
# at 0.3 m (tools/bench_multidate.py --size 1700 --gsd 0.3 --dates 19 --seeds 22) the tracks of
# 4-13 views left a median error of 0.48-0.60 px (those of 13 or more 0.15), and view 3 was off
# by 0.077 px along its rows; with the screen (594 of 939 tie points left out) 0.038 px. Worst
# view after the gauge, sparse stage alone, means over seeds (docs/measurements.md,
# forty-eighth session): 10-view stacks seeds 0-9 0.0205 -> 0.0191 px, one view per date 10
# views 0.0285 -> 0.0255, 33.45 S 0.0272 -> 0.0233, 20 views 0.0284 -> 0.0268. On 5 views of one
# date each it lost (seed 0 0.0515 -> 0.0615 px: 48 of its 175 tie points left out) and
# on 3-5 views of passes it moved nothing beyond noise: smaller stacks keep every tie point. Twice
# the median error as the bound instead of 0.3 px: 0.0197, 0.0254, 0.0223, 0.0275 and 0.045 px
# on the 1700 px stack.
TRACK_SCREEN_MEDIAN_PX = 0.3
TRACK_SCREEN_MIN_VIEWS = 6
# FEWER_OBSERVATIONS_NOTE. A view is dropped when fewer than [bundle] min_observations of its tie
# points agree with the other views, except where that would leave fewer than
# MIN_VIEWS_FOR_HEIGHT views tied and keeping those of [sparse] min_matches agreeing tie points
# or more does not: with two views the scene's height is the gauge's. 5 views of one date each
# at 1.29 N (tools/bench_multidate.py --dates 10 seed 64): views 2, 4 and 9 tied with view 9 at
# 19 agreeing tie points, and the two left put the scene at -34..31 m for a truth of 99..147 m
# (31.3% within 1 m); keeping it, 95..161 m and 71.0%. Where even that leaves two views (v10
# seed 3's 3-view subset), the views are dropped as before and the run asks for a range: a pair
# kept at 15-19 tie points put that scene 19 m up.
MIN_VIEWS_FOR_HEIGHT = 3
# A group that does reach the largest group, but through one pair of min_matches or more (a
# bridge of the graph of such pairs), is held by few tie points: the adjustments may leave it
# fewer than min_observations that agree, or tie it in one direction only, and drop it. Such a
# group is matched with its views' ``pair_repair`` next candidates too when its pairs into the
# rest (of _WEAK_PAIR_MIN matches or more) hold fewer than _WEAK_LINK_FACTOR x min_matches, and
# is adjusted on all those pairs (_bridge_sides). v10 seed 0 (tools/bench_multidate.py) with
# exact RPCs: one date's three views hung on one pair of 15 matches and were dropped (14 tie
# points agreed), now all ten views are kept, the worst 0.15 px off; with the scene's pointing
# errors, seeds 1 and 2 keep a view they dropped (10 of 10).


@dataclasses.dataclass(frozen=True)
class DroppedView:
    """A view the sparse stage could not use, and why (one line naming the problem)."""

    index: int  # the view's index among those given
    path: str  # its file (tie_views, which knows names only, puts the name given)
    reason: str

    @property
    def name(self) -> str:
        return os.path.basename(self.path)

    def message(self) -> str:
        """``NAME: reason``, for warnings and errors."""
        return f"{self.name}: {self.reason}"


# -- the core, shared with adjust_principal_points -----------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class TiedViews:
    """What :func:`tie_views` found. Views are indexed as given; ``kept`` lists those tied.

    ``shifts`` (V, 2) px: the corrections of the kept views (coarse + fine; NaN for dropped
    views) with respect to ``cameras`` (the fine adjustment's, uncorrected); ``sigma`` (V,) px:
    their uncertainty (inf for dropped views). ``points`` (N, 3) ENU m in the fine cameras'
    frame and ``obs`` (views numbered as given): every tie point the coarse adjustment kept, at
    its keypoints (the fine adjustment used the best registered of them), triangulated with the
    corrected cameras; ``point_error`` (N,) px the largest reprojection error of each (inf
    behind a camera), ``point_covariances`` (N, 3, 3) m^2 each one's for 1 px of error
    (:func:`satsweep.sparse.triangulation.point_covariances`).
    """

    names: tuple[str, ...]
    kept: tuple[int, ...]
    dropped: tuple[DroppedView, ...]
    shifts: np.ndarray
    coarse_shifts: np.ndarray
    sigma: np.ndarray
    cameras: tuple[Any, ...]  # the fine adjustment's cameras, uncorrected (per view)
    points: np.ndarray
    obs: Observations
    point_error: np.ndarray
    point_covariances: np.ndarray
    errors_before: np.ndarray  # (M,) px, obs with the uncorrected cameras and their triangulation
    graph: PairGraph
    matches: dict[tuple[int, int], int]  # verified matches of every pair matched
    n_features: tuple[int, ...]
    n_tracks: int
    track_length_histogram: dict[int, int]
    n_refine_dropped: int
    n_refine_contrast: int  # observations registered on local contrast (other dates)
    refine_choice: dict  # register_observations' choice of the contrast's scale, and its
    # tie points registered by a window beside them
    n_extended: int  # observations added where a view had not matched a tie point (extend_tracks)
    n_screened: int | None  # tie points left out by the fine adjustment's screen (_screened);
    # None where it did not run
    coarse: BundleSolution | None
    fine: BundleSolution | None
    seconds: dict[str, float]
    weak_links: tuple[tuple[int, int], ...] = ()  # pairs of fewer than min_matches that linked
    # a group of views to the others (_weak_links)


def _in_threads(function: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
    """``[function(x) for x in items]`` by up to SPARSE_THREADS_MAX threads (OpenCV's SIFT and
    numpy release the GIL). Read at each call, so that a test can set it to 1."""
    return map_in_threads(function, items, max_threads=SPARSE_THREADS_MAX, name="sparse")


def _detect(images: Sequence[np.ndarray], options: SparseOptions,
            budgets: Sequence[int] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """SIFT features of every image (strongest first), at most ``budgets[v]`` of view v
    (``options.max_features`` each when None)."""
    budgets = [options.max_features] * len(images) if budgets is None else list(budgets)
    return _in_threads(lambda k: detect_features(images[k], max_features=int(budgets[k]),
                                                 contrast_threshold=options.contrast_threshold,
                                                 scale=feature_scale_for(np.shape(images[k]),
                                                                         options)),
                       range(len(images)))


# A view cropped over a box larger than the AOI ([sparse] min_extent_m) detects up to
# max_features times its crop's area over the AOI's footprint in it, at most this many times
# max_features: the AOI keeps its density of features (the altitude range's tie points) while
# the box around it adds its own.
FEATURE_BUDGET_MAX_FACTOR = 4.0


def feature_budgets(views: Sequence[Any], aoi: Any, alt: Any, options: SparseOptions) -> list[int]:
    """Per view cropped over a box about ``aoi`` at the ``alt`` range, its SIFT budget
    (FEATURE_BUDGET_MAX_FACTOR)."""
    from satsweep.io.views import projected_aoi_box

    out = []
    for view in views:
        h, w = np.shape(view.image)[:2]
        c0, r0, c1, r1 = projected_aoi_box(view.rpc.projection, aoi, alt)
        inner = max(min(c1, w) - max(c0, 0.0), 1.0) * max(min(r1, h) - max(r0, 0.0), 1.0)
        factor = min(max(w * h / inner, 1.0), FEATURE_BUDGET_MAX_FACTOR)
        out.append(int(round(options.max_features * factor)))
    return out


def registration_window_px(cameras: Sequence[Any], options: SparseOptions) -> int:
    """The tie points' registration window (px): ``refine_window_px``, or the nearest odd
    count of pixels that ``refine_window_m`` spans at the finest of ``cameras``' ground samples
    (``geometry.camera.ground_sample_distance`` at the ENU origin) where that is more (at most
    63)."""
    from satsweep.geometry.camera import ground_sample_distance

    w = options.refine_window_px
    if w == 0 or options.refine_window_m <= 0.0 or not len(cameras):
        return w
    finest = min(ground_sample_distance(c.P, np.zeros(3)) for c in cameras)
    span = options.refine_window_m / finest
    odd = 2 * int(round((span - 1.0) / 2.0)) + 1
    return int(min(max(w, odd), 63))


def _camera_error(cam: Any) -> float:
    """The camera's largest approximation error over the AOI (px), 0 when not known."""
    err = getattr(cam, "error", None)
    return float(err.max_px) if err is not None else 0.0


def _largest_group(V: int, active: set[int], edges: Sequence[tuple[int, int]],
                   matches: dict[tuple[int, int], int]) -> set[int]:
    """The views of the connected component (over ``edges``) holding the most active views;
    ties go to the component with the most verified matches, then to the lowest view."""
    ij = np.array(edges, dtype=np.int64).reshape(-1, 2)
    labels = connected_labels(V, ij[:, 0], ij[:, 1])
    best, best_key = set(), None
    for lab in np.unique(labels[sorted(active)]):
        members = {v for v in active if labels[v] == lab}
        weight = sum(matches[e] for e in edges if e[0] in members)
        key = (len(members), weight, -min(members))
        if best_key is None or key > best_key:
            best, best_key = members, key
    return best


def _bridge_sides(V: int, main: set[int], edges: Sequence[tuple[int, int]]) -> list[set[int]]:
    """For each pair of ``edges`` whose removal splits ``main`` (connected by them), the views
    on its smaller side (on a tie, the side without ``main``'s lowest view)."""
    inner = [e for e in edges if e[0] in main and e[1] in main]
    sides = []
    for cut in inner:
        rest = np.array([e for e in inner if e != cut], dtype=np.int64).reshape(-1, 2)
        labels = connected_labels(V, rest[:, 0], rest[:, 1])
        side = {v for v in main if labels[v] == labels[cut[0]]}
        if len(side) == len(main):
            continue  # not a bridge
        if 2 * len(side) > len(main) or (2 * len(side) == len(main) and min(side) == min(main)):
            side = main - side
        sides.append(side)
    return sides


def _pairs_across(side: set[int], main: set[int], counts: dict[tuple[int, int], int]
                  ) -> list[tuple[int, int]]:
    """The pairs of _WEAK_PAIR_MIN verified matches or more between ``side`` and the rest of
    ``main``."""
    return [p for p, k in counts.items() if k >= _WEAK_PAIR_MIN and p[0] in main
            and p[1] in main and (p[0] in side) != (p[1] in side)]


def _thinly_linked(V: int, main: set[int], edges: Sequence[tuple[int, int]],
                   counts: dict[tuple[int, int], int], min_matches: int) -> set[int]:
    """The views of ``main`` on the smaller side of a bridge (``_bridge_sides``) whose pairs
    into the rest (``_pairs_across``) hold fewer than _WEAK_LINK_FACTOR x ``min_matches``
    verified matches: groups that one or two thin pairs hold to the others."""
    out: set[int] = set()
    for side in _bridge_sides(V, main, edges):
        across = sum(counts[p] for p in _pairs_across(side, main, counts))
        if across < _WEAK_LINK_FACTOR * min_matches:
            out |= side
    return out


def _pairs_into(outside: set[int], active: set[int], counts: dict[tuple[int, int], int],
                min_matches: int) -> list[tuple[int, int]]:
    """The matched pairs of fewer than ``min_matches`` verified matches between ``active``
    views with at least one view in ``outside`` (the pairs that could tie it), in order."""
    return sorted(p for p, k in counts.items() if k < min_matches and p[0] in active
                  and p[1] in active and (p[0] in outside or p[1] in outside))


def _weak_links(V: int, active: set[int], main: set[int], counts: dict[tuple[int, int], int],
                min_matches: int) -> tuple[set[int], list[tuple[int, int]]]:
    """The largest group ``main`` grown by the groups of views (linked by pairs of at least
    ``min_matches`` verified matches) whose weaker pairs into it (_WEAK_PAIR_MIN or more) hold
    at least _WEAK_LINK_FACTOR x ``min_matches`` verified matches together, and those pairs.
    Another date's acquisition of two or three views shares a few matches with each view of the
    others and many within itself: no single pair links it, all of them do."""
    strong = [p for p, k in counts.items() if k >= min_matches and p[0] in active and p[1] in active]
    ij = np.array(strong, dtype=np.int64).reshape(-1, 2)
    labels = connected_labels(V, ij[:, 0], ij[:, 1])
    main, links = set(main), []
    grown = True
    while grown:
        grown = False
        for lab in np.unique(labels[sorted(active - main)]) if active - main else ():
            members = {v for v in active - main if labels[v] == lab}
            weak = [p for p, k in counts.items() if _WEAK_PAIR_MIN <= k < min_matches
                    and ((p[0] in members and p[1] in main) or (p[1] in members and p[0] in main))]
            if sum(counts[p] for p in weak) >= _WEAK_LINK_FACTOR * min_matches:
                main |= members
                links += weak
                grown = True
                break
    return main, sorted(links)


# Fixed views ([bundle] fixed_views) whose corrections no motion of the scene brings within
# this (px) of zero together are an error: their RPCs disagree (tie points place views to a few
# hundredths of a pixel, vendor RPCs refined against ground control agree to tenths).
FIXED_AGREEMENT_PX = 1.0


def _shared_points(obs: Observations, V: int) -> np.ndarray:
    """(V, V) int: the number of tie points (tracks) each pair of views shares."""
    seen = np.zeros((obs.n_points, V), dtype=np.int64)
    seen[obs.point, obs.view] = 1
    return seen.T @ seen


def _tied_groups(cameras: Sequence[Any], fine: BundleSolution, options: BundleOptions,
                 shared: np.ndarray) -> set[int]:
    """The views (indices into ``cameras``) tied in every direction by their own tie points:
    the largest group of views linked pair by pair by at least ``min_observations`` shared tie
    points if it is tied alone (:func:`_tied_alone`), with every other such group that keeps it
    tied added, largest first; all views when the largest group is not tied alone (the uncertain
    direction is then inside it). ``shared``: :func:`_shared_points` of the solution."""
    V = len(cameras)
    edges = [(i, j) for i in range(V) for j in range(i + 1, V)
             if shared[i, j] >= options.min_observations]
    labels = connected_labels(V, np.array([e[0] for e in edges], np.int64),
                              np.array([e[1] for e in edges], np.int64))
    groups = sorted(({v for v in range(V) if labels[v] == lab} for lab in np.unique(labels)),
                    key=lambda g: (-len(g), min(g)))
    main = groups[0]
    if len(groups) == 1 or len(main) < 2 or not _tied_alone(sorted(main), cameras, fine, options):
        return set(range(V))
    for g in groups[1:]:
        if _tied_alone(sorted(main | g), cameras, fine, options):
            main = main | g
    return main


def _uncertainty_of(group: Sequence[int], cameras: Sequence[Any], fine: BundleSolution):
    """shift_uncertainty of the views ``group`` (indices into ``cameras`` and the solution's
    views) from the observations among them, at the solution ``fine`` (not solved again)."""
    mask = np.isin(fine.obs.view, group)
    alive = np.unique(fine.obs.point[fine.obs.subset_index(mask)])
    return shift_uncertainty([cameras[k] for k in group], _local(fine.obs, group),
                             fine.points[alive], fine.shifts[list(group)])


def _tied_alone(group: Sequence[int], cameras: Sequence[Any], fine: BundleSolution,
                options: BundleOptions) -> bool:
    """Whether the views ``group`` are tied in every direction by their own tie points: the
    uncertainty of their shifts (:func:`_uncertainty_of`) within ``max_shift_sigma_px``."""
    worst = _uncertainty_of(group, cameras, fine).worst_sigma
    return bool(worst <= options.max_shift_sigma_px)


def _one_by_one(cameras: Sequence[Any], fine: BundleSolution, options: BundleOptions) -> list[int]:
    """The views that dropping the least determined one after another (at the solution
    ``fine``, not solved again) removes before the others are tied in every direction."""
    group = list(range(len(cameras)))
    gone: list[int] = []
    while len(group) > 2:
        u = _uncertainty_of(group, cameras, fine)
        if u.worst_sigma <= options.max_shift_sigma_px:
            break
        gone.append(group.pop(u.worst_view))
    return gone


def _local(obs: Observations, kept: Sequence[int]) -> Observations:
    """Observations of the ``kept`` views only, views renumbered 0..len(kept) - 1."""
    index = np.full(max(int(obs.view.max(initial=-1)), max(kept, default=-1)) + 1, -1,
                    dtype=np.int64)
    index[list(kept)] = np.arange(len(kept))
    sub = obs.subset(index[obs.view] >= 0)
    return dataclasses.replace(sub, view=index[sub.view])


def _coarse_for(coarse: BundleSolution, kept: Sequence[int],
                left: Sequence[int]) -> BundleSolution:
    """The coarse solution of the views ``kept`` restricted to ``left`` (some of them): their
    shifts, observations (views renumbered 0..len(left) - 1) and the points that two of them
    still see. Dropping a view that the fine adjustment could not tie moves the others' coarse
    shifts by a small part of a pixel (that view carried few tie points, or tied them in one
    direction only), which the fine adjustment takes up; solving again cost each such round as
    much as the first (40 views dropping four: 1.45 of the 4.8 s of the sparse stage)."""
    position = {v: k for k, v in enumerate(kept)}
    views = [position[v] for v in left]  # the views left, in the solution's own numbering
    index = np.full(len(kept), -1, dtype=np.int64)
    index[views] = np.arange(len(views))
    rows = coarse.obs.subset_index(index[coarse.obs.view] >= 0)  # what _local would keep
    obs = coarse.obs.take(rows)
    alive = np.zeros(coarse.obs.n_points, dtype=bool)
    alive[coarse.obs.point[rows]] = True
    return dataclasses.replace(
        coarse, shifts=coarse.shifts[views], points=coarse.points[alive],
        anchors=coarse.anchors[alive], obs=dataclasses.replace(obs, view=index[obs.view]),
        errors_before=coarse.errors_before[rows], errors_after=coarse.errors_after[rows])


def _global(obs: Observations, kept: Sequence[int]) -> Observations:
    """Inverse of :func:`_local`: views renumbered as given."""
    return dataclasses.replace(obs, view=np.asarray(kept, dtype=np.int64)[obs.view])


def _screened(cameras: Sequence[Any], fine: BundleSolution, options: BundleOptions,
              names: Sequence[str]) -> tuple[BundleSolution, int]:
    """The fine adjustment again without the tie points whose median reprojection error in
    ``fine`` exceeds TRACK_SCREEN_MEDIAN_PX (``track_median_errors``), and how many were left
    out; ``fine`` itself (and 0) when none exceeds it, or when some view would keep fewer than
    ``options.min_observations`` observations, or when the second adjustment leaves one so."""
    bad = track_median_errors(fine) > TRACK_SCREEN_MEDIAN_PX
    if not bad.any():
        return fine, 0
    try:  # (the adjustment checks every view's count before it solves)
        return (adjust_observations(cameras, fine.obs.subset(~bad[fine.obs.point]), options,
                                    names=names), int(bad.sum()))
    except TooFewObservations:
        return fine, 0


def _worst_error(obs: Observations, errors: np.ndarray) -> np.ndarray:
    """(N,) the largest of each point's observation errors."""
    worst = np.zeros(obs.n_points)
    np.maximum.at(worst, obs.point, errors)
    return worst


def tie_views(images: Sequence[np.ndarray], cameras: Sequence[Any], names: Sequence[str],
              options: SparseOptions = SparseOptions(),
              bundle_options: BundleOptions = BundleOptions(), *,
              samples: np.ndarray | None = None, fine_cameras: Any = None,
              dropped: dict[int, str] | None = None, fixed: Sequence[int] = (),
              max_features: Sequence[int] | None = None,
              prior_range_up: tuple[float, float] | None = None) -> TiedViews:
    """Steps 1-7 of the module docstring on tonemapped ``images`` and their ``cameras``.

    ``cameras``: per view a PerspectiveCamera of its image (those of the prior range);
    ``samples``: ENU points of the AOI in the cameras' frame (:func:`graph.aoi_samples`), None
    for crops of one AOI; ``fine_cameras``: None to adjust finely with ``cameras`` too, else a
    callable ``(kept view indices, coarse solution over them) -> cameras of every view`` (the
    sparse stage fits them over the coarse tie points' altitudes); ``dropped``: views already
    known to be unusable (camera None), with the reason; ``fixed``: views whose corrections are
    held at zero (``BundleOptions.fixed_views``; the gauge is the smallest corrections without
    them); ``max_features``: per view its SIFT budget (:func:`feature_budgets`), None for
    ``options.max_features``; ``prior_range_up``: the prior altitude range's ends as up
    coordinates of the cameras' frame (:func:`adjust_coarse`'s), None for none. Views that cannot
    be tied are in the result's ``dropped``; raises
    CameraError for inputs of the wrong size and for fixed views that disagree
    (``FIXED_AGREEMENT_PX``).
    """
    V = len(images)
    if len(cameras) != V or len(names) != V:
        raise CameraError(f"tie_views: {V} images, {len(cameras)} cameras, {len(names)} names")
    for name, image, cam in zip(names, images, cameras):
        if cam is not None and np.shape(image) != (cam.height, cam.width):
            raise CameraError(f"{name}: image of shape {np.shape(image)} but the camera is "
                              f"{cam.width}x{cam.height} px")
    o, b = options, bundle_options
    seconds: dict[str, float] = {}
    dropped = dict(dropped or {})
    for v, cam in enumerate(cameras):
        if cam is None and v not in dropped:
            raise CameraError(f"tie_views: view {names[v]} has no camera and no reason to drop it")

    t0 = time.perf_counter()
    feats = _detect([im if v not in dropped else np.zeros((1, 1)) for v, im in enumerate(images)],
                    o, max_features)
    n_features = tuple(len(xy) for xy, _ in feats)
    for v, k in enumerate(n_features):
        if k < o.min_matches and v not in dropped:
            dropped[v] = (f"too few SIFT features ({k}; need at least {o.min_matches}): a blank, "
                          "cloudy or featureless image")
    seconds["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    thresholds = {(i, j): o.ransac_threshold_px + _camera_error(cameras[i]) + _camera_error(cameras[j])
                  for i in range(V) for j in range(i + 1, V) if i not in dropped and j not in dropped}
    graph = build_pair_graph(cameras, feats, o, samples=samples, exclude=sorted(dropped),
                             thresholds=thresholds)
    with_candidates = {v for c in graph.candidates for v in (c.i, c.j)}
    for v in range(V):
        if v not in dropped and v not in with_candidates:
            dropped[v] = (f"shares less than {o.pair_min_overlap:.0%} of the AOI with any other "
                          "view")
    seconds["graph"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pair_matches: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def match(pairs, options=o):
        for i, j in pairs:
            F = (fundamental_from_cameras(cameras[i], cameras[j])
                 if o.geometric_model == "cameras" else None)
            found = match_pair(feats[i][1], feats[j][1], feats[i][0], feats[j][0], options,
                               fundamental=F, threshold_px=thresholds[(i, j)])
            if (i, j) not in pair_matches or len(found[0]) > len(pair_matches[(i, j)][0]):
                pair_matches[(i, j)] = found

    match(graph.selected)
    repaired: set[int] = set()
    while True:
        active = set(range(V)) - set(dropped)
        counts = {p: len(m[0]) for p, m in pair_matches.items()}
        edges = [p for p, k in counts.items()
                 if k >= o.min_matches and p[0] in active and p[1] in active]
        main = _largest_group(V, active, edges, counts) if active else set()
        loose = sorted((active - main - repaired)
                       | (_thinly_linked(V, main, edges, counts, o.min_matches) - repaired))
        extra = repair_pairs(graph, set(pair_matches), loose, o.pair_repair) if o.pair_repair else []
        repaired.update(loose)
        if not extra:
            break
        match(extra)
    main, links = _weak_links(V, active, main, counts, o.min_matches)
    rematch = 2 * len(main) <= len(active) or len(active) >= REPAIR_ANY_MIN_VIEWS
    rematched = _pairs_into(active - main, active, counts, o.min_matches) \
        if o.repair_ratio > o.ratio and rematch else []
    if rematched:
        # Views outside the largest group (half of them or more, or any in a large stack): their
        # weak pairs matched again with the looser ratio test (REPAIR_RATIO_NOTE), the groups
        # and weak links taken anew.
        match(rematched, dataclasses.replace(o, ratio=o.repair_ratio))
        counts = {p: len(m[0]) for p, m in pair_matches.items()}
        edges = [p for p, k in counts.items()
                 if k >= o.min_matches and p[0] in active and p[1] in active]
        main = _largest_group(V, active, edges, counts)
        main, links = _weak_links(V, active, main, counts, o.min_matches)
    # A group held to the others by a bridge is adjusted on all its pairs into them, weak ones
    # included, as a group linked by weak pairs alone is (_weak_links).
    for side in _bridge_sides(V, main, edges):
        links = sorted(set(links) | {p for p in _pairs_across(side, main, counts)
                                     if counts[p] < o.min_matches})
    for v in sorted(active - main):
        dropped[v] = _unlinked_reason(v, counts, names, o.min_matches, len(main))
    seconds["matching"] = time.perf_counter() - t0

    matches = {p: len(m[0]) for p, m in sorted(pair_matches.items())}
    xys = [xy for xy, _ in feats]
    coarse = fine = None
    tied = False
    tracks: list = []
    n_refine_dropped = n_refine_contrast = n_extended = 0
    n_screened: int | None = None  # tie points the fine adjustment's screen left out
    refine_choice: dict = {}
    fine_cams = list(cameras)
    shifts = np.full((V, 2), np.nan)
    coarse_shifts = np.full((V, 2), np.nan)
    sigma = np.full(V, np.inf)
    # The coarse solution of a round that dropped views only after its coarse stage (the fine
    # adjustment left a view too few tie points, or its correction uncertain), with its views:
    # the next round restricts it to the views left instead of solving again, and keeps the
    # fine cameras (see _coarse_for).
    previous: tuple[list[int], BundleSolution] | None = None
    # The pairs of the last round: a reused round builds no tracks (None), so the report's count
    # and lengths, those of the views it kept, are built from them after the rounds.
    last_used: dict = {}
    for _ in range(V):  # each round ties the views or drops at least one
        used = {p: m for p, m in pair_matches.items()
                if (len(m[0]) >= o.min_matches or p in links) and p[0] not in dropped
                and p[1] not in dropped}
        active = set(range(V)) - set(dropped)
        main = _largest_group(V, active, list(used), matches) if active else set()
        for v in sorted(active - main):  # cut off by a view dropped in a previous round
            dropped[v] = "no longer tied to the largest group of views once others were dropped"
        kept = sorted(main)
        if len(kept) < 2:
            break
        used = {p: m for p, m in used.items() if p[0] in main and p[1] in main}
        reused = previous is not None and set(kept) <= set(previous[0])
        last_used, tracks = used, None
        if not reused:  # (a reused round restricts the previous coarse solution instead)
            t0 = time.perf_counter()
            tracks = build_tracks(V, used)
            obs = _local(observations_from_tracks(tracks, xys), kept)
            seconds["tracks"] = seconds.get("tracks", 0.0) + time.perf_counter() - t0

        t0 = time.perf_counter()
        local_cams = [cameras[v] for v in kept]
        if reused:
            coarse = _coarse_for(previous[1], previous[0], kept)
        else:
            coarse = adjust_coarse(local_cams, obs, b,
                                   fixed=[k for k, v in enumerate(kept) if v in fixed],
                                   prior_range_up=prior_range_up)
        previous = None
        seconds["coarse"] = seconds.get("coarse", 0.0) + time.perf_counter() - t0
        count = np.bincount(coarse.obs.view, minlength=len(kept))
        need = b.min_observations
        poor = [(kept[k], int(count[k])) for k in range(len(kept)) if count[k] < need]
        if poor and len(kept) - len(poor) < MIN_VIEWS_FOR_HEIGHT:
            # Two views leave the scene's height to the gauge (a pointing error along their
            # epipolar lines is a height offset): a view of min_matches agreeing tie points or
            # more is kept where that makes MIN_VIEWS_FOR_HEIGHT views tied (FEWER_OBSERVATIONS_NOTE).
            fewer = [(v, c) for v, c in poor if c < o.min_matches]
            if len(kept) - len(fewer) >= MIN_VIEWS_FOR_HEIGHT:
                poor, need = fewer, o.min_matches
        if poor:
            for v, c in poor:
                dropped[v] = (f"only {c} tie points agree with the other views (need at least "
                              f"{need}): does it see the same place?")
            continue

        if fine_cameras is not None and not reused:
            t0 = time.perf_counter()
            fine_cams = list(fine_cameras(kept, coarse))
            seconds["cameras"] = seconds.get("cameras", 0.0) + time.perf_counter() - t0
        local_fine = [shift_principal_point(fine_cams[v], s) for v, s in zip(kept, coarse.shifts)]
        chosen = thin_points(coarse.obs, o.fine_points_per_view)
        registered, residual = chosen, np.zeros(len(chosen.view))
        extended = bool(o.refine_window_px and o.extend_points_per_view and len(kept) >= 3)
        window_px = registration_window_px(local_fine, o)
        if o.refine_window_px:
            t0 = time.perf_counter()
            if extended:
                own = np.bincount(chosen.point, minlength=chosen.n_points)
                grown = extend_tracks(chosen, projection_stack(local_fine),
                                      [(c.height, c.width) for c in local_fine],
                                      margin_px=window_px + o.refine_max_shift_px,
                                      per_view=o.extend_points_per_view)
                # Extended, most tracks reach most views: every point chosen above would bring
                # an observation in nearly every view, and a stack of V views V times those.
                keep = thin_mask(grown, o.extend_points_per_view)
                chosen = grown.subset(keep)
                # (each point's own observations come first, the added ones after them)
                rank = np.arange(len(grown.point)) - np.searchsorted(grown.point, grown.point)
                n_extended = int(np.sum(keep & (rank >= own[grown.point])))
            registered, residual, n_refine_dropped = register_observations(
                chosen, [images[v] for v in kept], local_fine, window_px=window_px,
                max_shift_px=o.refine_max_shift_px, keep_fraction=o.refine_keep_fraction,
                at_least=_MIN_BEST_REGISTERED, threads=SPARSE_THREADS_MAX,
                beside_px=o.refine_beside_px, choice=refine_choice)
            refine_choice["window_px"] = window_px
            n_refine_contrast = int(np.sum(residual >= CONTRAST_RANK))
            seconds["refinement"] = seconds.get("refinement", 0.0) + time.perf_counter() - t0
        fine_obs = best_registered(registered, residual, o.refine_keep_fraction,
                                   at_least=_MIN_BEST_REGISTERED)
        t0 = time.perf_counter()
        n_screened = None
        try:
            fine_options = (b.replace(loss_scale_px=b.extended_loss_scale_px,
                                      loss=b.extended_loss) if extended else b)
            if need < b.min_observations:
                fine_options = fine_options.replace(min_observations=need)
            fine = adjust_observations(local_fine, fine_obs, fine_options,
                                       names=[names[v] for v in kept])
            if extended and len(kept) >= TRACK_SCREEN_MIN_VIEWS:
                fine, n_screened = _screened(local_fine, fine, fine_options,
                                             [names[v] for v in kept])
        except TooFewObservations as exc:
            for k, c in zip(exc.views, exc.counts):
                dropped[kept[k]] = (f"only {c} tie points left after the fine adjustment (need "
                                    f"at least {need})")
            seconds["fine"] = seconds.get("fine", 0.0) + time.perf_counter() - t0
            previous = (kept, coarse)
            continue
        certainty = shift_uncertainty(local_fine, fine.obs, fine.points, fine.shifts)
        seconds["fine"] = seconds.get("fine", 0.0) + time.perf_counter() - t0
        if len(kept) > 2 and not certainty.worst_sigma <= b.max_shift_sigma_px:
            # (With two views the one direction the tie points do not fix is the height of the
            # scene, part of the motion no image sees.) The view carrying most of the least
            # determined direction is dropped, and the stage runs again. But when groups of
            # views (linked pair by pair by at least min_observations shared tie points) split
            # the stack, the largest group tied alone, with every other group that keeps it so,
            # is kept and the rest dropped together, if that drops fewer views than dropping
            # one after another would (estimated without solving again): the uncertain
            # direction is then their motion against it, whose largest share may lie in the
            # larger group, and one view after another could end with the smaller group.
            shared = _shared_points(fine.obs, len(kept))
            main = _tied_groups(local_fine, fine, b, shared)
            if len(main) < len(kept) and (len(kept) - len(main)
                                          >= len(_one_by_one(local_fine, fine, b))):
                main = set(range(len(kept)))
            if len(main) < len(kept):
                for k in sorted(set(range(len(kept))) - main):
                    most = max(main, key=lambda m: shared[k, m])
                    dropped[kept[k]] = (
                        f"not tied in every direction to the {len(main)} views tied together (it "
                        f"shares at most {shared[k, most]} tie points with one of them, "
                        f"{names[kept[most]]}; their relative correction is uncertain by "
                        f"{certainty.worst_sigma:.2f} px, more than {b.max_shift_sigma_px:g} px)")
                previous = (kept, coarse)
                continue
            v = kept[certainty.worst_view]
            dropped[v] = (f"its pointing correction is uncertain by {certainty.worst_sigma:.2f} px "
                          f"(more than {b.max_shift_sigma_px:g} px): it is not tied to the other "
                          "views in every direction")
            previous = (kept, coarse)
            continue
        shifts[kept] = coarse.shifts + fine.shifts
        held = [k for k, v in enumerate(kept) if v in fixed]
        if held:
            # The fine adjustment's anchors keep the coarse gauge to tenths of a pixel: the fixed
            # views' corrections are made exactly zero by the motion no image sees (a shifted
            # principal point leaves a camera's Jacobian as it is).
            shifts[kept] = in_gauge(projection_stack(local_fine), shifts[kept],
                                    fine.points.mean(axis=0), held)
            rows = [kept[k] for k in held]
            left = np.hypot(*shifts[rows].T)
            if left.max() > FIXED_AGREEMENT_PX:
                raise CameraError(
                    "the fixed views ([bundle] fixed_views) disagree: no motion of the scene "
                    "zeroes all their corrections (left: " + ", ".join(
                        f"{names[v]} {d:.2f} px" for v, d in zip(rows, left))
                    + f", more than {FIXED_AGREEMENT_PX:g} px); their RPCs cannot all be right")
            shifts[rows] = np.where(np.abs(shifts[rows]) < 1e-9, 0.0, shifts[rows])  # rounding
        coarse_shifts[kept] = coarse.shifts
        sigma[kept] = certainty.sigma
        tied = True
        break
    if not tied:
        kept, fine = [], None
        for v in range(V):
            dropped.setdefault(v, "fewer than two views could be tied together")
    if tracks is None:
        t0 = time.perf_counter()
        tracks = build_tracks(V, last_used)
        seconds["tracks"] = seconds.get("tracks", 0.0) + time.perf_counter() - t0
    lengths = np.bincount([len(t) for t in tracks], minlength=V + 1) if tracks else np.zeros(V + 1, int)
    if fine is not None:
        # Every tie point the coarse adjustment kept, at its keypoints, triangulated with the
        # corrected cameras: the registration moves the keypoints of roof corners (windows over
        # a roof and the ground below) by pixels and drops them, and those are the highest points.
        local_fine = [fine_cams[v] for v in kept]
        P = projection_stack([shift_principal_point(c, s) for c, s in zip(local_fine, shifts[kept])])
        points, err, front = triangulate_observations(coarse.obs, P)
        point_error = _worst_error(coarse.obs, err)
        point_error[~front] = np.inf
        covariances = point_covariances(P, coarse.obs, points)
        obs = _global(coarse.obs, kept)
        P0 = projection_stack(local_fine)
        X0 = triangulate_observations(fine.obs, P0)[0]
        xy = project(P0, fine.obs.view, X0[fine.obs.point])[0]
        errors_before = np.hypot(*(xy - fine.obs.xy).T)
    else:
        obs = Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), 0)
        point_error, points, errors_before = np.zeros(0), np.zeros((0, 3)), np.zeros(0)
        covariances = np.zeros((0, 3, 3))
    return TiedViews(
        names=tuple(names), kept=tuple(kept),
        dropped=tuple(DroppedView(v, names[v], r) for v, r in sorted(dropped.items())),
        shifts=shifts, coarse_shifts=coarse_shifts, sigma=sigma, cameras=tuple(fine_cams),
        points=points, obs=obs, point_error=point_error, point_covariances=covariances,
        errors_before=errors_before, graph=graph,
        matches=matches,
        n_features=n_features, n_tracks=len(tracks),
        track_length_histogram={int(k): int(c) for k, c in enumerate(lengths) if c > 0},
        n_refine_dropped=n_refine_dropped, n_refine_contrast=n_refine_contrast,
        refine_choice=dict(refine_choice), n_extended=n_extended, n_screened=n_screened,
        coarse=coarse,
        fine=fine, seconds=seconds, weak_links=tuple(p for p in links if p[0] in kept and p[1] in kept))


# -- the stage -----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class SparseResult:
    """What the sparse stage gives the pipeline (see the module docstring).

    ``corrections_px`` (V, 2): per view given, the translation (col, row) in image pixels of its
    content with respect to its RPC (content of X at ``RPC(X) + correction``), NaN for a dropped
    view; apply it to any crop's camera with ``shift_principal_points``. ``altitude_range``:
    None when too few tie points bound the heights (``altitude["reason"]`` says why).
    """

    paths: tuple[str, ...]
    names: tuple[str, ...]
    corrections_px: np.ndarray
    correction_sigma_px: np.ndarray
    coarse_corrections_px: np.ndarray
    dropped: tuple[DroppedView, ...]
    prior_range: Any  # AltitudeRange the views were cropped at
    altitude_range: Any  # AltitudeRange | None
    altitude: dict[str, Any]  # how the range was found: tie points used, quantiles, reason
    tied: TiedViews
    frame: Any  # the ENU frame of tied.points (that of the fine adjustment's cameras)
    min_matches: int  # pairs with fewer verified matches were not used
    seconds: dict[str, float]
    fixed_views: tuple[int, ...] = ()  # the views whose corrections were held at zero
    fixed_absent: tuple[str, ...] = ()  # fixed views asked for that were not among the views
    tie_box: Any = None  # the AOI grown to [sparse] min_extent_m that the views were tied
    # over, None when that is the AOI
    surface_ties: dict[str, Any] | None = None  # the refinement on a first DSM's surface
    # (with_surface_shifts), None when it did not run

    @property
    def kept(self) -> tuple[int, ...]:
        return self.tied.kept

    @property
    def kept_paths(self) -> tuple[str, ...]:
        return tuple(self.paths[v] for v in self.kept)

    @property
    def warnings(self) -> tuple[str, ...]:
        """One line per dropped view, naming its file, and per fixed view not among them."""
        return (tuple(f"{d.path}: dropped by the sparse stage: {d.reason}" for d in self.dropped)
                + tuple(f"{entry}: a fixed view ([bundle] fixed_views) that does not see this "
                        "area: the corrections here are the smallest on average instead"
                        for entry in self.fixed_absent))

    @property
    def max_correction_px(self) -> float:
        """The largest |correction| component of the kept views (px): the extra crop margin a
        later crop needs to hold the AOI's content."""
        c = self.corrections_px[list(self.kept)]
        return float(np.abs(c).max(initial=0.0))

    def _indices(self, paths: Sequence[str | os.PathLike]) -> list[int | None]:
        """Each path's index among the views given to the stage (None: not given), the files
        compared by their real paths."""
        index = {os.path.realpath(p): v for v, p in enumerate(self.paths)}
        return [index.get(os.path.realpath(os.fspath(p))) for p in paths]

    def corrections_for(self, paths: Sequence[str | os.PathLike]) -> list[tuple[float, float]]:
        """The corrections of the given images (kept views only), in their order: the shifts to
        pass to ``shift_principal_points`` for a CameraSet of those images."""
        out = []
        for p, v in zip(paths, self._indices(paths)):
            if v is None or v not in self.kept:
                raise InputError(p, "no pointing correction: the sparse stage did not tie this view")
            out.append((float(self.corrections_px[v, 0]), float(self.corrections_px[v, 1])))
        return out

    def indices_of(self, paths: Sequence[str | os.PathLike]) -> list[int | None]:
        """Each image's index among the views given to the stage (None: not given), the
        files compared by their real paths."""
        return self._indices(paths)

    def with_surface_shifts(self, paths: Sequence[str | os.PathLike],
                            shifts: Sequence[Sequence[float]],
                            figures: dict[str, Any]) -> "SparseResult":
        """A copy whose corrections of the images ``paths`` (kept views) are moved by
        ``shifts`` (px, per image), with ``figures`` reported as ``surface_ties``
        (:mod:`satsweep.sparse.surface_ties`)."""
        corrections = self.corrections_px.copy()
        for p, v, s in zip(paths, self._indices(paths), shifts):
            if v is None or v not in self.kept:
                raise InputError(p, "no pointing correction: the sparse stage did not tie this view")
            corrections[v] += np.asarray(s, np.float64)
        return dataclasses.replace(self, corrections_px=corrections, surface_ties=dict(figures))

    def match_counts(self, paths: Sequence[str | os.PathLike]) -> np.ndarray:
        """(n, n) matches of each pair of the views ``paths``, an appearance similarity
        (:func:`satsweep.dense.similarity.similarity_from_matches`): the pair graph's probe
        (verified matches among the strongest features), or, in a stack small enough that every
        pair was matched without a probe, the pairs' verified matches; NaN for pairs without
        either and for views the stage was not given."""
        where = self._indices(paths)
        probes = {(c.i, c.j): c.probe for c in self.tied.graph.candidates if c.probe >= 0}
        if not probes:
            probes = dict(self.tied.matches)
        out = np.full((len(where), len(where)), np.nan)
        for a, i in enumerate(where):
            for b, j in enumerate(where):
                if i is not None and j is not None and i != j:
                    k = probes.get((min(i, j), max(i, j)))
                    if k is not None:
                        out[a, b] = k
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the ``sparse`` section of report.json)."""
        t, n = self.tied, self.names
        fine, coarse = t.fine, t.coarse

        def figures(sol: BundleSolution | None) -> dict[str, Any] | None:
            if sol is None or len(sol.errors_after) == 0:
                return None
            return {"points": int(sol.obs.n_points), "observations": int(len(sol.obs.view)),
                    "reprojection_error_px": {
                        "before": {"median": float(np.median(sol.errors_before)),
                                   "mean": float(np.mean(sol.errors_before))},
                        "after": {"median": float(np.median(sol.errors_after)),
                                  "mean": float(np.mean(sol.errors_after))}},
                    "solver_evaluations": list(sol.evaluations)}

        cands = {(c.i, c.j): c for c in t.graph.candidates}
        pairs = []
        for (i, j), k in t.matches.items():
            c = cands.get((i, j))
            pairs.append({"views": [n[i], n[j]], "matches": k, "used": i in t.kept
                          and j in t.kept and (k >= self.min_matches or (i, j) in t.weak_links),
                          "weak_link": (i, j) in t.weak_links,
                          "selected": (i, j) in t.graph.selected,
                          "base_to_height": None if c is None else c.base_to_height,
                          "overlap": None if c is None else c.overlap,
                          "probe_matches": None if c is None or c.probe < 0 else c.probe})
        views = {}
        for v, name in enumerate(n):
            entry: dict[str, Any] = {"features": t.n_features[v]}
            if v in t.kept:
                entry["correction_px"] = [float(x) for x in self.corrections_px[v]]
                entry["coarse_correction_px"] = [float(x) for x in self.coarse_corrections_px[v]]
                entry["correction_sigma_px"] = float(self.correction_sigma_px[v])
                entry["observations"] = int(np.sum(t.obs.view == v))
            views[name] = entry
        return {
            "views": views,
            "dropped": [{"image": d.path, "reason": d.reason} for d in self.dropped],
            "pair_graph": {"candidates": len(t.graph.candidates), "matched": len(t.matches),
                           "all_pairs": len(n) * (len(n) - 1) // 2, "pairs": pairs},
            "tracks": t.n_tracks,
            "track_length_histogram": {str(k): v for k, v in sorted(t.track_length_histogram.items())},
            "refine_dropped": t.n_refine_dropped,
            "refine_on_local_contrast": t.n_refine_contrast,
            "refine_contrast_sigma_px": t.refine_choice.get("contrast_sigma_px"),
            "refine_contrast_fine_spread_ratio": t.refine_choice.get("fine_spread_ratio"),
            # tie points registered by a window beside them ([sparse] refine_beside_px), of all
            "refine_beside_points": t.refine_choice.get("beside_points"),
            "refine_points": t.refine_choice.get("points"),
            "refine_window_px": t.refine_choice.get("window_px"),
            "extended_observations": t.n_extended,
            # tie points whose median error after the fine adjustment exceeded
            # TRACK_SCREEN_MEDIAN_PX, left out of it (None: the screen did not run)
            "screened_tie_points": t.n_screened,
            # tie points of views along nearly one line of sight, adjusted without an anchor
            # ([bundle] anchor_min_bh)
            "unanchored_tie_points": None if fine is None else fine.unanchored,
            "coarse": figures(coarse),
            "fine": figures(fine),
            "prior_range": [self.prior_range.min, self.prior_range.max],
            "tie_box": None if self.tie_box is None else {
                "lon_min": self.tie_box.lon_min, "lat_min": self.tie_box.lat_min,
                "lon_max": self.tie_box.lon_max, "lat_max": self.tie_box.lat_max,
                "width_m": self.tie_box.width_m, "height_m": self.tie_box.height_m,
                "note": "the AOI was smaller than [sparse] min_extent_m: the views were tied "
                        "over this box about it; the altitude range is the AOI's"},
            "altitude_range": self.altitude,
            # the corrections refined on a first DSM's surface (correction_px includes them;
            # None: not refined, [bundle] surface_ties)
            "surface_ties": self.surface_ties,
            "seconds": dict(self.seconds),
            "convention": "correction_px: the view's content of ground point X lies at RPC(X) + "
                          "correction (image pixels, col/row); it moves the principal point of "
                          "any crop's camera; defined up to the motion of the whole scene, "
                          "chosen to make the corrections smallest"
                          + (" with those of the fixed views (bundle.fixed_views) held at zero"
                             if self.fixed_views else ""),
                          "fixed_views": [n[v] for v in self.fixed_views],
        }


def _unlinked_reason(v: int, counts: dict[tuple[int, int], int], names: Sequence[str],
                     min_matches: int, main_size: int) -> str:
    """Why view ``v`` is outside the largest group of views that its matched pairs (``counts``:
    verified matches per pair (i, j)) with at least ``min_matches`` tie together."""
    mine = [(k, p) for p, k in counts.items() if v in p]
    if not mine:
        return "no pair of views to match it with"
    k, (i, j) = max(mine)
    other = names[j if i == v else i]
    if k < min_matches:
        return (f"too few verified matches with the other views (best: {other} with {k}; need "
                f"at least {min_matches}): does it see the same place?")
    return (f"tied to {other} ({k} verified matches), but no chain of pairs with at least "
            f"{min_matches} links it to the largest group of views ({main_size}): a date or "
            "place apart from the others?")


def fine_cube_altitudes(alt: np.ndarray, inside: np.ndarray, prior: Any,
                        min_points: int) -> tuple[float, float] | None:
    """The altitudes (lo, hi) over which the fine cameras are fitted: the _FINE_CUBE_QUANTILE and
    1 - _FINE_CUBE_QUANTILE quantiles of the coarse tie points' altitudes ``alt`` (NaN: not
    triangulated), widened by _FINE_CUBE_MARGIN_M and cut by the ``prior`` range, of those
    ``inside`` the tie box, or of all of them where fewer than ``min_points`` lie inside
    (FINE_CUBE_NOTE). None where fewer than ``min_points`` are finite, or the cut leaves no
    range: the prior's cameras then serve."""
    alt = np.asarray(alt, np.float64)
    use = np.asarray(inside, bool) & np.isfinite(alt)
    if use.sum() < min_points:
        use = np.isfinite(alt)
    if use.sum() < min_points:
        return None
    lo, hi = np.quantile(alt[use], [_FINE_CUBE_QUANTILE, 1.0 - _FINE_CUBE_QUANTILE])
    lo = max(float(lo) - _FINE_CUBE_MARGIN_M, float(prior.min))
    hi = min(float(hi) + _FINE_CUBE_MARGIN_M, float(prior.max))
    return (lo, hi) if lo < hi else None


def fit_cameras(views: Sequence[Any], aoi: Any, alt: Any, grid_size: tuple[int, int, int], *,
                only: Sequence[int] | None = None) -> tuple[Any, list[Any], dict[int, str]]:
    """Perspective cameras of the views' crops over the AOI x ``alt`` cube, one grid of
    ``grid_size`` samples for all (:func:`satsweep.geometry.camera.fit_camera`), in the frame
    ``frame_for(aoi, alt)``. Returns the frame, the cameras (None for the views not in ``only``
    and for those whose fit fails) and the failures' messages by view."""
    from satsweep.geometry.camera import CameraOptions, aoi_grid, fit_camera, frame_for

    frame = frame_for(aoi, alt)
    options = CameraOptions(grid_size=grid_size)
    grid = aoi_grid(frame, aoi, alt, grid_size)
    cams: list[Any] = []
    failed: dict[int, str] = {}
    for v, view in enumerate(views):
        if only is not None and v not in only:
            cams.append(None)
            continue
        try:
            cams.append(fit_camera(view.rpc, grid, np.shape(view.image), options))
        except CameraError as exc:
            cams.append(None)
            failed[v] = f"no perspective camera fits its RPC over the AOI ({exc})"
    return frame, cams, failed


def corrected_projections(tied: TiedViews) -> dict[int, np.ndarray]:
    """Per kept view of ``tied``, its corrected 3x4 camera (ENU -> pixels, float64)."""
    return {v: np.asarray(shift_principal_point(tied.cameras[v], tied.shifts[v]).P, np.float64)
            for v in tied.kept}


def tie_point_confirmer(tied: TiedViews, images: Sequence[np.ndarray]):
    """A function of a point index of ``tied.points`` and a depth (m, ``point_evidence``'s
    ``below_m``: how far under the point the views are searched): whether views outside its
    track see it where the track puts it (:mod:`satsweep.sparse.verify`), with the corrected
    cameras of ``tied`` and the views' tonemapped ``images``."""
    from satsweep.sparse.verify import SEARCH_HALF_M, point_evidence

    P = corrected_projections(tied)

    def confirm(i: int, below_m: float = SEARCH_HALF_M) -> bool:
        track = tied.obs.view[tied.obs.point == i]
        return point_evidence(tied.points[i], track, images, P, below_m=below_m).confirmed

    return confirm


def fixed_view_indices(fixed_views: Sequence[str], paths: Sequence[str],
                       names: Sequence[str], *, absent_ok: bool = False
                       ) -> tuple[list[int], list[str]]:
    """The indices of the views that ``fixed_views`` (``BundleOptions.fixed_views``) name, by
    file name or by path, and the entries that name none of them. OptionsError naming an entry
    that matches several views, or none unless ``absent_ok`` (the views of one tile of a run,
    whose inputs were checked whole: a fixed image need not see every tile)."""
    out, absent = [], []
    for entry in fixed_views:
        real = os.path.realpath(entry)
        hits = [v for v, (p, n) in enumerate(zip(paths, names))
                if entry == n or os.path.basename(p) == entry or os.path.realpath(p) == real]
        if len(hits) > 1 or not (hits or absent_ok):
            raise OptionsError(
                f"[bundle] fixed_views: {entry!r} names {'none' if not hits else 'several'} of "
                f"the views given ({', '.join(names)})")
        if hits:
            out.append(hits[0])
        else:
            absent.append(entry)
    return out, absent


def sparse_stage(views: Sequence[Any], aoi: Any, prior: Any,
                 options: SparseOptions = SparseOptions(),
                 bundle_options: BundleOptions = BundleOptions(), *,
                 names: Sequence[str] | None = None,
                 images: Sequence[np.ndarray] | None = None,
                 fixed_absent_ok: bool = False, tie_aoi: Any = None) -> SparseResult:
    """The sparse stage (module docstring) on ``views`` cropped at the ``prior`` altitude range.

    ``views``: :class:`satsweep.io.views.View` (``load_views(paths, aoi, prior, margin_px=...)``);
    ``aoi``: the AOI; ``prior``: the AltitudeRange they were cropped at (the user's, a DEM's or
    the RPCs'); ``images``: their tonemapped images if already made; ``names``: for messages,
    default the file names; ``fixed_absent_ok``: fixed views (``bundle_options.fixed_views``)
    that are not among ``views`` are a warning (a tile they do not see) rather than an
    OptionsError; ``tie_aoi``: the box the views were cropped at when larger than the AOI
    (``AOI.grown_to(options.min_extent_m)``: the cameras are fitted over it, while the pairs'
    overlaps and the altitude range are the AOI's), None for the AOI. Raises CameraError naming
    every view and why when fewer than two views can be tied.
    """
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.io.images import tonemap
    from satsweep.sparse.tiepoints import altitude_range_from_points

    t_all = time.perf_counter()
    seconds: dict[str, float] = {}
    paths = tuple(os.fspath(v.path) for v in views)
    names = tuple(os.path.basename(p) for p in paths) if names is None else tuple(names)
    t0 = time.perf_counter()
    if images is None:
        images = _in_threads(lambda v: tonemap(v.image), views)
    seconds["tonemap"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    tie_box = None if tie_aoi is None or tie_aoi is aoi else tie_aoi  # None: the AOI itself
    tie_aoi = aoi if tie_box is None else tie_box
    frame, prior_cams, failed = fit_cameras(views, tie_aoi, prior, options.camera_grid)
    seconds["cameras"] = time.perf_counter() - t0
    samples = aoi_samples(frame, aoi, (prior.min, prior.mid, prior.max))
    fine_frame = [frame]

    def refit(kept: Sequence[int], coarse: BundleSolution) -> list[Any]:
        """Cameras over the tie box x the coarse tie points' altitudes
        (:func:`fine_cube_altitudes`; the prior's cameras where they give none)."""
        lon, lat, alt = frame.to_geodetic(e=coarse.points[:, 0], n=coarse.points[:, 1],
                                          u=coarse.points[:, 2])
        cube = fine_cube_altitudes(alt, tie_aoi.contains(lon=lon, lat=lat), prior,
                                   options.altitude_min_points)
        if cube is None:
            fine_frame[0] = frame
            return list(prior_cams)
        fine, cams, failures = fit_cameras(views, tie_aoi, AltitudeRange(*cube),
                                           options.camera_grid, only=kept)
        if failures:  # a view that sees too little of the AOI's cube: the prior's cameras
            fine_frame[0] = frame
            return list(prior_cams)
        fine_frame[0] = fine
        return cams

    fixed, absent = fixed_view_indices(bundle_options.fixed_views, paths, names,
                                       absent_ok=fixed_absent_ok)
    tied = tie_views(images, prior_cams, names, options, bundle_options, samples=samples,
                     fine_cameras=refit, dropped=failed, fixed=fixed,
                     max_features=None if tie_box is None else feature_budgets(views, aoi, prior,
                                                                               options),
                     prior_range_up=(prior.min - frame.alt0, prior.max - frame.alt0))
    seconds.update({k: seconds.get(k, 0.0) + v for k, v in tied.seconds.items()})
    if len(tied.kept) < 2:
        why = "; ".join(f"{paths[d.index]}: {d.reason}" for d in tied.dropped) or "no view could be tied"
        raise CameraError(f"the sparse stage could not tie two views together: {why}")
    lost = [d for d in tied.dropped if d.index in fixed]
    if lost:
        raise CameraError("; ".join(
            f"{paths[d.index]}: a fixed view ([bundle] fixed_views) was dropped by the sparse "
            f"stage: {d.reason}" for d in lost))

    t0 = time.perf_counter()
    frame = fine_frame[0]
    altitude_range, altitude = altitude_range_from_points(
        tied.points, tied.obs, tied.point_error, frame, aoi, options, within=prior,
        confirm=tie_point_confirmer(tied, images),
        point_covariances=tied.point_covariances)
    seconds["altitude"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_all
    dropped = tuple(dataclasses.replace(d, path=paths[d.index]) for d in tied.dropped)
    result = SparseResult(
        paths=paths, names=names, corrections_px=tied.shifts, correction_sigma_px=tied.sigma,
        coarse_corrections_px=tied.coarse_shifts, dropped=dropped, prior_range=prior,
        altitude_range=altitude_range, altitude=altitude, tied=tied, frame=frame,
        min_matches=options.min_matches, seconds=seconds, fixed_views=tuple(fixed),
        fixed_absent=tuple(absent), tie_box=tie_box)
    return result

