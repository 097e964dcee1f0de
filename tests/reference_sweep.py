"""Numpy references of the plane-sweep kernels (test-only; float64 where arithmetic is involved).

Each function restates what one kernel computes, vectorised over pixels, written from the
definitions in the kernels' header comments rather than from the kernel code:

- ``census``: kernels/census.cl (raster-order bits, centre skipped, edge replication);
- ``warp_image`` / ``warped_census_cost`` / ``sampled_codes_cost`` / ``aggregate_best_k``:
  kernels/sweep.cl;
- ``box_mean`` / ``guided_filter``: kernels/guided_filter.cl (clipped windows, float64 cumsums);
- ``wta``: kernels/wta.cl (first argmin, local minima, parabola, confidence, validity).

Pixel (0, 0) is the centre of the first pixel; homographies map reference pixels to source pixels.
"""

from __future__ import annotations

import numpy as np


def _window_bits(img: np.ndarray, rx: int, ry: int, test) -> np.ndarray:
    """uint64 per pixel: one bit per neighbour of the (2 ry + 1) x (2 rx + 1) window (raster
    order, centre skipped, edge replication), the first in the highest used bit, set where
    ``test(neighbour, centre)`` (float32 arrays) holds."""
    img = np.asarray(img, dtype=np.float32)
    h, w = img.shape
    pad = np.pad(img, ((ry, ry), (rx, rx)), mode="edge")
    bits = np.zeros((h, w), np.uint64)
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            if dx == 0 and dy == 0:
                continue
            nb = pad[ry + dy:ry + dy + h, rx + dx:rx + dx + w]
            bits = (bits << np.uint64(1)) | test(nb, img).astype(np.uint64)
    return bits


def census(img: np.ndarray, rx: int, ry: int) -> np.ndarray:
    """Census codes (uint64) of a 2-D image, window (2 ry + 1) x (2 rx + 1), edge replication."""
    return _window_bits(img, rx, ry, lambda nb, centre: nb < centre)


def census_mask(img: np.ndarray, rx: int, ry: int, threshold: float) -> np.ndarray:
    """The edge-aware census's mask (uint64, the code's bit order): bit set where the neighbour
    lies within ``threshold`` of the centre, |v - c| < threshold in float32 as the kernel."""
    t = np.float32(threshold)
    return _window_bits(img, rx, ry, lambda nb, centre: np.abs(nb - centre) < t)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Number of differing bits of two uint64 code arrays."""
    return np.bitwise_count(np.asarray(a, np.uint64) ^ np.asarray(b, np.uint64)).astype(np.int64)


def ring_positions(rx: int, ry: int) -> np.ndarray:
    """(n_bits,) bool: which bits of a census code (highest first, raster order of the window)
    compare the centre with one of its 8 nearest neighbours."""
    return np.array([abs(dy) <= 1 and abs(dx) <= 1 for dy in range(-ry, ry + 1)
                     for dx in range(-rx, rx + 1) if (dy, dx) != (0, 0)])


def _weighted_bits(d: np.ndarray, rx: int, ry: int, ring_weight: float) -> np.ndarray:
    """The set bits of codes d (float64): their count, or with ring_weight = w
    (bits + w ring bits) n / (n + w n_ring); the ring's bits found bit by bit."""
    ring = ring_positions(rx, ry)
    n = ring.size
    bits = np.stack([(d >> np.uint64(n - 1 - k)) & np.uint64(1) for k in range(n)])
    bits = bits.astype(np.float64)
    total, ring_bits = bits.sum(axis=0), bits[ring].sum(axis=0)
    if ring_weight == 0.0:
        return total
    return (total + ring_weight * ring_bits) * n / (n + ring_weight * ring.sum())


