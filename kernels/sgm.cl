/* sgm.cl: semi-global matching (Hirschmueller 2008) over a plane-sweep cost volume.
 *
 * The sweep's volumes are plane-major, cost[d][H][W] for label (plane index) d, row y, column x,
 * d in [0, SGM_NL). SGM reads all labels of one pixel per step, so the volume is first turned
 * pixel-major, [H][W][SGM_NL] (the labels of a pixel contiguous: one cache line serves 16 labels on
 * a CPU, and consecutive work-items read consecutive labels on a GPU), aggregated in that layout,
 * and the sum turned back plane-major for the sweep's winner-take-all (wta.cl). The label is the
 * plane index of the sweep; neighbouring labels are neighbouring heights.
 *
 * sgm_to_pixel_major: out[(y W + x) NL + d] = cost[d H W + y W + x], with entries at or below
 *   SATSWEEP_INVALID / 2 (no valid source for that plane) replaced by missing_cost: a pixel with
 *   every plane missing thus has a constant cost and is filled by the smoothness terms alone.
 *   Work size: global = (H W), local = any; work-item i handles pixel i (all labels).
 * sgm_to_plane_major: out[d H W + i] = in[i NL + d]. Work size as above.
 *
 * sgm_path: aggregates the (pixel-major) costs along every scanline of ONE direction
 *   r = (dx, dy), dx, dy in {-1, 0, 1}, not both 0, and adds the path cost Lr into agg (pixel-major;
 *   written instead of added when accumulate == 0, for the first direction). The recurrence, for a
 *   pixel p whose predecessor p - r is inside the image:
 *
 *     Lr(p, d) = C(p, d) + (min(Lr(p-r, d), Lr(p-r, d-1) + P1, Lr(p-r, d+1) + P1, m + P2') - m)
 *     m        = min_k Lr(p-r, k)
 *     P2'      = max(P1, P2 / (1 + |I(p) - I(p-r)| * inv_sigma))
 *
 *   and Lr(p, d) = C(p, d) at the first pixel of a scanline. P2' is the large-jump penalty
 *   adapted to the reference (guide) image I: it falls where the guide has an edge, where height
 *   discontinuities are expected; inv_sigma = 1 / sigma with sigma in guide intensity units
 *   (inv_sigma = 0: no adaptation, P2' = max(P1, P2)). The terms in d-1, d+1 are absent at the
 *   label range ends. Subtracting m keeps Lr bounded (Lr <= max C + P2').
 *
 * Label bands (coarse-to-fine search): with banded != 0, label d of pixel p stands for the plane
 *   base[p] + d (base: one int per pixel, pixel-major like the volume), so neighbouring pixels may
 *   cover different windows of SGM_NL planes. The recurrence then compares the same PLANES: with
 *   delta = base[p] - base[p-r], Lr(p-r, d + delta) takes the place of Lr(p-r, d) (and d + delta
 *   +- 1 that of d +- 1), labels outside p-r's window counting as +inf; m is still the minimum over
 *   p-r's window. banded == 0 is the plain recurrence (delta = 0; base is not read).
 *
 * Scanlines of a direction: dy == 0: one per row (H lines) starting at column 0 (dx > 0) or
 *   W-1; dx == 0: one per column (W lines) starting at row 0 (dy > 0) or H-1; diagonal: W + H - 1
 *   lines, line i < W starting at (i, y0) and line i >= W at (x0, row j = i - W + 1 counted from
 *   y0), with x0 = 0 (dx > 0) or W-1 and y0 = 0 (dy > 0) or H-1. Each line steps by (dx, dy)
 *   until it leaves the image. The lines of one direction cover every pixel exactly once, so one
 *   launch per direction adds into agg without races; launches run in order on the queue.
 *
 * Work size of sgm_path: global = n_lines * SGM_WG, local = SGM_WG (required): one work-group per
 *   scanline. Its SGM_WG work-items share the labels (work-item l handles d = l, l + SGM_WG, ...)
 *   and find min_k Lr by a tree reduction in local memory (the argument lines must be 1).
 *   SGM_WG = 1 (best on CPUs) is instead one work-item per `lines` scanlines (the argument,
 *   1..SGM_LINES), global = ceil(n_lines / lines), local = 1, which
 *   steps through the labels SGM_VEC at a time in vector types; a GPU wants SGM_WG = 32 or 64 so
 *   that a warp shares one scanline.
 *
 * Compile-time constants: SGM_NL number of labels (1..SGM_MAX_LABELS), SGM_WG work-items per
 *   scanline (a power of two, default 1), SGM_LINES the most scanlines per work-item when
 *   SGM_WG == 1 (default 1; sizes the private arrays).
 *
 * Floating point: contraction into fused multiply-adds is disabled, so that each device rounds
 *   the documented sequence of float32 operations (the numpy reference in tests/reference_sgm.py
 *   computes the same sequence); the division in P2' may differ by a few ulp on GPUs.
 */
