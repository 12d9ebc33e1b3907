/* lsg.cl: line space gathering (Sun et al. 2010, sections 3-4).
 *
 * lsg_scatter (below) forms the same pairs with the roles swapped: a tree over the view
 * segments, one work-item per lighting segment.
 *
 * lsg_gather: one work-item per view segment. The view line is the 6-D hyperplane
 * w = (m_v, u_v) (moment in the Plücker frame); a stackless depth-first walk of the
 * perfect 8-ary tree (clscatter/estimators/line_tree.py) visits every node whose box meets the
 * slab |P . w| <= r' (|P . w| = d sin theta <= d, so nothing within r is culled) and whose
 * segments' 3-D box the view segment passes within r of (the Plücker test bounds the
 * distance between the infinite lines only; the box test culls segments that lie
 * elsewhere along them), tests
 * each point of a visited leaf against the same slab, then the surviving pairs with the
 * exact segment-to-segment distance, and adds the cylinder-kernel estimate of lsg.h for
 * every pair closer than r.
 *
 * Regions: the lighting segments of a launch all lie in one region (the scene medium, or
 * the inside of one dielectric material whose interior scatters), `medium` holds that
 * region's coefficients (sigma_s, kappa, g: the scene medium's, or the material's interior
 * ones, built on the host), and only the view segments of the same region (view_region
 * == region) gather; the others add 0. Light is gathered only where it is.
 *
 * Sample groups: with indexed = 1 work-item gid gathers view segment view_index[view_offset +
 * gid] (the segments of some of each pixel's camera samples, clscatter/estimators/line_gather.py)
 * and its estimate is multiplied by scale (spp over the samples in the group), so that
 * group alone estimates the whole pixel; indexed = 0 gathers view_offset + gid, scale 1.
 *
 * exhaustive = 1: the same per-pair code for every (view, light) pair, no culling: the
 * reference the tree must reproduce exactly (tests/test_lsg.py).
 *
 * The kernel adds its estimate into out[view] (so chunks of lighting rays sum), adds
 * (exact tests, valid pairs, points in the visited leaves, 0) to counts[view] (summed
 * the same way; the third is what the hierarchy alone leaves, the paper's "line
 * intersection tests" after culling) and,
 * when max_pairs > 0, appends every valid (view, light id) pair to pairs (tests compare
 * the sets).
 */
#include "common.h"
#include "lsg.h"
#include "fixed_sum.h"

typedef struct {
    float4 a, u;      /* view segment start, unit direction (normalised frame) */
    float len;
    int index;        /* global view segment index */
} ViewQuery;

/* Exact test of one pair (lighting segment L, view segment q): count, record, and
 * return its estimate (0 beyond r). */
float4 test_pair(LsgLine L, int line_id, const ViewQuery *q, float r,
                 float min_sin, float4 kappa, float g, int4 *cnt,
                 __global int2 *pairs, volatile __global int *pair_count, int max_pairs) {
    float4 la = L.a;
    float llen = la.w;
    la.w = 0.0f;
    float s, t;
    cnt->x += 1;
    if (seg_seg_dist2(la, L.u, llen, q->a, q->u, q->len, &s, &t) >= r * r) return (float4)(0.0f);
    cnt->y += 1;
    if (max_pairs > 0) {
        int k = atomic_inc(pair_count);
        if (k < max_pairs) pairs[k] = (int2)(q->index, line_id);
    }
    return lsg_pair(L, q->a, q->u, q->len, r, min_sin, kappa, g);
}

int load_query(__global const ViewSegment *views, int vi, ViewQuery *q) {
    ViewSegment v = views[vi];
    float4 ab = v.b - v.a;
    ab.w = 0.0f;
    float len = length3(ab);
    q->a = v.a;
    q->a.w = 0.0f;
    q->u = len > 0.0f ? ab / len : (float4)(0.0f);
    q->len = len;
    q->index = vi;
    return len > 0.0f;
}

/* The region of a view segment (common.h: a.w, 0 in the scene medium, m + 1 inside
 * dielectric material m). */
