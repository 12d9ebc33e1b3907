/* light_paths.cl: lighting rays from one light through specular chains.
 *
 * One work-item per lighting ray. Directions (point: the sphere; spot: its cone) or
 * start positions (directional: a rectangle facing the light that covers the region of
 * interest) come from a Hammersley point set with a per-light random rotation
 * (Cranley-Patterson), so N rays are stratified for any N. Every ray carries the same
 * flux, flux_per_ray = emitted power / N, computed on the host (clscatter/light_paths.py).
 * Mirrors and dielectrics split the ray deterministically (specular.h); diffuse and black
 * surfaces end it (single scattering: no diffuse bounce lights the medium). Every
 * straight piece inside the medium is appended to the LightSegment buffer (built with
 * SEGMENT_REGIONS = 3, the pieces inside glass that scatters too, tagged: see below).
 *
 * Targeted emission (num_targets > 0; clscatter/emission.py derives the maths): a point
 * or spot light's rays are drawn in cones around the specular objects' bounding spheres
 * and weighted by the balance-heuristic mixture pdf; ray_flags[gid] = 1 when the ray's
 * first hit is a mirror or dielectric (statistics). num_targets = 0: as before.
 *
 * Built with -DRAY_PIECES the same kernel appends RayPiece records instead (common.h):
 * the piece on which each branch ends (a diffuse or black surface, or leaving the scene
 * box) with the flux arriving there; the surface-caustic methods read these.
 */
#include "common.h"
#include "bvh.h"
#include "specular.h"

#ifndef PATH_STACK
#define PATH_STACK 16
#endif
#ifdef RAY_PIECES
#define LIGHT_RECORD RayPiece
#else
#define LIGHT_RECORD LightSegment
#endif
/* which pieces trace_light appends as LightSegments (bits): 1 the pieces in the scene
 * medium, 2 the pieces inside dielectrics whose interior scatters (specular.h,
 * interior_piece: tagged with the material in a.w, flux at a; line space gathering) */
#ifndef SEGMENT_REGIONS
#define SEGMENT_REGIONS 1
#endif

/* Append the piece [a, b] of branch br of lighting ray `ray` of light `light`. */
void append_light_segment(__global LightSegment *segs, int max_segs, volatile __global int *count,
                          float4 a, float4 b, const Branch *br, int light, int ray) {
    int idx = atomic_inc(count);
    if (idx < max_segs) {
        LightSegment sg;
        sg.a = a;
        sg.b = b;
        sg.flux = br->thr;
        sg.light = light;
        sg.depth = br->depth;
        sg.ray = ray;
        sg.branch = br->id;
        segs[idx] = sg;
    }
}

/* Each byte with its bits reversed. */
__constant uchar REVERSED_BYTE[256] = {
    0x00, 0x80, 0x40, 0xc0, 0x20, 0xa0, 0x60, 0xe0, 0x10, 0x90, 0x50, 0xd0,
    0x30, 0xb0, 0x70, 0xf0, 0x08, 0x88, 0x48, 0xc8, 0x28, 0xa8, 0x68, 0xe8,
    0x18, 0x98, 0x58, 0xd8, 0x38, 0xb8, 0x78, 0xf8, 0x04, 0x84, 0x44, 0xc4,
    0x24, 0xa4, 0x64, 0xe4, 0x14, 0x94, 0x54, 0xd4, 0x34, 0xb4, 0x74, 0xf4,
    0x0c, 0x8c, 0x4c, 0xcc, 0x2c, 0xac, 0x6c, 0xec, 0x1c, 0x9c, 0x5c, 0xdc,
    0x3c, 0xbc, 0x7c, 0xfc, 0x02, 0x82, 0x42, 0xc2, 0x22, 0xa2, 0x62, 0xe2,
    0x12, 0x92, 0x52, 0xd2, 0x32, 0xb2, 0x72, 0xf2, 0x0a, 0x8a, 0x4a, 0xca,
    0x2a, 0xaa, 0x6a, 0xea, 0x1a, 0x9a, 0x5a, 0xda, 0x3a, 0xba, 0x7a, 0xfa,
    0x06, 0x86, 0x46, 0xc6, 0x26, 0xa6, 0x66, 0xe6, 0x16, 0x96, 0x56, 0xd6,
    0x36, 0xb6, 0x76, 0xf6, 0x0e, 0x8e, 0x4e, 0xce, 0x2e, 0xae, 0x6e, 0xee,
    0x1e, 0x9e, 0x5e, 0xde, 0x3e, 0xbe, 0x7e, 0xfe, 0x01, 0x81, 0x41, 0xc1,
    0x21, 0xa1, 0x61, 0xe1, 0x11, 0x91, 0x51, 0xd1, 0x31, 0xb1, 0x71, 0xf1,
    0x09, 0x89, 0x49, 0xc9, 0x29, 0xa9, 0x69, 0xe9, 0x19, 0x99, 0x59, 0xd9,
    0x39, 0xb9, 0x79, 0xf9, 0x05, 0x85, 0x45, 0xc5, 0x25, 0xa5, 0x65, 0xe5,
    0x15, 0x95, 0x55, 0xd5, 0x35, 0xb5, 0x75, 0xf5, 0x0d, 0x8d, 0x4d, 0xcd,
    0x2d, 0xad, 0x6d, 0xed, 0x1d, 0x9d, 0x5d, 0xdd, 0x3d, 0xbd, 0x7d, 0xfd,
    0x03, 0x83, 0x43, 0xc3, 0x23, 0xa3, 0x63, 0xe3, 0x13, 0x93, 0x53, 0xd3,
    0x33, 0xb3, 0x73, 0xf3, 0x0b, 0x8b, 0x4b, 0xcb, 0x2b, 0xab, 0x6b, 0xeb,
    0x1b, 0x9b, 0x5b, 0xdb, 0x3b, 0xbb, 0x7b, 0xfb, 0x07, 0x87, 0x47, 0xc7,
    0x27, 0xa7, 0x67, 0xe7, 0x17, 0x97, 0x57, 0xd7, 0x37, 0xb7, 0x77, 0xf7,
    0x0f, 0x8f, 0x4f, 0xcf, 0x2f, 0xaf, 0x6f, 0xef, 0x1f, 0x9f, 0x5f, 0xdf,
    0x3f, 0xbf, 0x7f, 0xff
};

