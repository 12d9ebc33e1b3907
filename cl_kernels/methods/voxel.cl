/* voxel.cl: the voxel relighting pipeline (Sun et al. 2008, "Interactive relighting of
 * dynamic refractive objects"), every stage a kernel.
 *
 * Grid layout: a float grid of dims (nx, ny, nz) is stored x-major exactly like a NumPy
 * array of shape (nx, ny, nz) in C order: idx = (i * ny + j) * nz + k. Voxel (i, j, k)
 * spans lo + [i, i+1) * h (cubic voxels of side h, normalised frame); values live at the
 * voxel centres lo + (i + 0.5) * h and are trilinear between centres, clamped to the
 * nearest centre beyond the outermost ones (docs/scene_format.md, "What a volume means").
 *
 * Stages (host side: clscatter/methods/voxel/):
 *   vox_inside, vox_coverage     inside test at voxel centres, 4^3 coverage near the surface
 *   vox_blur                     separable convolution (Gaussian 9 taps; 3-tap smoothing)
 *   vox_gradient                 central differences of n
 *   vox_interior_gradient        grad n without the volumes' boundary jumps (sharp
 *                                boundaries: vox_cut, vox_refract, vox_cross)
 *   oct_reduce, oct_levels       min/max pyramid, dense octree level grid, step limits
 *   photon_emit, photon_march    photons where light enters the grid; adaptive marching
 *                                with line-segment deposition (3-D DDA, float CAS atomics)
 *   voxel_view_march             curved view rays at a fixed one-voxel step
 *   voxel_trace_camera/_rays     straight view paths outside the grid (includes view_paths.cl)
 */
#include "voxel.h"
#include "density.h"

/* The straight tracers' shadow rays. Their medium buffer has two records at least: the
 * scene's Medium first (so everything else reads it as before), then a void record
 * (present 0). Where photons light the surfaces that record is the grid's occluder
 * (bounded 1, bmin / bmax the grid box): a shadow ray that crosses the box gets nothing,
 * for the light that crosses the grid reaches surfaces as photons (photon_surface; not
 * twice). Else, in a scene with density volumes the buffer is density.h's (its record 1
 * the void one) and shadow rays are attenuated through the grids; with the plain Medium
 * record (no MEDIUM_DENSITY bit) they are the engine's. */
int vox_occluded(__global const Medium *m, float4 x, float4 wi, float dist, float tmin) {
    __global const Medium *o = m + 1;
    if (o->present != 0 || o->bounded != 1) return 0;
    float t0, t1;
    return ray_box(x, safe_inv_dir(wi), o->bmin, o->bmax, tmin, dist < T_INF ? dist : T_INF,
                   &t0, &t1);
}
float4 voxel_unoccluded(__global const BVHNode *nodes, __global const float4 *tris,
                        __global const int *light_grid, int li, __global const Medium *m,
                        float4 x, float4 wi, float dist, float tmin) {
    if (m->present & MEDIUM_DENSITY)
        return density_light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
    return light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
}
float4 voxel_shadow(__global const BVHNode *nodes, __global const float4 *tris,
                    __global const int *light_grid, int li, __global const Medium *m,
                    float4 x, float4 wi, float dist, float tmin) {
    if (vox_occluded(m, x, wi, dist, tmin)) return (float4)(0.0f);
    return voxel_unoccluded(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
}
#define light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin) \
    voxel_shadow(nodes, tris, light_grid, li, m, x, wi, dist, tmin)

#include "view_paths.cl"
#include "light_paths.cl"   /* basis() */

/* ------------------------------------------------------------------ voxelisation -- */

/* Next crossing of the ray o + t d (t > tmin) with the mesh; T_INF when none. Crossings
 * closer than CROSS_EPS to the previous one are one crossing: a ray through a shared edge
 * or vertex reports both triangles at the same t, which must count once for parity. */
#define CROSS_EPS 1e-6f
float next_crossing(__global const BVHNode *nodes, __global const float4 *tris, float4 o,
                    float4 d, float tmin) {
    Hit hit;
    return bvh_closest(nodes, tris, o, d, tmin, T_INF, &hit) ? hit.t : T_INF;
}

/* Inside test at the centres of one x-column (j, k) of the grid: one ray along +x from
 * outside the grid, parity of the crossings before each centre (a watertight mesh is
 * entered and left alternately, whatever its orientation). Writes inside[.] = 0 / 1. */
__kernel void vox_inside(__global const BVHNode *nodes, __global const float4 *tris,
                         float4 lo, int4 dims, float h, __global uchar *inside) {
    int gid = get_global_id(0);
    if (gid >= dims.y * dims.z) return;
    int j = gid / dims.z, k = gid % dims.z;
    float4 o = (float4)(lo.x - h, lo.y + (j + 0.5f) * h, lo.z + (k + 0.5f) * h, 0.0f);
    float4 d = (float4)(1.0f, 0.0f, 0.0f, 0.0f);
    int par = 0, i = 0;
    float t = next_crossing(nodes, tris, o, d, 0.0f);
    for (int guard = 0; guard < 4096 && i < dims.x; ++guard) {
        while (i < dims.x && (i + 1.5f) * h < t) {         /* centre i at t = (i + 1.5) h */
            inside[(i * dims.y + j) * dims.z + k] = (uchar)par;
            ++i;
        }
        if (t >= T_INF) break;
        par ^= 1;
        t = next_crossing(nodes, tris, o, d, t + CROSS_EPS * (1.0f + t));
    }
    for (; i < dims.x; ++i) inside[(i * dims.y + j) * dims.z + k] = 0;
}

/* Fractional coverage: where the 3x3x3 neighbourhood of the inside grid agrees the voxel
 * is wholly in or out; elsewhere 4x4x4 sub-samples (16 sub-columns along x, parity as in
 * vox_inside) give the fraction inside. refine_all = 1 refines every voxel (the dense
 * supersampled reference for the tests). */
#define SUB 4
__kernel void vox_coverage(__global const BVHNode *nodes, __global const float4 *tris,
                           float4 lo, int4 dims, float h, __global const uchar *inside,
                           int refine_all, __global float *coverage) {
    int idx = get_global_id(0);
    int n = dims.x * dims.y * dims.z;
    if (idx >= n) return;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    uchar c = inside[idx];
    int mixed = refine_all;
    for (int a = -1; a <= 1 && !mixed; ++a)
        for (int b = -1; b <= 1 && !mixed; ++b)
            for (int e = -1; e <= 1 && !mixed; ++e) {
                int ii = clamp(i + a, 0, dims.x - 1), jj = clamp(j + b, 0, dims.y - 1);
                int kk = clamp(k + e, 0, dims.z - 1);
                mixed = inside[(ii * dims.y + jj) * dims.z + kk] != c;
            }
    if (!mixed) { coverage[idx] = (float)c; return; }
    float4 d = (float4)(1.0f, 0.0f, 0.0f, 0.0f);
    int count = 0;
    float t_end = (i + 1) * h + h;        /* the voxel's far x face, t from the ray origin */
    for (int sb = 0; sb < SUB; ++sb)
        for (int sc = 0; sc < SUB; ++sc) {
            float4 o = (float4)(lo.x - h, lo.y + (j + (sb + 0.5f) / SUB) * h,
                                lo.z + (k + (sc + 0.5f) / SUB) * h, 0.0f);
            int par = 0, m = 0;
            float t = next_crossing(nodes, tris, o, d, 0.0f);
            for (int guard = 0; guard < 4096 && m < SUB; ++guard) {
                while (m < SUB && (i + (m + 0.5f) / SUB) * h + h < t) { count += par; ++m; }
                if (t >= t_end || t >= T_INF) break;
                par ^= 1;
                t = next_crossing(nodes, tris, o, d, t + CROSS_EPS * (1.0f + t));
            }
            for (; m < SUB; ++m) count += par;
        }
    coverage[idx] = count * (1.0f / (SUB * SUB * SUB));
}

/* One pass of a separable convolution along `axis` of a grid with `channels` floats per
 * voxel; taps w[0 .. 2r], edges clamped (the value beyond a face is the face voxel's). */
__kernel void vox_blur(__global const float *src, __global float *dst, int4 dims, int channels,
                       int axis, __global const float *w, int r) {
    int gid = get_global_id(0);
    int n = dims.x * dims.y * dims.z;
    if (gid >= n * channels) return;
    int idx = gid / channels, c = gid % channels;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    int len = axis == 0 ? dims.x : (axis == 1 ? dims.y : dims.z);
    int pos = axis == 0 ? i : (axis == 1 ? j : k);
    int stride = axis == 0 ? dims.y * dims.z : (axis == 1 ? dims.z : 1);
    float acc = 0.0f;
    for (int q = -r; q <= r; ++q) {
        int p = clamp(pos + q, 0, len - 1);
        acc += w[q + r] * src[(idx + (p - pos) * stride) * channels + c];
    }
    dst[gid] = acc;
}

/* vox_blur for float4 grids (the deposited radiance and directions): one work-item per
 * voxel, four channels at once. */
__kernel void vox_blur4(__global const float4 *src, __global float4 *dst, int4 dims, int axis,
                        __global const float *w, int r) {
    int idx = get_global_id(0);
    if (idx >= dims.x * dims.y * dims.z) return;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    int len = axis == 0 ? dims.x : (axis == 1 ? dims.y : dims.z);
    int pos = axis == 0 ? i : (axis == 1 ? j : k);
    int stride = axis == 0 ? dims.y * dims.z : (axis == 1 ? dims.z : 1);
    float4 acc = (float4)(0.0f);
    for (int q = -r; q <= r; ++q) {
        int p = clamp(pos + q, 0, len - 1);
        acc += w[q + r] * src[idx + (p - pos) * stride];
    }
    dst[idx] = acc;
}

/* grad n by central differences, one-sided on the faces of the grid (xyz of a float4). */
__kernel void vox_gradient(__global const float *n, int4 dims, float h, __global float4 *grad) {
    int idx = get_global_id(0);
    if (idx >= dims.x * dims.y * dims.z) return;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    int ia = max(i - 1, 0), ib = min(i + 1, dims.x - 1);
    int ja = max(j - 1, 0), jb = min(j + 1, dims.y - 1);
    int ka = max(k - 1, 0), kb = min(k + 1, dims.z - 1);
    float4 g = (float4)(0.0f);
    if (ib > ia) g.x = (n[(ib * dims.y + j) * dims.z + k] - n[(ia * dims.y + j) * dims.z + k]) / ((ib - ia) * h);
    if (jb > ja) g.y = (n[(i * dims.y + jb) * dims.z + k] - n[(i * dims.y + ja) * dims.z + k]) / ((jb - ja) * h);
    if (kb > ka) g.z = (n[(i * dims.y + j) * dims.z + kb] - n[(i * dims.y + j) * dims.z + ka]) / ((kb - ka) * h);
    grad[idx] = g;
}

/* ---------------------------------------------------------------------- octree -- */

/* One pyramid level (at offset doff) from the level below it (at soff) in the same two
 * buffers: each cell's min / max over its (up to) 2x2x2 children. */
__kernel void oct_reduce(__global float *pmin, __global float *pmax, int soff, int4 sd,
                         int doff, int4 dd) {
    __global const float *smin = pmin + soff, *smax = pmax + soff;
    __global float *dmin = pmin + doff, *dmax = pmax + doff;
    int idx = get_global_id(0);
    if (idx >= dd.x * dd.y * dd.z) return;
    int i = idx / (dd.y * dd.z), j = (idx / dd.z) % dd.y, k = idx % dd.z;
    float lo = INFINITY, hi = -INFINITY;
    for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b)
            for (int c = 0; c < 2; ++c) {
                int si = 2 * i + a, sj = 2 * j + b, sk = 2 * k + c;
                if (si >= sd.x || sj >= sd.y || sk >= sd.z) continue;
                int s = (si * sd.y + sj) * sd.z + sk;
                lo = fmin(lo, smin[s]);
                hi = fmax(hi, smax[s]);
            }
    dmin[idx] = lo;
    dmax[idx] = hi;
}

