/* bvh.cl: test and benchmark kernels for the BVH traversal in bvh.h.
 *
 * One work-item per ray. Triangle ids written here are indices into the *reordered*
 * triangle array (as in Hit.tri); the host (clscatter.accel.bvh.trace) maps them to
 * input triangle ids with BVH.order. Misses write t = INFINITY and tri = -1.
 */
#include "bvh.h"
#include "tile_grid.h"

/* t and slot of a closest hit (found) or of a miss (INFINITY, -1) */
void write_hit(int found, const Hit *h, int i, __global float *t_out, __global int *tri_out) {
    t_out[i] = found ? h->t : INFINITY;
    tri_out[i] = found ? h->tri : -1;
}

__kernel void closest_hit(__global const BVHNode *nodes, __global const float4 *tris,
                          __global const float4 *orig, __global const float4 *dir,
                          float tmin, float tmax, int n, __global float *t_out,
                          __global int *tri_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    Hit h;
    write_hit(bvh_closest(nodes, tris, orig[i], dir[i], tmin, tmax, &h), &h, i, t_out, tri_out);
}

/* closest_hit plus the barycentrics (u, v) of v1, v2; NaN on a miss */
__kernel void closest_hit_uv(__global const BVHNode *nodes, __global const float4 *tris,
                             __global const float4 *orig, __global const float4 *dir,
                             float tmin, float tmax, int n, __global float *t_out,
                             __global int *tri_out, __global float2 *uv_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    Hit h;
    int found = bvh_closest(nodes, tris, orig[i], dir[i], tmin, tmax, &h);
    write_hit(found, &h, i, t_out, tri_out);
    uv_out[i] = found ? (float2)(h.u, h.v) : (float2)(NAN, NAN);
}

__kernel void any_hit(__global const BVHNode *nodes, __global const float4 *tris,
                      __global const float4 *orig, __global const float4 *dir,
                      float tmin, float tmax, int n, __global int *hit_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    hit_out[i] = bvh_any(nodes, tris, orig[i], dir[i], tmin, tmax);
}

/* Test hook for tile_grid.h: rays from orig[i] along the grid's direction (own_dir == 0)
 * or along dir[i]; closest (any == 0: t and slot, as closest_hit) or any hit (any != 0:
 * t_out = 1 or 0). A ray outside the grid writes t = NaN and tri = -2. */
__kernel void grid_hit(__global const float4 *tris, __global const int *grid,
                       __global const float4 *orig, __global const float4 *dir, int own_dir,
                       float tmin, float tmax, int any, int n, __global float *t_out,
                       __global int *tri_out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float4 d = own_dir ? dir[i] : GRID_HEAD(grid)->dir;
    int tile = grid_tile(grid, orig[i], d);
    if (tile < 0) { t_out[i] = NAN; tri_out[i] = -2; return; }
    if (any) {
        t_out[i] = grid_any(tris, grid, tile, orig[i], d, tmin, tmax) ? 1.0f : 0.0f;
        tri_out[i] = -1;
        return;
    }
    Hit h;
    write_hit(grid_closest(tris, grid, tile, orig[i], d, tmin, tmax, &h), &h, i, t_out, tri_out);
}

/* Test hook for grid_any_toward: any hit on the ray from orig[i] towards the grid's
 * origin with t in (tmin, (1 - 1e-5) |origin - orig[i]|) (a spot light's shadow ray);
 * out = 1 / 0, or -1 where orig[i] lies outside the grid; a cube of grids (a point
 * light's) answers through the face orig[i] falls in. */
__kernel void grid_toward_hit(__global const float4 *tris, __global const int *grid,
                              __global const float4 *orig, float tmin, int n,
                              __global int *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float4 to = GRID_HEAD(grid)->origin - orig[i];
    to.w = 0.0f;
    float dist = length3(to);
    out[i] = grid_any_toward(tris, grid_cube_face(grid, orig[i]), orig[i], to / dist, tmin,
                             dist * (1.0f - 1e-5f));
}