int view_region(__global const ViewSegment *v) { return (int)rint(v->a.w); }

/* What a tree walk tests its nodes and points against (walk_of): the query's line as the
 * 6-D hyperplane w = (m, u) in the Plücker frame (its moment m taken there), as w4 (w0..w3)
 * and w2 (w4, w5), with its positive and negative parts (p, n: w = p + n, one of them 0 in
 * each coordinate); the plane test's threshold (lsg_threshold); and the query segment's
 * inverse direction for the 3-D box test, finite (a coordinate below 1e-20 in magnitude is
 * taken as 1e-20), so that no product in that test is 0 * inf. */
typedef struct {
    float4 w4, p4, n4;
    float2 w2, p2, n2;
    float4 inv;
    float thr;
} Walk;

Walk walk_of(const ViewQuery *q, float4 pl_centre, float pl_inv_scale, float radius,
             float max_m1) {
    Walk k;
    float4 m = cross3((q->a - pl_centre) * pl_inv_scale, q->u);
    k.w4 = (float4)(m.x, m.y, m.z, q->u.x);
    k.w2 = (float2)(q->u.y, q->u.z);
    k.p4 = fmax(k.w4, 0.0f);
    k.n4 = fmin(k.w4, 0.0f);
    k.p2 = fmax(k.w2, 0.0f);
    k.n2 = fmin(k.w2, 0.0f);
    float4 u = q->u;
    u.x = fabs(u.x) < 1e-20f ? 1e-20f : u.x;
    u.y = fabs(u.y) < 1e-20f ? 1e-20f : u.y;
    u.z = fabs(u.z) < 1e-20f ? 1e-20f : u.z;
    u.w = 1.0f;
    k.inv = 1.0f / u;
    k.thr = lsg_threshold(radius, pl_inv_scale, m, max_m1);
    return k;
}

/* Range of P . w over a node's 6-D box against [-thr, thr]: the box's corner nearest to
 * each side of the plane, by w's positive and negative parts (no per-coordinate minimum;
 * an empty box, lo > hi, fails). */
int node_near(__global const LineNode *nd, const Walk *k) {
    float4 lo4 = vload4(0, nd->lo), hi4 = vload4(0, nd->hi);
    float2 lo2 = vload2(2, nd->lo), hi2 = vload2(2, nd->hi);
    float4 a = k->p4 * lo4 + k->n4 * hi4, b = k->p4 * hi4 + k->n4 * lo4;
    float2 c = k->p2 * lo2 + k->n2 * hi2, d = k->p2 * hi2 + k->n2 * lo2;
    float lo = (a.x + a.y) + (a.z + a.w) + (c.x + c.y);
    float hi = (b.x + b.y) + (b.z + b.w) + (d.x + d.y);
    return lo <= k->thr && hi >= -k->thr;
}

/* Does the view segment pass within r of the 3-D box [lo, hi]? A slab test of the segment
 * against the box grown by r (the set of points within r of the box lies inside it) and by
 * a rounding allowance: it never culls a pair closer than r. */
int seg_near_box(const ViewQuery *q, const Walk *k, float4 lo, float4 hi, float r) {
    float4 e = r * 1.0001f + 1e-5f * (1.0f + fabs(lo) + fabs(hi));
    float4 ta = (lo - e - q->a) * k->inv, tb = (hi + e - q->a) * k->inv;
    int4 swap = isless(tb, ta);
    float4 near = select(ta, tb, swap), far = select(tb, ta, swap);
    float t0 = near.x > near.y ? near.x : near.y;   /* no NaN here: plain comparisons */
    t0 = near.z > t0 ? near.z : t0;
    t0 = t0 > 0.0f ? t0 : 0.0f;
    float t1 = far.x < far.y ? far.x : far.y;
    t1 = far.z < t1 ? far.z : t1;
    t1 = t1 < q->len ? t1 : q->len;
    return t0 <= t1 + 1e-5f * (1.0f + q->len);
}