/* Dense octree: for every voxel the coarsest level whose cell has n_max - n_min < eps2
 * (level 0 = the voxel itself always qualifies), and the step limit inside that node:
 * infinite where the node's range is also < eps (n essentially constant: march to the
 * node's face), `limit` voxels where it is in [eps, eps2) (Sun et al. 2008, sec. 5.3).
 * Pyramid level k is stored at offset off[k] with dims ceil(dims / 2^k). */
__kernel void oct_levels(__global const float *pmin, __global const float *pmax,
                         __global const int *off, int levels, int4 dims, float eps, float eps2,
                         float limit, __global uchar *level, __global float *smax) {
    int idx = get_global_id(0);
    if (idx >= dims.x * dims.y * dims.z) return;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    for (int L = levels - 1; L >= 0; --L) {
        int ly = (dims.y + (1 << L) - 1) >> L, lz = (dims.z + (1 << L) - 1) >> L;
        int c = off[L] + ((i >> L) * ly + (j >> L)) * lz + (k >> L);
        float range = pmax[c] - pmin[c];
        if (range < eps2 || L == 0) {
            level[idx] = (uchar)L;
            smax[idx] = range < eps ? INFINITY : limit;
            return;
        }
    }
}

/* ------------------------------------------------------------------- sampling -- */

/* Trilinear interpolation weights between voxel centres, clamped to the outermost ones. */
typedef struct { int i0, j0, k0, i1, j1, k1; float fx, fy, fz; } Tri;
Tri tri_setup(float4 x, float4 lo, int4 dims, float inv_h) {
    float4 p = (x - lo) * inv_h - 0.5f;
    Tri t;
    float px = clamp(p.x, 0.0f, (float)(dims.x - 1)), py = clamp(p.y, 0.0f, (float)(dims.y - 1));
    float pz = clamp(p.z, 0.0f, (float)(dims.z - 1));
    t.i0 = min((int)px, dims.x - 1); t.j0 = min((int)py, dims.y - 1); t.k0 = min((int)pz, dims.z - 1);
    t.i1 = min(t.i0 + 1, dims.x - 1); t.j1 = min(t.j0 + 1, dims.y - 1); t.k1 = min(t.k0 + 1, dims.z - 1);
    t.fx = px - t.i0; t.fy = py - t.j0; t.fz = pz - t.k0;
    return t;
}
float tri_f(__global const float *g, int4 d, const Tri *t) {
#define AT(i, j, k) g[((i) * d.y + (j)) * d.z + (k)]
    float c00 = mix(AT(t->i0, t->j0, t->k0), AT(t->i1, t->j0, t->k0), t->fx);
    float c10 = mix(AT(t->i0, t->j1, t->k0), AT(t->i1, t->j1, t->k0), t->fx);
    float c01 = mix(AT(t->i0, t->j0, t->k1), AT(t->i1, t->j0, t->k1), t->fx);
    float c11 = mix(AT(t->i0, t->j1, t->k1), AT(t->i1, t->j1, t->k1), t->fx);
#undef AT
    return mix(mix(c00, c10, t->fy), mix(c01, c11, t->fy), t->fz);
}
float4 tri_f4(__global const float4 *g, int4 d, const Tri *t) {
#define AT(i, j, k) g[((i) * d.y + (j)) * d.z + (k)]
    float4 c00 = mix(AT(t->i0, t->j0, t->k0), AT(t->i1, t->j0, t->k0), t->fx);
    float4 c10 = mix(AT(t->i0, t->j1, t->k0), AT(t->i1, t->j1, t->k0), t->fx);
    float4 c01 = mix(AT(t->i0, t->j0, t->k1), AT(t->i1, t->j0, t->k1), t->fx);
    float4 c11 = mix(AT(t->i0, t->j1, t->k1), AT(t->i1, t->j1, t->k1), t->fx);
#undef AT
    return mix(mix(c00, c10, t->fy), mix(c01, c11, t->fy), t->fz);
}

/* Voxel holding x (clamped into the grid). */
int4 voxel_of(float4 x, float4 lo, int4 dims, float inv_h) {
    float4 p = (x - lo) * inv_h;
    return (int4)(clamp((int)floor(p.x), 0, dims.x - 1), clamp((int)floor(p.y), 0, dims.y - 1),
                  clamp((int)floor(p.z), 0, dims.z - 1), 0);
}

/* ----------------------------------------------- sharp boundaries: Snell and Fresnel -- */

/* A voxelised volume's index rises from the outside's to the inside's over a band of
 * voxels (its blurred coverage w, about +-4 voxels wide). The ray equation through such a
 * band bends a path as Snell's law does only where the band is flat on the path's scale:
 * across a curved band a grazing path is bent less (a ball's rim rays by several degrees
 * at bands of 1/10 to 1/30 of its radius, converging slowly with the band's width), and a
 * continuous index reflects nothing. So a volume's boundary is made sharp again: it lies
 * where w = 1/2, paths cross it by Snell's law with the Fresnel transmittance of the
 * sharp interface, and inside and outside it they follow the ray equation with the
 * boundary's jump taken out of grad n (vox_interior_gradient). The boundary grid holds
 * per voxel (w, n_lo, n_hi, 0): the blurred weight of the volume weighing most there and
 * the indices on its outer (w -> 0) and inner (w -> 1) sides (voxelise.boundary_sides;
 * equal where no volume is near: nothing to cross); trilinear like every field. A path's
 * side (0 outside, 1 inside; -1 not known yet) is its state between steps. */
