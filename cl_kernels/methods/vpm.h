/* vpm.h: the photon map of volumetric photon mapping (clscatter/methods/vpm/photons.py
 * builds it over the estimators' balanced point tree) and its k-nearest-neighbour estimate.
 *
 * Photon: 20 bytes, as in Jensen's photon map: position, octahedral direction code (the
 * way the light travels), RGB9E5 power relative to a per-map power_scale. The photons are
 * sorted by leaf of a balanced point tree (point_tree.h: PointNode boxes, breadth-first;
 * leaf j holds photons [floor(j n / 2^levels), floor((j + 1) n / 2^levels))); knn_query
 * is that tree's k-nearest query (pt_knn) over the photons' positions, with a heap of
 * KNN entries in private memory.
 */
#ifndef CLSCATTER_VPM_H
#define CLSCATTER_VPM_H
#include "common.h"
#include "point_tree.h"

#ifndef KNN
#define KNN 32
#endif
#define PHOTON_FLOATS 5     /* a Photon is 5 floats wide; x, y, z come first */

typedef struct {
    float x, y, z;
    uint dir;      /* octahedral code: u in the low 16 bits, v in the high 16 */
    uint power;    /* RGB9E5 of power / power_scale */
} Photon;

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

/* The (at most) KNN photons nearest to p with squared distance < r2_search, as a
 * max-heap (hd, hi); returns how many were found. work[0] += boxes tested, work[1] +=
 * photons tested (statistics). */
int knn_query(__global const Photon *photons, int n, __global const PointNode *nodes,
              int levels, float4 p, float r2_search, float *hd, int *hi, int *work) {
    return pt_knn((__global const float *)photons, PHOTON_FLOATS, n, nodes, levels, p,
                  r2_search, KNN, hd, hi, work);
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
