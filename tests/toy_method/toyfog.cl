/* toyfog.cl: the toy method's one kernel (tests/toy_method/toyfog.py). */
#include "common.h"

__kernel void toyfog(__global const ViewSegment *segs, int n, float level,
                     __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    ViewSegment s = segs[i];
    float len = length(s.b.xyz - s.a.xyz);
    out[i] = (float4)(level * len * s.weight.xyz, 0.0f);
}
