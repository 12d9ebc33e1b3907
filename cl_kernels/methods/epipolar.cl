/* epipolar.cl: hierarchical volumetric shadows (Baran et al. 2010) for one light.
 *
 * Stages (host: clscatter/methods/epipolar/pipeline.py):
 *   epi_shadow_map     shadow map, ray traced: orthographic over the medium box along a
 *                      directional light, perspective over a spot light's cone (Sec. 2.2)
 *   epi_depth_map      camera depth map at pixel centres (grid lookup only)
 *   epi_rectify_shadow shadow map -> per light ray of a slice, blocker *beta* (not depth),
 *                      four sub-samples clustered into weighted modes (Sec. 7)
 *   epi_rectify_depth  depth map -> per grid view ray of a slice, the gamma range of its
 *                      part in the medium (Sec. 3; grid lookup)
 *   epi_integrate      one work-item per slice: the sweep of Fig. 6 over view rays with a
 *                      Fenwick tree of the SVD terms (Sec. 4-6)
 *   epi_rectify_image, epi_unrectify   resampling image <-> rectified grid (Sec. 2.2)
 *
 * The integrand (Eq. 3) of view ray beta at light ray gamma is factored as
 *   I(alpha, gamma, beta) = F(alpha, gamma) * sum_n Gamma_n(gamma) B_n(beta)
 *                           * exp(kappa (t_a - t_ref(beta)))
 * where Gamma_n, B_n come from the truncated SVD of the slice-independent, *referenced*
 * transmittance product K (clscatter/methods/epipolar/svd.py: K is the view and light
 * transmittance measured from the references t_ref(beta), l_ref(gamma), at most 1 where
 * pixels read it; B_n includes the pure-beta factors phase/sin(beta) and |ds/dgamma|),
 * F carries what depends on the light ray alone (its entry into the medium relative to
 * l_ref(gamma), the spot cone: the paper's "textured light"), and the last factor
 * restores the view transmittance from the segment start t_a relative to t_ref (so
 * results are radiance arriving at the start of the medium segment). Both remainders are
 * >= 1 and bounded by the references' spread over slices.
 */
#include "common.h"
#include "bvh.h"
#include "tile_grid.h"
#include "epipolar.h"

#define EPI_EXP_MAX 80.0f

/* ---- small helpers ---- */

/* linear interpolation in a table of n EPI_NV-vectors sampled uniformly on [lo, hi] */
void epi_table(__global const float *tab, int n, float lo, float hi, float x, float *out) {
    float s = (n > 1 && hi > lo) ? (x - lo) / (hi - lo) * (float)(n - 1) : 0.0f;
    s = clamp(s, 0.0f, (float)(n - 1));
    int i = min((int)s, n - 2 < 0 ? 0 : n - 2);
    float f = n > 1 ? s - (float)i : 0.0f;
    int j = n > 1 ? i + 1 : i;
    for (int c = 0; c < EPI_NV; ++c)
        out[c] = (1.0f - f) * tab[i * EPI_NV + c] + f * tab[j * EPI_NV + c];
}

float epi_kappa(__global const EpiFrame *fr, int c) {
    return c == 0 ? fr->kappa.x : (c == 1 ? fr->kappa.y : fr->kappa.z);
}

/* direction of the view ray beta in slice w */
float4 epi_view_dir(__global const EpiFrame *fr, float4 w, float beta) {
    return cos(beta) * fr->u + sin(beta) * w;
}

/* direction of the spot light ray gamma in slice w (from the light outwards) */
float4 epi_spot_dir(__global const EpiFrame *fr, float4 w, float gamma) {
    float c, s = sincos_fast(gamma, &c);
    return -c * fr->u + s * w;
}

/* gamma reached by the view ray beta at distance t (paper, Sec. 3 and 9), given
 * sb = sin(beta) and cb = cos(beta) (a caller holding the view direction has them
 * without trigonometry) */
float epi_gamma_sc(__global const EpiFrame *fr, float t, float sb, float cb) {
    if (fr->type == LIGHT_SPOT) return atan2_fast(t * sb, fr->D - t * cb);
    return t * sb;
}

float epi_gamma(__global const EpiFrame *fr, float t, float beta) {
    return epi_gamma_sc(fr, t, sin(beta), cos(beta));
}

/* ---- maps ---- */

/* The face of a spot light's shadow map that light direction l falls in (the largest
 * l.c: cube-map selection; a single face when the cone fits one map), or -1. */
int epi_face_of(__global const EpiFrame *fr, __global const EpiFace *faces, float4 l) {
    int best = -1;
    float bc = 1e-6f;
    for (int f = 0; f < fr->sm_faces; ++f) {
        float lc = dot3(l, faces[f].c);
        if (lc > bc) { bc = lc; best = f; }
    }
    return best;
}

/* When the host built a tile grid over the map (nx > 0: orthographic along -u for a
 * directional light, perspective from the light over a spot's single face), texels test
 * their tile's triangles instead of traversing the BVH; the stored depth is the same
 * (tile_grid.h). */
__kernel void epi_shadow_map(__global const BVHNode *nodes, __global const float4 *tris,
                             __global const EpiFrame *fr, __global const EpiFace *faces,
                             __global const int *grid, int ntex, __global float *out) {
    int gid = get_global_id(0);
    Hit hit;
    if (fr->type == LIGHT_DIRECTIONAL) {
        int res = fr->sm_res;
        if (gid >= res * res) return;
        float4 rect = fr->sm_rect;
        float x1 = rect.x + ((gid % res) + 0.5f) * (rect.z - rect.x) / res;
        float x2 = rect.y + ((gid / res) + 0.5f) * (rect.w - rect.y) / res;
        /* the map stores the blocker's axial coordinate z = (x - eye).u; a grid with
         * projected triangles (origin eye, axes sm_s1, sm_s2, direction -u) takes the
         * texel's plane coordinates as they are */
        float t;
        int got = grid_closest_plane(grid, x1, x2, -fr->z_start, 0.0f, T_INF, &t);
        if (got < 0) {
            float4 o = fr->eye + x1 * fr->sm_s1 + x2 * fr->sm_s2 + fr->z_start * fr->u;
            o.w = 0.0f;
            got = scene_closest(nodes, tris, grid, o, -fr->u, 0.0f, T_INF, &hit);
            t = hit.t;
        }
        out[gid] = got ? fr->z_start - t : T_INF;
        return;
    }
    if (gid >= ntex) return;
    /* spot: the face holding texel gid (faces are stored one after the other) */
    int f = 0;
    while (f + 1 < fr->sm_faces && gid >= (int)faces[f + 1].e2.w) ++f;
    __global const EpiFace *fc = &faces[f];
    int nx = (int)fc->c.w, ny = (int)fc->e1.w, loc = gid - (int)fc->e2.w;
    float4 rect = fc->rect;
    float x1 = rect.x + ((loc % nx) + 0.5f) * (rect.z - rect.x) / nx;
    float x2 = rect.y + ((loc / nx) + 0.5f) * (rect.w - rect.y) / ny;
    float4 c = fc->c, e1 = fc->e1, e2 = fc->e2;
    c.w = 0.0f; e1.w = 0.0f; e2.w = 0.0f;
    /* the map stores the blocker's distance from the light */
    float4 dir = normalize3(c + x1 * e1 + x2 * e2);
    dir.w = 0.0f;
    out[gid] = scene_closest(nodes, tris, grid, fr->light, dir, 0.0f, T_INF, &hit) ? hit.t
                                                                                : T_INF;
}

