/* bvh.h: BVH traversal and watertight ray/triangle intersection.
 *
 * The BVH is built on the host (clscatter/accel/bvh.py) in the depth-first layout of
 * BVHNode (common.h): a leaf (count > 0) holds triangles [left_first, left_first+count)
 * of the reordered triangle array; an interior node (count == 0) has its left child at
 * index + 1 and its right child at left_first. The only node with count == 0 and no
 * children is the root of an empty BVH, whose box is empty (bmin > bmax).
 * tris[3*i + 0..2] are the vertices v0, v1, v2 of triangle i (xyz, w unused).
 *
 * Interface for other kernels:
 *   int bvh_closest(nodes, tris, o, d, tmin, tmax, &hit)  closest hit with t in (tmin, tmax)
 *   int bvh_any(nodes, tris, o, d, tmin, tmax)            any hit with t in (tmin, tmax)
 * d need not be unit length (t is in units of |d|), but must not be the zero vector.
 * Hit.tri indexes the *reordered* triangle array (BVH.order maps it to the input index);
 * Hit.u and Hit.v are the barycentric weights of v1 and v2 (v0 gets 1 - u - v).
 *
 * Triangle test: Woop, Benthin & Wald 2013, "Watertight Ray/Triangle Intersection"
 * (JCGT 2(1)). The ray is transformed so that it runs along +z through the origin
 * (axis permutation by the largest |d| component, then a shear); the 2D edge functions
 * of the transformed vertices decide inside/outside. The transform of a vertex depends
 * only on the vertex and the ray, and an edge shared by two triangles gives edge
 * functions that are exact negatives of each other (no FMA contraction, see the pragma
 * below), so a ray through a shared edge or vertex can never slip between triangles.
 * An edge function that is exactly zero counts as inside for both triangles (the
 * paper's double-precision fallback is not used; a ray exactly on an edge may report
 * either neighbour, at the same distance). Double-sided, no backface culling. A
 * degenerate triangle has det == 0 in exact arithmetic; the host builder leaves exactly
 * degenerate (and non-finite) triangles out of every leaf, so they are never tested.
 *
 * Traversal: explicit stack of BVH_STACK_SIZE entries (the host builder guarantees
 * tree depth < BVH_STACK_SIZE, which bounds the stack), nearer child first, subtrees
 * whose box entry is beyond the closest hit so far are skipped. The slab test treats
 * zero direction components exactly (origin on a slab plane: the slab is everything)
 * and pads the exit distance as in Ize 2013 ("Robust BVH Ray Traversal", JCGT 2(2))
 * so float rounding never culls a box the ray really touches.
 * Portable OpenCL 1.2 C: no recursion, no fp64, no extensions.
 */
#ifndef CLSCATTER_BVH_H
#define CLSCATTER_BVH_H

#include "common.h"

#define BVH_STACK_SIZE 64
/* 1 + 2*gamma(3) with gamma(n) = n*eps/(1 - n*eps), eps = 2^-24, rounded up */
#define BVH_EXIT_PAD 1.0000004f

typedef struct { float t; int tri; float u; float v; } Hit;

/* Per-ray data for the watertight test: the rows of the permute+shear transform
 * (Ax = dot(A, sx_row), Ay = dot(A, sy_row), Az = dot(A, sz_row) for A = v - o). */
typedef struct {
    float4 o;
    float4 inv_d;
    float4 rx, ry, rz;
} BvhRay;

float4 bvh_unit_(int k) {
    return (float4)(k == 0 ? 1.0f : 0.0f, k == 1 ? 1.0f : 0.0f, k == 2 ? 1.0f : 0.0f, 0.0f);
}

float bvh_comp_(float4 v, int k) { return k == 0 ? v.x : (k == 1 ? v.y : v.z); }

