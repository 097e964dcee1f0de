/* sweep.cl: plane-sweep matching cost of a reference tile against NSRC source views.
 *
 * For a batch of planes and every pixel of a reference tile, each source view is warped into the
 * reference view by the plane's homography, a census code is compared with the reference code
 * (Hamming distance, in bits; census_term), plus with AD_WEIGHT > 0 the truncated absolute
 * difference of the warped source intensity and the reference intensity at the pixel
 * (AD-census, Mei et al. 2011: AD_WEIGHT * min(|I_src - I_ref|, AD_TRUNC) / AD_TRUNC bits), plus
 * with GRAD_WEIGHT > 0 the truncated differences of the two images' gradients (central
 * differences, neighbours clamped to the reference image as the census does: GRAD_WEIGHT *
 * (min(|dx_src - dx_ref|, GRAD_TRUNC) + min(|dy_src - dy_ref|, GRAD_TRUNC)) / (2 GRAD_TRUNC)
 * bits), and the per-source costs are aggregated by the mean of the NBEST lowest costs among the
 * sources in which the pixel is valid (robust to occlusion in the others).
 *
 * Shared arguments:
 *   src_offset[s]  first element of source s in the concatenated source buffer (row-major),
 *                  which holds one float more after the last source (SWEEP_SRC_PAD, read by
 *                  sweep_warp's paired taps with weight 0);
 *   src_size[2s], src_size[2s+1]  width and height of source s;
 *   homography     [n_planes][NSRC][9] row-major 3x3 maps from TILE-LOCAL reference pixels
 *                  (x - tx0, y - ty0) to source pixels (pixel (0,0) = centre of the first pixel);
 *   ref_code       [th][tw] census codes of the reference tile;
 *   ref_img        the whole reference image (ref_w x ref_h), for the AD and gradient terms;
 *   tw, th         tile size; tx0, ty0 its origin in the reference image; ref_w, ref_h the
 *                  reference image size; plane0 the first plane of the batch;
 *   cost           [batch][th][tw] output, batch = global size 2.
 * A source is valid at a pixel when the pixel maps (positive homogeneous denominator) into
 * [0, w-1] x [0, h-1] of the source. The aggregated cost is the mean of the min(NBEST, n_valid)
 * lowest valid costs; with no valid source it is INVALID_COST = COST_MAX (the worst cost, so
 * that filtering never favours such planes; wta.cl marks the pixel invalid geometrically).
 *
 * Compile-time constants: CENSUS_RX, CENSUS_RY, NSRC (number of sources, 1..32), NBEST (1..NSRC),
 *   WG_X, WG_Y (work-group size of sweep_census_cost), AD_WEIGHT (float, census bits, default 0:
 *   census alone; not used by sweep_code_cost) and AD_TRUNC (float, intensity units, > 0),
 *   GRAD_WEIGHT (float, census bits, default 0; needs CENSUS_RX, CENSUS_RY >= 1) and GRAD_TRUNC;
 *   optionally CENSUS_RING_WEIGHT (float) with CENSUS_RING, CENSUS_RING_LO, CENSUS_RING_HI and
 *   CENSUS_SCALE (census_term below: the 3 x 3 ring's bits weighted, every cost kernel);
 *   optionally CENSUS_MASK_THRESHOLD (float) with CENSUS_MASK_MIN_BITS (float): ref_code as
 *   census.cl writes it with the same threshold, its mask in the high word (census_term_masked
 *   below; the warped-census kernels only, not sweep_code_cost);
 *   shared with the host (common.h): SWEEP_VEC (positions per work-item of sweep_warp and
 *   sweep_warped_cost: 8).
 */
/* No contraction into fused multiply-adds: the staged kernel, the split kernels' vector paths and
 * their one-position forms then round the same sequence of float32 operations on every device,
 * which their bit-for-bit equality relies on (no measurable cost on PoCL). */
#pragma OPENCL FP_CONTRACT OFF
#include "common.h"

#if !defined(CENSUS_RX) || !defined(CENSUS_RY) || !defined(NSRC) || !defined(NBEST)
#error "CENSUS_RX, CENSUS_RY, NSRC and NBEST must be defined"
#endif

/* Positions per work-item of the split kernels (sweep_warp, sweep_warped_cost): float8 there. */
#if SWEEP_VEC != 8
#error "SWEEP_VEC must be 8 (the split kernels use float8)"
#endif

#ifndef AD_TRUNC
#define AD_TRUNC 1.0f
#endif
#define INVALID_COST COST_MAX
/* Per-source marker of "pixel not seen by this source" (costs are >= 0). */
#define SWEEP_NOT_SEEN (-1.0f)

#ifndef GRAD_TRUNC
#define GRAD_TRUNC 1.0f
#endif
/* The gradient reads one neighbour on every side of the (warped) pixel: with a census radius of 0
 * in either direction the term is left out (the host refuses GRAD_WEIGHT > 0 then). */
#define GRAD_READY (CENSUS_RX >= 1 && CENSUS_RY >= 1)

