/* raymap.cl: batched ray-map queries and density estimation (raymap.h; host:
 * clscatter/estimators/knn_queries.py and ray_density.py). One work-item per query.
 *
 * rm_knn_batch     K nearest segments of every query (indices, distances, counts)
 * rm_knn_list      the same over host-built per-query candidate lists (domain queries)
 * rm_intersect     all segments meeting every query's domain, appended as (query, segment)
 *                  pairs (a segment listed by several leaves comes more than once; the
 *                  host removes repeats)
 * rm_kth_end       the K-th nearest ray end point of every query (the reach of the lazy
 *                  refinement, ray_density.lazy_radius), over a balanced point tree
 * rm_splat         fixed-radius estimates the other way round: every segment adds its
 *                  weighted flux to the hits whose domain it qualifies for (below)
 * rm_density       irradiance estimates on surfaces (Havran et al. 2005, eq. 1):
 *                  E(x) = sum_i w(t_i) Phi_i / (pi R^2)
 *                  over the K nearest incoming rays (ray map: RM_HEMIDISC, weights from the
 *                  tangent-plane distance II.a; photon map: RM_SEGMENT on points), R = the
 *                  K-th distance (the domain radius when fewer than K exist), t_i = d_i / R,
 *                  w = 1 inside R for the box kernel, w = 2 (1 - t^2) for Epanechnikov's
 *                  (normalised over the unit disc: int_0^1 2 (1 - t^2) 2 pi t dt = pi).
 *                  With K found, the box kernel sums the K - 1 rays strictly inside R: for
 *                  a Poisson process E[(K - 1) / (pi R_K^2)] is exactly the density, while
 *                  K / (pi R_K^2) overestimates it by K / (K - 1); Epanechnikov's weight is
 *                  0 at the K-th ray, so both kernels are unbiased for uniform density.
 */
#include "common.h"
#include "raymap.h"
#include "point_tree.h"
#include "fixed_sum.h"

/* this work-item's heap (raymap.h, RM_HEAP): scratch_d/x hold RM_K entries per work-item
 * when RM_K > 256 and are unused (1 element) otherwise; a private hx also holds the table
 * of segments seen (RM_HX_SIZE) */
#if RM_K > 256
#define RM_HEAP_DECLARE \
    __global float *hd = scratch_d + (size_t)get_global_id(0) * RM_K; \
    __global int *hx = scratch_x + (size_t)get_global_id(0) * RM_K;
#else
#define RM_HEAP_DECLARE float hd[RM_K]; int hx[RM_HX_SIZE];
#endif

__kernel void rm_knn_batch(__global const RMNode *nodes, __global const int *refs,
                           __global const float4 *seg_a, __global const float4 *seg_b,
                           __global const float4 *seg_d, __global const float4 *qx,
                           __global const float4 *qn, int num_q, int k, int metric, int domain,
                           float radius, int incoming, float cos_alpha,
                           __global float *scratch_d, __global int *scratch_x,
                           __global int *out_idx, __global float *out_dist,
                           __global int *out_count, __global int *out_work) {
    int q = get_global_id(0);
    if (q >= num_q) return;
    RM_HEAP_DECLARE
    int work[2] = {0, 0};
    int c = rm_knn(nodes, refs, seg_a, seg_b, seg_d, qx[q], qn[q], min(k, RM_K), metric,
                   domain, radius, incoming, cos_alpha, hd, hx, work);
    for (int j = 0; j < k; ++j) {
        out_idx[q * k + j] = j < c ? hx[j] : -1;
        out_dist[q * k + j] = j < c ? hd[j] : -1.0f;
    }
    out_count[q] = c;
    out_work[2 * q] = work[0];
    out_work[2 * q + 1] = work[1];
}

/* K nearest over a host-built candidate list (knn_queries.py knn_lists): query q tests the
 * segments cand_ids[cand_off[q] .. cand_off[q + 1]) (unique, from every leaf meeting its
 * search box) with the same per-candidate test as the tree walk (rm_candidate). A domain
 * is required (radius > 0): it bounds the candidates. */
