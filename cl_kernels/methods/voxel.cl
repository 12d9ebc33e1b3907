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
 *   oct_reduce, oct_levels       min/max pyramid, dense octree level grid, step limits
 *   photon_emit, photon_march    photons where light enters the grid; adaptive marching
 *                                with line-segment deposition (3-D DDA, float CAS atomics)
 *   voxel_view_march             curved view rays at a fixed one-voxel step
 *   voxel_trace_camera/_rays     straight view paths outside the grid (includes view_paths.cl)
 */
#include "voxel.h"
#include "density.h"

/* Surfaces lit through density grids: in a scene with density volumes the straight
 * tracers get density.h's medium buffer (its Medium record first, so everything else reads
 * it as before), and their shadow rays are attenuated through the grids (smoke's shadows);
 * with the plain Medium record (no MEDIUM_DENSITY bit) they are the engine's. */
float4 voxel_shadow(__global const BVHNode *nodes, __global const float4 *tris,
                    __global const int *light_grid, int li, __global const Medium *m,
                    float4 x, float4 wi, float dist, float tmin) {
    if (m->present & MEDIUM_DENSITY)
        return density_light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
    return light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin);
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

/* ------------------------------------------------ Fresnel at smoothed boundaries -- */

/* Transmittance of a sharp dielectric interface from index n1 to n2 at incidence cosine
 * cos_i (unpolarised: 1 minus the mean of the s and p reflectances, specular.h's
 * fresnel_dielectric); 0 under total internal reflection. 1 when the indices differ by
 * less than VOX_DN_MIN (no interface: such a step reflects below 2e-7 at normal
 * incidence). */
#define VOX_DN_MIN 1e-3f
float vox_fresnel_t(float n1, float n2, float cos_i) {
    if (fabs(n1 - n2) < VOX_DN_MIN) return 1.0f;
    float ct;
    return 1.0f - fresnel_dielectric(clamp(cos_i, 0.0f, 1.0f), n1 / n2, &ct);
}

/* Crossing a smoothed boundary. A voxelised volume's index rises from the outside's to
 * the inside's over a band of voxels (its blurred coverage w), and the ray equation bends
 * paths through the band as Snell's law would at the sharp boundary, which lies where
 * w = 1/2. The boundary grid holds per voxel (w, n_lo, n_hi, 0): the blurred weight of
 * the volume with the largest weight there and the indices on its outer (w -> 0) and
 * inner (w -> 1) sides (equal where no volume is near: nothing to cross); trilinear like
 * every field. A path's crossing state is w at its previous step start (-1: none yet).
 * When w passes 1/2 between two step starts the path has crossed the boundary from
 * n1 to n2 (n_lo -> n_hi going in, n_hi -> n_lo going out), and keeps the transmittance
 * of the sharp interface, vox_fresnel_t(n1, n2, cos_i), once. The incidence comes from
 * the ray equation's invariant across a layered index: the component of v (= n x unit
 * direction) across grad n, k = |v x g| / |g| = n sin(theta), is the same on both sides,
 * so sin(theta_i) = k / n1. A path with k >= min(n1, n2) cannot exist on the lower-index
 * side: it is one that the band turns back (the continuous version of total internal
 * reflection; it crosses 1/2 out and back in, or not at all) and it keeps everything, as
 * total internal reflection does. Returns the factor for the path's flux / throughput. */
float vox_crossing(float *w_prev, float4 side, float4 v, float4 g) {
    float T = 1.0f;
    float w = side.x;
    if (*w_prev >= 0.0f && (*w_prev < 0.5f) != (w < 0.5f)) {
        int entering = w >= 0.5f;
        float n1 = entering ? side.y : side.z, n2 = entering ? side.z : side.y;
        float gl = length3(g);
        float k = gl > 0.0f ? length3(cross(v, g)) / gl : 0.0f;
        if (k < fmin(n1, n2)) {
            float s = k / n1;
            T = vox_fresnel_t(n1, n2, sqrt(fmax(0.0f, 1.0f - s * s)));
        }
    }
    *w_prev = w;
    return T;
}

/* Test hook: vox_crossing along given paths. Path p has `len` step starts; at step i its
 * sampled (w, n_lo, n_hi) is side[p * len + i], its v and grad n v[.], g[.]; out[p] is the
 * product of the factors (the flux the path keeps). */
