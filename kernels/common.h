/* common.h: definitions shared by every satsweep kernel.
 *
 * Included by each stage's .cl file with #include "common.h"; the host passes the folder that
 * holds this file as -I. Sizes and switches are compile-time -D constants set by the host.
 */
#ifndef SATSWEEP_COMMON_H
#define SATSWEEP_COMMON_H

/* Marker value for invalid float results (height, cost); NaN is avoided on purpose so that
 * comparisons behave the same on every device, including PoCL with fast-math. */
#define SATSWEEP_INVALID (-1.0e30f)

/* 2D index helpers for row-major images of width w. */
#define IDX2(x, y, w) ((y) * (w) + (x))

/* Clamp an integer coordinate into [0, n-1]. */
inline int clamp_index(int i, int n) { return i < 0 ? 0 : (i >= n ? n - 1 : i); }

#endif /* SATSWEEP_COMMON_H */
