/* common.h: structs shared with the host and small maths helpers used by every kernel.
 *
 * Every struct here is mirrored by a NumPy dtype in clscatter/structs.py; the test
 * tests/test_structs.py builds a kernel that reports sizeof/offsetof and compares.
 * Only float4/int fields are used (float3 is 16 bytes in OpenCL and a trap for hosts).
 *
 * Coordinates on the device are always the *normalised* frame (the scene's bounding box
 * centred at the origin, longest side 1; see clscatter/scene/normalised.py), so fixed
 * epsilons are meaningful and float32 keeps ~1e-7 relative precision everywhere. Far
 * objects lie outside that box at large coordinates (surface_offset).
 */
#ifndef CLSCATTER_COMMON_H
#define CLSCATTER_COMMON_H

#define PI_F 3.14159265358979323846f
#define INV_4PI_F 0.07957747154594767f
#define RAY_EPS 2e-5f          /* offset along the normal when leaving a surface (normalised units) */
#define T_INF 1e30f

/* PREFETCH_HINT(p): start loading the cache line that holds *p, to be read soon. Built
 * with -DCLSCATTER_CPU_PREFETCH (clscatter/device/programs.py, device_defines: a device
 * that is a CPU alone, whose clang-based compiler lowers __builtin_prefetch to a prefetch
 * instruction; OpenCL's own prefetch() compiles to nothing on PoCL's CPU device) it is
 * one; elsewhere nothing: a GPU hides the latency with other work-items. It never changes
 * a result. */
#ifdef CLSCATTER_CPU_PREFETCH
#define PREFETCH_HINT(p) __builtin_prefetch(p)
#else
#define PREFETCH_HINT(p) ((void)0)
#endif

/* How far along the normal a ray leaving a surface at p starts: RAY_EPS, or, where p
 * lies far out (objects far from the camera keep their large normalised coordinates:
 * clscatter/scene/model.py, FAR_FACTOR), 1e-6 of its largest coordinate (~8 float32 steps
 * of it, more than the rounding of a hit point there). RAY_EPS up to |p| = 20. */
float surface_offset(float4 p) {
    return fmax(RAY_EPS, 1e-6f * fmax(fabs(p.x), fmax(fabs(p.y), fabs(p.z))));
}

/* ---- Materials ---- */
#define MAT_DIFFUSE 0
#define MAT_MIRROR 1
#define MAT_DIELECTRIC 2
#define MAT_BLACK 3

typedef struct {
    float4 color;            /* diffuse albedo, or mirror reflectance (rgb) */
    float4 interior_sigma_a; /* dielectric: absorption inside (rgb, per normalised unit) */
    float4 interior_sigma_s; /* dielectric: scattering inside (rgb, per normalised unit) */
    float ior;
    int type;
    int pad0, pad1;
} Material;

/* ---- Lights ---- */
#define LIGHT_POINT 0
#define LIGHT_SPOT 1
#define LIGHT_DIRECTIONAL 2

typedef struct {
    float4 position;   /* point and spot */
    float4 direction;  /* unit: spot axis, or the direction a directional light travels */
    float4 power;      /* rgb intensity (point, spot; W/sr) or irradiance (directional; W/m^2) */
    float cos_cutoff;  /* spot: cos of the cone half-angle; -2 for the others */
    int type;
    int pad0, pad1;
} Light;

/* ---- Medium: homogeneous, optionally bounded by an axis-aligned box ---- */
typedef struct {
    float4 sigma_s;    /* rgb, per normalised unit */
    float4 sigma_a;
    float4 kappa;      /* extinction sigma_s + sigma_a */
    float4 bmin;       /* bounds; +-T_INF when unbounded */
    float4 bmax;
    float g;           /* Henyey-Greenstein asymmetry */
    int present;       /* 0: no medium anywhere */
    int bounded;
    float t_far;       /* unbounded: path length after which min transmittance < threshold */
} Medium;

/* ---- Camera (pinhole) ---- */
typedef struct {
    float4 origin;
    float4 forward;    /* unit */
    float4 right;      /* scaled by tan(fov_x/2): dir = forward + sx*right + sy*up, sx,sy in [-1,1] */
    float4 up;         /* scaled by tan(fov_y/2) */
    int width;
    int height;
    int spp;           /* samples per pixel */
    int spp_side;      /* >0: spp == side*side, stratified grid; 0: jittered random */
    int inside;        /* material index of the closed glass the camera is inside, or -1 */
    float radiance_scale;  /* that glass's ior^2 (1 in air): radiance / n^2 is what rays carry */
    int pad0, pad1;
} Camera;

/* ---- BVH (built on the host, clscatter/accel/bvh.py), depth-first layout ----
 * Leaf (count > 0): triangles [left_first, left_first + count) of the reordered arrays.
 * Interior (count == 0): left child is this node + 1, right child is left_first. */
typedef struct {
    float bmin[3];
    int left_first;
    float bmax[3];
    int count;
} BVHNode;

