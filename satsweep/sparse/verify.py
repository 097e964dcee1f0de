"""Photometric confirmation of single tie points: is a point seen where its track puts it by
views that did not match it?

The altitude range's ends are altitudes that several tie points share
(:func:`satsweep.sparse.tiepoints.supported_extremes`), because a wrong match accepted by two
views anywhere along its epipolar line gets a height of its own. The top of a lone tower is the
exception: its plain roof gives one or two features, seen by two views, and the range that
ignores it cuts the tower off. This module tells the two apart with the views themselves: a
small horizontal patch of ground at the point is sampled in every view that sees it, at heights
stepping through the point's altitude (the plane sweep of one patch); a view *confirms* the
point when its patch correlates best with the track's first view at the point's altitude (within
``tolerance_m``) and well (normalised cross-correlation ``min_ncc`` or more: gain, offset and most
of a date's radiometry cancel). A wrong match sits at an altitude where the other views see
different ground: they correlate better elsewhere or not at all.

Figures (tools/bench_multidate.py's 384 px multi-date scenes, seeds 0-1 of 10 and of 20 views;
tie points with the sparse stage's corrected cameras, judged against the exact surface): with
``MIN_NCC`` 0.7 and two confirming views outside the track, 24-68% of the right points are
confirmed and none of the 14 points that lie outside the true altitude range (one of them with a
single confirming view). Seed 0 of 10 views: the one tie point on its lone 156.6 m tower
(of a 100-125 m town) is confirmed by two views outside its track; the range goes from 95..138
m to 95..165 m (the prior's top), and the tower from 0% to 99.7% of its cells within 1 m.
A three-view stack has one view outside a two-view track: its top is never raised.

A view *contradicts* the point when its patch correlates as well (``min_ncc`` or more) at
another altitude, at least ``PEAK_EXCLUSION_PX`` pixels of parallax away: it sees the
reference's patch elsewhere. The heights tried span ``SEARCH_HALF_M`` about the point and, below
it, down to the range's supported floor (``point_evidence``'s ``below_m``): a wrong match far
above the roofs has the surface under it out of reach of the search about it, where no view can
see it elsewhere. Down there a view outside the track contradicts the point where it correlates
``min_ncc`` or more and does not see the point (under ``min_ncc`` within ``tolerance_m``); a view
that sees the point keeps its judgement about it, since the many heights below give chance peaks
to smooth patches (issue-form seed 11 with RPCs over 1000 m: a two-view point 40 m above its
roofs, confirmed by three views, is contradicted by 12 of 16; docs/measurements.md, fiftieth
session).

The point is confirmed when at least ``MIN_OTHER_VIEWS`` views
outside its track confirm it and more than ``CONFIRM_OVER_CONTRADICT`` times as many confirm it
as contradict it. Without that second condition (more confirming than contradicting, first) a
19-view stack of 0.3 m, 8-bit multi-date views (``satsweep synth --views 19 --acquisitions 13
--gsd 0.3 --product rgb8``, seed 7) raised its altitude range's top to 222 m
(the truth's top: 154 m, the supported top 159 m): a two-view match 68 m above the roofs, in a
patch of smooth shading whose broad correlation curves peaked by chance near the point in three
views (0.70-0.73), while three others correlated at 0.82-0.95 elsewhere. Over the 43 points
that the range asked about on 34 multi-date scenes (tools/bench_multidate.py's v10, v20, one
view per date and 8-bit scenes, 0.3 m scenes and that one), the rule confirms the same 2 of the
6 that lie within 3 m of the truth's altitudes (the lone tower among them) and none of the 37
beyond, against 2 before.

Twice as many, not merely more: over the points that 41 stacks' ranges asked about at the
forty-eighth session's code (tools/bench_multidate.py's v10 seeds 0-9, one view per date 5 and
10 views, 33.45 S seeds 31-38, 20 views, 5 views, the issue-form 0.3 m seeds 11-13), two points
were confirmed by two views against one, and both lay above the truth's top: 19 m (33.45 S seed
37) and 64 m (issue-form seed 12, whose range went to 95..214 m for a truth of 99..150 m when
the fine adjustment's corrections moved by 0.005 px and one of the two contradicting views
fell under ``MIN_NCC``). The right points confirmed there had 3 or 4 views against none.

Three times: with RPCs that span a kilometre of heights as real ones do (``satsweep synth
--rpc-height-scale 500``), issue-form seed 12 (19 views of one date each at 0.3 m) confirmed a
two-view point 27 m above its roofs with three views against one, and its range reached 192 m
for a truth of 99..150 m. Over the 35 stacks scanned so (tools/bench_multidate.py's 10 views in
passes and of one date each, 5 views so, 3 of one date each, four held-out scenes, the
issue-form seeds 11-13), the right points confirmed had 2-8 views against none, and one 5
against 1 (10 views of one date each, seed 4, a roof 0.9 m above the truth's top): no point of
the 76 stacks scanned was confirmed wrongly by more than three times as many views, except one
9 m above the top of a 33.45 S stack with six against none (forty-eighth session).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import cv2
import numpy as np

from satsweep.geometry.camera import ground_sample_distance
from satsweep.sparse.triangulation import project, projection_jacobian

# Half-side of the ground patch, in ground samples of the reference view (a 9 x 9 patch): small,
# because the point is a roof corner and the patch's part off the roof differs between views.
PATCH_RADIUS = 4
# Heights tried around the point's altitude (m) and their step: beyond a pixel of parallax in
# any pair of the views (0.5 m pixels, base-to-height ratios of 0.1 or more: 5 m or less).
SEARCH_HALF_M = 10.0
SEARCH_STEP_M = 0.5
# Highest correlation at the point's altitude, within this many metres.
TOLERANCE_M = 1.5
# Least normalised cross-correlation of a confirming view's patch with the reference's.
MIN_NCC = 0.7
# Fewest confirming views outside the point's own track.
MIN_OTHER_VIEWS = 2
# The confirming views outside the track must outnumber the contradicting ones more than this
# many times (module docstring).
CONFIRM_OVER_CONTRADICT = 3
# A view whose best correlation lies at least this many pixels of parallax from the point's
# altitude contradicts it (a pixel or two is the width of a correlation peak of 9 x 9 samples).
PEAK_EXCLUSION_PX = 2.0
# A patch whose values vary less than this (tonemapped units, 0..1 scale) has no texture.
MIN_STD = 1e-3


def _ground_patch(P_ref: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(S, 2) east/north offsets (m) of a square patch of the reference view's ground samples."""
    pixel_m = ground_sample_distance(P_ref, X)
    r = np.arange(-PATCH_RADIUS, PATCH_RADIUS + 1, dtype=np.float64) * pixel_m
    e, n = np.meshgrid(r, r)
    return np.stack([e.ravel(), n.ravel()], axis=1)


