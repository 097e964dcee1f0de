/* sgm.cl: semi-global matching (Hirschmueller 2008) over a plane-sweep cost volume.
 *
 * A plane-major volume, volume[d][H][W] for label (plane index) d, row y, column x, d in
 * [0, n_labels), is first turned pixel-major, [H][W][n_labels] (the labels of a pixel contiguous:
 * SGM reads all labels of one pixel per step; one cache line serves 16 labels on a CPU, and
 * consecutive work-items read consecutive labels on a GPU); the sweep can also leave its volume
 * in that layout on the device (sweep.cl's volume_pixel_major). It is aggregated in that layout,
 * and wta.cl's wta_pixel_major reads the sums so; sgm_to_plane_major turns them plane-major for a
 * caller that wants them. The label is the plane index of the sweep; neighbouring labels are
 * neighbouring heights.
 *
 * Label counts: n_labels (a kernel argument, 1 <= n_labels <= SGM_NL) is the labels of every
 *   pixel of a plain volume and the stride of its pixel-major layout; SGM_NL (a -D constant) is
 *   the most labels a program serves, which sizes its private, local and scratch arrays. The host
 *   rounds SGM_NL up (satsweep.dense.sgm.sgm_label_capacity), so that one program serves many
 *   label counts instead of a build per count; the sums are those of a program built for exactly
 *   n_labels, bit for bit.
 *
 * sgm_to_pixel_major: cost[(y W + x) NL + d] = volume[d H W + y W + x] (NL = n_labels), with
 *   entries at or below SATSWEEP_INVALID / 2 (no valid source for that plane) replaced by
 *   missing_cost: a pixel with every plane missing thus has a constant cost and is filled by the
 *   smoothness terms alone.
 *   Work size: global = (H W), rounded up to any multiple of the local size; local = any;
 *   work-item i handles pixel i (all labels), those past H W nothing.
 * sgm_to_plane_major: sums[d H W + i] = agg[i NL + d] (NL = n_labels). Work size as above.
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
 * Label bands (coarse-to-fine search): with banded != 0, pixel p has count[p] labels
 *   (1 <= count[p] <= SGM_NL; base and count: one int per pixel, pixel-major like the volume),
 *   label d < count[p] standing for the plane base[p] + d, so neighbouring pixels may cover
 *   different windows of planes, of different lengths. The recurrence then compares the same
 *   PLANES: with delta = base[p] - base[p-r], Lr(p-r, d + delta) takes the place of Lr(p-r, d)
 *   (and d + delta +- 1 that of d +- 1), labels outside p-r's window [0, count[p-r]) counting as
 *   +inf; m is the minimum over p-r's window. The labels of pixel p then start at
 *   offset[p] (one ulong per pixel, in floats) in both cost and agg, so that a volume may hold
 *   just the count[p] labels of each pixel (a ragged volume; offset[p] = p NL is the regular
 *   layout, whose labels past count[p] are neither read nor written), and a pixel costs time and
 *   memory in proportion to its count. banded == 0 is the plain recurrence (delta = 0, every
 *   pixel n_labels labels from p n_labels; base, count and offset are not read, n_labels is
 *   not used).
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
 * Compile-time constants: SGM_NL most labels (1..SGM_MAX_LABELS), SGM_WG work-items per
 *   scanline (a power of two, default 1), SGM_LINES the most scanlines per work-item when
 *   SGM_WG == 1 (default 1; sizes the private arrays); shared with the host (common.h):
 *   SGM_MAX_LABELS, SGM_SCAN_GUARD (sgm_scan's +inf guards, below), SATSWEEP_INVALID.
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

/* The recurrence of one step over labels 0 .. n_ - 1, shared by sgm_step and sgm_scan_step (whose
 * arrays live in different address spaces): cur[d] = Lr(p, d) from pv = Lr(p - r, .), then
 * ON_VEC (after each SGM_VEC labels d.., value v) or ON_ONE (after each single label d, value
 * v), and `result` = min_d Lr(p, d). */
