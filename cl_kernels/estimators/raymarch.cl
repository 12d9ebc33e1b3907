/* raymarch.cl: the reference for single scattering of direct light.
 *
 * One work-item per view segment (ViewSegment, from view_paths.cl; segment si =
 * seg_offset + the work-item, its result in out[si], times scale[si] when use_scale: a
 * segment of scale 0 is skipped, how a caller marches part of the segments). For every
 * light, STEPS jittered, stratified samples along the segment; at each, a shadow ray to the light
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
 * without noise and the pixel holding a light stays finite. In thick media (the rate r
 * of the view's and light path's transmittance along the segment, times the segment's
 * length or the light's distance h, above MIS_OPTICAL_DEPTH) half the strata sample
 * exp(-r t) instead (t = -log(1 - xi (1 - exp(-r len))) / r) and every sample is
 * weighted by the balance heuristic of the two densities: with uniform steps alone the
 * first optical depths of a thick segment, where all its light comes from, hold one or
 * two samples. Both are still quadrature along the ray with every sample shadow-tested.
 *
 * Built with DENSITY_GRIDS (density_march.cl) the same kernel renders density grids
 * (density.h): sigma_s(x) at every sample, T_view and T_light as exact optical depths
 * through the grids and the scene medium, the transmittance strategy's rate fitted from
 * the same optical depths, and every sample at the middle of its stratum.
 */
#include "common.h"
#include "bvh.h"
#include "lights.h"

/* beyond this optical depth (the transmittance strategy's rate times the light strategy's
 * length scale) a segment's steps are split between the two strategies; below it the
 * light's strategy alone (measured: on the built-in scenes of optical depth ~2 the split
 * only added noise at shadow edges; on epi_fog, 4.4, it cut the error 5x) */
#define MIS_OPTICAL_DEPTH 3.0f
/* a growing exp(-r t) over a segment: -r len at most this (float range) */
#define EXP_RATE_MAX 60.0f

/* where in its stratum a sample lies: jittered, or (density grids) the middle */
#ifdef DENSITY_GRIDS
#define STRATUM_OFFSET(rng) 0.5f
#else
#define STRATUM_OFFSET(rng) rng_next(rng)
#endif

float mean3(float4 v) { return (v.x + v.y + v.z) * (1.0f / 3.0f); }



/* The density of exp(-r t) on [0, len], normalised, for r of either sign (uniform where
 * |r| len is tiny), and its inverse CDF at xi in [0, 1). */
float exp_pdf(float r, float t, float len) {
    if (fabs(r) * len < 1e-4f) return 1.0f / len;
    return r * exp(-r * t) / -expm1(-r * len);
}
float exp_sample(float r, float xi, float len) {
    if (fabs(r) * len < 1e-4f) return xi * len;
    return -log1p(xi * expm1(-r * len)) / r;
}

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

    float4 kap = medium->kappa;
    float kmean = (kap.x + kap.y + kap.z) * (1.0f / 3.0f);
#ifdef DENSITY_GRIDS
    float tau_len = mean3(density_optical_depth(medium, sg.a, w, 0.0f, len));
#endif

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
        /* the transmittance strategy samples exp(-r t): the view's and the light path's
         * transmittance at the channels' mean extinction, the light path's length in the
         * medium fitted linearly between the segment's ends (r < 0 where the light comes
         * from the far end; the mean, not the least or largest extinction: measured the
         * best of the three on coloured media, tests/test_render.py) */
        float4 w0, w1;
        float d0, d1;
        light_arrival(L, sg.a, &w0, &d0);
        light_arrival(L, sg.b, &w1, &d1);
#ifdef DENSITY_GRIDS
        /* the same fit from optical depths: along the segment, and of the light paths
         * from its two ends */
        float dtau = mean3(density_optical_depth(medium, sg.b, w1, 0.0f, d1))
                   - mean3(density_optical_depth(medium, sg.a, w0, 0.0f, d0));
        float r = (tau_len + (isfinite(dtau) ? dtau : 0.0f)) / len;
        float t_prev = 0.0f;                    /* the view's optical depth up to t_prev */
        float4 tau_prev = (float4)(0.0f);
#else
        float ds = medium_path_length(medium, sg.b, w1, 0.0f, d1)
                 - medium_path_length(medium, sg.a, w0, 0.0f, d0);
        float r = kmean * (1.0f + (isfinite(ds) ? ds / len : 0.0f));
#endif
        r = fmax(r, -EXP_RATE_MAX / len);       /* exp(-r t) grows: keep it in float range */
        /* MIS where that falls or grows steeply over the scale of the light's own strategy:
         * the segment's length (uniform) or the light's distance h (equiangular) */
        int n_b = (fabs(r) * (equiangular ? h : len) > MIS_OPTICAL_DEPTH && steps > 1)
                ? steps / 2 : 0;
        int n_a = steps - n_b;
        float4 acc = (float4)(0.0f);
        for (int i = 0; i < steps; ++i) {
            /* the sample, from the light's strategy (i < n_a) or the transmittance one,
             * and both densities at it */
            float t, pa;
            if (i < n_a) {
                float xi = (i + STRATUM_OFFSET(&rng)) / n_a;
                if (equiangular) {
                    float tn = tan(th_a + xi * (th_b - th_a));
                    t = t_star + h * tn;
                    pa = 1.0f / ((th_b - th_a) * h * (1.0f + tn * tn));
                } else {
                    t = xi * len;
                    pa = 1.0f / len;
                }
            } else {
                t = exp_sample(r, (i - n_a + STRATUM_OFFSET(&rng)) / n_b, len);
                float d = t - t_star;
                pa = equiangular ? h / ((th_b - th_a) * (h * h + d * d)) : 1.0f / len;
            }
            float pb = n_b ? n_b * exp_pdf(r, t, len) : 0.0f;
            float dt = 1.0f / (n_a * pa + pb);              /* balance heuristic */
            t = clamp(t, 0.0f, len);
            float4 x = sg.a + t * w;
            x.w = 0.0f;
            float4 wi;
            float dist;
            float4 E = light_arrival(L, x, &wi, &dist);
            if (E.x == 0.0f && E.y == 0.0f && E.z == 0.0f) continue;
#ifdef DENSITY_GRIDS
            float4 ss = density_sigma_s(medium, x);
            if (ss.x == 0.0f && ss.y == 0.0f && ss.z == 0.0f) continue;
            if (t < t_prev) {                   /* the other strategy's samples: from 0 */
                t_prev = 0.0f;
                tau_prev = (float4)(0.0f);
            }
            tau_prev += density_optical_depth(medium, sg.a, w, t_prev, t);
            t_prev = t;
#endif
            float4 T_light = light_transmission(nodes, tris, light_grid, li, medium, x, wi, dist,
                                                1e-5f);
            float cos_theta = dot3(-wi, -w);      /* light travels along -wi; camera is at -w */
            float ph = hg_phase(cos_theta, medium->g);
#ifdef DENSITY_GRIDS
            acc += E * T_light * exp3(-tau_prev) * ss * (ph * dt);
#else
            acc += E * T_light * transmittance(kap, t) * (ph * dt);
#endif
        }
        result += acc;
    }
#ifdef DENSITY_GRIDS
    out[si] = result * sg.weight * sc;         /* sigma_s(x) is in every sample */
#else
    out[si] = result * medium->sigma_s * sg.weight * sc;
#endif
}
