/* raymap.h: ray proximity queries over the ray map's kd-tree (Havran et al. 2005).
 *
 * The tree is built on the host (clscatter/estimators/segment_tree.py) and read as is:
 * RMNode records (box, kind, children or the leaf's reference range) and an int array of
 * segment references sorted by leaf. Segments are given as start a, end b (float4, the
 * geometry the tree indexes; a == b for photons) and a unit travel direction d.
 *
 * Queries (Sec. 3.2) for a centre x with unit normal n:
 *   intersection: disc (the segment crosses the disc of radius r in the plane through x
 *   normal to n), hemisphere (it comes within r of x on the side n points to), sphere,
 *   axis-aligned box; disc and hemisphere take incoming rays only (d . n < 0).
 *   K nearest under a metric: RM_PLANE (II.a: distance from x to where the ray's supporting
 *   line meets the tangent plane), RM_SEGMENT (II.b), RM_LINE (II.c), RM_HEMIDISC
 *   (max of II.a and the distance to the segment's part above the plane: the paper's
 *   hemisphere-disc, Sec. 4.2); optionally restricted to a domain (sphere or hemisphere of
 *   radius r: a segment then qualifies when it meets the domain and its distance <= r)
 *   and to incoming rays.
 *
 * Traversal: explicit stack (no recursion), nearer child first; a node is skipped when
 * its box lies farther than the current bound (the K-th distance once K are found, else
 * the domain radius). The box distance bounds RM_SEGMENT and RM_HEMIDISC from below (a
 * segment's closest point lies in a leaf that lists it), so those searches prune; RM_PLANE
 * and RM_LINE have no such bound and visit every leaf of their domain. The K best are
 * kept in a bounded max-heap in private memory (root = the farthest kept); a segment
 * listed by several leaves is kept once. Directional nodes (Sec. 6.2): a query whose
 * normal is within alpha of the node's reference direction visits the back child only.
 */
#ifndef CLSCATTER_RAYMAP_H
#define CLSCATTER_RAYMAP_H
#include "common.h"

#ifndef RM_K
#define RM_K 64             /* largest K of a K-nearest query (heap size) */
#endif
#define RM_STACK 96         /* D_max = 30 spatial levels + directional nodes, two per level */
/* The K-nearest heap lives in private memory up to K = 256; larger heaps (8 KB per
 * work-item at K = 1024) would overflow private memory / work-item stacks on many
 * devices, so they live in a global scratch buffer (RM_K floats + ints per work-item). */
#if RM_K > 256
#define RM_HEAP __global
#else
#define RM_HEAP
#endif
#define KNN_HEAP RM_HEAP
#include "knn_heap.h"

#define RM_LEAF 0
#define RM_SPATIAL 1
#define RM_DIRECTIONAL 2

#define RM_PLANE 0
#define RM_SEGMENT 1
#define RM_LINE 2
#define RM_HEMIDISC 3

#define RM_DOM_NONE 0
#define RM_DOM_SPHERE 1
#define RM_DOM_HEMISPHERE 2

#define RM_Q_DISC 0
#define RM_Q_HEMISPHERE 1
#define RM_Q_SPHERE 2
#define RM_Q_BOX 3

typedef struct {
    float4 lo, hi;      /* cell */
    float4 aux;         /* spatial: split position, axis; directional: reference dir, sin(alpha) */
    int kind;           /* RM_LEAF, RM_SPATIAL, RM_DIRECTIONAL */
    int child;          /* first child (the second is child + 1) */
    int first, count;   /* leaf: references [first, first + count) */
} RMNode;

/* ---- distances (float32; the host mirrors them in knn_queries.py) ---- */
float rm_seg_dist(float4 x, float4 a, float4 b) {
    float4 ab = b - a;
    float l2 = dot3(ab, ab);
    float t = l2 > 0.0f ? clamp(dot3(x - a, ab) / l2, 0.0f, 1.0f) : 0.0f;
    return length3(a + t * ab - x);
}

float rm_line_dist(float4 x, float4 a, float4 d) { return length3(cross3(x - a, d)); }

/* II.a: where the supporting line meets the plane through x normal to n (T_INF if parallel) */
float rm_plane_dist(float4 x, float4 n, float4 a, float4 d) {
    float dn = dot3(d, n);
    if (fabs(dn) < 1e-7f) return T_INF;
    float t = dot3(x - a, n) / dn;
    return length3(a + t * d - x);
}

