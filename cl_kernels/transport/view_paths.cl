/* view_paths.cl: view paths from the camera through specular chains.
 *
 * One work-item per camera sample. Each path is followed through mirrors and
 * dielectrics up to max_depth bounces; a dielectric hit *splits* the path into its
 * Fresnel-weighted reflected and refracted branches (an explicit stack, no recursion),
 * so images of glass are noise-free and energy bookkeeping is exact. Branches whose
 * throughput falls below MIN_THROUGHPUT are dropped.
 *
 * Outputs, per sample (already divided by spp, so a pixel is the sum of its samples),
 * at out_offset + the sample's index in the launch:
 *   surface[s]  radiance of diffuse surfaces lit directly (shadow rays, medium attenuation)
 *   escaped[s]  throughput of branches that left the scene (for energy tests; no sky)
 * and the shared segment buffer: every straight piece of a path inside the medium, with
 * its weight = throughput * transmittance from the eye (common.h, ViewSegment); built
 * with SEGMENT_REGIONS = 2, the pieces inside glass that scatters instead (below).
 */
#include "common.h"
#include "bvh.h"
#include "lights.h"
#include "specular.h"

#ifndef PATH_STACK
#define PATH_STACK 16
#endif
#define MIN_THROUGHPUT 1e-4f
/* which pieces trace_view appends (bits): 1 the pieces in the scene medium (the shared
 * view segments), 2 the pieces inside dielectrics whose interior scatters (specular.h,
 * interior_piece; tagged with the material in a.w, weight = throughput at a times
 * 1 / ior^2 (interior_radiance_scale: radiance leaving glass into air), i.e. the interior
 * extinction from a on is the estimator's, as the medium's is) */
#ifndef SEGMENT_REGIONS
#define SEGMENT_REGIONS 1
#endif

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

/* The primary branch of camera sample s (pixel = s / spp): origin, stratified direction,
 * throughput 1/spp, in the closed glass the camera is inside (cam->inside, -1: in air)
 * with its ior^2 in the throughput (radiance / n^2 is what a branch carries, and the
 * camera sees the radiance where it is). Every camera-path tracer starts here. */
Branch camera_branch(__global const Camera *cam, uint seed, int s, int *pixel) {
    *pixel = s / cam->spp;
    int k = s % cam->spp;
    Rng rng = rng_seed(seed, (uint)*pixel, (uint)k);
    float inv_spp = 1.0f / cam->spp;
    Branch b;
    b.o = cam->origin;
    b.d = camera_dir(cam, *pixel % cam->width, *pixel / cam->width, k, &rng);
    float w = inv_spp * cam->radiance_scale;
    b.thr = (float4)(w, w, w, 0.0f);
    b.depth = 0;
    b.inside = cam->inside;
    b.id = 0;
    b.pad = 0;
    return b;
}

/* What every camera-path tracer does where branch br hits a surface: returns 1 for a
 * diffuse surface (the path ends there; *f and *mi hold the frame and material index for
 * the caller's own use: shading, recording the hit), else 0 after pushing the specular
 * children of a mirror or glass below depth_limit (a black surface just ends the path). */
int surface_hit(__global const float4 *tris, __global const float4 *normals,
                __global const int *tri_mat, __global const Material *materials,
                const Hit *hit, const Branch *br, int depth_limit, float min_weight,
                Branch *stack, int *top, int *next_id, SurfaceFrame *f, int *mi) {
    *f = surface_frame(tris, normals, hit, br->o, br->d);
    *mi = tri_mat[hit->tri];
    __global const Material *mat = &materials[*mi];
    if (mat->type == MAT_DIFFUSE) return 1;
    if (mat->type != MAT_BLACK && br->depth < depth_limit)
        push_specular(mat, *mi, br, f, min_weight, stack, top, PATH_STACK, next_id);
    return 0;
}