def census_term(a: np.ndarray, b: np.ndarray, rx: int, ry: int, ring_weight: float = 0.0,
                mask: np.ndarray | None = None, min_bits: float = 0.0):
    """The census term of two code arrays: the differing bits, or with ring_weight = w
    (bits + w ring bits) n / (n + w n_ring), float64. With ``mask`` (the reference's
    ``census_mask``) only the masked bits count, scaled by n / (the mask's own term); where the
    mask's term is under ``min_bits``, every bit counts."""
    d = np.asarray(a, np.uint64) ^ np.asarray(b, np.uint64)
    full = _weighted_bits(d, rx, ry, ring_weight)
    if mask is None:
        return full
    n = (2 * rx + 1) * (2 * ry + 1) - 1
    m = np.asarray(mask, np.uint64)
    wm = _weighted_bits(m, rx, ry, ring_weight)
    with np.errstate(divide="ignore", invalid="ignore"):
        masked = _weighted_bits(d & m, rx, ry, ring_weight) * n / wm
    return np.where(wm >= min_bits, masked, full)


def map_points(hom: np.ndarray, shape: tuple[int, int]):
    """(u, v, positive) of every pixel of a (h, w) grid through a 3x3 homography, float64."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    H = np.asarray(hom, np.float64)
    wz = H[2, 0] * xs + H[2, 1] * ys + H[2, 2]
    pos = wz > 0
    safe = np.where(pos, wz, 1.0)
    u = np.where(pos, (H[0, 0] * xs + H[0, 1] * ys + H[0, 2]) / safe, 0.0)
    v = np.where(pos, (H[1, 0] * xs + H[1, 1] * ys + H[1, 2]) / safe, 0.0)
    return u, v, pos


def bilinear_clamped(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at (u, v) after clamping into the image (float64)."""
    img = np.asarray(img, np.float64)
    h, w = img.shape
    u = np.clip(u, 0.0, w - 1.0)
    v = np.clip(v, 0.0, h - 1.0)
    x0 = np.floor(u).astype(np.int64)
    y0 = np.floor(v).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax, ay = u - x0, v - y0
    top = (1 - ax) * img[y0, x0] + ax * img[y0, x1]
    bot = (1 - ax) * img[y1, x0] + ax * img[y1, x1]
    return (1 - ay) * top + ay * bot


def warp_image(src: np.ndarray, hom: np.ndarray, shape: tuple[int, int]):
    """Source warped onto a (h, w) reference grid, and the validity of each reference pixel.

    Warped value: bilinear (clamped) sample at H q, 0 where the denominator is not positive.
    Valid: positive denominator and H q inside [0, w_s - 1] x [0, h_s - 1].
    """
    hs, ws = src.shape
    u, v, pos = map_points(hom, shape)
    warped = np.where(pos, bilinear_clamped(src, u, v), 0.0)
    valid = pos & (u >= 0) & (u <= ws - 1) & (v >= 0) & (v <= hs - 1)
    return warped, valid


