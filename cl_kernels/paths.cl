/* paths.cl: view paths from the camera through specular chains.
 *
 * One work-item per camera sample. Each path is followed through mirrors and
 * dielectrics up to max_depth bounces; a dielectric hit *splits* the path into its
 * Fresnel-weighted reflected and refracted branches (an explicit stack, no recursion),
 * so images of glass are noise-free and energy bookkeeping is exact. Branches whose
 * throughput falls below MIN_THROUGHPUT are dropped.
 *
 * Outputs, per sample (already divided by spp, so a pixel is the sum of its samples):
 *   surface[s]  radiance of diffuse surfaces lit directly (shadow rays, medium attenuation)
 *   escaped[s]  throughput of branches that left the scene (for energy tests; no sky)
 * and the shared segment buffer: every straight piece of a path inside the medium, with
 * its weight = throughput * transmittance from the eye (common.h, ViewSegment).
 */
#include "common.h"
#include "bvh.h"
#include "lights.h"

#ifndef PATH_STACK
#define PATH_STACK 16
#endif
#define MIN_THROUGHPUT 1e-4f

typedef struct {
    float4 o, d, thr;
    int depth;
    int inside;   /* index of the dielectric material the path is inside, or -1 */
    int id;       /* branch number within this sample's path tree (0: the camera ray) */
} Branch;

/* Unpolarised Fresnel reflectance for a dielectric interface; eta = n_i / n_t.
 * Returns 1 on total internal reflection and sets *cos_t otherwise. */
float fresnel_dielectric(float cos_i, float eta, float *cos_t) {
    float sin2_t = eta * eta * fmax(0.0f, 1.0f - cos_i * cos_i);
    if (sin2_t >= 1.0f) { *cos_t = 0.0f; return 1.0f; }
    float ct = sqrt(1.0f - sin2_t);
    *cos_t = ct;
    float rs = (eta * cos_i - ct) / (eta * cos_i + ct);
    float rp = (cos_i - eta * ct) / (cos_i + eta * ct);
    return 0.5f * (rs * rs + rp * rp);
}

/* Primary ray direction for sample k of pixel (px, py); stratified when spp is square. */
float4 camera_dir(__global const Camera *cam, int px, int py, int k, Rng *rng) {
    float u, v;
    if (cam->spp_side > 0) {
        int sx = k % cam->spp_side, sy = k / cam->spp_side;
        u = (sx + rng_next(rng)) / cam->spp_side;
        v = (sy + rng_next(rng)) / cam->spp_side;
    } else {
        u = rng_next(rng);
        v = rng_next(rng);
    }
    float fx = 2.0f * (px + u) / cam->width - 1.0f;
    float fy = 1.0f - 2.0f * (py + v) / cam->height;
    return normalize3(cam->forward + fx * cam->right + fy * cam->up);
}

/* Direct light at a diffuse point p, every light: n is the shading normal and gn the
 * geometric normal, both facing the viewer (shadow rays leave along gn). */
float4 shade_diffuse(__global const BVHNode *nodes, __global const float4 *tris,
                     __global const Light *lights, int num_lights, __global const Medium *medium,
                     float4 p, float4 n, float4 gn, float4 albedo) {
    float4 sum = (float4)(0.0f);
    float4 origin = p + gn * RAY_EPS;
    for (int i = 0; i < num_lights; ++i) {
        float4 wi;
        float dist;
        float4 E = light_arrival(&lights[i], p, &wi, &dist);
        float c = dot3(n, wi);
        if (c <= 0.0f || dot3(gn, wi) <= 0.0f || (E.x == 0.0f && E.y == 0.0f && E.z == 0.0f)) continue;
        sum += E * c * light_transmission(nodes, tris, medium, origin, wi, dist, 0.0f);
    }
    return sum * albedo * (1.0f / PI_F);
}

