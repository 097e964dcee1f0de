"""The appearance similarity that ranks a reference's sources (satsweep.dense.similarity):
from the metadata, from the sparse stage's probe matches, and which decided each pair."""

from __future__ import annotations

import math

import numpy as np

from satsweep.dense.similarity import (
    SAME_PASS_S,
    acquisition_passes,
    SEASON_SCALE_DAYS,
    SUN_SCALE_DEG,
    appearance_similarity,
    known_similarity,
    metadata_similarity,
    similarity_from_matches,
)
from satsweep.io.metadata import AcquisitionMetadata

NAN = float("nan")
# Float64 arithmetic on counts of a few hundred: exact to rounding.
EXACT = 1e-12


def _reference_from_matches(counts: np.ndarray) -> np.ndarray:
    """similarity_from_matches by loops: count / largest; unprobed pairs through one third view
    (the largest of the smaller similarities of the two legs); NaN where none."""
    n = len(counts)
    top = max(counts[i, j] for i in range(n) for j in range(n) if i != j and not math.isnan(counts[i, j]))
    s = np.full((n, n), NAN)
    for i in range(n):
        for j in range(n):
            s[i, j] = 1.0 if i == j else counts[i, j] / top
    out = s.copy()
    for i in range(n):
        for j in range(n):
            if math.isnan(s[i, j]):
                legs = [min(s[i, k], s[k, j]) for k in range(n)
                        if not math.isnan(s[i, k]) and not math.isnan(s[k, j])]
                out[i, j] = max(legs) if legs and max(legs) > 0 else NAN
    return out


def test_similarity_from_probe_matches_groups_the_dates():
    """Views 0-1 of one date (120 probe matches), 2-3 of another (90), 10-30 between dates; the
    pairs 1-3 and 0-4 were not probed, view 4 was probed with view 2 only. Each count over the
    largest; an unprobed pair through its best third view, against a loop reference."""
    c = np.full((5, 5), NAN)
    for (i, j), k in {(0, 1): 120, (2, 3): 90, (0, 2): 20, (0, 3): 30, (1, 2): 10,
                      (2, 4): 60}.items():
        c[i, j] = c[j, i] = k
    s = similarity_from_matches(c)
    np.testing.assert_allclose(s, _reference_from_matches(c), atol=EXACT)
    assert s[0, 1] == 1.0 and abs(s[2, 3] - 0.75) < EXACT
    assert abs(s[1, 3] - 0.25) < EXACT  # through view 0: min(1.0, 30 / 120)
    assert abs(s[3, 4] - 0.5) < EXACT  # through view 2: min(0.75, 60 / 120)
    # Nothing probed: nothing known but the diagonal
    none = similarity_from_matches(np.full((3, 3), NAN))
    assert np.isnan(none[~np.eye(3, dtype=bool)]).all() and (np.diag(none) == 1.0).all()


def test_metadata_then_tie_points_decide_each_pair():
    """Views 0-1 of one pass (metadata: 1), view 2 without metadata: its pairs come from the
    probe matches. Every pair decided, so the images are not measured (none are given)."""
    t0 = "2019-06-01T10:31:12Z"
    acq = [AcquisitionMetadata(acquisition_time_utc=t0, sun_azimuth_deg=150.0, sun_elevation_deg=60.0),
           AcquisitionMetadata(acquisition_time_utc="2019-06-01T10:31:40Z", sun_azimuth_deg=150.0,
                               sun_elevation_deg=60.0),
           None]
    c = np.array([[NAN, 10.0, 40.0], [10.0, NAN, 80.0], [40.0, 80.0, NAN]])
    sim, source = appearance_similarity(acq, [None] * 3, None, None, 0.0, matches=c)
    assert source[0, 1] == "metadata" and sim[0, 1] == 1.0
    assert source[0, 2] == source[2, 1] == "tie points"
    assert abs(sim[0, 2] - 0.5) < EXACT and abs(sim[1, 2] - 1.0) < EXACT