/* P . w for a stored Plücker point: +-d' sin(theta) of the two lines */
float plane_side(float8 P, const Walk *k) {
    return dot(P.s0123, k->w4) + P.s4 * k->w2.x + P.s5 * k->w2.y;
}

/* Does the walk enter node g: its 6-D box meets the slab |P . w| <= thr and the query
 * segment passes within r of its segments' 3-D box? */
int node_visited(__global const LineNode *nodes, __global const float4 *boxes, int g,
                 const Walk *k, const ViewQuery *q, float r) {
    return node_near(&nodes[g], k) && seg_near_box(q, k, boxes[2 * g], boxes[2 * g + 1], r);
}

/* The node after g's subtree in depth-first order (climb while g is the last of its 8
 * siblings, then its next sibling); 0 when the walk is over. */
int next_node(int g) {
    while (g != 0 && (g & 7) == 0) g = (g - 1) >> 3;
    return g == 0 ? 0 : g + 1;
}

/* The stackless depth-first walk of the perfect 8-ary tree (children 8g+1..8g+8, parent
 * (g-1)/8): from node *at (0 to start), the next leaf it enters (its index among the
 * leaves), or -1 when the walk is over; *at is left where the walk resumes. */
int walk_to_leaf(__global const LineNode *nodes, __global const float4 *boxes,
                 int first_leaf, int *at, const Walk *k, const ViewQuery *q, float r) {
    int g = *at;
    while (g >= 0) {
        if (node_visited(nodes, boxes, g, k, q, r)) {
            if (g < first_leaf) {
                g = 8 * g + 1;                        /* descend to the first child */
                continue;
            }
            int next = next_node(g);
            *at = next == 0 ? -1 : next;
            return g - first_leaf;
        }
        g = next_node(g);
        if (g == 0) break;
    }
    *at = -1;
    return -1;
}

__kernel void lsg_gather(__global const LineNode *nodes, __global const float4 *boxes,
                         __global const int2 *leaf_ranges,
                         int first_leaf, __global const LsgLine *lines,
                         __global const float8 *points,
                         __global const int *line_ids, int num_lines, float max_m1,
                         __global const ViewSegment *views, int view_offset, int num_views,
                         __global const int *view_index, int indexed, float scale,
                         float4 pl_centre, float pl_inv_scale, float radius, float min_sin,
                         __global const Medium *medium, int region, int exhaustive,
                         __global float4 *out, __global int4 *counts,
                         __global int2 *pairs, volatile __global int *pair_count, int max_pairs) {
    int gid = get_global_id(0);
    if (gid >= num_views) return;
    int vi = indexed ? view_index[view_offset + gid] : view_offset + gid;
    ViewQuery q;
    int4 cnt = (int4)(0, 0, 0, 0);
    float4 acc = (float4)(0.0f);
    if (view_region(&views[vi]) == region && load_query(views, vi, &q)) {
        float4 kappa = medium->kappa;
        float g = medium->g;
        if (exhaustive) {
            /* the reference: every pair, no culling */
            cnt.z = num_lines;
            for (int i = 0; i < num_lines; ++i)
                acc += test_pair(lines[i], line_ids[i], &q, radius, min_sin, kappa, g, &cnt,
                                 pairs, pair_count, max_pairs);
        } else {
            Walk k = walk_of(&q, pl_centre, pl_inv_scale, radius, max_m1);
            int at = 0, leaf;
            while ((leaf = walk_to_leaf(nodes, boxes, first_leaf, &at, &k, &q, radius)) >= 0) {
                int2 rg = leaf_ranges[leaf];
                cnt.z += rg.y - rg.x;             /* points the hierarchy did not cull */
                for (int i = rg.x; i < rg.y; ++i) {
                    if (fabs(plane_side(points[i], &k)) > k.thr) continue;
                    acc += test_pair(lines[i], line_ids[i], &q, radius, min_sin, kappa, g,
                                     &cnt, pairs, pair_count, max_pairs);
                }
            }
        }
        acc *= medium->sigma_s * (views[vi].weight * scale);
    }
    out[vi] += acc;
    counts[vi] += cnt;
}

