/* tile_grid.h: closest and any hit for rays that share a direction (orthographic grid)
 * or an origin (perspective grid), through a tile grid instead of the BVH.
 *
 * The grid (clscatter/accel/tile_grid.py) lists, per tile of a rectangle normal to its
 * direction, the triangles whose padded projection overlaps the tile, sorted by a key
 * that bounds their distance from below: the nearest axial coordinate along the
 * direction. A ray of the grid tests its tile's triangles in order and stops once a key
 * is past its closest hit. A perspective grid tests with the BVH's watertight test
 * (bvh_triangle): the same hit distance the BVH gives. An orthographic grid's triangles
 * come projected onto its plane (raster_triangles), so its rays run the same watertight
 * test from the stored edges (grid_raster_try): distances within float rounding.
 *
 * The grid is one int buffer (TileGrid.packed): the TileGrid record, then the tiles'
 * starts, the listed triangles' slots, the keys' float bits and (orthographic) the
 * projected triangles, at the record's offsets.
 *
 * Interface (g: the packed grid):
 *   int grid_tile(g, o, d)      tile of the ray (o, d), or -1 (no grid, or outside it)
 *   int grid_closest(tris, g, tile, o, d, tmin, tmax, &hit)
 *   int grid_any(tris, g, tile, o, d, tmin, tmax)
 *   int grid_closest_plane(g, p1, p2, base, tmin, tmax, &t)   an orthographic grid's ray
 *                               by its plane and axial coordinates; -1: ask the BVH
 * Orthographic: d must be the grid's unit direction. Perspective: o must be the grid's
 * origin and d a unit vector. t is a distance. Portable OpenCL 1.2 C.
 */
#ifndef CLSCATTER_TILE_GRID_H
#define CLSCATTER_TILE_GRID_H

#include "bvh.h"

typedef struct {
    float4 origin;   /* a point of the plane (orthographic) or the rays' origin */
    float4 s1, s2;   /* unit axes of the plane */
    float4 dir;      /* unit direction, normal to the plane */
    float4 rect;     /* (lo1, lo2, hi1, hi2) in plane (perspective: tangent) coordinates */
    int nx, ny;      /* tiles along s1, s2; nx == 0: no grid (use the BVH) */
    int items;       /* listed (triangle, tile) entries */
    int perspective; /* 1: rays from origin, plane coordinates divided by the depth */
    int light;       /* the light whose shadow rays it serves (scene grids), or -1 */
    int starts_at, items_at, keys_at;   /* offsets in words of the three arrays */
    int faces;       /* 6: a point light's cube, six perspective grids one after another */
    int next;        /* offset in words from this record to the next face's (0: last) */
    int raster_at;   /* orthographic: offset in words of the projected triangles, or 0 */
    int pad1;
} TileGrid;

#define GRID_HEAD(g) ((__global const TileGrid *)(g))

/* the tile at plane coordinates (x1, x2) (perspective: already divided by the depth), or
 * -1 outside the rectangle */
int grid_tile_at(__global const TileGrid *h, float x1, float x2) {
    float4 rect = h->rect;
    float fx = (x1 - rect.x) / (rect.z - rect.x) * h->nx;
    float fy = (x2 - rect.y) / (rect.w - rect.y) * h->ny;
    if (!(fx >= 0.0f && fx < (float)h->nx && fy >= 0.0f && fy < (float)h->ny)) return -1;
    return min((int)fy, h->ny - 1) * h->nx + min((int)fx, h->nx - 1);
}

int grid_tile(__global const int *g, float4 o, float4 d) {
    __global const TileGrid *h = GRID_HEAD(g);
    if (h->nx <= 0) return -1;
    float4 q = h->perspective ? d : o - h->origin;
    float depth = h->perspective ? dot3(q, h->dir) : 1.0f;
    if (!(depth > 0.0f)) return -1;
    return grid_tile_at(h, dot3(q, h->s1) / depth, dot3(q, h->s2) / depth);
}