def _parallax_px_per_m(P_ref: np.ndarray, P_v: np.ndarray, X: np.ndarray) -> float:
    """Pixels that view ``P_v``'s image of a point moves per metre of altitude along the
    reference's (``P_ref``) line of sight through ENU point ``X``: the pair's parallax there."""
    centre = -np.linalg.solve(P_ref[:, :3], P_ref[:, 3])
    ray = X - centre
    ray = ray / ray[2]
    _, _, J = projection_jacobian(P_v[None], np.zeros(1, np.int64), X[None])
    return float(np.hypot(*(J[0] @ ray)))


def _sample(image: np.ndarray, xy: np.ndarray, rows: int) -> np.ndarray:
    """Bilinear samples of ``image`` at pixels ``xy`` (K, 2), as ``rows`` rows of K / rows
    (OpenCV's remap takes fewer than 32767 of each), NaN where one falls outside."""
    h, w = image.shape[:2]
    inside = ((xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] <= h - 1))
    maps = xy.astype(np.float32).reshape(rows, -1, 2)
    values = cv2.remap(np.asarray(image, np.float32), maps, None, cv2.INTER_LINEAR).ravel()
    return np.where(inside, values, np.nan)


def _ncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of rows of ``a`` and ``b`` (H, S); NaN without texture or
    where a row holds NaN."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    sa, sb = np.sqrt((a * a).mean(axis=1)), np.sqrt((b * b).mean(axis=1))
    out = (a * b).mean(axis=1) / np.maximum(sa * sb, 1e-12)
    out[(sa < MIN_STD) | (sb < MIN_STD)] = np.nan
    return out


