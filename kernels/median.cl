/* median.cl: an edge-aware weighted median of a height map, the reference image as guide.
 *
 * out(p) = the weighted median of height(q) over the valid pixels q of the (2 MEDIAN_RADIUS + 1)^2
 * window around p (those inside the map), each weighing
 *     exp(-(guide(q) - guide(p))^2 inv_two_sigma2 - |q - p|^2 inv_two_radius2),
 * i.e. the lowest of the window's heights, in increasing order, at which the running sum of the
 * weights reaches half their total (found by a weighted selection, not a sort). A pixel of
 * another surface (another grey level) weighs little, so the median keeps the steps where the
 * image has its edges and removes the height noise of flat areas. Invalid pixels (height <=
 * SATSWEEP_INVALID / 2) do not vote and keep their value.
 * tests/reference_median.py holds the same rule in numpy (the tests compare the two).
 *
 * Work size: global = (w, h), each rounded up to any multiple of the local size; local = any.
 * Work-item (x, y) writes out[y w + x] (none outside the w x h map).
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

__kernel void weighted_median(__global const float *height, __global const float *guide,
                              __global float *out, const int w, const int h,
                              const float inv_two_sigma2, const float inv_two_radius2)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= w || y >= h)
        return;
    const int p = IDX2(x, y, w);
    const float hp = height[p];
    if (hp <= SATSWEEP_INVALID * 0.5f) {
        out[p] = hp;
        return;
    }
    const float gp = guide[p];
    float hv[MEDIAN_TAPS];
    float wv[MEDIAN_TAPS];
    int n = 0;
    float total = 0.0f;
    for (int dy = -MEDIAN_RADIUS; dy <= MEDIAN_RADIUS; ++dy) {
        const int yy = y + dy;
        if (yy < 0 || yy >= h)
            continue;
        for (int dx = -MEDIAN_RADIUS; dx <= MEDIAN_RADIUS; ++dx) {
            const int xx = x + dx;
            if (xx < 0 || xx >= w)
                continue;
            const int q = IDX2(xx, yy, w);
            const float hq = height[q];
            if (hq <= SATSWEEP_INVALID * 0.5f)
                continue;
            const float dg = guide[q] - gp;
            const float wq = exp(-dg * dg * inv_two_sigma2
                                 - (float)(dx * dx + dy * dy) * inv_two_radius2);
            hv[n] = hq;
            wv[n] = wq;
            ++n;
            total += wq;
        }
    }
    /* Weighted selection (a quickselect with three-way partitions): hv[lo .. hi] holds the
     * heights not yet placed, `below` the weight of those known to lie under them; the answer
     * is among hv[lo .. hi] while below < middle <= below + their weight. No full sort: about 3n
     * comparisons instead of the n^2 / 4 of an insertion sort. */
    const float middle = 0.5f * total;
    float below = 0.0f;
    int lo = 0, hi = n - 1;
    float result = hv[n - 1];
    while (1) {
        if (lo >= hi) {
            result = hv[lo < n ? lo : n - 1];
            break;
        }
        const float a = hv[lo], b = hv[(lo + hi) / 2], c = hv[hi];
        const float pivot = fmax(fmin(a, b), fmin(fmax(a, b), c)); /* median of three */
        int lt = lo, i = lo, gt = hi;
        float w_less = 0.0f, w_equal = 0.0f;
        while (i <= gt) {
            const float hq = hv[i], wi = wv[i];
            if (hq < pivot) {
                hv[i] = hv[lt];
                wv[i] = wv[lt];
                hv[lt] = hq;
                wv[lt] = wi;
                w_less += wi;
                ++lt;
                ++i;
            } else if (hq > pivot) {
                hv[i] = hv[gt];
                wv[i] = wv[gt];
                hv[gt] = hq;
                wv[gt] = wi;
                --gt;
            } else {
                w_equal += wi;
                ++i;
            }
        }
        if (below + w_less >= middle && lt > lo) {
            hi = lt - 1;
        } else if (below + w_less + w_equal >= middle || gt >= hi) {
            result = pivot; /* (or float rounding left nothing above: the highest) */
            break;
        } else {
            below += w_less + w_equal;
            lo = gt + 1;
        }
    }
    out[p] = result;
}
