/* voxel_direct.cl: raymarch.cl's direct single scattering for the view segments outside
 * the voxel grid, without the light that crosses the grid.
 *
 * Light whose straight path from the light to a medium point passes through the grid box
 * went through the grid's volumes: the photons carry it (bent) and hand it back beyond
 * the grid as lighting segments (photon_exits in voxel.cl). So here the grid box occludes
 * like a surface. The kernel is raymarch.cl's, unchanged: only light_transmission is
 * wrapped, and the box rides in the second record of the `medium` buffer (bmin, bmax), so
 * the kernel's signature stays raymarch's.
 */
#include "voxel.h"

float4 voxel_light_transmission(__global const BVHNode *nodes, __global const float4 *tris,
                                __global const int *light_grid, int li,
                                __global const Medium *m, float4 x, float4 wi, float dist,
                                float tmin) {
    float t0, t1;
    float tmax = dist < T_INF ? dist : T_INF;
    if (ray_box(x, safe_inv_dir(wi), m[1].bmin, m[1].bmax, tmin, tmax, &t0, &t1)) return (float4)(0.0f);
    return light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
}
#define light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin) \
    voxel_light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin)

#include "raymarch.cl"
