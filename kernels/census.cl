/* census.cl: census transform of a float32 image into 64-bit codes.
 *
 * census_transform: codes of the window of pixels [x0, x0 + out_w) x [y0, y0 + out_h) of the
 *   row-major image img (w x h), written row-major into codes (out_w x out_h). A full image is
 *   x0 = y0 = 0, out_w = w, out_h = h; a tile of the reference view passes its origin and size.
 * Work size: global = (out_w, out_h), each rounded up to any multiple of the local size; local =
 *   any (none required). Work-item (i, j) writes the code of image pixel (x0 + i, y0 + j); items
 *   past out_w/out_h return at once. The window must lie inside the image (host checks).
 * Compile-time constants: CENSUS_RX, CENSUS_RY (window half-width and half-height, pixels);
 *   optionally CENSUS_MASK_THRESHOLD (float, intensity units): each code's high 32-bit word then
 *   holds the mask of its comparisons whose neighbour v has |v - centre| < the threshold (bit k of
 *   the mask = bit k of the code), for the reference's edge-aware census (common.h).
 * Bit order and border rule: see common.h (raster order, centre skipped, edge replication).
 */
#include "common.h"

#ifndef CENSUS_RX
#error "CENSUS_RX must be defined"
#endif
#ifndef CENSUS_RY
#error "CENSUS_RY must be defined"
#endif

__kernel void census_transform(__global const float *img, const int w, const int h,
                               const int x0, const int y0, const int out_w, const int out_h,
                               __global ulong *codes)
{
    const int i = get_global_id(0);
    const int j = get_global_id(1);
    if (i >= out_w || j >= out_h) return;
    const int cx = x0 + i, cy = y0 + j;
    const float c = img[IDX2(cx, cy, w)];
    ulong code = 0;
#ifdef CENSUS_MASK_THRESHOLD
    ulong mask = 0;
#endif
    for (int dy = -CENSUS_RY; dy <= CENSUS_RY; ++dy) {
        const int yy = clamp_index(cy + dy, h);
        for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
            if (dx == 0 && dy == 0) continue;
            const float v = img[IDX2(clamp_index(cx + dx, w), yy, w)];
            code = (code << 1) | (ulong)(v < c);
#ifdef CENSUS_MASK_THRESHOLD
            mask = (mask << 1) | (ulong)(fabs(v - c) < CENSUS_MASK_THRESHOLD);
#endif
        }
    }
#ifdef CENSUS_MASK_THRESHOLD
    code |= mask << 32;
#endif
    codes[IDX2(i, j, out_w)] = code;
}