__kernel void vox_crossing_test(__global const float4 *side, __global const float4 *v,
                                __global const float4 *g, int count, int len,
                                __global float *out) {
    int p = get_global_id(0);
    if (p >= count) return;
    float w_prev = -1.0f, T = 1.0f;
    for (int i = 0; i < len; ++i) {
        int k = p * len + i;
        float4 vv = v[k], gg = g[k];
        vv.w = 0.0f;
        gg.w = 0.0f;
        T *= vox_crossing(&w_prev, side[k], vv, gg);
    }
    out[p] = T;
}

/* Test hook: vox_fresnel_t for arrays (n1, n2, cos_i) in xyz of each float4. */
__kernel void vox_fresnel_test(__global const float4 *cases, int count, __global float *out) {
    int i = get_global_id(0);
    if (i >= count) return;
    out[i] = vox_fresnel_t(cases[i].x, cases[i].y, cases[i].z);
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
 * Where a photon crosses a volume's smoothed boundary (grid `boundary`, vox_crossing; its
 * crossing state kept in crossing[p] between launches, -1 at the start) its flux is
 * multiplied by the Fresnel transmittance of the crossing; the reflected part is dropped.
 * pos.w afterwards: 1 live, 0 ended (surface, faded out), -1 left through a grid face (the
 * straight light beyond the grid: photon_exits). 
 * adaptive = 0 gives the fixed-step marcher (s = ds_min everywhere). */
__kernel void photon_march(__global float4 *pos, __global float4 *vel, __global float4 *flux,
                           int count, int steps, float4 glo, float4 ghi, int4 dims, float h,
                           __global const float *n_grid, __global const float4 *grad,
                           __global const float4 *kappa, __global const uchar *level,
                           __global const float *smax, int adaptive, float ds_min, float min_rel,
                           __global const BVHNode *nodes, __global const float4 *tris,
                           int test_surfaces, __global const float4 *boundary,
                           __global float *crossing, volatile __global float *rad,
                           volatile __global float *dirs, volatile __global int *counters) {
    int p = get_global_id(0);
    if (p >= count) return;
    float4 x = pos[p];
    if (x.w != 1.0f) return;
    x.w = 0.0f;
    float4 v = vel[p], F = flux[p];
    float xing = crossing[p];
    float inv_h = 1.0f / h;
    int alive = 1, taken = 0;
    float state = 1.0f;
    Pending pd = {-1, (float4)(0.0f), (float4)(0.0f)};
    for (int s = 0; s < steps && alive; ++s) {
        Tri tr = tri_setup(x, glo, dims, inv_h);
        float n = tri_f(n_grid, dims, &tr);
        float4 g = tri_f4(grad, dims, &tr);
        float vl = length3(v);
        if (!(vl > 0.0f)) { alive = 0; break; }
        float4 dir = v / vl;
        dir.w = 0.0f;
        F.xyz *= vox_crossing(&xing, tri_f4(boundary, dims, &tr), v, g);   /* Fresnel */
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
        float ds = step * n / vl;
        float len = fmin(step, box_exit(x, dir, glo, ghi));
        int stop = len < step;
        state = stop ? 2.0f : 1.0f;               /* 2: leaves through a grid face */
        if (test_surfaces) {
            Hit hit;
            if (bvh_closest(nodes, tris, x, dir, 0.0f, len, &hit)) { len = hit.t; stop = 1; state = 0.0f; }
        }
        float4 T = deposit_segment(x, dir, len, F, glo, dims, h, kappa, rad, dirs, &pd);
        F *= T;
        F.w = flux[p].w;
        x += len * dir;
        v += ds * g;
        v.w = 0.0f;
        ++taken;
        if (stop || fmax(F.x, fmax(F.y, F.z)) < min_rel * F.w) alive = 0;
        if (!stop && !alive) state = 0.0f;        /* faded out */
    }
    pending_flush(&pd, rad, dirs);
    crossing[p] = xing;
    pos[p] = (float4)(x.x, x.y, x.z, alive ? 1.0f : (state == 2.0f ? -1.0f : 0.0f));
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
 * transmittance. A ray ends where it leaves the grid (rays_out: the continuing ray, just
 * outside, with its throughput) or at a surface (rays_out from the step's start with
 * flags |= VOX_SKIP_FIRST: the straight tracer takes the surface from there, the piece up
 * to it already integrated here). radiance[r] is the ray's in-scattered light (weighted
 * by its throughput). Where the ray crosses a volume's smoothed boundary its throughput
 * is multiplied by the Fresnel transmittance of the crossing (vox_crossing, as for
 * photons); the reflected branch is not followed. */
