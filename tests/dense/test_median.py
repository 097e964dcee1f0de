"""The edge-aware weighted median of height maps (kernels/median.cl) against its numpy reference
and an exact synthetic step, on every usable OpenCL device (the ``cl_device`` fixture)."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.dense.median import MEDIAN_MAX_RADIUS_PX, radius_px, weighted_median
from satsweep.dense.mrf import MRFOptions
from satsweep.errors import OptionsError
from tests.reference_median import weighted_median_reference

# Where half the total weight lies this close (a fraction of the total) to the running sum at a
# height, float32 sums of up to 169 weights in [0, 1] (relative error ~1e-5) may stop one
# height earlier or later than the float64 reference: both are then the weighted median.
SUM_MARGIN = 1e-4


def _inputs(seed: int, shape=(37, 53)):
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    roof = (xx > w // 3) & (yy > h // 4)
    guide = np.where(roof, 0.7, 0.3) + rng.normal(0.0, 0.03, shape)
    height = np.where(roof, 12.0, 1.0) + rng.normal(0.0, 0.4, shape)
    valid = rng.uniform(size=shape) > 0.15
    return height, valid, guide, roof


@pytest.mark.parametrize("radius", [1, 2, 4, MEDIAN_MAX_RADIUS_PX])
def test_kernel_matches_numpy_reference(cl_device, radius):
    height, valid, guide, _ = _inputs(radius)
    got = weighted_median(cl_device, height, valid, guide, radius=radius, sigma=0.05)
    want, margin = weighted_median_reference(height, valid, guide, radius=radius, sigma=0.05)
    clear = valid & (margin > SUM_MARGIN)
    assert clear.sum() > 0.9 * valid.sum()
    np.testing.assert_allclose(got[clear], want[clear], rtol=0, atol=1e-5)  # float32 heights
    np.testing.assert_array_equal(got[~valid], height[~valid])


def test_ties_and_equal_heights_give_the_reference_median(cl_device):
    """Many equal heights (a quantised map: plane heights): the bisection meets ties."""
    height, valid, guide, _ = _inputs(11)
    height = np.round(height * 2.0) / 2.0
    got = weighted_median(cl_device, height, valid, guide, radius=3, sigma=0.05)
    want, margin = weighted_median_reference(height, valid, guide, radius=3, sigma=0.05)
    clear = valid & (margin > SUM_MARGIN)
    assert clear.sum() > 0.9 * valid.sum()
    np.testing.assert_allclose(got[clear], want[clear], rtol=0, atol=1e-5)


@pytest.mark.parametrize("offset", [-6.5, -40.0])
def test_heights_of_both_signs_give_the_reference_median(cl_device, offset):
    """Heights below zero and across it (ellipsoidal heights of coastal cities): the kernel's
    integer keys of negative floats order them as the floats, in the pixels' path and in the
    lanes of 8 (a map wider than two windows)."""
    height, valid, guide, _ = _inputs(3, shape=(29, 61))
    height = height + offset
    got = weighted_median(cl_device, height, valid, guide, radius=2, sigma=0.05)
    want, margin = weighted_median_reference(height, valid, guide, radius=2, sigma=0.05)
    clear = valid & (margin > SUM_MARGIN)
    assert clear.sum() > 0.9 * valid.sum()
    assert (height[valid] < 0).mean() > 0.3
    np.testing.assert_allclose(got[clear], want[clear], rtol=0, atol=1e-5)


def test_a_wide_map_at_the_largest_radius(cl_device):
    """A map 256 px wide at the largest window: the kernel's work-groups hold 8 windows of 169
    taps per work-item (PoCL crashed with the work-groups it chose itself for such a map)."""
    height, valid, guide, _ = _inputs(4, shape=(64, 256))
    got = weighted_median(cl_device, height, valid, guide, radius=MEDIAN_MAX_RADIUS_PX,
                          sigma=0.05)
    want, margin = weighted_median_reference(height, valid, guide, radius=MEDIAN_MAX_RADIUS_PX,
                                             sigma=0.05)
    clear = valid & (margin > SUM_MARGIN)
    assert clear.sum() > 0.9 * valid.sum()
    np.testing.assert_allclose(got[clear], want[clear], rtol=0, atol=1e-5)


def test_buffers_are_accounted_and_released(cl_device):
    from satsweep.opencl.buffers import DeviceMemory

    height, valid, guide, _ = _inputs(2)
    memory = DeviceMemory(cl_device.context)
    weighted_median(cl_device, height, valid, guide, radius=2, sigma=0.05, memory=memory)
    assert memory.peak == 3 * height.size * 4 and memory.live == 0  # height, guide, out: float32


def test_step_kept_at_the_image_edge_and_noise_removed(cl_device):
    height, valid, guide, roof = _inputs(7)
    truth = np.where(roof, 12.0, 1.0)
    got = weighted_median(cl_device, height, valid, guide, radius=3, sigma=0.05)
    err_before = np.abs(height - truth)[valid]
    err_after = np.abs(got - truth)[valid]
    # every pixel stays on its own side of the step (the noise is 0.4 m, the step 11 m) ...
    assert err_after.max() < 2.0
    # ... and the median of the window's heights halves the noise at least
    assert np.median(err_after) < 0.5 * np.median(err_before)


def test_no_valid_pixel_leaves_the_map_as_it_is(cl_device):
    height = np.full((8, 9), np.nan)
    out = weighted_median(cl_device, height, np.zeros((8, 9), bool), np.zeros((8, 9)),
                          radius=2, sigma=0.05)
    assert np.isnan(out).all()


def test_radius_in_pixels():
    assert radius_px(1.2, 0.3) == 4
    assert radius_px(1.2, 0.5) == 2
    assert radius_px(1.2, 2.0) == 1
    assert radius_px(1.2, 0.05) == MEDIAN_MAX_RADIUS_PX
    with pytest.raises(OptionsError, match="ground sample distance"):
        radius_px(1.2, 0.0)


def test_bad_arguments_are_named(cl_device):
    height, valid, guide, _ = _inputs(0)
    with pytest.raises(OptionsError, match="radius"):
        weighted_median(cl_device, height, valid, guide, radius=MEDIAN_MAX_RADIUS_PX + 1,
                        sigma=0.05)
    with pytest.raises(OptionsError, match="sigma"):
        weighted_median(cl_device, height, valid, guide, radius=2, sigma=0.0)
    with pytest.raises(OptionsError, match="shape"):
        weighted_median(cl_device, height, valid, guide[:-1], radius=2, sigma=0.05)


def test_options_check_and_consensus():
    with pytest.raises(OptionsError, match="median_sigma"):
        MRFOptions(median_sigma=0.0)
    with pytest.raises(OptionsError, match="consensus_median_radius_m"):
        MRFOptions(consensus_median_radius_m=-1.0)
    assert MRFOptions().median_radius_m == 0.0  # none outside a consensus
    assert MRFOptions().for_consensus().median_radius_m == MRFOptions().consensus_median_radius_m
    assert MRFOptions(consensus_median_radius_m=0.0).for_consensus().median_radius_m == 0.0
    assert MRFOptions(method="graphcut").for_consensus().median_radius_m == 0.0