/* Append the medium piece [a, b] of branch br of camera sample s to the segment buffer. */
void append_view_segment(__global ViewSegment *segs, int max_segs, volatile __global int *count,
                         float4 a, float4 b, const Branch *br, int pixel, int s) {
    int idx = atomic_inc(count);
    if (idx < max_segs) {
        ViewSegment sg;
        sg.a = a;
        sg.b = b;
        sg.weight = br->thr;
        sg.pixel = pixel;
        sg.depth = br->depth;
        sg.sample = s;
        sg.branch = br->id;
        segs[idx] = sg;
    }
}

/* Irradiance from every light at a diffuse point p (sum of E cos T): n is the shading
 * normal and gn the geometric normal, both facing the viewer (shadow rays leave along gn). */
float4 direct_irradiance(__global const BVHNode *nodes, __global const float4 *tris,
                         __global const int *light_grid, __global const Light *lights,
                         int num_lights, __global const Medium *medium, float4 p, float4 n,
                         float4 gn) {
    float4 sum = (float4)(0.0f);
    float4 origin = p + gn * surface_offset(p);
    for (int i = 0; i < num_lights; ++i) {
        float4 wi;
        float dist;
        float4 E = light_arrival(&lights[i], p, &wi, &dist);
        float c = dot3(n, wi);
        if (c <= 0.0f || dot3(gn, wi) <= 0.0f || (E.x == 0.0f && E.y == 0.0f && E.z == 0.0f)) continue;
        sum += E * c * light_transmission(nodes, tris, light_grid, i, medium, origin, wi,
                                          dist, 0.0f);
    }
    return sum;
}

/* Radiance a diffuse point of colour albedo sends towards the viewer under direct light. */
float4 shade_diffuse(__global const BVHNode *nodes, __global const float4 *tris,
                     __global const int *light_grid, __global const Light *lights,
                     int num_lights, __global const Medium *medium, float4 p, float4 n,
                     float4 gn, float4 albedo) {
    return direct_irradiance(nodes, tris, light_grid, lights, num_lights, medium, p, n, gn)
           * albedo
           * (1.0f / PI_F);
}

/* Append diffuse hit f (material mi) of branch br of camera sample s to the hit buffer. */
void append_diffuse_hit(__global DiffuseHit *hits, int max_hits, volatile __global int *count,
                        const SurfaceFrame *f, float4 albedo, const Branch *br, int pixel, int s) {
    int idx = atomic_inc(count);
    if (idx < max_hits) {
        DiffuseHit h;
        h.p = f->p;
        h.n = f->nf;
        h.g = f->gf;
        h.weight = br->thr * albedo * (1.0f / PI_F);
        h.weight.w = 0.0f;
        h.pixel = pixel;
        h.sample = s;
        h.depth = br->depth;
        h.branch = br->id;
        hits[idx] = h;
    }
}

/* Every camera path's outputs, each wanted or not (one tracer, so the same seeds and
 * branching everywhere): with shade, surface[s] (diffuse surfaces lit directly) and
 * escaped[s]; with want_segs, the straight medium pieces appended to segs; with
 * want_hits, one DiffuseHit per branch ending on a diffuse surface (weight = throughput *
 * albedo / pi: what shade_hits relights, what the ray and photon maps add surface
 * caustics to). */