#define VOX_DN_MIN 1e-3f   /* index steps below this are no interfaces (R < 2e-7) */

/* grad n without the boundaries' jumps, in place: grad[v] -= (n_hi - n_lo) grad w, grad w by
 * the central differences of vox_gradient (one-sided on the grid's faces) of boundary.x.
 * The step n_hi - n_lo is the voxel's own, or where the voxel lies outside every volume
 * (w = 0, no step recorded) that of its neighbour on the axis, so that a constant-index
 * volume leaves exactly 0 (the gradient of n there is the step times grad w); inside a
 * graded volume what remains is w grad n_v. */
__kernel void vox_interior_gradient(__global float4 *grad, __global const float4 *boundary,
                                    int4 dims, float h) {
    int idx = get_global_id(0);
    if (idx >= dims.x * dims.y * dims.z) return;
    int i = idx / (dims.y * dims.z), j = (idx / dims.z) % dims.y, k = idx % dims.z;
    int lo[3] = {max(i - 1, 0), max(j - 1, 0), max(k - 1, 0)};
    int hi[3] = {min(i + 1, dims.x - 1), min(j + 1, dims.y - 1), min(k + 1, dims.z - 1)};
    float4 b = boundary[idx];
    float sub[3] = {0.0f, 0.0f, 0.0f};
    for (int a = 0; a < 3; ++a) {
        if (hi[a] == lo[a]) continue;
        int pa[3] = {i, j, k}, pb[3] = {i, j, k};
        pa[a] = lo[a];
        pb[a] = hi[a];
        float4 ba = boundary[(pa[0] * dims.y + pa[1]) * dims.z + pa[2]];
        float4 bb = boundary[(pb[0] * dims.y + pb[1]) * dims.z + pb[2]];
        float dn = b.z - b.y;
        if (b.x <= 0.0f) dn = ba.x > 0.0f ? ba.z - ba.y : bb.z - bb.y;
        if (fabs(dn) < VOX_DN_MIN) continue;
        sub[a] = dn * (bb.x - ba.x) / ((hi[a] - lo[a]) * h);
    }
    float4 g = grad[idx];
    g.x -= sub[0];
    g.y -= sub[1];
    g.z -= sub[2];
    grad[idx] = g;
}

/* Boundary record (w, n_lo, n_hi) at x, trilinear. */
float4 vox_side_at(__global const float4 *boundary, int4 dims, float4 x, float4 lo, float inv_h) {
    Tri t = tri_setup(x, lo, dims, inv_h);
    return tri_f4(boundary, dims, &t);
}

/* grad w at voxel (i, j, k) (w = boundary.x), isotropic: along each axis the central
 * difference (one-sided on the grid's faces), smoothed across the other two axes with the
 * weights (1, 4, 1) / 6 (edges clamped). Its leading error, h^2 / 6 times the gradient of
 * the Laplacian, has no preferred direction: across a ball's curved band (the Laplacian of
 * a radial profile is radial) it does not tilt the normal, which a plain central
 * difference does (its error h^2 / 6 d3w/dx3 tilts it away from the grid's axes: about a
 * degree at a ball's rim, 64^3). */
float4 vox_w_gradient_at(__global const float4 *b, int4 d, int i, int j, int k, float inv_h) {
    const float c[3] = {1.0f / 6.0f, 4.0f / 6.0f, 1.0f / 6.0f};
    int at[3] = {i, j, k}, n[3] = {d.x, d.y, d.z};
    float g[3] = {0.0f, 0.0f, 0.0f};
    for (int a = 0; a < 3; ++a) {
        int a1 = (a + 1) % 3, a2 = (a + 2) % 3;
        int lo = max(at[a] - 1, 0), hi = min(at[a] + 1, n[a] - 1);
        if (hi == lo) continue;
        for (int p = -1; p <= 1; ++p)
            for (int q = -1; q <= 1; ++q) {
                int u[3], v[3];
                u[a] = hi; v[a] = lo;
                u[a1] = v[a1] = clamp(at[a1] + p, 0, n[a1] - 1);
                u[a2] = v[a2] = clamp(at[a2] + q, 0, n[a2] - 1);
                g[a] += c[p + 1] * c[q + 1] * (b[(u[0] * d.y + u[1]) * d.z + u[2]].x -
                                               b[(v[0] * d.y + v[1]) * d.z + v[2]].x);
            }
        g[a] *= inv_h / (hi - lo);
    }
    return (float4)(g[0], g[1], g[2], 0.0f);
}

/* Unit normal of the boundary at x, pointing inwards (towards larger w): vox_w_gradient_at
 * at the voxel centres, trilinear between them (as the marchers read grad n), so that it
 * turns continuously along the boundary; 0 where w is flat. */
float4 vox_boundary_normal(__global const float4 *boundary, int4 dims, float4 x, float4 lo,
                           float h) {
    float inv_h = 1.0f / h;
    Tri t = tri_setup(x, lo, dims, inv_h);
    float4 g = (float4)(0.0f);
    for (int c = 0; c < 8; ++c) {
        int i = (c & 1) ? t.i1 : t.i0, j = (c & 2) ? t.j1 : t.j0, k = (c & 4) ? t.k1 : t.k0;
        float wgt = ((c & 1) ? t.fx : 1.0f - t.fx) * ((c & 2) ? t.fy : 1.0f - t.fy) *
                    ((c & 4) ? t.fz : 1.0f - t.fz);
        g += wgt * vox_w_gradient_at(boundary, dims, i, j, k, inv_h);
    }
    g.w = 0.0f;
    float gl = length3(g);
    return gl > 0.0f ? g / gl : (float4)(0.0f);
}

/* Where on a step from w0 (its start) to w1 (its end) a path on `side` crosses w = 1/2:
 * the fraction of the step, w taken linear along it, clamped to [0, 1]; -1 when it does
 * not cross: the end lies on the path's side, or w does not move away from that side
 * along the step (a path just turned back, or just through, may start a hair beyond
 * 1/2 by the linear estimate: it is going home, not crossing again), or the side is not
 * known. So every crossing moves the path on, and a path cannot be caught at a boundary. */
float vox_cut(float w0, float w1, float side) {
    if (side < 0.0f) return -1.0f;
    int inside = side > 0.5f;
    if ((w1 >= 0.5f) == inside) return -1.0f;
    if (inside ? !(w1 < w0) : !(w1 > w0)) return -1.0f;
    return clamp((0.5f - w0) / (w1 - w0), 0.0f, 1.0f);
}

/* The crossing of vox_cut refined: w along the step x + s len dir is trilinear, not linear,
 * so the fraction t (w(t) = 1/2 between w(0) = w0 and w(1) = w1) is refined by a few
 * regula falsi steps on that bracket (one lookup each). t = 0 (a start past 1/2) stays. */
#define VOX_CUT_STEPS 3
float vox_cut_refine(__global const float4 *boundary, int4 dims, float4 x, float4 dir, float len,
                     float w0, float w1, float t, float4 lo, float inv_h) {
    if (!(t > 0.0f && t < 1.0f)) return t;
    float a = 0.0f, b = 1.0f, wa = w0, wb = w1;
    for (int it = 0; it < VOX_CUT_STEPS; ++it) {
        float wt = vox_side_at(boundary, dims, x + (t * len) * dir, lo, inv_h).x;
        if ((wt >= 0.5f) == (wa >= 0.5f)) { a = t; wa = wt; } else { b = t; wb = wt; }
        if (wb == wa) break;
        t = clamp(a + (0.5f - wa) / (wb - wa) * (b - a), a, b);
    }
    return t;
}

/* A path with velocity v (= n x its direction) meets the sharp boundary with unit normal
 * nrm (either orientation) from index n1 to n2. It is refracted by Snell's law (the
 * component of its direction along the boundary scaled by n1 / n2; |v| becomes n2), and
 * the unpolarised Fresnel transmittance of the interface is returned (fresnel_dielectric
 * of specular.h, as lsg and the straight tracers use); under total internal reflection it
 * is mirrored (|v| stays n1) and keeps everything (*turned = 1); the reflected part of a
 * transmitted path is dropped. Indices closer than VOX_DN_MIN, or no normal: no interface
 * (v unchanged, 1). */
float vox_refract(float4 *v, float4 nrm, float n1, float n2, int *turned) {
    *turned = 0;
    float vl = length3(*v);
    if (fabs(n1 - n2) < VOX_DN_MIN || !(vl > 0.0f) || dot3(nrm, nrm) == 0.0f) return 1.0f;
    float4 d = *v / vl;
    d.w = 0.0f;
    float c = dot3(d, nrm);
    float4 m = c < 0.0f ? -nrm : nrm;     /* along the direction of travel */
    c = fabs(c);
    float eta = n1 / n2, cos_t;
    float R = fresnel_dielectric(c, eta, &cos_t);
    if (R >= 1.0f && cos_t == 0.0f) {     /* total internal reflection */
        *turned = 1;
        *v = n1 * normalize3(d - 2.0f * c * m);
        return 1.0f;
    }
    *v = n2 * normalize3(eta * d + (cos_t - eta * c) * m);
    return 1.0f - R;
}

