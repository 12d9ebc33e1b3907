/* specular.h: what view paths (view_paths.cl) and light paths (light_paths.cl) share: the
 * branch record, the surface frame at a hit, and mirror / dielectric scattering.
 *
 * Paths are followed deterministically: a dielectric hit *splits* a branch into its
 * Fresnel-weighted reflected and refracted children (no Russian roulette), so images
 * of glass are noise-free and energy bookkeeping is exact. A branch's weight `thr` is
 * a throughput for view paths and a flux for light paths; both only ever get multiplied.
 * Radiance scaling by eta^2 at refraction is omitted from the branches: a branch carries
 * radiance / n^2 (relative to air), which no interface changes. Sources and the medium lie
 * outside all objects, so light reaches a view path in air, save light scattered inside
 * glass (interior_radiance_scale: / n^2); a camera inside glass sees n^2 times what its
 * branches carry, which camera_branch puts in their throughput (Camera.radiance_scale). */
#ifndef CLSCATTER_SPECULAR_H
#define CLSCATTER_SPECULAR_H
#include "common.h"
#include "bvh.h"

typedef struct {
    float4 o, d, thr;
    int depth;    /* specular bounces so far */
    int inside;   /* index of the dielectric material the branch is inside, or -1 */
    int id;       /* branch number within its path tree (0: the first ray) */
    int pad;
} Branch;

/* Unpolarised Fresnel reflectance for a dielectric interface; eta = n_i / n_t.
 * Returns 1 on total internal reflection and sets *cos_t otherwise. */
float fresnel_dielectric(float cos_i, float eta, float *cos_t) {
    float sin2_t = eta * eta * fmax(0.0f, 1.0f - cos_i * cos_i);
    if (sin2_t >= 1.0f) { *cos_t = 0.0f; return 1.0f; }
    float ct = sqrt(1.0f - sin2_t);
    *cos_t = ct;
    float rs = (eta * cos_i - ct) / (eta * cos_i + ct);
    float rp = (cos_i - eta * ct) / (cos_i + eta * ct);
    return 0.5f * (rs * rs + rp * rp);
}

/* Geometry at a hit: point p, shading normal nf and geometric normal gf both turned to
 * face the incoming ray, and whether the ray arrived on the side the geometric normal
 * points to (front: entering a closed object). */
typedef struct { float4 p, nf, gf; int front; } SurfaceFrame;

SurfaceFrame surface_frame(__global const float4 *tris, __global const float4 *normals,
                           const Hit *hit, float4 o, float4 d) {
    SurfaceFrame f;
    int i = hit->tri;
    float4 v0 = tris[3 * i], v1 = tris[3 * i + 1], v2 = tris[3 * i + 2];
    f.p = o + hit->t * d;
    f.p.w = 0.0f;
    float4 ng = normalize3(cross3(v1 - v0, v2 - v0));
    float4 ns = normalize3((1.0f - hit->u - hit->v) * normals[3 * i] + hit->u * normals[3 * i + 1] +
                           hit->v * normals[3 * i + 2]);
    if (dot3(ns, ns) == 0.0f) ns = ng;
    if (dot3(ns, ng) < 0.0f) ns = -ns;
    f.front = dot3(d, ng) < 0.0f;
    f.nf = f.front ? ns : -ns;
    f.gf = f.front ? ng : -ng;
    return f;
}

/* Children of a branch at a mirror or dielectric (material index mi), written to
 * out[0..1]; returns how many. Children below min_weight (max channel) are dropped. */
int specular_children(__global const Material *mat, int mi, const Branch *br,
                      const SurfaceFrame *f, float min_weight, Branch *out) {
    float cos_i = fmax(-dot3(br->d, f->nf), 0.0f);
    float4 refl_d = normalize3(br->d + 2.0f * cos_i * f->nf);
    if (dot3(refl_d, f->gf) <= 0.0f)   /* shading normal bent it below the surface */
        refl_d = normalize3(br->d - 2.0f * dot3(br->d, f->gf) * f->gf);
    Branch r;
    r.o = f->p + f->gf * surface_offset(f->p);
    r.d = refl_d;
    r.depth = br->depth + 1;
    r.inside = br->inside;
    r.pad = 0;
    if (mat->type == MAT_MIRROR) {
        r.thr = br->thr * mat->color;
        if (fmax(r.thr.x, fmax(r.thr.y, r.thr.z)) <= min_weight) return 0;
        out[0] = r;
        return 1;
    }
    /* dielectric: Fresnel split into reflection and refraction (TIR: reflection only) */
    float eta = f->front ? 1.0f / mat->ior : mat->ior;
    float cos_t;
    float F = fresnel_dielectric(cos_i, eta, &cos_t);
    r.thr = br->thr * F;
    Branch t;
    t.thr = br->thr * (1.0f - F);
    t.o = f->p - f->gf * surface_offset(f->p);
    t.d = normalize3(eta * br->d + (eta * cos_i - cos_t) * f->nf);
    t.depth = br->depth + 1;
    t.inside = f->front ? mi : -1;
    t.pad = 0;
    int keep_t = F < 1.0f && dot3(t.d, f->gf) < 0.0f &&
                 fmax(t.thr.x, fmax(t.thr.y, t.thr.z)) > min_weight;
    int keep_r = fmax(r.thr.x, fmax(r.thr.y, r.thr.z)) > min_weight;
    /* the stronger child goes last, so a stack pops it first */
    int n = 0;
    if (F >= 0.5f) {
        if (keep_t) out[n++] = t;
        if (keep_r) out[n++] = r;
    } else {
        if (keep_r) out[n++] = r;
        if (keep_t) out[n++] = t;
    }
    return n;
}

