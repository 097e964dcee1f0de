"""View selection against analytic satellite geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from satsweep.dense.selection import (
    CLOSE_SIMILARITY,
    ViewSelectionOptions,
    b_over_h,
    select_views,
    view_geometry,
)
from satsweep.errors import CameraError, OptionsError

ORBIT_M = 600e3
TIGHT = 1e-9  # pure float64 geometry, no approximation involved


@dataclasses.dataclass
class Pinhole:
    P: np.ndarray
    center: np.ndarray
    width: int = 400
    height: int = 400


def look_at(center, focal=1.2e6, size=400):
    """A pinhole at ``center`` looking at the ENU origin, principal point at the image centre."""
    center = np.asarray(center, float)
    z = -center / np.linalg.norm(center)
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]])
    P = K @ np.hstack([R, -R @ center[:, None]])
    return Pinhole(P=P, center=center, width=size, height=size)


def satellite(off_nadir_deg, azimuth_deg):
    t, a = np.radians(off_nadir_deg), np.radians(azimuth_deg)
    h = ORBIT_M * np.tan(t)
    return look_at([h * np.sin(a), h * np.cos(a), ORBIT_M])


def test_geometry_of_a_known_view():
    g = view_geometry(satellite(20, 90).center, np.zeros(3))
    assert g.incidence_deg == pytest.approx(20, abs=TIGHT)
    assert g.azimuth_deg == pytest.approx(90, abs=TIGHT)


def test_b_over_h_is_sum_of_tangents_for_opposite_views():
    g1 = view_geometry(satellite(10, 0).center, np.zeros(3))
    g2 = view_geometry(satellite(5, 180).center, np.zeros(3))
    assert b_over_h(g1, g2) == pytest.approx(np.tan(np.radians(10)) + np.tan(np.radians(5)), abs=TIGHT)


def test_two_views_each_reference_once():
    cams = [satellite(8, 0), satellite(7, 180)]
    sel = select_views(cams, mid_height=0.0)
    assert sorted(sel.references) == [0, 1]
    assert sel.sources == {0: (1,), 1: (0,)}
    assert not sel.warnings


def test_sources_ranked_by_useful_b_over_h():
    # view 1 is almost the same direction as view 0 (B/H ~ 0.02): not a useful source for 0.
    cams = [satellite(10, 0), satellite(11, 0), satellite(5, 180), satellite(30, 180)]
    sel = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(max_sources=2))
    bh = sel.b_over_h
    assert bh[0, 1] < 0.1
    assert 1 not in sel.sources[0]
    assert all(0.1 <= bh[0, j] <= 0.5 for j in sel.sources[0])
    # ranked by closeness to the target ratio
    d = [abs(bh[0, j] - 0.25) for j in sel.sources[0]]
    assert d == sorted(d)


def test_no_useful_pair_falls_back_with_a_warning():
    cams = [satellite(10, 0), satellite(11, 0)]
    sel = select_views(cams, mid_height=0.0)
    assert sel.sources[0] == (1,)
    assert any("no source with B/H" in w for w in sel.warnings)


def test_non_overlapping_views_are_an_error():
    far = look_at([5000.0, 0.0, ORBIT_M])
    # aim the second camera 50 km away: its crop sees nothing of the first one's
    shifted = dataclasses.replace(far)
    shifted.P = far.P @ np.array([[1, 0, 0, -5e4], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    with pytest.raises(CameraError, match="no stereo pair among the views.*overlaps it"):
        select_views([satellite(5, 0), shifted], mid_height=0.0)


def test_a_copy_of_a_view_is_no_stereo_pair():
    """Two cameras at one viewpoint (an image given twice under two names) have no parallax:
    an error rather than a sweep of flat planes."""
    cam = satellite(10, 0)
    with pytest.raises(CameraError, match="no stereo pair.*no parallax with view 1"):
        select_views([cam, dataclasses.replace(cam)], mid_height=0.0)
    # A third view with parallax keeps the run going, without the copy as a source.
    sel = select_views([cam, dataclasses.replace(cam), satellite(-10, 0)], mid_height=0.0)
    assert 1 not in sel.sources[0] and 0 not in sel.sources[1]
    assert any("no parallax" in w for w in sel.warnings)


def test_one_viewpoint_on_another_date_is_no_source_and_no_warning():
    """A repeat orbit (one viewpoint, two dates, as real stacks hold): the pair is no stereo
    pair either way, but only a pair that looks alike (or of unknown likeness) may be a copy
    and is warned about."""
    cam = satellite(10, 0)
    cams = [cam, dataclasses.replace(cam), satellite(-10, 0)]
    for likeness, warned in ((0.3, False), (CLOSE_SIMILARITY, True)):
        sim = np.ones((3, 3))
        sim[0, 1] = sim[1, 0] = likeness
        source = np.full((3, 3), "metadata", dtype=object)
        sel = select_views(cams, mid_height=0.0, similarity=sim, similarity_source=source)
        assert 1 not in sel.sources.get(0, ()) and 0 not in sel.sources.get(1, ())
        assert any("no parallax" in w for w in sel.warnings) == warned, sel.warnings
    # alone, a repeat orbit still explains why there is no stereo pair
    sim = np.array([[1.0, 0.3], [0.3, 1.0]])
    with pytest.raises(CameraError, match="no parallax with view 1.*another date"):
        select_views(cams[:2], mid_height=0.0, similarity=sim,
                     similarity_source=np.full((2, 2), "metadata", dtype=object))


def test_options_are_checked():
    with pytest.raises(OptionsError, match="min_b_over_h"):
        ViewSelectionOptions(min_b_over_h=0.6, max_b_over_h=0.5)


def _similar_stack(labels: str):
    """View 0 near nadir, views 1-3 around it at 12 degrees (all in B/H range); view 0's
    similarity to them 0.5, 0.1 and 0.05 (the others' to each other 0.05), from ``labels``."""
    cams = [satellite(2, 0), satellite(12, 90), satellite(12, 180), satellite(12, 270)]
    sim = np.full((4, 4), 0.05)
    np.fill_diagonal(sim, 1.0)
    sim[0, 1:] = sim[1:, 0] = [0.5, 0.1, 0.05]
    return cams, sim, np.full((4, 4), labels, dtype=object)


def test_dissimilar_sources_left_out_beside_a_close_one():
    """With a source of the reference's conditions (view 1 at similarity 1: its pass) the
    sources under min_similarity are left out."""
    cams, sim, labels = _similar_stack("metadata")
    sim[0, 1] = sim[1, 0] = 1.0
    sel = select_views(cams, mid_height=0.0, similarity=sim, similarity_source=labels)
    assert sel.sources[0] == (1,)


def test_sources_all_of_other_dates_are_all_kept():
    """The metadata say that no source shares the reference's conditions (all under
    CLOSE_SIMILARITY): none is left out, the most similar first."""
    from satsweep.dense.selection import CLOSE_SIMILARITY

    cams, sim, labels = _similar_stack("metadata")
    assert sim[0, 1:].max() < CLOSE_SIMILARITY
    sel = select_views(cams, mid_height=0.0, similarity=sim, similarity_source=labels)
    assert sel.sources[0][0] == 1 and sorted(sel.sources[0]) == [1, 2, 3]


@pytest.mark.parametrize("label", ["tie points", "images"])
def test_measured_similarity_only_ranks(label):
    """A similarity measured from tie points or images is relative to the stack's best pair:
    it orders the sources (the most similar first) but min_similarity leaves none out, where
    the same values from the metadata keep only the close source (see the test above with a
    source at 1) or, given bare (no labels), keep the cut."""
    cams, sim, labels = _similar_stack(label)
    sel = select_views(cams, mid_height=0.0, similarity=sim, similarity_source=labels)
    assert sel.sources[0][0] == 1 and sorted(sel.sources[0]) == [1, 2, 3]
    sim[0, 1] = sim[1, 0] = 1.0
    sel = select_views(cams, mid_height=0.0, similarity=sim, similarity_source=labels)
    assert sel.sources[0][0] == 1 and sorted(sel.sources[0]) == [1, 2, 3]
    metadata = select_views(cams, mid_height=0.0, similarity=sim,
                            similarity_source=np.full((4, 4), "metadata", dtype=object))
    assert metadata.sources[0] == (1,)
    bare = select_views(cams, mid_height=0.0, similarity=sim)
    assert bare.sources[0] == (1,)


def _one_sided_stack():
    """Five views from the west (azimuths 240-300, incidence 10-18 degrees) and two steeper
    ones from the east: the lowest incidences are all on one side."""
    west = [satellite(10, 240), satellite(12, 300), satellite(14, 270), satellite(16, 250),
            satellite(18, 290)]
    return west + [satellite(25, 90), satellite(27, 110)]


def test_references_see_every_side_that_some_view_sees():
    """By incidence alone the three references all look from the west, and the ground in front
    of every east-facing wall is hidden from all of them; side_coverage = 1 takes the best view
    from the east for the last slot."""
    from satsweep.dense.selection import SIDE_HALF_ANGLE_DEG, SIDES_DEG

    cams = _one_sided_stack()
    alone = select_views(cams, mid_height=0.0,
                         options=ViewSelectionOptions(max_references=3, side_coverage=0))
    assert alone.references == (0, 1, 2)
    sel = select_views(cams, mid_height=0.0,
                       options=ViewSelectionOptions(max_references=3, side_coverage=1))
    assert sel.references == (0, 1, 5)
    # Every side that one of the views sees is seen by a reference.
    az = np.array([g.azimuth_deg for g in sel.geometry])

    def seeing(side, views):
        return [v for v in views
                if abs((az[v] - side + 180.0) % 360.0 - 180.0) <= SIDE_HALF_ANGLE_DEG]

    for side in SIDES_DEG:
        assert bool(seeing(side, range(len(cams)))) == bool(seeing(side, sel.references)), side
    # With room for every view the rule changes nothing but the order.
    every = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(max_references=7))
    assert sorted(every.references) == list(range(7))


