/* vpm.h: the photon map of volumetric photon mapping (clscatter/methods/vpm/photontree.py builds
 * it) and its k-nearest-neighbour query.
 *
 * Photon: 20 bytes, as in Jensen's photon map: position, octahedral direction code (the
 * way the light travels), RGB9E5 power relative to a per-map power_scale.
 * PhotonNode: the box of one node of a perfect binary tree stored breadth-first (node i
 * has children 2i+1, 2i+2; leaf j = node 2^levels - 1 + j holds photons
 * [floor(j n / 2^levels), floor((j + 1) n / 2^levels)), a balanced kd-tree's leaves).
 * An empty map is one root with the empty box (+1e30, -1e30).
 *
 * The query keeps the KNN nearest photons within max_r2 in a bounded max-heap in private
 * memory (root = farthest kept photon), visits the nearer child first and prunes every
 * box farther than the current search radius (max_r2 until the heap is full, then the
 * heap's root). The traversal stack is explicit: one entry per level at most.
 */
#ifndef CLSCATTER_VPM_H
#define CLSCATTER_VPM_H
#include "common.h"
#include "knn_heap.h"

#ifndef KNN
#define KNN 32
#endif
#define PT_STACK 48

typedef struct {
    float x, y, z;
    uint dir;      /* octahedral code: u in the low 16 bits, v in the high 16 */
    uint power;    /* RGB9E5 of power / power_scale */
} Photon;

typedef struct {
    float bmin[3];
    float bmax[3];
} PhotonNode;

float4 photon_direction(uint code) {
    float u = (float)(code & 0xFFFFu) * (2.0f / 65535.0f) - 1.0f;
    float v = (float)(code >> 16) * (2.0f / 65535.0f) - 1.0f;
    float z = 1.0f - fabs(u) - fabs(v);
    float t = fmax(-z, 0.0f);
    float x = u - (u >= 0.0f ? t : -t);
    float y = v - (v >= 0.0f ? t : -t);
    return normalize3((float4)(x, y, z, 0.0f));
}

float4 photon_power(uint w, float power_scale) {
    float s = ldexp(power_scale, (int)(w >> 27) - 24);   /* 2^(e - B - N), B = 15, N = 9 */
    return (float4)((float)(w & 511u), (float)((w >> 9) & 511u), (float)((w >> 18) & 511u), 0.0f) * s;
}

float photon_dist2(__global const Photon *ph, float4 p) {
    float dx = ph->x - p.x, dy = ph->y - p.y, dz = ph->z - p.z;
    return dx * dx + dy * dy + dz * dz;
}

float node_dist2(__global const PhotonNode *nd, float4 p) {
    float dx = fmax(fmax(nd->bmin[0] - p.x, p.x - nd->bmax[0]), 0.0f);
    float dy = fmax(fmax(nd->bmin[1] - p.y, p.y - nd->bmax[1]), 0.0f);
    float dz = fmax(fmax(nd->bmin[2] - p.z, p.z - nd->bmax[2]), 0.0f);
    return dx * dx + dy * dy + dz * dz;
}

/* The (at most) KNN photons nearest to p with squared distance < r2_search, as a
 * max-heap (hd, hi); returns how many were found. work[0] += boxes tested, work[1] +=
 * photons tested (statistics). */