/* Distance from x to the part of [a, b] with (y - x) . n >= 0 (T_INF if none): the
 * hemisphere of radius r is met iff this is <= r. */
float rm_hemi_dist(float4 x, float4 n, float4 a, float4 b) {
    float sa = dot3(a - x, n), sb = dot3(b - x, n);
    if (sa < 0.0f && sb < 0.0f) return T_INF;
    if (sa < 0.0f) a = a + (sa / (sa - sb)) * (b - a);
    else if (sb < 0.0f) b = b + (sb / (sb - sa)) * (a - b);
    return rm_seg_dist(x, a, b);
}

float rm_metric(int metric, float4 x, float4 n, float4 a, float4 b, float4 d) {
    if (metric == RM_SEGMENT) return rm_seg_dist(x, a, b);
    if (metric == RM_LINE) return rm_line_dist(x, a, d);
    if (metric == RM_PLANE) return rm_plane_dist(x, n, a, d);
    return fmax(rm_plane_dist(x, n, a, d), rm_hemi_dist(x, n, a, b));
}

float rm_box_dist(__global const RMNode *nd, float4 x) {
    float4 e = fmax(fmax(nd->lo - x, x - nd->hi), (float4)(0.0f));
    return sqrt(e.x * e.x + e.y * e.y + e.z * e.z);
}

/* max over the cell of (y - x) . n: < 0 when the cell lies below the tangent plane */
float rm_box_above(__global const RMNode *nd, float4 x, float4 n) {
    float4 m = fmax(nd->lo * n, nd->hi * n);
    return m.x + m.y + m.z - dot3(x, n);
}

/* Does the query want only the back child of a directional node? */
int rm_covered(__global const RMNode *nd, float4 n, float cos_alpha) {
    return dot3(nd->aux, n) >= cos_alpha;
}

/* Segments a query has put in its heap so far, for private heaps: an open-addressing
 * table of RM_SEEN ids (stored + 1; 0 = empty) after the heap's RM_K ids in hx, and the
 * table's fill after it. A segment listed by several leaves is offered by each: the
 * table finds the repeat at once where a scan of the heap costs up to K compares. */
#if RM_K <= 256
#define RM_SEEN (2 * RM_K)
#define RM_HX_SIZE (RM_K + RM_SEEN + 1)
#else
#define RM_HX_SIZE RM_K
#endif

/* Empty the table of segments seen (with the heap's count set to 0: a new query). */
void rm_seen_clear(RM_HEAP int *hx) {
#ifdef RM_SEEN
    for (int j = RM_K; j < RM_HX_SIZE; ++j) hx[j] = 0;
#endif
}

/* Keep segment idx at distance v in the heap, once. A full heap refuses v >= its root
 * first (knn_heap_insert would refuse it too). A repeat carries the same v, so one that
 * was put in the heap before is either still there or was evicted by nearer ones (the
 * root only shrinks) and would be refused now: a segment put in before is skipped. While
 * the table is at most half full it answers that; after, a scan of the heap does (exact
 * as well: an evicted repeat is refused by the root test). */
void rm_heap_push(RM_HEAP float *hd, RM_HEAP int *hx, int *count, int k, float v, int idx) {
    if (*count == k && !(v < hd[0])) return;
#ifdef RM_SEEN
    int fill = hx[RM_K + RM_SEEN];
    if (fill < RM_SEEN / 2) {
        uint h = ((uint)idx * 2654435761u) & (RM_SEEN - 1);
        while (hx[RM_K + h] != 0) {
            if (hx[RM_K + h] == idx + 1) return;
            h = (h + 1) & (RM_SEEN - 1);
        }
        hx[RM_K + h] = idx + 1;
        hx[RM_K + RM_SEEN] = fill + 1;
        knn_heap_insert(hd, hx, count, k, v, idx);
        return;
    }
#endif
    for (int j = 0; j < *count; ++j)
        if (hx[j] == idx) return;
    knn_heap_insert(hd, hx, count, k, v, idx);
}

