/* median.cl: an edge-aware weighted median of a height map, the reference image as guide.
 *
 * out(p) = the weighted median of height(q) over the valid pixels q of the (2 MEDIAN_RADIUS + 1)^2
 * window around p (those inside the map), each weighing
 *     exp(-(guide(q) - guide(p))^2 inv_two_sigma2 - |q - p|^2 inv_two_radius2),
 * i.e. the lowest of the window's heights, in increasing order, at which the running sum of the
 * weights reaches half their total. A pixel of another surface (another grey level) weighs little,
 * so the median keeps the steps where the image has its edges and removes the height noise of
 * flat areas. Invalid pixels (height <= SATSWEEP_INVALID / 2) do not vote and keep their value.
 * satsweep.dense.median holds the same rule in numpy (its tests compare the two).
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
            /* insertion into the sorted prefix hv[0 .. n - 1] (heights increasing) */
            int k = n;
            while (k > 0 && hv[k - 1] > hq) {
                hv[k] = hv[k - 1];
                wv[k] = wv[k - 1];
                --k;
            }
            hv[k] = hq;
            wv[k] = wq;
            ++n;
            total += wq;
        }
    }
    const float middle = 0.5f * total;
    float run = 0.0f;
    float result = hv[n - 1];
    for (int k = 0; k < n; ++k) {
        run += wv[k];
        if (run >= middle) {
            result = hv[k];
            break;
        }
    }
    out[p] = result;
}