/* One crossing of a path at x (already moved to w = 1/2): the indices on both sides and
 * the normal from the boundary grid, then vox_refract; *side flips unless the path was
 * turned back (*turned = 1: a total internal reflection, which the marchers count as a
 * specular bounce: a voxelised sphere's normals are a little off, so a path entering
 * near grazing may meet the far side just past the critical angle and circle inside;
 * render.max_depth such bounces end it, as they end the engine's straight paths).
 * Returns the factor for its flux (throughput). */
float vox_cross(__global const float4 *boundary, int4 dims, float4 x, float4 lo, float h,
                float4 *v, float *side, int *turned) {
    float4 s = vox_side_at(boundary, dims, x, lo, 1.0f / h);
    int entering = *side < 0.5f;
    float n1 = entering ? s.y : s.z, n2 = entering ? s.z : s.y;
    float T = vox_refract(v, vox_boundary_normal(boundary, dims, x, lo, h), n1, n2, turned);
    if (!*turned) *side = entering ? 1.0f : 0.0f;
    return T;
}

/* Test hook: vox_refract for arrays of (v, nrm, (n1, n2)): v_out, and (T, turned) in out. */
__kernel void vox_refract_test(__global const float4 *v, __global const float4 *nrm,
                               __global const float4 *idx, int count, __global float4 *v_out,
                               __global float4 *out) {
    int i = get_global_id(0);
    if (i >= count) return;
    float4 vv = v[i], nn = nrm[i];
    vv.w = 0.0f;
    nn.w = 0.0f;
    int turned;
    float T = vox_refract(&vv, nn, idx[i].x, idx[i].y, &turned);
    v_out[i] = vv;
    out[i] = (float4)(T, (float)turned, 0.0f, 0.0f);
}

/* Test hook: vox_boundary_normal at points x[i] of a grid (lo, dims, h) of boundary records. */
__kernel void vox_normal_test(__global const float4 *boundary, int4 dims, float4 lo, float h,
                              __global const float4 *x, int count, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= count) return;
    float4 p = x[i];
    p.w = 0.0f;
    out[i] = vox_boundary_normal(boundary, dims, p, lo, h);
}

/* Test hook: vox_cut for arrays of (w0, w1, side). */
__kernel void vox_cut_test(__global const float4 *cases, int count, __global float *out) {
    int i = get_global_id(0);
    if (i >= count) return;
    out[i] = vox_cut(cases[i].x, cases[i].y, cases[i].z);
}

/* ----------------------------------------------------------------- deposition -- */

/* Float atomic add by compare-and-swap on the bit pattern (OpenCL 1.2 has no float
 * atomics): retry until no other work-item wrote the word between our read and swap.
 * The word is read atomically, and a failed swap hands back the value it found, which
 * the next try starts from: no plain read races with another work-item's swap. */
void atomic_add_f(volatile __global float *p, float v) {
    volatile __global uint *w = (volatile __global uint *)p;
    union { uint u; float f; } old, upd;
    old.u = atomic_or(w, 0u);
    for (;;) {
        upd.f = old.f + v;
        uint seen = atomic_cmpxchg(w, old.u, upd.u);
        if (seen == old.u) break;
        old.u = seen;
    }
}

/* A deposit not yet written: consecutive pieces of one photon's path often lie in the
 * same voxel (a step ends where the next begins), so they are summed privately and written
 * with atomics only when the path moves to another voxel (and at the end). */
typedef struct { int v; float4 e; float4 dw; } Pending;

void pending_flush(Pending *pd, volatile __global float *rad, volatile __global float *dirs) {
    if (pd->v >= 0 && pd->e.x + pd->e.y + pd->e.z > 0.0f) {
        int v = pd->v;
        atomic_add_f(&rad[4 * v + 0], pd->e.x);
        atomic_add_f(&rad[4 * v + 1], pd->e.y);
        atomic_add_f(&rad[4 * v + 2], pd->e.z);
        atomic_add_f(&dirs[4 * v + 0], pd->dw.x);
        atomic_add_f(&dirs[4 * v + 1], pd->dw.y);
        atomic_add_f(&dirs[4 * v + 2], pd->dw.z);
    }
    pd->v = -1;
    pd->e = (float4)(0.0f);
    pd->dw = (float4)(0.0f);
}

/* Deposit the straight segment x0 + s dir, s in [0, len] (dir unit), carrying rgb flux
 * `flux` at s = 0, into every voxel it crosses (3-D DDA, Amanatides & Woo): voxel v gets
 * the exact integral of the flux over its piece, int Phi(s) ds with Phi decaying by that
 * voxel's extinction (piecewise constant), in rad[v].rgb, and the same integral summed
 * over rgb times dir in dirs[v].xyz (through the caller's Pending: written when the path
 * moves on to another voxel). Returns the transmittance over the whole segment.
 * Pieces outside the grid deposit nothing (the caller clips segments to the grid). */
float4 deposit_segment(float4 x0, float4 dir, float len, float4 flux, float4 lo, int4 dims,
                       float h, __global const float4 *kappa, volatile __global float *rad,
                       volatile __global float *dirs, Pending *pd) {
    float inv_h = 1.0f / h;
    float4 p = (x0 - lo) * inv_h;                     /* voxel units */
    int ci = (int)floor(p.x), cj = (int)floor(p.y), ck = (int)floor(p.z);
    /* a start exactly on the far face of a grid edge belongs to the last voxel */
    ci = clamp(ci, 0, dims.x - 1); cj = clamp(cj, 0, dims.y - 1); ck = clamp(ck, 0, dims.z - 1);
    int sx = dir.x > 0.0f ? 1 : -1, sy = dir.y > 0.0f ? 1 : -1, sz = dir.z > 0.0f ? 1 : -1;
    /* parameter (in scene units) of the next face crossing on each axis */
    float tx = dir.x != 0.0f ? ((ci + (sx > 0)) - p.x) * h / dir.x : INFINITY;
    float ty = dir.y != 0.0f ? ((cj + (sy > 0)) - p.y) * h / dir.y : INFINITY;
    float tz = dir.z != 0.0f ? ((ck + (sz > 0)) - p.z) * h / dir.z : INFINITY;
    float dtx = dir.x != 0.0f ? h / fabs(dir.x) : INFINITY;
    float dty = dir.y != 0.0f ? h / fabs(dir.y) : INFINITY;
    float dtz = dir.z != 0.0f ? h / fabs(dir.z) : INFINITY;
    tx = fmax(tx, 0.0f); ty = fmax(ty, 0.0f); tz = fmax(tz, 0.0f);
    float t = 0.0f;
    float4 T = (float4)(1.0f, 1.0f, 1.0f, 0.0f);
    int guard = 3 * (int)(len * inv_h) + 8;
    while (t < len && guard-- > 0) {
        float t_next = fmin(fmin(tx, ty), fmin(tz, len));
        float piece = t_next - t;
        if (piece > 0.0f) {
            int v = (ci * dims.y + cj) * dims.z + ck;
            float4 kp = kappa[v];
            /* int_0^piece e^{-k s} ds = (1 - e^{-k piece}) / k, -> piece as k piece -> 0 */
            float4 Tp = exp3(-kp * piece);
            float4 integ;
            integ.x = kp.x * piece > 1e-4f ? (1.0f - Tp.x) / kp.x : piece * (1.0f - 0.5f * kp.x * piece);
            integ.y = kp.y * piece > 1e-4f ? (1.0f - Tp.y) / kp.y : piece * (1.0f - 0.5f * kp.y * piece);
            integ.z = kp.z * piece > 1e-4f ? (1.0f - Tp.z) / kp.z : piece * (1.0f - 0.5f * kp.z * piece);
            float4 e = flux * T * integ;
            e.w = 0.0f;
            if (v != pd->v) {
                pending_flush(pd, rad, dirs);
                pd->v = v;
            }
            pd->e += e;
            pd->dw += (e.x + e.y + e.z) * dir;
            T *= Tp;
        }
        t = t_next;
        if (t >= len) break;
        /* step into the neighbour across the nearest face (one axis at a time: at an
         * edge or corner the other axes follow with zero-length pieces) */
        if (tx <= ty && tx <= tz) { ci += sx; tx += dtx; if (ci < 0 || ci >= dims.x) break; }
        else if (ty <= tz) { cj += sy; ty += dty; if (cj < 0 || cj >= dims.y) break; }
        else { ck += sz; tz += dtz; if (ck < 0 || ck >= dims.z) break; }
    }
    T.w = 0.0f;
    return T;
}

