/* density.h: heterogeneous media on the device (docs/scene_format.md, "What a volume
 * means", Density): density grids sampled as the scene format says, their exact optical
 * depth along a ray, and the transport of a scene that has them.
 *
 * A grid holds the density at the centres of the voxels of its box [bmin, bmax]: voxel
 * (i, j, k) of an (nx, ny, nz) grid is centred at bmin + (i + 0.5, j + 0.5, k + 0.5) *
 * (bmax - bmin) / (nx, ny, nz). Between centres the density is trilinear; between the
 * outermost centres and the box faces it is that of the nearest centre (the index
 * coordinate is clamped); outside the box it is 0. Values are float32, x slowest:
 * value (i, j, k) is values[offset + (i * ny + j) * nz + k] (a C-order NumPy array).
 *
 * Coefficients: inside a grid's box sigma_s(x) = density(x) * sigma_s of the grid and
 * kappa(x) = density(x) * kappa, and the scene medium does not apply there (a volume's
 * coefficients replace the medium's in its region); where boxes overlap their
 * coefficients add. Outside every box the scene medium holds as before.
 *
 * Exact optical depth. Along a straight ray the trilinear density is a polynomial of
 * degree <= 3 between the planes through the voxel centres (in the clamped border slabs
 * too, where it is constant along the clamped axis), so density_integral steps from plane
 * to plane (a 3-D DDA over the cells between centres) and integrates every piece by
 * Simpson's rule, which is exact for cubics: the result is the integral up to float32
 * rounding, at two lookups per piece.
 *
 * Layout. The grids ride behind the scene's Medium record in the one `medium` buffer, so
 * every kernel keeps the engine's signature (voxel_direct.cl carries its box the same way):
 *   record 0   the scene medium, `present` = MEDIUM_HOMOGENEOUS if it has one | MEDIUM_DENSITY
 *   record 1   a void medium (present 0): light_transmission through it is the shadow test alone
 *   then       DensityHead, `count` DensityGrid records, the float values of every grid
 * (host: clscatter/estimators/density_march.py builds it).
 */
#ifndef CLSCATTER_DENSITY_H
#define CLSCATTER_DENSITY_H
#include "common.h"
#include "bvh.h"
#include "lights.h"
#include "specular.h"

#define MEDIUM_HOMOGENEOUS 1
#define MEDIUM_DENSITY 2
/* grids one scene may hold (the union of their boxes along a ray is merged in registers) */
#define DENSITY_MAX_GRIDS 8

typedef struct {
    float4 bmin, bmax;     /* the grid's box (normalised frame) */
    float4 sigma_s;        /* scattering per unit density (rgb, per normalised unit) */
    float4 kappa;          /* extinction per unit density */
    int nx, ny, nz;        /* voxels along x, y, z */
    int offset;            /* index of value (0, 0, 0) among the values */
} DensityGrid;

typedef struct {
    int count;             /* grids */
    int pad0, pad1, pad2;
} DensityHead;

__global const DensityHead *density_head(__global const Medium *m) {
    return (__global const DensityHead *)(m + 2);
}
__global const DensityGrid *density_grids(__global const Medium *m) {
    return (__global const DensityGrid *)(density_head(m) + 1);
}
__global const float *density_values(__global const Medium *m) {
    return (__global const float *)(density_grids(m) + density_head(m)->count);
}

/* Index coordinates per unit length: u = (p - bmin) * scale - 0.5 puts centre i at u = i. */
float4 density_scale(__global const DensityGrid *g) {
    float4 e = g->bmax - g->bmin;
    return (float4)(g->nx / e.x, g->ny / e.y, g->nz / e.z, 0.0f);
}

int density_in_box(__global const DensityGrid *g, float4 p) {
    return p.x >= g->bmin.x && p.y >= g->bmin.y && p.z >= g->bmin.z &&
           p.x <= g->bmax.x && p.y <= g->bmax.y && p.z <= g->bmax.z;
}

/* The density at index coordinates u: trilinear between centres, clamped to the outermost. */
float density_lookup(__global const DensityGrid *g, __global const float *v, float4 u) {
    float fx = clamp(u.x, 0.0f, (float)(g->nx - 1));
    float fy = clamp(u.y, 0.0f, (float)(g->ny - 1));
    float fz = clamp(u.z, 0.0f, (float)(g->nz - 1));
    int x0 = (int)fx, y0 = (int)fy, z0 = (int)fz;
    int x1 = min(x0 + 1, g->nx - 1), y1 = min(y0 + 1, g->ny - 1), z1 = min(z0 + 1, g->nz - 1);
    float tx = fx - x0, ty = fy - y0, tz = fz - z0;
    __global const float *b = v + g->offset;
    int ny = g->ny, nz = g->nz;
#define DENSITY_AT(i, j, k) b[((i) * ny + (j)) * nz + (k)]
    float c00 = mix(DENSITY_AT(x0, y0, z0), DENSITY_AT(x0, y0, z1), tz);
    float c01 = mix(DENSITY_AT(x0, y1, z0), DENSITY_AT(x0, y1, z1), tz);
    float c10 = mix(DENSITY_AT(x1, y0, z0), DENSITY_AT(x1, y0, z1), tz);
    float c11 = mix(DENSITY_AT(x1, y1, z0), DENSITY_AT(x1, y1, z1), tz);
#undef DENSITY_AT
    return mix(mix(c00, c01, ty), mix(c10, c11, ty), tx);
}

