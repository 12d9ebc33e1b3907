/* bvh.cl: test and benchmark kernels for the BVH traversal in bvh.h.
 *
 * One work-item per ray. Triangle ids written here are indices into the *reordered*
 * triangle array (as in Hit.tri); the host (clscatter.accel.bvh.trace) maps them to
 * input triangle ids with BVH.order. Misses write t = INFINITY and tri = -1.
 */
#include "bvh.h"

__kernel void closest_hit(__global const BVHNode *nodes, __global const float4 *tris,
                          __global const float4 *orig, __global const float4 *dir,
                          float tmin, float tmax, int n, __global float *t_out,
                          __global int *tri_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    Hit h;
    if (bvh_closest(nodes, tris, orig[i], dir[i], tmin, tmax, &h)) {
        t_out[i] = h.t;
        tri_out[i] = h.tri;
    } else {
        t_out[i] = INFINITY;
        tri_out[i] = -1;
    }
}

/* closest_hit plus the barycentrics (u, v) of v1, v2; NaN on a miss */
__kernel void closest_hit_uv(__global const BVHNode *nodes, __global const float4 *tris,
                             __global const float4 *orig, __global const float4 *dir,
                             float tmin, float tmax, int n, __global float *t_out,
                             __global int *tri_out, __global float2 *uv_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    Hit h;
    if (bvh_closest(nodes, tris, orig[i], dir[i], tmin, tmax, &h)) {
        t_out[i] = h.t;
        tri_out[i] = h.tri;
        uv_out[i] = (float2)(h.u, h.v);
    } else {
        t_out[i] = INFINITY;
        tri_out[i] = -1;
        uv_out[i] = (float2)(NAN, NAN);
    }
}

__kernel void any_hit(__global const BVHNode *nodes, __global const float4 *tris,
                      __global const float4 *orig, __global const float4 *dir,
                      float tmin, float tmax, int n, __global int *hit_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    hit_out[i] = bvh_any(nodes, tris, orig[i], dir[i], tmin, tmax);
}