/* Push br's specular children (specular_children) onto a path stack of capacity cap,
 * numbering them from *next_id: one place for the branching of every path tracer. */
void push_specular(__global const Material *mat, int mi, const Branch *br, const SurfaceFrame *f,
                   float min_weight, Branch *stack, int *top, int cap, int *next_id) {
    Branch kids[2];
    int n = specular_children(mat, mi, br, f, min_weight, kids);
    for (int c = 0; c < n && *top < cap; ++c) {
        kids[c].id = (*next_id)++;
        stack[(*top)++] = kids[c];
    }
}

/* The straight piece [*a, *b] of a branch before t_hit that lies in the medium (outside
 * every object, inside the medium bounds; cut at t_far when unbounded). Returns 0 when
 * there is none. Nothing attenuates the branch before *a: outside the bounds is vacuum. */
int medium_piece(__global const Medium *medium, const Branch *br, float t_hit, float4 *a, float4 *b) {
    float t0, t1;
    if (br->inside >= 0 || !medium->present) return 0;
    if (!medium_interval(medium, br->o, br->d, 0.0f, t_hit, &t0, &t1) || !(t1 > t0)) return 0;
    *a = br->o + t0 * br->d;
    *b = br->o + t1 * br->d;
    a->w = 0.0f;
    b->w = 0.0f;
    return 1;
}

/* Extinction inside a dielectric: its interior absorption plus its interior scattering
 * (light scattered inside leaves the branch as it does in the medium). */
float4 interior_kappa(__global const Material *mat) {
    return mat->interior_sigma_a + mat->interior_sigma_s;
}

/* 1 when a dielectric's interior scatters light (interior_sigma_s above 0 in any channel). */
int scatters_inside(__global const Material *mat) {
    float4 s = mat->interior_sigma_s;
    return mat->type == MAT_DIELECTRIC && fmax(s.x, fmax(s.y, s.z)) > 0.0f;
}

/* What radiance inside a dielectric of index n is worth relative to air (where a view
 * branch's throughput is measured): radiance / n^2 is invariant along a ray across an
 * interface, so light scattered inside and leaving towards a camera in air arrives divided
 * by n^2 (the Fresnel transmittance of the crossing is in the view branch's throughput
 * already; Fresnel is the same both ways; a camera inside glass has its n^2 there too). */
float interior_radiance_scale(__global const Material *mat) {
    return 1.0f / (mat->ior * mat->ior);
}

/* The region tag of a path piece (common.h, SEGMENT_FIELDS: the w lane of a): 0 in the
 * scene medium, m + 1 inside dielectric material m. */
float region_tag(int inside) { return inside >= 0 ? (float)(inside + 1) : 0.0f; }

/* The straight piece [*a, *b] = [o, o + t_hit d] of a branch inside a dielectric whose
 * interior scatters (scatters_inside), ending where it meets the object's surface again
 * (found: a branch inside a closed object always does; an open surface gives none).
 * a.w holds the region tag (inside + 1). Returns 0 when there is none. */
int interior_piece(__global const Material *materials, const Branch *br, int found, float t_hit,
                   float4 *a, float4 *b) {
    if (br->inside < 0 || !found || !(t_hit > 0.0f) || !scatters_inside(&materials[br->inside]))
        return 0;
    *a = br->o;
    *b = br->o + t_hit * br->d;
    a->w = region_tag(br->inside);
    b->w = 0.0f;
    return 1;
}

/* Attenuation of a branch over [0, t_hit]: the medium outside objects, or the interior
 * extinction (interior_kappa: absorption and scattering) of the dielectric it is inside. */
float4 branch_attenuation(__global const Medium *medium, __global const Material *materials,
                          const Branch *br, float t_hit) {
    if (br->inside >= 0) return transmittance(interior_kappa(&materials[br->inside]), t_hit);
    if (!medium->present) return (float4)(1.0f, 1.0f, 1.0f, 0.0f);
    return transmittance(medium->kappa, medium_path_length(medium, br->o, br->d, 0.0f, t_hit));
}

#endif