/* ---- View segments: the shared product of the view-path tracer ----
 * A straight piece of a camera path lying in the medium. weight = path throughput
 * (specular bounces, dielectric absorption) * medium transmittance from the eye to a,
 * divided by the pixel's sample count, so a method's per-segment radiance estimates sum
 * directly into pixels. (sample, branch) identifies a segment independently of its
 * position in the buffer (segments are appended in no fixed order), so methods seed
 * their random numbers with it and stay deterministic. */
/* One layout for every straight path piece (64 bytes; host: structs._segment): the ends
 * a, b (xyz), an rgb value, the owner (pixel or light), the specular bounces before the
 * piece, the path's index (camera sample or lighting ray) and its branch in that path's
 * tree (0 = the primary ray). View and light segments share it under their own names.
 * The w lane of a is the piece's region: 0 in the scene medium (every piece of the shared
 * buffers), m + 1 inside dielectric material m whose interior scatters (only where a
 * tracer is built with SEGMENT_REGIONS & 2: line space gathering's own traces). */
#define SEGMENT_FIELDS(value, owner, index) \
    float4 a; float4 b; float4 value; int owner; int depth; int index; int branch;

/* weight (rgb), pixel = y * width + x, sample = pixel * spp + k */
typedef struct { SEGMENT_FIELDS(weight, pixel, sample) } ViewSegment;

/* ---- Light segments: the product of the light-path tracer (light_paths.cl) ----
 * A straight piece of a lighting ray inside the medium. flux is the rgb flux (W) the
 * ray carries at a (emitted flux per ray, times specular weights and attenuation up to
 * a); along the segment it decays as exp(-kappa s). */
/* flux (rgb), light = index of the emitting light, ray = lighting ray index within it */
typedef struct { SEGMENT_FIELDS(flux, light, ray) } LightSegment;

/* ---- Ray pieces: lighting rays that END (light_paths.cl built with -DRAY_PIECES) ----
 * The last straight piece of a lighting branch outside every object: it ends on a
 * diffuse or black surface, or where it leaves the scene's bounding box. flux is the rgb
 * flux arriving at b (specular weights and attenuation included). The surface-caustic
 * methods (ray map, photon map) are built from them. */
#define PIECE_DIFFUSE 0
#define PIECE_BLACK 1
#define PIECE_ESCAPED 2
typedef struct {
    float4 a;          /* start (the light, or the last specular hit) */
    float4 b;          /* end */
    float4 flux;       /* rgb flux arriving at b */
    int light;         /* emitting light */
    int depth;         /* specular bounces before this piece */
    int ray;           /* lighting ray index within its light */
    int branch;        /* branch of that ray's path tree */
    int end;           /* PIECE_DIFFUSE, PIECE_BLACK or PIECE_ESCAPED */
    int pad0, pad1, pad2;
} RayPiece;

/* ---- Diffuse hits of view paths (view_paths.cl, trace_diffuse_hits) ----
 * Where a camera path meets a diffuse surface: radiance leaving towards the camera is
 * weight * E for any irradiance E arriving there (weight = path throughput * albedo / pi,
 * already divided by the pixel's sample count). */
typedef struct {
    float4 p;          /* hit point */
    float4 n;          /* shading normal, turned towards the viewer */
    float4 g;          /* geometric normal, turned towards the viewer (shadow rays leave along it) */
    float4 weight;     /* rgb */
    int pixel;         /* y * width + x */
    int sample;        /* camera sample index */
    int depth;         /* specular bounces before the hit */
    int branch;        /* branch of that sample's path tree */
} DiffuseHit;

/* ---- Small helpers ---- */
float4 vec3(float x, float y, float z) { return (float4)(x, y, z, 0.0f); }
float dot3(float4 a, float4 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
float4 cross3(float4 a, float4 b) {
    return (float4)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x, 0.0f);
}
float length3(float4 a) { return sqrt(dot3(a, a)); }
float4 normalize3(float4 a) {
    float l = length3(a);
    return l > 0.0f ? a / l : (float4)(0.0f);
}
/* atan2 for hot kernels: the builtin is a slow scalar routine on some drivers (PoCL's
 * CPU device: 26.4 ns per work-item against 8.6 for this one and 4.9 for exp,
 * tools/bench_epipolar_costs.py, docs/bench/epipolar_costs.json). Reduced to
 * a = min/max in [0, 1], then to |z| <= tan(pi/8), then Cephes' atanf polynomial (relative error ~2e-7); measured
 * within 4e-7 rad of float64 atan2 over all quadrants (tests/test_fast_math.py).
 * NaN in gives NaN; both arguments infinite is not handled (no caller passes it). */
float atan2_fast(float y, float x) {
    float ax = fabs(x), ay = fabs(y);
    float mx = fmax(ax, ay), mn = fmin(ax, ay);
    float a = mx > 0.0f ? mn / mx : 0.0f;
    int big = a > 0.41421356237f;
    float z = big ? (a - 1.0f) / (a + 1.0f) : a;
    float z2 = z * z;
    float r = (((8.05374449538e-2f * z2 - 1.38776856032e-1f) * z2 + 1.99777106478e-1f) * z2
               - 3.33329491539e-1f) * z2 * z + z;
    if (big) r += 0.78539816339744831f;
    if (ay > ax) r = 1.57079632679489662f - r;
    if (x < 0.0f) r = 3.14159265358979324f - r;
    return isnan(x + y) ? x + y : copysign(r, y);
}

