/* guided_filter.cl: box filters and the guided filter (He, Sun and Tang) of cost slices.
 *
 * Every kernel works on a stack of planes of a tile, row-major [plane][th][tw] (plane stride
 * tw * th). Box windows are (2 BOX_R + 1)^2 clipped to the tile, and means divide by the number of
 * pixels of the clipped window (not by the full window area). A tile with margin at least 2 BOX_R
 * therefore gives, at its kept interior, the same values as the whole image.
 *
 * Sums are running (sliding-window) sums restarted at the start of each chunk of BOX_CHUNK rows
 * (columns): each work-item sums its first window directly, then adds the entering and subtracts
 * the leaving sample, so the cost per pixel is (2 BOX_R + 1) / BOX_CHUNK + 2 operations, O(1) in
 * the radius when BOX_CHUNK >= 2 BOX_R + 1, and float32 drift is bounded by BOX_CHUNK steps.
 *
 * Work sizes (ncy = ceil(th / BOX_CHUNK), ncx = ceil(tw / BOX_CHUNK), each rounded up to any
 * multiple of any local size; local = any):
 *   box_cols_sum, gf_cols_p : global (ceil(tw / GF_COLS_VEC), ncy, planes); work-item (g, c, p)
 *                             handles rows [c BOX_CHUNK, (c + 1) BOX_CHUNK) of the columns
 *                             [g GF_COLS_VEC, (g + 1) GF_COLS_VEC) (clipped to tw) of plane p;
 *   box_rows_mean, gf_rows_ab, gf_rows_q : global (ncx, th, planes); work-item (c, y, p) handles
 *                             columns [c BOX_CHUNK, (c + 1) BOX_CHUNK) of row y of plane p;
 *   gf_rows_q_pixel_major    : global (ncx, ih); work-item (c, y) handles columns
 *                             [c BOX_CHUNK, (c + 1) BOX_CHUNK) of interior row y, all planes;
 *   gf_guide_fields          : global (tw, th); work-item (x, y) handles one pixel.
 *
 * Guided filter of a cost slice p with guide I (the reference tile), He et al. (2013), eq. 7-8:
 *   a = (mean(I p) - mean(I) mean(p)) / (var(I) + GF_EPS),  b = mean(p) - a mean(I),
 *   q = mean(a) I + mean(b).
 * Host sequence: gf_guide_fields -> box_cols_sum -> box_rows_mean gives the guide means (once per
 * tile); per batch of nb planes: gf_cols_p (p -> [colsum p | colsum I p], 2 nb planes),
 * gf_rows_ab (-> [a | b]), box_cols_sum on the 2 nb planes, gf_rows_q (-> q, nb planes), or,
 * when the filtered interior goes straight to SGM's pixel-major volume, gf_rows_q_pixel_major.
 * Compile-time constants: BOX_R (radius, pixels), BOX_CHUNK, GF_EPS (float, guide units
 * squared); shared with the host (common.h): GF_COLS_VEC (columns per work-item of the column
 * kernels: 8).
 */
#include "common.h"

#if !defined(BOX_R) || !defined(BOX_CHUNK)
#error "BOX_R and BOX_CHUNK must be defined"
#endif

/* Number of samples of the window [i - BOX_R, i + BOX_R] inside [0, n). */
inline int window_count(const int i, const int n)
{
    return min(i + BOX_R, n - 1) - max(i - BOX_R, 0) + 1;
}

/* Column kernels: each work-item runs the sliding sums of GF_COLS_VEC adjacent columns at once, so
 * that every step down the rows reads and writes GF_COLS_VEC contiguous floats (vload/vstore): a
 * CPU executing the work-items of a group one after the other would otherwise stride through
 * memory one float per row. The last group of a row may be narrower (scalar tail). */
#if GF_COLS_VEC != 8
#error "GF_COLS_VEC must be 8 (the column kernels use float8)"
#endif