/* Returns 0 for a zero (or NaN) direction, which can hit nothing. */
int bvh_ray_setup(float4 o, float4 d, BvhRay *r) {
    o.w = 0.0f;
    d.w = 0.0f;
    float ax = fabs(d.x), ay = fabs(d.y), az = fabs(d.z);
    int kz = ax > ay ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2);
    int kx = kz == 2 ? 0 : kz + 1;
    int ky = kx == 2 ? 0 : kx + 1;
    float dz = bvh_comp_(d, kz);
    if (!(dz != 0.0f)) return 0;
    if (dz < 0.0f) { int s = kx; kx = ky; ky = s; }   /* keep the winding (paper, Fig. 2) */
    float sx = bvh_comp_(d, kx) / dz;
    float sy = bvh_comp_(d, ky) / dz;
    float sz = 1.0f / dz;
    r->o = o;
    r->inv_d = (float4)(1.0f / d.x, 1.0f / d.y, 1.0f / d.z, 0.0f);   /* +-inf for zeros */
    r->rx = bvh_unit_(kx) - sx * bvh_unit_(kz);
    r->ry = bvh_unit_(ky) - sy * bvh_unit_(kz);
    r->rz = sz * bvh_unit_(kz);
    return 1;
}

/* Slab test against a node box; *t_entry is the entry distance (clamped to tmin). */
int bvh_box(const BvhRay *r, float4 bmin, float4 bmax, float tmin, float tmax, float *t_entry) {
    float4 ta = (bmin - r->o) * r->inv_d;
    float4 tb = (bmax - r->o) * r->inv_d;
    float4 lo = fmin(ta, tb), hi = fmax(ta, tb);
    /* NaN only from 0 * inf: zero direction component with the origin on that slab
     * plane; the ray then lies in the closed slab for every t */
    int4 bad = isnan(ta) | isnan(tb);
    lo = select(lo, (float4)(-INFINITY), bad);
    hi = select(hi, (float4)(INFINITY), bad);
    float a = fmax(fmax(lo.x, lo.y), fmax(lo.z, tmin));
    float b = fmin(fmin(fmin(hi.x, hi.y), hi.z) * BVH_EXIT_PAD, tmax);
    *t_entry = a;
    return a <= b;
}

/* 2D edge function E(P, Q) = Px*Qy - Py*Qx of the projected vertices P, Q. The
 * operands are put in a canonical order first, so E(Q, P) == -E(P, Q) holds exactly even
 * where a compiler fuses the multiply-subtract into an FMA (some GPU compilers do so
 * regardless of FP_CONTRACT): the two triangles sharing an edge then always agree. */
float bvh_edge(float px, float py, float qx, float qy) {
    int swap = px > qx || (px == qx && py > qy);
    float ax = swap ? qx : px, ay = swap ? qy : py;
    float bx = swap ? px : qx, by = swap ? py : qy;
    float e = ax * by - ay * bx;
    return swap ? -e : e;
}

/* Watertight ray/triangle test; on a hit with t in (tmin, tmax) writes t, u, v. */
int bvh_triangle(const BvhRay *r, float4 v0, float4 v1, float4 v2, float tmin, float tmax,
                 float *t_out, float *u_out, float *v_out) {
#pragma OPENCL FP_CONTRACT OFF
    float4 A = v0 - r->o, B = v1 - r->o, C = v2 - r->o;
    float Ax = A.x * r->rx.x + A.y * r->rx.y + A.z * r->rx.z;
    float Ay = A.x * r->ry.x + A.y * r->ry.y + A.z * r->ry.z;
    float Bx = B.x * r->rx.x + B.y * r->rx.y + B.z * r->rx.z;
    float By = B.x * r->ry.x + B.y * r->ry.y + B.z * r->ry.z;
    float Cx = C.x * r->rx.x + C.y * r->rx.y + C.z * r->rx.z;
    float Cy = C.x * r->ry.x + C.y * r->ry.y + C.z * r->ry.z;
    /* edge functions; U weights v0, V weights v1, W weights v2 */
    float U = bvh_edge(Cx, Cy, Bx, By);     /* Cx*By - Cy*Bx */
    float V = bvh_edge(Ax, Ay, Cx, Cy);     /* Ax*Cy - Ay*Cx */
    float W = bvh_edge(Bx, By, Ax, Ay);     /* Bx*Ay - By*Ax */
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f)) return 0;
    float det = U + V + W;
    if (det == 0.0f) return 0;
    float Az = A.x * r->rz.x + A.y * r->rz.y + A.z * r->rz.z;
    float Bz = B.x * r->rz.x + B.y * r->rz.y + B.z * r->rz.z;
    float Cz = C.x * r->rz.x + C.y * r->rz.y + C.z * r->rz.z;
    float T = U * Az + V * Bz + W * Cz;
    float inv_det = 1.0f / det;
    float t = T * inv_det;
    if (!(t > tmin && t < tmax)) return 0;
    *t_out = t;
    *u_out = V * inv_det;
    *v_out = W * inv_det;
    return 1;
}

