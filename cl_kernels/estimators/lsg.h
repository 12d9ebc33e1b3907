/* lsg.h: structs and pair maths of line space gathering (Sun et al. 2010).
 *
 * LsgLine is mirrored on the host by clscatter/estimators/line_gather.py (LSG_LINE);
 * tests/test_lsg.py checks its size and offsets. The tree's nodes reach the kernels as
 * blocks of 8 boxes side by side (clscatter/estimators/line_tree.py, child_rows).
 *
 * ---- The estimate (derived here, not copied from the paper) ----
 * Single scattering along a view segment x(t) = a_v + t u_v, t in [0, len_v]:
 *     L = int_0^len_v sigma_s T_v(t) int p(w', -u_v) L(x(t), w') dw' dt,  T_v = exp(-kappa t)
 * (the segment's weight carries the rest of the way to the eye). Replace the integrand
 * at x(t) by its average over the disc of radius r perpendicular to the view axis: the
 * t-integral becomes a volume integral over the finite cylinder C (radius r, flat caps
 * at t = 0 and t = len_v) divided by pi r^2. Lighting rays of flux Phi are a track-length
 * sample of the light field: int_C f(x) L(x, w') dw' dx ~ sum_l int_{l in C} f Phi_l(s) ds.
 * Hence, per lighting segment l (start a_l, unit u_l, flux Phi_l at a_l):
 *
 *     L ~ sum_l sigma_s p(-u_l.u_v) Phi_l / (pi r^2)
 *                * int_{s in chord_l} exp(-kappa (s + t(s))) ds
 *
 * where chord_l is the part of the lighting segment inside C and t(s) the view parameter
 * of its projection. With constant coefficients the integral is exact (t(s) is linear);
 * for a short chord it is Phi(s*) T_v(t*) ell: the flux attenuated along the lighting
 * segment to the closest point times the transmittance back to the view segment's start.
 * For a chord of length ell = 2 sqrt(r^2 - d^2) / sin(theta) through a long cylinder this
 * is the paper's eq. (6)-(8) with the correct constant (the paper prints sqrt(r^2-d^2)
 * without the 2 and an extra 1/|x - x0|); a uniform beam of irradiance E = n Phi gives
 * back sigma_s p E len exactly (tests/test_lsg.py, analytic beam).
 *
 * Near-parallel pairs: 1/sin(theta) grows without bound, but the chord is cut by the
 * cylinder's caps (the view segment's length) and by the lighting segment's own ends:
 * that is the clamp, and it is exact. sin(theta) < min_sin (default 1e-6) is treated as
 * parallel (inside the cylinder for its whole overlap or not at all), which guards the
 * division; the caps then bound the chord.
 *
 * Pairs are selected by the exact segment-to-segment distance d < r (valid pairs); a
 * valid pair whose lighting segment only touches the rounded end of that capsule, not
 * the flat-capped cylinder, contributes 0.
 */
#ifndef CLSCATTER_LSG_H
#define CLSCATTER_LSG_H
#include "common.h"

/* A lighting segment as the gather kernel reads it (tree order). Its Plücker point
 * (u, m) with m = ((a - centre) / scale) x u lives in a separate array, in blocks of 8
 * points by coordinate (line_tree.point_blocks), so the plane test reads 24 bytes a point,
 * 8 points at once, not the whole segment. */
typedef struct {
    float4 a;      /* start, normalised frame; w: length */
    float4 u;      /* unit direction (its orientation: the light's travel direction) */
    float4 flux;   /* rgb flux at a */
} LsgLine;

/* Squared distance between segments p1 + s d1, s in [0, l1] and p2 + t d2, t in [0, l2]
 * (unit d1, d2), with the closest parameters (Ericson, Real-Time Collision Detection
 * 5.1.9, specialised to unit directions). */
float seg_seg_dist2(float4 p1, float4 d1, float l1, float4 p2, float4 d2, float l2,
                    float *s_out, float *t_out) {
    float4 r = p1 - p2;
    float b = dot3(d1, d2);
    float c = dot3(d1, r);
    float f = dot3(d2, r);
    float4 n = cross3(d1, d2);
    float denom = dot3(n, n);                 /* 1 - b^2, accurate for near-parallel */
    float s = denom > 1e-12f ? clamp((b * f - c) / denom, 0.0f, l1) : 0.0f;
    float t = b * s + f;
    if (t < 0.0f) {
        t = 0.0f;
        s = clamp(-c, 0.0f, l1);
    } else if (t > l2) {
        t = l2;
        s = clamp(b * l2 - c, 0.0f, l1);
    }
    *s_out = s;
    *t_out = t;
    float4 dv = r + s * d1 - t * d2;
    return dot3(dv, dv);
}

/* (1 - exp(-x)) / x for 0 <= x < EXP_RATIO_SERIES_MAX (float or float4): its Taylor
 * series to x^3, whose remainder, under x^4 / 120 < 6e-8, is below float32 rounding. A
 * pair's chord is usually far shorter than a mean free path, so this spares the expm1. */