/* Test hook: deposit a batch of segments (a, b, flux). */
__kernel void deposit_test(__global const float4 *a, __global const float4 *b,
                           __global const float4 *flux, int count, float4 lo, int4 dims, float h,
                           __global const float4 *kappa, volatile __global float *rad,
                           volatile __global float *dirs, __global float4 *trans) {
    int gid = get_global_id(0);
    if (gid >= count) return;
    float4 ab = b[gid] - a[gid];
    ab.w = 0.0f;
    float len = length3(ab);
    Pending pd = {-1, (float4)(0.0f), (float4)(0.0f)};
    trans[gid] = len > 0.0f ? deposit_segment(a[gid], ab / len, len, flux[gid], lo, dims, h, kappa,
                                              rad, dirs, &pd)
                            : (float4)(1.0f, 1.0f, 1.0f, 0.0f);
    pending_flush(&pd, rad, dirs);
}

/* ------------------------------------------------------------------- photons -- */

/* Exit distance along unit dir from x of the box [bmin, bmax] (x inside). */
float box_exit(float4 x, float4 dir, float4 bmin, float4 bmax) {
    float tx = dir.x > 0.0f ? (bmax.x - x.x) / dir.x : (dir.x < 0.0f ? (bmin.x - x.x) / dir.x : INFINITY);
    float ty = dir.y > 0.0f ? (bmax.y - x.y) / dir.y : (dir.y < 0.0f ? (bmin.y - x.y) / dir.y : INFINITY);
    float tz = dir.z > 0.0f ? (bmax.z - x.z) / dir.z : (dir.z < 0.0f ? (bmin.z - x.z) / dir.z : INFINITY);
    return fmax(fmin(fmin(tx, ty), tz), 0.0f);
}

/* Photons of one light, where its light enters the grid. Photon p of S*S takes stratum
 * (p % S, p / S), jittered: a direction in the cone (axis, cos_max) uniform in solid
 * angle for point / spot lights, a start on the rectangle (rect_o, rect_u, rect_v)
 * facing a directional light. Photons that miss the grid, fall outside a spot's cone or
 * are shadowed on the way (any surface) start dead; the others start at the grid face
 * with flux = per-photon flux * medium transmittance from the light, and v = n(x) dir. */
__kernel void photon_emit(__global const BVHNode *nodes, __global const float4 *tris,
                          __global const Light *lights, int light_index,
                          __global const Medium *medium, int S, uint seed,
                          float4 axis, float cos_max, float4 rect_o, float4 rect_u, float4 rect_v,
                          float4 flux_per_photon, float4 glo, float4 ghi, int4 dims, float h,
                          __global const float *n_grid,
                          __global float4 *pos, __global float4 *vel, __global float4 *flux,
                          volatile __global int *entering) {
    int p = get_global_id(0);
    if (p >= S * S) return;
    __global const Light *L = &lights[light_index];
    Rng rng = rng_seed(seed, (uint)light_index, (uint)p);
    float u = ((p % S) + rng_next(&rng)) / S, w = ((p / S) + rng_next(&rng)) / S;
    float4 o, d;
    if (L->type == LIGHT_DIRECTIONAL) {
        d = L->direction;
        o = rect_o + u * rect_u + w * rect_v;
    } else {
        float4 t, b;
        basis(axis, &t, &b);
        float ct = 1.0f - u * (1.0f - cos_max);
        float st = sqrt(fmax(0.0f, 1.0f - ct * ct));
        float phi = 2.0f * PI_F * w;
        d = normalize3(ct * axis + st * cos(phi) * t + st * sin(phi) * b);
        o = L->position;
    }
    o.w = 0.0f; d.w = 0.0f;
    float t0, t1;
    int alive = ray_box(o, safe_inv_dir(d), glo, ghi, 0.0f, T_INF, &t0, &t1) && t1 > t0;
    if (L->type == LIGHT_SPOT && dot3(d, L->direction) < L->cos_cutoff) alive = 0;
    float4 x = o + t0 * d;
    x.w = 0.0f;
    float4 F = (float4)(0.0f);
    if (alive) {
        /* shadowed before the grid? and the medium's transmittance from the light */
        if (L->type == LIGHT_DIRECTIONAL) {
            alive = !bvh_any(nodes, tris, x, -d, 1e-5f, T_INF);
            F = flux_per_photon * transmittance(medium->kappa,
                                                medium_path_length(medium, x, -d, 0.0f, T_INF));
        } else {
            alive = t0 <= 0.0f || !bvh_any(nodes, tris, o, d, 0.0f, t0);
            F = flux_per_photon * transmittance(medium->kappa, medium_path_length(medium, o, d, 0.0f, t0));
        }
        if (!medium->present) F = flux_per_photon;
    }
    Tri tr = tri_setup(x, glo, dims, 1.0f / h);
    float n = tri_f(n_grid, dims, &tr);
    pos[p] = (float4)(x.x, x.y, x.z, alive ? 1.0f : 0.0f);
    if (alive) atomic_inc(entering);        /* photons that reach the grid (statistics) */
    vel[p] = n * d;
    F.w = fmax(F.x, fmax(F.y, F.z));      /* flux at the start: the termination reference */
    flux[p] = alive ? F : (float4)(0.0f);
}

/* Adaptive photon marching (Sun et al. 2008, eqs. 4-6, sec. 4.4 and 5.3), up to `steps`
 * steps per launch for every live photon:
 *   s   = clamp(distance to the face of the octree node holding x (+ a nudge), ds_min, smax)
 *   x' = x + s v/|v|      (= x + ds/n v with ds = s n/|v|: the arc-length step)
 *   v' = v + ds grad n(x)
 * The straight segment x -> x' (clipped at the grid's faces and at the first surface) is
 * deposited voxel by voxel (deposit_segment), which also attenuates the flux. A photon
 * dies when it leaves the grid, hits a surface, or its flux falls below min_rel times its
 * starting flux. Live photons are counted in counters[0], steps taken in counters[1].
 * grad n here is the interior gradient (vox_interior_gradient): a step whose end lies across
 * a volume's sharp boundary (w of the grid `boundary` passing 1/2: vox_cut) is cut where
 * it crosses, and there the photon is refracted by Snell's law and keeps the Fresnel
 * transmittance (vox_cross; the reflected part is dropped), or is turned back whole by
 * total internal reflection (max_turns of them end it); its side of the boundaries and
 * its turns so far are kept in crossing[p] between launches as side + 2 x turns (-1 at
 * the start: side not known yet).
 * pos.w afterwards: 1 live, 0 ended (faded out, or turned back max_turns times), -1 left
 * through a grid face (the straight light beyond the grid: photon_exits, photon_surface),
 * -2 met a surface: pos is then the start of the step that met it, vel its direction and
 * flux what arrives there (photon_surface finds the surface again). 
 * adaptive = 0 gives the fixed-step marcher (s = ds_min everywhere). */