/* Does segment (a, b, d) qualify for the query (x, n): incoming when asked, within the
 * domain of radius r, metric <= r? If so *v is its metric value. The domain's distance is
 * computed once and reused by the metric it bounds (RM_SEGMENT in a sphere, RM_HEMIDISC
 * in a hemisphere). `cut` (T_INF: none) is a bound the caller refuses anything at or past
 * (a full heap's root): a hemisphere-disc candidate whose hemisphere distance alone
 * reaches it is refused before its plane distance (the metric is at least that). Shared
 * by the K-nearest searches (rm_candidate) and the fixed-radius splat (rm_splat). */
int rm_qualify(float4 x, float4 n, float4 a, float4 b, float4 d, int metric, int domain,
               float r, int incoming, float cut, float *v) {
    if (incoming && dot3(d, n) >= 0.0f) return 0;
    float dom = 0.0f;
    if (domain == RM_DOM_SPHERE) {
        dom = rm_seg_dist(x, a, b);
        if (dom > r) return 0;
    } else if (domain == RM_DOM_HEMISPHERE) {
        dom = rm_hemi_dist(x, n, a, b);
        if (dom > r) return 0;
    }
    if (domain == RM_DOM_SPHERE && metric == RM_SEGMENT) {
        *v = dom;
    } else if (domain == RM_DOM_HEMISPHERE && metric == RM_HEMIDISC) {
        if (cut < T_INF && !(dom < cut)) return 0;
        *v = fmax(rm_plane_dist(x, n, a, d), dom);
    } else {
        *v = rm_metric(metric, x, n, a, b, d);
    }
    return *v <= r;                                      /* also drops T_INF and NaN */
}

/* Test one candidate segment s (rm_qualify) and keep it in the heap if it qualifies
 * (rm_leaf; rm_knn_list in raymap.cl over host-built candidate lists). */
void rm_candidate(int s, __global const float4 *seg_a, __global const float4 *seg_b,
                  __global const float4 *seg_d, float4 x, float4 n, int k, int metric,
                  int domain, float r, int incoming, RM_HEAP float *hd, RM_HEAP int *hx,
                  int *count) {
    float v;
    if (rm_qualify(x, n, seg_a[s], seg_b[s], seg_d[s], metric, domain, r, incoming,
                   *count == k ? hd[0] : T_INF, &v))
        rm_heap_push(hd, hx, count, k, v, s);
}

/* Test the references of one leaf and keep the qualifying ones in the heap. */
void rm_leaf(__global const RMNode *nd, __global const int *refs, __global const float4 *seg_a,
             __global const float4 *seg_b, __global const float4 *seg_d, float4 x, float4 n,
             int k, int metric, int domain, float r, int incoming, RM_HEAP float *hd,
             RM_HEAP int *hx, int *count, int *work) {
    for (int j = 0; j < nd->count; ++j) {
        work[1] += 1;
        rm_candidate(refs[nd->first + j], seg_a, seg_b, seg_d, x, n, k, metric, domain, r,
                     incoming, hd, hx, count);
    }
}

/* K nearest segments to x under `metric` (see the header). Fills hd/hx (a max-heap, not
 * sorted) and returns how many were found; work[0] += nodes visited, work[1] += segment
 * references tested. radius <= 0 means no domain (then metric must be RM_SEGMENT or
 * RM_HEMIDISC, which prune by distance). */