def test_known_similarity_leaves_to_the_images_what_nothing_else_tells():
    """Before the images are compared (the program forecast's selection): the metadata where
    both views have them, the probe matches where probed, and "images" with similarity 1 for
    the rest (view 3: no metadata, never probed); the same values as appearance_similarity's
    for every pair the images do not decide."""
    t0 = "2019-06-01T10:31:12Z"
    acq = [AcquisitionMetadata(acquisition_time_utc=t0, sun_azimuth_deg=150.0,
                               sun_elevation_deg=60.0),
           AcquisitionMetadata(acquisition_time_utc="2019-06-01T10:31:40Z", sun_azimuth_deg=150.0,
                               sun_elevation_deg=60.0),
           None, None]
    c = np.full((4, 4), NAN)
    for (i, j), k in {(0, 1): 10.0, (0, 2): 40.0, (1, 2): 80.0}.items():
        c[i, j] = c[j, i] = k
    sim, source = known_similarity(acq, matches=c)
    assert source[0, 1] == "metadata" and sim[0, 1] == 1.0
    assert source[0, 2] == source[1, 2] == "tie points" and abs(sim[0, 2] - 0.5) < EXACT
    assert all(source[i, 3] == source[3, i] == "images" and sim[i, 3] == 1.0 for i in range(3))
    assert (np.diag(sim) == 1.0).all()
    first = appearance_similarity(acq[:3], [None] * 3, None, None, 0.0, matches=c[:3, :3])
    np.testing.assert_array_equal(first[0], sim[:3, :3])
    assert (first[1] == source[:3, :3]).all()


def test_metadata_similarity_of_two_dates():
    """Sun directions 15 degrees apart at one elevation and 45 days apart: exp(-1/2) each."""
    a = AcquisitionMetadata(acquisition_time_utc="2019-06-01T10:30:00Z", sun_azimuth_deg=150.0,
                            sun_elevation_deg=90.0 - 1e-9)
    b = AcquisitionMetadata(acquisition_time_utc="2019-07-16T10:30:00Z", sun_azimuth_deg=150.0,
                            sun_elevation_deg=90.0 - SUN_SCALE_DEG)
    s = metadata_similarity(a, b)
    assert abs(s - math.exp(-1.0)) < 1e-6, s
    assert SEASON_SCALE_DAYS == 45.0
    assert metadata_similarity(a, None) is None


def test_leaf_season_over_the_year_and_the_hemispheres():
    """Leafless in winter, in leaf in summer, linear between (mid-ramp dates computed from the
    constants); half a year off in the south; no leafless season in the tropics; None without a
    date."""
    from satsweep.dense.similarity import LEAF_FALL_DOY, LEAF_OUT_DOY, TROPICS_LAT_DEG, leaf_season

    def on(date, lat=48.85):
        return leaf_season(AcquisitionMetadata(acquisition_time_utc=date + "T00:00:00Z"), lat)

    assert on("2019-01-15") == 0.0 and on("2019-12-20") == 0.0
    assert on("2019-07-01") == 1.0 and on("2019-09-15") == 1.0
    # 1 May 2019 is day 121 (its midnight: 121.0); 1 November is day 305.
    out, fall = LEAF_OUT_DOY, LEAF_FALL_DOY
    assert abs(on("2019-05-01") - (121.0 - out[0]) / (out[1] - out[0])) < 1e-12
    assert abs(on("2019-11-01") - (fall[1] - 305.0) / (fall[1] - fall[0])) < 1e-12
    assert on("2019-07-01", lat=-34.6) == 0.0 and on("2019-01-15", lat=-34.6) == 1.0
    assert on("2019-01-15", lat=TROPICS_LAT_DEG - 1.0) == 1.0
    assert leaf_season(AcquisitionMetadata(), 48.85) is None
    assert leaf_season(None, 48.85) is None


def test_acquisition_passes_group_views_of_one_pass():
    """Views acquired less than SAME_PASS_S apart (in time order, each within it of the one
    before) share a label; another day, or the same day hours later, is another pass; views
    without a date-time have none. Given out of order, the labels still group the same views."""
    def at(t):
        return AcquisitionMetadata(acquisition_time_utc=t)

    assert 9 * 60 < SAME_PASS_S  # 10:30 and 10:39 are one pass
    acq = [at("2019-06-01T10:30:00Z"), None, at("2019-06-01T14:30:00Z"),
           at("2019-06-01T10:39:00Z"), at("2019-07-16T10:30:00Z"), AcquisitionMetadata()]
    passes = acquisition_passes(acq)
    assert passes[1] is None and passes[5] is None
    assert passes[0] == passes[3]
    assert len({passes[0], passes[2], passes[4]}) == 3
    order = [4, 3, 2, 1, 0, 5]
    again = acquisition_passes([acq[i] for i in order])
    for i, j in ((0, 3), (0, 2), (2, 4)):
        assert (again[order.index(i)] == again[order.index(j)]) == (passes[i] == passes[j])