/* camera ray through a continuous position in the image (x right, y down, in pixels of
 * a w x h raster spanning the camera's field of view; the view_paths.cl convention) */
float4 epi_camera_dir(__global const Camera *cam, float px, float py, int w, int h) {
    float fx = 2.0f * px / w - 1.0f;
    float fy = 1.0f - 2.0f * py / h;
    return normalize3(cam->forward + fx * cam->right + fy * cam->up);
}

/* continuous raster position of direction v (w x h raster); 0 when v is behind */
int epi_project(__global const Camera *cam, float4 v, int w, int h, float *px, float *py) {
    float z = dot3(v, cam->forward);
    if (!(z > 0.0f)) return 0;
    float sx = dot3(v, cam->right) / dot3(cam->right, cam->right) / z;
    float sy = dot3(v, cam->up) / dot3(cam->up, cam->up) / z;
    *px = (sx + 1.0f) * 0.5f * w;
    *py = (1.0f - sy) * 0.5f * h;
    return 1;
}

__kernel void epi_depth_map(__global const BVHNode *nodes, __global const float4 *tris,
                            __global const Camera *cam, int w, int h, __global float *out) {
    int gid = get_global_id(0);
    if (gid >= w * h) return;
    float4 d = epi_camera_dir(cam, (gid % w) + 0.5f, (gid / w) + 0.5f, w, h);
    Hit hit;
    out[gid] = bvh_closest(nodes, tris, cam->origin, d, 0.0f, T_INF, &hit) ? hit.t : T_INF;
}

/* ---- rectification ---- */

/* Shadow-map value seen by the light ray gamma of slice w (nearest texel, as in shadow
 * mapping): the blocker's axial coordinate z (directional) or its distance r from the
 * light (spot, in the face its direction falls in); T_INF when nothing blocks it. */
float epi_blocker(__global const EpiFrame *fr, __global const EpiFace *faces,
                  __global const float *smap, float4 w, float gamma) {
    float x1, x2;
    float4 rect;
    int nx, ny, base = 0;
    if (fr->type == LIGHT_DIRECTIONAL) {
        /* the light ray through eye + gamma w projects to one point of the map */
        x1 = gamma * dot3(w, fr->sm_s1);
        x2 = gamma * dot3(w, fr->sm_s2);
        rect = fr->sm_rect;
        nx = ny = fr->sm_res;
    } else {
        /* every direction of the cone (up to 90 degrees) lies in one of the faces */
        float4 l = epi_spot_dir(fr, w, gamma);
        int f = epi_face_of(fr, faces, l);
        if (f < 0) return T_INF;
        __global const EpiFace *fc = &faces[f];
        float lc = dot3(l, fc->c);
        x1 = dot3(l, fc->e1) / lc;
        x2 = dot3(l, fc->e2) / lc;
        rect = fc->rect;
        nx = (int)fc->c.w;
        ny = (int)fc->e1.w;
        base = (int)fc->e2.w;
    }
    float fx = (x1 - rect.x) / (rect.z - rect.x) * nx;
    float fy = (x2 - rect.y) / (rect.w - rect.y) * ny;
    if (!(fx >= 0.0f && fx < nx && fy >= 0.0f && fy < ny)) return T_INF;
    return smap[base + (int)fy * nx + (int)fx];
}

/* The blocker's slice position (z, rho) and its beta = atan2(rho, z) (paper, Sec. 3: the
 * value changes in rectification, depth -> beta). */
float epi_blocker_beta(__global const EpiFrame *fr, float gamma, float v) {
    if (fr->type == LIGHT_DIRECTIONAL) return atan2_fast(gamma, v);
    float c, s = sincos_fast(gamma, &c);
    return atan2_fast(v * s, fr->D - v * c);
}

/* Sort key increasing with beta along one light ray (directional: beta falls as z
 * rises; spot: beta rises with r), and the key difference that makes one pixel angle
 * beta_tol of beta at (gamma, v): d beta / d z = -gamma / (gamma^2 + z^2) and
 * d beta / d r = D sin(gamma) / t^2 with t the distance from the eye. */
float epi_mode_key(__global const EpiFrame *fr, float v) {
    return fr->type == LIGHT_DIRECTIONAL ? -v : v;
}
float epi_mode_tol(__global const EpiFrame *fr, float gamma, float v) {
    if (fr->type == LIGHT_DIRECTIONAL) return fr->beta_tol * (gamma * gamma + v * v) / fmax(gamma, 1e-12f);
    float c, s = sincos_fast(gamma, &c);
    float z = fr->D - v * c, rho = v * s;
    return fr->beta_tol * (z * z + rho * rho) / fmax(fr->D * s, 1e-12f);
}

/* One work-item per (slice, light ray): the termination modes of the light ray.
 * term[(k*d + i)*EPI_MODES + m] = (beta, frac): at beta, remove the fraction frac of what
 * is left of the light ray (frac relative to the remainder, so the sweep can scale the
 * leaf it holds; 1 = the rest). frac = 0 marks an unused entry. Sub-samples are grouped
 * by depth (one pixel angle of beta apart at most from a mode's first member), so only
 * one atan2 per mode is needed; a mode's beta is that of its mean gamma and depth. */