/* The census term of the XOR of two codes: the differing bits, or with CENSUS_RING_WEIGHT (w)
 * CENSUS_SCALE * (bits + w * bits of the ring mask CENSUS_RING), CENSUS_SCALE = n / (n + w n_ring)
 * so that it spans 0..CENSUS_NBITS as the plain count does. census_term8 is the same for the
 * codes of 8 pixels held as low and high 32-bit words (sweep_warped_cost): the same integer sums
 * and float32 operations, so both give the same value bit for bit. */
#ifdef CENSUS_RING_WEIGHT
#if !defined(CENSUS_RING) || !defined(CENSUS_RING_LO) || !defined(CENSUS_RING_HI) \
    || !defined(CENSUS_SCALE)
#error "CENSUS_RING_WEIGHT needs CENSUS_RING, CENSUS_RING_LO, CENSUS_RING_HI and CENSUS_SCALE"
#endif
inline float census_term(const ulong x)
{
    return CENSUS_SCALE
           * ((float)popcount(x) + CENSUS_RING_WEIGHT * (float)popcount(x & CENSUS_RING));
}
inline float8 census_term8(const uint8 lo, const uint8 hi)
{
    return CENSUS_SCALE * (convert_float8(popcount(lo) + popcount(hi))
                           + CENSUS_RING_WEIGHT
                             * convert_float8(popcount(lo & (uint8)CENSUS_RING_LO)
                                              + popcount(hi & (uint8)CENSUS_RING_HI)));
}
#else
inline float census_term(const ulong x) { return (float)popcount(x); }
inline float8 census_term8(const uint8 lo, const uint8 hi)
{
    return convert_float8(popcount(lo) + popcount(hi));
}
#endif

/* The census term of a source's code against a reference code rc (x = code ^ rc): census_term of
 * the differing bits, or with CENSUS_MASK_THRESHOLD (common.h) of those the reference's mask (rc's
 * high word) keeps, scaled by n / wm, wm = census_mask_weight(rc) (the mask's own census_term,
 * the same for every source: the callers take it once per pixel), so that it still spans
 * 0..CENSUS_NBITS; a mask weighing under CENSUS_MASK_MIN_BITS (a pixel unlike most of its
 * window) keeps every bit. The comparisons across an edge of the reference image (a roof's
 * against the ground beside it) then do not pull a pixel to the other side's height.
 * census_term_masked8: the same for 8 pixels' low words x_lo, masks m and their weights wm
 * (sweep_warped_cost). Without a mask census_term_masked is census_term (wm unused). */
#ifdef CENSUS_MASK_THRESHOLD
#ifndef CENSUS_MASK_MIN_BITS
#error "CENSUS_MASK_THRESHOLD needs CENSUS_MASK_MIN_BITS"
#endif
inline float census_mask_weight(const ulong rc) { return census_term(rc >> 32); }
inline float census_term_masked(const ulong x, const ulong rc, const float wm)
{
    return wm >= CENSUS_MASK_MIN_BITS ? census_term(x & (rc >> 32)) * (float)CENSUS_NBITS / wm
                                      : census_term(x & 0xFFFFFFFFUL);
}
inline float8 census_term_masked8(const uint8 x_lo, const uint8 m, const float8 wm)
{
    return select(census_term8(x_lo, (uint8)0u),
                  census_term8(x_lo & m, (uint8)0u) * (float)CENSUS_NBITS / wm,
                  wm >= (float8)CENSUS_MASK_MIN_BITS);
}
#else
inline float census_mask_weight(const ulong rc) { return 0.0f; }
inline float census_term_masked(const ulong x, const ulong rc, const float wm)
{
    return census_term(x);
}
#endif

/* The AD term of a source intensity against the reference intensity (0 when AD_WEIGHT = 0). */
inline float ad_cost(const float src, const float ref)
{
    return AD_WEIGHT * fmin(fabs(src - ref), AD_TRUNC) / AD_TRUNC;
}

/* The gradient term: source central differences (dxs, dys) against the reference's at image
 * pixel (X, Y), whose neighbours are clamped to the reference image (0 when GRAD_WEIGHT = 0). */
inline float grad_cost(const float dxs, const float dys, __global const float *ref_img,
                       const int ref_w, const int ref_h, const int X, const int Y)
{
    if (GRAD_WEIGHT == 0.0f) return 0.0f;
    __global const float *row = ref_img + (size_t)Y * ref_w;
    const float dxr = row[clamp_index(X + 1, ref_w)] - row[clamp_index(X - 1, ref_w)];
    const float dyr = ref_img[(size_t)clamp_index(Y + 1, ref_h) * ref_w + X]
                      - ref_img[(size_t)clamp_index(Y - 1, ref_h) * ref_w + X];
    return GRAD_WEIGHT * (fmin(fabs(dxs - dxr), GRAD_TRUNC) + fmin(fabs(dys - dyr), GRAD_TRUNC))
           / (2.0f * GRAD_TRUNC);
}