def _canopy_views(green_shares, size=100, seed=0):
    """Vegetation index images: every view has grass (0.17) on a fifth of its pixels, the rest
    0.01, and on ``green_shares`` of its pixels canopy in leaf (0.34, more than 1% of the stack's
    pixels: the greenest level)."""
    rng = np.random.default_rng(seed)
    views = []
    for share in green_shares:
        x = np.full(size * size, 0.01)
        order = rng.permutation(size * size)
        n_green = int(round(share * size * size))
        x[order[:n_green]] = 0.34
        x[order[n_green:n_green + size * size // 5]] = 0.17
        views.append(x.reshape(size, size))
    return views


def test_leaf_state_from_vegetation_scales_each_views_canopy_share():
    """The share of each view's pixels at least halfway between VEGETATION_INDEX_MIN and the
    stack's CANOPY_QUANTILE above the view's neutral level (NEUTRAL_QUANTILE: the 0.01 of most
    pixels; the canopy here, grass stays under it), scaled from the pale views' median share
    to the green views', against the shares the images were built with."""
    from satsweep.dense.similarity import leaf_state_from_vegetation

    shares = [0.02, 0.12, 0.10, 0.03, 0.13]
    views = _canopy_views(shares)
    # halfway 0.075: the pale views 0.02 and 0.03 (level 0.025), the green ones 0.10, 0.12
    # and 0.13 (level 0.12)
    expected = [min(1.0, max(0.0, (s - 0.025) / (0.12 - 0.025))) for s in shares]
    got = leaf_state_from_vegetation(views)
    assert np.allclose(got, expected, atol=EXACT)
    assert got[0] == 0.0 and got[4] == 1.0 and 0.0 < got[3] < got[2] < got[1] == 1.0
    # valid masks: pixels outside them do not count (view 2's canopy half masked out: 0.10 ->
    # about 0.053, a pale view now; the green level the median of 0.12 and 0.13)
    masks = [np.ones((100, 100), bool) for _ in views]
    green = views[2] >= 0.3
    masks[2] = ~(green & (np.arange(100)[:, None] < 50))
    share_2 = float(np.mean(views[2][masks[2]] >= 0.3))
    assert 0.03 < share_2 < 0.075
    got = leaf_state_from_vegetation(views, masks)
    low = float(np.median([0.02, 0.03, share_2]))
    assert np.allclose(got[2], (share_2 - low) / (0.125 - low), atol=EXACT)


def test_leaf_state_from_vegetation_ignores_each_views_colour_cast():
    """A cast that moves every pixel's index of a view alike (each date's image stretched on
    its own, haze) leaves the estimate as it was: each view is taken from its neutral level."""
    from satsweep.dense.similarity import leaf_state_from_vegetation

    views = _canopy_views([0.02, 0.12, 0.08, 0.03])
    plain = leaf_state_from_vegetation(views)
    assert 0.0 < plain[2] < 1.0
    cast = [v + c for v, c in zip(views, (0.0, 0.02, 0.12, -0.10))]
    assert np.allclose(leaf_state_from_vegetation(cast), plain, atol=EXACT)


def test_leaf_state_unknown_without_a_season_in_the_colours():
    """None where a view has no index (a panchromatic image), where no pixel is greener than
    the vegetation threshold, and where the shares differ too little (LEAF_SHARE_SPREAD) or by
    too small a ratio (LEAF_SHARE_RATIO): every date alike."""
    from satsweep.dense.similarity import (LEAF_SHARE_RATIO, LEAF_SHARE_SPREAD,
                                           leaf_state_from_vegetation)

    views = _canopy_views([0.02, 0.12])
    assert leaf_state_from_vegetation([views[0], None]) is None
    assert leaf_state_from_vegetation([np.full((10, 10), 0.05)] * 3) is None
    low = 0.10
    assert leaf_state_from_vegetation(_canopy_views([low, low * LEAF_SHARE_RATIO - 0.01])) is None
    close = _canopy_views([0.01, 0.01 + LEAF_SHARE_SPREAD - 0.005])
    assert leaf_state_from_vegetation(close) is None
    apart = _canopy_views([0.01, 0.01 + LEAF_SHARE_SPREAD + 0.005])
    assert leaf_state_from_vegetation(apart) == [0.0, 1.0]
