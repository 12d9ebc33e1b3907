/* lsg_test.cl: a test hook for lsg.h (tests/test_lsg.py): the chord's attenuation
 * integral exp_segment_integral, one work-item per (e0, x, D). */
#include "lsg.h"

__kernel void lsg_exp_integral(__global const float4 *e0, __global const float4 *x,
                               __global const float *D, int n, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    out[i] = exp_segment_integral(e0[i], x[i], D[i]);
}
