"""Sweep + MRF tile by tile (satsweep.pipeline.sweep_refine_tiled), on every usable device.

The reconstruct path with an MRF must not hold a whole reference's cost volume: it sweeps and
refines tiles with an overlap. Checked here against the untiled computation (the sweep with its
volume kept, then the refinement) on translation scenes with exact homographies: identical when
one tile covers the reference, and nearly identical with many tiles (SGM paths are cut at the
tile borders, beyond the overlap).
"""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.dense.mrf import MRFOptions, refine
from satsweep.dense.planes import plane_heights_for, translation_homographies, visible_at
from satsweep.dense.sweep import PlaneSweep, SweepOptions
from satsweep.dense.tiled import (
    MIN_MRF_TILE_PX,
    _source_windows,
    mrf_sweep_options,
    mrf_tile_side,
    sweep_refine_tiled,
)
from satsweep.errors import DeviceError
from tests import reference_sweep as ref

SHIFTS = ((0.52, 0.0), (0.1, -0.4))
ALT_RANGE = (0.0, 20.0)
# Many tiles against one: pixels whose fractional plane index differs by more than this ...
TILED_INDEX_TOL = 0.5
# ... may be at most this share of the pixels. SGM paths restart at tile borders; measured on this
# scene: 0.004% of the pixels differ with a 32-pixel overlap, 1.7% with none (which must fail).
TILED_MAX_DIFFERENT = 0.002


def _scene(shape, seed=3):
    shifts = np.asarray(SHIFTS, np.float64)
    ref_img, srcs, truth = ref.translation_scene(shape, shifts, ALT_RANGE, seed=seed, noise=0.01)
    fn = lambda h: translation_homographies(shifts, h)  # noqa: E731
    heights = plane_heights_for(fn, shape, ALT_RANGE, 0.5)
    return ref_img, srcs, fn(heights), heights


def _untiled(device, ref_img, srcs, hom, heights, sweep, mrf):
    """The reference computation: one whole-image sweep keeping its volume, then refine; valid
    where the refinement is, a source sees the chosen plane and (lr_check) the check passed."""
    r, volume = PlaneSweep(device, mrf_sweep_options(sweep, mrf)).height_map_with_cost_volume(
        ref_img, srcs, hom, heights)
    initial = np.clip(np.rint(r.plane_index), 0, heights.size - 1).astype(np.int32)
    m = refine(device, volume, ref_img, heights, mrf,
               cost_scale=float(sweep.census_bits), reject_range_edges=sweep.reject_range_edges,
               initial_labels=initial)
    valid = m.valid & visible_at(hom, m.labels, [s.shape for s in srcs])
    return m, valid & r.valid if sweep.lr_check else valid


@pytest.mark.parametrize("method", ["sgm", "graphcut"])
@pytest.mark.parametrize("sweep", [SweepOptions(), SweepOptions(lr_check=True),
                                   SweepOptions(prefilter_sigma_px=0.6)],
                         ids=["defaults", "lr_check", "prefilter"])
def test_one_tile_is_the_untiled_result(cl_device, method, sweep):
    ref_img, srcs, hom, heights = _scene((40, 46))
    mrf = MRFOptions(method=method)
    got, _ = sweep_refine_tiled(cl_device, ref_img, srcs, hom, heights, sweep, mrf)
    want, valid = _untiled(cl_device, ref_img, srcs, hom, heights, sweep, mrf)
    assert got.split.n_tiles == 1
    np.testing.assert_array_equal(got.plane_index, want.plane_index)
    np.testing.assert_array_equal(got.valid, valid)
    np.testing.assert_array_equal(np.isnan(got.height), ~valid)
    np.testing.assert_array_equal(got.height[valid], want.height[valid])


def test_each_mrf_sweeps_with_its_own_filter_radius():
    sweep = SweepOptions(gf_radius=5)
    assert mrf_sweep_options(sweep, MRFOptions(method="sgm", sgm_sweep_gf_radius=2)) \
        == sweep.replace(gf_radius=2)
    assert mrf_sweep_options(sweep, MRFOptions(method="sgm", sgm_sweep_gf_radius=None)) == sweep
    assert mrf_sweep_options(sweep, MRFOptions(method="graphcut", sgm_sweep_gf_radius=2,
                                               gc_sweep_gf_radius=3)) == sweep.replace(gf_radius=3)
    assert mrf_sweep_options(sweep, MRFOptions(method="graphcut", gc_sweep_gf_radius=None)) == sweep
    assert mrf_sweep_options(sweep, MRFOptions(method="none", gc_sweep_gf_radius=3)) == sweep