__kernel void photon_march(__global float4 *pos, __global float4 *vel, __global float4 *flux,
                           int count, int steps, float4 glo, float4 ghi, int4 dims, float h,
                           __global const float *n_grid, __global const float4 *grad,
                           __global const float4 *kappa, __global const uchar *level,
                           __global const float *smax, int adaptive, float ds_min, float min_rel,
                           __global const BVHNode *nodes, __global const float4 *tris,
                           int test_surfaces, __global const float4 *boundary,
                           __global float *crossing, int max_turns, volatile __global float *rad,
                           volatile __global float *dirs, volatile __global int *counters) {
    int p = get_global_id(0);
    if (p >= count) return;
    float4 x = pos[p];
    if (x.w != 1.0f) return;
    x.w = 0.0f;
    float4 v = vel[p], F = flux[p];
    float xs = crossing[p];
    float side = xs < 0.0f ? -1.0f : fmod(xs, 2.0f);
    int turns = xs < 0.0f ? 0 : (int)(0.5f * xs);
    float inv_h = 1.0f / h;
    int alive = 1, taken = 0;
    float state = 1.0f;
    Pending pd = {-1, (float4)(0.0f), (float4)(0.0f)};
    for (int s = 0; s < steps && alive; ++s) {
        Tri tr = tri_setup(x, glo, dims, inv_h);
        float n = tri_f(n_grid, dims, &tr);
        float4 g = tri_f4(grad, dims, &tr);
        float w0 = tri_f4(boundary, dims, &tr).x;
        if (side < 0.0f) side = w0 >= 0.5f ? 1.0f : 0.0f;
        float vl = length3(v);
        if (!(vl > 0.0f)) { alive = 0; break; }
        float4 dir = v / vl;
        dir.w = 0.0f;
        float step = ds_min;
        if (adaptive) {
            int4 c = voxel_of(x, glo, dims, inv_h);
            int vi = (c.x * dims.y + c.y) * dims.z + c.z;
            int L = level[vi];
            int4 a = (int4)((c.x >> L) << L, (c.y >> L) << L, (c.z >> L) << L, 0);
            int4 b = min(a + (1 << L), dims);
            float4 nlo = glo + convert_float4(a) * h, nhi = glo + convert_float4(b) * h;
            /* nudge 1e-3 voxel past the face so the next step starts in the next node */
            float t_node = box_exit(x, dir, nlo, nhi) + 1e-3f * h;
            step = clamp(t_node, ds_min, fmax(smax[vi] * h, ds_min));
        }
        float len = fmin(step, box_exit(x, dir, glo, ghi));
        int stop = len < step;
        state = stop ? 2.0f : 1.0f;               /* 2: leaves through a grid face */
        if (test_surfaces) {
            Hit hit;
            if (bvh_closest(nodes, tris, x, dir, 0.0f, len, &hit)) { len = hit.t; stop = 1; state = 3.0f; }
        }
        /* a boundary on the way: the step ends where the path meets it */
        float w1 = vox_side_at(boundary, dims, x + len * dir, glo, inv_h).x;
        float cut = vox_cut_refine(boundary, dims, x, dir, len, w0, w1, vox_cut(w0, w1, side),
                                   glo, inv_h);
        if (cut >= 0.0f && cut < 1.0f) { len *= cut; stop = 0; state = 1.0f; }
        float4 T = deposit_segment(x, dir, len, F, glo, dims, h, kappa, rad, dirs, &pd);
        F *= T;
        F.w = flux[p].w;
        if (state == 3.0f) { ++taken; break; }   /* at a surface: pos stays at the step's start */
        x += len * dir;
        v += (len * n / vl) * g;                  /* ds = len n / |v| */
        v.w = 0.0f;
        int turned = 0;
        if (cut >= 0.0f && !stop) F.xyz *= vox_cross(boundary, dims, x, glo, h, &v, &side, &turned);
        turns += turned;
        ++taken;
        if (stop || fmax(F.x, fmax(F.y, F.z)) < min_rel * F.w || turns >= max_turns) alive = 0;
        if (!stop && !alive) state = 0.0f;        /* faded out */
    }
    pending_flush(&pd, rad, dirs);
    crossing[p] = side < 0.0f ? -1.0f : side + 2.0f * turns;
    if (state == 3.0f) alive = 0;
    pos[p] = (float4)(x.x, x.y, x.z,
                      alive ? 1.0f : (state == 2.0f ? -1.0f : (state == 3.0f ? -2.0f : 0.0f)));
    vel[p] = v;
    flux[p] = F;
    if (alive) atomic_inc(&counters[0]);
    atomic_add(&counters[1], taken);
}

/* The light beyond the grid: every photon that left through a grid face goes on straight
 * in its last direction (docs/scene_format.md, "Beyond"); its piece in the scene medium up to
 * the first surface is appended as a lighting segment with the photon's flux, which the
 * line-space gatherer (cl_kernels/lsg.cl) turns into single scattering outside the grid. */
__kernel void photon_exits(__global const float4 *pos, __global const float4 *vel,
                           __global const float4 *flux, int count, int light_index,
                           __global const BVHNode *nodes, __global const float4 *tris,
                           __global const Medium *medium, __global LightSegment *segs,
                           int max_segs, volatile __global int *seg_count) {
    int p = get_global_id(0);
    if (p >= count || pos[p].w != -1.0f || !medium->present) return;
    float4 x = pos[p];
    x.w = 0.0f;
    float4 d = normalize3(vel[p]);
    Hit hit;
    float t_hit = bvh_closest(nodes, tris, x, d, 0.0f, T_INF, &hit) ? hit.t : T_INF;
    float t0, t1;
    if (!medium_interval(medium, x, d, 0.0f, t_hit, &t0, &t1) || !(t1 > t0)) return;
    int idx = atomic_inc(seg_count);
    if (idx >= max_segs) return;
    LightSegment sg;
    sg.a = x + t0 * d;
    sg.b = x + t1 * d;
    sg.a.w = 0.0f;
    sg.b.w = 0.0f;
    sg.flux = flux[p];        /* no medium between x and a: a is x or the bounds' entry */
    sg.flux.w = 0.0f;
    sg.light = light_index;
    sg.depth = 1;
    sg.ray = p;
    sg.branch = 0;
    segs[idx] = sg;
}

/* The same light deposited into the coarse *outer* grid (bounds olo, dims od, voxel oh,
 * extinction okappa: the scene medium's), as one straight segment per photon from the
 * exit to the first surface or the medium's end: the "grid" way of carrying the light
 * beyond the grid, read back by outer_view. */
__kernel void photon_outer(__global const float4 *pos, __global const float4 *vel,
                           __global const float4 *flux, int count,
                           __global const BVHNode *nodes, __global const float4 *tris,
                           __global const Medium *medium, float4 olo, float4 ohi, int4 od,
                           float oh, __global const float4 *okappa, volatile __global float *rad,
                           volatile __global float *dirs) {
    int p = get_global_id(0);
    if (p >= count || pos[p].w != -1.0f || !medium->present) return;
    float4 x = pos[p];
    x.w = 0.0f;
    float4 d = normalize3(vel[p]);
    Hit hit;
    float t_hit = bvh_closest(nodes, tris, x, d, 0.0f, T_INF, &hit) ? hit.t : T_INF;
    float t0, t1, b0, b1;
    if (!medium_interval(medium, x, d, 0.0f, t_hit, &t0, &t1) || !(t1 > t0)) return;
    if (!ray_box(x, safe_inv_dir(d), olo, ohi, t0, t1, &b0, &b1) || !(b1 > b0)) return;
    /* flux at b0: no medium before t0, the medium's extinction from t0 to b0 */
    float4 F = flux[p] * transmittance(medium->kappa, b0 - t0);
    Pending pd = {-1, (float4)(0.0f), (float4)(0.0f)};
    deposit_segment(x + b0 * d, d, b1 - b0, F, olo, od, oh, okappa, rad, dirs, &pd);
    pending_flush(&pd, rad, dirs);
}

/* Photons on diffuse surfaces, as photon-map records (RayPiece, the photon map's input:
 * clscatter/estimators/ray_density.py): a photon that met a surface in the grid (pos.w = -2:
 * pos the start of that step) or left the grid (pos.w = -1: it goes on straight, the
 * format's "Beyond" rule) is followed along vel to the first surface; where that surface
 * is diffuse one record is appended: a = where the piece starts, b = the hit, the flux
 * arriving (a photon beyond the grid attenuated by the scene medium on the way), end
 * PIECE_DIFFUSE, ray = the photon's index. Mirrors and glass end it (no bounce).
 * straight = 1: the states are photon_emit's (pos.w = 1 where the photon enters the grid)
 * and every entering photon goes on straight through the grid as if it held nothing: the
 * straight light through the grid that the grid's occluder takes from the view paths'
 * shadow rays (the surface photon map's seam correction, pipeline.py). */
__kernel void photon_surface(__global const float4 *pos, __global const float4 *vel,
                             __global const float4 *flux, int count, int light_index,
                             int straight, __global const BVHNode *nodes,
                             __global const float4 *tris, __global const int *tri_mat,
                             __global const Material *materials, __global const Medium *medium,
                             __global RayPiece *pieces, int max_pieces,
                             volatile __global int *piece_count) {
    int p = get_global_id(0);
    if (p >= count) return;
    float4 x = pos[p];
    if (straight ? x.w != 1.0f : (x.w != -1.0f && x.w != -2.0f)) return;
    int beyond = x.w != -2.0f;
    x.w = 0.0f;
    float4 d = normalize3(vel[p]);
    Hit hit;
    if (!bvh_closest(nodes, tris, x, d, 0.0f, T_INF, &hit)) return;
    if (materials[tri_mat[hit.tri]].type != MAT_DIFFUSE) return;
    float4 F = flux[p];
    if (beyond) F *= transmittance(medium->kappa, medium_path_length(medium, x, d, 0.0f, hit.t));
    F.w = 0.0f;
    if (!(fmax(F.x, fmax(F.y, F.z)) > 0.0f)) return;
    int idx = atomic_inc(piece_count);
    if (idx >= max_pieces) return;
    RayPiece rp;
    rp.a = x;
    rp.b = x + hit.t * d;
    rp.b.w = 0.0f;
    rp.flux = F;
    rp.light = light_index;
    rp.depth = 0;
    rp.ray = p;
    rp.branch = 0;
    rp.end = PIECE_DIFFUSE;
    rp.pad0 = rp.pad1 = rp.pad2 = 0;
    pieces[idx] = rp;
}

