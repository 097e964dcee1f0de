/* median.cl: an edge-aware weighted median of a height map, the reference image as guide.
 *
 * out(p) = the weighted median of height(q) over the valid pixels q of the (2 MEDIAN_RADIUS + 1)^2
 * window around p (those inside the map), each weighing
 *     exp(-(guide(q) - guide(p))^2 inv_two_sigma2 - |q - p|^2 inv_two_radius2),
 * i.e. the lowest of the window's heights, in increasing order, at which the running sum of the
 * weights reaches half their total. A pixel of another surface (another grey level) weighs
 * little, so the median keeps the steps where the image has its edges and removes the height
 * noise of flat areas. Invalid pixels (height <= SATSWEEP_INVALID / 2) do not vote and keep
 * their value. tests/reference_median.py holds the same rule in numpy (the tests compare the two).
 *
 * The height is found by bisection over the heights' order-preserving 32-bit keys (key_of): the
 * smallest key whose running weight (the weights of the taps at or below it, summed in the
 * window's raster order) reaches half the total is a tap's key. No data-dependent indexing, so
 * that 8 pixels run in float8 lanes (PoCL: 6 times the speed of a quickselect per pixel at a
 * radius of 4 px, on a 1441 x 1581 map 1.92 -> 0.29 s).
 *
 * weighted_median8: work size global = (ceil(w / 8), h), each rounded up to a multiple of the
 *   local size; local = (l, 1) with l <= 16 (median.MEDIAN_LOCAL: a work-item's private windows
 *   take 64 bytes a tap, which PoCL holds for the whole work-group on one thread's stack).
 *   Work-item (g, y) writes out[y w + x] for x in [8 g, 8 g + 8) within the map: in float8 lanes
 *   where the 8 windows lie inside the map's columns, else pixel by pixel (median_at, the same
 *   sums in the same order).
 * Compile-time constant: MEDIAN_RADIUS (window radius, px, 1 .. MEDIAN_MAX_RADIUS).
 */
#include "common.h"

#ifndef MEDIAN_RADIUS
#error "MEDIAN_RADIUS must be defined"
#endif
#define MEDIAN_MAX_RADIUS 6
#if MEDIAN_RADIUS < 1 || MEDIAN_RADIUS > MEDIAN_MAX_RADIUS
#error "MEDIAN_RADIUS must lie in 1 .. MEDIAN_MAX_RADIUS"
#endif
#define MEDIAN_TAPS ((2 * MEDIAN_RADIUS + 1) * (2 * MEDIAN_RADIUS + 1))
/* The key of a tap that does not vote (above every finite height's). */
#define MEDIAN_NO_KEY 0xffffffffu

/* A float's order-preserving key: the bits with the sign set for positive numbers, every bit
 * flipped for negative ones (finite values; -0 sorts just under +0). */
inline uint key_of(const float f)
{
    const uint u = as_uint(f);
    return u >= 0x80000000u ? ~u : (u | 0x80000000u);
}

inline float float_of(const uint k)
{
    return as_float(k >= 0x80000000u ? (k & 0x7fffffffu) : ~k);
}

inline uint8 key_of8(const float8 f)
{
    const uint8 u = as_uint8(f);
    return select(u | (uint8)0x80000000u, ~u, u >= (uint8)0x80000000u);
}

inline float8 float_of8(const uint8 k)
{
    return as_float8(select(~k, k & (uint8)0x7fffffffu, k >= (uint8)0x80000000u));
}