#define SGM_STEP_BODY(c, pv, cur, n_, prev_min, jump, p1, ON_VEC, ON_ONE, result)               \
    do {                                                                                       \
        const float8 jump8_ = (float8)(jump), p18_ = (float8)(p1), min8_ = (float8)(prev_min); \
        float8 vmin_ = (float8)(MAXFLOAT);                                                     \
        float cmin_ = MAXFLOAT;                                                                \
        int d = 0;                                                                             \
        for (; d + SGM_VEC <= (n_); d += SGM_VEC) {                                            \
            float8 m_ = fmin(vload8(0, (pv) + d), jump8_);                                     \
            m_ = fmin(m_, vload8(0, (pv) + d - 1) + p18_);                                     \
            m_ = fmin(m_, vload8(0, (pv) + d + 1) + p18_);                                     \
            const float8 v = vload8(0, (c) + d) + (m_ - min8_);                                \
            vstore8(v, 0, (cur) + d);                                                          \
            ON_VEC;                                                                            \
            vmin_ = fmin(vmin_, v);                                                            \
        }                                                                                      \
        for (; d < (n_); ++d) {                                                                \
            float m_ = fmin((pv)[d], (jump));                                                  \
            m_ = fmin(m_, (pv)[d - 1] + (p1));                                                 \
            m_ = fmin(m_, (pv)[d + 1] + (p1));                                                 \
            const float v = (c)[d] + (m_ - (prev_min));                                        \
            (cur)[d] = v;                                                                      \
            ON_ONE;                                                                            \
            cmin_ = fmin(cmin_, v);                                                            \
        }                                                                                      \
        const float4 m4_ = fmin(vmin_.lo, vmin_.hi);                                           \
        const float2 m2_ = fmin(m4_.lo, m4_.hi);                                               \
        (result) = fmin(cmin_, fmin(m2_.x, m2_.y));                                            \
    } while (0)

/* One step of scanline k's recurrence at pixel idx over its n labels: cur = Lr(p, .),
 * agg (+)= cur; returns min_d Lr(p, d). prev points at Lr(p - r, .) shifted by the band delta
 * (see above). */
inline float sgm_step(__global const float *c, __global float *a, const float *pv, float *cur,
                      const int n, const float prev_min, const float jump, const float p1,
                      const int accumulate)
{
    float result;
    SGM_STEP_BODY(c, pv, cur, n, prev_min, jump, p1,
                  vstore8(accumulate ? vload8(0, a + d) + v : v, 0, a + d),
                  a[d] = accumulate ? a[d] + v : v, result);
    return result;
}

