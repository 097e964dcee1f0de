/* selftest.cl: the trivial kernel that `satsweep devices` builds and runs on each device to prove
 * that the device can compile and execute satsweep's kernels (listing a platform is not enough).
 *
 * scale_add: out[i] = SCALE * a[i] + i, for i in [0, n).
 * Work size: global = (n,) rounded up to any multiple; local = any (none required).
 * Compile-time constants: -DSCALE=<float>.
 */
#include "common.h"

#ifndef SCALE
#error "SCALE must be defined with -DSCALE=<float>"
#endif

__kernel void scale_add(__global const float *a, __global float *out, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    out[i] = SCALE * a[i] + (float)i;
}