def test_a_near_nadir_reference_sees_every_side():
    from satsweep.dense.selection import NADIR_DEG

    cams = [satellite(NADIR_DEG / 2, 270)] + _one_sided_stack()
    sel = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(max_references=3))
    assert sel.references == (0, 1, 2)


def _seasons_stack():
    """Six views around nadir, the three lowest incidences of winter dates (leaf_season 0),
    the three steeper ones of summer dates (1)."""
    cams = [satellite(5, 0), satellite(8, 120), satellite(10, 240),
            satellite(14, 60), satellite(16, 180), satellite(18, 300)]
    return cams, [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]


def test_references_from_dates_in_leaf():
    """By incidence alone the four references are the three winter views and one summer view;
    leaf_on_references = 0.5 wants two of the four in leaf, so the best summer view takes the
    last slot. Unknown dates and the rule off change nothing."""
    cams, leaf = _seasons_stack()
    opts = dict(max_references=4, side_coverage=0)
    plain = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(**opts))
    assert plain.references == (0, 1, 2, 3)
    sel = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(**opts),
                       leaf_season=leaf)
    assert sel.references == (0, 1, 3, 4)
    assert sum(leaf[r] for r in sel.references) >= 0.5 * 4
    off = select_views(cams, mid_height=0.0, leaf_season=leaf,
                       options=ViewSelectionOptions(**opts, leaf_on_references=0.0))
    assert off.references == plain.references
    unknown = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(**opts),
                           leaf_season=[None] * len(cams))
    assert unknown.references == plain.references and unknown.sources == plain.sources
    # Dates part in leaf count for their part: two winter views at 0.5 make up one in leaf.
    half = select_views(cams, mid_height=0.0, options=ViewSelectionOptions(**opts),
                        leaf_season=[0.5, 0.5, 0.0, 1.0, 1.0, 1.0])
    assert half.references == plain.references