__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void sgm_path(__global const float *cost, __global const float *guide, __global float *agg,
              const int w, const int h, const int dx, const int dy,
              const float p1, const float p2, const float inv_sigma, const int accumulate,
              __global const int *base, __global const int *count,
              __global const ulong *offset, const int banded, const int n_labels,
              const int lines)
{
    /* Each step's labels sit between +inf guards of SGM_GUARD entries, so that a band shift
     * delta (clamped to +-(SGM_NL + 1), beyond which the windows do not meet) reads only guards
     * outside the window. A step of n < SGM_NL labels leaves entries n .. SGM_NL - 1 of its
     * array stale: the next step sets those it reads to +inf first (prev_n: the count of the
     * step in prev). */
    float buf[SGM_LINES][2][SGM_BUF];
    float *prev[SGM_LINES], *cur[SGM_LINES];
    int xs[SGM_LINES], ys[SGM_LINES], prev_base[SGM_LINES], prev_n[SGM_LINES];
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
        prev_n[k] = SGM_NL;  /* the zero start: every entry valid */
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
            const int n = banded ? count[idx] : n_labels;
            const int delta = clamp(cur_base - prev_base[k], -(SGM_NL + 1), SGM_NL + 1);
            /* this step reads prev up to entry n - 1 + delta + 1 */
            for (int j = prev_n[k]; j < min(n + delta + 1, SGM_NL); ++j) prev[k][j] = INFINITY;
            const size_t at = banded ? offset[idx] : idx * (size_t)n_labels;
            prev_min[k] = sgm_step(cost + at, agg + at, prev[k] + delta, cur[k], n, prev_min[k],
                                   jump, p1, accumulate);
            prev_n[k] = n;
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

/* sgm_scan (CPUs): the paths of 4 directions in ONE raster scan of the image, as in
 * Hirschmueller's and OpenCV's SGBM, instead of one launch per direction: each pixel's costs are
 * read once and its aggregate written once per scan, so the volumes travel through memory twice
 * for 8 directions instead of 8 times (sgm_path reads the costs and reads and writes agg once
 * per direction).
 *
 *   Work-item 0 (the forward scan) visits rows top to bottom and each row left to right and
 *   computes the directions (1, 0), (0, 1), (1, 1), (-1, 1): their predecessors (x - 1, y),
 *   (x, y - 1), (x - 1, y - 1), (x + 1, y - 1) are visited before (x, y). Work-item 1 (the
 *   backward scan) visits the image in reverse order and computes (-1, 0), (0, -1), (-1, -1),
 *   (1, -1). With paths == 4 only the horizontal and vertical directions are computed (the first
 *   four of satsweep.mrf.SGM_DIRECTIONS), with paths == 8 all of them. A scan's sum at a pixel
 *   is F = ((Lr(1,0) + Lr(0,1)) + Lr(1,1)) + Lr(-1,1) (B likewise, backward directions), each
 *   Lr the recurrence documented above, bit for bit the values of sgm_path, with label bands and
 *   counts when banded != 0 (base, count and offset as for sgm_path; a pixel's labels past its
 *   count are neither read nor written).
 *   agg = F + B: sgm_path's sum up to the order of the additions.
 *   The scans share agg without a third volume, in two launches (phase 0, then phase 1) that
 *   meet at row h / 2: in phase 0 the forward scan stores F in rows [0, h / 2) and the backward
 *   scan B in rows [h / 2, h); in phase 1 each goes on through the other's rows and adds its sum
 *   to what is there (the launches run in order on the queue, so those rows are complete).
 *   scratch: SGM_SCAN_SCRATCH(w, n_labels) floats per work-item, kept from phase 0 to phase 1: the steps of
 *   the 3 directions that come from the row before, for two rows (row yi in slot yi % 2,
 *   2 x 3 x w steps), two steps of the horizontal direction, and the minima of the rows'
 *   steps (2 x 3 x w); every step between +inf guards of SGM_SCAN_GUARD entries, which phase 0
 *   writes first.
 *
 * Work size of sgm_scan: global = 2, local = 1 (required): the two scans run side by side, one
 *   per core. A scan visits the image in order, so it does not use more cores; GPUs use
 *   sgm_path with a work-group per scanline.
 */
/* floats per step in the scratch (its labels and guards), and per scan, for n labels: sized by
 * the volume's labels rather than SGM_NL, so a program of a larger capacity walks the same
 * memory */
#define SGM_SCAN_STEP(n) ((size_t)(n) + 2 * SGM_SCAN_GUARD)
#define SGM_SCAN_SCRATCH(w, n) ((size_t)(6 * (w) + 2) * SGM_SCAN_STEP(n) + (size_t)6 * (w))

/* cur = Lr(p, .) over n labels of one direction from pv = Lr(p - r, .) (its entries d - 1 and
 * d + 1 +inf where they lie outside its window), as sgm_step without the aggregate; returns
 * min_d Lr(p, d). */
inline float sgm_scan_step(__global const float *c, __global const float *pv, __global float *cur,
                           const int n, const float prev_min, const float jump, const float p1)
{
    float result;
    SGM_STEP_BODY(c, pv, cur, n, prev_min, jump, p1, (void)0, (void)0, result);
    return result;
}

/* Lr(p, .) = C(p, .) at the first pixel of a scanline (what sgm_path's zero start gives). */
inline float sgm_scan_first(__global const float *c, __global float *cur, const int n)
{
    float cmin = MAXFLOAT;
    for (int d = 0; d < n; ++d) {
        cur[d] = c[d];
        cmin = fmin(cmin, c[d]);
    }
    return cmin;
}

/* cur[d] = Lr(p, d) of a banded step, its predecessor's label j = d + delta read only inside the
 * predecessor's n_prev labels (+inf outside); returns it. */
inline float sgm_band_one(__global const float *c, __global const float *pv, __global float *cur,
                          const int d, const int delta, const int n_prev, const float prev_min,
                          const float jump, const float p1)
{
    const int j = d + delta;
    float m = jump;
    if (j >= 0 && j < n_prev) m = fmin(m, pv[j]);
    if (j >= 1 && j - 1 < n_prev) m = fmin(m, pv[j - 1] + p1);
    if (j + 1 >= 0 && j + 1 < n_prev) m = fmin(m, pv[j + 1] + p1);
    const float v = c[d] + (m - prev_min);
    cur[d] = v;
    return v;
}

/* sgm_scan_step over n labels from a predecessor step pv of n_prev labels whose label j stands
 * for this pixel's label j - delta (label bands and counts): the labels [a, b) whose three
 * predecessor entries all lie inside pv run as sgm_scan_step (no guard entries needed), the
 * others one by one with tests. The same values as the guarded step. */
inline float sgm_band_step(__global const float *c, __global const float *pv, __global float *cur,
                           const int n, const int n_prev, const int delta, const float prev_min,
                           const float jump, const float p1)
{
    const int a = clamp(1 - delta, 0, n);
    const int b = max(a, min(n, n_prev - 1 - delta));
    float cmin = b > a ? sgm_scan_step(c + a, pv + delta + a, cur + a, b - a, prev_min, jump, p1)
                       : MAXFLOAT;
    for (int d = 0; d < a; ++d)
        cmin = fmin(cmin, sgm_band_one(c, pv, cur, d, delta, n_prev, prev_min, jump, p1));
    for (int d = b; d < n; ++d)
        cmin = fmin(cmin, sgm_band_one(c, pv, cur, d, delta, n_prev, prev_min, jump, p1));
    return cmin;
}

/* One direction at a pixel of n labels (guide value gv): from the predecessor's step pv (guide
 * value gp, minimum pmin, n_prev labels, band offset delta) when it is inside the image, else
 * the first step. Every step keeps +inf just past its labels (entry n; entries -SGM_SCAN_GUARD
 * .. -1 are +inf from phase 0 on), so that a step whose reads, entries delta - 1 .. n + delta of
 * pv, lie within -SGM_SCAN_GUARD .. n_prev (every pixel of a plain volume, and those inside a
 * block of one window) runs the guarded step; the others test their reads (sgm_band_step). */
inline float sgm_scan_dir(__global const float *c, __global const float *pv, __global float *cur,
                          const int inside, const float pmin, const float gv, const float gp,
                          const float p1, const float p2, const float inv_sigma, const int n,
                          const int n_prev, const int delta)
{
    float result;
    if (!inside) {
        result = sgm_scan_first(c, cur, n);
    } else {
        const float jump = pmin + fmax(p1, p2 / (1.0f + fabs(gv - gp) * inv_sigma));
        result = (delta >= 1 - SGM_SCAN_GUARD && n + delta <= n_prev)
                     ? sgm_scan_step(c, pv + delta, cur, n, pmin, jump, p1)
                     : sgm_band_step(c, pv, cur, n, n_prev, delta, pmin, jump, p1);
    }
    if (n < SGM_NL) cur[n] = INFINITY;
    return result;
}

/* the window (first plane, label count) of pixel i in sgm_scan */
#define B(i) (banded ? base[i] : 0)
#define N(i) (banded ? count[i] : n_labels)
__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void sgm_scan(__global const float *cost, __global const float *guide, __global float *agg,
              __global float *scratch, const int w, const int h, const float p1, const float p2,
              const float inv_sigma, const int paths, const int phase,
              __global const int *base, __global const int *count,
              __global const ulong *offset, const int banded, const int n_labels)
{
    const int back = get_global_id(0);
    if (back > 1) return;
    const int s = back ? -1 : 1;              /* step of x and y along the scan */
    const int diag = paths == 8;
    const int own = back ? h - h / 2 : h / 2; /* rows the scan stores in phase 0 */
    const size_t stride = SGM_SCAN_STEP(n_labels);
    __global float *sc = scratch + (size_t)back * SGM_SCAN_SCRATCH(w, n_labels);
    __global float *rows = sc;                                      /* [slot][k][x] steps */
    __global float *hor = sc + (size_t)6 * w * stride;             /* two horizontal steps */
    __global float *mins = hor + 2 * stride;                        /* [slot][k][x] minima */
    if (phase == 0) {
        for (size_t i = 0; i < (size_t)(6 * w + 2); ++i) {
            __global float *step = sc + i * stride;
            for (int g = 0; g < SGM_SCAN_GUARD; ++g) {
                step[g] = INFINITY;
                step[SGM_SCAN_GUARD + n_labels + g] = INFINITY;
            }
        }
    }
    const int add = phase != 0;
    const int yi0 = add ? own : 0, yi1 = add ? h : own;
    for (int yi = yi0; yi < yi1; ++yi) {
        const int y = back ? h - 1 - yi : yi;
        const int cs = yi & 1, ps = 1 - cs;   /* slots of this row and of the row before */
        __global float *prow = rows + (size_t)ps * 3 * w * stride + SGM_SCAN_GUARD;
        __global float *crow = rows + (size_t)cs * 3 * w * stride + SGM_SCAN_GUARD;
        __global const float *pmins = mins + (size_t)ps * 3 * w;
        __global float *cmins = mins + (size_t)cs * 3 * w;
        int hs = 0, hbase = 0, hn = n_labels;
        float hmin = 0.0f, hguide = 0.0f;
        for (int xi = 0; xi < w; ++xi) {
            const int x = back ? w - 1 - xi : xi;
            const size_t idx = (size_t)y * (size_t)w + (size_t)x;
            const size_t at = banded ? offset[idx] : idx * (size_t)n_labels;
            __global const float *c = cost + at;
            const float gv = guide[idx];
            const int up = yi > 0;
            const size_t iup = up ? (size_t)(y - s) * (size_t)w : 0;   /* row y - s */
            /* this pixel's window (plain: 0, n_labels); B(i), N(i): predecessor i's */
            const int pb = B(idx), n = N(idx);
            /* horizontal (s, 0): predecessor (x - s, y) */
            __global float *hp = hor + (size_t)hs * stride + SGM_SCAN_GUARD;
            __global float *hc = hor + (size_t)(1 - hs) * stride + SGM_SCAN_GUARD;
            hmin = sgm_scan_dir(c, hp, hc, xi > 0, hmin, gv, hguide, p1, p2, inv_sigma, n, hn,
                                pb - hbase);
            hguide = gv;
            hs = 1 - hs;
            hbase = pb;
            hn = n;
            /* vertical (0, s): predecessor (x, y - s) */
            __global float *v0 = crow + (size_t)x * stride;
            cmins[x] = sgm_scan_dir(c, prow + (size_t)x * stride, v0, up,
                                    up ? pmins[x] : 0.0f, gv, up ? guide[iup + x] : 0.0f,
                                    p1, p2, inv_sigma, n, up ? N(iup + x) : n_labels,
                                    up ? pb - B(iup + x) : 0);
            __global float *a = agg + at;
            if (diag) {
                /* (s, s): predecessor (x - s, y - s); (-s, s): predecessor (x + s, y - s) */
                const int in1 = up && xi > 0, in2 = up && xi < w - 1;
                const int xa = in1 ? x - s : x, xb = in2 ? x + s : x;
                __global float *v1 = crow + ((size_t)w + (size_t)x) * stride;
                __global float *v2 = crow + ((size_t)2 * w + (size_t)x) * stride;
                cmins[w + x] = sgm_scan_dir(
                    c, prow + ((size_t)w + (size_t)xa) * stride, v1, in1,
                    in1 ? pmins[w + xa] : 0.0f, gv, in1 ? guide[iup + xa] : 0.0f, p1, p2,
                    inv_sigma, n, in1 ? N(iup + xa) : n_labels, in1 ? pb - B(iup + xa) : 0);
                cmins[2 * w + x] = sgm_scan_dir(
                    c, prow + ((size_t)2 * w + (size_t)xb) * stride, v2, in2,
                    in2 ? pmins[2 * w + xb] : 0.0f, gv, in2 ? guide[iup + xb] : 0.0f, p1, p2,
                    inv_sigma, n, in2 ? N(iup + xb) : n_labels, in2 ? pb - B(iup + xb) : 0);
                int d = 0;
                for (; d + SGM_VEC <= n; d += SGM_VEC) {
                    const float8 f = ((vload8(0, hc + d) + vload8(0, v0 + d)) + vload8(0, v1 + d))
                                     + vload8(0, v2 + d);
                    vstore8(add ? vload8(0, a + d) + f : f, 0, a + d);
                }
                for (; d < n; ++d) {
                    const float f = ((hc[d] + v0[d]) + v1[d]) + v2[d];
                    a[d] = add ? a[d] + f : f;
                }
            } else {
                int d = 0;
                for (; d + SGM_VEC <= n; d += SGM_VEC) {
                    const float8 f = vload8(0, hc + d) + vload8(0, v0 + d);
                    vstore8(add ? vload8(0, a + d) + f : f, 0, a + d);
                }
                for (; d < n; ++d) {
                    const float f = hc[d] + v0[d];
                    a[d] = add ? a[d] + f : f;
                }
            }
        }
    }
}
#undef B
#undef N

#else
__kernel __attribute__((reqd_work_group_size(SGM_WG, 1, 1)))
void sgm_path(__global const float *cost, __global const float *guide, __global float *agg,
              const int w, const int h, const int dx, const int dy,
              const float p1, const float p2, const float inv_sigma, const int accumulate,
              __global const int *base, __global const int *count,
              __global const ulong *offset, const int banded, const int n_labels,
              const int lines)
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
    int prev_n = SGM_NL;

    /* x, y are the same for every work-item of the group, so the loop and its barriers are
     * uniform across the group. */
    while (x >= 0 && x < w && y >= 0 && y < h) {
        const size_t idx = (size_t)y * (size_t)w + (size_t)x;
        const float gv = guide[idx];
        const float p2a = first ? p2
                                : fmax(p1, p2 / (1.0f + fabs(gv - prev_guide) * inv_sigma));
        const float jump = prev_min + p2a;
        const int cur_base = banded ? base[idx] : 0;
        const int n = banded ? count[idx] : n_labels;
        const size_t at = banded ? offset[idx] : idx * (size_t)n_labels;
        const int delta = first ? 0 : cur_base - prev_base;
        float cmin = MAXFLOAT;
        for (int k = 0; k < SGM_LPT; ++k) {
            const int d = lid + k * SGM_WG;
            if (d < n) {
                const size_t o = at + d;
                const float c = cost[o];
                float v = c;
                if (!first) {
                    const int j = d + delta;  /* the same plane in p - r's window */
                    float m = jump;
                    if (j >= 0 && j < prev_n) m = fmin(m, prev[j]);
                    if (j - 1 >= 0 && j - 1 < prev_n) m = fmin(m, prev[j - 1] + p1);
                    if (j + 1 >= 0 && j + 1 < prev_n) m = fmin(m, prev[j + 1] + p1);
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
            if (d < n) prev[d] = cur[k];
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
        prev_n = n;
        first = 0;
        x += dx;
        y += dy;
    }
}
#endif

__kernel void sgm_to_pixel_major(__global const float *volume, __global float *cost,
                                 const int n_pix, const int n_labels, const float missing_cost)
{
    const int i = get_global_id(0);
    if (i >= n_pix) return;
    for (int d = 0; d < n_labels; ++d) {
        const float c = volume[(size_t)d * n_pix + i];
        cost[(size_t)i * n_labels + d] = c > SGM_INVALID_BELOW ? c : missing_cost;
    }
}

__kernel void sgm_to_plane_major(__global const float *agg, __global float *sums, const int n_pix,
                                 const int n_labels)
{
    const int i = get_global_id(0);
    if (i >= n_pix) return;
    for (int d = 0; d < n_labels; ++d)
        sums[(size_t)d * n_pix + i] = agg[(size_t)i * n_labels + d];
}