/* The watertight test for a ray of an orthographic grid at plane coordinates (p1, p2)
 * and axial coordinate base, against triangle record R (raster_triangles in
 * tile_grid.py: the projection every ray of the grid shares, done on the host): the
 * edge functions U, V, W (weights of v0, v1, v2) from the stored canonical edges, a hit
 * when they agree in sign (zero counts as inside) and their sum is not 0, at the
 * weighted depth. On a hit with t in (tmin, *best), writes *best (and hit). */
int grid_raster_try(__global const float4 *R, int tri, float p1, float p2, float base,
                    float tmin, float *best, Hit *hit) {
#pragma OPENCL FP_CONTRACT OFF
    __global const float4 *r = R + 5 * tri;
    float4 e0 = r[0], e1 = r[1], e2 = r[2], sg = r[3], z = r[4];
    float U = sg.x * (e0.z * (p2 - e0.y) - e0.w * (p1 - e0.x));
    float V = sg.y * (e1.z * (p2 - e1.y) - e1.w * (p1 - e1.x));
    float W = sg.z * (e2.z * (p2 - e2.y) - e2.w * (p1 - e2.x));
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f)) return 0;
    float det = U + V + W;
    if (det == 0.0f) return 0;
    float inv_det = 1.0f / det;
    float t = (U * z.x + V * z.y + W * z.z) * inv_det - base;
    if (!(t > tmin && t < *best)) return 0;
    *best = t;
    if (hit) {
        hit->t = t;
        hit->tri = tri;
        hit->u = V * inv_det;
        hit->v = W * inv_det;
    }
    return 1;
}

/* The tile's list in order, up to the first key past the closest hit *best: with the
 * projected triangles R when given (p1, p2, base: the ray's plane and axial coordinates),
 * else the BVH's test on ray r. any_hit != 0 returns at the first hit. */
int grid_list(__global const float4 *tris, __global const int *g, int tile,
              __global const float4 *R, const BvhRay *r, float p1, float p2, float base,
              float tmin, float *best, int any_hit, Hit *hit) {
    __global const TileGrid *h = GRID_HEAD(g);
    __global const int *starts = g + h->starts_at;
    __global const int *items = g + h->items_at;
    __global const float *keys = (__global const float *)(g + h->keys_at);
    int found = 0;
    int end = starts[tile + 1];
    for (int k = starts[tile]; k < end; ++k) {
        if (keys[k] - base >= *best) break;       /* this and every later one is farther */
        if (R ? grid_raster_try(R, items[k], p1, p2, base, tmin, best, hit)
              : bvh_try_triangle(r, tris, items[k], tmin, best, hit)) {
            found = 1;
            if (any_hit) return 1;
        }
    }
    return found;
}

int grid_traverse(__global const float4 *tris, __global const int *g, int tile, float4 o,
                  float4 d, float tmin, float tmax, int any_hit, Hit *hit) {
    __global const TileGrid *h = GRID_HEAD(g);
    /* an orthographic grid's rays share the projection: its triangles come projected */
    __global const float4 *R = h->raster_at > 0 && !h->perspective
                               ? (__global const float4 *)(g + h->raster_at) : 0;
    BvhRay r;
    if (!R && !bvh_ray_setup(o, d, &r)) return 0;
    /* axial coordinate of the origin (0 for a perspective grid's own rays) */
    float4 q = o - h->origin;
    float base = h->perspective ? 0.0f : dot3(q, h->dir);
    float p1 = R ? dot3(q, h->s1) : 0.0f, p2 = R ? dot3(q, h->s2) : 0.0f;
    float best = tmax;
    return grid_list(tris, g, tile, R, &r, p1, p2, base, tmin, &best, any_hit, hit);
}

int grid_closest(__global const float4 *tris, __global const int *g, int tile, float4 o,
                 float4 d, float tmin, float tmax, Hit *hit) {
    return grid_traverse(tris, g, tile, o, d, tmin, tmax, 0, hit);
}

/* Closest hit distance (*t, T_INF for none) of the ray of an orthographic grid with
 * projected triangles given by its plane coordinates (p1, p2) and axial coordinate base
 * (relative to the grid's origin), for callers that hold those already (a shadow map's
 * texels): no ray origin to project. Returns -1 where the grid cannot answer (no
 * projected triangles, or outside it): the caller asks the BVH. */