/* sin(x), with cos(x) in *c, for hot kernels (the builtins are slow scalar routines on
 * some drivers, as atan2 is: sin + cos 32.1 ns per work-item on PoCL's CPU device
 * against 3.9 for this, tools/bench_epipolar_costs.py): x reduced by multiples of pi/2
 * with a three-part pi/2 (Cody & Waite), then Cephes' sinf/cosf polynomials on |r| <= pi/4 and the quadrant's
 * swap. Within 2e-7 of float64 for |x| <= 1e3 (tests/test_fast_math.py; the epipolar
 * kernels pass light-ray angles within +-pi); NaN and inf give NaN; sin(-0) is +0. */
float sincos_fast(float x, float *c) {
    float j = rint(x * 0.63661977236758134f);            /* 2 / pi */
    float r = ((x - j * 1.5703125f) - j * 4.837512969970703125e-4f)
              - j * 7.54978995489188216e-8f;              /* pi/2 in three parts */
    float z = r * r;
    float sr = ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f) * z * r + r;
    float cr = ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z
                + 4.166664568298827e-2f) * z * z - 0.5f * z + 1.0f;
    int q = ((int)j) & 3;
    float s = (q & 1) ? cr : sr;
    float co = (q & 1) ? sr : cr;
    if (q == 1 || q == 2) co = -co;
    if (q >= 2) s = -s;
    *c = co;
    return s;
}

float4 exp3(float4 a) { return (float4)(exp(a.x), exp(a.y), exp(a.z), 0.0f); }

/* Transmittance exp(-kappa * t) for rgb kappa. */
float4 transmittance(float4 kappa, float t) { return exp3(-kappa * t); }

/* Henyey-Greenstein phase function, normalised over the sphere; cos_theta is between
 * the light's travel direction and the direction towards the camera. */
float hg_phase(float cos_theta, float g) {
    float denom = 1.0f + g * g - 2.0f * g * cos_theta;
    return INV_4PI_F * (1.0f - g * g) / (denom * sqrt(denom));
}

/* Ray/box slab test: [t0, t1] of the ray inside the box, clamped to [tmin, tmax].
 * Returns 0 when the intersection is empty. inv_d may hold +-inf. */
int ray_box(float4 o, float4 inv_d, float4 bmin, float4 bmax, float tmin, float tmax,
                   float *t0, float *t1) {
    float4 ta = (bmin - o) * inv_d;
    float4 tb = (bmax - o) * inv_d;
    float4 lo = fmin(ta, tb), hi = fmax(ta, tb);
    /* NaN (0 * inf when o lies on a slab plane) is dropped by fmin/fmax */
    float a = fmax(fmax(lo.x, lo.y), fmax(lo.z, tmin));
    float b = fmin(fmin(hi.x, hi.y), fmin(hi.z, tmax));
    *t0 = a;
    *t1 = b;
    return a <= b;
}

float4 safe_inv_dir(float4 d) {
    return (float4)(1.0f / d.x, 1.0f / d.y, 1.0f / d.z, 0.0f);
}

/* Medium interval along a ray: the part of [tmin, tmax] inside the medium bounds. */
int medium_interval(__global const Medium *m, float4 o, float4 d, float tmin, float tmax,
                           float *t0, float *t1) {
    if (!m->present) return 0;
    if (!m->bounded) { *t0 = tmin; *t1 = fmin(tmax, tmin + m->t_far); return *t0 < *t1; }
    return ray_box(o, safe_inv_dir(d), m->bmin, m->bmax, tmin, tmax, t0, t1);
}

/* Length of [tmin, tmax] along a ray that lies inside the medium (no t_far cut: this is
 * for transmittance, e.g. a light path or the rest of a view segment). */
float medium_path_length(__global const Medium *m, float4 o, float4 d, float tmin, float tmax) {
    if (!m->present) return 0.0f;
    if (!m->bounded) return fmax(tmax - tmin, 0.0f);
    float t0, t1;
    if (!ray_box(o, safe_inv_dir(d), m->bmin, m->bmax, tmin, tmax, &t0, &t1)) return 0.0f;
    return t1 - t0;
}

/* ---- Random numbers: PCG hash, stateless per (pixel, sample, dimension) ---- */
uint pcg_hash(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}
typedef struct { uint s; } Rng;
Rng rng_seed(uint a, uint b, uint c) {
    Rng r; r.s = pcg_hash(a ^ pcg_hash(b ^ pcg_hash(c))); return r;
}
float rng_next(Rng *r) {
    r->s = pcg_hash(r->s);
    return (float)(r->s >> 8) * (1.0f / 16777216.0f);
}

#endif