/* Mean of the NBEST lowest costs among the valid sources (bit s of valid set). */
inline float aggregate_best(const float *cst, const uint valid)
{
    uint used = 0u;
    float acc = 0.0f;
    int taken = 0;
    for (int t = 0; t < NBEST; ++t) {
        int best = -1;
        float bc = 0.0f;
        for (int s = 0; s < NSRC; ++s) {
            const uint bit = 1u << s;
            if ((valid & bit) && !(used & bit) && (best < 0 || cst[s] < bc)) { best = s; bc = cst[s]; }
        }
        if (best < 0) break;
        used |= 1u << best;
        acc += bc;
        ++taken;
    }
    if (taken == 0) return INVALID_COST;
    return taken == 1 ? acc : acc / (float)taken;
}

/* Validity of the tile-local reference pixel (x, y) in source s (see above). */
inline int source_valid(__global const float *H, const float x, const float y,
                        const int sw, const int sh)
{
    float u, v;
    if (!apply_homography(H, x, y, &u, &v)) return 0;
    return u >= 0.0f && u <= (float)(sw - 1) && v >= 0.0f && v <= (float)(sh - 1);
}

#if defined(WG_X) && defined(WG_Y)
#define PATCH_W (WG_X + 2 * CENSUS_RX)
#define PATCH_H (WG_Y + 2 * CENSUS_RY)

/* sweep_census_cost: census of the WARPED SOURCE IMAGE versus the reference census.
 * The warped image at reference pixel q is the bilinear sample (clamped coordinates) of the source
 * at H q; its census uses the warped image at the neighbours of q, the neighbours being clamped
 * into the REFERENCE image (the border rule of census.cl applied in the reference view), so the
 * result at any tile pixel equals that of a whole-image computation. Where the denominator is not
 * positive the warped value is 0.
 * Work size: global = (ceil(tw / WG_X) * WG_X, ceil(th / WG_Y) * WG_Y, batch); local = (WG_X,
 *   WG_Y, 1) exactly. Each work-group stages the warped (WG_X + 2 CENSUS_RX) x (WG_Y + 2 CENSUS_RY)
 *   neighbourhood of its block in local memory once per source; each work-item then computes the
 *   census and Hamming cost of its pixel for plane plane0 + get_global_id(2) and writes the
 *   aggregated cost. Items outside the tile help staging and write nothing. */
__kernel __attribute__((reqd_work_group_size(WG_X, WG_Y, 1)))
void sweep_census_cost(__global const float *src_img, __global const long *src_offset,
                       __global const int *src_size, __global const float *homography,
                       __global const ulong *ref_code, __global const float *ref_img,
                       const int tw, const int th,
                       const int tx0, const int ty0, const int ref_w, const int ref_h,
                       const int plane0, __global float *cost)
{
    __local float patch[PATCH_W * PATCH_H];
    /* Per-item, per-source cost (>= 0), or SWEEP_NOT_SEEN. Kept in local memory rather than in
     * private variables across the barriers of the source loop: PoCL 3.1 mis-compiled private
     * state (a validity bit mask) carried across barriers inside this loop. */
    __local float item_cost[NSRC * WG_X * WG_Y];
    const int lx = get_local_id(0), ly = get_local_id(1);
    const int item = ly * WG_X + lx;
    const int bx = get_group_id(0) * WG_X, by = get_group_id(1) * WG_Y;
    const int plane = plane0 + get_global_id(2);
    for (int s = 0; s < NSRC; ++s) {
        __global const float *H = homography + (plane * NSRC + s) * 9;
        __global const float *img = src_img + src_offset[s];
        const int sw = src_size[2 * s], sh = src_size[2 * s + 1];
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int i = item; i < PATCH_W * PATCH_H; i += WG_X * WG_Y) {
            const int px = i % PATCH_W, py = i / PATCH_W;
            const int rx = clamp_index(tx0 + bx - CENSUS_RX + px, ref_w) - tx0;
            const int ry = clamp_index(ty0 + by - CENSUS_RY + py, ref_h) - ty0;
            float u, v;
            patch[i] = apply_homography(H, (float)rx, (float)ry, &u, &v)
                           ? sample_bilinear_clamped(img, sw, sh, u, v) : 0.0f;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int x = bx + lx, y = by + ly;
        float c_s = SWEEP_NOT_SEEN;
        if (x < tw && y < th && source_valid(H, (float)x, (float)y, sw, sh)) {
            const int base = (ly + CENSUS_RY) * PATCH_W + lx + CENSUS_RX;
            const float c = patch[base];
            ulong code = 0;
            for (int dy = -CENSUS_RY; dy <= CENSUS_RY; ++dy) {
                for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
                    if (dx == 0 && dy == 0) continue;
                    code = (code << 1) | (ulong)(patch[base + dy * PATCH_W + dx] < c);
                }
            }
            const ulong rc = ref_code[IDX2(x, y, tw)];
            c_s = census_term_masked(code ^ rc, rc, census_mask_weight(rc))
                  + ad_cost(c, ref_img[(size_t)(ty0 + y) * ref_w + tx0 + x]);
#if GRAD_READY
            c_s += grad_cost(patch[base + 1] - patch[base - 1],
                             patch[base + PATCH_W] - patch[base - PATCH_W], ref_img, ref_w,
                             ref_h, tx0 + x, ty0 + y);
#endif
        }
        item_cost[s * WG_X * WG_Y + item] = c_s;
    }
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= tw || y >= th) return;
    float cst[NSRC];
    uint valid = 0u;
    for (int s = 0; s < NSRC; ++s) {
        const float c_s = item_cost[s * WG_X * WG_Y + item];
        cst[s] = c_s;
        if (c_s >= 0.0f) valid |= 1u << s;
    }
    cost[(size_t)get_global_id(2) * tw * th + IDX2(x, y, tw)] = aggregate_best(cst, valid);
}
#endif