__kernel void epi_rectify_shadow(__global const EpiFrame *fr, __global const EpiSlice *slices,
                                 int slice0, int nbatch, __global const EpiFace *faces,
                                 __global const float *smap, __global float2 *term) {
    int gid = get_global_id(0);
    int d = fr->d;
    if (gid >= nbatch * d) return;
    int kl = gid / d, i = gid % d;
    __global const EpiSlice *sl = &slices[slice0 + kl];
    float dg = (sl->gamma_hi - sl->gamma_lo) / d;
    float g[EPI_MODES], v[EPI_MODES], key[EPI_MODES];
    int ns = fr->prefilter ? EPI_MODES : 1;
    for (int s = 0; s < ns; ++s) {
        float off = fr->prefilter ? (s + 0.5f) / EPI_MODES : 0.5f;
        g[s] = sl->gamma_lo + (i + off) * dg;
        v[s] = epi_blocker(fr, faces, smap, sl->w, g[s]);
        key[s] = v[s] >= 0.5f * T_INF ? INFINITY : epi_mode_key(fr, v[s]);
    }
    for (int s = 1; s < ns; ++s)            /* insertion sort by key, at most 4 values */
        for (int r = s; r > 0 && key[r - 1] > key[r]; --r) {
            float x = key[r]; key[r] = key[r - 1]; key[r - 1] = x;
            x = v[r]; v[r] = v[r - 1]; v[r - 1] = x;
            x = g[r]; g[r] = g[r - 1]; g[r - 1] = x;
        }
    __global float2 *out = term + (size_t)gid * EPI_MODES;
    int m = 0;
    float left = 1.0f;
    int s = 0;
    float prev = -1.0f;
    while (s < ns && key[s] < INFINITY) {   /* sub-samples that hit nothing stay lit */
        float tol = epi_mode_tol(fr, g[s], v[s]);
        int e = s + 1;
        float sg = g[s], sv = v[s];
        while (e < ns && key[e] - key[s] <= tol) { sg += g[e]; sv += v[e]; ++e; }
        float wgt = (float)(e - s) / ns;
        /* keep the modes in beta order: the sweep applies them in that order */
        float beta = fmax(epi_blocker_beta(fr, sg / (e - s), sv / (e - s)), prev);
        prev = beta;
        out[m++] = (float2)(beta, e == ns ? 1.0f : wgt / left);
        left -= wgt;
        s = e;
    }
    for (; m < EPI_MODES; ++m) out[m] = (float2)(0.0f, 0.0f);
}

/* One work-item per (slice, grid view ray): the view ray beta_j of the slice, its medium
 * interval ending at the depth map's surface (nearest pixel), as (beta, gamma0, gamma1,
 * t_a) events for epi_integrate. */
__kernel void epi_rectify_depth(__global const EpiFrame *fr, __global const EpiSlice *slices,
                                int slice0, int nbatch, __global const Medium *medium,
                                __global const Camera *cam, __global const float *depth,
                                int dw, int dh, __global float4 *events) {
    int gid = get_global_id(0);
    int R = fr->rays;
    if (gid >= nbatch * R) return;
    int kl = gid / R, j = gid % R;
    __global const EpiSlice *sl = &slices[slice0 + kl];
    float beta = sl->beta_lo + (j + 0.5f) * (sl->beta_hi - sl->beta_lo) / R;
    float4 v = epi_view_dir(fr, sl->w, beta);
    v.w = 0.0f;
    float t_hit = T_INF, px, py;
    if (epi_project(cam, v, dw, dh, &px, &py)) {
        int ix = clamp((int)px, 0, dw - 1), iy = clamp((int)py, 0, dh - 1);
        t_hit = depth[iy * dw + ix];
    }
    float t0, t1;
    float4 ev = (float4)(beta, 0.0f, 0.0f, 0.0f);
    if (medium_interval(medium, fr->eye, v, 0.0f, t_hit, &t0, &t1) && t1 > t0) {
        ev.y = epi_gamma(fr, t0, beta);
        ev.z = epi_gamma(fr, t1, beta);
        ev.w = t0;
    }
    events[(size_t)slice0 * R + gid] = ev;     /* slice k's rays start at k * R */
}

/* ---- integration ---- */

/* F(alpha, gamma) per channel: what depends on the light ray alone, relative to the
 * light-side reference lref = l_ref(gamma) that K contains (svd.py). Directional: the
 * light ray enters the box at the axial coordinate z_exit (t1 along +u; defined, and
 * continuous, even for a near miss), K has exp(-kappa (z_ref - z)), so F =
 * exp(kappa (z_ref - z_exit)). Spot: it enters at r_enter from the light, K has
 * exp(-kappa (r - r_ref)), so F = exp(kappa (r_enter - r_ref)), times the fraction of the
 * light ray's cell [gamma +- dg/2] inside the cone. The exponent is clamped to the spread
 * measured over the light rays that meet the medium (fr->lspan): a ray that misses the
 * box has an arbitrary entry, and an unbounded value would swamp the float32 prefix sums
 * of its slice (it is never integrated: no view segment of the slice reaches it). */
void epi_light_factor_span(__global const EpiFrame *fr, __global const EpiSlice *sl,
                           float gamma, float dg, float lref, float span, float *F) {
    float x = 0.0f, cov = 1.0f;
    float t0, t1;
    if (fr->type == LIGHT_DIRECTIONAL) {
        float4 o = fr->eye + gamma * sl->w;
        ray_box(o, safe_inv_dir(fr->u), fr->bmin, fr->bmax, -T_INF, T_INF, &t0, &t1);
        x = lref - t1;                               /* z_ref - z_exit */
    } else {
        float a = fmax(gamma - 0.5f * dg, sl->cone_lo), b = fmin(gamma + 0.5f * dg, sl->cone_hi);
        cov = dg > 0.0f ? clamp((b - a) / dg, 0.0f, 1.0f) : 0.0f;
        if (fr->bounded) {
            float4 l = epi_spot_dir(fr, sl->w, gamma);
            ray_box(fr->light, safe_inv_dir(l), fr->bmin, fr->bmax, 0.0f, T_INF, &t0, &t1);
            x = t0 - lref;                           /* r_enter - r_ref */
        }
    }
    x = clamp(x, -span, span);
    for (int c = 0; c < EPI_NCH; ++c)
        F[c] = cov * exp(clamp(epi_kappa(fr, c) * x, -EPI_EXP_MAX, EPI_EXP_MAX));
}

void epi_light_factor(__global const EpiFrame *fr, __global const EpiSlice *sl, float gamma,
                      float dg, float lref, float *F) {
    epi_light_factor_span(fr, sl, gamma, dg, lref, fr->lspan, F);
}

/* linear interpolation in a table of n floats sampled uniformly on [lo, hi] */
float epi_table1(__global const float *tab, int n, float lo, float hi, float x) {
    float s = (n > 1 && hi > lo) ? (x - lo) / (hi - lo) * (float)(n - 1) : 0.0f;
    s = clamp(s, 0.0f, (float)(n - 1));
    int i = min((int)s, n - 2 < 0 ? 0 : n - 2);
    int j = n > 1 ? i + 1 : i;
    float f = n > 1 ? s - (float)i : 0.0f;
    return (1.0f - f) * tab[i] + f * tab[j];
}

