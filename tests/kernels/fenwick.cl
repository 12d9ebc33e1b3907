/* fenwick.cl: test hook for the Fenwick (half) tree of epipolar.h.
 *
 * One work-item per tree. Every tree starts from its own leaves, builds in O(d), then
 * runs the same script of operations: op.x == 0 removes the fraction op.z of leaf op.y
 * (fw_scale_leaf), op.x == 1 writes the prefix sum at continuous index op.y (fw_query).
 * tests/test_epipolar.py compares the results with NumPy cumsum in float64.
 */
#include "epipolar.h"

__kernel void fenwick_test(int ntree, int d, __global const float *init,
                           __global const float4 *ops, int nops, int nq, __global float *T,
                           __global float *L, __global float *out) {
    int t = get_global_id(0);
    if (t >= ntree) return;
    __global float *Tt = T + (size_t)t * d * EPI_NV;
    __global float *Lt = L + (size_t)t * d * EPI_NV;
    __global const float *it = init + (size_t)t * d * EPI_NV;
    for (int k = 0; k < d * EPI_NV; ++k) {
        Tt[k] = it[k];
        Lt[k] = it[k];
    }
    fw_build(Tt, d);
    int q = 0;
    for (int k = 0; k < nops; ++k) {
        float4 op = ops[k];
        if (op.x == 0.0f) {
            fw_scale_leaf(Tt, Lt, d, (int)op.y, op.z);
        } else {
            float acc[EPI_NV];
            for (int c = 0; c < EPI_NV; ++c) acc[c] = 0.0f;
            fw_query(Tt, Lt, d, op.y, acc);
            for (int c = 0; c < EPI_NV; ++c) out[((size_t)t * nq + q) * EPI_NV + c] = acc[c];
            ++q;
        }
    }
}
