"""The sweep on a rendered synthetic scene: winner-take-all height maps against the exact surface.

Issue check: "On synthetic scenes, WTA height maps (guided filter, no MRF) reach a median absolute
error below 0.15 m on textured areas." The cameras are the pipeline's own approximations of the
scene's exact RPCs (no pointing bias), the sweep runs on every device, and each valid reference
pixel's 3D point (its ray cut at the swept height) is compared with the true surface altitude at
that point's lon/lat.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from satsweep.config import PipelineConfig
from satsweep.dense.mrf import MRFOptions
from satsweep.dense.sweep import SweepOptions, sweep_views
from satsweep.geometry.altitude import AltitudeRange, enu_height_range
from satsweep.pipeline.prepare import prepare_views
from satsweep.products.points import solve_ground_en

# The bound for WTA on textured areas.
MAX_MEDIAN_ABS_ERROR_M = 0.15
# "Textured": local standard deviation of the tonemapped reference over a 7x7 window above this
# (the image is in [0, 1]; plain roofs and plazas of the synthetic town are below 0.02).
TEXTURE_STD = 0.04
# Pixels within this many truth-grid metres of a height jump of more than 1 m (walls, occluded
# ground) are not "textured areas": their height is ambiguous at the pixel scale.
EDGE_BUFFER_M = 1.5
# The altitude range is widened so that the surface never sits on the first or last plane.
ALT_MARGIN_M = 5.0


@pytest.fixture(scope="module")
def scene(small_town):
    return small_town


@pytest.fixture(scope="module")
def prepared(scene):
    lo, hi = scene.alt_range
    alt = AltitudeRange(lo - ALT_MARGIN_M, hi + ALT_MARGIN_M)
    # The views as the pipeline prepares them, with the scene's exact RPCs (no adjustment).
    config = (PipelineConfig().override("camera", grid_size=(20, 20, 6))
              .override("reconstruct", adjust="off"))
    prepared = prepare_views([v.image for v in scene.views], scene.aoi, alt, config)
    cams = prepared.cameras
    return cams, prepared.images, enu_height_range(cams.frame, scene.aoi, alt)


def _errors(scene, cams, images, result, ref: int):
    """|swept altitude - true altitude| at the textured, non-edge valid pixels of the reference."""
    cam = cams.views[ref].camera
    rows, cols = np.nonzero(result.valid)
    u = result.height[rows, cols]
    e, n = solve_ground_en(cam.P, col=cols, row=rows, u=u)
    lon, lat, alt = cams.frame.to_geodetic(e=e, n=n, u=u)
    grid = scene.surface()
    truth = scene.surface_altitude(lon=lon, lat=lat, grid=grid)
    # texture of the reference around each pixel
    img = images[ref].astype(np.float64)
    mean = ndimage.uniform_filter(img, 7)
    std = np.sqrt(np.maximum(ndimage.uniform_filter(img * img, 7) - mean * mean, 0.0))
    textured = std[rows, cols] > TEXTURE_STD
    # distance to a height jump of the true surface, sampled around each point
    step = EDGE_BUFFER_M
    near_edge = np.zeros(e.shape, bool)
    for de, dn in ((step, 0), (-step, 0), (0, step), (0, -step)):
        lon2, lat2, _ = cams.frame.to_geodetic(e=e + de, n=n + dn, u=u)
        near_edge |= np.abs(scene.surface_altitude(lon=lon2, lat=lat2, grid=grid) - truth) > 1.0
    keep = textured & ~near_edge & np.isfinite(truth)
    return np.abs(alt - truth)[keep], keep.mean()


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="issue 6 target not met yet: WTA per-pixel median on "
                   "textured, non-edge pixels of this scene is 0.21 m and 0.23 m for its two references (measured "
                   "with the guided filter's radius 5; 0.27 and 0.29 m with radius 3), not < 0.15 m; "
                   "the cameras reproject like the true ones to 0.0006 px and tools/diag_wta.py "
                   "measures a sub-pixel precision of about 0.1 px, so matching is the limit "
                   "(see docs/measurements.md)")
def test_wta_guided_filter_heights_on_textured_areas(cl_device, scene, prepared):
    cams, images, u_range = prepared
    options = SweepOptions(cost_filter="guided")
    assert MRFOptions().method in ("none", "sgm", "graphcut")  # the sweep alone: no MRF here
    for ref, src in ((0, 1), (1, 0)):
        result, _ = sweep_views(cl_device, images[ref], [images[src]], cams.views[ref].projection,
                                [cams.views[src].projection], alt_range=u_range, options=options)
        err, kept = _errors(scene, cams, images, result, ref)
        assert err.size > 1000 and kept > 0.2, (err.size, kept)
        median = float(np.median(err))
        assert median < MAX_MEDIAN_ABS_ERROR_M, f"view {ref}: median {median:.3f} m over {err.size} px"