/* lower bound: first event of [0, n) whose beta is >= b, searched from the hint h
 * outwards in doubling steps, then by halving (galloping): a few steps when the answer
 * is near h (the modes of neighbouring light rays), about 2 log2 n at worst */
int epi_lower_bound(__global const float4 *ev, int n, float b, int h) {
    h = clamp(h, 0, n);
    int lo, hi, step = 1;
    if (h < n && ev[h].x < b) {                   /* the answer is past h */
        lo = h + 1;
        hi = lo;
        while (hi < n && ev[hi].x < b) { lo = hi + 1; hi += step; step <<= 1; }
        hi = min(hi, n);
    } else {                                      /* the answer is h or before */
        hi = h;
        lo = h - 1;
        while (lo >= 0 && !(ev[lo].x < b)) { hi = lo; lo -= step; step <<= 1; }
        lo = max(lo + 1, 0);
    }
    while (lo < hi) {
        int mid = (lo + hi) >> 1;
        if (ev[mid].x < b) lo = mid + 1; else hi = mid;
    }
    return lo;
}

/* ---- the error estimate's light-ray sums (svd.riemann_sums on the device) ---- */

/* svd.soft: y for y >= 0, expm1(y) below */
float epi_soft(float y) { return y >= 0.0f ? y : expm1(y); }

/* K of svd.py at one (gamma, beta) with the references tr = t_ref(beta), lr = l_ref(gamma),
 * exactly (not from the SVD's tables); soft: the referenced formulation's soft branch.
 * sb, cb: sin and cos of beta (a sample's, computed once). */
float epi_k_exact(__global const EpiFrame *fr, float kap, float g, float gam, float beta,
                  float sb, float cb, float tr, float lr, int soft) {
    float a, b, ph = 1.0f;
    if (fr->type == LIGHT_SPOT) {
        float cs, cg;
        float s = fmin(gam + beta, PI_F - 1e-4f);      /* beyond pi - beta no view ray reaches */
        float ss = sincos_fast(s, &cs), sg = sincos_fast(gam, &cg);
        a = kap * (fr->D * sg / ss - tr);
        b = kap * (fr->D * sb / ss - lr);
        ph = hg_phase(cs, g);
    } else {
        float isb = 1.0f / fmax(sb, 1e-12f);
        a = kap * (gam * isb - tr);                     /* distance from the eye */
        b = kap * (lr - gam * (cb * isb));              /* light path from the reference */
    }
    float e = soft ? epi_soft(a) + epi_soft(b) : a + b;
    if (isnan(e)) e = 700.0f;
    return ph * exp(-fmin(e, 700.0f));
}

/* One work-item per (held-out sample j, light-ray count dlist[w]), gid = w * n + j: what
 * the sweep computes for the sample without occluders, with the exact K (svd.riemann_sums,
 * float32 with compensated sums): over the d light rays of the sample's slice kidx[j]
 * (cells of dg = (gamma_hi - gamma_lo) / d, values at the centres, a spot cone as the
 * cell's coverage), the overlap of each cell with [g_a, g_b] times F K, per channel. F as
 * epi_light_factor with the references' span; the references l_ref (nl nodes over
 * [l_lo, l_hi]) and t_ref (nt nodes over [t_lo, t_hi]). held[j] = (beta, g_a, g_b, -).
 * A sample spanning more than max_cells cells gets NaN (as the host's). */
__kernel void epi_riemann(__global const EpiFrame *fr, __global const EpiSlice *slices,
                          __global const int *kidx, __global const float4 *held, int n,
                          __global const int *dlist, int nd,
                          __global const float *lref, int nl, float l_lo, float l_hi,
                          __global const float *tref, int nt, float t_lo, float t_hi,
                          float span, int soft, float g, int max_cells,
                          __global float4 *out) {
    int gid = get_global_id(0);
    if (gid >= n * nd) return;
    int j = gid % n, d = dlist[gid / n];
    __global const EpiSlice *sl = &slices[kidx[j]];
    float4 h = held[j];
    float beta = h.x;
    float dg = fmax((sl->gamma_hi - sl->gamma_lo) / d, 1e-30f);
    float ma = clamp((h.y - sl->gamma_lo) / dg, 0.0f, (float)d);
    float mb = clamp((h.z - sl->gamma_lo) / dg, 0.0f, (float)d);
    int i0 = (int)floor(ma), i1 = min((int)ceil(mb), d);
    if (i1 - i0 > max_cells) {
        out[gid] = (float4)(NAN);
        return;
    }
    float tr = epi_table1(tref, nt, t_lo, t_hi, beta);
    float cb, sb = sincos_fast(beta, &cb);
    float sum[3] = {0.0f, 0.0f, 0.0f}, err[3] = {0.0f, 0.0f, 0.0f};
    for (int i = i0; i < i1; ++i) {
        float ov = clamp(fmin((float)(i + 1), mb) - fmax((float)i, ma), 0.0f, 1.0f);
        float gc = sl->gamma_lo + (i + 0.5f) * dg;
        float lr = epi_table1(lref, nl, l_lo, l_hi, gc);
        float F[EPI_NCH];
        epi_light_factor_span(fr, sl, gc, dg, lr, span, F);
        for (int c = 0; c < EPI_NCH; ++c) {
            float k = epi_k_exact(fr, epi_kappa(fr, c), g, gc, beta, sb, cb, tr, lr, soft);
            float v = ov * dg * F[c] * k;
            float y = v - err[c], t = sum[c] + y;     /* Kahan */
            err[c] = (t - sum[c]) - y;
            sum[c] = t;
        }
    }
    out[gid] = (float4)(sum[0], sum[1], sum[2], 0.0f);
}

/* beta a sorts before beta b in the runs (the bucket sort's order: NaN last) */
int epi_before(float a, float b) {
    return a < b || (isnan(b) && !isnan(a));
}

