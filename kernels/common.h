/* common.h: definitions shared by every satsweep kernel.
 *
 * Included by each stage's .cl file with #include "common.h"; the host passes the folder that
 * holds this file as -I. Sizes and switches are compile-time -D constants set by the host.
 */
#ifndef SATSWEEP_COMMON_H
#define SATSWEEP_COMMON_H

/* Constants shared with the host. Their one source is satsweep/opencl/constants.py, whose
 * SHARED_DEFINES Device.build passes to every build as -D definitions; no kernel defines them
 * itself, and a build without them stops here:
 *   SATSWEEP_INVALID  marker of invalid float results (height, cost), -1e30 (not NaN, so that
 *                     comparisons behave the same on every device, PoCL with fast-math included);
 *   WTA_BIG, WTA_NSTATE, WTA_S_M1 .. WTA_S_MAX  the winner-take-all state's "infinite" cost, its
 *                     number of fields and the slot of each (wta.cl);
 *   SWEEP_VEC, WTA_VEC, GF_COLS_VEC  pixels per work-item of the vector kernels (sweep.cl, wta.cl,
 *                     guided_filter.cl);
 *   SWEEP_BAND_PLANES  planes per bit of the split sweep kernels' band sets (sweep.cl);
 *   SGM_MAX_LABELS, SGM_SCAN_GUARD  most labels of an SGM volume, +inf guards of sgm_scan
 *                     (sgm.cl). */
#if !defined(SATSWEEP_INVALID) || !defined(WTA_BIG) || !defined(WTA_NSTATE)
#error "SATSWEEP_INVALID, WTA_BIG and WTA_NSTATE must be defined (satsweep/opencl/constants.py)"
#endif
#if !defined(WTA_S_M1) || !defined(WTA_S_I1) || !defined(WTA_S_M1P) || !defined(WTA_S_M1N) \
    || !defined(WTA_S_M2) || !defined(WTA_S_PREV) || !defined(WTA_S_PREV2) || !defined(WTA_S_MAX)
#error "the slots WTA_S_M1 .. WTA_S_MAX must be defined (satsweep/opencl/constants.py)"
#endif
#if !defined(SWEEP_VEC) || !defined(WTA_VEC) || !defined(GF_COLS_VEC) || !defined(SWEEP_BAND_PLANES)
#error "SWEEP_VEC, WTA_VEC, GF_COLS_VEC and SWEEP_BAND_PLANES must be defined (satsweep/opencl/constants.py)"
#endif
#if !defined(SGM_MAX_LABELS) || !defined(SGM_SCAN_GUARD)
#error "SGM_MAX_LABELS and SGM_SCAN_GUARD must be defined (satsweep/opencl/constants.py)"
#endif

/* 2D index helpers for row-major images of width w. */
#define IDX2(x, y, w) ((y) * (w) + (x))

/* Clamp an integer coordinate into [0, n-1]. */
inline int clamp_index(int i, int n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

/* ---- geometry and sampling helpers (plane sweep) ------------------------------------------ */

/* Apply a row-major 3x3 homography H (9 floats) to the pixel (x, y): (u, v) = (H x~)_xy / (H x~)_z.
 * Returns 0 when the homogeneous denominator is not positive (point behind the camera or at
 * infinity), 1 otherwise. The operations are written out in a fixed order so that every device
 * rounds the same sequence of float32 operations. */
inline int apply_homography(__global const float *H, const float x, const float y,
                            float *u, float *v)
{
    const float wz = H[6] * x + H[7] * y + H[8];
    if (!(wz > 0.0f)) { *u = 0.0f; *v = 0.0f; return 0; }
    *u = (H[0] * x + H[1] * y + H[2]) / wz;
    *v = (H[3] * x + H[4] * y + H[5]) / wz;
    return 1;
}

/* Bilinear sample of a row-major float image (w x h) at (x, y); pixel (0, 0) is the centre of the
 * first pixel. The coordinates are clamped into [0, w-1] x [0, h-1] first (edge replication), so
 * the result is always defined; the caller decides separately whether (x, y) was inside. */
inline float sample_bilinear_clamped(__global const float *img, const int w, const int h,
                                     float x, float y)
{
    x = fmin(fmax(x, 0.0f), (float)(w - 1));
    y = fmin(fmax(y, 0.0f), (float)(h - 1));
    const float fx = floor(x), fy = floor(y);
    const int x0 = (int)fx, y0 = (int)fy;
    const int x1 = min(x0 + 1, w - 1), y1 = min(y0 + 1, h - 1);
    const float ax = x - fx, ay = y - fy;
    const float top = (1.0f - ax) * img[IDX2(x0, y0, w)] + ax * img[IDX2(x1, y0, w)];
    const float bot = (1.0f - ax) * img[IDX2(x0, y1, w)] + ax * img[IDX2(x1, y1, w)];
    return (1.0f - ay) * top + ay * bot;
}

/* Census transform convention (census.cl and sweep.cl share it):
 * - window of (2*CENSUS_RY+1) rows x (2*CENSUS_RX+1) columns centred on the pixel;
 * - neighbours are visited in raster order (top row first, left to right), the centre skipped;
 *   each appends one bit at the least significant end: code = (code << 1) | (neighbour < centre),
 *   so the first neighbour ends in the most significant used bit;
 * - neighbours outside the image take the value of the nearest edge pixel (clamped coordinates).
 * CENSUS_NBITS = window area - 1 must be at most 64 (codes are ulong). */
#if defined(CENSUS_RX) && defined(CENSUS_RY)
#define CENSUS_NBITS ((2 * CENSUS_RX + 1) * (2 * CENSUS_RY + 1) - 1)
#if CENSUS_NBITS > 64
#error "census window too large for a 64-bit code"
#endif
/* Matching cost of one source at one pixel and plane, in census bits: the Hamming distance plus,
 * with AD_WEIGHT > 0 (AD-census), AD_WEIGHT * min(|I_src - I_ref|, AD_TRUNC) / AD_TRUNC of the
 * (warped) intensities, plus with GRAD_WEIGHT > 0 the same for the two image gradients
 * (sweep.cl). COST_MAX is the largest such cost. */
#ifndef AD_WEIGHT
#define AD_WEIGHT 0.0f
#endif
#ifndef GRAD_WEIGHT
#define GRAD_WEIGHT 0.0f
#endif
#define COST_MAX ((float)CENSUS_NBITS + AD_WEIGHT + GRAD_WEIGHT)
/* Edge-aware census (CENSUS_MASK_THRESHOLD, intensity units): the reference's codes carry in
 * their high 32-bit word a mask of the comparisons whose neighbour lies within the threshold of
 * the centre's intensity (same bit order as the code, census.cl); the cost kernels count only
 * those bits (census_term_masked, sweep.cl). The code must then fit in the low word. */
#ifdef CENSUS_MASK_THRESHOLD
#if CENSUS_NBITS > 32
#error "CENSUS_MASK_THRESHOLD needs a census code of at most 32 bits"
#endif
#endif
#endif

#endif /* SATSWEEP_COMMON_H */