/* lsg_scatter: the same pairs and estimates formed from the lighting side (a Gatherer
 * with queries = "lights", clscatter/estimators/line_gather.py). The perfect 8-ary tree
 * is built over the VIEW segments' Plücker points (once per set of view segments: every
 * pass and every light move reuses it) and one work-item per lighting segment walks it
 * with its own line as the hyperplane w = (m_l, u_l): the side relation is symmetric, so
 * the culling is the same test with the roles swapped. views[i] is the view segment at
 * tree position i (its record as lsg_gather reads it, so load_query gives the same
 * floats) and view_ids[i] its index. Each valid pair's estimate (test_pair, as
 * lsg_gather forms it) times the view segment's factor sigma_s (weight scale) goes into
 * that view's exact fixed-point sum at tree position i (fixed_sum.h, in units of
 * 1 / fixed_scale, cleared by the host before a chunk; lsg_scatter_finish adds the sums
 * into out[]), and the
 * view's valid-pair count (counts[view].y) is raised atomically; the lighting segment's
 * own (tests, valid pairs, points in the visited leaves, 0) go to light_counts. */
__kernel void lsg_scatter(__global const LineNode *nodes, __global const float4 *boxes,
                          __global const int2 *leaf_ranges, int first_leaf,
                          __global const ViewSegment *views, __global const float8 *points,
                          __global const int *view_ids, float max_m1,
                          __global const LsgLine *lights, __global const int *light_ids,
                          int light_offset, int num_lights, float scale,
                          float4 pl_centre, float pl_inv_scale, float radius, float min_sin,
                          __global const Medium *medium, float fixed_scale,
                          volatile __global uint *acc, volatile __global int *counts,
                          __global int4 *light_counts,
                          __global int2 *pairs, volatile __global int *pair_count, int max_pairs) {
    int li = light_offset + get_global_id(0);
    if (li >= num_lights) return;
    LsgLine L = lights[li];
    ViewQuery q;                                   /* the lighting segment walks the tree */
    q.a = L.a;
    q.a.w = 0.0f;
    q.u = L.u;
    q.len = L.a.w;
    q.index = li;
    int4 cnt = (int4)(0, 0, 0, 0);
    if (q.len > 0.0f) {
        float4 kappa = medium->kappa, sigma_s = medium->sigma_s;
        float g = medium->g;
        Walk k = walk_of(&q, pl_centre, pl_inv_scale, radius, max_m1);
        int at = 0, leaf;
        while ((leaf = walk_to_leaf(nodes, boxes, first_leaf, &at, &k, &q, radius)) >= 0) {
            int2 rg = leaf_ranges[leaf];
            cnt.z += rg.y - rg.x;
            for (int i = rg.x; i < rg.y; ++i) {
                if (fabs(plane_side(points[i], &k)) > k.thr) continue;
                ViewQuery v;
                if (!load_query(views, i, &v)) continue;
                v.index = view_ids[i];
                int before = cnt.y;
                float4 e = test_pair(L, light_ids[li], &v, radius, min_sin, kappa, g, &cnt,
                                     pairs, pair_count, max_pairs);
                if (cnt.y == before) continue;
                atomic_inc(&counts[4 * v.index + 1]);
                e *= sigma_s * (views[i].weight * scale) * fixed_scale;
                fixed_add(acc, 3 * i, e.x);
                fixed_add(acc, 3 * i + 1, e.y);
                fixed_add(acc, 3 * i + 2, e.z);
            }
        }
    }
    light_counts[li] = cnt;
}

/* out[view_ids[i]] += lsg_scatter's sum at tree position i (divided by fixed_scale:
 * times inv_scale). */
__kernel void lsg_scatter_finish(__global const uint *acc, __global const int *view_ids,
                                 int num_views, float inv_scale, __global float4 *out) {
    int i = get_global_id(0);
    if (i >= num_views) return;
    out[view_ids[i]] += (float4)(fixed_read(acc, 3 * i), fixed_read(acc, 3 * i + 1),
                                 fixed_read(acc, 3 * i + 2), 0.0f) * inv_scale;
}