/* Split form of sweep_census_cost (the same costs, bit for bit), in two launches per chunk of
 * planes: sweep_warp writes the warped sources once, sweep_warped_cost reads them. It needs no
 * barriers and no clamping in its inner loop, which CPU OpenCL compilers vectorise far better
 * than the staged kernel (tools/bench_sweep.py measures both).
 *
 * sweep_warp: for planes plane0 .. plane0 + nb - 1 and every source s, the source warped onto
 *   the tile extended by the census radii: with pw = tw + 2 CENSUS_RX, ph = th + 2 CENSUS_RY,
 *   warped[((b NSRC + s) ph + py) pw + px] = the bilinear sample (clamped coordinates) of source
 *   s at H(plane0 + b, s) applied to the tile-local reference pixel
 *   (clamp(tx0 + px - CENSUS_RX, ref_w) - tx0, clamp(ty0 + py - CENSUS_RY, ref_h) - ty0), or 0
 *   where the homogeneous denominator is not positive: exactly what sweep_census_cost stages;
 *   and seen[same index] = 1 when that position maps (positive denominator) into
 *   [0, w-1] x [0, h-1] of the source (for a tile pixel, the validity rule above).
 *   Work size: global = (ceil(pw / SWEEP_VEC), ph, nb NSRC), each of the first two rounded up to
 *   any multiple; local = any. Work-item (g, py, b NSRC + s) writes positions
 *   [g SWEEP_VEC, (g + 1) SWEEP_VEC) (clipped to pw) of row py, if plane plane0 + b is in that
 *   group's window: warp_window[2 (py ceil(pw / SWEEP_VEC) + g) + {0, 1}] = [first, end) planes
 *   (counted like plane0; [0, planes) warps every plane; plane windows of a coarse-to-fine
 *   sweep skip the rest, whose positions keep what they held), and, with band_words > 0, in that
 *   group's band set warp_bands[group band_words + {0 .. band_words - 1}] (bit k: planes
 *   [k SWEEP_BAND_PLANES, (k + 1) SWEEP_BAND_PLANES), counted from band_base: plane
 *   band_base + plane0 + b; band_words = 0: the window alone, warp_bands not read).
 * sweep_warped_cost: the census of the warped sources (sweep_warp's output for the same planes,
 *   with its validity) against the reference codes, plus the AD and gradient terms, aggregated
 *   over the sources like sweep_census_cost, into cost[(slot0 + b) th tw + y tw + x].
 *   Work size: global = (ceil(tw / SWEEP_VEC), th, nb), the first two rounded up to any multiple;
 *   local = any. Work-item (g, y, b) writes pixels [g SWEEP_VEC, (g + 1) SWEEP_VEC) (clipped to
 *   tw) of row y for slot b, if plane plane0 + b (the plane of sweep_warp's slot b) is in that
 *   group's window cost_window[2 (y ceil(tw / SWEEP_VEC) + g) + {0, 1}] and band set
 *   cost_bands (as warp_window and warp_bands; the positions a computed group reads must have
 *   been warped for that plane), else the worst cost INVALID_COST there (a cost filter may read
 *   it).
 */
/* sweep_warp's per-position form: the sample and validity at warped-buffer index k of the
 * tile-local reference pixel (rx, ry) (the reference form of the vector path, and the path of the
 * last, narrower group of a row). */
inline void warp_position(__global const float *img, const int sw, const int sh,
                          __global const float *H, const int rx, const int ry, const size_t k,
                          __global float *warped, __global uchar *seen)
{
    float u, v;
    const int ok = apply_homography(H, (float)rx, (float)ry, &u, &v);
    warped[k] = ok ? sample_bilinear_clamped(img, sw, sh, u, v) : 0.0f;
    seen[k] = (uchar)(ok && u >= 0.0f && u <= (float)(sw - 1) && v >= 0.0f && v <= (float)(sh - 1));
}

/* Whether group g's band set (band_words 32-bit words per group; bit k: planes
 * [k SWEEP_BAND_PLANES, (k + 1) SWEEP_BAND_PLANES) of the whole sweep) holds plane p. */
inline int in_band(__global const uint *bands, const int g, const int band_words, const int p)
{
    const int k = p / SWEEP_BAND_PLANES;
    return (int)((bands[(size_t)g * band_words + (k >> 5)] >> (k & 31)) & 1u);
}

/* sweep_warp handles SWEEP_VEC (8) adjacent positions of a row per work-item in vector types
 * (the homography and the bilinear weights in float8; the taps are gathered lane by lane), with
 * the same float32 operations as warp_position, so the samples are the same values. */