__kernel void voxel_view_march(__global const VoxRay *rays, int count, float4 glo, float4 ghi,
                               int4 dims, float h, __global const float *n_grid,
                               __global const float4 *grad, __global const float4 *sigma_s,
                               __global const float4 *kappa, __global const float4 *rad,
                               __global const float4 *dirs, float g_phase, int max_steps,
                               __global const BVHNode *nodes, __global const float4 *tris,
                               int test_surfaces, __global const float4 *boundary,
                               __global float4 *radiance, __global VoxRay *rays_out) {
    int r = get_global_id(0);
    if (r >= count) return;
    VoxRay ray = rays[r];
    float4 x = ray.o, thr = ray.thr;
    x.w = 0.0f;
    float inv_h = 1.0f / h, inv_vol = inv_h * inv_h * inv_h;
    Tri tr0 = tri_setup(x, glo, dims, inv_h);
    float4 v = tri_f(n_grid, dims, &tr0) * ray.d;
    v.w = 0.0f;
    float4 L = (float4)(0.0f);
    int ended = 0;
    float4 dir = ray.d;
    float xing = -1.0f;
    for (int s = 0; s < max_steps; ++s) {
        Tri tr = tri_setup(x, glo, dims, inv_h);
        float n = tri_f(n_grid, dims, &tr);
        float4 g = tri_f4(grad, dims, &tr);
        float vl = length3(v);
        if (!(vl > 0.0f)) break;
        dir = v / vl;
        dir.w = 0.0f;
        thr *= vox_crossing(&xing, tri_f4(boundary, dims, &tr), v, g);   /* Fresnel */
        float len = fmin(h, box_exit(x, dir, glo, ghi));
        int leave = len < h;
        int surf = 0;
        if (test_surfaces) {
            Hit hit;
            if (bvh_closest(nodes, tris, x, dir, 0.0f, len, &hit)) { len = hit.t; surf = 1; }
        }
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
        L += thr * ss * E * ph * integ;
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
        v += (h * n / vl) * g;
        v.w = 0.0f;
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
 * no attenuation, no stop). Returns the directly lit surface radiance. */
float4 voxel_follow(Branch first, int first_flags, int pixel, int sample, int depth_limit,
                    __global const BVHNode *nodes, __global const float4 *tris,
                    __global const int *light_grid, __global const int *camera_grid,
                    __global const float4 *normals, __global const int *tri_mat,
                    __global const Material *materials, __global const Light *lights,
                    int num_lights, __global const Medium *medium, float4 gmin, float4 gmax,
                    float min_weight, __global ViewSegment *segs, int max_segs,
                    volatile __global int *seg_count, __global VoxRay *stopped, int max_stopped,
                    volatile __global int *stop_count) {
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
                        stack, &top, &next_id, &f, &mi))
            radiance += br.thr * shade_diffuse(nodes, tris, light_grid, lights, num_lights,
                                               medium, f.p, f.nf, f.gf, materials[mi].color);
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
                                 volatile __global int *seg_count) {
    int gid = get_global_id(0);
    if (gid >= num_samples) return;
    int s = sample_offset + gid, pixel;
    float inv_spp = 1.0f / cam->spp;
    Branch b = camera_branch(cam, seed, s, &pixel);
    surface[gid] = voxel_follow(b, 0, pixel, s, max_depth, nodes, tris, light_grid, camera_grid,
                                normals, tri_mat,
                                materials, lights, num_lights, medium, gmin, gmax,
                                MIN_THROUGHPUT * inv_spp, segs, max_segs, seg_count, stopped,
                                max_stopped, stop_count);
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
                               volatile __global int *seg_count) {
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
                                stop_count);
}
