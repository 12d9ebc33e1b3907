/* raymarch.cl: the reference for single scattering of direct light.
 *
 * One work-item per view segment (ViewSegment, from view_paths.cl; segment si =
 * seg_offset + the work-item, its result in out[si], times scale[si] when use_scale: a
 * segment of scale 0 is skipped, how a caller marches part of the segments). For every light, STEPS
 * jittered, stratified samples along the segment; at each, a shadow ray to the light
 * (any-hit through the BVH, or through the scene's light grid for the directional light
 * it serves: tile_grid.h, the same answer) and the medium transmittance on the way, the
 * HG phase function and sigma_s:
 *
 *   L = sum_lights  int_0^len  sigma_s p(cos) E_light(x(t)) V T_light(x(t)) T_view(t) dt
 *
 * where T_view(t) = exp(-kappa t) from the segment start (its weight carries the rest
 * of the way to the eye) and cos is between the light's travel direction and the
 * direction back towards the camera.
 *
 * Sample placement per light: directional lights use uniform strata in t. Point and
 * spot lights use equiangular strata (Kulla & Fajardo 2012): t = t* + h tan(theta),
 * theta uniform between the ends, so the 1/d^2 peak near the light is integrated
 * without noise and the pixel holding a light stays finite. Both are still plain
 * quadrature along the ray with every sample shadow-tested.
 */
#include "common.h"
#include "bvh.h"
#include "lights.h"

__kernel void raymarch(__global const BVHNode *nodes, __global const float4 *tris,
                       __global const int *light_grid, __global const Light *lights, int num_lights,
                       __global const Medium *medium,
                       __global const ViewSegment *segs, int seg_offset, int num_segs,
                       __global const float *scale, int use_scale,
                       int steps, uint seed, __global float4 *out) {
    int gid = get_global_id(0);
    if (gid >= num_segs) return;
    int si = seg_offset + gid;
    ViewSegment sg = segs[si];
    float4 ab = sg.b - sg.a;
    ab.w = 0.0f;
    float len = length3(ab);
    float4 result = (float4)(0.0f);
    float sc = use_scale ? scale[si] : 1.0f;
    if (len <= 0.0f || sc == 0.0f) { out[si] = result; return; }
    float4 w = ab / len;
    Rng rng = rng_seed(seed, (uint)sg.sample, (uint)sg.branch ^ 0x5ca77e3u);

    for (int li = 0; li < num_lights; ++li) {
        __global const Light *L = &lights[li];
        int equiangular = L->type != LIGHT_DIRECTIONAL;
        float t_star = 0.0f, h = 1.0f, th_a = 0.0f, th_b = 0.0f;
        if (equiangular) {
            float4 to = L->position - sg.a;
            t_star = dot3(to, w);
            float4 perp = to - t_star * w;
            h = fmax(length3(perp), 1e-6f * fmax(len, 1e-3f));  /* ray through the light: clamp */
            th_a = atan2(0.0f - t_star, h);
            th_b = atan2(len - t_star, h);
        }
        float4 acc = (float4)(0.0f);
        for (int i = 0; i < steps; ++i) {
            float xi = (i + rng_next(&rng)) / steps;
            float t, dt;
            if (equiangular) {
                float th = th_a + xi * (th_b - th_a);
                float tn = tan(th);
                t = t_star + h * tn;
                dt = (th_b - th_a) / steps * h * (1.0f + tn * tn);   /* dt/dtheta * dtheta */
            } else {
                t = xi * len;
                dt = len / steps;
            }
            t = clamp(t, 0.0f, len);
            float4 x = sg.a + t * w;
            x.w = 0.0f;
            float4 wi;
            float dist;
            float4 E = light_arrival(L, x, &wi, &dist);
            if (E.x == 0.0f && E.y == 0.0f && E.z == 0.0f) continue;
            float4 T_light = light_transmission(nodes, tris, light_grid, li, medium, x, wi, dist,
                                                1e-5f);
            float cos_theta = dot3(-wi, -w);      /* light travels along -wi; camera is at -w */
            float ph = hg_phase(cos_theta, medium->g);
            acc += E * T_light * transmittance(medium->kappa, t) * (ph * dt);
        }
        result += acc;
    }
    out[si] = result * medium->sigma_s * sg.weight * sc;
}
