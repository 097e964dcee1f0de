"""Tests of satsweep.sparse.verify: photometric confirmation of single tie points.

Reference: the exact ground truth of a satsweep.synth scene. A tie point is right when its
altitude is the true surface's at its place (in the gauge of the corrected cameras: the scene
moved by the motion dX that no image sees, see test_stage); a wrong match is made exactly by
moving a right point along its reference view's line of sight: that view sees the same pixel,
the others see other ground.
"""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.io.images import tonemap
from satsweep.sparse.stage import sparse_stage, tie_point_confirmer
from satsweep.sparse.verify import MIN_OTHER_VIEWS, confirming_views
from tests.sparse.test_stage import SIZE_PX, _motion, _views

# A right point: within this of the true surface (m): keypoints at full resolution on 0.5 m
# pixels and base-to-height ratios of 0.2-0.8 give a metre or less.
RIGHT_M = 1.0
# How far a right point is moved along its reference's line of sight to make a wrong one (m of
# altitude): several pixels of parallax in every other view.
MOVE_M = (-12.0, 12.0)


@pytest.fixture(scope="module")
def six_views(synthetic_scene):
    scene = synthetic_scene(seed=2, n_views=6, size_px=SIZE_PX, bias_px=20.0)
    views, prior = _views(scene)
    result = sparse_stage(views, scene.aoi, prior)
    images = [tonemap(v.image) for v in views]
    return scene, result, images


def _right_points(scene, result) -> np.ndarray:
    _, dX = _motion(result, scene)
    frame = result.frame
    pts = result.tied.points
    lon, lat, alt = frame.to_geodetic(e=pts[:, 0] - dX[0], n=pts[:, 1] - dX[1],
                                      u=pts[:, 2] - dX[2])
    inside = scene.aoi.contains(lon=lon, lat=lat)
    truth = np.full(len(pts), np.nan)
    truth[inside] = scene.surface_altitude(lon=lon[inside], lat=lat[inside])
    ok = np.abs(alt - truth) < RIGHT_M
    return np.flatnonzero(ok & (result.tied.point_error <= 1.0))


def test_right_points_are_confirmed_and_moved_ones_are_not(six_views):
    scene, result, images = six_views
    tied = result.tied
    confirm = tie_point_confirmer(tied, images)
    right = _right_points(scene, result)
    assert right.size >= 20
    confirmed = [i for i in right if confirm(int(i))]
    # Many right points lie by walls or in cast shadows that other dates see differently: not
    # all are confirmed, but the range needs only its highest.
    assert len(confirmed) >= 0.2 * right.size
    from satsweep.sparse.bundle import shift_principal_point

    P = {v: np.asarray(shift_principal_point(tied.cameras[v], tied.shifts[v]).P, np.float64)
         for v in tied.kept}
    for i in confirmed:
        track = tied.obs.view[tied.obs.point == i]
        ref = P[int(track[0])]
        M, p4 = ref[:, :3], ref[:, 3]
        centre = -np.linalg.solve(M, p4)
        ray = tied.points[i] - centre
        for dz in MOVE_M:
            moved = tied.points[i] + ray * (dz / ray[2])
            outside, views = confirming_views(moved, track, images, P)
            assert outside < MIN_OTHER_VIEWS, (i, dz, views)


def test_a_lone_point_above_the_supported_top_raises_it_only_when_confirmed(six_views):
    """altitude_range_from_points: the highest point is moved up along its reference's line of
    sight, alone above the others: it does not raise the top; a confirmer that accepts
    everything lets it."""
    from satsweep.sparse.options import SparseOptions
    from satsweep.sparse.tiepoints import altitude_range_from_points

    scene, result, images = six_views
    tied = result.tied
    right = _right_points(scene, result)
    top = right[np.argmax(tied.points[right, 2])]
    points = tied.points.copy()
    points[top, 2] += 30.0
    args = (points, tied.obs, tied.point_error, result.frame, scene.aoi, SparseOptions())
    plain, _ = altitude_range_from_points(*args)
    checked, record = altitude_range_from_points(*args, confirm=tie_point_confirmer(
        _replace_points(tied, points), images))
    accepted, record_all = altitude_range_from_points(*args, confirm=lambda i: True)
    assert checked.max == pytest.approx(plain.max)
    assert record["unsupported_points_tried"] >= 1 and "confirmed_top_m" not in record
    assert accepted.max > plain.max + 10.0 and record_all["confirmed_top_m"] > plain.max


def _replace_points(tied, points):
    import dataclasses

    return dataclasses.replace(tied, points=points)