/* The density of grid g at point p (0 outside its box). */
float density_at(__global const DensityGrid *g, __global const float *v, float4 p) {
    if (!density_in_box(g, p)) return 0.0f;
    return density_lookup(g, v, (p - g->bmin) * density_scale(g) - 0.5f);
}

/* The integral of grid g's density along o + t d over [t0, t1] (d need not be unit: the
 * result is per unit of t), exact up to rounding (see the top of this file). */
float density_integral(__global const DensityGrid *g, __global const float *v, float4 o,
                       float4 d, float t0, float t1) {
    float a, b;
    if (!ray_box(o, safe_inv_dir(d), g->bmin, g->bmax, t0, t1, &a, &b) || !(b > a))
        return 0.0f;
    float4 sc = density_scale(g);
    float4 u0 = (o - g->bmin) * sc - 0.5f;
    float4 du = d * sc;
    float uo[3] = {u0.x, u0.y, u0.z}, ud[3] = {du.x, du.y, du.z};
    float next[3], k[3], step[3];
    for (int c = 0; c < 3; ++c) {            /* the first centre plane ahead on each axis */
        float ua = uo[c] + a * ud[c];
        step[c] = ud[c] > 0.0f ? 1.0f : -1.0f;
        k[c] = ud[c] > 0.0f ? floor(ua) + 1.0f : ceil(ua) - 1.0f;
        next[c] = ud[c] != 0.0f ? (k[c] - uo[c]) / ud[c] : T_INF;
    }
    float t = a, fa = density_lookup(g, v, u0 + a * du), sum = 0.0f;
    int pieces = g->nx + g->ny + g->nz + 8;  /* planes crossed inside the box, and slack */
    for (int it = 0; it < pieces && t < b; ++it) {
        int c = next[0] <= next[1] ? (next[0] <= next[2] ? 0 : 2) : (next[1] <= next[2] ? 1 : 2);
        float te = fmin(next[c], b);
        if (te > t) {
            float fm = density_lookup(g, v, u0 + (0.5f * (t + te)) * du);
            float fe = density_lookup(g, v, u0 + te * du);
            sum += (te - t) * (fa + 4.0f * fm + fe) * (1.0f / 6.0f);
            t = te;
            fa = fe;
        }
        if (next[c] <= te) {
            k[c] += step[c];
            next[c] = (k[c] - uo[c]) / ud[c];
        }
    }
    if (t < b) {                             /* not reached: rounding left a sliver */
        float fm = density_lookup(g, v, u0 + (0.5f * (t + b)) * du);
        sum += (b - t) * (fa + 4.0f * fm + density_lookup(g, v, u0 + b * du)) * (1.0f / 6.0f);
    }
    return sum;
}

/* The scene medium holds at x: it exists and x lies in its bounds (grids aside). */
int homogeneous_at(__global const Medium *m, float4 x) {
    if (!(m->present & MEDIUM_HOMOGENEOUS)) return 0;
    return !m->bounded || (x.x >= m->bmin.x && x.y >= m->bmin.y && x.z >= m->bmin.z &&
                           x.x <= m->bmax.x && x.y <= m->bmax.y && x.z <= m->bmax.z);
}

/* Length of [t0, t1] along o + t d (d unit) where the scene medium holds: inside its bounds
 * and outside every grid's box (the union of the boxes' intervals, merged in order). */
float homogeneous_length(__global const Medium *m, float4 o, float4 d, float t0, float t1) {
    if (!(m->present & MEDIUM_HOMOGENEOUS)) return 0.0f;
    float4 inv = safe_inv_dir(d);
    float h0 = t0, h1 = t1;
    if (m->bounded && !ray_box(o, inv, m->bmin, m->bmax, t0, t1, &h0, &h1)) return 0.0f;
    if (!(h1 > h0)) return 0.0f;
    __global const DensityGrid *gs = density_grids(m);
    int n = min(density_head(m)->count, DENSITY_MAX_GRIDS);
    float s[DENSITY_MAX_GRIDS], e[DENSITY_MAX_GRIDS];
    int k = 0;
    for (int i = 0; i < n; ++i) {
        float a, b;
        if (!ray_box(o, inv, gs[i].bmin, gs[i].bmax, h0, h1, &a, &b) || !(b > a)) continue;
        int j = k++;
        for (; j > 0 && s[j - 1] > a; --j) { s[j] = s[j - 1]; e[j] = e[j - 1]; }
        s[j] = a;
        e[j] = b;
    }
    float covered = 0.0f, cs = h0, ce = h0;
    for (int j = 0; j < k; ++j) {
        if (s[j] > ce) { covered += ce - cs; cs = s[j]; ce = e[j]; }
        else ce = fmax(ce, e[j]);
    }
    covered += ce - cs;
    return fmax(h1 - h0 - covered, 0.0f);
}

