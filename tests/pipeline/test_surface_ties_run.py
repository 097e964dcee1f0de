"""A run refines its pointing corrections on its first DSM's surface ([bundle] surface_ties)."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.config import PipelineConfig
from satsweep.pipeline.run import reconstruct
from tools.bench_multidate import pointing_error

# Three views of three dates (256 px, 0.5 m): the sparse stage ties them on 50-80 observations
# per view, and leaves them uncertain by 0.048 px (its correction_sigma_px), 0.058 px off the
# truth after the gauge; refined on the surface, 0.012 px (sixty-seventh session).
THREE_DATES = dict(seed=2, n_views=3, acquisitions=3, size_px=256, gsd_m=0.5, bias_px=2.0,
                   large_bias_px=30.0)
# Issue 26's target for the corrections, after the gauge.
POINTING_TARGET_PX = 0.05


def _run(scene, out, **bundle):
    return reconstruct([v.image for v in scene.views], scene.aoi, out,
                       config=PipelineConfig().override("bundle", **bundle), verbose=False)


@pytest.mark.parametrize("fixed", [(), ("view_01.tif",)])
def test_a_run_corrects_its_views_on_the_surface(tmp_path, synthetic_scene, fixed):
    """With the refinement on, the corrections applied to the cameras are the sparse stage's
    plus the shifts found on the surface, which the report gives per view (the cameras of the
    dense stages' second run: the report's "ba" is theirs), and they lie within issue 26's
    0.05 px of the truth. A fixed view keeps a correction of zero."""
    scene = synthetic_scene(**THREE_DATES)
    off = _run(scene, tmp_path / "off", surface_ties="off", fixed_views=fixed)
    on = _run(scene, tmp_path / "on", surface_ties="on", fixed_views=fixed)
    assert off.report["sparse"]["surface_ties"] is None
    ties = on.report["sparse"]["surface_ties"]
    assert ties["reason"] == "[bundle] surface_ties = on"
    assert ties["registered_points"] > 100 and min(ties["observations"].values()) > 100
    assert on.report["timings_s"]["surface ties"] > 0.0
    before = off.report["ba"]["principal_point_shift_px"]
    after = on.report["ba"]["principal_point_shift_px"]
    assert sorted(after) == sorted(before) == sorted(ties["shift_px"])
    for name, shift in after.items():
        np.testing.assert_allclose(shift, np.add(before[name], ties["shift_px"][name]),
                                   rtol=0, atol=1e-9)
        assert on.report["sparse"]["views"][name]["correction_px"] == pytest.approx(shift)
    views = list(range(len(scene.views)))
    assert pointing_error(scene, views, after) <= POINTING_TARGET_PX
    for name in fixed:
        assert after[name] == [0.0, 0.0] and before[name] == [0.0, 0.0]
    if not fixed:  # auto: this stack's sparse corrections are uncertain enough to refine
        auto = _run(scene, tmp_path / "auto")
        assert auto.report["sparse"]["surface_ties"]["reason"].startswith(
            "the tie points left a correction uncertain by 0.0")