__kernel void box_cols_sum(__global const float *in, __global float *out, const int tw,
                           const int th)
{
    const int x0 = get_global_id(0) * GF_COLS_VEC, c = get_global_id(1);
    const size_t base = (size_t)get_global_id(2) * tw * th;
    const int y0 = c * BOX_CHUNK;
    if (x0 >= tw || y0 >= th) return;
    const int y1 = min(y0 + BOX_CHUNK, th);
    __global const float *col = in + base + x0;
    __global float *dst = out + base + x0;
    if (x0 + GF_COLS_VEC <= tw) {
        float8 s = (float8)(0.0f);
        for (int j = max(y0 - BOX_R, 0); j <= min(y0 + BOX_R, th - 1); ++j)
            s += vload8(0, col + (size_t)j * tw);
        for (int y = y0; y < y1; ++y) {
            vstore8(s, 0, dst + (size_t)y * tw);
            if (y + BOX_R + 1 < th) s += vload8(0, col + (size_t)(y + BOX_R + 1) * tw);
            if (y - BOX_R >= 0) s -= vload8(0, col + (size_t)(y - BOX_R) * tw);
        }
        return;
    }
    for (int x = 0; x < tw - x0; ++x) {
        float s = 0.0f;
        for (int j = max(y0 - BOX_R, 0); j <= min(y0 + BOX_R, th - 1); ++j) s += col[(size_t)j * tw + x];
        for (int y = y0; y < y1; ++y) {
            dst[(size_t)y * tw + x] = s;
            if (y + BOX_R + 1 < th) s += col[(size_t)(y + BOX_R + 1) * tw + x];
            if (y - BOX_R >= 0) s -= col[(size_t)(y - BOX_R) * tw + x];
        }
    }
}

/* Row kernels with small radii (BOX_R <= ROW_DIRECT_MAX_R) sum each window directly, 8 adjacent
 * columns at once (the sum of the 2 BOX_R + 1 shifted float8 rows, in increasing column order):
 * PoCL leaves the sliding one-column form scalar, and for these radii the direct vector sums
 * take fewer operations per pixel. Groups of 8 whose window would leave the tile, or that cross
 * the end of the work-item's chunk, sum the same columns in the same order one at a time. Larger
 * radii keep the sliding sums (O(1) per pixel in the radius). */
#define ROW_DIRECT_MAX_R 7
#define ROW_VEC 8

/* Whether the group of ROW_VEC columns starting at x (chunk end x1) takes the vector path. */
inline int row_group_inside(const int x, const int x1, const int tw)
{
    return x - BOX_R >= 0 && x + ROW_VEC + BOX_R <= tw && x + ROW_VEC <= x1;
}

/* Window sums of columns x .. x + 7 (all windows inside the row). */
inline float8 row_sum8(__global const float *r, const int x)
{
    float8 s = (float8)(0.0f);
    for (int d = -BOX_R; d <= BOX_R; ++d) s += vload8(0, r + x + d);
    return s;
}

/* The window sum of column x, clipped to the row (the same order as row_sum8). */
inline float row_sum1(__global const float *r, const int x, const int tw)
{
    float s = 0.0f;
    for (int i = max(x - BOX_R, 0); i <= min(x + BOX_R, tw - 1); ++i) s += r[i];
    return s;
}

__kernel void box_rows_mean(__global const float *in, __global float *out, const int tw,
                            const int th)
{
    const int c = get_global_id(0), y = get_global_id(1);
    const int x0 = c * BOX_CHUNK;
    if (y >= th || x0 >= tw) return;
    const int x1 = min(x0 + BOX_CHUNK, tw);
    const size_t base = (size_t)get_global_id(2) * tw * th + (size_t)y * tw;
    __global const float *row = in + base;
    const int ny = window_count(y, th);
#if BOX_R <= ROW_DIRECT_MAX_R
    for (int x = x0; x < x1; x += ROW_VEC) {
        if (row_group_inside(x, x1, tw)) {
            vstore8(row_sum8(row, x) / (float)(ny * (2 * BOX_R + 1)), 0, out + base + x);
            continue;
        }
        for (int xx = x; xx < min(x + ROW_VEC, x1); ++xx)
            out[base + xx] = row_sum1(row, xx, tw) / (float)(ny * window_count(xx, tw));
    }
#else
    float s = 0.0f;
    for (int i = max(x0 - BOX_R, 0); i <= min(x0 + BOX_R, tw - 1); ++i) s += row[i];
    for (int x = x0; x < x1; ++x) {
        out[base + x] = s / (float)(ny * window_count(x, tw));
        if (x + BOX_R + 1 < tw) s += row[x + BOX_R + 1];
        if (x - BOX_R >= 0) s -= row[x - BOX_R];
    }
#endif
}

#ifdef GF_EPS
/* guide_i[y][x] = I, guide_mean[0][y][x] = I and guide_mean[1][y][x] = I^2 for the tile whose
 * origin is (tx0, ty0) in the reference image ref (ref_w wide); box_cols_sum and box_rows_mean
 * then turn guide_mean into [mean I | mean I^2], which gf_rows_ab reads. */