def central_differences(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I(x+1) - I(x-1), I(y+1) - I(y-1)) with edge-replicated neighbours (float64)."""
    p = np.pad(np.asarray(img, np.float64), 1, mode="edge")
    return p[1:-1, 2:] - p[1:-1, :-2], p[2:, 1:-1] - p[:-2, 1:-1]


def warped_census_cost(ref_codes: np.ndarray, src: np.ndarray, hom: np.ndarray, rx: int, ry: int,
                       *, ref_img: np.ndarray | None = None, ad_weight: float = 0.0,
                       ad_truncation: float = 1.0, grad_weight: float = 0.0,
                       grad_truncation: float = 1.0, ring_weight: float = 0.0,
                       mask: np.ndarray | None = None, mask_min_bits: float = 0.0):
    """Census term (``census_term``, ring_weight) of the census of the warped source
    (float32-rounded warp) and validity; with
    ad_weight > 0 plus ad_weight * min(|warped - ref_img|, ad_truncation) / ad_truncation; with
    grad_weight > 0 plus grad_weight * (min(|dx_w - dx_ref|, t) + min(|dy_w - dy_ref|, t)) / (2 t)
    (central differences of the warped image and of ref_img, t = grad_truncation). ``mask``,
    ``mask_min_bits``: the edge-aware census (``census_term``)."""
    warped, valid = warp_image(src, hom, ref_codes.shape)
    warped = warped.astype(np.float32)
    cost = census_term(ref_codes, census(warped, rx, ry), rx, ry, ring_weight, mask,
                       mask_min_bits)
    if ad_weight > 0:
        diff = np.abs(warped.astype(np.float64) - np.asarray(ref_img, np.float64))
        cost = cost + ad_weight * np.minimum(diff, ad_truncation) / ad_truncation
    if grad_weight > 0:
        (wx, wy), (gx, gy) = central_differences(warped), central_differences(ref_img)
        t = grad_truncation
        cost = cost + grad_weight * (np.minimum(np.abs(wx - gx), t)
                                     + np.minimum(np.abs(wy - gy), t)) / (2 * t)
    return cost, valid


def sampled_codes_cost(ref_codes: np.ndarray, src_codes: np.ndarray, hom: np.ndarray,
                       rx: int | None = None, ry: int | None = None, ring_weight: float = 0.0):
    """Hamming cost of the source codes at the nearest warped pixel (floor(u + 0.5)), validity;
    with ring_weight (and the census radii rx, ry) the census term of ``census_term``."""
    hs, ws = src_codes.shape
    u, v, pos = map_points(hom, ref_codes.shape)
    valid = pos & (u >= 0) & (u <= ws - 1) & (v >= 0) & (v <= hs - 1)
    iu = np.clip(np.floor(u + 0.5).astype(np.int64), 0, ws - 1)
    iv = np.clip(np.floor(v + 0.5).astype(np.int64), 0, hs - 1)
    if ring_weight:
        return np.where(valid, census_term(ref_codes, src_codes[iv, iu], rx, ry, ring_weight),
                        0), valid
    return np.where(valid, hamming(ref_codes, src_codes[iv, iu]), 0), valid


def aggregate_best_k(costs: np.ndarray, valid: np.ndarray, k: int, invalid_cost: float) -> np.ndarray:
    """Mean of the k lowest valid costs along axis 0; invalid_cost where no source is valid."""
    c = np.where(valid, np.asarray(costs, np.float64), np.inf)
    c = np.sort(c, axis=0)[:k]
    n = np.minimum(valid.sum(axis=0), k)
    total = np.where(np.isfinite(c), c, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), invalid_cost)


def sweep_volume(ref: np.ndarray, srcs, hom: np.ndarray, rx: int, ry: int, k: int,
                 mode: str = "warped_census", ad_weight: float = 0.0,
                 ad_truncation: float = 1.0, grad_weight: float = 0.0,
                 grad_truncation: float = 1.0, ring_weight: float = 0.0) -> np.ndarray:
    """Aggregated cost volume (n_planes, h, w) of a whole reference image (float64); the AD and
    gradient terms (warped_census mode) and the census ring's weight as in warped_census_cost;
    no valid source costs bits + ad_weight + grad_weight."""
    ref_codes = census(ref, rx, ry)
    nbits = (2 * rx + 1) * (2 * ry + 1) - 1
    src_codes = [census(s, rx, ry) for s in srcs] if mode == "sampled_codes" else None
    vol = np.empty((hom.shape[0],) + ref.shape)
    for p in range(hom.shape[0]):
        cs, vs = [], []
        for s, src in enumerate(srcs):
            if mode == "sampled_codes":
                c, v = sampled_codes_cost(ref_codes, src_codes[s], hom[p, s], rx, ry, ring_weight)
            else:
                c, v = warped_census_cost(ref_codes, src, hom[p, s], rx, ry, ref_img=ref,
                                          ad_weight=ad_weight, ad_truncation=ad_truncation,
                                          grad_weight=grad_weight, grad_truncation=grad_truncation,
                                          ring_weight=ring_weight)
            cs.append(c)
            vs.append(v)
        vol[p] = aggregate_best_k(np.stack(cs), np.stack(vs), k,
                                  float(nbits) + ad_weight + grad_weight)
    return vol


def box_sum_axis(x: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Sums over the clipped window [i - r, i + r] along one axis (float64 cumulative sums)."""
    x = np.moveaxis(np.asarray(x, np.float64), axis, -1)
    n = x.shape[-1]
    cs = np.concatenate([np.zeros(x.shape[:-1] + (1,)), np.cumsum(x, axis=-1)], axis=-1)
    i = np.arange(n)
    hi = np.minimum(i + r + 1, n)
    lo = np.maximum(i - r, 0)
    return np.moveaxis(cs[..., hi] - cs[..., lo], -1, axis)


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """Mean over the (2r+1)^2 window clipped to the last two axes (count of inside pixels)."""
    x = np.asarray(x, np.float64)
    h, w = x.shape[-2:]
    s = box_sum_axis(box_sum_axis(x, r, -2), r, -1)
    ny = box_sum_axis(np.ones(h), r, 0)
    nx = box_sum_axis(np.ones(w), r, 0)
    return s / (ny[:, None] * nx[None, :])