#pragma OPENCL FP_CONTRACT OFF
#include "common.h"

#ifndef SGM_NL
#error "SGM_NL must be defined"
#endif
#ifndef SGM_WG
#define SGM_WG 1
#endif
#ifndef SGM_LINES
#define SGM_LINES 1
#endif
#if SGM_LINES < 1 || (SGM_WG > 1 && SGM_LINES != 1)
#error "SGM_LINES must be >= 1, and 1 with SGM_WG > 1"
#endif
#define SGM_MAX_LABELS 1024
#if SGM_NL < 1 || SGM_NL > SGM_MAX_LABELS
#error "SGM_NL out of range"
#endif
#if (SGM_WG & (SGM_WG - 1)) != 0
#error "SGM_WG must be a power of two"
#endif

/* +inf guard entries on each side of a step's labels (one-work-item path) */
#define SGM_GUARD (SGM_NL + 2)
/* labels per work-item */
#define SGM_LPT ((SGM_NL + SGM_WG - 1) / SGM_WG)
/* cost values at or below this are the sweep's invalid marker */
#define SGM_INVALID_BELOW (0.5f * SATSWEEP_INVALID)

/* First pixel of scanline `line` of direction (dx, dy), as documented above. */
inline void sgm_line_start(const int line, const int w, const int h, const int dx, const int dy,
                           int *x, int *y)
{
    const int x0 = dx > 0 ? 0 : w - 1;
    const int y0 = dy > 0 ? 0 : h - 1;
    if (dy == 0) {
        *x = x0;
        *y = line;
    } else if (dx == 0 || line < w) {
        *x = line;
        *y = y0;
    } else {
        const int j = line - w + 1;
        *x = x0;
        *y = dy > 0 ? j : h - 1 - j;
    }
}

#if SGM_WG == 1
/* One work-item per `lines` adjacent scanlines (CPUs): the labels of a step are processed
 * SGM_VEC at a time with OpenCL vector types, so that the CPU's SIMD lanes share them (PoCL
 * vectorises across work-items, and a scanline has only one). Lr(p - r, .) lives in a private
 * array with +inf guards at d = -1 and d = SGM_NL, so that the terms in d - 1 and d + 1 need no
 * test at the range ends (fmin(m, inf + P1) = m: the same values as the per-label code below),
 * and the current and previous steps swap arrays instead of copying. Before the first pixel of a
 * scanline the previous step is all zeros with minimum 0, so the recurrence gives exactly Lr = C
 * there (every term is >= 0 and the zero term wins: C + (0 - 0)).
 * The work-item's `lines` scanlines (1 <= lines <= SGM_LINES; lines g lines .. g lines + lines - 1)
 * advance one step each in turn: scanlines of a vertical or diagonal direction that start side by side
 * stay side by side, so each round of steps reads and writes neighbouring pixels, whose labels
 * are contiguous in the pixel-major volumes (one scanline at a time jumps a whole image row per
 * step, which the CPU's caches and prefetchers serve poorly). Each scanline's values are those
 * of the same recurrence computed alone. */
#define SGM_VEC 8
#define SGM_BUF (SGM_NL + 2 * SGM_GUARD)

/* One step of scanline k's recurrence at pixel idx: cur = Lr(p, .), agg (+)= cur; returns
 * min_d Lr(p, d). prev points at Lr(p - r, .) shifted by the band delta (see above). */