int grid_closest_plane(__global const int *g, float p1, float p2, float base, float tmin,
                       float tmax, float *t) {
    __global const TileGrid *h = GRID_HEAD(g);
    if (h->nx <= 0 || h->perspective || h->raster_at <= 0) return -1;
    int tile = grid_tile_at(h, p1, p2);
    if (tile < 0) return -1;
    float best = tmax;
    int found = grid_list(0, g, tile, (__global const float4 *)(g + h->raster_at), 0, p1, p2,
                          base, tmin, &best, 0, 0);
    *t = found ? best : T_INF;
    return found;
}

int grid_any(__global const float4 *tris, __global const int *g, int tile, float4 o,
             float4 d, float tmin, float tmax) {
    return grid_traverse(tris, g, tile, o, d, tmin, tmax, 1, 0);
}

/* Any hit for a ray from o towards a perspective grid's origin (a spot light's shadow
 * ray: o a lit point, d towards the light), tested along the ray itself, so the answer
 * is the BVH's. Its tile is that of the direction from the origin to o; every point of
 * the segment is nearer the origin than o, hence at a smaller depth, so the list stops
 * at the first key (a triangle's least depth) of |o - origin| or more. Returns -1 when o
 * lies outside the grid (the caller asks the BVH). */
int grid_any_toward(__global const float4 *tris, __global const int *g, float4 o, float4 d,
                    float tmin, float tmax) {
    __global const TileGrid *h = GRID_HEAD(g);
    float4 q = o - h->origin;
    q.w = 0.0f;
    int tile = h->perspective ? grid_tile(g, h->origin, q) : -1;
    if (tile < 0) return -1;
    BvhRay r;
    if (!bvh_ray_setup(o, d, &r)) return 0;
    float lim = length3(q);
    __global const int *starts = g + h->starts_at;
    __global const int *items = g + h->items_at;
    __global const float *keys = (__global const float *)(g + h->keys_at);
    float best = tmax;
    int end = starts[tile + 1];
    for (int k = starts[tile]; k < end && keys[k] < lim; ++k)
        if (bvh_try_triangle(&r, tris, items[k], tmin, &best, 0)) return 1;
    return 0;
}

/* The face of a cube of grids (faces == 6) that point p falls in, seen from the cube's
 * origin: face 2 k + s for the axis k of the largest |p - origin| component, s = 1 on its
 * negative side (clscatter.accel.tile_grid._cube_grids); the grid itself otherwise. */
__global const int *grid_cube_face(__global const int *g, float4 p) {
    __global const TileGrid *h = GRID_HEAD(g);
    if (h->faces != 6) return g;
    float4 q = p - h->origin;
    float ax = fabs(q.x), ay = fabs(q.y), az = fabs(q.z);
    int k = ax >= ay ? (ax >= az ? 0 : 2) : (ay >= az ? 1 : 2);
    float c = k == 0 ? q.x : (k == 1 ? q.y : q.z);
    int f = 2 * k + (c < 0.0f);
    for (int i = 0; i < f; ++i) g += GRID_HEAD(g)->next;
    return g;
}

/* Closest hit through the grid where the ray is one of its rays (tile found), else the
 * BVH: callers hand every ray of a family here and get the BVH's answer either way. */
int scene_closest(__global const BVHNode *nodes, __global const float4 *tris,
                  __global const int *g, float4 o, float4 d, float tmin, float tmax, Hit *hit) {
    int tile = grid_tile(g, o, d);
    return tile >= 0 ? grid_closest(tris, g, tile, o, d, tmin, tmax, hit)
                     : bvh_closest(nodes, tris, o, d, tmin, tmax, hit);
}

int scene_any(__global const BVHNode *nodes, __global const float4 *tris,
              __global const int *g, float4 o, float4 d, float tmin, float tmax) {
    int tile = grid_tile(g, o, d);
    return tile >= 0 ? grid_any(tris, g, tile, o, d, tmin, tmax)
                     : bvh_any(nodes, tris, o, d, tmin, tmax);
}

#endif
