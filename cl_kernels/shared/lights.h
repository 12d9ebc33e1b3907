/* lights.h: light arriving at a point, shared by surface shading (view_paths.cl) and the
 * medium methods (raymarch.cl, ...). One place for the light models of docs/scene_format.md:
 * point and spot lights give intensity I (W/sr) -> I / d^2; a spot is a hard-edged cone
 * of uniform intensity; a directional light gives irradiance E on a facing surface. */
#ifndef CLSCATTER_LIGHTS_H
#define CLSCATTER_LIGHTS_H
#include "common.h"
#include "bvh.h"
#include "tile_grid.h"

/* Unoccluded, unattenuated irradiance (on a surface facing the light) at x, with wi the
 * unit direction from x towards the light and dist the distance (T_INF: directional). */
float4 light_arrival(__global const Light *L, float4 x, float4 *wi, float *dist) {
    if (L->type == LIGHT_DIRECTIONAL) {
        *wi = -L->direction;
        *dist = T_INF;
        return L->power;
    }
    float4 to = L->position - x;
    to.w = 0.0f;
    float d2 = fmax(dot3(to, to), 1e-20f);
    float d = sqrt(d2);
    *wi = to / d;
    *dist = d;
    if (L->type == LIGHT_SPOT && dot3(-*wi, L->direction) < L->cos_cutoff) return (float4)(0.0f);
    return L->power / d2;
}

/* The medium's part of light_transmission: transmittance along the light path's piece
 * inside the medium's bounds. */
float4 light_medium_fraction(__global const Medium *m, float4 x, float4 wi, float dist) {
    float len = medium_path_length(m, x, wi, 0.0f, dist);
    return len > 0.0f ? transmittance(m->kappa, len) : (float4)(1.0f, 1.0f, 1.0f, 0.0f);
}

/* Fraction of light li's light reaching x: 0 when a surface blocks the way (every
 * surface, glass included, occludes direct light; caustics are the caustic methods' job),
 * else the medium's transmittance along the part of the light path inside its bounds.
 * The shadow ray goes through the scene's light grid (tile_grid.h; packed) when that
 * grid serves light li, with the BVH's answer: parallel rays for a directional light,
 * rays towards the light for a spot or point light (a point light's grid is a cube of
 * six faces); otherwise, or where x lies outside the grid, through the BVH. */
float4 light_transmission(__global const BVHNode *nodes, __global const float4 *tris,
                          __global const int *light_grid, int li, __global const Medium *m,
                          float4 x, float4 wi, float dist, float tmin) {
    float tmax = dist < T_INF ? dist * (1.0f - 1e-5f) : T_INF;
    __global const TileGrid *g = GRID_HEAD(light_grid);
    int blocked = -1;
    if (g->light == li)
        blocked = g->perspective
            ? grid_any_toward(tris, grid_cube_face(light_grid, x), x, wi, tmin, tmax)
            : scene_any(nodes, tris, light_grid, x, wi, tmin, tmax);
    if (blocked < 0) blocked = bvh_any(nodes, tris, x, wi, tmin, tmax);
    if (blocked) return (float4)(0.0f);
    return light_medium_fraction(m, x, wi, dist);
}

#endif