int rm_knn(__global const RMNode *nodes, __global const int *refs,
           __global const float4 *seg_a, __global const float4 *seg_b,
           __global const float4 *seg_d, float4 x, float4 n, int k, int metric, int domain,
           float radius, int incoming, float cos_alpha, RM_HEAP float *hd, RM_HEAP int *hx,
           int *work) {
    int count = 0;
    rm_seen_clear(hx);
    int bounded = metric == RM_SEGMENT || metric == RM_HEMIDISC;
    float r = domain == RM_DOM_NONE ? T_INF : radius;
    int stack[RM_STACK];
    float lbs[RM_STACK];
    int top = 0;
    stack[top] = 0;
    lbs[top++] = 0.0f;
    while (top > 0) {
        --top;
        int ni = stack[top];
        float lb = lbs[top];
        float bound = count < k ? r : hd[0];
        if (lb > bound) continue;
        __global const RMNode *nd = &nodes[ni];
        work[0] += 1;
        if (nd->kind == RM_LEAF) {
            rm_leaf(nd, refs, seg_a, seg_b, seg_d, x, n, k, metric, domain, r, incoming, hd, hx,
                    &count, work);
            continue;
        }
        int c0 = nd->child, c1 = nd->child + 1;
        if (nd->kind == RM_DIRECTIONAL) {
            if (top + 2 > RM_STACK) continue;            /* cannot happen for D_max <= 30 */
            if (!(incoming && rm_covered(nd, n, cos_alpha))) {
                stack[top] = c1;
                lbs[top++] = lb;
            }
            stack[top] = c0;
            lbs[top++] = lb;
            continue;
        }
        /* spatial: push the farther child first so that the nearer one is popped first */
        float d0 = rm_box_dist(&nodes[c0], x), d1 = rm_box_dist(&nodes[c1], x);
        if (domain == RM_DOM_HEMISPHERE) {
            if (rm_box_above(&nodes[c0], x, n) < 0.0f) d0 = T_INF;
            if (rm_box_above(&nodes[c1], x, n) < 0.0f) d1 = T_INF;
        }
        if (!bounded) {                                  /* only the domain prunes */
            d0 = d0 <= r ? 0.0f : T_INF;
            d1 = d1 <= r ? 0.0f : T_INF;
        }
        if (top + 2 > RM_STACK) continue;
        int near_c = d0 <= d1 ? c0 : c1, far_c = d0 <= d1 ? c1 : c0;
        float near_d = fmin(d0, d1), far_d = fmax(d0, d1);
        bound = count < k ? r : hd[0];
        if (far_d <= bound) { stack[top] = far_c; lbs[top++] = far_d; }
        if (near_d <= bound) { stack[top] = near_c; lbs[top++] = near_d; }
    }
    return count;
}

/* Candidate-list reuse for coherent queries (Sec. 6.3). After a full query at x0 with
 * K-th distance d0, rm_collect lists every leaf within d0 + 2 eps of x0 (both children
 * of directional nodes, no domain: the next query's normal may differ). For a query y
 * with |y - x0| <= eps, a segment in no listed leaf is farther than d0 + 2 eps from x0,
 * so farther than d0 + eps from y under every metric that bounds the segment distance
 * from above (RM_SEGMENT, RM_HEMIDISC). Searching the listed leaves only is therefore
 * exact whenever its K-th distance (the domain radius if fewer than K) is <= d0 + eps;
 * otherwise the query walks the tree. Returns the number of leaves, -1 if over cap. */
int rm_collect(__global const RMNode *nodes, float4 x, float bound, int *list, int cap) {
    int stack[RM_STACK];
    int top = 0, m = 0;
    stack[top++] = 0;
    while (top > 0) {
        __global const RMNode *nd = &nodes[stack[--top]];
        if (rm_box_dist(nd, x) > bound) continue;
        if (nd->kind == RM_LEAF) {
            if (nd->count == 0) continue;
            if (m == cap) return -1;
            list[m++] = (int)(nd - nodes);
            continue;
        }
        if (top + 2 > RM_STACK) return -1;
        stack[top++] = nd->child + 1;
        stack[top++] = nd->child;
    }
    return m;
}

/* Does segment s meet query domain `qtype` (see the header)? x, n: centre and normal
 * (RM_Q_BOX: x = min corner, n = max corner). */
int rm_meets(int qtype, float4 x, float4 n, float r, float4 a, float4 b, float4 d) {
    if (qtype == RM_Q_SPHERE) return rm_seg_dist(x, a, b) <= r;
    if (qtype == RM_Q_BOX) {
        float t0, t1;
        return ray_box(a, safe_inv_dir(b - a), x, n, 0.0f, 1.0f, &t0, &t1);
    }
    if (dot3(d, n) >= 0.0f) return 0;                   /* incoming rays only */
    if (qtype == RM_Q_HEMISPHERE) return rm_hemi_dist(x, n, a, b) <= r;
    /* disc: the segment crosses the plane within the disc */
    float4 ab = b - a;
    float sa = dot3(a - x, n), sb = dot3(b - x, n);
    if (sa < 0.0f || sb > 0.0f) return 0;                /* incoming: from above to below */
    float t = sa > sb ? sa / (sa - sb) : 0.0f;
    return length3(a + t * ab - x) <= r;
}

#endif