__kernel void rm_knn_list(__global const int *cand_off, __global const int *cand_ids,
                          __global const float4 *seg_a, __global const float4 *seg_b,
                          __global const float4 *seg_d, __global const float4 *qx,
                          __global const float4 *qn, int num_q, int k, int metric, int domain,
                          float radius, int incoming,
                          __global float *scratch_d, __global int *scratch_x,
                          __global int *out_idx, __global float *out_dist,
                          __global int *out_count) {
    int q = get_global_id(0);
    if (q >= num_q) return;
    RM_HEAP_DECLARE
    float4 x = qx[q], n = qn[q];
    int kk = min(k, RM_K), c = 0;
    rm_seen_clear(hx);
    int end = cand_off[q + 1];
    for (int j = cand_off[q]; j < end; ++j)
        rm_candidate(cand_ids[j], seg_a, seg_b, seg_d, x, n, kk, metric, domain, radius,
                     incoming, hd, hx, &c);
    for (int j = 0; j < k; ++j) {
        out_idx[q * k + j] = j < c ? hx[j] : -1;
        out_dist[q * k + j] = j < c ? hd[j] : -1.0f;
    }
    out_count[q] = c;
}

/* For every query, the K-th nearest of the end points `ends` (sorted by leaf of their
 * balanced point tree, point_tree.h) with squared distance < r2_search: its index in
 * that order, or -1 when fewer than K lie within. */
__kernel void rm_kth_end(__global const float4 *ends, int num_ends,
                         __global const PointNode *end_nodes, int levels,
                         __global const float4 *qx, int num_q, int k, float r2_search,
                         __global float *scratch_d, __global int *scratch_x,
                         __global int *out_idx) {
    int q = get_global_id(0);
    if (q >= num_q) return;
    RM_HEAP_DECLARE
    int work[2] = {0, 0};
    float4 x = qx[q];
    x.w = 0.0f;
    int kk = min(k, RM_K);
    int c = pt_knn((__global const float *)ends, 4, num_ends, end_nodes, levels, x, r2_search,
                   kk, hd, hx, work);
    out_idx[q] = c == kk ? hx[0] : -1;
}

__kernel void rm_intersect(__global const RMNode *nodes, __global const int *refs,
                           __global const float4 *seg_a, __global const float4 *seg_b,
                           __global const float4 *seg_d, __global const float4 *qx,
                           __global const float4 *qn, __global const float *qr, int num_q,
                           int qtype, float cos_alpha,
                           __global int2 *pairs, int max_pairs, volatile __global int *pair_count) {
    int q = get_global_id(0);
    if (q >= num_q) return;
    float4 x = qx[q], n = qn[q];
    float r = qr[q];
    int incoming = qtype == RM_Q_DISC || qtype == RM_Q_HEMISPHERE;
    int stack[RM_STACK];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
        __global const RMNode *nd = &nodes[stack[--top]];
        /* constrained traversal (Sec. 5.3): the domain's bounding box against the cell */
        if (qtype == RM_Q_BOX) {
            if (any(nd->lo.xyz > n.xyz) || any(nd->hi.xyz < x.xyz)) continue;
        } else {
            if (rm_box_dist(nd, x) > r) continue;
            if (qtype == RM_Q_HEMISPHERE && rm_box_above(nd, x, n) < 0.0f) continue;
        }
        if (nd->kind == RM_LEAF) {
            for (int j = 0; j < nd->count; ++j) {
                int s = refs[nd->first + j];
                if (rm_meets(qtype, x, n, r, seg_a[s], seg_b[s], seg_d[s])) {
                    int idx = atomic_inc(pair_count);
                    if (idx < max_pairs) pairs[idx] = (int2)(q, s);
                }
            }
            continue;
        }
        if (top + 2 > RM_STACK) continue;
        if (nd->kind == RM_DIRECTIONAL && incoming && rm_covered(nd, n, cos_alpha)) {
            stack[top++] = nd->child;
            continue;
        }
        stack[top++] = nd->child + 1;
        stack[top++] = nd->child;
    }
}

#ifndef RM_LIST
#define RM_LIST 48          /* leaves in a reusable candidate list */
#endif