__kernel void gf_guide_fields(__global const float *ref, const int ref_w, const int tx0,
                              const int ty0, const int tw, const int th,
                              __global float *guide_i, __global float *guide_mean)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= tw || y >= th) return;
    const float v = ref[(size_t)(ty0 + y) * ref_w + tx0 + x];
    guide_i[IDX2(x, y, tw)] = v;
    guide_mean[IDX2(x, y, tw)] = v;
    guide_mean[(size_t)tw * th + IDX2(x, y, tw)] = v * v;
}

/* sums[b] = column sums of p[b], sums[nb + b] = column sums of I p[b] (GF_COLS_VEC columns per
 * work-item, as box_cols_sum). */
__kernel void gf_cols_p(__global const float *p, __global const float *guide_i,
                        __global float *sums, const int tw, const int th, const int nb)
{
    const int x0 = get_global_id(0) * GF_COLS_VEC, c = get_global_id(1), b = get_global_id(2);
    const int y0 = c * BOX_CHUNK;
    if (x0 >= tw || y0 >= th) return;
    const int y1 = min(y0 + BOX_CHUNK, th);
    const size_t plane = (size_t)tw * th;
    __global const float *col = p + b * plane + x0;
    __global const float *gcol = guide_i + x0;
    __global float *out_s = sums + b * plane + x0;
    __global float *out_si = sums + (nb + b) * plane + x0;
    if (x0 + GF_COLS_VEC <= tw) {
        float8 s = (float8)(0.0f), si = (float8)(0.0f);
        for (int j = max(y0 - BOX_R, 0); j <= min(y0 + BOX_R, th - 1); ++j) {
            const float8 v = vload8(0, col + (size_t)j * tw);
            s += v;
            si += vload8(0, gcol + (size_t)j * tw) * v;
        }
        for (int y = y0; y < y1; ++y) {
            vstore8(s, 0, out_s + (size_t)y * tw);
            vstore8(si, 0, out_si + (size_t)y * tw);
            if (y + BOX_R + 1 < th) {
                const size_t k = (size_t)(y + BOX_R + 1) * tw;
                const float8 v = vload8(0, col + k);
                s += v;
                si += vload8(0, gcol + k) * v;
            }
            if (y - BOX_R >= 0) {
                const size_t k = (size_t)(y - BOX_R) * tw;
                const float8 v = vload8(0, col + k);
                s -= v;
                si -= vload8(0, gcol + k) * v;
            }
        }
        return;
    }
    for (int x = 0; x < tw - x0; ++x) {
        float s = 0.0f, si = 0.0f;
        for (int j = max(y0 - BOX_R, 0); j <= min(y0 + BOX_R, th - 1); ++j) {
            const float v = col[(size_t)j * tw + x];
            s += v;
            si += gcol[(size_t)j * tw + x] * v;
        }
        for (int y = y0; y < y1; ++y) {
            out_s[(size_t)y * tw + x] = s;
            out_si[(size_t)y * tw + x] = si;
            if (y + BOX_R + 1 < th) {
                const size_t k = (size_t)(y + BOX_R + 1) * tw + x;
                s += col[k];
                si += gcol[k] * col[k];
            }
            if (y - BOX_R >= 0) {
                const size_t k = (size_t)(y - BOX_R) * tw + x;
                s -= col[k];
                si -= gcol[k] * col[k];
            }
        }
    }
}

/* Sliding sums over the row windows of two rows r0, r1 (tw samples each), shared by gf_rows_ab
 * and gf_rows_q: row_pair_window gives the sums of the window of column x0; row_pair_slide moves
 * them from the window of column x to that of x + 1. */
inline float2 row_pair_window(__global const float *r0, __global const float *r1, const int x0,
                              const int tw)
{
    float2 s = (float2)(0.0f, 0.0f);
    for (int i = max(x0 - BOX_R, 0); i <= min(x0 + BOX_R, tw - 1); ++i) {
        s.x += r0[i];
        s.y += r1[i];
    }
    return s;
}

inline float2 row_pair_slide(float2 s, __global const float *r0, __global const float *r1,
                             const int x, const int tw)
{
    if (x + BOX_R + 1 < tw) {
        s.x += r0[x + BOX_R + 1];
        s.y += r1[x + BOX_R + 1];
    }
    if (x - BOX_R >= 0) {
        s.x -= r0[x - BOX_R];
        s.y -= r1[x - BOX_R];
    }
    return s;
}