/* One work-item per slice (paper, Fig. 6). The events are runs sorted by beta, each
 * (beta, gamma0, gamma1, t_a); run r is events[ev_off[r] .. ev_off[r+1]). Slice k sweeps
 * run k, and with two_runs also run k - 1 (run nslices - 1 for slice 0 of a full fan:
 * wrap), merged by beta: the segment lookup's runs hold the samples by their first
 * slice, whose second slice is the next. out gets, per event and channel,
 *   exp(kappa (t_a - t_ref(beta))) * sum_n B_n(beta) * (Q_n(gamma1) - Q_n(gamma0))
 * with Q_n the prefix sums of F * Gamma_n * dgamma over the light rays still lit, at
 * out[p] for event p of a single run, at out[2 p + side] with two runs (side 0: the
 * slice's own run, 1: the previous one).
 * The SVD tables come per group of slices (slice->group): gtab [group][n_g][EPI_NV] over
 * groups[group].xy (gamma), btab [group][n_b][EPI_NV] over groups[group].zw (beta), and
 * the references gref [group][n_g] = l_ref, bref [group][n_b] = t_ref on the same grids.
 * term: the rectified termination modes (epi_rectify_shadow); the sweep overwrites their
 * betas with the modes' buckets. Scratch: tree/leaf [nbatch][d][EPI_NV]; from
 * cnt_off[k] - cnt_off[slice0] + kl on, the slice's cnt (one more than its events),
 * merged (its events in sweep order, two_runs only) and dst (their places in out);
 * sorted [nbatch][d * EPI_MODES]. work[k] = (tree updates, tree queries) for --stats. */
__kernel void epi_integrate(__global const EpiFrame *fr, __global const EpiSlice *slices,
                            int slice0, int nbatch, __global float2 *term,
                            __global const int *ev_off, int two_runs, int wrap, int nslices,
                            __global const int *cnt_off, __global const float4 *events,
                            __global const float *gtab_all, int n_g,
                            __global const float *btab_all, int n_b,
                            __global const float *gref_all, __global const float *bref_all,
                            __global const float4 *groups, __global float *tree, __global float *leaf, __global int *cnt_all,
                            __global float4 *merged_all, __global int *dst_all,
                            __global int2 *sorted_all, __global float4 *out,
                            __global int2 *work) {
    int kl = get_global_id(0);
    if (kl >= nbatch) return;
    int k = slice0 + kl;
    int d = fr->d;
    __global const EpiSlice *sl = &slices[k];
    __global float *T = tree + (size_t)kl * d * EPI_NV;
    __global float *L = leaf + (size_t)kl * d * EPI_NV;
    float dg = (sl->gamma_hi - sl->gamma_lo) / d;
    /* this slice's SVD group: its tables, references and ranges */
    int grp = sl->group;
    __global const float *gtab = gtab_all + (size_t)grp * n_g * EPI_NV;
    __global const float *btab = btab_all + (size_t)grp * n_b * EPI_NV;
    __global const float *gref = gref_all + (size_t)grp * n_g;
    __global const float *bref = bref_all + (size_t)grp * n_b;
    float4 rg = groups[grp];
    float g_lo = rg.x, g_hi = rg.y, b_lo = rg.z, b_hi = rg.w;

    /* ---- the tree: b[i] = F(alpha, gamma_i) Gamma(gamma_i) dgamma (Sec. 6, textured light) ---- */
    for (int i = 0; i < d; ++i) {
        float g = sl->gamma_lo + (i + 0.5f) * dg;
        float G[EPI_NV], F[EPI_NCH];
        epi_table(gtab, n_g, g_lo, g_hi, g, G);
        epi_light_factor(fr, sl, g, dg, epi_table1(gref, n_g, g_lo, g_hi, g), F);
        for (int c = 0; c < EPI_NCH; ++c)
            for (int n = 0; n < EPI_NT; ++n) {
                float v = G[c * EPI_NT + n] * F[c] * dg;
                L[i * EPI_NV + c * EPI_NT + n] = v;
                T[i * EPI_NV + c * EPI_NT + n] = v;
            }
    }
    fw_build(T, d);

    /* ---- the events: run A (this slice's) and run B (the previous slice's, or none),
     * merged by beta into ev (A first on equal betas), dst[q] where event q's result goes */
    int ea = ev_off[k], na = ev_off[k + 1] - ea, eb = 0, nb = 0;
    if (two_runs && (k > 0 || wrap)) {
        int pk = k > 0 ? k - 1 : nslices - 1;
        eb = ev_off[pk];
        nb = ev_off[pk + 1] - eb;
    }
    int ne = na + nb;
    size_t base = (size_t)(cnt_off[k] - cnt_off[slice0]) + kl;
    __global int *cnt = cnt_all + base;                  /* ne + 1 buckets */
    __global const float4 *ev = events + ea;
    __global int *dst = dst_all + base;
    if (two_runs) {
        __global const float4 *A = events + ea, *B = events + eb;
        __global float4 *mev = merged_all + base;
        int ia = 0, ib = 0;
        for (int q = 0; q < ne; ++q) {
            int side = ib < nb && (ia == na || epi_before(B[ib].x, A[ia].x));
            mev[q] = side ? B[ib] : A[ia];
            dst[q] = 2 * (side ? eb + ib : ea + ia) + side;
            if (side) ++ib; else ++ia;
        }
        ev = mev;
    } else {
        for (int q = 0; q < ne; ++q) dst[q] = ea + q;
    }

    /* ---- termination lists: bucket the modes by the first event at or after them, once
     * per mode ---- */
    __global int2 *srt = sorted_all + (size_t)kl * d * EPI_MODES;
    __global float2 *tm = term + (size_t)kl * d * EPI_MODES;
    for (int q = 0; q <= ne; ++q) cnt[q] = 0;
    int hint[EPI_MODES];                         /* mode m of the last ray with one */
    for (int m = 0; m < EPI_MODES; ++m) hint[m] = 0;
    for (int i = 0; i < d * EPI_MODES; ++i)      /* the bucket replaces the mode's beta */
        if (tm[i].y > 0.0f) {
            int q = epi_lower_bound(ev, ne, tm[i].x, hint[i % EPI_MODES]);
            hint[i % EPI_MODES] = q;
            cnt[q] += 1;
            tm[i].x = as_float(q);
        }
    int run = 0;
    for (int q = 0; q <= ne; ++q) { int c = cnt[q]; cnt[q] = run; run += c; }
    for (int i = 0; i < d * EPI_MODES; ++i)     /* stable: modes of a ray stay in beta order */
        if (tm[i].y > 0.0f)
            srt[cnt[as_int(tm[i].x)]++] = (int2)(i / EPI_MODES, as_int(tm[i].y));
    /* now cnt[q] is the end of bucket q */

    /* ---- the sweep over view rays, away from the light ---- */
    int p = 0, queries = 0;
    for (int q = 0; q < ne; ++q) {
        for (int end = cnt[q]; p < end; ++p)
            fw_scale_leaf(T, L, d, srt[p].x, as_float(srt[p].y));
        float4 e = ev[q];
        float a0[EPI_NV], a1[EPI_NV], Bt[EPI_NV];
        for (int c = 0; c < EPI_NV; ++c) { a0[c] = 0.0f; a1[c] = 0.0f; }
        if (e.z > e.y && dg > 0.0f) {
            fw_query(T, L, d, (e.y - sl->gamma_lo) / dg, a0);
            fw_query(T, L, d, (e.z - sl->gamma_lo) / dg, a1);
            queries += 2;
        }
        epi_table(btab, n_b, b_lo, b_hi, e.x, Bt);
        float dt = e.w - epi_table1(bref, n_b, b_lo, b_hi, e.x);    /* t_a - t_ref(beta) */
        float r[3] = {0.0f, 0.0f, 0.0f};
        for (int c = 0; c < EPI_NCH; ++c) {
            float s = 0.0f;
            for (int n = 0; n < EPI_NT; ++n)
                s += Bt[c * EPI_NT + n] * (a1[c * EPI_NT + n] - a0[c * EPI_NT + n]);
            /* radiance is >= 0; float cancellation of the signed SVD terms is not */
            r[c] = fmax(s, 0.0f) * exp(clamp(epi_kappa(fr, c) * dt, -EPI_EXP_MAX, EPI_EXP_MAX));
        }
        out[dst[q]] = (float4)(r[0], r[1], r[2], 0.0f);
    }
    work[k] = (int2)(p, queries);
}