def guided_filter(p: np.ndarray, guide: np.ndarray, r: int, eps: float) -> np.ndarray:
    """He et al. guided filter of each slice of p (..., h, w) with the 2-D guide (float64)."""
    g = np.asarray(guide, np.float64)
    p = np.asarray(p, np.float64)
    mi = box_mean(g, r)
    var = box_mean(g * g, r) - mi * mi
    mp = box_mean(p, r)
    mip = box_mean(g * p, r)
    a = (mip - mi * mp) / (var + eps)
    b = mp - a * mi
    return box_mean(a, r) * g + box_mean(b, r)


def wta(vol: np.ndarray, nbits: float):
    """(best index, fractional index, confidence, best cost) of a (n_planes, h, w) volume;
    confidence = (second local minimum - best) / nbits (the largest cost), clipped to [0, 1]."""
    vol = np.asarray(vol, np.float64)
    n = vol.shape[0]
    inf = np.full((1,) + vol.shape[1:], np.inf)
    prev = np.concatenate([inf, vol[:-1]])
    nxt = np.concatenate([vol[1:], inf])
    is_min = (vol < prev) & (vol <= nxt)
    i1 = np.argmin(vol, axis=0)
    m1 = np.take_along_axis(vol, i1[None], 0)[0]
    others = np.where(is_min, vol, np.inf)
    np.put_along_axis(others, i1[None], np.inf, 0)
    m2 = others.min(axis=0)
    c2 = np.where(np.isfinite(m2), m2, vol.max(axis=0))
    conf = np.clip((c2 - m1) / nbits, 0.0, 1.0)
    cp = np.take_along_axis(prev, i1[None], 0)[0]
    cn = np.take_along_axis(nxt, i1[None], 0)[0]
    inner = (i1 > 0) & (i1 < n - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = np.where(inner, cp - 2 * m1 + cn, 0.0)
        off = np.where(denom > 0, 0.5 * (cp - cn) / np.where(denom > 0, denom, 1.0), 0.0)
    off = np.clip(off, -0.5, 0.5)
    return i1, i1 + off, conf, m1


def valid_at_plane(best: np.ndarray, hom: np.ndarray, src_shapes, reject_edges: bool) -> np.ndarray:
    """Whether each pixel maps into at least one source with the homographies of its best plane."""
    n_planes = hom.shape[0]
    ok = np.zeros(best.shape, bool)
    for p in np.unique(best):
        sel = best == p
        for s, shape in enumerate(src_shapes):
            u, v, pos = map_points(hom[p, s], best.shape)
            ok |= sel & pos & (u >= 0) & (u <= shape[1] - 1) & (v >= 0) & (v <= shape[0] - 1)
    if reject_edges:
        ok &= (best > 0) & (best < n_planes - 1)
    return ok


# -- synthetic scenes with exact ground truth ---------------------------------------------------
def smooth_noise(shape: tuple[int, int], sigma: float, rng: np.random.Generator) -> np.ndarray:
    """White noise blurred by a Gaussian of ``sigma`` pixels, rescaled to [0, 1] (float64)."""
    from scipy import ndimage

    t = ndimage.gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
    return (t - t.min()) / (t.max() - t.min())


def translation_scene(shape: tuple[int, int], shifts_px_per_m, alt_range=(0.0, 20.0), *,
                      seed: int = 0, texture_sigma: float = 1.0, n_bumps: int = 6,
                      noise: float = 0.0):
    """A synthetic reference + sources whose parallax is a translation proportional to height.

    The ground is a smooth height field h(X, Y) (a slanted plane plus Gaussian hills, metres
    within ``alt_range``) carrying a texture T(X, Y). The reference is nadir: ref(x, y) = T(x, y)
    with ground truth h(x, y). Source s sees the ground point (X, Y) at (X + sx h, Y + sy h), so
    its homography for the plane u = h is a translation by (sx h, sy h); each source pixel is
    rendered by solving X = u - sx h(X, Y), Y = v - sy h(X, Y) by fixed-point iteration (a
    contraction here: the parallax slope stays below one pixel per pixel).
    Returns (ref, [src], truth) with float32 images and a float64 truth map.
    """
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    h, w = shape
    shifts = np.asarray(shifts_px_per_m, np.float64).reshape(-1, 2)
    lo, hi = alt_range
    margin = int(np.ceil(np.abs(shifts).max() * max(abs(lo), abs(hi)))) + 8
    tex = smooth_noise((h + 2 * margin, w + 2 * margin), texture_sigma, rng)
    cx = rng.uniform(0, w, n_bumps)
    cy = rng.uniform(0, h, n_bumps)
    sig = rng.uniform(0.12, 0.25, n_bumps) * min(h, w)
    amp = rng.uniform(0.1, 0.3, n_bumps) * (hi - lo)
    slope = rng.uniform(-0.1, 0.1, 2) * (hi - lo) / max(h, w)
    base = lo + 0.2 * (hi - lo)

    def height(X, Y):
        z = base + slope[0] * (X - w / 2) + slope[1] * (Y - h / 2)
        for i in range(n_bumps):
            z = z + amp[i] * np.exp(-((X - cx[i]) ** 2 + (Y - cy[i]) ** 2) / (2 * sig[i] ** 2))
        return np.clip(z, lo + 0.5, hi - 0.5)

    def texture(X, Y):
        return ndimage.map_coordinates(tex, [Y + margin, X + margin], order=3, mode="nearest")

    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    ref = texture(xs, ys)
    truth = height(xs, ys)
    srcs = []
    for sx, sy in shifts:
        X, Y = xs.copy(), ys.copy()
        for _ in range(40):
            z = height(X, Y)
            X, Y = xs - sx * z, ys - sy * z
        img = texture(X, Y)
        if noise > 0:
            img = img + rng.normal(0.0, noise, img.shape)
        srcs.append(img.astype(np.float32))
    if noise > 0:
        ref = ref + rng.normal(0.0, noise, ref.shape)
    return ref.astype(np.float32), srcs, truth


def census_ambiguity(img: np.ndarray, rx: int, ry: int, tol: float) -> np.ndarray:
    """Per pixel, how many census comparisons are within ``tol`` (could flip under rounding)."""
    img = np.asarray(img, dtype=np.float64)
    h, w = img.shape
    pad = np.pad(img, ((ry, ry), (rx, rx)), mode="edge")
    n = np.zeros((h, w), np.int64)
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            if dx or dy:
                n += np.abs(pad[ry + dy:ry + dy + h, rx + dx:rx + dx + w] - img) <= tol
    return n
