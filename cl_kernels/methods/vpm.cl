/* vpm.cl: volumetric photon mapping, the gather (Jensen & Christensen 1998).
 *
 * One work-item per view segment (ViewSegment, from view_paths.cl). The segment is marched
 * with a fixed step dx from a per-segment random offset u: samples at t_i = (i + u) dx,
 * each standing for a length dx, so the sum is an unbiased estimate of the integral
 * along the segment (jittered regular sampling). Samples farther than max_r from the
 * photon map's box cannot find a photon and are skipped without changing the result.
 * At every sample the KNN nearest photons give the in-scattered radiance (vpm.h):
 *
 *   L = weight * sigma_s * sum_i dx * T(t_i) * sum_p f(w_p . -w) Phi_p / V(r)
 *
 * with T(t) = exp(-kappa t) from the segment start (the weight carries the rest of the
 * way to the eye) and V(r) = 4/3 pi r^3, or in a bounded medium the part of that ball
 * inside the medium box. out.w returns the number of samples taken, work_out the boxes and
 * photons the kNN queries tested (statistics); both are indexed by segment (seg_offset +
 * work-item), so launches over chunks fill one buffer.
 */
#include "common.h"
#include "vpm.h"

__kernel void vpm_gather(__global const ViewSegment *segs, int seg_offset, int num_segs,
                         __global const Photon *photons, int num_photons,
                         __global const PointNode *nodes, int levels, float power_scale,
                         __global const Medium *medium, float dx, float max_r2, uint seed,
                         __global float4 *out, __global int2 *work_out) {
    int gid = get_global_id(0);
    if (gid >= num_segs) return;
    ViewSegment sg = segs[seg_offset + gid];
    float4 ab = sg.b - sg.a;
    ab.w = 0.0f;
    float len = length3(ab);
    out[seg_offset + gid] = (float4)(0.0f);
    work_out[seg_offset + gid] = (int2)(0, 0);
    if (len <= 0.0f || num_photons <= 0) return;
    float4 w = ab / len;

    /* ---- the part of the segment within max_r of the photons' box ---- */
    float r = sqrt(max_r2);
    __global const PointNode *root = &nodes[0];
    float4 lo = (float4)(root->bmin[0] - r, root->bmin[1] - r, root->bmin[2] - r, 0.0f);
    float4 hi = (float4)(root->bmax[0] + r, root->bmax[1] + r, root->bmax[2] + r, 0.0f);
    float t0, t1;
    if (!ray_box(sg.a, safe_inv_dir(w), lo, hi, 0.0f, len, &t0, &t1)) return;

    /* ---- jittered regular samples inside [t0, t1) ---- */
    Rng rng = rng_seed(seed, (uint)sg.sample, (uint)sg.branch ^ 0x7f4a7c15u);
    float u = rng_next(&rng);
    int i = max(0, (int)ceil(t0 / dx - u));
    float4 wo = -w;
    float4 acc = (float4)(0.0f);
    float hd[KNN];
    int hi_[KNN];
    int work[2] = {0, 0};
    int steps = 0;
    float r_prev = r;
    for (;; ++i) {
        float t = (i + u) * dx;
        if (t >= t1) break;
        if (t < t0) continue;
        float4 x = sg.a + t * w;
        x.w = 0.0f;
        /* the KNN photons of the previous sample lie within r_prev + dx of this one, so
         * its KNN nearest do too: search that ball first (it only prunes: a ball holding
         * KNN photons holds the KNN nearest), the whole max_r ball when it holds fewer */
        int count = 0;
        float r2_try = (r_prev + dx) * (r_prev + dx);
        if (r2_try < max_r2)
            count = knn_query(photons, num_photons, nodes, levels, x, r2_try, hd, hi_, work);
        if (count < KNN)
            count = knn_query(photons, num_photons, nodes, levels, x, max_r2, hd, hi_, work);
        r_prev = count == KNN ? sqrt(hd[0]) : r;
        if (count > 0) {
            float r2;
            float4 sum = knn_sum(photons, power_scale, hd, hi_, count, max_r2, wo, medium->g, &r2);
            float rk = sqrt(fmax(r2, 1e-30f));
            float vol = medium->bounded ? ball_volume_in_box(x, rk, medium->bmin, medium->bmax)
                                        : (4.0f / 3.0f) * PI_F * rk * rk * rk;
            acc += sum / fmax(vol, 1e-30f) * transmittance(medium->kappa, t);
        }
        ++steps;
    }
    float4 res = acc * dx * medium->sigma_s * sg.weight;
    res.w = (float)steps;
    out[seg_offset + gid] = res;
    work_out[seg_offset + gid] = (int2)(work[0], work[1]);
}

/* Kernel-level test hook: the kNN query and estimate at given points. For each query q:
 * count[q], the heap's photon indices idx[q * KNN + k] (k < count) and the estimate. */
__kernel void vpm_knn(__global const float4 *points, __global const float4 *wo, int num_points,
                      __global const Photon *photons, int num_photons,
                      __global const PointNode *nodes, int levels, float power_scale,
                      float g, float max_r2, __global int *count_out, __global int *idx_out,
                      __global float4 *est_out) {
    int gid = get_global_id(0);
    if (gid >= num_points) return;
    float hd[KNN];
    int hi_[KNN];
    int work[2] = {0, 0};
    float4 p = points[gid];
    p.w = 0.0f;
    int count = knn_query(photons, num_photons, nodes, levels, p, max_r2, hd, hi_, work);
    count_out[gid] = count;
    for (int k = 0; k < KNN; ++k) idx_out[gid * KNN + k] = k < count ? hi_[k] : -1;
    est_out[gid] = knn_estimate(photons, power_scale, hd, hi_, count, max_r2, wo[gid], g);
}
