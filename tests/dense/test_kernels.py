"""Every plane-sweep kernel against its numpy reference (tests/reference_sweep.py), on small
random inputs, on every usable OpenCL device (the ``cl_device`` fixture).

Exact comparisons (census codes, Hamming costs, argmin) use inputs on which float32 arithmetic
is exact: images quantised to multiples of 1/256 and homographies that translate by multiples of
1/4 pixel, so bilinear weights and samples are exactly representable. General homographies are
compared with tolerances derived from float32 rounding.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from satsweep.dense.sweep import (CENSUS_MASK_MIN_BITS, PlaneSweep, SweepOptions, box_chunk,
                                  census_mask_defines, census_ring_defines,
                                  group_windows, source_image, source_layout)
from satsweep.opencl.constants import SWEEP_VEC, WTA_BIG, WTA_NSTATE, WTA_SLOT, WTA_VEC
from satsweep.opencl.device import launch
from tests import reference_sweep as ref

F32_EPS = float(np.finfo(np.float32).eps)
# Bilinear warp of a [0, 1] image with a general homography: the float32 evaluation of the
# homography at coordinates <= 128 px is off by a few ulp (~1e-5 px); with image gradients below
# 1 per pixel and the bilinear rounding this bounds the value error well below 1e-4.
WARP_ATOL = 1e-4
# Box means of values up to 64 (census costs) over <= 15x15 windows: float32 sliding sums of at
# most BOX_CHUNK + window steps, relative error ~ 50 eps of the largest partial sum.
BOX_ATOL = 64 * 100 * F32_EPS
# Guided filter of costs in [0, 64] with a [0, 1] guide: the covariance and variance are
# differences of float32 means (cancellation), divided by var + eps with eps >= 1e-3 here, so the
# output error is ~ 64 * 1e3 * (rounding of the means ~ 1e-6); measured errors are ~1e-3.
GF_ATOL = 2e-2
# The best-k mean divides an integer sum by k on the device: OpenCL allows 2.5 ulp for division.
DIV_RTOL = 3 * F32_EPS
# The parabola offset is a ratio of float32 differences of costs up to 64: a few ulp of 64
# relative to a denominator >= 1/256 (quantised inputs below).
PARABOLA_ATOL = 1e-3


def _quantised(rng, shape, levels=256):
    """Random image with values k / levels: exact in float32 products with quarter weights."""
    return (rng.integers(0, levels, shape) / levels).astype(np.float32)


def _buf(dev, arr):
    mf = cl.mem_flags
    return cl.Buffer(dev.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(arr))


def _empty(dev, nbytes):
    return cl.Buffer(dev.context, cl.mem_flags.READ_WRITE, max(int(nbytes), 4))


def _read(dev, buf, shape, dtype):
    out = np.empty(shape, dtype)
    cl.enqueue_copy(dev.queue, out, buf)
    dev.queue.finish()
    return out


def _census_dev(dev, img, rx, ry, x0=0, y0=0, out_w=None, out_h=None, mask=0.0):
    """Codes of census.cl; with ``mask`` (a threshold) the edge-aware census's mask in their
    high words (the host's census_mask_defines)."""
    h, w = img.shape
    out_w = w if out_w is None else out_w
    out_h = h if out_h is None else out_h
    defs = {"CENSUS_RX": rx, "CENSUS_RY": ry}
    defs.update(census_mask_defines(SweepOptions(census_window=(2 * ry + 1, 2 * rx + 1),
                                                 census_mask_threshold=mask)))
    prg = dev.build("census", defs)
    out = _empty(dev, 8 * out_w * out_h)
    i32 = np.int32
    launch(cl.Kernel(prg, "census_transform"), dev.queue, (out_w, out_h), _buf(dev, img), i32(w),
           i32(h), i32(x0), i32(y0), i32(out_w), i32(out_h), out)
    return _read(dev, out, (out_h, out_w), np.uint64)


def _sweep_dev(dev, ref_img, srcs, hom, rx, ry, k, mode="warped_census", wg=(16, 16),
               tile=None, ad=None, grad=None, ring=0.0, pad=0.0, mask=0.0):
    """Run one sweep kernel over all planes of hom (n_planes, n_src, 3, 3) on a tile.

    tile = (tx0, ty0, tw, th) of ref_img (default: the whole image); hom maps tile-local pixels.
    mode: "warped_census" (the staged kernel sweep_census_cost), "split" (sweep_warp then
    sweep_warped_cost, two planes a launch) or "sampled_codes" (sweep_code_cost). ad, grad =
    (weight, truncation) of the AD and gradient terms (default: none); ring: the census ring's
    weight (the host's census_ring_defines); pad: the value of the floats after the last source
    ("split": SWEEP_SRC_PAD of them, as the sweep uploads); mask: the edge-aware census's
    threshold (census_mask_defines), the reference's codes carrying its mask.
    """
    h, w = ref_img.shape
    tx0, ty0, tw, th = tile if tile is not None else (0, 0, w, h)
    n_planes, n_src = hom.shape[:2]
    defs = {"CENSUS_RX": rx, "CENSUS_RY": ry, "NSRC": n_src, "NBEST": k}
    if ad is not None:
        defs.update({"AD_WEIGHT": float(ad[0]), "AD_TRUNC": float(ad[1])})
    if grad is not None:
        defs.update({"GRAD_WEIGHT": float(grad[0]), "GRAD_TRUNC": float(grad[1])})
    if mode == "warped_census":
        defs.update({"WG_X": wg[0], "WG_Y": wg[1]})
    defs.update(census_ring_defines(SweepOptions(census_window=(2 * ry + 1, 2 * rx + 1),
                                                 census_ring_weight=ring)))
    defs.update(census_mask_defines(SweepOptions(census_window=(2 * ry + 1, 2 * rx + 1),
                                                 census_mask_threshold=mask)))
    prg = dev.build("sweep", defs)
    codes = _census_dev(dev, ref_img, rx, ry, tx0, ty0, tw, th, mask=mask)
    sizes, offsets = source_layout(srcs)
    hom32 = np.ascontiguousarray(hom.reshape(n_planes, n_src, 9), np.float32)
    out = _empty(dev, 4 * n_planes * tw * th)
    i32 = np.int32
    if mode == "split":
        data = source_image(srcs, pad)  # with the pad sweep_warp's paired taps may read
        pw, ph, chunk = tw + 2 * rx, th + 2 * ry, 2
        warped = _empty(dev, 4 * chunk * n_src * pw * ph)
        seen = _empty(dev, chunk * n_src * pw * ph)
        bufs = [_buf(dev, a) for a in (data, offsets, sizes, hom32, codes, ref_img.astype(np.float32))]
        # every plane at every position (group_windows of windows of every plane)
        every = (np.zeros((th, tw), np.int64), np.full((th, tw), n_planes, np.int64))
        warp_window, cost_window = (_buf(dev, a) for a in group_windows(
            SweepOptions(census_window=(2 * ry + 1, 2 * rx + 1)), *every))
        no_bands = _buf(dev, np.zeros(1, np.uint32))  # band_words 0: the windows alone
        for p0 in range(0, n_planes, chunk):
            nb = min(chunk, n_planes - p0)
            launch(cl.Kernel(prg, "sweep_warp"), dev.queue, (-(-pw // SWEEP_VEC), ph, nb * n_src),
                   *bufs[:4], i32(tw), i32(th), i32(tx0), i32(ty0), i32(w), i32(h),
                   i32(p0), warp_window, no_bands, i32(0), i32(0), warped, seen)
            launch(cl.Kernel(prg, "sweep_warped_cost"), dev.queue, (-(-tw // SWEEP_VEC), th, nb),
                   warped, seen,
                   bufs[4], bufs[5], i32(tw), i32(th), i32(tx0),
                   i32(ty0), i32(w), i32(h), i32(p0), i32(p0),
                   cost_window, no_bands, i32(0), i32(0), out)
    elif mode == "warped_census":
        data = source_image(srcs)
        gx = -(-tw // wg[0]) * wg[0]
        gy = -(-th // wg[1]) * wg[1]
        cl.Kernel(prg, "sweep_census_cost")(
            dev.queue, (gx, gy, n_planes), (wg[0], wg[1], 1), _buf(dev, data), _buf(dev, offsets),
            _buf(dev, sizes), _buf(dev, hom32), _buf(dev, codes),
            _buf(dev, ref_img.astype(np.float32)), i32(tw), i32(th), i32(tx0),
            i32(ty0), i32(w), i32(h), i32(0), out)
    else:
        data = np.concatenate([ref.census(s, rx, ry).ravel() for s in srcs])
        launch(cl.Kernel(prg, "sweep_code_cost"), dev.queue, (tw, th, n_planes),
               _buf(dev, data), _buf(dev, offsets),
               _buf(dev, sizes), _buf(dev, hom32), _buf(dev, codes), i32(tw), i32(th), i32(0), out)
    return _read(dev, out, (n_planes, th, tw), np.float32)


def _translations(shifts):
    """(n_planes, n_src, 3, 3) pure translations from shifts (n_planes, n_src, 2)."""
    shifts = np.asarray(shifts, np.float64)
    hom = np.tile(np.eye(3), shifts.shape[:2] + (1, 1))
    hom[..., 0, 2] = shifts[..., 0]
    hom[..., 1, 2] = shifts[..., 1]
    return hom


# float32 rounding of the AD term (at most AD_WEIGHT = 8 bits; a few ulp of it).
AD_ATOL = 1e-5
# float32 rounding of the ring-weighted census term: CENSUS_SCALE and one product, on terms of
# at most 64 bits (a few ulp of 64).
RING_ATOL = 2e-5


# -- census ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [(7, 9), (5, 5), (3, 7), (9, 7)])
def test_census_matches_reference_bit_for_bit(cl_device, window):
    rng = np.random.default_rng(1)
    # Few levels so that ties (neighbour == centre, bit 0) occur often.
    img = _quantised(rng, (37, 53), levels=8)
    rx, ry = window[1] // 2, window[0] // 2
    got = _census_dev(cl_device, img, rx, ry)
    np.testing.assert_array_equal(got, ref.census(img, rx, ry))


def test_census_of_a_tile_is_the_crop_of_the_whole_image(cl_device):
    rng = np.random.default_rng(2)
    img = rng.random((40, 45)).astype(np.float32)
    full = ref.census(img, 4, 3)
    got = _census_dev(cl_device, img, 4, 3, x0=30, y0=1, out_w=15, out_h=39)
    np.testing.assert_array_equal(got, full[1:40, 30:45])


def test_census_bit_order_and_border_rule(cl_device):
    """The documented convention on a hand-made case: raster order, first neighbour in the most
    significant bit, bit = neighbour < centre, neighbours outside the image edge-replicated."""
    img = np.array([[0.0, 1.0, 0.0], [0.0, 0.5, 0.0], [1.0, 1.0, 1.0]], np.float32)
    codes = _census_dev(cl_device, img, 1, 1)
    np.testing.assert_array_equal(codes, ref.census(img, 1, 1))
    # Centre (1, 1) = 0.5; neighbours in raster order 0, 1, 0, 0, 0, 1, 1, 1.
    assert codes[1, 1] == 0b10111000
    # Pixel (2, 0) = 0.0 (top right): the clamped window is 0,0,0 / 1,_,1 / 0,0,0 with the
    # centre 0.0 never greater: code 0. Pixel (1, 2) = 1.0 (bottom middle): window rows
    # 0,0.5,0 / 1,_,1 / 1,1,1 (the bottom row replicated): bits 1,1,1, 0,0, 0,0,0.
    assert codes[0, 2] == 0
    assert codes[2, 1] == 0b11100000


# -- sweep costs -------------------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["warped_census", "split"])
def test_warped_census_cost_exact_for_dyadic_translations(cl_device, form):
    rng = np.random.default_rng(3)
    h, w = 45, 61
    ref_img = _quantised(rng, (h, w))
    src = _quantised(rng, (h + 4, w - 3))
    # Quarter-pixel shifts, some large enough to push part of the view outside the source.
    shifts = np.array([[[0.25, -0.5]], [[3.75, 1.25]], [[-6.5, 0.0]], [[0.0, 12.25]]])
    hom = _translations(shifts)
    got = _sweep_dev(cl_device, ref_img, [src], hom, 4, 3, 1, mode=form)
    codes = ref.census(ref_img, 4, 3)
    for p in range(hom.shape[0]):
        cost, valid = ref.warped_census_cost(codes, src, hom[p, 0], 4, 3)
        want = np.where(valid, cost, 62)
        np.testing.assert_array_equal(got[p], want)
    assert (got == 62).any() and (got < 62).any()


@pytest.mark.parametrize("form", ["warped_census", "split"])
def test_warped_census_cost_on_a_tile_equals_the_whole_image(cl_device, form):
    """Census neighbours are clamped to the reference image, not to the tile."""
    rng = np.random.default_rng(4)
    ref_img = _quantised(rng, (40, 50))
    src = _quantised(rng, (40, 50))
    hom = _translations([[[0.75, -0.25]], [[-1.5, 2.0]]])
    whole = _sweep_dev(cl_device, ref_img, [src], hom, 4, 3, 1, mode=form)
    tx0, ty0, tw, th = 7, 5, 30, 33
    shift = np.eye(3)
    shift[0, 2], shift[1, 2] = tx0, ty0
    local = hom @ shift
    tile = _sweep_dev(cl_device, ref_img, [src], local, 4, 3, 1, mode=form, wg=(8, 8),
                      tile=(tx0, ty0, tw, th))
    np.testing.assert_array_equal(tile, whole[:, ty0:ty0 + th, tx0:tx0 + tw])


def test_warp_image_matches_bilinear_reference(cl_device):
    rng = np.random.default_rng(5)
    src = rng.random((50, 60)).astype(np.float32)
    prg = cl_device.build("sweep", {"CENSUS_RX": 1, "CENSUS_RY": 1, "NSRC": 1, "NBEST": 1})
    # A perspective homography (rotation, scale, shear, mild projective terms).
    hom = np.array([[0.93, 0.21, 4.3], [-0.17, 1.08, -2.6], [2.1e-4, -1.3e-4, 1.0]])
    out_h, out_w = 44, 57
    out = _empty(cl_device, 4 * out_h * out_w)
    seen = _empty(cl_device, out_h * out_w)
    i32 = np.int32
    launch(cl.Kernel(prg, "warp_image"), cl_device.queue, (out_w, out_h), _buf(cl_device, src),
           i32(60), i32(50), _buf(cl_device, hom.astype(np.float32).ravel()),
           i32(out_w), i32(out_h), out, seen)
    got = _read(cl_device, out, (out_h, out_w), np.float32)
    got_seen = _read(cl_device, seen, (out_h, out_w), np.uint8).astype(bool)
    want, want_seen = ref.warp_image(src, hom.astype(np.float32), (out_h, out_w))
    np.testing.assert_allclose(got, want, atol=WARP_ATOL, rtol=0)
    assert want_seen.any() and (~want_seen).any()
    # Membership may only differ for points within rounding of the source border.
    u, v, _ = ref.map_points(hom.astype(np.float32), (out_h, out_w))
    near_border = (np.abs(u) < 1e-3) | (np.abs(u - 59) < 1e-3) | (np.abs(v) < 1e-3) | (np.abs(v - 49) < 1e-3)
    assert ((got_seen != want_seen) <= near_border).all()


@pytest.mark.parametrize("form", ["warped_census", "split"])
def test_warped_census_cost_general_homography_within_rounding(cl_device, form):
    """With a general warp, a census bit may only differ where the reference comparison is
    within the warp tolerance: |cost - reference| <= number of such ambiguous comparisons."""
    rng = np.random.default_rng(6)
    ref_img = rng.random((48, 52)).astype(np.float32)
    src = rng.random((50, 56)).astype(np.float32)
    hom = np.array([[[[1.02, 0.05, 1.3], [-0.04, 0.98, 0.7], [1e-4, -2e-4, 1.0]]],
                    [[[0.97, -0.03, -0.6], [0.02, 1.01, 2.2], [-1e-4, 1e-4, 1.0]]]])
    hom32 = hom.astype(np.float32).astype(np.float64)
    got = _sweep_dev(cl_device, ref_img, [src], hom32, 4, 3, 1, mode=form)
    codes = ref.census(ref_img, 4, 3)
    for p in range(hom.shape[0]):
        warped, valid = ref.warp_image(src, hom32[p, 0], ref_img.shape)
        cost = ref.hamming(codes, ref.census(warped.astype(np.float32), 4, 3))
        slack = ref.census_ambiguity(warped, 4, 3, 2 * WARP_ATOL)
        # Pixels within rounding of the source border may differ in validity: skip those.
        u, v, _ = ref.map_points(hom32[p, 0], ref_img.shape)
        border = (np.abs(u) < 1e-3) | (np.abs(u - 55) < 1e-3) | (np.abs(v) < 1e-3) | (np.abs(v - 49) < 1e-3)
        sel = valid & ~border
        assert sel.mean() > 0.8
        assert (np.abs(got[p][sel] - cost[sel]) <= slack[sel]).all()
        assert (got[p][~valid & ~border] == 62).all()


@pytest.mark.parametrize("ring", [0.0, 2.0])
@pytest.mark.parametrize("window", [(5, 5), (7, 9)])
def test_split_sweep_equals_staged_kernel_bit_for_bit(cl_device, window, ring):
    """sweep_warp + sweep_warped_cost give exactly sweep_census_cost's costs: perspective
    homographies, two sources with best-2 aggregation, a tile inside the image (clamped census
    neighbours at its border), sources partly out of view; with and without the census ring's
    weight (its 7 x 9 ring spans both 32-bit words of the vector path's codes)."""
    rng = np.random.default_rng(9)
    rx, ry = window[1] // 2, window[0] // 2
    ref_img = rng.random((41, 53)).astype(np.float32)
    srcs = [rng.random((45, 50)).astype(np.float32), rng.random((39, 57)).astype(np.float32)]
    base = np.array([[1.02, 0.05, 1.3], [-0.04, 0.98, 0.7], [1e-4, -2e-4, 1.0]])
    hom = np.stack([[base + np.array([[0, 0, 2.5 * p - 3.0 * s], [0, 0, 0.7 * s - 1.1 * p], [0, 0, 0]])
                     for s in range(2)] for p in range(5)])
    tx0, ty0, tw, th = 3, 6, 37, 29
    shift = np.eye(3)
    shift[0, 2], shift[1, 2] = tx0, ty0
    local = (hom @ shift).astype(np.float32).astype(np.float64)
    tile = (tx0, ty0, tw, th)
    staged = _sweep_dev(cl_device, ref_img, srcs, local, rx, ry, 2, wg=(8, 8), tile=tile, ring=ring)
    split = _sweep_dev(cl_device, ref_img, srcs, local, rx, ry, 2, mode="split", tile=tile,
                       ring=ring)
    np.testing.assert_array_equal(split, staged)
    invalid = (2 * rx + 1) * (2 * ry + 1) - 1
    assert (staged == invalid).any() and (staged < invalid).any()


@pytest.mark.parametrize("form", ["warped_census", "split"])
@pytest.mark.parametrize("terms", [(8.0, 0.0), (0.0, 4.0), (8.0, 4.0)], ids=["ad", "grad", "both"])
def test_ad_census_cost_matches_reference(cl_device, form, terms):
    """With AD_WEIGHT > 0 each source's cost is the Hamming distance plus
    AD_WEIGHT * min(|I_src - I_ref|, AD_TRUNC) / AD_TRUNC, with GRAD_WEIGHT > 0 plus the
    truncated gradient differences, on a tile inside the image (the tile touches the image's
    top and right edges, where the gradients' neighbours are clamped); the no-source cost is
    COST_MAX = census bits + AD_WEIGHT + GRAD_WEIGHT."""
    rng = np.random.default_rng(12)
    ref_img = rng.random((36, 44)).astype(np.float32)
    src = np.clip(np.roll(ref_img, 1, axis=1) + 0.05 * rng.standard_normal(ref_img.shape), 0, 1)
    src = src.astype(np.float32)
    (weight, gweight), trunc, gtrunc = terms, 0.15, 0.1
    # Dyadic translations: the warp is exact, so only the float32 AD arithmetic differs.
    hom = _translations([[[1.0, 0.0]], [[0.5, -0.25]], [[20.0, 0.0]]])
    tx0, ty0, tw, th = 4, 0, 40, 30
    shift = np.eye(3)
    shift[0, 2], shift[1, 2] = tx0, ty0
    local = hom @ shift
    got = _sweep_dev(cl_device, ref_img, [src], local, 2, 2, 1, mode=form, wg=(8, 8),
                     tile=(tx0, ty0, tw, th), ad=(weight, trunc), grad=(gweight, gtrunc))
    codes = ref.census(ref_img, 2, 2)
    for p in range(hom.shape[0]):
        cost, valid = ref.warped_census_cost(codes, src, hom[p, 0], 2, 2, ref_img=ref_img,
                                             ad_weight=weight, ad_truncation=trunc,
                                             grad_weight=gweight, grad_truncation=gtrunc)
        want = np.where(valid, cost, 24 + weight + gweight)[ty0:ty0 + th, tx0:tx0 + tw]
        np.testing.assert_allclose(got[p], want, atol=AD_ATOL, rtol=0)
    census_only = _sweep_dev(cl_device, ref_img, [src], local, 2, 2, 1, mode=form, wg=(8, 8),
                             tile=(tx0, ty0, tw, th))
    assert (got > census_only).mean() > 0.5  # the term is there where intensities differ
    assert (got == 24 + weight + gweight).any()  # shifted 20 px: part of the tile sees no source


def _noisy_source_on_tile(rng, ref_img):
    """(src, hom, tile, local) for the census-term tests on a 36 x 44 reference: the reference
    moved by a pixel with a third of its pixels redrawn (codes that differ), four dyadic or
    quarter translations (exact warps; no rounding tie when sampled), the last 20 px (part of
    the tile sees no source), a tile (tx0, ty0, tw, th) inside the image and the translations
    from its local pixels."""
    src = np.roll(ref_img, 1, axis=1).copy()
    noisy = rng.random(src.shape) < 0.3
    src[noisy] = _quantised(rng, src.shape)[noisy]
    hom = _translations([[[1.0, 0.0]], [[0.5, -0.25]], [[2.25, 0.75]], [[20.0, 0.0]]])
    tile = (4, 2, 36, 30)
    shift = np.eye(3)
    shift[0, 2], shift[1, 2] = tile[0], tile[1]
    return src.astype(np.float32), hom, tile, hom @ shift


@pytest.mark.parametrize("window", [(5, 5), (7, 9)])
@pytest.mark.parametrize("form", ["warped_census", "split", "sampled_codes"])
def test_census_ring_weight_matches_reference(cl_device, form, window):
    """With census_ring_weight w each source's census term is (bits + w ring bits) n / (n + w
    n_ring), the ring's bits those comparing the centre with its 8 nearest neighbours (found bit
    by bit in the reference, from the window's raster order): in every cost kernel, on a tile
    inside the image; the term still spans 0..n (the no-source cost stays n)."""
    rng = np.random.default_rng(21)
    rx, ry = window[1] // 2, window[0] // 2
    n, w = window[0] * window[1] - 1, 2.0
    ref_img = _quantised(rng, (36, 44))
    src, hom, (tx0, ty0, tw, th), local = _noisy_source_on_tile(rng, ref_img)
    got = _sweep_dev(cl_device, ref_img, [src], local, rx, ry, 1, mode=form, wg=(8, 8),
                     tile=(tx0, ty0, tw, th), ring=w)
    plain = _sweep_dev(cl_device, ref_img, [src], local, rx, ry, 1, mode=form, wg=(8, 8),
                       tile=(tx0, ty0, tw, th))
    codes = ref.census(ref_img, rx, ry)
    src_codes = ref.census(src, rx, ry)
    for p in range(hom.shape[0]):
        if form == "sampled_codes":
            cost, valid = ref.sampled_codes_cost(codes, src_codes, hom[p, 0], rx, ry, w)
        else:
            cost, valid = ref.warped_census_cost(codes, src, hom[p, 0], rx, ry, ring_weight=w)
        want = np.where(valid, cost, n)[ty0:ty0 + th, tx0:tx0 + tw]
        np.testing.assert_allclose(got[p], want, atol=RING_ATOL, rtol=0)
    assert (np.abs(got - plain) > 0.1).mean() > 0.3  # the weight changes the costs
    assert got.max() <= n + RING_ATOL and (got == n).any()  # shifted 20 px: no source


@pytest.mark.parametrize("ring", [0.0, 8.0])
@pytest.mark.parametrize("form", ["warped_census", "split"])
def test_census_mask_matches_reference(cl_device, form, ring):
    """With census_mask_threshold t the reference's codes carry the mask of the comparisons
    whose neighbour lies within t of the centre, and each source's census term counts only
    those bits, scaled by n / (the mask's own term), or every bit where that term is under
    CENSUS_MASK_MIN_BITS: in both warped-census kernels, with and without the ring's weight,
    on a tile inside the image. An image of two flat halves with texture (a roof beside the
    ground) gives masks of every kind: whole windows, windows cut by the step, and pixels
    unlike their whole window."""
    rng = np.random.default_rng(33)
    rx = ry = 2
    n, t = 24, 0.12
    ref_img = _quantised(rng, (36, 44), levels=64) * np.float32(0.125)  # most windows whole
    ref_img[:, 22:] += np.float32(0.5)  # a step of 0.5 at column 22
    ref_img[10, 5] = np.float32(1.0)  # an isolated bright pixel: unlike its window
    src, hom, (tx0, ty0, tw, th), local = _noisy_source_on_tile(rng, ref_img)
    got = _sweep_dev(cl_device, ref_img, [src], local, rx, ry, 1, mode=form, wg=(8, 8),
                     tile=(tx0, ty0, tw, th), ring=ring, mask=t)
    plain = _sweep_dev(cl_device, ref_img, [src], local, rx, ry, 1, mode=form, wg=(8, 8),
                       tile=(tx0, ty0, tw, th), ring=ring)
    codes = ref.census(ref_img, rx, ry)
    mask = ref.census_mask(ref_img, rx, ry, t)
    for p in range(hom.shape[0]):
        cost, valid = ref.warped_census_cost(codes, src, hom[p, 0], rx, ry, ring_weight=ring,
                                             mask=mask, mask_min_bits=CENSUS_MASK_MIN_BITS)
        want = np.where(valid, cost, n)[ty0:ty0 + th, tx0:tx0 + tw]
        np.testing.assert_allclose(got[p], want, atol=RING_ATOL, rtol=0)
    # the masks are of every kind there, and the mask changes the costs beside the step only
    weights = ref.census_term(mask, np.zeros_like(mask), rx, ry, ring)[ty0:ty0 + th, tx0:tx0 + tw]
    assert (weights == n).mean() > 0.5 and (weights < CENSUS_MASK_MIN_BITS).any()
    assert ((weights >= CENSUS_MASK_MIN_BITS) & (weights < n)).any()
    changed = np.abs(got - plain) > RING_ATOL
    assert changed.any() and not changed[:, weights == n].any()
    assert got.max() <= n + RING_ATOL and (got == n).any()  # shifted 20 px: no source


def test_sampled_codes_cost_exact(cl_device):
    rng = np.random.default_rng(7)
    ref_img = _quantised(rng, (33, 47))
    src = _quantised(rng, (36, 44))
    # Quarter shifts never land on a rounding tie (x.5).
    hom = _translations([[[0.25, -0.75]], [[2.75, 1.25]], [[-5.25, 3.0]]])
    got = _sweep_dev(cl_device, ref_img, [src], hom, 4, 3, 1, mode="sampled_codes")
    codes = ref.census(ref_img, 4, 3)
    src_codes = ref.census(src, 4, 3)
    for p in range(hom.shape[0]):
        cost, valid = ref.sampled_codes_cost(codes, src_codes, hom[p, 0])
        np.testing.assert_array_equal(got[p], np.where(valid, cost, 62))


@pytest.mark.parametrize("mode", ["warped_census", "split", "sampled_codes"])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_best_k_aggregation_over_sources(cl_device, mode, k):
    rng = np.random.default_rng(8 + k)
    h, w = 32, 40
    ref_img = _quantised(rng, (h, w))
    # Source 0 is the reference itself (cost 0 at zero shift); sources 1-2 are noise. Shifts
    # push each source partly outside so that 0, 1, 2 or 3 sources are valid across the image.
    srcs = [ref_img.copy(), _quantised(rng, (h, w)), _quantised(rng, (h, w))]
    shifts = np.array([[[0.0, 0.0], [9.25, 0.0], [0.0, -7.75]],
                       [[-12.25, 0.0], [20.0, 0.5], [0.25, 16.0]],
                       [[45.0, 0.0], [-45.0, 0.0], [0.0, 40.0]]])
    hom = _translations(shifts)
    got = _sweep_dev(cl_device, ref_img, srcs, hom, 4, 3, k, mode=mode)
    codes = ref.census(ref_img, 4, 3)
    src_codes = [ref.census(s, 4, 3) for s in srcs]
    for p in range(hom.shape[0]):
        cs, vs = [], []
        for s in range(3):
            if mode in ("warped_census", "split"):
                c, v = ref.warped_census_cost(codes, srcs[s], hom[p, s], 4, 3)
            else:
                c, v = ref.sampled_codes_cost(codes, src_codes[s], hom[p, s])
            cs.append(c)
            vs.append(v)
        want = ref.aggregate_best_k(np.stack(cs), np.stack(vs), k, 62.0)
        np.testing.assert_allclose(got[p], want, rtol=DIV_RTOL, atol=0)
    # The last plane maps the whole reference outside every source: all invalid.
    assert (got[2] == 62).all()
    # Zero shift of source 0 gives cost 0 with k = 1 wherever source 0 is valid.
    if k == 1:
        assert (got[0] == 0).all()


def test_split_sweep_reads_the_pad_with_zero_weight(cl_device):
    """sweep_warp's paired taps read one float past a source's last column where the sample is
    clamped there (weight 0): past the last source, the pad, whose value then changes nothing
    (with a weight above 0 a huge pad would show in the costs)."""
    rng = np.random.default_rng(21)
    h, w = 24, 40
    ref_img = _quantised(rng, (h, w))
    srcs = [_quantised(rng, (h, w)), _quantised(rng, (h, w))]
    # Shifts that put part of the reference past both sources' last column and last row.
    hom = _translations(np.array([[[6.5, 3.0], [11.0, 5.5]], [[15.25, 9.0], [2.0, 13.75]]]))
    zero = _sweep_dev(cl_device, ref_img, srcs, hom, 2, 2, 1, mode="split", ad=(8.0, 0.15))
    huge = _sweep_dev(cl_device, ref_img, srcs, hom, 2, 2, 1, mode="split", ad=(8.0, 0.15),
                      pad=1e30)
    np.testing.assert_array_equal(zero, huge)


# -- box and guided filters ----------------------------------------------------------------------
# Radii up to 7 take the row kernels' direct vector sums, larger ones their sliding sums
# (guided_filter.cl ROW_DIRECT_MAX_R): both forms are checked.
@pytest.mark.parametrize("radius", [0, 1, 3, 7, 9])
def test_box_filter_matches_float64_reference(cl_device, radius):
    rng = np.random.default_rng(10 + radius)
    # 70 columns > BOX_CHUNK = 32: several chunks per row with restarted sums.
    vol = (rng.random((3, 45, 70)) * 62).astype(np.float32)
    guide = rng.random((45, 70)).astype(np.float32)
    sweep = PlaneSweep(cl_device, SweepOptions(cost_filter="box", box_radius=radius))
    got = sweep.filter_volume(vol, guide)
    np.testing.assert_allclose(got, ref.box_mean(vol, radius), atol=BOX_ATOL, rtol=0)
    assert box_chunk(radius) >= 2 * radius + 1


@pytest.mark.parametrize("radius,eps", [(1, 1e-3), (4, 1e-3), (6, 1e-2), (9, 1e-3)])
def test_guided_filter_matches_float64_reference(cl_device, radius, eps):
    rng = np.random.default_rng(20 + radius)
    guide = ref.smooth_noise((41, 67), 1.5, rng).astype(np.float32)
    vol = (rng.random((4, 41, 67)) * 62).astype(np.float32)
    sweep = PlaneSweep(cl_device, SweepOptions(cost_filter="guided", gf_radius=radius, gf_eps=eps))
    got = sweep.filter_volume(vol, guide)
    want = ref.guided_filter(vol, guide, radius, eps)
    np.testing.assert_allclose(got, want, atol=GF_ATOL, rtol=0)
    # The filter is edge-aware: it differs from a plain box mean of the same radius.
    assert np.abs(want - ref.box_mean(vol, radius)).max() > 100 * GF_ATOL


# -- winner-take-all ----------------------------------------------------------------------------------
def _wta_dev(dev, vol, hom, src_shapes, nb, reject_edges, rx=4, ry=3):
    """Stream vol (n_planes, h, w) through wta_update in batches of nb, then finalize."""
    n_planes, h, w = vol.shape
    n_src = len(src_shapes)
    prg = dev.build("wta", {"NSRC": n_src, "CENSUS_RX": rx, "CENSUS_RY": ry})
    i32 = np.int32
    q = dev.queue
    state = _empty(dev, 4 * WTA_NSTATE * h * w)
    launch(cl.Kernel(prg, "wta_init"), q, (w, h), state, i32(w), i32(h))
    upd = cl.Kernel(prg, "wta_update")
    for p0 in range(0, n_planes, nb):
        n = min(nb, n_planes - p0)
        launch(upd, q, (-(-w // WTA_VEC), h), _buf(dev, vol[p0:p0 + n]), i32(w), i32(h), i32(0),
               i32(0), i32(w), i32(h), i32(n), i32(p0), state)
    sizes = np.array([[s[1], s[0]] for s in src_shapes], np.int32).ravel()
    outs = [_empty(dev, 4 * h * w) for _ in range(3)] + [_empty(dev, h * w)]
    launch(cl.Kernel(prg, "wta_finalize"), q, (w, h),
           state, i32(w), i32(h), i32(n_planes), i32(0), i32(0),
           _buf(dev, np.ascontiguousarray(hom.reshape(n_planes, n_src, 9), np.float32)),
           _buf(dev, sizes), i32(1 if reject_edges else 0), *outs)
    return (*(_read(dev, o, (h, w), np.float32) for o in outs[:3]),
            _read(dev, outs[3], (h, w), np.uint8).astype(bool))


@pytest.mark.parametrize("counted", [False, True])
def test_wta_pixel_major_equals_streaming_state(cl_device, counted):
    """wta_pixel_major over a pixel-major volume leaves exactly the state of wta_init followed by
    wta_update over the same planes (plane-major): every field, bit for bit. With label counts,
    each pixel's state is that of its first count planes (counts that differ within a work-item's
    8 pixels, and equal ones)."""
    rng = np.random.default_rng(41)
    n_planes, h, w = 13, 17, 19
    # Costs on a 1/4 grid (ties, plateaus), a constant block and an increasing ramp (first plane).
    vol = (rng.integers(0, 40, (n_planes, h, w)) / 4).astype(np.float32)
    vol[:, :3, :3] = 5.0
    vol[:, 5, :] = np.arange(n_planes, dtype=np.float32)[:, None]
    count = rng.integers(1, n_planes + 1, (h, w)).astype(np.int32)
    count[10:, :] = 6  # whole work-items of one count
    prg = cl_device.build("wta", {"NSRC": 1, "CENSUS_RX": 1, "CENSUS_RY": 1})
    i32, q = np.int32, cl_device.queue
    want = np.empty((WTA_NSTATE, h, w), np.float32)
    for n in (np.unique(count) if counted else [n_planes]):
        streamed = _empty(cl_device, 4 * WTA_NSTATE * h * w)
        launch(cl.Kernel(prg, "wta_init"), q, (w, h), streamed, i32(w), i32(h))
        launch(cl.Kernel(prg, "wta_update"), q, (-(-w // WTA_VEC), h),
               _buf(cl_device, np.ascontiguousarray(vol[:n])), i32(w),
               i32(h), i32(0), i32(0), i32(w), i32(h), i32(n), i32(0),
               streamed)
        state = _read(cl_device, streamed, (WTA_NSTATE, h, w), np.float32)
        mine = (count == n) if counted else np.ones((h, w), bool)
        want[:, mine] = state[:, mine]
    one_pass = _empty(cl_device, 4 * WTA_NSTATE * h * w)
    pixel_major = np.ascontiguousarray(vol.transpose(1, 2, 0))
    launch(cl.Kernel(prg, "wta_pixel_major"), q, (-(-h * w // WTA_VEC),),
           _buf(cl_device, pixel_major),
           i32(h * w), i32(n_planes), _buf(cl_device, count),
           _buf(cl_device, np.arange(h * w, dtype=np.uint64) * n_planes),
           i32(1 if counted else 0), one_pass)
    got = _read(cl_device, one_pass, (WTA_NSTATE, h, w), np.float32)
    np.testing.assert_array_equal(got, want)
    if not counted:  # (a truncated pixel's minimum may be its last plane, tested at the finish)
        assert (want[WTA_SLOT["I1"]] >= 0).all()  # every pixel found a minimum


@pytest.mark.parametrize("counted", [False, True])
def test_wta_close_leaves_the_reference_minima(cl_device, counted):
    """wta_pixel_major then wta_close (SGM's winner-take-all): each pixel's closed state holds,
    over its planes (its first count planes with counts), the first argmin (I1), its cost (M1),
    the costs of the planes around it (M1P, M1N: WTA_BIG past the pixel's first or last plane)
    and the second-lowest local minimum, or the largest cost where there is none (M2), as the
    numpy reference finds them. Costs on a 1/4 grid are exact in float32: equal, bit for bit."""
    rng = np.random.default_rng(43)
    n_planes, h, w = 12, 15, 21
    vol = (rng.integers(0, 40, (n_planes, h, w)) / 4).astype(np.float32)
    vol[:, :3, :3] = 5.0  # constant: one minimum, at the first plane, and no second one
    vol[:, 5, :] = -np.arange(n_planes, dtype=np.float32)[:, None]  # the minimum at the last
    count = rng.integers(1, n_planes + 1, (h, w)).astype(np.int32) if counted \
        else np.full((h, w), n_planes, np.int32)
    prg = cl_device.build("wta", {"NSRC": 1, "CENSUS_RX": 1, "CENSUS_RY": 1})
    i32, q = np.int32, cl_device.queue
    state = _empty(cl_device, 4 * WTA_NSTATE * h * w)
    count_buf = _buf(cl_device, count)
    launch(cl.Kernel(prg, "wta_pixel_major"), q, (-(-h * w // WTA_VEC),),
           _buf(cl_device, np.ascontiguousarray(vol.transpose(1, 2, 0))),
           i32(h * w), i32(n_planes), count_buf,
           _buf(cl_device, np.arange(h * w, dtype=np.uint64) * n_planes),
           i32(1 if counted else 0), state)
    launch(cl.Kernel(prg, "wta_close"), q, (h * w,), state, i32(h * w), i32(n_planes), count_buf,
           i32(1 if counted else 0))
    got = _read(cl_device, state, (WTA_NSTATE, h, w), np.float32)
    big = np.float32(WTA_BIG)
    for n in np.unique(count):
        mine = count == n
        part = vol[:n].astype(np.float64)
        i1, _, _, m1 = ref.wta(part, 1.0)
        edge = np.full((1, h, w), np.inf)
        prev, nxt = np.concatenate([edge, part[:-1]]), np.concatenate([part[1:], edge])
        before = np.take_along_axis(prev, i1[None], 0)[0]
        after = np.take_along_axis(nxt, i1[None], 0)[0]
        others = np.where((part < prev) & (part <= nxt), part, np.inf)  # the local minima
        np.put_along_axis(others, i1[None], np.inf, 0)
        m2 = np.where(np.isfinite(others.min(0)), others.min(0), part.max(0))
        want = {"I1": i1, "M1": m1, "M1P": np.where(np.isinf(before), big, before),
                "M1N": np.where(np.isinf(after), big, after), "M2": m2}
        for field, value in want.items():
            np.testing.assert_array_equal(got[WTA_SLOT[field]][mine],
                                          value.astype(np.float32)[mine], err_msg=field)
    assert (got[WTA_SLOT["I1"]][5] == count[5] - 1).all()  # the last plane, tested on closing


@pytest.mark.parametrize("nb", [1, 3, 16])
def test_wta_streaming_matches_reference(cl_device, nb):
    rng = np.random.default_rng(30 + nb)
    n_planes, h, w = 11, 23, 29
    # Costs on a 1/4 grid: many ties and plateaus exercise the first-argmin and minimum rules.
    vol = (rng.integers(0, 40, (n_planes, h, w)) / 4).astype(np.float32)
    vol[:, :3, :3] = 5.0  # constant: a single (first-plane) minimum
    hom = _translations(np.zeros((n_planes, 1, 2)))
    index, conf, best, valid = _wta_dev(cl_device, vol, hom, [(h, w)], nb, reject_edges=False)
    i1, frac, want_conf, m1 = ref.wta(vol, 62)
    # The fractional index lies within half a plane of the first argmin and matches the parabola.
    assert (np.abs(index - i1) <= 0.5).all()
    np.testing.assert_allclose(index, frac, atol=PARABOLA_ATOL, rtol=0)
    assert (index != np.round(index)).any()  # refinement happened somewhere
    np.testing.assert_array_equal(best, m1)
    np.testing.assert_allclose(conf, want_conf, atol=1e-6, rtol=0)
    assert valid.all()
    assert (index[:3, :3] == 0).all()


def test_wta_validity_from_geometry_and_range_edges(cl_device):
    n_planes, h, w = 6, 20, 30
    rng = np.random.default_rng(40)
    vol = rng.random((n_planes, h, w)).astype(np.float32)
    # Plane p shifts the source by 5 p pixels: at higher planes more columns fall outside.
    hom = _translations(np.stack([np.array([[5.0 * p, 0.0]]) for p in range(n_planes)]))
    for reject in (False, True):
        _, _, _, valid = _wta_dev(cl_device, vol, hom, [(h, w)], 4, reject_edges=reject)
        best = np.argmin(vol, axis=0)
        np.testing.assert_array_equal(valid, ref.valid_at_plane(best, hom, [(h, w)], reject))
        assert valid.any() and (~valid).any()