/* The pixels at i and i + 1 of 8 lanes, two at a time: the bilinear sample's left and right taps
 * in 8 paired loads instead of 16 (PoCL: a fifth of sweep_warp's time). Where the right tap is
 * clamped onto the left, at a source's last column, its weight ax is 0 and the pixel after it
 * (the next row's first, or the buffer's pad, SWEEP_SRC_PAD; finite: the sweep refuses other
 * images) adds 0 * finite = 0: sample_bilinear_clamped's value (a zero's sign aside). */
inline void gather8_pairs(__global const float *img, const int8 i, float8 *left, float8 *right)
{
    const float2 p0 = vload2(0, img + i.s0), p1 = vload2(0, img + i.s1);
    const float2 p2 = vload2(0, img + i.s2), p3 = vload2(0, img + i.s3);
    const float2 p4 = vload2(0, img + i.s4), p5 = vload2(0, img + i.s5);
    const float2 p6 = vload2(0, img + i.s6), p7 = vload2(0, img + i.s7);
    *left = (float8)(p0.x, p1.x, p2.x, p3.x, p4.x, p5.x, p6.x, p7.x);
    *right = (float8)(p0.y, p1.y, p2.y, p3.y, p4.y, p5.y, p6.y, p7.y);
}

__kernel void sweep_warp(__global const float *src_img, __global const long *src_offset,
                         __global const int *src_size, __global const float *homography,
                         const int tw, const int th, const int tx0, const int ty0,
                         const int ref_w, const int ref_h, const int plane0,
                         __global const int *warp_window, __global const uint *warp_bands,
                         const int band_words, const int band_base,
                         __global float *warped, __global uchar *seen)
{
    const int pw = tw + 2 * CENSUS_RX, ph = th + 2 * CENSUS_RY;
    const int px0 = get_global_id(0) * SWEEP_VEC, py = get_global_id(1), bs = get_global_id(2);
    if (px0 >= pw || py >= ph) return;
    const int s = bs % NSRC, b = bs / NSRC;
    /* planes [first, end) of this group of positions (plane windows): others are not warped
     * (one unsigned comparison: the int2 form cost PoCL 5% of a full sweep's time) */
    const int g = py * ((pw + SWEEP_VEC - 1) / SWEEP_VEC) + (int)get_global_id(0);
    const int first = warp_window[2 * g];
    if ((uint)(plane0 + b - first) >= (uint)(warp_window[2 * g + 1] - first)) return;
    if (band_words > 0 && !in_band(warp_bands, g, band_words, band_base + plane0 + b)) return;
    __global const float *H = homography + ((plane0 + b) * NSRC + s) * 9;
    __global const float *img = src_img + src_offset[s];
    const int ry = clamp_index(ty0 - CENSUS_RY + py, ref_h) - ty0;
    const int sw = src_size[2 * s], sh = src_size[2 * s + 1];
    const size_t k = ((size_t)bs * ph + py) * pw + px0;
    if (px0 + SWEEP_VEC > pw) {
        for (int i = 0; px0 + i < pw; ++i)
            warp_position(img, sw, sh, H, clamp_index(tx0 - CENSUS_RX + px0 + i, ref_w) - tx0,
                          ry, k + i, warped, seen);
        return;
    }
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const float8 x = convert_float8(clamp((int8)(tx0 - CENSUS_RX + px0) + lane, (int8)0,
                                          (int8)(ref_w - 1)) - (int8)tx0);
    const float y = (float)ry;
    /* apply_homography, lane by lane */
    const float8 wz = H[6] * x + H[7] * y + H[8];
    const int8 ok = wz > (float8)0.0f;
    const float8 u = select((float8)0.0f, (H[0] * x + H[1] * y + H[2]) / wz, ok);
    const float8 v = select((float8)0.0f, (H[3] * x + H[4] * y + H[5]) / wz, ok);
    /* sample_bilinear_clamped, lane by lane */
    const float8 cx = fmin(fmax(u, (float8)0.0f), (float8)(float)(sw - 1));
    const float8 cy = fmin(fmax(v, (float8)0.0f), (float8)(float)(sh - 1));
    const float8 fx = floor(cx), fy = floor(cy);
    const int8 x0 = convert_int8(fx), y0 = convert_int8(fy);
    const int8 y1 = min(y0 + (int8)1, (int8)(sh - 1));
    const float8 ax = cx - fx, ay = cy - fy;
    const int8 r0 = y0 * (int8)sw, r1 = y1 * (int8)sw;
    float8 left, right;
    gather8_pairs(img, r0 + x0, &left, &right);
    const float8 top = ((float8)1.0f - ax) * left + ax * right;
    gather8_pairs(img, r1 + x0, &left, &right);
    const float8 bot = ((float8)1.0f - ax) * left + ax * right;
    vstore8(select((float8)0.0f, ((float8)1.0f - ay) * top + ay * bot, ok), 0, warped + k);
    const int8 in = ok & (u >= (float8)0.0f) & (u <= (float8)(float)(sw - 1))
                    & (v >= (float8)0.0f) & (v <= (float8)(float)(sh - 1));
    vstore8(convert_uchar8(in & (int8)1), 0, seen + k);
}