/* Eq. (1) from the heap of a finished K-nearest query (see the header of this file). */
float4 rm_estimate(__global const float4 *seg_a, __global const float4 *seg_d,
                   __global const float4 *seg_flux, float4 x, float4 n, RM_HEAP const float *hd,
                   RM_HEAP const int *hx, int c, int kk, float radius, int plane_weights, int epanechnikov) {
    float R = c == kk ? hd[0] : radius;
    float4 e = (float4)(0.0f);
    if (c == 0 || !(R > 0.0f)) return e;
    for (int j = 0; j < c; ++j) {
        if (c == kk && j == 0 && !epanechnikov) continue;       /* the K-th: on the boundary */
        int s = hx[j];
        float d = plane_weights ? rm_plane_dist(x, n, seg_a[s], seg_d[s]) : hd[j];
        float t = fmin(d / R, 1.0f);
        float w = epanechnikov ? 2.0f * (1.0f - t * t) : 1.0f;
        e += w * seg_flux[s];
    }
    e *= 1.0f / (PI_F * R * R);
    e.w = 0.0f;
    return e;
}

/* One work-item answers `run` consecutive queries (keep them coherent, e.g. in pixel
 * order); with reuse_eps > 0 it reuses candidate lists between them (raymap.h). Query q
 * writes out_e[out_offset + q] and its work pair there: batches fill one buffer. The
 * domain radius is `radius`, or with per_query_radius qr[q] (progressive passes: a fixed
 * radius per query, K then only bounds the rays gathered); with want_r, out_r[out_offset
 * + q] gets the estimate's R (the K-th distance, or the domain radius when fewer exist). */
__kernel void rm_density(__global const RMNode *nodes, __global const int *refs,
                         __global const float4 *seg_a, __global const float4 *seg_b,
                         __global const float4 *seg_d, __global const float4 *seg_flux,
                         __global const float4 *qx, __global const float4 *qn, int num_q,
                         int k, int metric, float radius, int plane_weights, int epanechnikov,
                         float cos_alpha, int run, float reuse_eps,
                         __global const float *qr, int per_query_radius,
                         __global float *scratch_d, __global int *scratch_x, int out_offset,
                         __global float4 *out_e, __global int *out_work,
                         __global float *out_r, int want_r) {
    int first = get_global_id(0) * run;
    if (first >= num_q) return;
    int last = min(first + run, num_q);
    RM_HEAP_DECLARE
    int list[RM_LIST];
    int nlist = -1;
    float4 x0 = (float4)(0.0f);
    float d0 = 0.0f;
    int kk = min(k, RM_K);
    int domain = metric == RM_HEMIDISC ? RM_DOM_HEMISPHERE : RM_DOM_SPHERE;
    for (int q = first; q < last; ++q) {
        float4 x = qx[q], n = qn[q];
        float rq = per_query_radius ? qr[q] : radius;
        int work[2] = {0, 0};
        int c = -1;
        if (nlist >= 0 && length3(x - x0) <= reuse_eps) {
            c = 0;
            rm_seen_clear(hx);
            for (int j = 0; j < nlist; ++j)
                rm_leaf(&nodes[list[j]], refs, seg_a, seg_b, seg_d, x, n, kk, metric, domain,
                        rq, 1, hd, hx, &c, work);
            float dk = c == kk ? hd[0] : rq;
            if (!(dk <= d0 + reuse_eps)) c = -1;           /* not provably exact: walk */
        }
        if (c < 0) {
            c = rm_knn(nodes, refs, seg_a, seg_b, seg_d, x, n, kk, metric, domain, rq, 1,
                       cos_alpha, hd, hx, work);
            if (reuse_eps > 0.0f) {
                x0 = x;
                d0 = c == kk ? hd[0] : rq;
                nlist = rm_collect(nodes, x, d0 + 2.0f * reuse_eps, list, RM_LIST);
            }
        }
        int o = out_offset + q;
        out_e[o] = rm_estimate(seg_a, seg_d, seg_flux, x, n, hd, hx, c, kk, rq,
                               plane_weights, epanechnikov);
        out_work[2 * o] = work[0];
        out_work[2 * o + 1] = work[1];
        if (want_r) out_r[o] = c == kk ? hd[0] : rq;      /* the estimate's R */
    }
}

/* What each diffuse hit sends to its pixel: its weight (throughput x albedo / pi) times
 * the irradiance e[i] estimated there (surface_caustics sums these per pixel). */
__kernel void rm_weigh_hits(__global const DiffuseHit *hits, __global const float4 *e, int n,
                            __global float4 *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float4 v = hits[i].weight * e[i];
    v.w = 0.0f;
    out[i] = v;
}