/* The base-2 radical inverse (van der Corput) of i to 24 bits: the low three bytes of i,
 * bit-reversed, as a fraction. Reversed by a byte table rather than the usual
 * shift-and-mask cascade, which compilers turn into a bit-reverse intrinsic that not
 * every OpenCL implementation provides. */
float radical_inverse2(uint i) {
    uint r = ((uint)REVERSED_BYTE[i & 0xFFu] << 16) | ((uint)REVERSED_BYTE[(i >> 8) & 0xFFu] << 8)
             | (uint)REVERSED_BYTE[(i >> 16) & 0xFFu];
    return (float)r * (1.0f / 16777216.0f);
}

/* Any unit vectors t, b completing n to an orthonormal basis (Duff et al. 2017). */
void basis(float4 n, float4 *t, float4 *b) {
    float s = n.z >= 0.0f ? 1.0f : -1.0f;
    float a = -1.0f / (s + n.z);
    float c = n.x * n.y * a;
    *t = (float4)(1.0f + s * n.x * n.x * a, s * c, -s * n.x, 0.0f);
    *b = (float4)(c, s + n.y * n.y * a, -n.y, 0.0f);
}

__kernel void trace_light(__global const BVHNode *nodes, __global const float4 *tris,
                          __global const float4 *normals, __global const int *tri_mat,
                          __global const Material *materials,
                          __global const Light *lights, int light_index,
                          __global const Medium *medium, int max_depth, uint seed,
                          int ray_offset, int ray_stride, int num_rays, int rays_total,
                          float4 flux_per_ray,
                          float4 rect_origin, float4 rect_u, float4 rect_v,
                          __global const float4 *targets, __global const int *target_offsets,
                          int num_targets, __global int *ray_flags,
                          __global LIGHT_RECORD *segs, int max_segs,
                          volatile __global int *seg_count) {
    int gid = get_global_id(0);
    if (gid >= num_rays) return;
    int ray = ray_offset + gid * ray_stride;   /* ray_stride > 1: an interleaved chunk */
    __global const Light *L = &lights[light_index];
    Rng rot = rng_seed(seed, (uint)light_index, 0x9e3779b9u);   /* same rotation for all rays */
    /* targeted emission (num_targets > 0, point/spot; clscatter/emission.py): rays
     * [target_offsets[k], target_offsets[k+1]) are stratified in cone k = targets[k]
     * (axis xyz, w = 1 - cos half-angle) */
    int k = -1, ray_k = ray, n_local = rays_total;
    if (num_targets > 0 && L->type != LIGHT_DIRECTIONAL) {
        k = 0;
        while (k + 1 < num_targets && ray >= target_offsets[k + 1]) ++k;
        ray_k = ray - target_offsets[k];
        n_local = target_offsets[k + 1] - target_offsets[k];
    }
    float u = (ray_k + 0.5f) / n_local + rng_next(&rot);
    float v = radical_inverse2((uint)ray_k) + rng_next(&rot);
    u -= floor(u);
    v -= floor(v);

    Branch stack[PATH_STACK];
    Branch first;
    if (L->type == LIGHT_DIRECTIONAL) {
        first.o = rect_origin + u * rect_u + v * rect_v;
        first.d = L->direction;
    } else {
        float z = L->type == LIGHT_SPOT ? 1.0f - u * (1.0f - L->cos_cutoff) : 1.0f - 2.0f * u;
        float r = sqrt(fmax(0.0f, 1.0f - z * z));
        float phi = 2.0f * PI_F * v;
        float4 axis = L->type == LIGHT_SPOT ? L->direction : (float4)(0.0f, 0.0f, 1.0f, 0.0f);
        if (k >= 0) {
            /* s = 1 - z from the cone's 1 - cos: sin = sqrt(s (2 - s)) stays accurate for
             * narrow cones, where 1 - z*z would cancel to a few ulps */
            float s = u * targets[k].w;
            z = 1.0f - s;
            r = sqrt(fmax(0.0f, s * (2.0f - s)));
            axis = targets[k];
            axis.w = 0.0f;
        }
        float4 t, b;
        basis(axis, &t, &b);
        first.o = L->position;
        first.d = normalize3(r * cos(phi) * t + r * sin(phi) * b + z * axis);
    }
    first.o.w = 0.0f;
    first.thr = flux_per_ray;
    if (k >= 0) {
        /* flux_per_ray holds the intensity I: a ray carries I / (N pdf) with the balance-
         * heuristic mixture density sum_j n_j [w in cone j] / Omega_j (its own cone always
         * counts: the boundary test may round either way, on a set of measure zero) */
        if (L->type == LIGHT_SPOT && dot3(first.d, L->direction) < L->cos_cutoff) {
            ray_flags[gid] = 0;
            return;                               /* outside the spot: no light */
        }
        float dens = 0.0f;
        for (int j = 0; j < num_targets; ++j) {
            float4 c = targets[j];
            float hit_j = j == k || dot3(first.d, c) >= 1.0f - c.w;   /* c.w: 1 - cos */
            dens += hit_j * (float)(target_offsets[j + 1] - target_offsets[j]) / (2.0f * PI_F * c.w);
        }
        first.thr = flux_per_ray / dens;
    }
    first.depth = 0;
    first.inside = -1;
    first.id = 0;
    first.pad = 0;
    stack[0] = first;
    int top = 1, next_id = 1;
    float min_flux = 1e-4f * fmax(first.thr.x, fmax(first.thr.y, first.thr.z));
    int flag = 0;                                 /* first hit specular (statistics) */

    while (top > 0) {
        Branch br = stack[--top];
        Hit hit;
        int found = bvh_closest(nodes, tris, br.o, br.d, 0.0f, T_INF, &hit);
        float t_hit = found ? hit.t : T_INF;
#ifdef RAY_PIECES
        if (br.inside < 0) {
            /* does the branch end here? diffuse/black hit, or escape through the scene box */
            int end = -1;
            float t_end = t_hit;
            if (found) {
                int mt = materials[tri_mat[hit.tri]].type;
                end = mt == MAT_DIFFUSE ? PIECE_DIFFUSE : mt == MAT_BLACK ? PIECE_BLACK : -1;
            } else {
                float4 lo = (float4)(nodes[0].bmin[0], nodes[0].bmin[1], nodes[0].bmin[2], 0.0f);
                float4 hi = (float4)(nodes[0].bmax[0], nodes[0].bmax[1], nodes[0].bmax[2], 0.0f);
                float t0, t1;
                if (ray_box(br.o, safe_inv_dir(br.d), lo, hi, 0.0f, T_INF, &t0, &t1) && t1 > 0.0f) {
                    end = PIECE_ESCAPED;
                    t_end = t1;
                }
            }
            if (end >= 0) {
                int idx = atomic_inc(seg_count);
                if (idx < max_segs) {
                    RayPiece pc;
                    pc.a = br.o;
                    pc.b = br.o + t_end * br.d;
                    pc.a.w = 0.0f;
                    pc.b.w = 0.0f;
                    pc.flux = br.thr * branch_attenuation(medium, materials, &br, t_end);
                    pc.light = light_index;
                    pc.depth = br.depth;
                    pc.ray = ray;
                    pc.branch = br.id;
                    pc.end = end;
                    pc.pad0 = pc.pad1 = pc.pad2 = 0;
                    segs[idx] = pc;
                }
            }
        }
#else
        float4 a, b;
#if SEGMENT_REGIONS & 1
        if (medium_piece(medium, &br, t_hit, &a, &b))
            append_light_segment(segs, max_segs, seg_count, a, b, &br, light_index, ray);
#endif
#if SEGMENT_REGIONS & 2
        if (interior_piece(materials, &br, found, t_hit, &a, &b))
            append_light_segment(segs, max_segs, seg_count, a, b, &br, light_index, ray);
#endif
#endif
        if (br.id == 0 && found) {
            int mt0 = materials[tri_mat[hit.tri]].type;
            flag = mt0 == MAT_MIRROR || mt0 == MAT_DIELECTRIC;
        }
        if (!found || br.depth >= max_depth) continue;
        int mi = tri_mat[hit.tri];
        __global const Material *mat = &materials[mi];
        if (mat->type != MAT_MIRROR && mat->type != MAT_DIELECTRIC) continue;
        br.thr *= branch_attenuation(medium, materials, &br, t_hit);
        SurfaceFrame f = surface_frame(tris, normals, &hit, br.o, br.d);
        push_specular(mat, mi, &br, &f, min_flux, stack, &top, PATH_STACK, &next_id);
    }
    ray_flags[gid] = flag;
}