/* The cost of tile pixel (x, y) for plane slot b of sweep_warp's output, one pixel at a time:
 * the reference form of sweep_warped_cost's vector path, and its path for the pixels that path
 * does not take (the last, narrower group of a row; with the gradient term, pixels whose
 * reference neighbours are clamped). */
inline float warped_cost_px(__global const float *warped, __global const uchar *seen,
                            __global const ulong *ref_code, __global const float *ref_img,
                            const int tw, const int th, const int tx0, const int ty0,
                            const int ref_w, const int ref_h, const int x, const int y, const int b)
{
    const int pw = tw + 2 * CENSUS_RX, ph = th + 2 * CENSUS_RY;
    const ulong rc = ref_code[IDX2(x, y, tw)];
    const float wm = census_mask_weight(rc);
    const float ref_i = ref_img[(size_t)(ty0 + y) * ref_w + tx0 + x];
    float cst[NSRC];
    uint valid = 0u;
    for (int s = 0; s < NSRC; ++s) {
        const size_t k = ((size_t)(b * NSRC + s) * ph + y + CENSUS_RY) * pw + x + CENSUS_RX;
        cst[s] = 0.0f;
        if (!seen[k]) continue;  /* the tile pixel's own warp position: the validity rule */
        __global const float *w = warped + k;
        const float c = w[0];
        ulong code = 0;
        for (int dy = -CENSUS_RY; dy <= CENSUS_RY; ++dy) {
            for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
                if (dx == 0 && dy == 0) continue;
                code = (code << 1) | (ulong)(w[dy * pw + dx] < c);
            }
        }
        cst[s] = census_term_masked(code ^ rc, rc, wm) + ad_cost(c, ref_i);
#if GRAD_READY
        cst[s] += grad_cost(w[1] - w[-1], w[pw] - w[-pw], ref_img, ref_w, ref_h, tx0 + x, ty0 + y);
#endif
        valid |= 1u << s;
    }
    return aggregate_best(cst, valid);
}

/* sweep_warped_cost computes SWEEP_VEC (8) adjacent pixels of a row per work-item in OpenCL
 * vector types (float8, uint8): PoCL does not vectorise the one-pixel form across work-items (its
 * compiled code is scalar), and this form is 3-5 times faster there. Every step is the same
 * float32 operation as in warped_cost_px, so both give the same costs bit for bit. */
/* Census bits that do not fit in the low 32-bit word of the code (the first comparisons). */
#define CENSUS_HI_BITS (CENSUS_NBITS > 32 ? CENSUS_NBITS - 32 : 0)

