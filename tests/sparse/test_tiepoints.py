"""The altitude range of the sparse stage's adjusted tie points (satsweep.sparse.tiepoints): the
range that reconstruct and cameras sweep when the user gives none."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from satsweep.geometry.altitude import AltitudeRange
from satsweep.sparse.options import SparseOptions
from satsweep.sparse.tiepoints import (
    TOP_VIEW_SETS_MIN_VIEWS,
    altitude_range_from_points,
    highest_supported_near,
    supported_extremes,
    view_members,
)


# -- the range of the sparse stage's adjusted tie points ---------------------------------------
def test_supported_extremes_ignore_lone_heights():
    rng = np.random.default_rng(0)
    ground = rng.uniform(100.0, 101.0, 300)
    roof = np.array([141.0, 142.5, 143.0])  # a roof's corners
    lone = np.array([-400.0, 60.0, 190.0, 900.0])  # wrong matches, each at a height of its own
    a = np.concatenate([ground, roof, lone])
    lo, hi = supported_extremes(a, support=2, window_m=3.0)
    assert lo == ground.min() and hi == 143.0
    assert supported_extremes(a, support=1, window_m=3.0) == (-400.0, 900.0)
    # fewer values than the support: the extremes
    assert supported_extremes(np.array([5.0]), support=3, window_m=1.0) == (5.0, 5.0)


@pytest.mark.parametrize("radius", [0.0, 5.0, 20.0])
def test_highest_supported_near_against_brute_force(radius):
    """Against a loop over every point and every other: the highest point with ``support``
    points (itself included) within the window under it and the radius around it."""
    rng = np.random.default_rng(1)
    alt = np.round(rng.uniform(0.0, 40.0, 300), 1)  # ties of altitude included
    xy = rng.uniform(0.0, 100.0, (300, 2))
    for support in (1, 2, 3, 5):
        ref = None
        for i in range(alt.size):
            near = (alt <= alt[i]) & (alt >= alt[i] - 3.0)
            if radius > 0.0:
                near &= np.hypot(*(xy - xy[i]).T) <= radius
            if near.sum() >= support and (ref is None or alt[i] > ref):
                ref = float(alt[i])
        assert highest_supported_near(alt, xy, support, 3.0, radius) == ref, (support, radius)
    assert highest_supported_near(alt[:1], xy[:1], 2, 3.0, radius) is None


class _Frame:
    """ENU = (lon, lat, alt) offsets, for points given directly in degrees and metres."""

    @staticmethod
    def to_geodetic(*, e, n, u):
        return np.asarray(e), np.asarray(n), np.asarray(u)

    @staticmethod
    def from_geodetic(*, lon, lat, alt):
        return np.asarray(lon), np.asarray(lat), np.asarray(alt)


def _adjusted(alts, views, errors, lon=0.5):
    from satsweep.geometry.aoi import AOI
    from satsweep.sparse.tracks import Observations

    alts = np.asarray(alts, float)
    views = np.asarray(views)
    points = np.column_stack([np.full(alts.size, lon), np.full(alts.size, 0.5), alts])
    obs = Observations(point=np.repeat(np.arange(alts.size), views),
                       view=np.concatenate([np.arange(k) for k in views]),
                       xy=np.zeros((int(views.sum()), 2)), n_points=alts.size)
    return points, obs, np.asarray(errors, float), AOI(0.0, 0.0, 1.0, 1.0)


def test_adjusted_range_takes_its_floor_from_points_of_three_views():
    """Ground at 100 m seen by 3 views, a roof at 150 m seen by 2, two-view wrong matches at
    70 m (a pair of them) and one with a large error at 400 m: the floor is the three-view
    ground's, the top the two-view roof's, each widened by its margin."""
    o = SparseOptions()
    alts = [100.0 + 0.1 * k for k in range(30)] + [150.0, 151.0] + [70.0, 70.5] + [400.0]
    views = [3] * 30 + [2, 2] + [2, 2] + [2]
    errors = [0.2] * 34 + [3.0]
    points, obs, err, aoi = _adjusted(alts, views, errors)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng == AltitudeRange(100.0 - o.altitude_margin_below_m, 151.0 + o.altitude_margin_above_m)
    assert record["tie_points"] == 34 and record["tie_points_for_the_lowest"] == 30
    # kept within a prior range it overlaps
    rng, _ = altitude_range_from_points(points, obs, err, _Frame, aoi, o,
                                        within=AltitudeRange(98.0, 160.0))
    assert rng == AltitudeRange(98.0, 160.0)
    # the supported floor and top past the prior's (the corrected cameras put the scene there):
    # the range reaches them, and only the margins beyond the prior are cut
    rng, _ = altitude_range_from_points(points, obs, err, _Frame, aoi, o,
                                        within=AltitudeRange(103.0, 150.5))
    assert rng == AltitudeRange(100.0, 151.0)
    rng, _ = altitude_range_from_points(points, obs, err, _Frame, aoi, o,
                                        within=AltitudeRange(99.0, 150.5))
    assert rng == AltitudeRange(99.0, 151.0)


def test_tie_points_of_vague_heights_do_not_bound_the_range():
    """Ground at 100 m and a roof at 150 m of views 0.3 and 0.1 apart (base-to-height); 40 points
    of a pair along nearly one line of sight (0.004, as bench_multidate's one view per date seed
    39) spread from
    -300 to 400 m, in pairs within the support window: with their height sigmas given, they do
    not raise the top, and the record counts them; without, the highest pair holds the top."""
    o = SparseOptions()
    ground = [100.0 + 0.05 * k for k in range(30)]
    roof = [150.0, 150.5, 151.0]
    vague = list(np.repeat(np.linspace(-300.0, 400.0, 20), 2) + np.tile([0.0, 0.5], 20))
    alts = ground + roof + vague
    views = [3] * 30 + [2] * 3 + [2] * len(vague)
    points, obs, err, aoi = _adjusted(alts, views, [0.2] * len(alts))
    # per pixel, a GSD of 0.5 m: 0.35 m across the lines of sight, 2 x 0.35 / (B/H) along them
    # (here vertical)
    bh = np.array([0.3] * 30 + [0.1] * 3 + [0.004] * len(vague))
    cov = np.zeros((len(bh), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = 0.35 ** 2
    cov[:, 2, 2] = (0.7 / bh) ** 2
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o, point_covariances=cov)
    assert rng == AltitudeRange(100.0 - o.altitude_margin_below_m, 151.0 + o.altitude_margin_above_m)
    assert record["vague_tie_points"] == len(vague) and record["tie_points"] == 33
    plain, _ = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert plain.max > 400.0
    # the bound is the option's: at 0.003 they count again
    loose = dataclasses.replace(o, altitude_min_bh=0.003)
    again, record = altitude_range_from_points(points, obs, err, _Frame, aoi, loose,
                                               point_covariances=cov)
    assert again == plain and record["vague_tie_points"] == 0


def test_adjusted_range_takes_a_ground_of_two_view_points_under_that_of_three():
    """One view per date: the ground's texture changes, so its tie points are of two views
    (60 at 100-101 m) while the roofs' are of three or more (30 at 120 m, 30 at 150 m). The
    floor is the two-view ground's, not the lower roof's; a handful of two-view points agreeing
    lower (4 at 60 m, fewer than FEWER_VIEWS_MIN_SUPPORT) does not set it, nor does a two-view
    ground within the margin under the three-view floor."""
    from satsweep.sparse.tiepoints import FEWER_VIEWS_MIN_SUPPORT

    o = SparseOptions()
    ground = list(np.linspace(100.0, 101.0, 60))
    roofs = [120.0 + 0.01 * k for k in range(30)] + [150.0 + 0.01 * k for k in range(30)]
    wrong = [60.0, 60.5, 61.0, 61.5][:FEWER_VIEWS_MIN_SUPPORT - 1]
    alts = ground + roofs + wrong
    views = [2] * 60 + [3] * 60 + [2] * len(wrong)
    points, obs, err, aoi = _adjusted(alts, views, [0.2] * len(alts))
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 100.0 - o.altitude_margin_below_m
    assert record["floor_from_fewer_views"]["altitude_m"] == 100.0
    assert record["floor_from_fewer_views"]["points"] == 60 + len(wrong)
    # switched off: the floor of the three-view points
    off = dataclasses.replace(o, altitude_floor_fewer_fraction=0.0)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, off)
    assert rng.min == 120.0 - o.altitude_margin_below_m and "floor_from_fewer_views" not in record
    # a two-view ground within the margin under the three-view floor leaves it
    near = [a + 18.5 for a in ground] + roofs + wrong  # 118.5-119.5 m against 120 m
    points, obs, err, aoi = _adjusted(near, views, [0.2] * len(near))
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 120.0 - o.altitude_margin_below_m and "floor_from_fewer_views" not in record


def test_adjusted_range_needs_enough_points_near_the_aoi():
    """Points count within altitude_aoi_margin_m of the AOI (a roof across its edge may have its
    features outside), not farther."""
    o = SparseOptions()
    far = 1.0 + o.altitude_aoi_margin_m + 0.5  # the AOI spans 0..1 (units of _Frame: metres)
    flat = [100.0 + 0.01 * k for k in range(30)]  # (points at one spot and height are one)
    points, obs, err, aoi = _adjusted(flat, [2] * 30, [0.1] * 30, lon=far)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng is None and "only 0 adjusted tie points within 25 m of the AOI" in record["reason"]
    near = 1.0 + o.altitude_aoi_margin_m - 0.5
    points, obs, err, aoi = _adjusted(flat, [2] * 30, [0.1] * 30, lon=near)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng is not None and record["tie_points_near_aoi"] == 30
    # too few points of three views: the floor comes from all of them, where
    # FEWER_VIEWS_MIN_SUPPORT of them agree (two wrong two-view matches do not)
    from satsweep.sparse.tiepoints import FEWER_VIEWS_MIN_SUPPORT

    low = [90.0 + 0.5 * k for k in range(FEWER_VIEWS_MIN_SUPPORT)]
    points, obs, err, aoi = _adjusted(flat[:25] + low, [2] * (25 + len(low)), [0.1] * (25 + len(low)))
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 90.0 - o.altitude_margin_below_m
    assert record["tie_points_for_the_lowest"] == 25 + len(low)
    points, obs, err, aoi = _adjusted(flat[:25] + low[:2], [2] * 27, [0.1] * 27)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 100.0 - o.altitude_margin_below_m


def test_the_top_needs_its_support_on_one_roof():
    """Two two-view wrong matches 1.7 m apart in height but far apart across the AOI (a 20-view
    stack: 163 and 161 m, 45 m apart, over a town whose top is at 126 m) do not set the top;
    a roof's two corners near each other do. With the radius 0 the chance pair sets it."""
    alts = [100.0 + 0.1 * k for k in range(30)] + [126.0, 125.5] + [162.9, 161.2]
    views = [3] * 30 + [2, 2] + [2, 2]
    points, obs, err, aoi = _adjusted(alts, views, [0.2] * 34)
    points[30:32, 0] = [0.50, 0.55]  # the roof's corners
    points[32:34, 0] = [0.05, 0.95]  # the chance pair, across the AOI
    o = dataclasses.replace(SparseOptions(), altitude_support_radius_m=0.3)  # AOI units
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert record["supported_extremes_m"][1] == 126.0
    assert rng.max == 126.0 + o.altitude_margin_above_m
    anywhere = dataclasses.replace(o, altitude_support_radius_m=0.0)
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, anywhere)
    assert record["supported_extremes_m"][1] == 162.9


