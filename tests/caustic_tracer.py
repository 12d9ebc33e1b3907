"""An independent NumPy light tracer for the volumetric caustic of a glass sphere.

A point light (intensity I, W/sr) shines on a smooth dielectric sphere (centre c, radius r,
index n) in a homogeneous medium (sigma_s, sigma_a, Henyey-Greenstein g) that fills an
axis-aligned box. Everything here is written from the physics, sharing no code with
clscatter (nothing is imported from it): exact ray-sphere intersections, Snell's law and
the unpolarised Fresnel reflectance (the mean of the s and p reflectances) at both
interfaces, exp(-kappa s) along every straight piece inside the medium box (and
exp(-kappa_interior s) inside the glass), and internal reflections, split
deterministically: at every interface a photon's power is divided between the reflected
and the refracted branch, so no Russian roulette noise enters.

The result is a list of *beams*: straight rays in the medium, each with the power it
carries at its start (after the light-to-glass path, the glass interfaces and the interior),
its direction and its length up to the box's wall. From them:

- ``flux_through_disc``: the power that crosses a disc of a horizontal plane (beam by beam,
  attenuated up to the plane);
- ``radiance_image``: the single-scattered radiance each pixel of a pinhole camera sees,
  from the identity that fluence integrates over a volume to power x length: for a beam of
  power Phi(s) = Phi_0 exp(-kappa s),

      integral over the pixel's image-plane area of L  =  sum over beams of
      integral ds  Phi(s) sigma_s p(cos theta) exp(-kappa t_medium) / (t^2 J),

  t the distance from the camera to the beam's point x(s), t_medium the part of it inside
  the medium box, theta the angle between the beam's direction and the direction from x to
  the camera, and J = d(solid angle)/d(image-plane area) = tan_x tan_y cos^3(gamma) (gamma:
  the angle between the view ray and the camera's axis). The pixel's value is that
  integral divided by the pixel's image-plane area (the box filter of docs/scene_format.md).
  The integral along each beam is sampled at stratified jittered points, so the estimate
  is unbiased (no density estimation, no blur); its only noise is the photons' and the
  points'.

View rays are taken as straight lines from the camera: only pixels whose view rays miss
the sphere (``pixels_missing_sphere``) may be compared. The medium inside the glass is
none (a dielectric's interior is clear unless its interior coefficients are given: only
absorption inside is modelled here, and nothing scatters there).

The camera model is that of docs/scene_format.md: fov along x (or y), square pixels,
image row 0 at the top.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


# ---- scene description --------------------------------------------------------------------
@dataclass
class Sphere:
    center: np.ndarray
    radius: float
    ior: float
    interior_sigma_a: np.ndarray = None     # rgb, per scene unit; None: clear

    def __post_init__(self):
        self.center = np.asarray(self.center, float)
        self.interior_sigma_a = (np.zeros(3) if self.interior_sigma_a is None
                                 else np.broadcast_to(np.asarray(self.interior_sigma_a, float),
                                                      (3,)).copy())


@dataclass
class Medium:
    sigma_s: np.ndarray
    sigma_a: np.ndarray
    g: float
    box_min: np.ndarray
    box_max: np.ndarray

    def __post_init__(self):
        self.sigma_s = np.broadcast_to(np.asarray(self.sigma_s, float), (3,)).copy()
        self.sigma_a = np.broadcast_to(np.asarray(self.sigma_a, float), (3,)).copy()
        self.box_min = np.asarray(self.box_min, float)
        self.box_max = np.asarray(self.box_max, float)

    @property
    def kappa(self) -> np.ndarray:
        return self.sigma_s + self.sigma_a


@dataclass
class Camera:
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float
    width: int
    height: int
    fov_axis: str = "x"

    def __post_init__(self):
        self.origin = np.asarray(self.origin, float)
        fwd = np.asarray(self.target, float) - self.origin
        self.forward = fwd / np.linalg.norm(fwd)
        right = np.cross(self.forward, np.asarray(self.up, float))
        self.right = right / np.linalg.norm(right)
        self.upv = np.cross(self.right, self.forward)
        half = np.tan(np.radians(self.fov) / 2)
        aspect = self.width / self.height
        self.tan_x, self.tan_y = ((half, half / aspect) if self.fov_axis == "x"
                                  else (half * aspect, half))

    def pixel_rays(self, u: float = 0.5, v: float = 0.5) -> np.ndarray:
        """(H, W, 3) unit directions through the point (u, v) of every pixel."""
        px = (np.arange(self.width) + u) / self.width * 2 - 1
        py = 1 - (np.arange(self.height) + v) / self.height * 2
        d = (self.forward[None, None] + px[None, :, None] * self.tan_x * self.right
             + py[:, None, None] * self.tan_y * self.upv)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, p) -> tuple[float, float] | None:
        """(column, row) in pixels of world point ``p`` (None behind the camera): the
        inverse of :meth:`pixel_rays`."""
        q = np.asarray(p, float) - self.origin
        depth = q @ self.forward
        if depth <= 0:
            return None
        u = (q @ self.right) / depth / self.tan_x
        v = (q @ self.upv) / depth / self.tan_y
        return (u + 1) / 2 * self.width, (1 - v) / 2 * self.height


@dataclass
class Beams:
    origin: np.ndarray      # (M, 3)
    direction: np.ndarray   # (M, 3) unit
    power: np.ndarray       # (M, 3) W at the origin
    length: np.ndarray      # (M,) to the medium box's wall (the end of the light path)
    depth: np.ndarray       # (M,) specular events before the beam: 1 = reflected at entry
    photon: np.ndarray      # (M,) index of the photon (for grouping into batches)

    def select(self, mask: np.ndarray) -> Beams:
        return Beams(*(getattr(self, f)[mask] for f in
                       ("origin", "direction", "power", "length", "depth", "photon")))


# ---- geometry and optics ------------------------------------------------------------------
def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def ray_sphere(o, d, c, r):
    """Distances (t_near, t_far) along unit d from o to the sphere; NaN where it misses."""
    oc = o - c
    b = _dot(oc, d)
    disc = b * b - (_dot(oc, oc) - r * r)
    with np.errstate(invalid="ignore"):
        s = np.sqrt(disc)
    s = np.where(disc >= 0, s, np.nan)
    return -b - s, -b + s


def ray_box(o, d, lo, hi):
    """Slab test: (t_enter, t_exit) of the line o + t d with the box (t_enter may be < 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
    tmin = np.nanmax(np.minimum(t0, t1), axis=-1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=-1)
    return tmin, tmax


def fresnel_unpolarised(cos_i, n1, n2):
    """Reflectance of a smooth interface from index n1 into n2 (1 under total internal
    reflection), and the cosine of the refracted direction."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (n1 / n2) ** 2 * (1.0 - cos_i ** 2)
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
        rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    R = 0.5 * (rs * rs + rp * rp)
    R = np.where(tir, 1.0, np.nan_to_num(R, nan=1.0))
    return R, cos_t, tir


def reflect(d, n):
    return d - 2.0 * _dot(d, n)[:, None] * n


def refract(d, n, n1, n2, cos_t):
    """Snell's law in vector form: d unit incident, n unit normal against d (d.n < 0)."""
    eta = n1 / n2
    cos_i = -_dot(d, n)
    t = eta * d + (eta * cos_i - cos_t)[:, None] * n
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def hg(cos_theta, g):
    """Henyey-Greenstein phase function, normalised over the sphere (isotropic: 1/4pi)."""
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos_theta) ** 1.5)