inline float sgm_step(__global const float *c, __global float *a, const float *pv, float *cur,
                      const float prev_min, const float jump, const float p1,
                      const int accumulate)
{
    const float8 jump8 = (float8)(jump), p18 = (float8)(p1), min8 = (float8)(prev_min);
    float8 vmin = (float8)(MAXFLOAT);
    float cmin = MAXFLOAT;
    int d = 0;
    for (; d + SGM_VEC <= SGM_NL; d += SGM_VEC) {
        float8 m = fmin(vload8(0, pv + d), jump8);
        m = fmin(m, vload8(0, pv + d - 1) + p18);
        m = fmin(m, vload8(0, pv + d + 1) + p18);
        const float8 v = vload8(0, c + d) + (m - min8);
        vstore8(v, 0, cur + d);
        vstore8(accumulate ? vload8(0, a + d) + v : v, 0, a + d);
        vmin = fmin(vmin, v);
    }
    for (; d < SGM_NL; ++d) {
        float m = fmin(pv[d], jump);
        m = fmin(m, pv[d - 1] + p1);
        m = fmin(m, pv[d + 1] + p1);
        const float v = c[d] + (m - prev_min);
        cur[d] = v;
        a[d] = accumulate ? a[d] + v : v;
        cmin = fmin(cmin, v);
    }
    const float4 m4 = fmin(vmin.lo, vmin.hi);
    const float2 m2 = fmin(m4.lo, m4.hi);
    return fmin(cmin, fmin(m2.x, m2.y));
}