/* What the grid's occluder takes from diffuse hits, for the surface photon map's seam
 * correction (pipeline.py, seam_correction). For hit i and light li: out[i].xyz = the
 * irradiance the light sends straight to the hit (direct_irradiance's term of view_paths.cl:
 * E cos, the shadow ray, the medium's transmittance from record 0 of `medium`) where its
 * shadow ray crosses the grid box [glo, ghi], else 0; out[i].w = 1 where the shadow ray
 * passes within `delta` of the box's surface (it meets the box grown by delta on every
 * side but not the box shrunk by delta), else 0. */
__kernel void voxel_seam(__global const DiffuseHit *hits, int n, __global const Light *lights,
                         int light_index, __global const BVHNode *nodes,
                         __global const float4 *tris, __global const int *light_grid,
                         __global const Medium *medium, float4 glo, float4 ghi, float delta,
                         __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    DiffuseHit hh = hits[i];
    float4 origin = hh.p + hh.g * surface_offset(hh.p);
    float4 wi;
    float dist, t0, t1;
    float4 E = light_arrival(&lights[light_index], hh.p, &wi, &dist);
    float tmax = dist < T_INF ? dist : T_INF;
    float4 inv = safe_inv_dir(wi);
    float4 dl = (float4)(delta, delta, delta, 0.0f);
    float4 slo = glo + dl, shi = ghi - dl;
    int grown = ray_box(origin, inv, glo - dl, ghi + dl, 0.0f, tmax, &t0, &t1);
    int shrunk = slo.x < shi.x && slo.y < shi.y && slo.z < shi.z &&
                 ray_box(origin, inv, slo, shi, 0.0f, tmax, &t0, &t1);
    int through = ray_box(origin, inv, glo, ghi, 0.0f, tmax, &t0, &t1);
    float c = dot3(hh.n, wi);
    float4 r = (float4)(0.0f);
    if (through && c > 0.0f && dot3(hh.g, wi) > 0.0f)
        r = E * c * voxel_unoccluded(nodes, tris, light_grid, light_index, medium, origin, wi,
                                     dist, 0.0f);
    r.w = grown && !shrunk ? 1.0f : 0.0f;
    out[i] = r;
}

/* Single scattering along view segments outside the grid from the outer grid's light
 * (the light that went through the volumes): midpoint rule at one outer voxel,
 * sigma_s p_HG(mean direction . towards camera) fluence exp(-kappa t), times the
 * segment's weight. */
__kernel void outer_view(__global const ViewSegment *segs, int count, __global const Medium *medium,
                         float4 olo, int4 od, float oh, __global const float4 *rad,
                         __global const float4 *dirs, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= count) return;
    ViewSegment sg = segs[i];
    float4 ab = sg.b - sg.a;
    ab.w = 0.0f;
    float len = length3(ab);
    float4 acc = (float4)(0.0f);
    if (len > 0.0f) {
        float4 w = ab / len;
        int n = max(1, (int)ceil(len / oh));        /* one sample per outer voxel */
        float dt = len / n, inv_h = 1.0f / oh, inv_vol = inv_h * inv_h * inv_h;
        for (int k = 0; k < n; ++k) {
            float t = (k + 0.5f) * dt;
            float4 x = sg.a + t * w;
            x.w = 0.0f;
            Tri tr = tri_setup(x, olo, od, inv_h);
            float4 E = tri_f4(rad, od, &tr) * inv_vol;
            float4 D = tri_f4(dirs, od, &tr);
            float dl = length3(D);
            float ph = dl > 0.0f ? hg_phase(dot3(D / dl, -w), medium->g) : INV_4PI_F;
            acc += E * (ph * dt) * transmittance(medium->kappa, t);
        }
    }
    out[i] = acc * medium->sigma_s * sg.weight;
}

/* -------------------------------------------------------------- viewing pass -- */

/* Curved view rays through the grid at a fixed step of one voxel (sec. 4.5): x' = x +
 * h v/|v|, v' = v + ds grad n. On each step the in-scattered radiance at the step's
 * midpoint, sigma_s p_HG(mean photon direction . towards camera) * fluence, fluence =
 * deposited flux-length / voxel volume, is integrated exactly against the step's
 * transmittance and scaled by (n0 / n)^2, n0 the index where the ray starts (radiance
 * / n^2 is invariant along the ray: light scattered inside glass of index 1.5 reaches the
 * camera in air at 1 / 2.25 of its radiance there, times the transmittance). A ray ends where it leaves the grid (rays_out: the continuing ray, just
 * outside, with its throughput) or at a surface (rays_out from the step's start with
 * flags |= VOX_SKIP_FIRST: the straight tracer takes the surface from there, the piece up
 * to it already integrated here). radiance[r] is the ray's in-scattered light (weighted
 * by its throughput). grad n is the interior gradient: where the ray meets a volume's
 * sharp boundary the step is cut there and the ray is refracted by Snell's law, its
 * throughput multiplied by the Fresnel transmittance (vox_cut, vox_cross, as for photons;
 * the reflected branch is not followed), or turned back by total internal reflection,
 * which counts as a specular bounce in the ray's depth (the ray ends, dropped, at
 * max_depth). */
__kernel void voxel_view_march(__global const VoxRay *rays, int count, float4 glo, float4 ghi,
                               int4 dims, float h, __global const float *n_grid,
                               __global const float4 *grad, __global const float4 *sigma_s,
                               __global const float4 *kappa, __global const float4 *rad,
                               __global const float4 *dirs, float g_phase, int max_steps,
                               __global const BVHNode *nodes, __global const float4 *tris,
                               int test_surfaces, __global const float4 *boundary,
                               int max_depth, __global float4 *radiance,
                               __global VoxRay *rays_out) {
    int r = get_global_id(0);
    if (r >= count) return;
    VoxRay ray = rays[r];
    float4 x = ray.o, thr = ray.thr;
    x.w = 0.0f;
    float inv_h = 1.0f / h, inv_vol = inv_h * inv_h * inv_h;
    Tri tr0 = tri_setup(x, glo, dims, inv_h);
    float n0 = tri_f(n_grid, dims, &tr0);   /* the index where the ray starts (the camera's) */
    float4 v = n0 * ray.d;
    v.w = 0.0f;
    float4 L = (float4)(0.0f);
    int ended = 0;
    float4 dir = ray.d;
    float side = -1.0f;
    for (int s = 0; s < max_steps; ++s) {
        Tri tr = tri_setup(x, glo, dims, inv_h);
        float n = tri_f(n_grid, dims, &tr);
        float4 g = tri_f4(grad, dims, &tr);
        float w0 = tri_f4(boundary, dims, &tr).x;
        if (side < 0.0f) side = w0 >= 0.5f ? 1.0f : 0.0f;
        float vl = length3(v);
        if (!(vl > 0.0f)) break;
        dir = v / vl;
        dir.w = 0.0f;
        float len = fmin(h, box_exit(x, dir, glo, ghi));
        int leave = len < h;
        int surf = 0;
        if (test_surfaces) {
            Hit hit;
            if (bvh_closest(nodes, tris, x, dir, 0.0f, len, &hit)) { len = hit.t; surf = 1; }
        }
        /* a boundary on the way: the step ends where the ray meets it */
        float w1 = vox_side_at(boundary, dims, x + len * dir, glo, inv_h).x;
        float cut = vox_cut_refine(boundary, dims, x, dir, len, w0, w1, vox_cut(w0, w1, side),
                                   glo, inv_h);
        if (cut >= 0.0f && cut < 1.0f) { len *= cut; leave = 0; surf = 0; }
        float4 m = x + 0.5f * len * dir;
        Tri tm = tri_setup(m, glo, dims, inv_h);
        float4 ss = tri_f4(sigma_s, dims, &tm), kp = tri_f4(kappa, dims, &tm);
        float4 E = tri_f4(rad, dims, &tm) * inv_vol;
        float4 D = tri_f4(dirs, dims, &tm);
        float dl = length3(D);
        float ph = dl > 0.0f ? hg_phase(dot3(D / dl, -dir), g_phase) : INV_4PI_F;
        float4 Tp = exp3(-kp * len);
        float4 integ;
        integ.x = kp.x * len > 1e-4f ? (1.0f - Tp.x) / kp.x : len;
        integ.y = kp.y * len > 1e-4f ? (1.0f - Tp.y) / kp.y : len;
        integ.z = kp.z * len > 1e-4f ? (1.0f - Tp.z) / kp.z : len;
        integ.w = 0.0f;
        /* radiance / n^2 is what a ray carries unchanged (through graded index and, times
         * the Fresnel transmittance, across a boundary): light scattered where the index
         * is n_m arrives where the ray started scaled by (n0 / n_m)^2 */
        float nm = tri_f(n_grid, dims, &tm), rel_n = n0 / nm;
        L += thr * ss * E * ph * integ * (rel_n * rel_n);
        if (surf) {
            /* hand the surface to the straight tracer: from x along dir, no medium on
             * the way (integrated here up to the hit) */
            ray.o = x;
            ray.d = dir;
            ray.flags |= VOX_SKIP_FIRST;
            thr *= Tp;
            ended = 1;
            break;
        }
        thr *= Tp;
        x += len * dir;
        x.w = 0.0f;
        if (leave) {
            ray.o = x + 2.0f * RAY_EPS * dir;   /* just outside, so it is not stopped again */
            ray.o.w = 0.0f;
            ray.d = dir;
            ended = 1;
            break;
        }
        v += (len * n / vl) * g;
        v.w = 0.0f;
        if (cut >= 0.0f) {
            int turned;
            thr *= vox_cross(boundary, dims, x, glo, h, &v, &side, &turned);
            if (turned) {                       /* a specular bounce: the path's depth */
                ray.flags += 1 << 4;
                if ((ray.flags >> 4) >= max_depth) break;
            }
        }
    }
    if (!ended) thr = (float4)(0.0f);       /* ran out of steps: drop the remainder */
    thr.w = 0.0f;
    ray.thr = thr;
    radiance[r] = L;
    rays_out[r] = ray;
}

