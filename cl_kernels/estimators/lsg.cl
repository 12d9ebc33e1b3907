/* lsg.cl: line space gathering (Sun et al. 2010, sections 3-4).
 *
 * lsg_scatter (below) forms the same pairs with the roles swapped: a tree over the view
 * segments, one work-item per lighting segment; lsg_splat (at the end) forms them for the
 * view segments on a pinhole camera's rays without a tree, from screen cells.
 *
 * lsg_gather: one work-item per view segment. The view line is the 6-D hyperplane
 * w = (m_v, u_v) (moment in the Plücker frame); a depth-first walk of the perfect 8-ary
 * tree (clscatter/estimators/line_tree.py; a bounded stack, a node's 8 children tested at
 * once from their boxes side by side) visits every node whose box meets the
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
 * return its estimate (0 beyond r). The lighting segment's id, line_ids[line], is read
 * only to record the pair (max_pairs > 0): in a render it costs no load. A pair whose
 * closest point on L (parameter s from L's start) lies outside [own_lo, own_hi) is not
 * this call's (lsg_splat tests a lighting segment in pieces that own their s ranges);
 * the tree walks pass -INFINITY and INFINITY, which own every pair. */
float4 test_pair(__global const LsgLine *L, __global const int *line_ids, int line,
                 const ViewQuery *q, float r, float min_sin, float4 kappa, float g, int4 *cnt,
                 __global int2 *pairs, volatile __global int *pair_count, int max_pairs,
                 float own_lo, float own_hi) {
    cnt->x += 1;
    float4 la = L->a, lu = L->u;
    float llen = la.w;
    la.w = 0.0f;
    float s, t;
    if (seg_seg_dist2(la, lu, llen, q->a, q->u, q->len, &s, &t) >= r * r) return (float4)(0.0f);
    if (s < own_lo || s >= own_hi) return (float4)(0.0f);
    cnt->y += 1;
    if (max_pairs > 0) {
        int k = atomic_inc(pair_count);
        if (k < max_pairs) pairs[k] = (int2)(q->index, line_ids[line]);
    }
    return lsg_pair(la, lu, llen, L->flux, q->a, q->u, q->len, r, min_sin, kappa, g);
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

/* The lanes of ok that are set (non-zero), as bits: bit j for lane j. */
uint lane_bits8(int8 ok) {
    ok &= (int8)(1, 2, 4, 8, 16, 32, 64, 128);
    int4 h = ok.lo | ok.hi;
    int2 h2 = h.lo | h.hi;
    return (uint)(h2.x | h2.y);
}

/* The lanes of block b's plane test near (points 8b .. 8b + 7) that are set and whose
 * point lies in [first, last), as bits (lane_bits8). Most blocks have no point near: one
 * branch tells. */
uint near_in_range(int8 near, int b, int first, int last) {
    int4 n4 = near.lo | near.hi;
    int2 n2 = n4.lo | n4.hi;
    if ((n2.x | n2.y) == 0) return 0u;
    int8 i = (int8)(8 * b) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    return lane_bits8(near & (i >= (int8)(first)) & (i < (int8)(last)));
}

/* The plane test of the 8 Plücker points of block b (line_tree.point_blocks, POINT_LANES
 * = 8: rows u.x, u.y, u.z, m.x, m.y, m.z, a point per lane; P . w = +-d' sin(theta) of
 * the two lines), as bits: bit j set where point 8b + j lies in the leaf's range [rg.x,
 * rg.y) and |P . w| <= thr. */
uint block_near(__global const float8 *points, int b, const Walk *k, int2 rg) {
    __global const float8 *P = points + 6 * b;
    float8 d = (P[0] * k->w4.x + P[1] * k->w4.y) + (P[2] * k->w4.z + P[3] * k->w4.w)
             + (P[4] * k->w2.x + P[5] * k->w2.y);
    return near_in_range(islessequal(fabs(d), (float8)(k->thr)), b, rg.x, rg.y);
}

/* The lowest point of block b among the bits *m (block_near), taken from them. A leaf's
 * points are those of its blocks rg.x / 8 .. (rg.y + 7) / 8 that block_near returns. */
int take_point(uint *m, int b) {
    uint low = *m & (0u - *m);
    *m &= *m - 1u;
    return 8 * b + (int)(31u - clz(low));
}

/* Points that passed the plane test, queued for their exact tests: a point's record is
 * prefetched as it is queued and tested LSG_QUEUE points later (or when the walk is over),
 * so that the load of a record far away in memory overlaps the scan instead of stalling
 * it. First in, first out: the pairs are tested, and their estimates added, in the order
 * of the walk, as without the queue. Without a prefetch (PREFETCH_HINT, common.h: a GPU,
 * whose other work-items hide the latency) the queue is one point deep, which keeps its
 * slot in a register. A build may set LSG_QUEUE (a power of two; tests compare depths). */
#ifndef LSG_QUEUE
#ifdef CLSCATTER_CPU_PREFETCH
#define LSG_QUEUE 16
#else
#define LSG_QUEUE 1
#endif
#endif
typedef struct {
    int item[LSG_QUEUE];
    int pushed, taken;
} Pending;

/* Queue point i; returns the point whose turn has come (queued LSG_QUEUE points
 * earlier), or -1 while the queue fills. */
int pending_push(Pending *p, int i) {
    int due = -1;
    if (p->pushed - p->taken == LSG_QUEUE) due = p->item[p->taken++ & (LSG_QUEUE - 1)];
    p->item[p->pushed++ & (LSG_QUEUE - 1)] = i;
    return due;
}

/* The oldest point still queued, taken from the queue; -1 when it is empty. */
int pending_pop(Pending *p) {
    return p->taken < p->pushed ? p->item[p->taken++ & (LSG_QUEUE - 1)] : -1;
}

/* Lane-wise maximum and minimum without NaN handling (the walk's values are never NaN:
 * Walk's inverse direction is finite). */
float8 max8(float8 a, float8 b) { return select(a, b, isgreater(b, a)); }
float8 min8(float8 a, float8 b) { return select(a, b, isless(b, a)); }

/* One axis of a slab test of the query segment (origin coordinate o, inverse direction
 * inv) against 8 boxes [blo, bhi] grown by r and a rounding allowance: narrows each
 * box's [t0, t1]. */
void slab8(float8 blo, float8 bhi, float o, float inv, float r, float8 *t0, float8 *t1) {
    float8 e = r * 1.0001f + 1e-5f * (1.0f + fabs(blo) + fabs(bhi));
    float8 ta = (blo - e - o) * inv, tb = (bhi + e - o) * inv;
    *t0 = max8(*t0, min8(ta, tb));
    *t1 = min8(*t1, max8(ta, tb));
}

/* Which of the 8 nodes of block g the walk enters, as bits (bit c: column c): the nodes
 * whose 6-D box meets the slab |P . w| <= thr and whose segments' 3-D box the query
 * segment passes within r of (the Plücker test bounds the distance between the infinite
 * lines only; the box test culls segments that lie elsewhere along them). A slab test of
 * the segment against each box grown by r (the points within r of a box lie inside it)
 * and by a rounding allowance, so it never culls a pair closer than r; a box's corner
 * nearest to each side of the plane by w's positive and negative parts. Block 0 holds the
 * root (column 0), block g + 1 the children of node g (line_tree.child_rows; rows 6-D lo
 * 0-5, hi 6-11, 3-D lo 12-14, hi 15-17); an empty box (lo > hi) fails. */
uint block_visited(__global const float8 *kids, int g, const Walk *k, const ViewQuery *q,
                   float r) {
    __global const float8 *c = kids + 18 * g;
    /* the box's nearest corner on each side of the plane: lo (hi) sums p c_lo + n c_hi
     * (p c_hi + n c_lo) over the 6 coordinates, as pairs of pairs */
    float8 lo = ((k->p4.x * c[0] + k->n4.x * c[6]) + (k->p4.y * c[1] + k->n4.y * c[7]))
              + ((k->p4.z * c[2] + k->n4.z * c[8]) + (k->p4.w * c[3] + k->n4.w * c[9]))
              + ((k->p2.x * c[4] + k->n2.x * c[10]) + (k->p2.y * c[5] + k->n2.y * c[11]));
    float8 hi = ((k->p4.x * c[6] + k->n4.x * c[0]) + (k->p4.y * c[7] + k->n4.y * c[1]))
              + ((k->p4.z * c[8] + k->n4.z * c[2]) + (k->p4.w * c[9] + k->n4.w * c[3]))
              + ((k->p2.x * c[10] + k->n2.x * c[4]) + (k->p2.y * c[11] + k->n2.y * c[5]));
    int8 near = islessequal(lo, (float8)(k->thr)) & isgreaterequal(hi, (float8)(-k->thr));
    float8 t0 = (float8)(0.0f), t1 = (float8)(q->len);
    slab8(c[12], c[15], q->a.x, k->inv.x, r, &t0, &t1);
    slab8(c[13], c[16], q->a.y, k->inv.y, r, &t0, &t1);
    slab8(c[14], c[17], q->a.z, k->inv.z, r, &t0, &t1);
    int8 hit = islessequal(t0, t1 + 1e-5f * (1.0f + q->len));
    return lane_bits8(near & hit);
}

/* Levels a walk can descend (line_tree.WALK_LEVELS, which the host checks; its trees are
 * far shallower: a node index must fit an int). */
#define LSG_MAX_LEVELS 12

/* A depth-first walk of the perfect 8-ary tree (children 8g+1..8g+8, first_leaf the
 * first leaf's node index): per level, the first node of the block entered and which of
 * its nodes are still to enter (bits, block_visited). Level 0 is block 0, the root alone.
 * The stack is bounded by LSG_MAX_LEVELS. */
typedef struct {
    int first[LSG_MAX_LEVELS + 1];
    uint todo[LSG_MAX_LEVELS + 1];
    int level;        /* -1: over */
} TreeWalk;

void walk_start(TreeWalk *s, __global const float8 *kids, const Walk *k, const ViewQuery *q,
                float r) {
    s->level = 0;
    s->first[0] = 0;
    s->todo[0] = block_visited(kids, 0, k, q, r);
}

/* The next leaf the walk enters (its index among the leaves), in depth-first order, or -1
 * when the walk is over. */
int walk_next(TreeWalk *s, __global const float8 *kids, int first_leaf, const Walk *k,
              const ViewQuery *q, float r) {
    while (s->level >= 0) {
        uint m = s->todo[s->level];
        if (m == 0u) { s->level--; continue; }
        s->todo[s->level] = m & (m - 1u);                 /* the lowest node, taken */
        int g = s->first[s->level] + (int)(31u - clz(m & (0u - m)));
        if (g >= first_leaf) return g - first_leaf;
        s->level++;
        s->first[s->level] = 8 * g + 1;
        s->todo[s->level] = block_visited(kids, g + 1, k, q, r);
    }
    return -1;
}

__kernel void lsg_gather(__global const float8 *kids, __global const int2 *leaf_ranges,
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
                acc += test_pair(lines + i, line_ids, i, &q, radius, min_sin, kappa, g, &cnt,
                                 pairs, pair_count, max_pairs, -INFINITY, INFINITY);
        } else {
            Walk k = walk_of(&q, pl_centre, pl_inv_scale, radius, max_m1);
            TreeWalk walk;
            walk_start(&walk, kids, &k, &q, radius);
            Pending queue;
            queue.pushed = queue.taken = 0;
            int leaf, i;
            while ((leaf = walk_next(&walk, kids, first_leaf, &k, &q, radius)) >= 0) {
                int2 rg = leaf_ranges[leaf];
                cnt.z += rg.y - rg.x;             /* points the hierarchy did not cull */
                for (int b = rg.x >> 3; b < (rg.y + 7) >> 3; ++b) {
                    uint m = block_near(points, b, &k, rg);
                    while (m != 0u) {
                        int p = take_point(&m, b);
                        PREFETCH_HINT(&lines[p].a);       /* a 48-byte record: 1 or 2 lines */
                        PREFETCH_HINT(&lines[p].flux);
                        if ((i = pending_push(&queue, p)) >= 0)
                            acc += test_pair(lines + i, line_ids, i, &q, radius, min_sin, kappa,
                                             g, &cnt, pairs, pair_count, max_pairs, -INFINITY,
                                             INFINITY);
                    }
                }
            }
            while ((i = pending_pop(&queue)) >= 0)
                acc += test_pair(lines + i, line_ids, i, &q, radius, min_sin, kappa, g, &cnt,
                                 pairs, pair_count, max_pairs, -INFINITY, INFINITY);
        }
        acc *= medium->sigma_s * (views[vi].weight * scale);
    }
    out[vi] += acc;
    counts[vi] += cnt;
}