/* ---- resampling between the image and the rectified grid ---- */

/* slices k0, k1 around angle phi and the weight f of k1 (phis sorted, unwrapped; the
 * same code as geometry.Slices.bracket: a full fan wraps, an open fan is cut in the
 * middle of its gap and clamps at its ends) */
void epi_bracket(__global const float *phis, int n, int full, __global const int *lut,
                 int bins, float phi, int *k0, int *k1, float *f) {
    float two_pi = 2.0f * PI_F;
    float base = full ? phis[0] : phis[0] - 0.5f * (two_pi - (phis[n - 1] - phis[0]));
    /* phi - base mod 2 pi in [0, 2 pi) by floor (the builtin fmod is a slow scalar
     * routine on some drivers: PoCL's CPU device, 14.0 ns per work-item against 2.0,
     * tools/bench_epipolar_costs.py) */
    float r = phi - base;
    r -= two_pi * floor(r / two_pi);
    r = r >= two_pi ? r - two_pi : (r < 0.0f ? 0.0f : r);
    float x = base + r;
    /* lo = number of phis <= x, found in the window the lookup table gives its bin (one
     * bin of slack each side for rounding; Slices.lookup_table) */
    int b = clamp((int)(r * ((float)bins / two_pi)), 0, bins - 1);
    int lo = b >= 1 ? lut[b - 1] : 0, hi = b + 2 <= bins ? lut[b + 2] : n;
    while (lo < hi) {
        int mid = (lo + hi) >> 1;
        if (phis[mid] <= x) lo = mid + 1; else hi = mid;
    }
    int i = lo - 1;
    int first = i < 0, last = i == n - 1;
    i = clamp(i, 0, n - 1);
    int j = min(i + 1, n - 1);
    float nxt = phis[j];
    if (full && last) { j = 0; nxt = phis[0] + two_pi; }
    float gap = nxt - phis[i];
    *k0 = i;
    *k1 = j;
    *f = gap > 0.0f ? clamp((x - phis[i]) / gap, 0.0f, 1.0f) : 0.0f;
    if (!full && (first || last)) { *k1 = i; *f = 0.0f; }
}

/* beta of the unit direction v and the slices around it (geometry.Axis.coords +
 * bracket); *sb, *cb: sin and cos of beta (|v - (v.u) u| and v.u) */
float epi_locate(__global const EpiFrame *fr, __global const float *phis, int n, int full,
                 __global const int *lut, int bins, float4 v, int *k0, int *k1, float *f,
                 float *sb, float *cb) {
    float c = dot3(v, fr->u);
    float4 perp = v - c * fr->u;
    float phi = atan2_fast(dot3(perp, fr->b2), dot3(perp, fr->b1));
    epi_bracket(phis, n, full, lut, bins, phi, k0, k1, f);
    *sb = length3(perp);
    *cb = c;
    return atan2_fast(*sb, c);
}

/* One work-item per view segment: what epi_samples needs of it that no light changes,
 * built once per set of view segments (pipeline.py): dirs = (unit direction v from the
 * eye to its end b, t_b = |b - eye|), ta = max((a - eye).v, 0), the distances of its ends
 * from the eye. 20 bytes read per light move instead of the 64-byte record. */
__kernel void epi_view_dirs(__global const ViewSegment *segs, int n, float4 eye,
                            __global float4 *dirs, __global float *ta) {
    int gid = get_global_id(0);
    if (gid >= n) return;
    float4 a = segs[gid].a - eye, b = segs[gid].b - eye;
    a.w = 0.0f;
    b.w = 0.0f;
    float t_b = length3(b);
    float4 v = b / fmax(t_b, 1e-30f);
    ta[gid] = fmax(dot3(a, v), 0.0f);
    v.w = t_b;
    dirs[gid] = v;
}

/* One work-item per primary view segment (segment lookup): its coordinates and the two
 * slices around it, from its direction and distances (epi_view_dirs). geo = (beta,
 * gamma(t_a), gamma(t_b), t_a) with t_a, t_b the distances of the segment's ends from the
 * eye; idx = (k0, k1, weight of k1 as bits, in the ring). The ring is the disc of radius
 * ring.z pixels around the epipole (ring.x, ring.y). */
__kernel void epi_samples(__global const EpiFrame *fr, __global const float *phis, int nslices,
                          int full, __global const int *lut, int bins,
                          __global const Camera *cam, float4 ring,
                          __global const float4 *dirs, __global const float *ta, int n,
                          __global float4 *geo, __global int4 *idx) {
    int gid = get_global_id(0);
    if (gid >= n) return;
    float4 v = dirs[gid];
    float t_b = v.w, t_a = ta[gid];
    v.w = 0.0f;
    int k0, k1;
    float f;
    float sb, cb;
    float beta = epi_locate(fr, phis, nslices, full, lut, bins, v, &k0, &k1, &f, &sb, &cb);
    float px, py;
    int in_ring = ring.z > 0.0f && epi_project(cam, v, cam->width, cam->height, &px, &py)
                  && hypot(px - ring.x, py - ring.y) < ring.z;
    geo[gid] = (float4)(beta, epi_gamma_sc(fr, t_a, sb, cb), epi_gamma_sc(fr, t_b, sb, cb), t_a);
    idx[gid] = (int4)(k0, k1, as_int(f), in_ring);
}

