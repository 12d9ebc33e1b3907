/* probe.cl: the tiny kernel every candidate device must build and run correctly
 * before clscatter uses it (clscatter/device.py). Exercises the common header too. */
#include "common.h"

__kernel void probe(__global const float *a, int n, __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float4 v = vec3(a[i], 1.0f, 2.0f);
    out[i] = dot3(v, v) + hg_phase(0.0f, 0.0f) * 4.0f * PI_F;  /* a^2 + 5 + 1 */
}
