"""An independent NumPy reference for single scattering inside a refracting glass ball.

A sphere (centre c, radius R, index n) holds a homogeneous medium (sigma_s, sigma_a,
Henyey-Greenstein g); around it is clear air of index 1 with no medium. A point light of
intensity I (W/sr) outside lights it; the pinhole camera of docs/scene_format.md (fov
across x or y, square pixels, row 0 at the top, box filter) looks at it. Written from the
physics, sharing no code with clscatter (nothing is imported from it; the camera, ray-sphere,
Fresnel and phase helpers are those of the independent caustic tracer beside it).

Modelling choices, all of them:

- **Exact sphere**, Snell's law, unpolarised Fresnel (the mean of the s and p
  reflectances) at every interface; floats are float64.
- **View side.** Each camera ray refracts into the ball with transmittance 1 - F and
  crosses it on a chord of length 2 R cos theta_t. Light scattered towards the camera at
  depth t along it is attenuated back to the entry point by exp(-kappa t), kappa =
  sigma_s + sigma_a. Leaving glass of index n into air divides radiance by n^2 (radiance /
  n^2 is invariant along a ray across an interface); the same point carries the
  transmittance 1 - F (Fresnel is the same in both directions). With ``reflections``, the
  view ray's first internal reflection at the far end of its chord is followed too: a
  second chord of the same length (a chord of a sphere meets the surface at the same angle
  at both ends), weighted by the internal Fresnel reflectance and exp(-kappa chord).
- **Light side.** By the axial symmetry of a sphere and a point light, every light path to
  an interior point x lies in the meridional plane through the light, the centre and x. In
  that plane the light's rays are parametrised by the angle beta of their entry point about
  the centre (up to the grazing entry, cos beta = R / D, D the light's distance from the
  centre; everything is smooth in beta) and have the polar angle alpha(beta) at the light.
  Each refracts into the ball (family 0, its first chord) and, with ``reflections``,
  reflects once at the far surface (family 1, its second chord). The rays of a family that
  pass through x are the roots of the signed distance f(beta) of x from the ray, found by a
  scan of ``rays`` rays and linear interpolation within each bracket of a sign change: the
  refracted rays cross near the far side (spherical aberration: a caustic whose fold is
  the edge of the lit region), the reflected ones more so, and cross the axis (a focal
  line), so a point may be reached by none, one or several. The irradiance each path
  delivers is that of its ray tube: the tube's solid angle at the light,
  |sin alpha| d alpha d psi (psi the turn about the axis), over its cross-section at x,
  |df| times rho d psi (rho the distance of x from the axis), times the power left:
  E = I T |sin alpha| |d alpha| / (|df| rho) with the bracket's differences, T the Fresnel
  transmittance at entry (times the internal reflectance for family 1) times exp(-kappa s),
  s the path length inside up to x.
- **Along a chord**, each family is integrated over the pieces of the chord it lights,
  cut where the number of its paths through the point changes (a shadow's edge, a
  caustic's fold, where E has a 1/sqrt singularity): found between equally spaced points,
  then by bisection. Each piece gets the midpoint rule in v on t = t0 + (t1 - t0)(1 -
  cos(pi v)) / 2, whose dt vanishes like sqrt at both ends (:func:`chord_light`).
- **Scattering**: sigma_s p(cos) E, the phase angle between the direction the light
  travels at x and the direction towards the camera there (the reversed view ray inside
  the glass), as docs/scene_format.md defines it.
- **Neglected**: with ``reflections = False`` every internal reflection (of view and of
  light paths); with ``reflections = True`` the second and later ones (products of two
  reflectances: a few tenths of a percent where kappa R ~ 1). Light reflected off the
  outside of the ball never enters it and does not count; nothing outside scatters.

A pixel is the mean over ``sub`` x ``sub`` points of it (midpoints of a regular grid: the
box filter). :func:`interior_image` also returns, per pixel, the least cosine of incidence
of its view rays on the sphere (0 where one misses): pixels near the rim have small ones.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from caustic_tracer import Camera, fresnel_unpolarised, hg, ray_sphere


@dataclass
class GlassBall:
    """The ball: centre, radius, index, and its medium (grey sigma_s, sigma_a, HG g)."""

    center: np.ndarray
    radius: float
    ior: float
    sigma_s: float
    sigma_a: float
    g: float

    def __post_init__(self):
        self.center = np.asarray(self.center, float)

    @property
    def kappa(self) -> float:
        return self.sigma_s + self.sigma_a


def _reflect_2d(dz, dr, nz, nr):
    """(dz, dr) mirrored about the unit normal (nz, nr)."""
    dn = dz * nz + dr * nr
    return dz - 2 * dn * nz, dr - 2 * dn * nr


def light_chords(beta: np.ndarray, dist: float, ball: GlassBall,
                 reflections: bool) -> tuple[np.ndarray, list]:
    """The interior chords of the light's rays in the meridional plane: coordinates (z along
    the axis from the light towards the centre, rho across it), the light at the origin, the
    centre at (dist, 0); the ray that enters at the point of polar angle ``beta`` about the
    centre (radians from the axis towards the light, |beta| at most acos(R / dist), the
    grazing entry). Returns the rays' polar angles alpha at the light, and one tuple per
    chord family (the refracted chord, and with ``reflections`` the chord after the first
    internal reflection): start (z, rho), unit direction (z, rho), the fraction of the ray's
    power the interfaces leave it (the extinction not included), and the path length inside
    before the start. Everything is smooth in beta (the entry point is not, in alpha, near
    grazing)."""
    R, n = ball.radius, ball.ior
    nz, nr = -np.cos(beta), np.sin(beta)                      # outward normal at entry
    pz, pr = dist + R * nz, R * nr
    alpha = np.arctan2(pr, pz)
    cz, cr = np.cos(alpha), np.sin(alpha)
    cos_i = np.clip(-(cz * nz + cr * nr), 0.0, 1.0)
    F, cos_t, _ = fresnel_unpolarised(cos_i, 1.0, n)
    eta = 1.0 / n
    dz = eta * cz + (eta * cos_i - cos_t) * nz
    dr = eta * cr + (eta * cos_i - cos_t) * nr
    norm = np.hypot(dz, dr)
    dz, dr = dz / norm, dr / norm
    out = [(pz, pr, dz, dr, 1.0 - F, np.zeros_like(beta))]
    if reflections:
        chord = 2 * R * cos_t
        qz, qr = pz + chord * dz, pr + chord * dr
        mz, mr = (qz - dist) / R, qr / R
        F_int, _, _ = fresnel_unpolarised(np.clip(dz * mz + dr * mr, 0.0, 1.0), n, 1.0)
        ez, er = _reflect_2d(dz, dr, mz, mr)
        out.append((qz, qr, ez, er, (1.0 - F) * F_int, chord))
    return alpha, out


class LightField:
    """The light of a point light (``light_pos``, ``intensity`` W/sr) inside the ball,
    family by family (0: refracted at entry; 1: then reflected once inside, with
    ``reflections``), from a scan of ``rays`` rays of the meridional plane (uniform in the
    entry point's angle)."""

    def __init__(self, light_pos, intensity: float, ball: GlassBall, reflections: bool,
                 rays: int = 1024):
        self.light_pos = np.asarray(light_pos, float)
        self.intensity, self.ball = float(intensity), ball
        axis = ball.center - self.light_pos
        dist = float(np.linalg.norm(axis))
        self.axis = axis / dist
        b_max = np.arccos(ball.radius / dist)
        self.alpha, self.chords = light_chords(np.linspace(-b_max, b_max, rays), dist, ball,
                                               reflections)

    def _meridional(self, x):
        v = x - self.light_pos
        z = v @ self.axis
        rvec = v - z[:, None] * self.axis
        rho = np.linalg.norm(rvec, axis=1)
        return z, rho, rvec / np.maximum(rho, 1e-300)[:, None]

    def _changes(self, z, rho, k: int, chunk: int = 512):
        """Per chunk of points, whether the signed distance of each point from the rays of
        family k, f = dz (rho - pr) - dr (z - pz), changes sign between rays j and j + 1
        (found in float32; the brackets' f is recomputed in float64)."""
        pz, pr, dz, dr = self.chords[k][:4]
        c = dr * pz - dz * pr
        dz32, dr32, c32 = (q.astype(np.float32) for q in (dz, dr, c))
        for lo in range(0, len(z), chunk):
            zz = z[lo:lo + chunk, None].astype(np.float32)
            rr = rho[lo:lo + chunk, None].astype(np.float32)
            above = rr * dz32 - zz * dr32 > -c32
            yield lo, above[:, :-1] != above[:, 1:]

    def paths(self, x: np.ndarray, k: int) -> np.ndarray:
        """How many light paths of family k reach each point of ``x`` (N, 3)."""
        z, rho, _ = self._meridional(x)
        return np.concatenate([ch.sum(axis=1) for _, ch in self._changes(z, rho, k)]
                              or [np.zeros(0, int)])

    def at(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The light of family k at points ``x`` (N, 3): arrays (index into x, irradiance
        E, unit direction of travel (., 3)), one row per light path reaching a point."""
        z, rho, e_rho = self._meridional(x)
        found = [(lo + i, j) for lo, ch in self._changes(z, rho, k) for i, j in [np.nonzero(ch)]]
        pt, j = (np.concatenate(a) for a in zip(*found)) if found else (np.zeros(0, int),) * 2
        pz, pr, dz, dr, T0, s0 = self.chords[k]
        c = dr * pz - dz * pr
        f0 = dz[j] * rho[pt] - dr[j] * z[pt] + c[j]
        f1 = dz[j + 1] * rho[pt] - dr[j + 1] * z[pt] + c[j + 1]
        w = np.clip(f0 / (f0 - f1), 0.0, 1.0)

        def lerp(q):
            return q[j] + w * (q[j + 1] - q[j])
        uz, ur = lerp(dz), lerp(dr)
        un = np.hypot(uz, ur)
        uz, ur = uz / un, ur / un
        s = lerp(s0) + (z[pt] - lerp(pz)) * uz + (rho[pt] - lerp(pr)) * ur
        # the tube: |sin alpha| d alpha d psi at the light, |df| times rho d psi at x
        a = self.alpha
        E = (self.intensity * lerp(T0) * np.exp(-self.ball.kappa * s) * np.abs(np.sin(lerp(a)))
             * np.abs(a[j + 1] - a[j]) / (np.abs(f1 - f0) * rho[pt]))
        return pt, E, uz[:, None] * self.axis + ur[:, None] * e_rho[pt]


def _view_chords(o, d, ball: GlassBall, reflections: bool) -> tuple[list, np.ndarray]:
    """The interior chords of camera rays (o, unit d; all hitting the ball): per chord,
    (start, unit direction, length, weight at the start: transmittance into the glass /
    n^2, times the internal reflectance and the chord's extinction for the second one),
    and the cosine of incidence at entry."""
    R, n = ball.radius, ball.ior
    t0, _ = ray_sphere(o, d, ball.center, R)
    p = o + t0[:, None] * d
    nrm = (p - ball.center) / R
    cos_i = np.clip(-np.einsum("ij,ij->i", d, nrm), 0.0, 1.0)
    F, cos_t, _ = fresnel_unpolarised(cos_i, 1.0, n)
    eta = 1.0 / n
    dt = eta * d + (eta * cos_i - cos_t)[:, None] * nrm
    dt /= np.linalg.norm(dt, axis=1, keepdims=True)
    chord = 2 * R * cos_t
    out = [(p, dt, chord, (1.0 - F) / n ** 2)]
    if reflections:
        q = p + chord[:, None] * dt
        m = (q - ball.center) / R
        cm = np.clip(np.einsum("ij,ij->i", dt, m), 0.0, 1.0)
        F_int, _, _ = fresnel_unpolarised(cm, n, 1.0)
        out.append((q, dt - 2 * cm[:, None] * m, chord,
                    out[0][3] * F_int * np.exp(-ball.kappa * chord)))
    return out, cos_i


def lit_pieces(field: LightField, k: int, p, dv, length, coarse: int = 64,
               bisections: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut the chords p + t dv, t in [0, length] (M of them) where the number of light paths
    of family k reaching the point changes (a shadow edge, a caustic's fold): found between
    ``coarse`` + 1 equally spaced points, then by bisection. Returns (chord index, t0, t1)
    of the pieces that light reaches."""
    m = len(length)
    tc = length[:, None] * (np.arange(coarse + 1) / coarse)[None, :]
    cnt = field.paths((p[:, None, :] + tc[..., None] * dv[:, None, :]).reshape(-1, 3), k)
    cnt = cnt.reshape(m, coarse + 1)
    ci, cj = np.nonzero(cnt[:, :-1] != cnt[:, 1:])
    lo, hi, c_lo = tc[ci, cj], tc[ci, cj + 1], cnt[ci, cj]
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        same = field.paths(p[ci] + mid[:, None] * dv[ci], k) == c_lo
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    # every chord's break points, in order: its ends and the edges
    ray = np.concatenate([np.arange(m), np.arange(m), ci])
    t = np.concatenate([np.zeros(m), length, 0.5 * (lo + hi)])
    o = np.lexsort((t, ray))
    ray, t = ray[o], t[o]
    same_ray = ray[:-1] == ray[1:]
    r, t0, t1 = ray[:-1][same_ray], t[:-1][same_ray], t[1:][same_ray]
    mid = p[r] + (0.5 * (t0 + t1))[:, None] * dv[r]
    lit = (field.paths(mid, k) > 0) & (t1 > t0)
    return r[lit], t0[lit], t1[lit]


def chord_light(field: LightField, k: int, p, dv, length, steps: int = 24) -> tuple:
    """The light of family k along chords p + t dv, t in [0, length] (M of them), as
    quadrature nodes: arrays (chord index, t, weight dt, irradiance E, unit direction of
    travel (., 3)), one row per node and light path; sum(dt * g(t) * E) over a chord's rows
    is the integral of g E along it. Each piece the light reaches (:func:`lit_pieces`) gets
    ``steps`` nodes, the midpoint rule in v on t = t0 + (t1 - t0)(1 - cos(pi v)) / 2: the
    substitution's dt vanishes like sqrt(t - t0) at both ends, which takes out the 1/sqrt
    singularity of a caustic's fold at a piece's end."""
    r, a, b = lit_pieces(field, k, p, dv, length)
    v = (np.arange(steps) + 0.5) / steps
    t = (a[:, None] + (b - a)[:, None] * (0.5 - 0.5 * np.cos(np.pi * v))[None, :]).reshape(-1)
    dt = ((b - a)[:, None] * (0.5 * np.pi / steps) * np.sin(np.pi * v)[None, :]).reshape(-1)
    ray = np.repeat(r, steps)
    idx, E, u = field.at(p[ray] + t[:, None] * dv[ray], k)
    return ray[idx], t[idx], dt[idx], E, u


def interior_radiance(o, d, light_pos, intensity: float, ball: GlassBall,
                      reflections: bool = False, steps: int = 24,
                      rays: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (N,) the camera receives along rays (o (N, 3) or (3,), unit d (N, 3)) from
    single scattering inside the ball, and each ray's cosine of incidence (0: a miss):
    every view chord's integral of sigma_s p E exp(-kappa t) (:func:`chord_light`) for
    each family of light, times the chord's weight."""
    d = np.asarray(d, float)
    o = np.broadcast_to(np.asarray(o, float), d.shape)
    out = np.zeros(len(d))
    cos_in = np.zeros(len(d))
    t0, _ = ray_sphere(o, d, ball.center, ball.radius)
    hit = np.flatnonzero(np.isfinite(t0) & (t0 > 0))
    if not len(hit):
        return out, cos_in
    field = LightField(light_pos, intensity, ball, reflections, rays)
    chords, cos_in[hit] = _view_chords(o[hit], d[hit], ball, reflections)
    for p, dv, length, w0 in chords:
        for k in range(len(field.chords)):
            ray, t, dt, E, ul = chord_light(field, k, p, dv, length, steps)
            cos = -np.einsum("ij,ij->i", ul, dv[ray])             # light travel . towards eye
            contrib = ball.sigma_s * hg(cos, ball.g) * E * w0[ray] * np.exp(-ball.kappa * t) * dt
            out[hit] += np.bincount(ray, weights=contrib, minlength=len(hit))
    return out, cos_in


def interior_image(cam: Camera, light_pos, intensity: float, ball: GlassBall,
                   reflections: bool = False, sub: int = 2, steps: int = 24,
                   rays: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) radiance of the ball's interior scattering as the camera sees it (box filter:
    the mean over sub x sub points of each pixel), and (H, W) the least cosine of incidence
    of a pixel's rays on the sphere (0 where one misses it)."""
    img = np.zeros((cam.height, cam.width))
    least = np.ones((cam.height, cam.width))
    for a in range(sub):
        for b in range(sub):
            d = cam.pixel_rays((a + 0.5) / sub, (b + 0.5) / sub).reshape(-1, 3)
            L, c = interior_radiance(cam.origin, d, light_pos, intensity, ball, reflections,
                                     steps, rays)
            img += L.reshape(img.shape) / sub ** 2
            least = np.minimum(least, c.reshape(img.shape))
    return img, least