def test_twin_tie_points_do_not_support_each_other():
    """SIFT's twin keypoints (one position, two orientations) matched in the views make two
    tracks at one spot: a wrong match of such twins at 69.5 m does not hold the floor of a
    ground at 100 m by itself, while two wrong matches at two spots would (points of three
    views, whose floor two agreeing points hold)."""
    from satsweep.sparse.tiepoints import DUPLICATE_POINT_M

    o = SparseOptions()
    ground = [100.0 + 0.05 * k for k in range(40)]
    alts = ground + [69.5, 69.5]
    points, obs, err, aoi = _adjusted(alts, [3] * len(alts), [0.2] * len(alts))
    points[:, 0] = np.linspace(0.1, 0.9, len(alts))  # each point at a spot of its own ...
    points[-1] = points[-2]  # ... but the twins
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 100.0 - o.altitude_margin_below_m
    assert record["duplicate_tie_points"] == 1 and record["tie_points"] == len(ground) + 1
    points[-1, 0] += 10 * DUPLICATE_POINT_M  # two spots: two wrong matches agreeing
    rng, record = altitude_range_from_points(points, obs, err, _Frame, aoi, o)
    assert rng.min == 69.5 - o.altitude_margin_below_m and record["duplicate_tie_points"] == 0


def _observed(view_lists):
    from satsweep.sparse.tracks import Observations

    point = np.concatenate([np.full(len(v), i) for i, v in enumerate(view_lists)])
    view = np.concatenate([np.asarray(v) for v in view_lists])
    return Observations(point=point, view=view, xy=np.zeros((point.size, 2)),
                        n_points=len(view_lists))