/* value of grid row k (R samples over the slice's beta range) at beta, linear */
float4 epi_grid_at(__global const EpiSlice *sl, __global const float4 *grid, int R, float beta) {
    float span = sl->beta_hi - sl->beta_lo;
    float s = span > 0.0f ? (beta - sl->beta_lo) / span * R - 0.5f : 0.0f;
    s = clamp(s, 0.0f, (float)(R - 1));
    int j = min((int)s, R - 1);
    int j1 = min(j + 1, R - 1);
    float f = s - j;
    return (1.0f - f) * grid[j] + f * grid[j1];
}

/* One work-item per direction: bilinear lookup in the rectified grid (R values per
 * slice) at the direction's (alpha, beta). */
__kernel void epi_unrectify(__global const EpiFrame *fr, __global const EpiSlice *slices,
                            __global const float *phis, int nslices, int full,
                            __global const int *lut, int bins, int R,
                            __global const float4 *grid, __global const float4 *dirs, int n,
                            __global float4 *out) {
    int gid = get_global_id(0);
    if (gid >= n) return;
    float4 v = dirs[gid];
    v.w = 0.0f;
    int k0, k1;
    float f;
    float sb, cb;
    float beta = epi_locate(fr, phis, nslices, full, lut, bins, v, &k0, &k1, &f, &sb, &cb);
    float4 a = epi_grid_at(&slices[k0], grid + (size_t)k0 * R, R, beta);
    float4 b = epi_grid_at(&slices[k1], grid + (size_t)k1 * R, R, beta);
    out[gid] = (1.0f - f) * a + f * b;
}

/* One work-item per grid sample: bilinear sample of a (h, w) float4 image at the grid
 * view ray's pixel position (the rectification of an image, for tests and tools). */
__kernel void epi_rectify_image(__global const EpiFrame *fr, __global const EpiSlice *slices,
                                int nslices, int R, __global const Camera *cam,
                                __global const float4 *img, int w, int h,
                                __global float4 *grid) {
    int gid = get_global_id(0);
    if (gid >= nslices * R) return;
    int k = gid / R, j = gid % R;
    __global const EpiSlice *sl = &slices[k];
    float beta = sl->beta_lo + (j + 0.5f) * (sl->beta_hi - sl->beta_lo) / R;
    float4 v = epi_view_dir(fr, sl->w, beta);
    float px, py;
    float4 r = (float4)(0.0f);
    if (epi_project(cam, v, w, h, &px, &py)) {
        float x = clamp(px - 0.5f, 0.0f, (float)(w - 1)), y = clamp(py - 0.5f, 0.0f, (float)(h - 1));
        int x0 = min((int)x, w - 1), y0 = min((int)y, h - 1);
        int x1 = min(x0 + 1, w - 1), y1 = min(y0 + 1, h - 1);
        float fx = x - x0, fy = y - y0;
        r = (1.0f - fy) * ((1.0f - fx) * img[y0 * w + x0] + fx * img[y0 * w + x1])
            + fy * ((1.0f - fx) * img[y1 * w + x0] + fx * img[y1 * w + x1]);
    }
    grid[gid] = r;
}

/* ---- the segment lookup's per-sample tables, on the device (pipeline.py) ----
 * Sample i is view segment i (all segments of the image, sorted by camera sample);
 * live[j] (j < L) lists the samples the sweep integrates, in increasing order. */

/* Ring weight of every view segment (pipeline.ring_weights): 1 within the ring around
 * the epipole (the anti-epipole when the light is behind the camera: front = 0),
 * smoothstep to 0 across the band out to `outer`, 0 beyond; only primary segments
 * (depth 0) take part (deeper ones are ray marched whole: weight 0, not live).
 * live_flag = primary and w < 1 (the sweep), counts = (primary samples with w > 0,
 * those with 0 < w < 1). */
__kernel void epi_ring(__global const ViewSegment *segs, __global const float4 *geo, int n,
                       int front, float radius, float outer, __global float *wr,
                       __global int *live_flag, volatile __global int *counts) {
    int i = get_global_id(0);
    if (i >= n) return;
    int primary = segs[i].depth == 0;
    float beta = geo[i].x;
    float ang = front ? beta : PI_F - beta;
    float w = 0.0f;
    if (radius > 0.0f) {
        if (ang < radius) w = 1.0f;
        else if (ang < outer) {
            float x = clamp((outer - ang) / fmax(outer - radius, 1e-12f), 0.0f, 1.0f);
            w = x * x * (3.0f - 2.0f * x);
        }
    }
    if (!primary) w = 0.0f;
    wr[i] = w;
    live_flag[i] = primary && w < 1.0f;
    if (primary && w > 0.0f) {
        atomic_inc(&counts[0]);
        if (w < 1.0f) atomic_inc(&counts[1]);
    }
}

/* Scale of each segment for the ray-marched parts: primary[i] = 1 for depth 0, deeper[i]
 * = 1 for the segments behind mirrors and glass (counts[0] counts them). */
__kernel void epi_split(__global const ViewSegment *segs, int n, __global float *primary,
                        __global float *deeper, volatile __global int *counts) {
    int i = get_global_id(0);
    if (i >= n) return;
    int d = segs[i].depth > 0;
    primary[i] = d ? 0.0f : 1.0f;
    deeper[i] = d ? 1.0f : 0.0f;
    if (d) atomic_inc(&counts[0]);
}

/* group of slice k when the S slices are cut into G contiguous arcs */
int epi_group_of(int k, int S, int G) { return (int)(((long)k * G) / S); }

/* The beta range of the live samples touching each group of slices (through either of
 * their two slices): bmin/bmax hold float bits (beta >= 0, so int order is float order).
 * One work-item per block of EPI_RANGE_BLOCK samples reduces them privately, then one
 * atomic per group it saw (not one per sample: all samples share G <= 16 addresses). */
#define EPI_RANGE_BLOCK 256
#define EPI_MAX_GROUPS 16
__kernel void epi_view_ranges(__global const float4 *geo, __global const int4 *idx,
                              __global const int *live, int L, int S, int G,
                              volatile __global int *bmin, volatile __global int *bmax) {
    int j0 = get_global_id(0) * EPI_RANGE_BLOCK;
    if (j0 >= L || G > EPI_MAX_GROUPS) return;
    int lo[EPI_MAX_GROUPS], hi[EPI_MAX_GROUPS];
    for (int g = 0; g < G; ++g) { lo[g] = INT_MAX; hi[g] = -1; }
    for (int j = j0; j < min(L, j0 + EPI_RANGE_BLOCK); ++j) {
        int i = live[j];
        int b = as_int(fmax(geo[i].x, 0.0f));
        int g0 = epi_group_of(idx[i].x, S, G), g1 = epi_group_of(idx[i].y, S, G);
        lo[g0] = min(lo[g0], b);
        hi[g0] = max(hi[g0], b);
        lo[g1] = min(lo[g1], b);
        hi[g1] = max(hi[g1], b);
    }
    for (int g = 0; g < G; ++g)
        if (hi[g] >= 0) {
            atomic_min(&bmin[g], lo[g]);
            atomic_max(&bmax[g], hi[g]);
        }
}