@dataclasses.dataclass(frozen=True)
class PointEvidence:
    """What the views say of one tie point (module docstring)."""

    track: tuple[int, ...]  # the views of the point's track (its first: the reference)
    confirming: tuple[int, ...]  # views whose patch correlates best at the point's altitude
    contradicting: tuple[int, ...]  # views outside the track that correlate as well elsewhere

    @property
    def outside(self) -> int:
        """The confirming views outside the point's track."""
        return sum(1 for v in self.confirming if v not in self.track)

    @property
    def confirmed(self) -> bool:
        """At least MIN_OTHER_VIEWS views outside the track confirm the point, and more than
        CONFIRM_OVER_CONTRADICT times as many as contradict it."""
        return (self.outside >= MIN_OTHER_VIEWS
                and self.outside > CONFIRM_OVER_CONTRADICT * len(self.contradicting))


def point_evidence(X: np.ndarray, track_views: Sequence[int], images: Sequence[np.ndarray],
                   P: dict[int, np.ndarray], *, below_m: float = SEARCH_HALF_M) -> PointEvidence:
    """The views that confirm and contradict ENU point ``X`` (module docstring).

    ``images``: the views' tonemapped images (indexed as the views); ``P``: per view tried, its
    corrected 3x4 camera (ENU -> that image's pixels). The track's first view is the reference.
    The heights tried reach ``below_m`` metres under the point (SEARCH_HALF_M at least) and
    SEARCH_HALF_M over it.
    """
    track = tuple(int(t) for t in track_views)
    ref = track[0]
    reach = max(SEARCH_HALF_M, float(below_m)) if np.isfinite(below_m) else SEARCH_HALF_M
    heights = np.arange(-SEARCH_STEP_M * np.floor(reach / SEARCH_STEP_M),
                        SEARCH_HALF_M + 0.5 * SEARCH_STEP_M, SEARCH_STEP_M)
    offsets = _ground_patch(P[ref], X)
    S = offsets.shape[0]
    grid = np.empty((heights.size * S, 3))
    grid[:, 0] = X[0] + np.tile(offsets[:, 0], heights.size)
    grid[:, 1] = X[1] + np.tile(offsets[:, 1], heights.size)
    grid[:, 2] = X[2] + np.repeat(heights, S)

    def patches(v: int) -> np.ndarray | None:
        """(heights, S) samples of view v; a height with a sample outside the image is NaN."""
        xy, depth = project(P[v][None], np.zeros(len(grid), np.int64), grid)
        if not np.all(depth > 0):
            return None
        values = _sample(images[v], xy, heights.size).reshape(heights.size, S)
        values[~np.all(np.isfinite(values), axis=1)] = np.nan
        return values

    reference = patches(ref)
    at_point = int(np.argmin(np.abs(heights)))
    if reference is None or not np.isfinite(reference[at_point]).all():
        return PointEvidence(track=track, confirming=(), contradicting=())
    # The heights within SEARCH_HALF_M of the point (the ones each view is judged on), and
    # those within TOLERANCE_M (a view's correlation there: how well it sees the point).
    about = np.abs(heights) <= SEARCH_HALF_M + 1e-9
    at = np.abs(heights) <= TOLERANCE_M + 1e-9
    confirming, contradicting = [], []
    for v in sorted(P):
        if v == ref:
            continue
        other = patches(v)
        if other is None:
            continue
        score = _ncc(reference, other)
        if not np.isfinite(score).any():
            continue
        near = np.where(about, score, np.nan)
        if np.isfinite(near).any():
            best = int(np.nanargmax(near))
            if score[best] >= MIN_NCC:
                if abs(heights[best]) <= TOLERANCE_M:
                    confirming.append(v)
                    continue
                if (v not in track and abs(heights[best]) * _parallax_px_per_m(P[ref], P[v], X)
                        >= PEAK_EXCLUSION_PX):
                    contradicting.append(v)
                    continue
        # Deeper (below_m): a view outside the track that does not see the patch at the point
        # (under MIN_NCC within TOLERANCE_M) and sees it down there contradicts; one that sees it
        # at the point keeps its judgement above, whatever chance peak the deeper heights hold.
        deep = np.where(about, np.nan, score)
        if v in track or not np.isfinite(deep).any() or np.nanmax(deep) < MIN_NCC:
            continue
        seen_at_point = np.isfinite(score[at]).any() and np.nanmax(score[at]) >= MIN_NCC
        if not seen_at_point:
            contradicting.append(v)
    return PointEvidence(track=track, confirming=tuple(confirming),
                         contradicting=tuple(contradicting))