/* The throughput filter between the viewing pass and the straight tracer: keep[r] = 1
 * where ray r still carries light (largest rgb throughput above min_thr, view_paths.cl's
 * MIN_THROUGHPUT per sample), else 0. The host compacts the rays by these flags on the
 * device (clscatter/primitives.py: compact). */
__kernel void vox_keep_flags(__global const VoxRay *rays, int count, float min_thr,
                             __global int *keep) {
    int r = get_global_id(0);
    if (r >= count) return;
    float4 t = rays[r].thr;
    keep[r] = fmax(t.x, fmax(t.y, t.z)) > min_thr ? 1 : 0;
}

/* ------------------------------------------------- straight paths outside the grid -- */

/* Follow one branch tree exactly as trace_view does (view_paths.cl), except that a
 * branch outside every object whose straight ray enters the grid box (gmin, gmax) before
 * its next surface stops there: its medium piece and attenuation end at the box, and it
 * is appended to `stopped` for the viewing pass. The first branch may carry
 * VOX_SKIP_FIRST: its first piece was integrated by the viewing pass (no medium piece,
 * no attenuation, no stop). Returns the directly lit surface radiance; with want_hits
 * every diffuse hit is also appended to `hits` (append_diffuse_hit of view_paths.cl), where
 * the surface photons' estimate is added. */
float4 voxel_follow(Branch first, int first_flags, int pixel, int sample, int depth_limit,
                    __global const BVHNode *nodes, __global const float4 *tris,
                    __global const int *light_grid, __global const int *camera_grid,
                    __global const float4 *normals, __global const int *tri_mat,
                    __global const Material *materials, __global const Light *lights,
                    int num_lights, __global const Medium *medium, float4 gmin, float4 gmax,
                    float min_weight, __global ViewSegment *segs, int max_segs,
                    volatile __global int *seg_count, __global VoxRay *stopped, int max_stopped,
                    volatile __global int *stop_count, int want_hits, __global DiffuseHit *hits,
                    int max_hits, volatile __global int *hit_count) {
    Branch stack[PATH_STACK];
    stack[0] = first;
    int top = 1, next_id = first.id + 1;
    int skip = first_flags & VOX_SKIP_FIRST;
    float4 radiance = (float4)(0.0f);
    while (top > 0) {
        Branch br = stack[--top];
        Hit hit;
        int found = br.id == 0      /* a camera ray (trace_view's rule) */
            ? scene_closest(nodes, tris, camera_grid, br.o, br.d, 0.0f, T_INF, &hit)
            : bvh_closest(nodes, tris, br.o, br.d, 0.0f, T_INF, &hit);
        float t_hit = found ? hit.t : T_INF;
        float tb0, tb1;
        int stop = !skip && br.inside < 0 &&
                   ray_box(br.o, safe_inv_dir(br.d), gmin, gmax, 0.0f, t_hit, &tb0, &tb1);
        float t_end = stop ? tb0 : t_hit;
        float4 a, b;
        if (!skip && medium_piece(medium, &br, t_end, &a, &b))
            append_view_segment(segs, max_segs, seg_count, a, b, &br, pixel, sample);
        if (!skip && (stop || found)) br.thr *= branch_attenuation(medium, materials, &br, t_end);
        skip = 0;
        if (stop) {
            int idx = atomic_inc(stop_count);
            if (idx < max_stopped) {
                VoxRay vr;
                vr.o = br.o + tb0 * br.d;
                vr.o.w = 0.0f;
                vr.d = br.d;
                vr.thr = br.thr;
                vr.pixel = pixel; vr.sample = sample; vr.branch = br.id;
                vr.flags = br.depth << 4;     /* depth above the flag bits */
                stopped[idx] = vr;
            }
            continue;
        }
        if (!found) continue;
        SurfaceFrame f;
        int mi;
        if (surface_hit(tris, normals, tri_mat, materials, &hit, &br, depth_limit, min_weight,
                        stack, &top, &next_id, &f, &mi)) {
            radiance += br.thr * shade_diffuse(nodes, tris, light_grid, lights, num_lights,
                                               medium, f.p, f.nf, f.gf, materials[mi].color);
            if (want_hits)      /* the photons' light is added there (surface photon map) */
                append_diffuse_hit(hits, max_hits, hit_count, &f, materials[mi].color, &br,
                                   pixel, sample);
        }
    }
    return radiance;
}

/* Camera samples [sample_offset, + num_samples): the same rays as trace_view. */
__kernel void voxel_trace_camera(__global const BVHNode *nodes, __global const float4 *tris,
                                 __global const int *light_grid, __global const int *camera_grid,
                                 __global const float4 *normals, __global const int *tri_mat,
                                 __global const Material *materials,
                                 __global const Light *lights, int num_lights,
                                 __global const Medium *medium, __global const Camera *cam,
                                 int max_depth, uint seed, int sample_offset, int num_samples,
                                 float4 gmin, float4 gmax, __global float4 *surface,
                                 __global VoxRay *stopped, int max_stopped,
                                 volatile __global int *stop_count,
                                 __global ViewSegment *segs, int max_segs,
                                 volatile __global int *seg_count, int want_hits,
                                 __global DiffuseHit *hits, int max_hits,
                                 volatile __global int *hit_count) {
    int gid = get_global_id(0);
    if (gid >= num_samples) return;
    int s = sample_offset + gid, pixel;
    float inv_spp = 1.0f / cam->spp;
    Branch b = camera_branch(cam, seed, s, &pixel);
    surface[gid] = voxel_follow(b, 0, pixel, s, max_depth, nodes, tris, light_grid, camera_grid,
                                normals, tri_mat,
                                materials, lights, num_lights, medium, gmin, gmax,
                                MIN_THROUGHPUT * inv_spp, segs, max_segs, seg_count, stopped,
                                max_stopped, stop_count, want_hits, hits, max_hits, hit_count);
}

/* Continue the rays the viewing pass handed back (leaving the grid or meeting a surface).
 * Branch ids continue from the ray's id times 64 so (sample, branch) stays unique. */
__kernel void voxel_trace_rays(__global const BVHNode *nodes, __global const float4 *tris,
                               __global const int *light_grid, __global const int *camera_grid,
                               __global const float4 *normals, __global const int *tri_mat,
                               __global const Material *materials,
                               __global const Light *lights, int num_lights,
                               __global const Medium *medium, int max_depth, float min_weight,
                               __global const VoxRay *rays, int count, float4 gmin, float4 gmax,
                               __global float4 *surface,
                               __global VoxRay *stopped, int max_stopped,
                               volatile __global int *stop_count,
                               __global ViewSegment *segs, int max_segs,
                               volatile __global int *seg_count, int want_hits,
                               __global DiffuseHit *hits, int max_hits,
                               volatile __global int *hit_count) {
    int gid = get_global_id(0);
    if (gid >= count) return;
    VoxRay r = rays[gid];
    Branch b;
    b.o = r.o; b.d = r.d; b.thr = r.thr;
    b.depth = r.flags >> 4; b.inside = -1; b.id = r.branch * 64 + 1; b.pad = 0;
    if (fmax(b.thr.x, fmax(b.thr.y, b.thr.z)) <= 0.0f) { surface[gid] = (float4)(0.0f); return; }
    surface[gid] = voxel_follow(b, r.flags & 15, r.pixel, r.sample, max_depth, nodes, tris,
                                light_grid, camera_grid,
                                normals, tri_mat, materials, lights, num_lights, medium, gmin,
                                gmax, min_weight, segs, max_segs, seg_count, stopped, max_stopped,
                                stop_count, want_hits, hits, max_hits, hit_count);
}