def test_view_members_mark_each_point_s_views():
    obs = _observed([[0, 1], [1, 0], [0, 2], [2, 1, 0], [3, 4]])
    want = np.zeros((5, 5), bool)
    for i, v in enumerate([[0, 1], [1, 0], [0, 2], [2, 1, 0], [3, 4]]):
        want[i, v] = True
    np.testing.assert_array_equal(view_members(obs, 5), want)
    from satsweep.sparse.tracks import Observations

    none = Observations(point=np.zeros(0, int), view=np.zeros(0, int), xy=np.zeros((0, 2)),
                        n_points=0)
    assert view_members(none, 0).shape == (0, 0)


def test_a_top_of_one_set_of_views_needs_the_views_confirmation():
    """A repeated pattern matched wrongly by one pair: its points share a height and a place
    (a ten-view stack: 379 m over roofs that end at 158 m). Where TOP_VIEW_SETS_MIN_VIEWS views
    or more are tied, a top held by one set of views above the top of two sets stands only
    where the other views confirm it; a roof matched by two pairs needs nothing."""
    n_ground = 30
    alts = [100.0 + 0.1 * k for k in range(n_ground)] + [126.0, 125.5] + [379.0, 378.2]
    m = TOP_VIEW_SETS_MIN_VIEWS  # views tied
    tracks = ([list(range(m)), list(range(m - 1))] * (n_ground // 2)
              + [[0, 1], [4, 5]]  # the roof: two pairs
              + [[2, 3], [3, 2]])  # the pattern: one pair
    points = np.column_stack([np.full(len(alts), 0.5), np.full(len(alts), 0.5), alts])
    err = np.full(len(alts), 0.2)
    aoi = _adjusted([0.0], [1], [0.0])[3]
    o = SparseOptions()
    asked = []

    def deny(i, below_m):
        asked.append(i)
        return False

    rng, record = altitude_range_from_points(points, _observed(tracks), err, _Frame, aoi, o,
                                             confirm=deny)
    assert record["supported_extremes_m"][1] == 126.0
    assert asked[0] == len(alts) - 2  # the pattern's top point, asked first
    assert record["one_view_set_top"] == {"altitude_m": 379.0, "confirmed": False}
    rng, record = altitude_range_from_points(points, _observed(tracks), err, _Frame, aoi, o,
                                             confirm=lambda i, below_m: True)
    assert record["supported_extremes_m"][1] == 379.0
    # Without views to ask (confirm None): as before.
    rng, record = altitude_range_from_points(points, _observed(tracks), err, _Frame, aoi, o)
    assert record["supported_extremes_m"][1] == 379.0
    # The roof held by one pair too, nothing confirmed: the ground's top (two sets of views).
    roof_one_pair = [t if i != n_ground + 1 else [0, 1] for i, t in enumerate(tracks)]
    rng, record = altitude_range_from_points(points, _observed(roof_one_pair), err, _Frame,
                                             aoi, o, confirm=lambda i, below_m: False)
    assert record["supported_extremes_m"][1] == alts[n_ground - 1]
    # Fewer views tied: one pair's support is enough, as before (a small stack's roofs).
    fewer = [[v for v in t if v < m - 2] for t in tracks]
    fewer = [t if len(t) >= 2 else [0, 1] for t in fewer]
    rng, record = altitude_range_from_points(points, _observed(fewer), err, _Frame, aoi, o,
                                             confirm=lambda i, below_m: False)
    assert record["supported_extremes_m"][1] == 379.0


def test_a_top_of_two_pairs_with_a_view_in_common_needs_the_views_confirmation():
    """Two pairs that share a view are not two sets of views for the top (a 19-view stack, seed
    75: points of views 9-12 and 9-13 held a top 68 m over the roofs): the top needs the views'
    confirmation as one pair's would; a track of three views beside a pair with a view in
    common counts as a second set."""
    n_ground = 30
    alts = [100.0 + 0.1 * k for k in range(n_ground)] + [126.0, 125.5] + [228.0, 225.6]
    m = TOP_VIEW_SETS_MIN_VIEWS
    ground = [list(range(m)), list(range(m - 1))] * (n_ground // 2)
    points = np.column_stack([np.full(len(alts), 0.5), np.full(len(alts), 0.5), alts])
    err = np.full(len(alts), 0.2)
    aoi = _adjusted([0.0], [1], [0.0])[3]
    o = SparseOptions()
    for roof, wrong, want in (([[0, 1], [4, 5]], [[2, 3], [2, 4]], 126.0),
                              ([[0, 1], [4, 5]], [[2, 3], [2, 3, 4]], 228.0),
                              ([[0, 1], [1, 5]], [[2, 3], [2, 4]], alts[n_ground - 1])):
        asked = []

        def deny(i, below_m):
            asked.append(i)
            return False

        rng, record = altitude_range_from_points(points, _observed(ground + roof + wrong), err,
                                                 _Frame, aoi, o, confirm=deny)
        assert record["supported_extremes_m"][1] == want, (roof, wrong)
        if want != 228.0:
            assert asked[0] == len(alts) - 2
            assert record["one_view_set_top"] == {"altitude_m": 228.0, "confirmed": False}


def test_highest_supported_near_with_view_members():
    """Two sets of views count where they have no view in common, or where they differ and one
    holds three views or more."""
    alt = np.array([100.0, 100.5, 126.0, 125.5, 379.0, 378.2])
    xy = np.zeros((6, 2))

    def members(view_lists):
        out = np.zeros((len(view_lists), 8), bool)
        for i, v in enumerate(view_lists):
            out[i, v] = True
        return out

    ground = [[0, 1, 2], [0, 1, 2, 3]]
    for roof, wrong, want in (([0, 1], [4, 5]), ([2, 3], [2, 4]), 126.0), \
                              (([0, 1], [4, 5]), ([2, 3], [2, 3, 4]), 379.0), \
                              (([0, 1], [1, 5]), ([2, 3], [2, 4]), 100.5), \
                              (([0, 1], [1, 5]), ([2, 3], [3, 2]), 100.5):
        got = highest_supported_near(alt, xy, 2, 3.0, 10.0, min_view_sets=2,
                                     view_members=members(ground + list(roof) + list(wrong)))
        assert got == want, (roof, wrong)
    assert highest_supported_near(alt, xy, 2, 3.0, 10.0, view_members=members(
        ground + [[0, 1], [0, 1], [2, 3], [2, 3]])) == 379.0  # one set is enough
    with pytest.raises(ValueError, match="min_view_sets"):
        highest_supported_near(alt, xy, 2, 3.0, 10.0, min_view_sets=3,
                               view_members=members(ground * 3))
    with pytest.raises(ValueError, match="needs view_members"):
        highest_supported_near(alt, xy, 2, 3.0, 10.0, min_view_sets=2)