/* Optical depth (rgb) of [t0, t1] along o + t d (d unit): every grid's kappa times its
 * density's integral, plus the scene medium's kappa over its length outside the boxes. */
float4 density_optical_depth(__global const Medium *m, float4 o, float4 d, float t0, float t1) {
    __global const DensityGrid *gs = density_grids(m);
    __global const float *v = density_values(m);
    int n = density_head(m)->count;
    float4 tau = (float4)(0.0f);
    for (int i = 0; i < n; ++i) {
        float s = density_integral(&gs[i], v, o, d, t0, t1);
        if (s > 0.0f) tau += gs[i].kappa * s;
    }
    float h = homogeneous_length(m, o, d, t0, t1);
    if (h > 0.0f) tau += m->kappa * h;
    tau.w = 0.0f;
    return tau;
}

/* sigma_s (rgb) at x: the grids' whose box holds x, else the scene medium's where it holds. */
float4 density_sigma_s(__global const Medium *m, float4 x) {
    __global const DensityGrid *gs = density_grids(m);
    __global const float *v = density_values(m);
    int n = density_head(m)->count, inside = 0;
    float4 ss = (float4)(0.0f);
    for (int i = 0; i < n; ++i) {
        if (!density_in_box(&gs[i], x)) continue;
        inside = 1;
        ss += gs[i].sigma_s * density_lookup(&gs[i], v, (x - gs[i].bmin) * density_scale(&gs[i]) - 0.5f);
    }
    if (!inside && homogeneous_at(m, x)) ss = m->sigma_s;
    ss.w = 0.0f;
    return ss;
}

/* ---- The transport of a scene with grids: what view_paths.cl and raymarch.cl call, in
 * their density builds (density_view.cl, density_march.cl), instead of the homogeneous
 * medium_piece, branch_attenuation and light_transmission. ---- */

/* Fraction of light li's light reaching x: light_transmission's shadow test (through the
 * void record: no medium), times exp(-optical depth) along the light path. */
float4 density_light_transmission(__global const BVHNode *nodes, __global const float4 *tris,
                                  __global const int *light_grid, int li,
                                  __global const Medium *m, float4 x, float4 wi, float dist,
                                  float tmin) {
    float4 vis = light_transmission(nodes, tris, light_grid, li, m + 1, x, wi, dist, tmin);
    if (vis.x == 0.0f) return vis;
    return exp3(-density_optical_depth(m, x, wi, 0.0f, dist));
}

/* The straight piece of a branch before t_hit that any medium covers: from the first
 * entry into the scene medium or a grid's box to the last exit (outside objects only).
 * Nothing attenuates the branch before its start. */
int density_piece(__global const Medium *m, const Branch *br, float t_hit, float4 *a, float4 *b) {
    if (br->inside >= 0) return 0;
    float lo = T_INF, hi = -T_INF, t0, t1;
    if ((m->present & MEDIUM_HOMOGENEOUS) &&
        medium_interval(m, br->o, br->d, 0.0f, t_hit, &t0, &t1) && t1 > t0) {
        lo = t0;
        hi = t1;
    }
    float4 inv = safe_inv_dir(br->d);
    __global const DensityGrid *gs = density_grids(m);
    for (int i = 0; i < density_head(m)->count; ++i) {
        if (ray_box(br->o, inv, gs[i].bmin, gs[i].bmax, 0.0f, t_hit, &t0, &t1) && t1 > t0) {
            lo = fmin(lo, t0);
            hi = fmax(hi, t1);
        }
    }
    if (!(hi > lo)) return 0;
    *a = br->o + lo * br->d;
    *b = br->o + hi * br->d;
    a->w = 0.0f;
    b->w = 0.0f;
    return 1;
}

/* Attenuation of a branch over [0, t_hit]: the grids and the scene medium outside objects,
 * or the interior extinction (interior_kappa) of the dielectric it is inside. */
float4 density_branch_attenuation(__global const Medium *m, __global const Material *materials,
                                  const Branch *br, float t_hit) {
    if (br->inside >= 0) return transmittance(interior_kappa(&materials[br->inside]), t_hit);
    return exp3(-density_optical_depth(m, br->o, br->d, 0.0f, t_hit));
}

#endif
