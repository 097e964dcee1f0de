"""tools/diag_tie_errors.py: its truth against the scene's own, and its exact oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from satsweep.sparse.bundle import shift_principal_point
from satsweep.sparse.stage import SparseOptions, fit_cameras
from satsweep.sparse.triangulation import projection_stack
from tools.bench_ba import sparse_inputs
from tools.diag_tie_errors import FLAT_M, FLAT_RADIUS_M, RAY_STEP_M, TruthSurface, diagnose

# Three dates of two views with pointing errors up to 32 px (as test_stage's multi-date scene).
MULTIDATE = dict(seed=0, n_views=6, size_px=256, gsd_m=0.5, bias_px=2.0, acquisitions=3,
                 large_bias_px=30.0)
# A ray cast stops within one step below the surface, plus what the ray's sideways move over that
# step (tan(incidence) per metre, incidences under 40 deg) meets on ground that slopes: "flat"
# allows FLAT_M over FLAT_RADIUS_M.
RAY_TOL_M = RAY_STEP_M * (1.0 + math.tan(math.radians(40.0)) * FLAT_M / FLAT_RADIUS_M)
# The fitted cameras reproduce the synthetic pushbroom cameras to a few thousandths of a pixel
# over the AOI's cube (measured 0.005-0.006 px on this scene).
CAMERA_TOL_PX = 0.02
# Observations at their true positions leave only the solver's and the measure's own error
# (measured 0.002 px here, 0.005-0.009 px on tools/bench_multidate.py's 384 px stacks; the
# scene's real ties: 0.04 px).
EXACT_ORACLE_TOL_PX = 0.01


@pytest.fixture(scope="module")
def scene(synthetic_scene):
    return synthetic_scene(**MULTIDATE)


def test_ray_casts_land_on_the_scene_surface(scene):
    """Pixels of two views cast through their true cameras land on the true surface: where it
    is flat, at the altitude ``Scene.surface_altitude`` gives for their lon/lat; everywhere,
    where the synthetic pushbroom camera sees them."""
    views, prior = sparse_inputs(scene)
    frame, cams, _ = fit_cameras(views, scene.aoi, prior, SparseOptions().camera_grid)
    P = projection_stack([shift_principal_point(c, v.bias_px) for c, v in zip(cams, scene.views)])
    surface = TruthSurface(scene, frame)
    rng = np.random.default_rng(0)
    for k in (0, 3):
        h, w = views[k].image.shape
        xy = np.c_[rng.uniform(0, w, 200), rng.uniform(0, h, 200)]
        X = surface.ray_cast(P, np.full(len(xy), k), xy)
        assert np.isfinite(X).all()
        lon, lat, alt = frame.to_geodetic(e=X[:, 0], n=X[:, 1], u=X[:, 2])
        flat = surface.span(X) < FLAT_M
        assert flat.sum() > 50
        assert np.abs(alt - scene.surface_altitude(lon=lon, lat=lat))[flat].max() <= RAY_TOL_M
        e, n, u = scene.frame.from_geodetic(lon=lon, lat=lat, alt=alt)
        col, row = scene.views[k].camera.project(e=e, n=n, u=u)
        assert np.hypot(col - views[k].x0 - xy[:, 0], row - views[k].y0 - xy[:, 1]).max() < CAMERA_TOL_PX


def test_the_exact_oracle_gives_the_true_corrections(scene):
    """With every registered observation moved to where its track's truth point lies, the fine
    adjustment finds the true pointing errors; the measure splits the ties by date."""
    row = diagnose(str(scene.directory), "exact", 0.3, False)
    assert row["kept"] == len(scene.views)
    assert row["oracle_worst_view_px"] < EXACT_ORACLE_TOL_PX < row["worst_view_px"]
    assert row["same_date_flat_n"] > 0 and row["other_date_flat_n"] > 0
    assert row["off_truth_n"] == 0