/* The least t_a of those samples at each of `nodes` uniform nodes over the group's
 * range (svd.node_extremes): tmin [G][nodes] as float bits (t_a >= 0), +inf where none. */
__kernel void epi_view_nodes(__global const float4 *geo, __global const int4 *idx,
                             __global const int *live, int L, int S, int G,
                             __global const float2 *range, int nodes,
                             volatile __global int *tmin) {
    int j = get_global_id(0);
    if (j >= L) return;
    int i = live[j];
    float4 gi = geo[i];
    int ta = as_int(fmax(gi.w, 0.0f));
    int g[2] = {epi_group_of(idx[i].x, S, G), epi_group_of(idx[i].y, S, G)};
    for (int q = 0; q < 2; ++q) {
        if (q == 1 && g[1] == g[0]) break;
        float2 r = range[g[q]];
        float x = (gi.x - r.x) / fmax(r.y - r.x, 1e-30f) * (float)(nodes - 1);
        int node = clamp((int)rint(x), 0, nodes - 1);
        atomic_min(&tmin[g[q] * nodes + node], ta);
    }
}

/* Event keys, one per live sample j (sample i = live[j]): the sample's run is that of
 * its first slice k0; beta orders a run. Slice k sweeps its own run (the samples' k0
 * side) merged with run k - 1 (their k1 side, k1 = k0 + 1; epi_bracket), so each sample
 * is sorted once and read by both slices (epi_integrate). */
__kernel void epi_event_keys(__global const float4 *geo, __global const int4 *idx,
                             __global const int *live, int L, int nslices,
                             __global const EpiSlice *slices, int bins,
                             __global int *keys, __global float *beta) {
    int j = get_global_id(0);
    if (j >= L) return;
    int i = live[j];
    float b = geo[i].x;
    beta[j] = b;
    /* bin of beta in the slice's beta range: non-decreasing in beta (every step of it
     * rounds monotonically, clamped), so sorting by (bucket, beta) is sorting by (slice,
     * beta); NaN sorts last, as in the bucket sort's float order */
    int k = clamp(idx[i].x, 0, nslices - 1);
    float lo = slices[k].beta_lo, span = slices[k].beta_hi - lo;
    float u = span > 0.0f ? (b - lo) / span * (float)bins : 0.0f;
    int s = isnan(u) ? bins - 1 : (int)clamp(floor(u), 0.0f, (float)(bins - 1));
    keys[j] = k * bins + s;
}

/* The runs in sorted order (perm from the bucket sort): event p = (beta, gamma_a,
 * gamma_b, t_a) of its sample; inv[j] = p. */
__kernel void epi_events(__global const float4 *geo, __global const int *live, int L,
                         __global const int *perm, __global float4 *events,
                         __global int *inv) {
    int p = get_global_id(0);
    if (p >= L) return;
    int j = perm[p];
    events[p] = geo[live[j]];
    inv[j] = p;
}

/* Back to the samples: the blend of a live sample's two results (res[2 p]: its first
 * slice, weight 1 - f; res[2 p + 1]: its second, weight f; p = inv[j], its place in the
 * runs; a weight-0 side is not read), times the light's colour (sigma_s x power) and
 * the sweep's share 1 - w_ring, into values[i] (the caller zeroes values: samples not
 * live stay 0). With one channel in the sweep (grey extinction), its result serves all
 * three. `acc` given per live sample instead (grid lookup: use_acc = 1) skips the blend. */
__kernel void epi_sample_values(__global const float4 *res, __global const int *inv,
                                __global const int4 *idx, __global const int *live, int L,
                                __global const float4 *acc, int use_acc,
                                __global const float *wr, float4 colour,
                                __global float4 *values) {
    int j = get_global_id(0);
    if (j >= L) return;
    int i = live[j];
    float4 s;
    if (use_acc) {
        s = acc[j];
    } else {
        float f = as_float(idx[i].z);
        s = (float4)(0.0f);
        size_t p = (size_t)inv[j];
        if (1.0f - f > 0.0f) s += (1.0f - f) * res[2 * p];
        if (f > 0.0f) s += f * res[2 * p + 1];
    }
#if EPI_NCH == 1
    s = (float4)(s.x, s.x, s.x, 0.0f);
#endif
    values[i] = s * colour * (1.0f - wr[i]);
}

/* weighted[i] = values[i] * segment i's weight (its throughput and transmittance to the eye) */
__kernel void epi_weighted(__global const float4 *values, __global const ViewSegment *segs,
                           int n, __global float4 *weighted) {
    int i = get_global_id(0);
    if (i >= n) return;
    float4 w = segs[i].weight;
    w.w = 0.0f;
    weighted[i] = values[i] * w;
}

/* Test hook: sincos_fast (common.h) over an array: out[2i] = sin, out[2i+1] = cos. */
__kernel void sincos_test(__global const float *x, int n, __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    float c, s = sincos_fast(x[i], &c);
    out[2 * i] = s;
    out[2 * i + 1] = c;
}

/* Test hook: epi_lower_bound of beta b[i] from hint h[i] in the n events
 * (tests/test_epipolar.py). */
__kernel void epi_lower_bound_test(__global const float4 *ev, int n, __global const float *b,
                                   __global const int *h, int m, __global int *out) {
    int i = get_global_id(0);
    if (i < m) out[i] = epi_lower_bound(ev, n, b[i], h[i]);
}

/* Test hook: atan2_fast (common.h) over arrays (tests/test_fast_math.py). */
__kernel void atan2_test(__global const float *y, __global const float *x, int n,
                         __global float *out) {
    int i = get_global_id(0);
    if (i < n) out[i] = atan2_fast(y[i], x[i]);
}

/* Test hook: epi_bracket over angles (tests/test_epipolar.py). */
__kernel void epi_bracket_test(__global const float *phis, int n, int full,
                               __global const int *lut, int bins, __global const float *phi,
                               int m, __global int4 *out) {
    int i = get_global_id(0);
    if (i >= m) return;
    int k0, k1;
    float f;
    epi_bracket(phis, n, full, lut, bins, phi[i], &k0, &k1, &f);
    out[i] = (int4)(k0, k1, as_int(f), 0);
}