/* Words of a view's record in lsg_scatter's and lsg_splat's sums (see lsg_scatter). */
#define SCATTER_WORDS 8

/* lsg_scatter's exact test of lighting segment li (lights[li]) against the view segment
 * at tree position i, and for a valid pair its estimate times the view's factor into the
 * view's fixed-point sum and a valid pair into the view's count (see lsg_scatter). */
void scatter_pair(__global const LsgLine *lights, __global const int *light_ids, int li,
                  __global const ViewSegment *views, __global const int *view_ids, int i,
                  float radius, float min_sin, __global const Medium *medium, float scale,
                  float fixed_scale, volatile __global uint *acc, int4 *cnt,
                  __global int2 *pairs, volatile __global int *pair_count, int max_pairs,
                  float own_lo, float own_hi) {
    ViewQuery v;
    if (!load_query(views, i, &v)) return;
    v.index = view_ids[i];
    int before = cnt->y;
    float4 e = test_pair(lights + li, light_ids, li, &v, radius, min_sin, medium->kappa,
                         medium->g, cnt, pairs, pair_count, max_pairs, own_lo, own_hi);
    if (cnt->y == before) return;
    volatile __global uint *rec = acc + SCATTER_WORDS * i;
    atomic_inc(rec + 6);
    e *= medium->sigma_s * (views[i].weight * scale) * fixed_scale;
    fixed_add(rec, 0, e.x);
    fixed_add(rec, 1, e.y);
    fixed_add(rec, 2, e.z);
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
 * the view's record at tree position i, SCATTER_WORDS words cleared by the host before a
 * chunk: its exact fixed-point sums (words 0-5, fixed_sum.h, in units of 1 / fixed_scale)
 * and its valid pairs (word 6), all in one cache line (lsg_scatter_finish adds them into
 * out[] and counts[view].y); the lighting segment's
 * own (tests, valid pairs, points in the visited leaves, 0) go to light_counts. A launch
 * takes lighting segments light_offset .. light_offset + num_lights - 1 (as lsg_gather
 * takes its view segments: the work-items of the last group past them return). */
__kernel void lsg_scatter(__global const float8 *kids, __global const int2 *leaf_ranges,
                          int first_leaf,
                          __global const ViewSegment *views, __global const float8 *points,
                          __global const int *view_ids, float max_m1,
                          __global const LsgLine *lights, __global const int *light_ids,
                          int light_offset, int num_lights, float scale,
                          float4 pl_centre, float pl_inv_scale, float radius, float min_sin,
                          __global const Medium *medium, float fixed_scale,
                          volatile __global uint *acc, __global int4 *light_counts,
                          __global int2 *pairs, volatile __global int *pair_count, int max_pairs) {
    int gid = get_global_id(0);
    if (gid >= num_lights) return;
    int li = light_offset + gid;
    LsgLine L = lights[li];
    ViewQuery q;                                   /* the lighting segment walks the tree */
    q.a = L.a;
    q.a.w = 0.0f;
    q.u = L.u;
    q.len = L.a.w;
    q.index = li;
    int4 cnt = (int4)(0, 0, 0, 0);
    if (q.len > 0.0f) {
        Walk k = walk_of(&q, pl_centre, pl_inv_scale, radius, max_m1);
        TreeWalk walk;
        walk_start(&walk, kids, &k, &q, radius);
        Pending queue;
        queue.pushed = queue.taken = 0;
        int leaf, i;
        while ((leaf = walk_next(&walk, kids, first_leaf, &k, &q, radius)) >= 0) {
            int2 rg = leaf_ranges[leaf];
            cnt.z += rg.y - rg.x;
            for (int b = rg.x >> 3; b < (rg.y + 7) >> 3; ++b) {
                uint m = block_near(points, b, &k, rg);
                while (m != 0u) {
                    int p = take_point(&m, b);
                    PREFETCH_HINT(views + p);             /* a 64-byte record */
                    PREFETCH_HINT(view_ids + p);
                    PREFETCH_HINT((__global const uint *)acc + SCATTER_WORDS * p);
                    if ((i = pending_push(&queue, p)) >= 0)
                        scatter_pair(lights, light_ids, li, views, view_ids, i, radius, min_sin,
                                     medium, scale, fixed_scale, acc, &cnt, pairs,
                                     pair_count, max_pairs, -INFINITY, INFINITY);
                }
            }
        }
        while ((i = pending_pop(&queue)) >= 0)
            scatter_pair(lights, light_ids, li, views, view_ids, i, radius, min_sin, medium,
                         scale, fixed_scale, acc, &cnt, pairs, pair_count, max_pairs,
                         -INFINITY, INFINITY);
    }
    light_counts[li] = cnt;
}

/* out[view_ids[i]] += lsg_scatter's sums at tree position i (divided by fixed_scale:
 * times inv_scale), and its valid pairs into counts[view_ids[i]].y. */
__kernel void lsg_scatter_finish(__global const uint *acc, __global const int *view_ids,
                                 int num_views, float inv_scale, __global float4 *out,
                                 __global int *counts) {
    int i = get_global_id(0);
    if (i >= num_views) return;
    __global const uint *rec = acc + SCATTER_WORDS * i;
    int v = view_ids[i];
    out[v] += (float4)(fixed_read(rec, 0), fixed_read(rec, 1), fixed_read(rec, 2), 0.0f)
              * inv_scale;
    counts[4 * v + 1] += (int)rec[6];
}

/* ---- The lighting side over camera rays: screen cells (lsg_splat) ----
 *
 * A view segment on a camera ray (a line through the eye: the camera is a pinhole) needs
 * no tree. The host sorts such segments by the cell of a grid over the image plane that
 * their direction falls in (tangent coordinates X = x / z, Y = y / z in the camera frame
 * ex, ey, ez; grid: the lower corner (X, Y) and the inverse cell size in x and y, nx by ny
 * cells, cell_start[c] .. cell_start[c + 1] the segments of cell c = row nx + column),
 * and a lighting segment's candidates are the segments of the cells whose rays can pass
 * within r of it. Exact tests, estimates and sums are lsg_scatter's (scatter_pair), so
 * the pairs and the fixed-point sums are the same as from the tree; only the candidates
 * differ.
 *
 * The cells: the lighting segment is clipped to the frustum of the grid's rays grown by
 * R (r, plus reach, the host's bound on how far a segment's line passes from the eye,
 * plus a rounding allowance: no point within r of a camera ray is outside it) and cut
 * into pieces. A piece whose depth z stays above NEAR_REACHES R projects to a 2-D segment
 * in the tangent plane, and a ball of radius R around a point of it at depth z to within
 * R sqrt(1 + X^2 + Y^2) / (z - R) of the point's projection (|dX| <= (|dxy| + |X||dz|) /
 * (z + dz), Cauchy-Schwarz): the piece's cells are those its 2-D segment, widened by the
 * largest such radius on the piece (the depth at most doubles along a piece, so this is
 * at most about twice the narrowest), crosses, taken row by row: a row's cells are
 * consecutive in the cell order, so each row is one run of the segments, read in order.
 * The part nearer the camera's plane than that (a lighting segment passing within a few
 * R of the eye) takes every cell. Pieces own the pairs whose closest point on the
 * lighting segment lies in their part of it (test_pair's own_lo, own_hi; the first and last extend to
 * infinity), so a view segment that two pieces' cells both hold is counted once. */
#define NEAR_REACHES 4.0f
#define SPLAT_MAX_PIECES 32

/* Narrow [*s0, *s1] to where f0 + f1 s <= 0 (empty: *s0 > *s1). */
void clip_below(float f0, float f1, float *s0, float *s1) {
    if (f1 > 0.0f) *s1 = fmin(*s1, -f0 / f1);
    else if (f1 < 0.0f) *s0 = fmax(*s0, -f0 / f1);
    else if (f0 > 0.0f) *s0 = INFINITY;
}

/* floor(v) as a cell index, clamped to [-1, n] (v may be huge or infinite). */
int cell_floor(float v, int n) { return (int)floor(clamp(v, -1.0f, (float)n)); }

/* Test lighting segment li against the view segments FIRST .. LAST - 1 of the cell order,
 * owning the pairs whose closest point on it lies in [own_lo, own_hi): first the plane
 * test of the two lines (a camera ray's moment about the eye is at most reach, so |P . w|
 * = |u_v . m_l + u_l . m_v| <= d sin(theta) needs |u_v . m_l| <= d + reach: thr), then
 * the exact one. */
#define SPLAT_TEST(I) \
    scatter_pair(lights, light_ids, li, views, view_ids, (I), radius, min_sin, medium, scale, \
                 fixed_scale, acc, &cnt, pairs, pair_count, max_pairs, own_lo, own_hi)
#define SPLAT_RANGE(FIRST, LAST) { \
    int f_ = (FIRST), l_ = (LAST); \
    cnt.z += max(l_ - f_, 0); \
    for (int b_ = f_ >> 3; 8 * b_ < l_; ++b_) { \
        uint m_ = dir_block_near(dirs, b_, ml, thr, f_, l_); \
        while (m_ != 0u) { \
            int v_ = take_point(&m_, b_); \
            PREFETCH_HINT(views + v_); \
            PREFETCH_HINT((__global const uint *)acc + SCATTER_WORDS * v_); \
            int due_ = pending_push(&queue, v_); \
            if (due_ >= 0) SPLAT_TEST(due_); \
        } \
    } }