int knn_query(__global const Photon *photons, int n, __global const PhotonNode *nodes,
              int levels, float4 p, float r2_search, float *hd, int *hi, int *work) {
    int count = 0;
    float r2 = r2_search;
    if (n <= 0 || node_dist2(&nodes[0], p) >= r2) return 0;
    int stack[PT_STACK];
    float sdist[PT_STACK];
    int sp = 0;
    int first_leaf = (1 << levels) - 1;
    int node = 0;
    while (1) {
        if (node >= first_leaf) {
            long j = node - first_leaf;
            int start = (int)((j * n) >> levels);
            int end = (int)(((j + 1) * n) >> levels);
            work[1] += end - start;
            for (int i = start; i < end; ++i) {
                float d2 = photon_dist2(&photons[i], p);
                if (d2 >= r2) continue;
                knn_heap_insert(hd, hi, &count, KNN, d2, i);
                if (count == KNN) r2 = hd[0];
            }
        } else {
            int c = 2 * node + 1;
            work[0] += 2;
            float da = node_dist2(&nodes[c], p);
            float db = node_dist2(&nodes[c + 1], p);
            int near = da <= db ? c : c + 1;
            float dn = fmin(da, db), df = fmax(da, db);
            if (df < r2 && sp < PT_STACK) {
                stack[sp] = near == c ? c + 1 : c;
                sdist[sp] = df;
                ++sp;
            }
            if (dn < r2) { node = near; continue; }
        }
        node = -1;
        while (sp > 0) {
            --sp;
            if (sdist[sp] < r2) { node = stack[sp]; break; }
        }
        if (node < 0) break;
    }
    return count;
}

/* The volumetric radiance estimate (Jensen & Christensen 1998; eq. 4 of the LSG paper),
 * without sigma_s: sum_p f(w_p . wo) Phi_p / V(r), wo towards the camera. This returns
 * the sum and sets *r2 to the squared kernel radius. A full heap uses r = distance to
 * the KNN-th photon and sums the KNN - 1 photons inside it (for photons of a Poisson
 * process, E[(k-1) / V(r_k)] is exactly the density, while k / V(r_k) is biased by
 * k / (k-1)); fewer than KNN photons within max_r: all of them, r = max_r (a fixed-radius
 * estimate). */
float4 knn_sum(__global const Photon *photons, float power_scale, const float *hd,
               const int *hi, int count, float max_r2, float4 wo, float g, float *r2) {
    *r2 = count == KNN ? hd[0] : max_r2;
    int skip = count == KNN ? 0 : -1;
    float4 sum = (float4)(0.0f);
    for (int k = 0; k < count; ++k) {
        if (k == skip) continue;
        __global const Photon *ph = &photons[hi[k]];
        float4 d = photon_direction(ph->dir);
        sum += photon_power(ph->power, power_scale) * hg_phase(dot3(d, wo), g);
    }
    return sum;
}

/* Volume of the ball (c, r) inside the box [bmin, bmax] (c inside it), as the ball's volume
 * times the fraction inside each axis' slab: 1 - caps beyond the slab's faces, cap of
 * height c_h = r - h having volume pi c_h^2 (3 r - c_h) / 3. Exact next to one face, an
 * edge or a corner through the centre; a close approximation in between. Photons exist
 * only inside a bounded medium, so this is the volume the kNN ball can find them in:
 * dividing by it removes the estimate's deficit next to the medium's walls. */
float ball_volume_in_box(float4 c, float r, float4 bmin, float4 bmax) {
    float ball = (4.0f / 3.0f) * PI_F * r * r * r;
    float lo[3] = {c.x - bmin.x, c.y - bmin.y, c.z - bmin.z};
    float hi[3] = {bmax.x - c.x, bmax.y - c.y, bmax.z - c.z};
    float frac = 1.0f;
    for (int a = 0; a < 3; ++a) {
        float out = 0.0f;
        float h0 = clamp(lo[a], 0.0f, r), h1 = clamp(hi[a], 0.0f, r);
        float c0 = r - h0, c1 = r - h1;
        out += PI_F * c0 * c0 * (3.0f * r - c0) / 3.0f;
        out += PI_F * c1 * c1 * (3.0f * r - c1) / 3.0f;
        frac *= fmax(1.0f - out / ball, 0.0f);
    }
    return ball * frac;
}

/* The estimate without the wall correction (an unbounded medium, and the test hook). */
float4 knn_estimate(__global const Photon *photons, float power_scale, const float *hd,
                    const int *hi, int count, float max_r2, float4 wo, float g) {
    if (count == 0) return (float4)(0.0f);
    float r2;
    float4 sum = knn_sum(photons, power_scale, hd, hi, count, max_r2, wo, g, &r2);
    r2 = fmax(r2, 1e-30f);
    return sum / ((4.0f / 3.0f) * PI_F * r2 * sqrt(r2));
}

#endif