__kernel void sweep_warped_cost(__global const float *warped, __global const uchar *seen,
                                __global const ulong *ref_code, __global const float *ref_img,
                                const int tw, const int th, const int tx0, const int ty0,
                                const int ref_w, const int ref_h, const int slot0,
                                const int plane0, __global const int *cost_window,
                                __global const uint *cost_bands, const int band_words,
                                const int band_base, __global float *cost)
{
    const int x0 = get_global_id(0) * SWEEP_VEC, y = get_global_id(1), b = get_global_id(2);
    if (x0 >= tw || y >= th) return;
    __global float *out = cost + (size_t)(slot0 + b) * tw * th + IDX2(x0, y, tw);
    /* planes [first, end) of this group of pixels (plane windows): others get the worst cost */
    const int g = y * ((tw + SWEEP_VEC - 1) / SWEEP_VEC) + (int)get_global_id(0);
    const int first = cost_window[2 * g];
    if ((uint)(plane0 + b - first) >= (uint)(cost_window[2 * g + 1] - first)
        || (band_words > 0 && !in_band(cost_bands, g, band_words, band_base + plane0 + b))) {
        for (int i = 0; x0 + i < tw && i < SWEEP_VEC; ++i) out[i] = INVALID_COST;
        return;
    }
    /* The vector path needs the group's 8 pixels inside the tile and, for the gradient term,
     * unclamped reference neighbours. */
    int full = x0 + SWEEP_VEC <= tw;
#if GRAD_READY
    if (GRAD_WEIGHT != 0.0f)
        full = full && tx0 + x0 >= 1 && tx0 + x0 + SWEEP_VEC < ref_w && ty0 + y >= 1
               && ty0 + y < ref_h - 1;
#endif
    if (!full) {
        for (int i = 0; x0 + i < tw && i < SWEEP_VEC; ++i)
            out[i] = warped_cost_px(warped, seen, ref_code, ref_img, tw, th, tx0, ty0, ref_w,
                                    ref_h, x0 + i, y, b);
        return;
    }
    const int pw = tw + 2 * CENSUS_RX, ph = th + 2 * CENSUS_RY;
    /* the 8 reference codes as 16 32-bit words (no 8-wide 64-bit vectors, which AVX2 lacks) */
    __global const uint *rc_words = (__global const uint *)(ref_code + IDX2(x0, y, tw));
    const uint8 rc_a = vload8(0, rc_words), rc_b = vload8(1, rc_words);
#ifdef __ENDIAN_LITTLE__
    const uint8 rc_lo = (uint8)(rc_a.even, rc_b.even), rc_hi = (uint8)(rc_a.odd, rc_b.odd);
#else
    const uint8 rc_lo = (uint8)(rc_a.odd, rc_b.odd), rc_hi = (uint8)(rc_a.even, rc_b.even);
#endif
#ifdef CENSUS_MASK_THRESHOLD
    const float8 mask_w = census_term8(rc_hi, (uint8)0u);  /* census_mask_weight, 8 pixels */
#endif
    __global const float *ref_row = ref_img + (size_t)(ty0 + y) * ref_w + tx0 + x0;
    const float8 ref_i = vload8(0, ref_row);
#if GRAD_READY
    const float8 dxr = vload8(0, ref_row + 1) - vload8(0, ref_row - 1);
    const float8 dyr = vload8(0, ref_row + ref_w) - vload8(0, ref_row - ref_w);
#endif
    float8 cst[NSRC];
    int8 ok[NSRC];
    for (int s = 0; s < NSRC; ++s) {
        const size_t k = ((size_t)(b * NSRC + s) * ph + y + CENSUS_RY) * pw + x0 + CENSUS_RX;
        ok[s] = convert_int8(vload8(0, seen + k)) != (int8)0;
        cst[s] = (float8)0.0f;
        if (!any(ok[s])) continue;
        __global const float *w = warped + k;
        const float8 c = vload8(0, w);
        uint8 lo = (uint8)0u, hi = (uint8)0u;
        int bit = 0;
        for (int dy = -CENSUS_RY; dy <= CENSUS_RY; ++dy) {
            for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
                if (dx == 0 && dy == 0) continue;
                const uint8 m = as_uint8(vload8(0, w + dy * pw + dx) < c) & (uint8)1u;
                if (bit < CENSUS_HI_BITS) hi = (hi << (uint8)1u) | m;
                else lo = (lo << (uint8)1u) | m;
                ++bit;
            }
        }
#ifdef CENSUS_MASK_THRESHOLD
        cst[s] = census_term_masked8(lo ^ rc_lo, rc_hi, mask_w)  /* hi: no bits (32 at most) */
#else
        cst[s] = census_term8(lo ^ rc_lo, hi ^ rc_hi)
#endif
                 + AD_WEIGHT * fmin(fabs(c - ref_i), (float8)AD_TRUNC) / AD_TRUNC;
#if GRAD_READY
        if (GRAD_WEIGHT != 0.0f)
            cst[s] += GRAD_WEIGHT * (fmin(fabs(vload8(0, w + 1) - vload8(0, w - 1) - dxr),
                                          (float8)GRAD_TRUNC)
                                     + fmin(fabs(vload8(0, w + pw) - vload8(0, w - pw) - dyr),
                                            (float8)GRAD_TRUNC))
                      / (2.0f * GRAD_TRUNC);
#endif
    }
    /* aggregate_best, lane by lane: the mean of the NBEST lowest valid costs. */
    int8 used[NSRC];
    for (int s = 0; s < NSRC; ++s) used[s] = (int8)0;
    float8 acc = (float8)0.0f;
    int8 taken = (int8)0;
    for (int t = 0; t < NBEST; ++t) {
        int8 best = (int8)-1;
        float8 bc = (float8)0.0f;
        for (int s = 0; s < NSRC; ++s) {
            const int8 pick = ok[s] & ~used[s] & ((best < (int8)0) | (cst[s] < bc));
            best = select(best, (int8)s, pick);
            bc = select(bc, cst[s], pick);
        }
        const int8 have = best >= (int8)0;
        for (int s = 0; s < NSRC; ++s) used[s] |= best == (int8)s;
        acc = select(acc, acc + bc, have);
        taken -= have;  /* have is -1 where true */
    }
    const float8 mean = select(acc / convert_float8(taken), acc, taken == (int8)1);
    vstore8(select(mean, (float8)INVALID_COST, taken == (int8)0), 0, out);
}

/* sweep_code_cost: census codes of the SOURCE sampled at the warped position (nearest pixel,
 * floor(u + 0.5)) versus the reference census. src_code holds every source's codes (census.cl on
 * the whole source image) concatenated like the images.
 * Work size: global = (tw, th, batch), each of the first two rounded up to any multiple; local =
 *   any. Work-item (x, y, b) writes the aggregated cost of tile pixel (x, y) for plane
 *   plane0 + b. */