/* The plane test |u_v . ml| <= thr of the 8 view segments of block b of the cell order
 * (line_tree.point_blocks of their unit directions u_v: rows x, y, z, a segment per lane),
 * as bits: bit j set where segment 8b + j lies in [first, last) and passes (in the order
 * of the cell order, as take_point takes them). */
uint dir_block_near(__global const float8 *dirs, int b, float4 ml, float thr, int first,
                    int last) {
    __global const float8 *D = dirs + 3 * b;
    float8 d = D[0] * ml.x + D[1] * ml.y + D[2] * ml.z;
    return near_in_range(islessequal(fabs(d), (float8)(thr)), b, first, last);
}

__kernel void lsg_splat(__global const ViewSegment *views, __global const float8 *dirs,
                        __global const int *view_ids,
                        __global const int *cell_start, int nx, int ny, float4 eye,
                        float4 ex, float4 ey, float4 ez, float4 grid, float reach,
                        __global const LsgLine *lights, __global const int *light_ids,
                        int light_offset, int num_lights, float scale, float radius,
                        float min_sin, __global const Medium *medium, float fixed_scale,
                        volatile __global uint *acc, __global int4 *light_counts,
                        __global int2 *pairs,
                        volatile __global int *pair_count, int max_pairs) {
    int gid = get_global_id(0);
    if (gid >= num_lights) return;
    int li = light_offset + gid;
    float4 la = lights[li].a, lu = lights[li].u;
    float len = la.w;
    la.w = 0.0f;
    int4 cnt = (int4)(0, 0, 0, 0);
    float4 w = la - eye;
    float3 p = (float3)(dot3(w, ex), dot3(w, ey), dot3(w, ez));
    float3 d = (float3)(dot3(lu, ex), dot3(lu, ey), dot3(lu, ez));
    float R = (radius + reach) * 1.001f + 2e-6f * (1.0f + length(p) + len);
    float4 ml = cross3(w, lu);                   /* the lighting line's moment about the eye */
    float thr = radius * 1.0001f + reach + 1e-5f * (1.0f + fabs(ml.x) + fabs(ml.y) + fabs(ml.z));
    /* the frustum of the grid's rays grown by R: its four sides and z >= -R */
    float xlo = grid.x, xhi = grid.x + (float)nx / grid.z;
    float ylo = grid.y, yhi = grid.y + (float)ny / grid.w;
    float s0 = 0.0f, s1 = len > 0.0f ? len : -1.0f;
    clip_below(p.x - xhi * p.z - R * sqrt(1.0f + xhi * xhi), d.x - xhi * d.z, &s0, &s1);
    clip_below(xlo * p.z - p.x - R * sqrt(1.0f + xlo * xlo), xlo * d.z - d.x, &s0, &s1);
    clip_below(p.y - yhi * p.z - R * sqrt(1.0f + yhi * yhi), d.y - yhi * d.z, &s0, &s1);
    clip_below(ylo * p.z - p.y - R * sqrt(1.0f + ylo * ylo), ylo * d.z - d.y, &s0, &s1);
    clip_below(-p.z - R, -d.z, &s0, &s1);
    if (s0 <= s1) {
        /* the near part (z < NEAR_REACHES R: every cell) on one side, the far part in
         * pieces of depth ratio <= 2 on the other, in the order of s */
        float zg = NEAR_REACHES * R;
        float za = p.z + s0 * d.z, zb = p.z + s1 * d.z;
        float sg = d.z != 0.0f ? clamp((zg - p.z) / d.z, s0, s1) : (za < zg ? s1 : s0);
        /* [n0, n1]: near, [f0, f1]: far (either may be empty) */
        float n0 = s0, n1 = s0, f0 = s0, f1 = s1;
        int near_first = 1;
        if (za < zg || zb < zg) {
            if (za >= zg) { f1 = sg; n0 = sg; n1 = s1; near_first = 0; }   /* far, near */
            else if (zb >= zg) { n1 = sg; f0 = sg; }                       /* near, far */
            else { n1 = s1; f0 = s1; f1 = s1 - 1.0f; }                    /* near only */
        }
        float zlo = fmin(p.z + f0 * d.z, p.z + f1 * d.z), zhi = fmax(p.z + f0 * d.z, p.z + f1 * d.z);
        int pieces = f1 >= f0 ? (zhi > 2.0f * zlo ? (int)ceil(log2(zhi / zlo)) : 1) : 0;
        pieces = min(pieces, SPLAT_MAX_PIECES);
        int has_near = n1 > n0 || (za < zg && zb < zg);
        int total = pieces + has_near;
        for (int j = 0; j < total; ++j) {
            int is_near = has_near && (near_first ? j == 0 : j == total - 1);
            float sa, sb;
            if (is_near) {
                sa = n0;
                sb = n1;
            } else {
                /* far piece k in the order of s: boundaries where z = zlo 2^m */
                int k = j - (has_near && near_first);
                int m0 = d.z > 0.0f ? k : pieces - 1 - k;       /* its lower depth index */
                float zs0 = zlo * exp2((float)m0), zs1 = m0 + 1 == pieces ? zhi : zlo * exp2((float)(m0 + 1));
                float b0 = m0 == 0 ? (p.z + f0 * d.z <= p.z + f1 * d.z ? f0 : f1)
                                   : (zs0 - p.z) / d.z;
                float b1 = m0 + 1 == pieces ? (p.z + f0 * d.z <= p.z + f1 * d.z ? f1 : f0)
                                            : (zs1 - p.z) / d.z;
                if (pieces == 1) { b0 = f0; b1 = f1; }
                sa = fmin(b0, b1);
                sb = fmax(b0, b1);
            }
            float own_lo = j == 0 ? -INFINITY : sa, own_hi = j == total - 1 ? INFINITY : sb;
            Pending queue;      /* exact tests behind a prefetch, as in the tree walks */
            queue.pushed = queue.taken = 0;
            if (is_near) {
                SPLAT_RANGE(0, cell_start[nx * ny]);
                for (int i; (i = pending_pop(&queue)) >= 0;) SPLAT_TEST(i);
                continue;
            }
            float3 A = p + sa * d, B = p + sb * d;
            float zmin = fmin(A.z, B.z);
            float XA = A.x / A.z, YA = A.y / A.z, XB = B.x / B.z, YB = B.y / B.z;
            float S = fmax(sqrt(1.0f + XA * XA + YA * YA), sqrt(1.0f + XB * XB + YB * YB));
            float rho = R * S / (zmin - R) * 1.001f + 1e-5f * S;
            /* cell coordinates (x: columns, y: rows), the piece's ends sorted by row */
            float xa = (XA - grid.x) * grid.z, ya = (YA - grid.y) * grid.w;
            float xb = (XB - grid.x) * grid.z, yb = (YB - grid.y) * grid.w;
            float rx = rho * grid.z, ry = rho * grid.w;
            if (ya > yb) {
                float t = ya; ya = yb; yb = t;
                t = xa; xa = xb; xb = t;
            }
            float span = yb - ya;
            int c0 = max(cell_floor(ya - ry, ny), 0), c1 = min(cell_floor(yb + ry, ny), ny - 1);
            for (int c = c0; c <= c1; ++c) {
                /* the part of the piece within ry of row c, and its columns: one run of
                 * the cell order */
                float lo = fmax(ya, (float)c - ry), hi = fmin(yb, (float)(c + 1) + ry);
                float e1 = span > 1e-6f ? xa + clamp((lo - ya) / span, 0.0f, 1.0f) * (xb - xa)
                                        : fmin(xa, xb);
                float e2 = span > 1e-6f ? xa + clamp((hi - ya) / span, 0.0f, 1.0f) * (xb - xa)
                                        : fmax(xa, xb);
                int r0 = max(cell_floor(fmin(e1, e2) - rx, nx), 0);
                int r1 = min(cell_floor(fmax(e1, e2) + rx, nx), nx - 1);
                if (r0 <= r1) {
                    SPLAT_RANGE(cell_start[c * nx + r0], cell_start[c * nx + r1 + 1]);
                }
            }
            for (int i; (i = pending_pop(&queue)) >= 0;) SPLAT_TEST(i);
        }
    }
    light_counts[li] += cnt;
}