def test_sgm_filter_radius_reaches_the_sweep(cl_device):
    """The tiled path's result changes with sgm_sweep_gf_radius and equals the untiled sweep with
    that radius (so the option is used, not only stored)."""
    ref_img, srcs, hom, heights = _scene((40, 46))
    sweep = SweepOptions(gf_radius=3)
    r2, _ = sweep_refine_tiled(cl_device, ref_img, srcs, hom, heights, sweep,
                               MRFOptions(sgm_sweep_gf_radius=2))
    r3, _ = sweep_refine_tiled(cl_device, ref_img, srcs, hom, heights, sweep,
                               MRFOptions(sgm_sweep_gf_radius=None))
    assert (r2.plane_index != r3.plane_index).any()
    want, _ = _untiled(cl_device, ref_img, srcs, hom, heights, sweep.replace(gf_radius=2),
                       MRFOptions(sgm_sweep_gf_radius=None))
    np.testing.assert_array_equal(r2.plane_index, want.plane_index)


def test_many_tiles_agree_with_one(cl_device):
    ref_img, srcs, hom, heights = _scene((150, 170))
    sweep = SweepOptions()
    one, _ = sweep_refine_tiled(cl_device, ref_img, srcs, hom, heights, sweep, MRFOptions())
    calls = []
    many, seconds = sweep_refine_tiled(cl_device, ref_img, srcs, hom, heights, sweep,
                                       MRFOptions(tile_px=MIN_MRF_TILE_PX, tile_overlap_px=32),
                                       progress=lambda done, total: calls.append((done, total)))
    assert one.split.n_tiles == 1 and many.split.n_tiles == 3 * 3 and seconds > 0
    assert calls == [(k, 9) for k in range(1, 10)]
    different = np.abs(many.plane_index - one.plane_index) > TILED_INDEX_TOL
    assert different.mean() <= TILED_MAX_DIFFERENT
    assert np.mean(many.valid != one.valid) <= TILED_MAX_DIFFERENT


def test_tile_side_follows_the_budget():
    mrf = MRFOptions(tile_px=1024, tile_overlap_px=64)
    big = 1 << 40
    assert mrf_tile_side(100, mrf, big, big) == 1024
    # 3 volumes of (side + 128)^2 x 100 planes x 4 bytes within 3 * 4 * 100 * 500^2 bytes.
    assert mrf_tile_side(100, mrf, 3 * 4 * 100 * 500 ** 2, big) == 500 - 128
    # One allocation of (side + 128)^2 x 100 x 4 bytes at most.
    assert mrf_tile_side(100, mrf, big, 4 * 100 * 400 ** 2) == 400 - 128
    with pytest.raises(DeviceError, match="tile_overlap_px"):
        mrf_tile_side(100, mrf, 3 * 4 * 100 * 150 ** 2, big)


def test_source_windows_hold_every_sample_of_the_tile():
    """Every tile pixel, on every plane: when it maps inside the source, its bilinear neighbours
    lie in the window; when it maps outside, it is outside the window on a side where the window
    ends at the source's edge (so validity and edge-clamped values are those of the whole
    source). Mild perspective, sources partly and wholly beside the tile's footprint."""
    rng = np.random.default_rng(8)
    th, tw = 37, 45
    src_shapes = [(120, 150), (60, 70), (80, 90)]
    n_planes = 9
    hom = np.zeros((n_planes, len(src_shapes), 3, 3))
    offsets = [(20.0, 30.0), (40.0, -10.0), (200.0, 5.0)]  # inside, across an edge, outside
    for p in range(n_planes):
        for s_, (ox, oy) in enumerate(offsets):
            h = np.eye(3)
            h[:2, :2] += rng.normal(0.0, 0.05, (2, 2))
            h[0, 2], h[1, 2] = ox + 1.5 * p, oy - 0.7 * p
            h[2, :2] = rng.normal(0.0, 2e-4, 2)
            hom[p, s_] = h
    windows = _source_windows(hom, (th, tw), src_shapes)
    ys, xs = np.mgrid[0:th, 0:tw].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    for s_, ((sh, sw), (x0, y0, x1, y1)) in enumerate(zip(src_shapes, windows)):
        assert 0 <= x0 < x1 <= sw and 0 <= y0 < y1 <= sh
        m = hom[:, s_] @ pts
        u, v = m[:, 0] / m[:, 2], m[:, 1] / m[:, 2]
        inside = (u >= 0) & (u <= sw - 1) & (v >= 0) & (v <= sh - 1)
        fu, fv = np.floor(u[inside]), np.floor(v[inside])
        assert (fu >= x0).all() and (np.minimum(fu + 1, sw - 1) < x1).all()
        assert (fv >= y0).all() and (np.minimum(fv + 1, sh - 1) < y1).all()
        assert (u[u < 0].size == 0 or x0 == 0) and (u[u > sw - 1].size == 0 or x1 == sw)
        assert (v[v < 0].size == 0 or y0 == 0) and (v[v > sh - 1].size == 0 or y1 == sh)
    assert windows[0] != (0, 0, 150, 120)  # the first source is really cut