/* The weighted median at pixel (x, y), one pixel (the path of windows that leave the map). */
inline float median_at(__global const float *height, __global const float *guide,
                       const int w, const int h, const int x, const int y,
                       const float inv_two_sigma2, const float inv_two_radius2)
{
    const int p = IDX2(x, y, w);
    const float hp = height[p];
    if (hp <= SATSWEEP_INVALID * 0.5f)
        return hp;
    const float gp = guide[p];
    uint kv[MEDIAN_TAPS];
    float wv[MEDIAN_TAPS];
    float total = 0.0f;
    uint kmin = MEDIAN_NO_KEY, kmax = 0u;
    int t = 0;
    for (int dy = -MEDIAN_RADIUS; dy <= MEDIAN_RADIUS; ++dy) {
        const int yy = y + dy;
        for (int dx = -MEDIAN_RADIUS; dx <= MEDIAN_RADIUS; ++dx, ++t) {
            const int xx = x + dx;
            kv[t] = MEDIAN_NO_KEY;
            wv[t] = 0.0f;
            if (yy < 0 || yy >= h || xx < 0 || xx >= w)
                continue;
            const int q = IDX2(xx, yy, w);
            const float hq = height[q];
            if (hq <= SATSWEEP_INVALID * 0.5f)
                continue;
            const float dg = guide[q] - gp;
            wv[t] = exp(-dg * dg * inv_two_sigma2 - (float)(dx * dx + dy * dy) * inv_two_radius2);
            kv[t] = key_of(hq);
            total += wv[t];
            kmin = min(kmin, kv[t]);
            kmax = max(kmax, kv[t]);
        }
    }
    /* lo: a key whose running weight is under half the total; hi: one where it reaches it. */
    const float middle = 0.5f * total;
    uint lo = kmin - 1u, hi = kmax;
    while (hi - lo > 1u) {
        const uint mid = lo + ((hi - lo) >> 1);
        float s = 0.0f;
        for (int i = 0; i < MEDIAN_TAPS; ++i)
            s += kv[i] <= mid ? wv[i] : 0.0f;
        if (s >= middle)
            hi = mid;
        else
            lo = mid;
    }
    return float_of(hi);
}

__kernel void weighted_median8(__global const float *height, __global const float *guide,
                               __global float *out, const int w, const int h,
                               const float inv_two_sigma2, const float inv_two_radius2)
{
    const int x0 = get_global_id(0) * 8;
    const int y = get_global_id(1);
    if (x0 >= w || y >= h)
        return;
    if (x0 < MEDIAN_RADIUS || x0 + 8 + MEDIAN_RADIUS > w) {
        for (int i = 0; i < 8 && x0 + i < w; ++i)
            out[IDX2(x0 + i, y, w)] = median_at(height, guide, w, h, x0 + i, y, inv_two_sigma2,
                                                inv_two_radius2);
        return;
    }
    const float8 hp = vload8(0, height + IDX2(x0, y, w));
    const float8 gp = vload8(0, guide + IDX2(x0, y, w));
    const int8 centre = hp > (float8)(SATSWEEP_INVALID * 0.5f);
    uint8 kv[MEDIAN_TAPS];
    float8 wv[MEDIAN_TAPS];
    float8 total = (float8)0.0f;
    uint8 kmin = (uint8)MEDIAN_NO_KEY, kmax = (uint8)0u;
    int t = 0;
    for (int dy = -MEDIAN_RADIUS; dy <= MEDIAN_RADIUS; ++dy) {
        const int yy = y + dy;
        for (int dx = -MEDIAN_RADIUS; dx <= MEDIAN_RADIUS; ++dx, ++t) {
            kv[t] = (uint8)MEDIAN_NO_KEY;
            wv[t] = (float8)0.0f;
            if (yy < 0 || yy >= h)
                continue;
            const float8 hq = vload8(0, height + IDX2(x0 + dx, yy, w));
            const float8 dg = vload8(0, guide + IDX2(x0 + dx, yy, w)) - gp;
            const uint8 ok = as_uint8(hq > (float8)(SATSWEEP_INVALID * 0.5f));
            wv[t] = select((float8)0.0f,
                           exp(-dg * dg * inv_two_sigma2
                               - (float)(dx * dx + dy * dy) * inv_two_radius2), ok);
            kv[t] = select((uint8)MEDIAN_NO_KEY, key_of8(hq), ok);
            total += wv[t];
            kmin = min(kmin, kv[t]);
            kmax = max(kmax, select((uint8)0u, kv[t], ok));
        }
    }
    /* median_at's bisection in each lane; a lane without a valid centre stops at once. */
    const float8 middle = 0.5f * total;
    uint8 lo = select((uint8)0u, kmin - (uint8)1u, as_uint8(centre));
    uint8 hi = select((uint8)1u, kmax, as_uint8(centre));
    int8 active = as_int8(hi - lo > (uint8)1u);
    while (any(active)) {
        const uint8 mid = lo + ((hi - lo) >> (uint8)1u);
        float8 s = (float8)0.0f;
        for (int i = 0; i < MEDIAN_TAPS; ++i)
            s += select((float8)0.0f, wv[i], as_int8(kv[i] <= mid));
        const int8 reach = s >= middle;
        hi = select(hi, mid, as_uint8(active & reach));
        lo = select(lo, mid, as_uint8(active & ~reach));
        active = as_int8(hi - lo > (uint8)1u);
    }
    vstore8(select(hp, float_of8(hi), centre), 0, out + IDX2(x0, y, w));
}