def _box_length(o, d, t_a, t_b, lo, hi):
    """Length of the part of the segment o + t d, t in [t_a, t_b], inside the box."""
    t0, t1 = ray_box(o, d, lo, hi)
    return np.clip(np.minimum(t1, t_b) - np.maximum(t0, t_a), 0.0, None)


# ---- a scene dict, read ------------------------------------------------------------------
def from_scene_dict(d: dict):
    """The tracer's description of a scene dict in the TOML schema (plain numbers read from
    the dict; object 1 is the glass sphere, the one light a point or a spot aimed at its
    centre): (sphere, medium, camera, light position, intensity, spot half-angle in
    radians or None). No medium: clear air around everything."""
    ball = d["objects"][1]
    glass = d["materials"][ball["material"]]
    assert glass["type"] == "dielectric" and "interior_sigma_s" not in glass
    sphere = Sphere(ball["center"], ball["radius"], glass["ior"],
                       glass.get("interior_sigma_a"))
    m = d.get("medium")
    if m is None:                    # clear air: beams go on to the surfaces
        medium = Medium(0.0, 0.0, 0.0, [-1e3] * 3, [1e3] * 3)
    else:
        medium = Medium(m["sigma_s"], m["sigma_a"], m["g"], m["bounds"]["min"],
                           m["bounds"]["max"])
        floor = d["objects"][0]      # the floor is the box's bottom face: beams end there
        assert floor["origin"][1] == m["bounds"]["min"][1] and floor["edge_u"][1] == 0.0
    c = d["camera"]
    cam = Camera(c["origin"], c["target"], c["up"], c["fov"], *c["resolution"],
                    fov_axis=c.get("fov_axis", "x"))
    (light,) = d["lights"]
    assert light["type"] in ("point", "spot")
    half = None
    if light["type"] == "spot":       # aimed at the centre, its cone within the ball
        assert list(light["target"]) == list(ball["center"])
        half = math.radians(light["cutoff_angle"])
    return sphere, medium, cam, light["position"], light["intensity"], half