def test_sources_ranked_by_leaf_state():
    """Two sources at the same B/H from the reference, one of its leaf state and one of the
    other: the first ranks first, whatever their order by incidence."""
    cams = [satellite(2, 0), satellite(12, 90), satellite(12, 270)]
    for leaf, first in (([1.0, 0.0, 1.0], 2), ([1.0, 1.0, 0.0], 1)):
        sel = select_views(cams, mid_height=0.0, leaf_season=leaf,
                           options=ViewSelectionOptions(max_references=1))
        assert sel.sources[0][0] == first, (leaf, sel.sources[0])
        assert sorted(sel.sources[0]) == [1, 2]


def test_leaf_options_are_checked():
    with pytest.raises(OptionsError, match="leaf_on_references"):
        ViewSelectionOptions(leaf_on_references=1.5)
    with pytest.raises(OptionsError, match="leaf_state_weight"):
        ViewSelectionOptions(leaf_state_weight=-1.0)


def _ring_stack(size: int, n: int = 14):
    """``n`` views of ``size`` px crops around the AOI, incidences 6-24 degrees, azimuths all
    around: every view has sources in the useful B/H range."""
    cams = []
    for k in range(n):
        cam = satellite(6.0 + 18.0 * k / (n - 1), (k * 137.5) % 360.0)
        cams.append(dataclasses.replace(cam, width=size, height=size))
    return cams


@pytest.mark.parametrize("size, expected", [
    (400, 12),  # 0.16 Mpx each: max_references
    (1000, 10),  # 1 Mpx each: 10 of them fill the 10 Mpx
    (1300, 8),  # 1.69 Mpx: 5 would fill them, but BUDGET_FREE_REFERENCES stay
    (1700, 8),
])
def test_the_references_crops_keep_within_their_megapixels(size, expected):
    from satsweep.dense.selection import BUDGET_FREE_REFERENCES

    options = ViewSelectionOptions()
    assert (options.max_references, options.reference_megapixels) == (12, 10.0)
    assert BUDGET_FREE_REFERENCES == 8
    sel = select_views(_ring_stack(size), mid_height=0.0)
    assert len(sel.references) == sel.reference_limit == expected
    assert sel.to_dict()["reference_limit"] == expected
    # Without the limit, max_references alone; a smaller max_references is never raised.
    free = select_views(_ring_stack(size), mid_height=0.0,
                        options=ViewSelectionOptions(reference_megapixels=0.0))
    assert len(free.references) == 12
    assert free.references[:expected] == sel.references
    few = select_views(_ring_stack(size), mid_height=0.0,
                       options=ViewSelectionOptions(max_references=5))
    assert len(few.references) == 5


def test_the_median_crop_sets_the_references_pixels():
    """Crops of unequal sizes: the median's pixels count for each."""
    from satsweep.dense.selection import reference_limit

    options = ViewSelectionOptions()
    assert reference_limit(options, [250_000] * 7 + [4_000_000] * 6) == 12  # median 0.25 Mpx
    assert reference_limit(options, [250_000] * 6 + [1_000_000] * 7) == 10  # median 1 Mpx
    assert reference_limit(options, []) == 12
    assert reference_limit(ViewSelectionOptions(reference_megapixels=2.5), [250_000] * 3) == 10


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf")])
def test_reference_megapixels_is_checked(value):
    with pytest.raises(OptionsError, match="reference_megapixels"):
        ViewSelectionOptions(reference_megapixels=value)