__kernel void trace_view(__global const BVHNode *nodes, __global const float4 *tris,
                         __global const float4 *normals, __global const int *tri_mat,
                         __global const Material *materials,
                         __global const Light *lights, int num_lights,
                         __global const Medium *medium, __global const Camera *cam,
                         int max_depth, uint seed, int sample_offset, int num_samples,
                         __global float4 *surface, __global float4 *escaped,
                         __global ViewSegment *segs, int max_segs,
                         volatile __global int *seg_count) {
    int gid = get_global_id(0);
    if (gid >= num_samples) return;
    int s = sample_offset + gid;
    int pixel = s / cam->spp, k = s % cam->spp;
    int px = pixel % cam->width, py = pixel / cam->width;
    Rng rng = rng_seed(seed, (uint)pixel, (uint)k);
    float inv_spp = 1.0f / cam->spp;

    Branch stack[PATH_STACK];
    int top = 0;
    stack[0].o = cam->origin;
    stack[0].d = camera_dir(cam, px, py, k, &rng);
    stack[0].thr = (float4)(inv_spp, inv_spp, inv_spp, 0.0f);
    stack[0].depth = 0;
    stack[0].inside = -1;
    stack[0].id = 0;
    top = 1;
    int next_id = 1;

    float4 radiance = (float4)(0.0f), escape = (float4)(0.0f);
    while (top > 0) {
        Branch br = stack[--top];
        Hit hit;
        int found = bvh_closest(nodes, tris, br.o, br.d, 0.0f, T_INF, &hit);
        float t_hit = found ? hit.t : T_INF;

        /* ---- the straight piece in the medium (the medium lies outside all objects) ---- */
        if (br.inside < 0 && medium->present) {
            float t0, t1;
            if (medium_interval(medium, br.o, br.d, 0.0f, t_hit, &t0, &t1) && t1 > t0) {
                int idx = atomic_inc(seg_count);
                if (idx < max_segs) {
                    ViewSegment sg;
                    sg.a = br.o + t0 * br.d;
                    sg.b = br.o + t1 * br.d;
                    sg.a.w = 0.0f;
                    sg.b.w = 0.0f;
                    sg.weight = br.thr;
                    sg.pixel = pixel;
                    sg.depth = br.depth;
                    sg.sample = s;
                    sg.branch = br.id;
                    segs[idx] = sg;
                }
            }
            if (found) br.thr *= transmittance(medium->kappa,
                                               medium_path_length(medium, br.o, br.d, 0.0f, t_hit));
        } else if (br.inside >= 0 && found) {
            br.thr *= transmittance(materials[br.inside].interior_sigma_a, t_hit);
        }
        if (!found) {
            escape += br.thr;
            continue;
        }

        /* ---- surface interaction ---- */
        float4 v0 = tris[3 * hit.tri], v1 = tris[3 * hit.tri + 1], v2 = tris[3 * hit.tri + 2];
        float4 p = br.o + hit.t * br.d;
        p.w = 0.0f;
        float4 ng = normalize3(cross3(v1 - v0, v2 - v0));
        float4 ns = normalize3((1.0f - hit.u - hit.v) * normals[3 * hit.tri] +
                               hit.u * normals[3 * hit.tri + 1] + hit.v * normals[3 * hit.tri + 2]);
        if (dot3(ns, ns) == 0.0f) ns = ng;
        if (dot3(ns, ng) < 0.0f) ns = -ns;
        int front = dot3(br.d, ng) < 0.0f;          /* arriving from the side ng points to */
        float4 nf = front ? ns : -ns;                /* shading normal facing the ray */
        float4 gf = front ? ng : -ng;                /* geometric normal facing the ray */
        int mi = tri_mat[hit.tri];
        __global const Material *mat = &materials[mi];

        if (mat->type == MAT_DIFFUSE) {
            radiance += br.thr * shade_diffuse(nodes, tris, lights, num_lights, medium, p, nf, gf,
                                               mat->color);
            continue;
        }
        if (mat->type == MAT_BLACK || br.depth >= max_depth) continue;

        float cos_i = fmax(-dot3(br.d, nf), 0.0f);
        float4 refl_d = normalize3(br.d + 2.0f * cos_i * nf);
        if (dot3(refl_d, gf) <= 0.0f) refl_d = normalize3(br.d + 2.0f * (-dot3(br.d, gf)) * gf);
        Branch r;
        r.o = p + gf * RAY_EPS;
        r.d = refl_d;
        r.depth = br.depth + 1;
        r.inside = br.inside;
        r.id = next_id++;

        if (mat->type == MAT_MIRROR) {
            r.thr = br.thr * mat->color;
            if (fmax(r.thr.x, fmax(r.thr.y, r.thr.z)) > MIN_THROUGHPUT * inv_spp && top < PATH_STACK)
                stack[top++] = r;
            continue;
        }

        /* dielectric: Fresnel split into reflection and refraction (TIR: reflection only) */
        float eta = front ? 1.0f / mat->ior : mat->ior;
        float cos_t;
        float F = fresnel_dielectric(cos_i, eta, &cos_t);
        r.thr = br.thr * F;
        Branch tr;
        tr.thr = br.thr * (1.0f - F);
        tr.o = p - gf * RAY_EPS;
        tr.d = normalize3(eta * br.d + (eta * cos_i - cos_t) * nf);
        tr.depth = br.depth + 1;
        tr.inside = front ? mi : -1;
        tr.id = next_id++;
        if (dot3(tr.d, gf) >= 0.0f) tr.thr = (float4)(0.0f); /* shading-normal artefact */
        float lim = MIN_THROUGHPUT * inv_spp;
        int keep_r = fmax(r.thr.x, fmax(r.thr.y, r.thr.z)) > lim;
        int keep_t = F < 1.0f && fmax(tr.thr.x, fmax(tr.thr.y, tr.thr.z)) > lim;
        /* push the weaker branch first so the stronger one is followed next */
        int t_first = F >= 0.5f;
        if (t_first) {
            if (keep_t && top < PATH_STACK) stack[top++] = tr;
            if (keep_r && top < PATH_STACK) stack[top++] = r;
        } else {
            if (keep_r && top < PATH_STACK) stack[top++] = r;
            if (keep_t && top < PATH_STACK) stack[top++] = tr;
        }
    }
    surface[gid] = radiance;
    escaped[gid] = escape;
}

/* Test hook: fresnel_dielectric over an array of cosines (tests/test_render.py). */
__kernel void fresnel_test(__global const float *cos_i, float eta, __global float *out) {
    int i = get_global_id(0);
    float ct;
    out[i] = fresnel_dielectric(cos_i[i], eta, &ct);
}