# ---- the light tracer ---------------------------------------------------------------------
def cone_directions(light_pos, sphere: Sphere, n: int, rng,
                    half_angle: float | None = None) -> tuple[np.ndarray, float]:
    """n directions uniform (stratified in cos and azimuth) over the cone from the light
    towards the sphere's centre, of ``half_angle`` (radians; default: the cone the sphere
    subtends, which it must not exceed), and the cone's solid angle."""
    axis = sphere.center - light_pos
    dist = np.linalg.norm(axis)
    axis /= dist
    cos_max = np.sqrt(1 - (sphere.radius / dist) ** 2)
    if half_angle is not None:
        assert np.cos(half_angle) >= cos_max, "the cone must lie within the sphere"
        cos_max = np.cos(half_angle)
    # stratified: a sqrt(n) x sqrt(n) grid of (cos, phi) cells, jittered
    k = int(np.ceil(np.sqrt(n)))
    i, j = np.divmod(np.arange(k * k), k)
    u1 = (i + rng.random(k * k)) / k
    u2 = (j + rng.random(k * k)) / k
    cos_t = 1 - u1 * (1 - cos_max)
    sin_t = np.sqrt(np.clip(1 - cos_t ** 2, 0, None))
    phi = 2 * np.pi * u2
    a = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(axis, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    d = (cos_t[:, None] * axis + (sin_t * np.cos(phi))[:, None] * e1
         + (sin_t * np.sin(phi))[:, None] * e2)
    return d, 2 * np.pi * (1 - cos_max)


def trace(light_pos, intensity, sphere: Sphere, medium: Medium, n_photons: int, seed: int,
          max_internal: int = 8, half_angle: float | None = None,
          fresnel: bool = True) -> Beams:
    """Trace ``n_photons`` photons from a point light of ``intensity`` (rgb W/sr) to the
    sphere and through it: the beam reflected at the entry and one beam leaving after each
    of up to ``max_internal`` internal reflections (beyond, the power left is dropped: it
    is below F^max_internal of the entering power). ``half_angle`` (radians): a spot
    light aimed at the sphere's centre whose hard-edged cone lies within the sphere.
    ``fresnel=False``: nothing is reflected (Snell's directions, all the power refracted),
    the physics of a glass ball whose index rises continuously, as when voxelised."""
    rng = np.random.default_rng(seed)
    light_pos = np.asarray(light_pos, float)
    inten = np.broadcast_to(np.asarray(intensity, float), (3,))
    d, omega = cone_directions(light_pos, sphere, n_photons, rng, half_angle)
    n = len(d)
    o = np.broadcast_to(light_pos, d.shape).copy()
    photon = np.arange(n)
    t_in, _ = ray_sphere(o, d, sphere.center, sphere.radius)
    hit = np.isfinite(t_in) & (t_in > 0)
    o, d, photon, t_in = o[hit], d[hit], photon[hit], t_in[hit]
    kappa = medium.kappa
    lo, hi = medium.box_min, medium.box_max
    # power carried by each photon, attenuated on its way to the glass
    tau = _box_length(o, d, 0.0, t_in, lo, hi)[:, None] * kappa
    w = inten * (omega / n) * np.exp(-tau)
    x = o + t_in[:, None] * d
    nrm = (x - sphere.center) / sphere.radius
    cos_i = -_dot(d, nrm)
    R, cos_t, _ = fresnel_unpolarised(cos_i, 1.0, sphere.ior)
    if not fresnel:
        R = np.zeros_like(R)
    out = [(x, reflect(d, nrm), R[:, None] * w, np.full(len(x), 1), photon)]
    d = refract(d, nrm, 1.0, sphere.ior, cos_t)
    w = (1 - R)[:, None] * w
    for k in range(max_internal + 1):
        # from a point on the sphere, inwards: the chord is -2 (x - c).d
        chord = np.clip(-2.0 * _dot(x - sphere.center, d), 0.0, None)
        w = w * np.exp(-chord[:, None] * sphere.interior_sigma_a)
        x = x + chord[:, None] * d
        nrm = x - sphere.center
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)    # outward: d.nrm > 0
        x = sphere.center + sphere.radius * nrm              # no drift off the surface
        R, cos_t, tir = fresnel_unpolarised(_dot(d, nrm), sphere.ior, 1.0)
        if not fresnel:
            R = tir.astype(float)
        out.append((x, refract(d, -nrm, sphere.ior, 1.0, cos_t), (1 - R)[:, None] * w,
                    np.full(len(x), k + 2), photon))
        d = reflect(d, nrm)
        w = R[:, None] * w
    origin, direction, power, depth, ph = (np.concatenate(a) for a in zip(*out))
    # beams below 1e-9 of a photon's power carry nothing measurable: dropped
    keep = power.max(axis=1) > 1e-9 * inten.max() * omega / n
    origin, direction, power, depth, ph = (a[keep] for a in (origin, direction, power, depth, ph))
    # the wall of the medium box ends every beam (nothing is outside it)
    _, t_exit = ray_box(origin, direction, lo, hi)
    return Beams(origin, direction, power, np.clip(t_exit, 0.0, None), depth, ph)