#define EXP_RATIO_SERIES_MAX 0.05f
#define EXP_RATIO_SERIES(x) (1.0f - (x) * (0.5f - (x) * (1.0f / 6.0f - (x) * (1.0f / 24.0f))))

/* int_0^D exp(-(e0 + x s / D)) ds = exp(-e0) D (1 - exp(-x)) / x, one channel (x >= 0). */
float exp_segment_integral1(float e0, float x, float D) {
    float ratio = x < EXP_RATIO_SERIES_MAX ? EXP_RATIO_SERIES(x) : -expm1(-x) / x;
    return exp(-e0) * D * ratio;
}

/* The same per channel; in a grey medium (equal channels) computed once. */
float4 exp_segment_integral(float4 e0, float4 x, float D) {
    if (e0.x == e0.y && e0.y == e0.z && x.x == x.y && x.y == x.z)
        return (float4)(exp_segment_integral1(e0.x, x.x, D));
    float4 ratio = EXP_RATIO_SERIES(x);
    if (x.x >= EXP_RATIO_SERIES_MAX || x.y >= EXP_RATIO_SERIES_MAX || x.z >= EXP_RATIO_SERIES_MAX)
        ratio = select(ratio, -expm1(-x) / x, isgreaterequal(x, (float4)(EXP_RATIO_SERIES_MAX)));
    return exp(-e0) * D * ratio;
}

/* The estimate of one pair (see the top of this file) without sigma_s and the view
 * segment's weight: p Phi int_chord exp(-kappa (s + t(s))) ds / (pi r^2), for the
 * lighting segment from la (w 0) along unit lu for llen with rgb flux at la (an
 * LsgLine's a, u, flux) and the view segment from va along unit vu for vlen. */
float4 lsg_pair(float4 la, float4 lu, float llen, float4 flux, float4 va, float4 vu,
                float vlen, float r, float min_sin, float4 kappa, float g) {
    float4 w0 = la - va;
    float ta = dot3(w0, vu);                  /* view parameter of the light start */
    float cphi = dot3(lu, vu);
    /* chord inside the infinite cylinder: |q0 + s q1| <= r */
    float4 q0 = w0 - ta * vu;
    float4 q1 = lu - cphi * vu;
    float qq = dot3(q1, q1);                  /* sin^2 theta */
    float s_lo = 0.0f, s_hi = llen;
    if (qq > min_sin * min_sin) {
        float4 x = cross3(q0, q1);
        float disc = r * r * qq - dot3(x, x);
        if (disc <= 0.0f) return (float4)(0.0f);
        float sc = -dot3(q0, q1) / qq;
        float h = sqrt(disc) / qq;
        s_lo = fmax(s_lo, sc - h);
        s_hi = fmin(s_hi, sc + h);
    } else if (dot3(q0, q0) >= r * r) {
        return (float4)(0.0f);
    }
    /* the flat caps: 0 <= t(s) = ta + s cphi <= vlen */
    if (fabs(cphi) > 1e-7f) {
        float s0 = -ta / cphi, s1 = (vlen - ta) / cphi;
        s_lo = fmax(s_lo, fmin(s0, s1));
        s_hi = fmin(s_hi, fmax(s0, s1));
    } else if (ta < 0.0f || ta > vlen) {
        return (float4)(0.0f);
    }
    float D = s_hi - s_lo;
    if (!(D > 0.0f)) return (float4)(0.0f);
    /* attenuation over the chord: exp(-kappa (s + t(s))), linear in s */
    float t_lo = clamp(ta + s_lo * cphi, 0.0f, vlen);
    float4 e0 = kappa * (s_lo + t_lo);
    float4 x = kappa * ((1.0f + cphi) * D);
    float ph = hg_phase(-cphi, g);            /* light direction vs towards the camera */
    return flux * exp_segment_integral(e0, x, D) * (ph / (PI_F * r * r));
}

/* The plane-query threshold in the Plücker frame: r' = r / scale, widened for float32
 * rounding. |P.w| is a 6-term sum of products that cancel down to d sin(theta): its
 * rounding error is below ~8 eps sum|P_i w_i| <= 8 eps (|m_v|_1 + max_l |m_l|_1) (unit
 * directions); the stored P and the view moment carry a few more eps of the same size,
 * and the exact distance test (float32, normalised frame) a few eps absolute. 1e-5 (~80
 * eps) and 1e-6 / scale cover all of it with room; it only loosens the culling. */
float lsg_threshold(float r, float inv_scale, float4 mv, float max_m1) {
    float mv1 = fabs(mv.x) + fabs(mv.y) + fabs(mv.z);
    return r * inv_scale * (1.0f + 1e-4f) + 1e-5f * (mv1 + max_m1 + 1.0f) + 1e-6f * inv_scale;
}

#endif