__kernel void sweep_code_cost(__global const ulong *src_code, __global const long *src_offset,
                              __global const int *src_size, __global const float *homography,
                              __global const ulong *ref_code, const int tw, const int th,
                              const int plane0, __global float *cost)
{
    const int x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= tw || y >= th) return;
    const int plane = plane0 + b;
    const ulong rc = ref_code[IDX2(x, y, tw)];
    float cst[NSRC];
    uint valid = 0u;
    for (int s = 0; s < NSRC; ++s) {
        __global const float *H = homography + (plane * NSRC + s) * 9;
        const int sw = src_size[2 * s], sh = src_size[2 * s + 1];
        float u, v;
        cst[s] = 0.0f;
        if (apply_homography(H, (float)x, (float)y, &u, &v)
            && u >= 0.0f && u <= (float)(sw - 1) && v >= 0.0f && v <= (float)(sh - 1)) {
            const int ix = min((int)floor(u + 0.5f), sw - 1);
            const int iy = min((int)floor(v + 0.5f), sh - 1);
            cst[s] = census_term(src_code[src_offset[s] + IDX2(ix, iy, sw)] ^ rc);
            valid |= 1u << s;
        }
    }
    cost[(size_t)b * tw * th + IDX2(x, y, tw)] = aggregate_best(cst, valid);
}

/* volume_pixel_windows: the interior of a batch of nb cost planes, cost[nb][th][tw] (interior
 * origin (mx, my) in the tile, size iw x ih), into a RAGGED volume of per-pixel plane windows:
 * interior pixel i = y iw + x keeps the planes [label_first[i], label_first[i] + label_count[i])
 * (counted like plane0: from the tile's first plane) as its labels 0 .. label_count[i] - 1 from
 * volume[label_offset[i]] on; the batch holds planes plane0 .. plane0 + nb - 1, and a pixel
 * copies those of them in its window (volume[label_offset[i] + plane0 + b - label_first[i]] =
 * cost[b][my + y][mx + x]).
 * Work size: global = (iw, ih), each rounded up to any multiple; local = any. Work-item (x, y)
 *   writes the labels of one pixel that the batch holds. */
__kernel void volume_pixel_windows(__global const float *cost, const int tw, const int th,
                                   const int mx, const int my, const int iw, const int ih,
                                   const int nb, const int plane0,
                                   __global const int *label_first,
                                   __global const int *label_count,
                                   __global const ulong *label_offset, __global float *volume)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= iw || y >= ih) return;
    const int i = IDX2(x, y, iw);
    const int first = label_first[i] - plane0;  /* the window's first plane, in batch slots */
    const int b0 = max(first, 0), b1 = min(first + label_count[i], nb);
    __global const float *c = cost + IDX2(mx + x, my + y, tw);
    __global float *o = volume + label_offset[i] - first;
    const size_t plane = (size_t)tw * th;
    for (int b = b0; b < b1; ++b) o[b] = c[b * plane];
}

/* volume_pixel_major: the interior of a batch of nb filtered cost planes, cost[nb][th][tw]
 * (interior origin (mx, my) in the tile, size iw x ih), into a cost volume of the whole reference
 * kept in the PIXEL-MAJOR layout that SGM aggregates in (sgm.cl): volume[out_offset + ((oy + y)
 * out_w + ox + x) n_planes + plane0 + b] = cost[b][my + y][mx + x], where (ox, oy) is the
 * interior's origin in the reference and n_planes the volume's label count (a ragged volume,
 * whose blocks hold their own label counts, gives each block's start as out_offset, its width as
 * out_w and its own count as n_planes, with ox = oy = 0).
 * Work size: global = (iw, ih), each rounded up to any multiple; local = any. Work-item (x, y)
 *   writes the nb labels of one pixel. */
__kernel void volume_pixel_major(__global const float *cost, const int tw, const int th,
                                 const int mx, const int my, const int iw, const int ih,
                                 const int nb, __global float *volume, const int out_w,
                                 const int ox, const int oy, const int n_planes,
                                 const int plane0, const ulong out_offset)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= iw || y >= ih) return;
    __global const float *c = cost + IDX2(mx + x, my + y, tw);
    __global float *o = volume + out_offset + (size_t)IDX2(ox + x, oy + y, out_w) * n_planes
                        + plane0;
    const size_t plane = (size_t)tw * th;
    for (int b = 0; b < nb; ++b) o[b] = c[b * plane];
}

/* warp_image: a source image resampled onto the reference grid by one homography (the warp that
 * sweep_census_cost performs before its census), for inspection and tests.
 * out[y][x] = bilinear sample (clamped coordinates) of src (sw x sh) at H (x, y), or 0 where the
 *   homogeneous denominator is not positive; seen[y][x] = 1 when H (x, y) lies inside the source.
 * Work size: global = (out_w, out_h), each rounded up to any multiple; local = any. One pixel per
 *   work-item. Needs only common.h (the sweep constants must still be defined to build the file).
 */
__kernel void warp_image(__global const float *src, const int sw, const int sh,
                         __global const float *homography, const int out_w, const int out_h,
                         __global float *out, __global uchar *seen)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= out_w || y >= out_h) return;
    float u, v;
    const int ok = apply_homography(homography, (float)x, (float)y, &u, &v);
    out[IDX2(x, y, out_w)] = ok ? sample_bilinear_clamped(src, sw, sh, u, v) : 0.0f;
    seen[IDX2(x, y, out_w)] = (uchar)(ok && u >= 0.0f && u <= (float)(sw - 1) && v >= 0.0f
                                      && v <= (float)(sh - 1));
}