# ---- what the beams deliver ---------------------------------------------------------------
def flux_through_disc(beams: Beams, medium: Medium, plane_y: float, center_xz, radius: float):
    """Power (rgb) that crosses the disc {y = plane_y, |(x, z) - center_xz| < radius}, each
    beam attenuated by the medium up to the plane (beams end at the box's wall)."""
    dy = beams.direction[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane_y - beams.origin[:, 1]) / dy
    ok = np.isfinite(t) & (t > 0) & (t <= beams.length * (1 + 1e-9))
    p = beams.origin + np.where(ok, t, 0)[:, None] * beams.direction
    rho = np.hypot(p[:, 0] - center_xz[0], p[:, 2] - center_xz[1])
    ok &= rho < radius
    tau = _box_length(beams.origin, beams.direction, 0.0, np.where(ok, t, 0.0),
                      medium.box_min, medium.box_max)[:, None] * medium.kappa
    return (beams.power * np.exp(-tau) * ok[:, None]).sum(axis=0)


def radiance_image(beams: Beams, medium: Medium, cam: Camera, samples: int = 16,
                   seed: int = 0, chunk: int = 1 << 21) -> np.ndarray:
    """(H, W, 3) single-scattered radiance (box-filtered pixel means) of the beams' light as
    the camera sees it, with ``samples`` stratified jittered points per beam."""
    rng = np.random.default_rng(seed)
    W, H = cam.width, cam.height
    acc = np.zeros((3, W * H))
    kappa, sigma_s = medium.kappa, medium.sigma_s
    pix_area = (2.0 / W) * (2.0 / H)            # in the image plane's [-1, 1]^2 units
    per = max(1, chunk // samples)
    for a in range(0, len(beams.power), per):
        b = slice(a, a + per)
        o, d, L, P = beams.origin[b], beams.direction[b], beams.length[b], beams.power[b]
        m = len(L)
        u = (np.arange(samples)[None, :] + rng.random((m, samples))) / samples
        s = (u * L[:, None]).ravel()
        idx = np.repeat(np.arange(m), samples)
        x = o[idx] + s[:, None] * d[idx]
        v = x - cam.origin
        z = v @ cam.forward
        t = np.linalg.norm(v, axis=1)
        front = z > 1e-9
        fx = np.where(front, (v @ cam.right) / np.where(front, z, 1) / cam.tan_x, 9.0)
        fy = np.where(front, (v @ cam.upv) / np.where(front, z, 1) / cam.tan_y, 9.0)
        px = np.floor((fx + 1) / 2 * W).astype(np.int64)
        py = np.floor((1 - fy) / 2 * H).astype(np.int64)
        inside = front & (px >= 0) & (px < W) & (py >= 0) & (py < H)
        vu = v / t[:, None]
        t_enter, _ = ray_box(np.broadcast_to(cam.origin, v.shape), vu, medium.box_min,
                             medium.box_max)
        t_med = np.clip(t - np.clip(t_enter, 0, None), 0, None)
        cos_theta = -_dot(d[idx], vu)            # light's travel vs towards the camera
        cos_g = z / t
        J = cam.tan_x * cam.tan_y * cos_g ** 3
        geo = hg(cos_theta, medium.g) * (L[idx] / samples) / (t * t * J * pix_area)
        w = (P[idx] * sigma_s * np.exp(-np.outer(s, kappa) - np.outer(t_med, kappa))
             * geo[:, None])
        pix = (py * W + px)[inside]
        for c in range(3):
            acc[c] += np.bincount(pix, weights=w[inside, c], minlength=W * H)
    return acc.T.reshape(H, W, 3)


def pixels_missing_sphere(cam: Camera, sphere: Sphere, margin_px: float = 1.5) -> np.ndarray:
    """(H, W) bool: pixels whose whole footprint (grown by ``margin_px`` pixels) sees past the
    sphere, so their view rays are straight lines through the medium."""
    d = cam.pixel_rays()
    oc = sphere.center - cam.origin
    tc = d @ oc
    miss_dist = np.linalg.norm(oc[None, None] - tc[..., None] * d, axis=-1)
    pix_angle = 2 * max(cam.tan_x / cam.width, cam.tan_y / cam.height)   # > one pixel
    room = sphere.radius + margin_px * pix_angle * np.linalg.norm(oc)
    return (miss_dist > room) | (tc < -sphere.radius)


# ---- a closed form for an axial light ---------------------------------------------------
def axial_exit_rays(light_height: float, radius: float, ior: float, alpha: np.ndarray,
                    k: int):
    """For a light on the sphere's axis at ``light_height`` above its centre, the photon
    leaving at polar angle ``alpha`` from the downward axis exits after ``k`` internal
    reflections (k = -1: reflected at the entry) from the point (rho, y) relative to the
    centre, with the unit direction (d_rho, d_y), in the half-plane of its azimuth; the
    fraction of its power that leaves there; and the path length in the glass. Written
    from the planar geometry (Descartes' rainbow construction): each chord subtends pi - 2
    theta_t at the centre, deviation 2 (theta_i - theta_t) + k (pi - 2 theta_t)."""
    b = light_height * np.sin(alpha)                      # impact parameter
    th_i = np.arcsin(np.clip(b / radius, -1, 1))
    th_t = np.arcsin(np.sin(th_i) / ior)
    # entry point: polar angle from the upward axis, on the side of the photon's azimuth
    t_in = light_height * np.cos(alpha) - np.sqrt(radius ** 2 - b ** 2)
    ey = light_height - t_in * np.cos(alpha)
    erho = t_in * np.sin(alpha)
    ang = np.arctan2(erho, ey)                            # from +y towards +rho
    cos_i, cos_t = np.cos(th_i), np.cos(th_t)
    rs = (cos_i - ior * cos_t) / (cos_i + ior * cos_t)
    rp = (ior * cos_i - cos_t) / (ior * cos_i + cos_t)
    F = 0.5 * (rs ** 2 + rp ** 2)
    inc = np.array([np.sin(alpha), -np.cos(alpha)])       # (rho, y) direction of travel
    if k < 0:
        # mirror the incoming direction in the normal at the entry point
        nrm = np.array([np.sin(ang), np.cos(ang)])
        dn = inc[0] * nrm[0] + inc[1] * nrm[1]
        dr = inc - 2 * dn * nrm
        return radius * np.sin(ang), radius * np.cos(ang), dr[0], dr[1], F, 0.0
    # angles measured clockwise (from +y towards +rho, with rho to the right and y up):
    # every chord moves the point on to ang + (pi - 2 th_t), and every interface turns the
    # direction of travel clockwise, by th_i - th_t at each refraction and pi - 2 th_t at
    # each internal reflection
    ex_ang = ang + (k + 1) * (np.pi - 2 * th_t)
    dev = 2 * (th_i - th_t) + k * (np.pi - 2 * th_t)
    c, s = np.cos(dev), np.sin(dev)
    dr = np.array([c * inc[0] + s * inc[1], -s * inc[0] + c * inc[1]])
    frac = (1 - F) ** 2 * F ** k
    return (radius * np.sin(ex_ang), radius * np.cos(ex_ang), dr[0], dr[1], frac,
            (k + 1) * 2 * radius * cos_t)


# ---- surface irradiance: what diffuse surfaces show of the beams ------------------------
def _first_surface(o, d, floor_y, floor_half, boxes):
    """Where beams o + t d first meet a diffuse receiver: the floor quad {y = floor_y,
    |x|, |z| <= floor_half} or a box of ``boxes`` [(lo, hi)]; (t (inf: none), unit
    normal facing the beam)."""
    m = len(o)
    t_best = np.full(m, np.inf)
    nrm = np.zeros((m, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (floor_y - o[:, 1]) / d[:, 1]
    p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
    ok = (t > 1e-9) & (np.abs(p[:, 0]) <= floor_half) & (np.abs(p[:, 2]) <= floor_half)
    t_best[ok] = t[ok]
    nrm[ok] = [0.0, 1.0, 0.0]
    for lo, hi in boxes:
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        t0, t1 = ray_box(o, d, lo, hi)
        ok = (t0 > 1e-9) & (t0 <= t1) & (t0 < t_best)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d[ok]
            near = np.minimum((lo - o[ok]) * inv, (hi - o[ok]) * inv)
        axis = np.argmax(np.nan_to_num(near, nan=-np.inf), axis=1)
        face = np.zeros((ok.sum(), 3))
        face[np.arange(len(axis)), axis] = -np.sign(d[ok][np.arange(len(axis)), axis])
        t_best[ok] = t0[ok]
        nrm[ok] = face
    return t_best, nrm


def _blocked(x, cam_origin, sphere: Sphere, boxes):
    """Whether the straight line from points x to the camera is blocked by the sphere or
    a box (x lifted off its surface by a hair first)."""
    v = cam_origin - x
    dist = np.linalg.norm(v, axis=1)
    u = v / dist[:, None]
    x = x + 1e-7 * u
    t0, t1 = ray_sphere(x, u, sphere.center, sphere.radius)
    hit = np.isfinite(t0) & (t1 > 0) & (t0 < dist)
    for lo, hi in boxes:
        b0, b1 = ray_box(x, u, np.asarray(lo, float), np.asarray(hi, float))
        hit |= (b0 <= b1) & (b1 > 1e-6) & (b0 < dist)
    return hit


def surface_image(beams: Beams, cam: Camera, sphere: Sphere, albedo: float,
                  floor_y: float = 0.0, floor_half: float = 2.5, boxes=(),
                  chunk: int = 1 << 20) -> np.ndarray:
    """(H, W, 3) radiance (box-filtered pixel means) of diffuse surfaces (albedo
    ``albedo``: the floor quad and ``boxes``) lit by the beams, no medium. Each beam ends
    where it first meets a receiver; its power Phi lands at x, and a surface seen
    directly (nothing between x and the camera) shows the pixel it projects to

        integral over the pixel's image-plane area of L  =  sum of
        albedo / pi  Phi  cos(theta_s) / (t^2 J),

    (L = albedo / pi  E, E dA = dPhi; theta_s between the normal and the direction to the
    camera, t the distance, J as in :func:`radiance_image`), divided by the pixel's
    area. No density estimation: no blur, no boundary bias; its only noise is the
    photons'. Pixels that see the floor through the sphere get nothing (compare where
    :func:`pixels_missing_sphere`)."""
    W, H = cam.width, cam.height
    acc = np.zeros((3, W * H))
    pix_area = (2.0 / W) * (2.0 / H)
    for a in range(0, len(beams.power), chunk):
        b = slice(a, a + chunk)
        o, d, P = beams.origin[b], beams.direction[b], beams.power[b]
        t, nrm = _first_surface(o, d, floor_y, floor_half, boxes)
        ok = np.isfinite(t)
        x, nrm, P = o[ok] + t[ok, None] * d[ok], nrm[ok], P[ok]
        v = cam.origin - x
        dist = np.linalg.norm(v, axis=1)
        cos_s = _dot(nrm, v) / dist
        z = -(v @ cam.forward)
        seen = (cos_s > 0) & (z > 1e-9) & ~_blocked(x, cam.origin, sphere, boxes)
        x, P, cos_s, z, dist = x[seen], P[seen], cos_s[seen], z[seen], dist[seen]
        q = x - cam.origin
        fx = (q @ cam.right) / z / cam.tan_x
        fy = (q @ cam.upv) / z / cam.tan_y
        px = np.floor((fx + 1) / 2 * W).astype(np.int64)
        py = np.floor((1 - fy) / 2 * H).astype(np.int64)
        inside = (px >= 0) & (px < W) & (py >= 0) & (py < H)
        J = cam.tan_x * cam.tan_y * (z / dist) ** 3
        w = P * (albedo / np.pi * cos_s / (dist * dist * J * pix_area))[:, None]
        pix = (py * W + px)[inside]
        for c in range(3):
            acc[c] += np.bincount(pix, weights=w[inside, c], minlength=W * H)
    return acc.T.reshape(H, W, 3)