__kernel void trace_view(__global const BVHNode *nodes, __global const float4 *tris,
                         __global const int *light_grid, __global const int *camera_grid,
                         __global const float4 *normals, __global const int *tri_mat,
                         __global const Material *materials,
                         __global const Light *lights, int num_lights,
                         __global const Medium *medium, __global const Camera *cam,
                         int max_depth, uint seed, int sample_offset, int num_samples,
                         int shade, int want_segs, int want_hits,
                         int out_offset, __global float4 *surface, __global float4 *escaped,
                         __global ViewSegment *segs, int max_segs,
                         volatile __global int *seg_count,
                         __global DiffuseHit *hits, int max_hits,
                         volatile __global int *hit_count) {
    int gid = get_global_id(0);
    if (gid >= num_samples) return;
    int s = sample_offset + gid, pixel;
    float inv_spp = 1.0f / cam->spp;

    Branch stack[PATH_STACK];
    stack[0] = camera_branch(cam, seed, s, &pixel);
    int top = 1, next_id = 1;

    float4 radiance = (float4)(0.0f), escape = (float4)(0.0f);
    while (top > 0) {
        Branch br = stack[--top];
        Hit hit;
        /* the camera's own rays (branch 0) through the camera grid, the rest the BVH */
        int found = br.id == 0
            ? scene_closest(nodes, tris, camera_grid, br.o, br.d, 0.0f, T_INF, &hit)
            : bvh_closest(nodes, tris, br.o, br.d, 0.0f, T_INF, &hit);
        float t_hit = found ? hit.t : T_INF;

        /* ---- the straight piece in the medium (the medium lies outside all objects) ---- */
        float4 a, b;
#if SEGMENT_REGIONS & 1
        if (want_segs && medium_piece(medium, &br, t_hit, &a, &b))
            append_view_segment(segs, max_segs, seg_count, a, b, &br, pixel, s);
#endif
#if SEGMENT_REGIONS & 2
        if (want_segs && interior_piece(materials, &br, found, t_hit, &a, &b)) {
            Branch seen = br;      /* the radiance inside, as the camera in air sees it */
            seen.thr *= interior_radiance_scale(&materials[br.inside]);
            append_view_segment(segs, max_segs, seg_count, a, b, &seen, pixel, s);
        }
#endif
        if (found) br.thr *= branch_attenuation(medium, materials, &br, t_hit);
        if (!found) {
            escape += br.thr;
            continue;
        }

        /* ---- surface interaction ---- */
        SurfaceFrame f;
        int mi;
        if (surface_hit(tris, normals, tri_mat, materials, &hit, &br, max_depth,
                        MIN_THROUGHPUT * inv_spp, stack, &top, &next_id, &f, &mi)) {
            if (want_hits)
                append_diffuse_hit(hits, max_hits, hit_count, &f, materials[mi].color, &br,
                                   pixel, s);
            if (shade)
                radiance += br.thr * shade_diffuse(nodes, tris, light_grid, lights, num_lights,
                                                   medium, f.p, f.nf, f.gf,
                                                   materials[mi].color);
        }
    }
    if (shade) {
        surface[out_offset + gid] = radiance;
        escaped[out_offset + gid] = escape;
    }
}

/* Sort keys of n appended records (view segments or diffuse hits: `stride` int words
 * each, the camera sample and the branch at the given words): the sample relative to
 * base, and the branch (exact as a float below 2^24), so that a bucket sort orders them
 * by (sample, branch) whatever order the atomic appends ran in. */
__kernel void record_keys(__global const int *records, int stride, int sample_word,
                          int branch_word, int n, int base, __global int *keys,
                          __global float *branch) {
    int i = get_global_id(0);
    if (i >= n) return;
    __global const int *r = records + (size_t)i * stride;
    keys[i] = r[sample_word] - base;
    branch[i] = (float)r[branch_word];
}

/* The surface shading of trace_view again, at recorded diffuse hits (a light change:
 * no camera path is traced again): out[i] = weight * direct irradiance. */
__kernel void shade_hits(__global const BVHNode *nodes, __global const float4 *tris,
                         __global const int *light_grid,
                         __global const Light *lights, int num_lights,
                         __global const Medium *medium, __global const DiffuseHit *hits,
                         int n, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    DiffuseHit h = hits[i];
    out[i] = h.weight * direct_irradiance(nodes, tris, light_grid, lights, num_lights, medium,
                                          h.p, h.n, h.g);
}

/* Test hook: fresnel_dielectric over an array of cosines (tests/test_render.py). */
__kernel void fresnel_test(__global const float *cos_i, float eta, int n, __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float ct;
    out[i] = fresnel_dielectric(cos_i[i], eta, &ct);
}