/* ---- Fixed-radius estimates by splatting (clscatter/estimators/disc_splat.py) ----
 *
 * With a fixed radius R_q per hit, eq. (1) is a sum over the segments that qualify for
 * hit q (rm_qualify: incoming, within the domain of radius R_q, metric <= R_q), so it can
 * be formed from the segments' side: one work-item per segment walks a balanced tree over
 * the hits (point_tree.h's layout: a perfect binary tree breadth-first, leaf j holding the
 * hits [j n >> levels, (j + 1) n >> levels) in tree order), whose node boxes bound every
 * hit's ball x_q +- R_q, and adds w Phi to each hit it qualifies for. hx[i].w holds R_i.
 *
 * The sums are exact (fixed_sum.h): the result does not depend on the order the
 * work-items add in. The host picks fixed_scale so that no sum reaches 2^62. */

/* Does the segment [a, b] meet the node's box? (common.h's slab test; a point when a == b) */
int rm_seg_meets_box(float4 a, float4 b, __global const PointNode *nd) {
    float4 lo = (float4)(nd->bmin[0], nd->bmin[1], nd->bmin[2], 0.0f);
    float4 hi = (float4)(nd->bmax[0], nd->bmax[1], nd->bmax[2], 0.0f);
    float t0, t1;
    return ray_box(a, safe_inv_dir(b - a), lo, hi, 0.0f, 1.0f, &t0, &t1);
}

__kernel void rm_splat(__global const PointNode *nodes, int levels, int num_hits,
                       __global const float4 *hx, __global const float4 *hn,
                       __global const float4 *seg_a, __global const float4 *seg_b,
                       __global const float4 *seg_d, __global const float4 *seg_flux,
                       int first, int num_segs, int metric, int plane_weights,
                       int epanechnikov, float fixed_scale, volatile __global uint *acc,
                       __global int *out_work) {
    int s = first + get_global_id(0);
    if (s >= num_segs) return;
    float4 a = seg_a[s], b = seg_b[s], d = seg_d[s], flux = seg_flux[s];
    int domain = metric == RM_HEMIDISC ? RM_DOM_HEMISPHERE : RM_DOM_SPHERE;
    int first_leaf = (1 << levels) - 1;
    int work[2] = {0, 0};
    int node = 0;
    while (1) {
        work[0] += 1;
        if (rm_seg_meets_box(a, b, &nodes[node])) {
            if (node < first_leaf) {
                node = 2 * node + 1;                     /* descend to the left child */
                continue;
            }
            long j = node - first_leaf;
            int lo = (int)((j * num_hits) >> levels), hi = (int)(((j + 1) * num_hits) >> levels);
            work[1] += hi - lo;
            for (int i = lo; i < hi; ++i) {
                float4 x = hx[i], n = hn[i];
                float R = x.w, v;
                x.w = 0.0f;
                if (!rm_qualify(x, n, a, b, d, metric, domain, R, 1, T_INF, &v)) continue;
                float dist = plane_weights ? rm_plane_dist(x, n, a, d) : v;
                float t = fmin(dist / R, 1.0f);
                float wq = (epanechnikov ? 2.0f * (1.0f - t * t) : 1.0f) * fixed_scale;
                fixed_add(acc, 3 * i, wq * flux.x);
                fixed_add(acc, 3 * i + 1, wq * flux.y);
                fixed_add(acc, 3 * i + 2, wq * flux.z);
            }
        }
        /* next node: climb while this is a right child, then the right sibling */
        while (node != 0 && (node & 1) == 0) node = (node - 1) >> 1;
        if (node == 0) break;
        node += 1;
    }
    out_work[2 * s] = work[0];
    out_work[2 * s + 1] = work[1];
}

/* The estimates of rm_splat's sums: E = sum / (fixed_scale pi R^2), written to the hit's
 * place in the caller's order (ids: tree order -> caller's index). */
__kernel void rm_splat_finish(__global const uint *acc, __global const float4 *hx,
                              __global const int *ids, int num_hits, float inv_scale,
                              __global float4 *out_e) {
    int i = get_global_id(0);
    if (i >= num_hits) return;
    float R = hx[i].w;
    float norm = R > 0.0f ? 1.0f / (PI_F * R * R) : 0.0f;
    out_e[ids[i]] = (float4)(fixed_read(acc, 3 * i), fixed_read(acc, 3 * i + 1),
                             fixed_read(acc, 3 * i + 2), 0.0f) * inv_scale * norm;
}