/* From column sums [p | I p] and the guide means [mean I | mean I^2]: ab[b] = a, ab[nb + b] = b. */
__kernel void gf_rows_ab(__global const float *sums, __global const float *guide_mean,
                         __global float *ab, const int tw, const int th, const int nb)
{
    const int c = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    const int x0 = c * BOX_CHUNK;
    if (y >= th || x0 >= tw) return;
    const int x1 = min(x0 + BOX_CHUNK, tw);
    const size_t plane = (size_t)tw * th;
    const size_t row = (size_t)y * tw;
    __global const float *rp = sums + b * plane + row;
    __global const float *rip = sums + (nb + b) * plane + row;
    __global const float *rmi = guide_mean + row, *rmii = guide_mean + plane + row;
    __global float *ra = ab + b * plane + row, *rb = ab + (nb + b) * plane + row;
    const int ny = window_count(y, th);
#if BOX_R <= ROW_DIRECT_MAX_R
    for (int x = x0; x < x1; x += ROW_VEC) {
        if (row_group_inside(x, x1, tw)) {
            const float n = (float)(ny * (2 * BOX_R + 1));
            const float8 mp = row_sum8(rp, x) / n, mip = row_sum8(rip, x) / n;
            const float8 mi = vload8(0, rmi + x), mii = vload8(0, rmii + x);
            const float8 a = (mip - mi * mp) / (mii - mi * mi + GF_EPS);
            vstore8(a, 0, ra + x);
            vstore8(mp - a * mi, 0, rb + x);
            continue;
        }
        for (int xx = x; xx < min(x + ROW_VEC, x1); ++xx) {
            const float n = (float)(ny * window_count(xx, tw));
            const float mp = row_sum1(rp, xx, tw) / n, mip = row_sum1(rip, xx, tw) / n;
            const float mi = rmi[xx], mii = rmii[xx];
            const float a = (mip - mi * mp) / (mii - mi * mi + GF_EPS);
            ra[xx] = a;
            rb[xx] = mp - a * mi;
        }
    }
#else
    float2 s = row_pair_window(rp, rip, x0, tw);
    for (int x = x0; x < x1; ++x) {
        const float n = (float)(ny * window_count(x, tw));
        const float mp = s.x / n, mip = s.y / n;
        const float mi = rmi[x], mii = rmii[x];
        const float a = (mip - mi * mp) / (mii - mi * mi + GF_EPS);
        ra[x] = a;
        rb[x] = mp - a * mi;
        s = row_pair_slide(s, rp, rip, x, tw);
    }
#endif
}

/* q over the columns [x0, x1) of one row (chunk start x0, as gf_rows_q's work-items), from the
 * rows ra, rb of the column sums of a and b and the guide row ri: STORE8(x, q8) stores columns
 * x .. x + 7, STORE1(x, q) column x. A macro, so that gf_rows_q and gf_rows_q_pixel_major run
 * the same float32 operations on every column and store them differently. */
#if BOX_R <= ROW_DIRECT_MAX_R
#define GF_Q_ROW(ra, rb, ri, x0, x1, tw, ny, STORE8, STORE1)                                  \
    for (int x = (x0); x < (x1); x += ROW_VEC) {                                              \
        if (row_group_inside(x, (x1), (tw))) {                                                \
            const float n = (float)((ny) * (2 * BOX_R + 1));                                  \
            const float8 q8 = (row_sum8((ra), x) / n) * vload8(0, (ri) + x)                   \
                              + row_sum8((rb), x) / n;                                        \
            STORE8(x, q8);                                                                    \
            continue;                                                                         \
        }                                                                                     \
        for (int xx = x; xx < min(x + ROW_VEC, (x1)); ++xx) {                                 \
            const float n = (float)((ny) * window_count(xx, (tw)));                           \
            STORE1(xx, (row_sum1((ra), xx, (tw)) / n) * (ri)[xx] + row_sum1((rb), xx, (tw)) / n); \
        }                                                                                     \
    }
#else
#define GF_Q_ROW(ra, rb, ri, x0, x1, tw, ny, STORE8, STORE1)                                  \
    {                                                                                         \
        float2 s = row_pair_window((ra), (rb), (x0), (tw));                                   \
        for (int x = (x0); x < (x1); ++x) {                                                   \
            const float n = (float)((ny) * window_count(x, (tw)));                            \
            STORE1(x, (s.x / n) * (ri)[x] + s.y / n);                                         \
            s = row_pair_slide(s, (ra), (rb), x, (tw));                                       \
        }                                                                                     \
    }
