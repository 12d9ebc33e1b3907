/* epipolar.h: structs and the Fenwick (half) tree of the epipolar method.
 *
 * Baran et al. 2010, "A Hierarchical Volumetric Shadow Algorithm for Single Scattering".
 * The structs mirror clscatter/methods/epipolar/geometry.py (EPI_FRAME, EPI_SLICE); their layout
 * is checked by tests/test_epipolar.py. Coordinates are those of that module: the axis u
 * from the eye towards the light, slices = half-planes (unit w normal to u), beta = angle
 * of a view ray from u, gamma = light-ray coordinate (distance from the eye for a
 * directional light, angle at the light for a spot light).
 *
 * Vector width: the tree holds EPI_NV = EPI_NT * EPI_NCH floats per light ray (EPI_NT
 * SVD terms for each of EPI_NCH colour channels; one channel when the extinction is
 * grey). Defaults below are for the Fenwick test kernels.
 */
#ifndef CLSCATTER_EPIPOLAR_H
#define CLSCATTER_EPIPOLAR_H
#include "common.h"

#ifndef EPI_NT
#define EPI_NT 4
#endif
#ifndef EPI_NCH
#define EPI_NCH 1
#endif
#define EPI_NV (EPI_NT * EPI_NCH)
#define EPI_MODES 4          /* depth sub-samples per light ray (paper, Sec. 7) */

typedef struct {
    float4 eye;      /* camera origin */
    float4 u;        /* unit axis, eye -> light */
    float4 b1, b2;   /* orthonormal basis normal to u (phi = atan2(v.b2, v.b1)) */
    float4 light;    /* spot: position */
    float4 kappa;    /* rgb extinction */
    float4 bmin, bmax;  /* medium box (bounded) */
    float4 cone;     /* spot: cone axis (xyz), cos of the half-angle (w) */
    float4 sm_s1, sm_s2;  /* shadow-map axes: directional b1, b2; spot: normal to the cone axis */
    float4 sm_rect;  /* shadow-map extent (lo1, lo2, hi1, hi2) in map coordinates */
    float D;         /* spot: |light - eye| */
    float z_start;   /* directional: axial coordinate where shadow-map rays start */
    float beta_tol;  /* prefilter: sub-samples closer than this in beta form one mode */
    float lspan;     /* bound of |light-side reference - light entry| (svd.Refs.span) */
    int type;        /* LIGHT_DIRECTIONAL or LIGHT_SPOT */
    int bounded;
    int sm_res;      /* shadow map is sm_res x sm_res */
    int d;           /* light rays per slice */
    int prefilter;   /* 1: four sub-samples per light ray, clustered into modes */
    int rays;        /* grid lookup: view rays per slice */
    int nch;
    int sm_faces;    /* spot: perspective maps in the faces buffer (1, or 5 for a wide cone) */
} EpiFrame;

/* One perspective shadow-map face of a spot light (clscatter/methods/epipolar/maps.py):
 * texel (ix, iy) looks along normalize(c + x1 e1 + x2 e2), x1, x2 over rect at texel
 * centres; c.w = nx, e1.w = ny, e2.w = offset of its first texel in the map buffer. */
typedef struct {
    float4 c, e1, e2, rect;
} EpiFace;

typedef struct {
    float4 w;                    /* unit, normal to u, inside the half-plane */
    float beta_lo, beta_hi;      /* beta range of the slice's image half-line (grid lookup) */
    float gamma_lo, gamma_hi;    /* light rays: gamma_i = lo + (i + 0.5) (hi - lo) / d */
    float cone_lo, cone_hi;      /* spot: gamma interval inside the cone */
    float phi;                   /* angle of w around u */
    int group;                   /* its SVD group (tables of svd.py, one per arc of slices) */
} EpiSlice;

/* ---- Fenwick (half) tree of EPI_NV-vectors (Fenwick 1994; paper, Sec. 5) ----
 * d light rays, 0-based i. T holds the tree: node j (1-based) at T[(j-1)*EPI_NV], the sum
 * of leaves (j - lowbit(j), j]; a prefix sum walks j -= lowbit(j) (log2 d nodes), an
 * update walks j += lowbit(j). Right children are never stored (the "half tree").
 * L holds the complete lowest level (the leaves' current values) so that the query at
 * ceil(m) is the query at floor(m) plus one leaf (paper: 1.5 n floats; here 2 n, the
 * leaves are kept whole so that zeroing a leaf can subtract its exact value). */

/* O(d) build from the leaves already copied into T. */
void fw_build(__global float *T, int d) {
    for (int j = 1; j <= d; ++j) {
        int p = j + (j & -j);
        if (p > d) continue;
        for (int c = 0; c < EPI_NV; ++c) T[(p - 1) * EPI_NV + c] += T[(j - 1) * EPI_NV + c];
    }
}

/* Add delta to leaf i in the tree (not in L). */
void fw_add(__global float *T, int d, int i, const float *delta) {
    for (int j = i + 1; j <= d; j += j & -j)
        for (int c = 0; c < EPI_NV; ++c) T[(j - 1) * EPI_NV + c] += delta[c];
}

/* Remove the fraction frac of leaf i's current value (frac >= 1 zeroes it exactly). */
void fw_scale_leaf(__global float *T, __global float *L, int d, int i, float frac) {
    float delta[EPI_NV];
    for (int c = 0; c < EPI_NV; ++c) {
        float cur = L[i * EPI_NV + c];
        delta[c] = frac >= 1.0f ? -cur : -frac * cur;
        L[i * EPI_NV + c] = frac >= 1.0f ? 0.0f : cur + delta[c];
    }
    fw_add(T, d, i, delta);
}

/* acc += sum of the first m leaves, m continuous in [0, d]: the prefix at floor(m) plus
 * the fraction m - floor(m) of the next leaf (the lerp between floor and ceil queries). */
void fw_query(__global const float *T, __global const float *L, int d, float m, float *acc) {
    m = clamp(m, 0.0f, (float)d);
    int k = (int)floor(m);
    float f = m - (float)k;
    for (int j = k; j > 0; j -= j & -j)
        for (int c = 0; c < EPI_NV; ++c) acc[c] += T[(j - 1) * EPI_NV + c];
    if (k < d && f > 0.0f)
        for (int c = 0; c < EPI_NV; ++c) acc[c] += f * L[k * EPI_NV + c];
}

#endif