__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void sgm_path(__global const float *cost, __global const float *guide, __global float *agg,
              const int w, const int h, const int dx, const int dy,
              const float p1, const float p2, const float inv_sigma, const int accumulate,
              __global const int *base, const int banded, const int lines)
{
    /* Each step's labels sit between +inf guards of SGM_GUARD entries, so that a band shift
     * delta (clamped to +-(SGM_NL + 1), beyond which the windows do not meet) reads only guards
     * outside the window. */
    float buf[SGM_LINES][2][SGM_BUF];
    float *prev[SGM_LINES], *cur[SGM_LINES];
    int xs[SGM_LINES], ys[SGM_LINES], prev_base[SGM_LINES];
    float prev_min[SGM_LINES], prev_guide[SGM_LINES];
    const int n_lines = dy == 0 ? h : (dx == 0 ? w : w + h - 1);
    for (int k = 0; k < lines; ++k) {
        for (int i = 0; i < SGM_GUARD; ++i) {
            buf[k][0][i] = buf[k][1][i] = INFINITY;
            buf[k][0][SGM_GUARD + SGM_NL + i] = buf[k][1][SGM_GUARD + SGM_NL + i] = INFINITY;
        }
        prev[k] = buf[k][0] + SGM_GUARD;
        cur[k] = buf[k][1] + SGM_GUARD;
        for (int d = 0; d < SGM_NL; ++d) prev[k][d] = 0.0f;
        const int line = get_global_id(0) * lines + k;
        if (line < n_lines) {
            sgm_line_start(line, w, h, dx, dy, &xs[k], &ys[k]);
        } else {
            xs[k] = -1;  /* no such line: outside from the start */
            ys[k] = -1;
        }
        prev_min[k] = 0.0f;
        prev_guide[k] = 0.0f;
        prev_base[k] = (banded && xs[k] >= 0) ? base[(size_t)ys[k] * (size_t)w + (size_t)xs[k]] : 0;
    }
    int running = 1;
    while (running) {
        running = 0;
        for (int k = 0; k < lines; ++k) {
            const int x = xs[k], y = ys[k];
            if (!(x >= 0 && x < w && y >= 0 && y < h)) continue;
            running = 1;
            const size_t idx = (size_t)y * (size_t)w + (size_t)x;
            const float gv = guide[idx];
            const float jump = prev_min[k]
                               + fmax(p1, p2 / (1.0f + fabs(gv - prev_guide[k]) * inv_sigma));
            const int cur_base = banded ? base[idx] : 0;
            const float *pv = prev[k] + clamp(cur_base - prev_base[k], -(SGM_NL + 1), SGM_NL + 1);
            prev_min[k] = sgm_step(cost + idx * SGM_NL, agg + idx * SGM_NL, pv, cur[k],
                                   prev_min[k], jump, p1, accumulate);
            float *t = prev[k];
            prev[k] = cur[k];
            cur[k] = t;
            prev_guide[k] = gv;
            prev_base[k] = cur_base;
            xs[k] = x + dx;
            ys[k] = y + dy;
        }
    }
}
#else
__kernel __attribute__((reqd_work_group_size(SGM_WG, 1, 1)))
void sgm_path(__global const float *cost, __global const float *guide, __global float *agg,
              const int w, const int h, const int dx, const int dy,
              const float p1, const float p2, const float inv_sigma, const int accumulate,
              __global const int *base, const int banded, const int lines)
{
    __local float prev[SGM_NL];   /* Lr(p - r, .) */
    __local float red[SGM_WG];    /* reduction scratch for min_k */
    float cur[SGM_LPT];

    const int line = get_group_id(0);
    const int lid = get_local_id(0);
    int x, y;
    sgm_line_start(line, w, h, dx, dy, &x, &y);
    float prev_min = 0.0f;
    float prev_guide = 0.0f;
    int first = 1;
    int prev_base = 0;

    /* x, y are the same for every work-item of the group, so the loop and its barriers are
     * uniform across the group. */
    while (x >= 0 && x < w && y >= 0 && y < h) {
        const size_t idx = (size_t)y * (size_t)w + (size_t)x;
        const float gv = guide[idx];
        const float p2a = first ? p2
                                : fmax(p1, p2 / (1.0f + fabs(gv - prev_guide) * inv_sigma));
        const float jump = prev_min + p2a;
        const int cur_base = banded ? base[idx] : 0;
        const int delta = first ? 0 : cur_base - prev_base;
        float cmin = MAXFLOAT;
        for (int k = 0; k < SGM_LPT; ++k) {
            const int d = lid + k * SGM_WG;
            if (d < SGM_NL) {
                const size_t o = idx * SGM_NL + d;
                const float c = cost[o];
                float v = c;
                if (!first) {
                    const int j = d + delta;  /* the same plane in p - r's window */
                    float m = jump;
                    if (j >= 0 && j < SGM_NL) m = fmin(m, prev[j]);
                    if (j - 1 >= 0 && j - 1 < SGM_NL) m = fmin(m, prev[j - 1] + p1);
                    if (j + 1 >= 0 && j + 1 < SGM_NL) m = fmin(m, prev[j + 1] + p1);
                    v = c + (m - prev_min);
                }
                cur[k] = v;
                agg[o] = accumulate ? agg[o] + v : v;
                cmin = fmin(cmin, v);
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);   /* everyone has read prev */
        for (int k = 0; k < SGM_LPT; ++k) {
            const int d = lid + k * SGM_WG;
            if (d < SGM_NL) prev[d] = cur[k];
        }
        red[lid] = cmin;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int s = SGM_WG / 2; s > 0; s >>= 1) {
            if (lid < s) red[lid] = fmin(red[lid], red[lid + s]);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        prev_min = red[0];
        barrier(CLK_LOCAL_MEM_FENCE);   /* everyone has read red[0] before it is overwritten */
        prev_guide = gv;
        prev_base = cur_base;
        first = 0;
        x += dx;
        y += dy;
    }
}
#endif

__kernel void sgm_to_pixel_major(__global const float *cost, __global float *out, const int n_pix,
                                 const float missing_cost)
{
    const int i = get_global_id(0);
    if (i >= n_pix) return;
    for (int d = 0; d < SGM_NL; ++d) {
        const float c = cost[(size_t)d * n_pix + i];
        out[(size_t)i * SGM_NL + d] = c > SGM_INVALID_BELOW ? c : missing_cost;
    }
}

__kernel void sgm_to_plane_major(__global const float *in, __global float *out, const int n_pix)
{
    const int i = get_global_id(0);
    if (i >= n_pix) return;
    for (int d = 0; d < SGM_NL; ++d) out[(size_t)d * n_pix + i] = in[(size_t)i * SGM_NL + d];
}