#endif

/* From column sums [a | b]: q[b] = mean(a) I + mean(b). */
__kernel void gf_rows_q(__global const float *sums, __global const float *guide_i,
                        __global float *q, const int tw, const int th, const int nb)
{
    const int c = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    const int x0 = c * BOX_CHUNK;
    if (y >= th || x0 >= tw) return;
    const int x1 = min(x0 + BOX_CHUNK, tw);
    const size_t plane = (size_t)tw * th;
    const size_t row = (size_t)y * tw;
    __global const float *ra = sums + b * plane + row;
    __global const float *rb = sums + (nb + b) * plane + row;
    __global const float *ri = guide_i + row;
    __global float *rq = q + b * plane + row;
    const int ny = window_count(y, th);
#define Q_STORE8(x, v) vstore8((v), 0, rq + (x))
#define Q_STORE1(x, v) (rq[x] = (v))
    GF_Q_ROW(ra, rb, ri, x0, x1, tw, ny, Q_STORE8, Q_STORE1)
#undef Q_STORE8
#undef Q_STORE1
}

/* gf_rows_q_pixel_major: gf_rows_q's q of the tile interior (origin (mx, my) in the tile, size
 * iw x ih) written straight into the PIXEL-MAJOR volume of the whole reference that SGM
 * aggregates (the layout of sweep.cl's volume_pixel_major):
 *   volume[out_offset + ((oy + y) out_w + ox + x) n_planes + plane0 + b] = q[b][my + y][mx + x],
 * with the same float32 operations per column as gf_rows_q (the same chunks of the tile's rows),
 * so the same values, without the plane-major q and the copy. Each work-item writes all nb labels
 * of its pixels, so each pixel's run of nb floats is written whole.
 * Work size: global = (ncx, ih) (ncx = ceil(tw / BOX_CHUNK)), each rounded up to any multiple;
 *   local = any. Work-item (c, y) computes columns [c BOX_CHUNK, (c + 1) BOX_CHUNK) (clipped to
 *   tw) of tile row my + y for planes 0 .. nb - 1 and writes those inside [mx, mx + iw). */
__kernel void gf_rows_q_pixel_major(__global const float *sums, __global const float *guide_i,
                                    const int tw, const int th, const int nb, const int mx,
                                    const int my, const int iw, const int ih,
                                    __global float *volume, const int out_w, const int ox,
                                    const int oy, const int n_planes, const int plane0,
                                    const ulong out_offset)
{
    const int c = get_global_id(0), yi = get_global_id(1);
    const int x0 = c * BOX_CHUNK;
    if (yi >= ih || x0 >= tw) return;
    const int x1 = min(x0 + BOX_CHUNK, tw);
    if (x1 <= mx || x0 >= mx + iw) return;
    const int y = my + yi;
    const size_t plane = (size_t)tw * th;
    const size_t row = (size_t)y * tw;
    __global const float *ri = guide_i + row;
    /* o[(x - mx) n_planes] is label plane0 + b of tile column x of this row, x in [mx, mx + iw) */
    __global float *o = volume + out_offset + ((size_t)(oy + yi) * out_w + ox) * n_planes
                        + plane0;
    const int ny = window_count(y, th);
    for (int b = 0; b < nb; ++b, ++o) {
        __global const float *ra = sums + b * plane + row;
        __global const float *rb = sums + (nb + b) * plane + row;
#define PM_STORE1(x, v) if ((x) >= mx && (x) < mx + iw) o[(size_t)((x) - mx) * n_planes] = (v)
#define PM_STORE8(x, v)                                                                       \
        {                                                                                     \
            const float8 qv = (v);                                                            \
            PM_STORE1((x), qv.s0); PM_STORE1((x) + 1, qv.s1); PM_STORE1((x) + 2, qv.s2);      \
            PM_STORE1((x) + 3, qv.s3); PM_STORE1((x) + 4, qv.s4); PM_STORE1((x) + 5, qv.s5);  \
            PM_STORE1((x) + 6, qv.s6); PM_STORE1((x) + 7, qv.s7);                             \
        }
        GF_Q_ROW(ra, rb, ri, x0, x1, tw, ny, PM_STORE8, PM_STORE1)
#undef PM_STORE8
#undef PM_STORE1
    }
}
#endif