/* Test triangle i of tris against the ray; a hit nearer than *best becomes the closest
 * so far (*best, and *hit unless NULL). Shared by the BVH's leaves and tile_grid.h. */
int bvh_try_triangle(const BvhRay *r, __global const float4 *tris, int i, float tmin,
                     float *best, Hit *hit) {
    float t, u, v;
    if (!bvh_triangle(r, tris[3 * i], tris[3 * i + 1], tris[3 * i + 2], tmin, *best,
                      &t, &u, &v))
        return 0;
    *best = t;
    if (hit) { hit->t = t; hit->tri = i; hit->u = u; hit->v = v; }
    return 1;
}

/* Shared traversal; any_hit != 0 returns at the first hit found (hit may be NULL). */
int bvh_traverse(__global const BVHNode *nodes, __global const float4 *tris, float4 o,
                 float4 d, float tmin, float tmax, int any_hit, Hit *hit) {
    /* a BVHNode is 32 bytes: (bmin.xyz, left_first) and (bmax.xyz, count) as float4 */
    __global const float4 *nf = (__global const float4 *)nodes;
    BvhRay r;
    if (!bvh_ray_setup(o, d, &r)) return 0;
    float4 lo = nf[0], hi = nf[1];
    if (!(lo.x <= hi.x)) return 0;          /* empty BVH: empty root box */
    float best = tmax;
    float t_entry;
    if (!bvh_box(&r, lo, hi, tmin, best, &t_entry)) return 0;
    int found = 0;
    int stack[BVH_STACK_SIZE];
    float stack_t[BVH_STACK_SIZE];
    int sp = 0;
    int ni = 0;
    for (;;) {
        int first = as_int(lo.w), count = as_int(hi.w);
        int next = -1;
        if (count > 0) {
            for (int i = first; i < first + count; ++i) {
                if (bvh_try_triangle(&r, tris, i, tmin, &best, hit)) {
                    found = 1;
                    if (any_hit) return 1;
                }
            }
        } else {
            int left = ni + 1, right = first;
            float tl, tr;
            int hl = bvh_box(&r, nf[2 * left], nf[2 * left + 1], tmin, best, &tl);
            int hr = bvh_box(&r, nf[2 * right], nf[2 * right + 1], tmin, best, &tr);
            if (hl && hr) {
                int far_node = right;
                float far_t = tr;
                next = left;
                if (tr < tl) { next = right; far_node = left; far_t = tl; }
                stack[sp] = far_node;
                stack_t[sp] = far_t;
                ++sp;
            } else if (hl) {
                next = left;
            } else if (hr) {
                next = right;
            }
        }
        while (next < 0) {
            if (sp == 0) return found;
            --sp;
            if (stack_t[sp] <= best) next = stack[sp];
        }
        ni = next;
        lo = nf[2 * ni];
        hi = nf[2 * ni + 1];
    }
}

int bvh_closest(__global const BVHNode *nodes, __global const float4 *tris, float4 o, float4 d,
                float tmin, float tmax, Hit *hit) {
    return bvh_traverse(nodes, tris, o, d, tmin, tmax, 0, hit);
}

int bvh_any(__global const BVHNode *nodes, __global const float4 *tris, float4 o, float4 d,
            float tmin, float tmax) {
    return bvh_traverse(nodes, tris, o, d, tmin, tmax, 1, 0);
}

#endif
