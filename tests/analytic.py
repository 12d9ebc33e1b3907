"""Analytic and quadrature references for single scattering (a helper for tests).

This is an importable helper module, not a test file. Everything is float64 NumPy and
follows the "Radiometric conventions" of ``docs/scene_format.md``:

* homogeneous medium with scattering ``sigma_s`` and extinction ``kappa``; both are
  *scalars per call* (the caller loops over the rgb channels);
* Henyey-Greenstein phase function :func:`hg`, where ``cos`` is the cosine between the
  light's travel direction (light -> scattering point) and the direction towards the
  camera (scattering point -> eye, i.e. minus the view ray direction);
* single scattering radiance along a view ray ``x(t) = o + t w`` (``w`` unit)::

      L = integral sigma_s p(cos(t)) L_i(x(t)) T_view(t) dt,
      T_view(t) = exp(-kappa * length of [0, t] inside the medium);

* point / spot lights have intensity ``I`` (W/sr), directional lights irradiance ``E``
  (W/m^2); Lambertian surfaces reflect ``albedo / pi * irradiance``.

Contents
--------
``hg``                    Henyey-Greenstein phase function.
``camera_rays``           the renderer's pinhole camera convention (the only copy here).
``camera_kwargs``         camera arguments from a ``[camera]`` table or a model Camera.
``pixel_average``         box-filtered pixel values of a per-ray function (stratified).
``airlight_point``        point light, unbounded medium, no occluders (quad / Gauss).
``airlight_point_closed_form``  the classic kappa = 0, g = 0 airlight integral.
``airlight_spot``         hard-edged spot light, unbounded medium, no occluders.
``directional_slab``      directional light, medium in an axis-aligned box (closed form).
``directional_slab_quad`` the same by adaptive quadrature (a cross-check).
``diffuse_point_lit``     radiance of a Lambertian point lit by a point light.
``diffuse_directional_lit``  the same for a directional light.

Ray arrays: ``o`` is one origin ``(3,)`` or one per ray ``(N, 3)``; ``dirs`` is
``(N, 3)`` (normalised internally; a single ``(3,)`` direction is accepted too); results
are ``(N,)``. ``t_max`` (scalar or ``(N,)``) ends the view ray, e.g. at an occluder.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import integrate

__all__ = [
    "hg",
    "camera_rays",
    "camera_kwargs",
    "pixel_average",
    "airlight_point",
    "airlight_point_closed_form",
    "airlight_spot",
    "directional_slab",
    "directional_slab_quad",
    "ray_box",
    "diffuse_point_lit",
    "diffuse_directional_lit",
]

FOUR_PI = 4.0 * math.pi


# --------------------------------------------------------------------------------------
# Phase function
# --------------------------------------------------------------------------------------
def hg(cos, g):
    """Henyey-Greenstein phase function, normalised to 1 over the sphere.

    ``p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5)``; ``cos`` is the cosine between
    the light's travel direction and the direction towards the camera (so ``g > 0``
    favours light that keeps going towards the camera). Broadcasts ``cos`` and ``g``;
    ``g = 0`` gives ``1 / (4 pi)``.
    """
    cos = np.asarray(cos, np.float64)
    g = np.asarray(g, np.float64)
    denom = 1.0 + g * g - 2.0 * g * cos
    return (1.0 - g * g) / (FOUR_PI * denom * np.sqrt(denom))


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------
def _normalize(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def camera_rays(origin, target, up, fov, fov_axis, width, height, u=0.5, v=0.5):
    """Unit view-ray directions ``(H, W, 3)`` of the renderer's pinhole camera.

    The convention (identical to ``clscatter/scene/normalised.py`` and the kernels)::

        forward = normalize(target - origin)
        right   = normalize(cross(forward, up)),   true_up = cross(right, forward)
        aspect  = W / H
        fov_axis "x": tan_x = tan(fov / 2), tan_y = tan_x / aspect
        fov_axis "y": tan_y = tan(fov / 2), tan_x = tan_y * aspect
        pixel position (px + u, py + v), u, v in [0, 1):
            sx = 2 (px + u) / W - 1,   sy = 1 - 2 (py + v) / H
        dir = normalize(forward + sx tan_x right + sy tan_y true_up)

    ``fov`` is the full angle in degrees; row 0 is the top of the image. ``u`` and ``v``
    are sub-pixel offsets, scalars or arrays broadcastable to ``(H, W)`` (values outside
    [0, 1) are allowed: ``u = 0`` on pixel 0 and ``u = 1`` on pixel W-1 give the image's
    left and right edges). ``origin`` is not needed for directions but kept so the
    argument list is the full camera.
    """
    origin = np.asarray(origin, np.float64)
    fwd = _normalize(np.asarray(target, np.float64) - origin)
    right = _normalize(np.cross(fwd, np.asarray(up, np.float64)))
    tup = np.cross(right, fwd)
    width, height = int(width), int(height)
    aspect = width / height
    half = math.tan(math.radians(float(fov)) / 2.0)
    if fov_axis == "x":
        tan_x, tan_y = half, half / aspect
    elif fov_axis == "y":
        tan_x, tan_y = half * aspect, half
    else:
        raise ValueError(f"fov_axis must be 'x' or 'y', not {fov_axis!r}")
    px = np.arange(width, dtype=np.float64)[None, :]
    py = np.arange(height, dtype=np.float64)[:, None]
    u = np.broadcast_to(np.asarray(u, np.float64), (height, width))
    v = np.broadcast_to(np.asarray(v, np.float64), (height, width))
    sx = 2.0 * (px + u) / width - 1.0
    sy = 1.0 - 2.0 * (py + v) / height
    d = fwd + (sx * tan_x)[..., None] * right + (sy * tan_y)[..., None] * tup
    return _normalize(d)


def camera_kwargs(cam) -> dict:
    """``origin, target, up, fov, fov_axis, width, height`` as a dict.

    ``cam`` is a ``[camera]`` TOML table (``resolution = [W, H]``, ``fov_axis`` optional,
    default "x") or an object with those attributes (``clscatter.scene.model.Camera``,
    which has ``width`` / ``height``). Use as ``pixel_average(fn, **camera_kwargs(cam))``.
    """
    if isinstance(cam, dict):
        w, h = cam["resolution"]
        return dict(origin=np.asarray(cam["origin"], np.float64),
                    target=np.asarray(cam["target"], np.float64),
                    up=np.asarray(cam.get("up", [0.0, 1.0, 0.0]), np.float64),
                    fov=float(cam.get("fov", 45.0)), fov_axis=cam.get("fov_axis", "x"),
                    width=int(w), height=int(h))
    return dict(origin=np.asarray(cam.origin, np.float64), target=np.asarray(cam.target, np.float64),
                up=np.asarray(cam.up, np.float64), fov=float(cam.fov), fov_axis=cam.fov_axis,
                width=int(cam.width), height=int(cam.height))


def pixel_average(fn, origin, target, up, fov, fov_axis, width, height, sub=4):
    """Box-filtered image of a per-ray function: ``(H, W)`` (or ``(H, W, C)``).

    ``fn(origin, dirs)`` gets the camera origin ``(3,)`` and unit directions ``(N, 3)``
    and returns ``(N,)`` (or ``(N, C)``, e.g. rgb). Each pixel is the mean over a
    ``sub x sub`` grid of sub-pixel positions at the centres of the strata,
    ``u, v = (i + 0.5) / sub``; ``sub = 1`` samples pixel centres only. Bind the other
    arguments with a lambda or ``functools.partial``, e.g.::

        img = pixel_average(lambda o, d: airlight_point(o, d, lp, 10.0, 0.2, 0.3, 0.0,
                                                        method="gauss"),
                            **camera_kwargs(scene_dict["camera"]), sub=4)

    (``sub * sub * W * H`` rays: prefer the vectorised references — ``method="gauss"``,
    :func:`directional_slab` — over per-ray quad for more than a few thousand rays.)
    """
    origin = np.asarray(origin, np.float64)
    width, height, sub = int(width), int(height), int(sub)
    acc = None
    for j in range(sub):
        for i in range(sub):
            d = camera_rays(origin, target, up, fov, fov_axis, width, height,
                            (i + 0.5) / sub, (j + 0.5) / sub)
            val = np.asarray(fn(origin, d.reshape(-1, 3)), np.float64)
            val = val.reshape((height, width) + val.shape[1:])
            acc = val.copy() if acc is None else acc + val
    return acc / (sub * sub)


# --------------------------------------------------------------------------------------
# Ray helpers
# --------------------------------------------------------------------------------------
def _rays(o, dirs, t_max=np.inf):
    dirs = np.atleast_2d(np.asarray(dirs, np.float64))
    w = _normalize(dirs)
    n = w.shape[0]
    o = np.broadcast_to(np.asarray(o, np.float64), (n, 3))
    t_max = np.broadcast_to(np.asarray(t_max, np.float64), (n,))
    return o, w, t_max


def ray_box(o, dirs, box_min, box_max):
    """Slab test: ``(t_in, t_out, hit)`` of the lines ``o + t w`` with a closed box.

    ``t_in <= t_out`` where ``hit``; not clamped to ``t >= 0`` (the caller does).
    Directions parallel to a slab are handled exactly (miss when outside it).
    """
    o, w, _ = _rays(o, dirs)
    lo = np.asarray(box_min, np.float64)
    hi = np.asarray(box_max, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / w
        ta = (lo - o) * inv
        tb = (hi - o) * inv
    t1 = np.minimum(ta, tb)
    t2 = np.maximum(ta, tb)
    par = w == 0.0
    inside = (o >= lo) & (o <= hi)
    t1 = np.where(par, np.where(inside, -np.inf, np.inf), t1)
    t2 = np.where(par, np.where(inside, np.inf, -np.inf), t2)
    t_in = t1.max(axis=1)
    t_out = t2.min(axis=1)
    return t_in, t_out, t_in <= t_out


# --------------------------------------------------------------------------------------
# Point light, unbounded medium
# --------------------------------------------------------------------------------------
def _quad(f, a, b, epsabs, epsrel):
    """quad on [a, b] (a <= b). An interval shorter than 1e-6 of |a|, |b| gets a
    16-point Gauss-Legendre rule instead (quad reports "bad integrand behaviour" when
    it bisects down to a few ulps)."""
    if not b > a:
        return 0.0
    if b - a <= 1e-6 * max(abs(a), abs(b)):
        half, mid = 0.5 * (b - a), 0.5 * (a + b)
        return half * sum(wk * f(mid + half * xk) for xk, wk in zip(_GL_X, _GL_W))
    return integrate.quad(f, a, b, epsabs=epsabs, epsrel=epsrel, limit=200)[0]


def _closest_approach(o, w, light_pos):
    """Unclamped closest-approach parameter t_c of the line and the distance h there."""
    lp = np.asarray(light_pos, np.float64)
    t_c = np.einsum("ij,ij->i", lp - o, w)
    h = np.linalg.norm(o + t_c[:, None] * w - lp, axis=1)
    return t_c, h


# The point-light integral in angle form. Write t = t_c + sigma u with u = |t - t_c| >= 0
# on each side sigma = +-1 of the closest approach t_c (the peak), and u = h cot(phi),
# phi in (0, pi/2] (phi = pi/2 at the peak, phi -> 0 far away). Then
#     d = h / sin(phi),  dt = h / sin^2(phi) dphi,  so  I / d^2 dt = I / h dphi,
#     phase cosine = dot((x - light)/d, -w) = -sigma cos(phi),
#     t + d = t_c + h cot(phi/2) (sigma = +1)  or  t_c + h tan(phi/2) (sigma = -1).
# The integrand is bounded and smooth in phi, and phi = atan2(h, u) keeps full relative
# precision even for a short piece of ray far from the light (where the textbook
# atan((t - t_c)/h) differences cancel).
def _phi(u, h):
    return np.arctan2(h, u)


def _integrand_phi(phi, sgn, t_c, h, intensity, sigma_s, kappa, g):
    """sigma_s I / h p(-sgn cos phi) exp(-kappa (t + d)) on side sgn (see above)."""
    cos_phase = -sgn * np.cos(phi)
    val = sigma_s * intensity / h * hg(cos_phase, g)
    if kappa != 0:
        half = np.tan(0.5 * phi)
        with np.errstate(divide="ignore", over="ignore"):
            td = t_c + h * np.where(sgn > 0, 1.0 / half, half)
            val = val * np.exp(-kappa * td)
    return val


def _sides(t_c, ta, tb):
    """The two sides of the peak: [(sgn, u_lo, u_hi)] with u = |t - t_c| (arrays)."""
    plus = (1.0, np.maximum(ta - t_c, 0.0), np.maximum(tb - t_c, 0.0))
    minus = (-1.0, np.maximum(t_c - tb, 0.0), np.maximum(t_c - ta, 0.0))
    return plus, minus


def _u_breaks(h, u_lo, kappa):
    """Break points in u = |t - t_c|: the scales of 1/d^2 (h 10^k, which the angle form
    squeezes towards phi = 0 when h is small) and those of the attenuation (m / kappa,
    from the peak and from the side's start u_lo)."""
    cand = []
    for k in range(14):
        cand += [h * 10.0 ** k, 3.0 * h * 10.0 ** k]
    if kappa > 0:
        for m in (0.25, 1.0, 3.0, 8.0, 20.0, 50.0):
            cand += [m / kappa, u_lo + m / kappa]
    return cand


def _segment_quad(t_c, h, ta, tb, intensity, sigma_s, kappa, g, epsrel, scale=0.0):
    """Adaptive quad of one ray's point-light integral over t in [ta, tb] (angle form),
    split at the peak t_c and at the break points of :func:`_u_breaks`."""
    total = 0.0
    for sgn, u_lo, u_hi in _sides(t_c, ta, tb):
        u_lo, u_hi = float(u_lo), float(u_hi)
        if not u_hi > u_lo:
            continue
        us = [u_lo] + sorted(u for u in _u_breaks(h, u_lo, kappa) if u_lo < u < u_hi) + [u_hi]
        ph = _phi(np.asarray(us), h)          # decreasing
        f = lambda x, s=sgn: float(_integrand_phi(x, s, t_c, h, intensity, sigma_s, kappa, g))
        for a, b in zip(ph[1:], ph[:-1]):
            total += _quad(f, a, b, 1e-3 * epsrel * scale, epsrel)
    return total


def _segment_quad_t(t_c, h, ta, tb, o, w, lp, intensity, sigma_s, kappa, g, epsrel, scale=0.0):
    """Adaptive quad directly in t, split at the peak t* = clamp(t_c, ta, tb) and at
    t* +- h 10^k and t* +- m / kappa (the independent cross-check of the angle form)."""
    if not tb > ta:
        return 0.0

    def f(t):
        dv = o + t * w - lp
        d2 = float(dv @ dv)
        d = math.sqrt(d2)
        cos = -float(dv @ w) / d
        return sigma_s * float(hg(cos, g)) * intensity / d2 * math.exp(-kappa * (d + t))

    t_star = min(max(t_c, ta), tb)
    big = 1e3 * (h + abs(t_c) + 1.0)
    scales = [h * 10.0 ** k for k in range(14) if h * 10.0 ** k <= big]
    if kappa > 0:
        scales += [m / kappa for m in (0.25, 1.0, 4.0, 16.0)]
    # a finite interval carries the breaks; an infinite tail is left to quad's mapping
    hi_lim = tb if math.isfinite(tb) else t_star + max(scales)
    pts = {t_star} | {t_star + s for s in scales} | {t_star - s for s in scales}
    pts = [ta] + sorted(p for p in pts if ta < p < hi_lim) + [hi_lim]
    total = 0.0
    for a, b in zip(pts[:-1], pts[1:]):
        total += _quad(f, a, b, 1e-3 * epsrel * scale, epsrel)
    if not math.isfinite(tb):
        total += integrate.quad(f, hi_lim, np.inf, epsabs=1e-3 * epsrel * max(scale, total),
                                epsrel=epsrel, limit=200)[0]
    return total


# Gauss-Legendre nodes for the vectorised method
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)


def _gauss_phi_breaks(h, u_lo, kappa, g):
    """Panel ends (angles, one row per ray) for the vectorised Gauss rule: u = h/3, h, 3h
    (fixed angles), the attenuation scales u = u_lo + m / kappa (u_lo: the side's start)
    and geometric angles pi/2 4^-k (only with attenuation), and, for a peaked phase function, angles ~ (1 - |g|) (where p(-sgn cos phi) varies
    fastest)."""
    cand = [np.full_like(h, math.atan(1.0 / c)) for c in (1.0 / 3.0, 1.0, 3.0)]
    if kappa > 0:
        cand += [_phi(u_lo + m / kappa, h) for m in (0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0)]
        # the attenuation goes like exp(-2 kappa h / phi) near phi = 0: geometric panels
        cand += [np.full_like(h, 0.5 * math.pi * 4.0 ** -k) for k in range(2, 14)]
    if abs(g) > 0.3:
        cand += [np.full_like(h, min((1.0 - abs(g)) * c, 1.5)) for c in (0.3, 1.0, 3.0)]
    return np.stack(cand, axis=1)


def _segments_gauss(t_c, h, ta, tb, intensity, sigma_s, kappa, g, sub=2):
    """Vectorised composite Gauss-Legendre (angle form) over [ta, tb], one per ray.

    Per side of the peak, panels end at the angles of :func:`_gauss_phi_breaks` (clipped
    per ray to the side's range) and each panel is split in ``sub``; 16 nodes per
    sub-panel.
    """
    out = np.zeros(t_c.shape[0])
    for sgn, u_lo, u_hi in _sides(t_c, ta, tb):
        ok = u_hi > u_lo
        if not np.any(ok):
            continue
        tc, hh, lo_, hi_ = t_c[ok], h[ok], u_lo[ok], u_hi[ok]
        p_lo, p_hi = _phi(hi_, hh), _phi(lo_, hh)            # the angle decreases with u
        ph = np.clip(_gauss_phi_breaks(hh, lo_, kappa, g), p_lo[:, None], p_hi[:, None])
        ph = np.sort(np.concatenate([p_lo[:, None], ph, p_hi[:, None]], axis=1), axis=1)
        a, b = ph[:, :-1], ph[:, 1:]
        frac = np.arange(sub + 1) / sub
        edges = a[..., None] + (b - a)[..., None] * frac          # (m, P, sub+1)
        lo, hi = edges[..., :-1], edges[..., 1:]
        half = 0.5 * (hi - lo)
        x = (0.5 * (hi + lo))[..., None] + half[..., None] * _GL_X
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            f = _integrand_phi(x, sgn, tc[:, None, None, None], hh[:, None, None, None],
                               intensity, sigma_s, kappa, g)
        f = np.where(np.isfinite(f), f, 0.0)
        out[ok] += np.sum(f * _GL_W * half[..., None], axis=(1, 2, 3))
    return out


def _point_segments(o, w, light_pos, intensity, sigma_s, kappa, g, ta, tb, method, epsrel):
    """Point-light single scattering over t in [ta_i, tb_i] per ray (unbounded medium)."""
    if method not in ("quad", "quad_t", "gauss"):
        raise ValueError(f"unknown method {method!r}")
    lp = np.asarray(light_pos, np.float64)
    t_c, h = _closest_approach(o, w, lp)
    n = w.shape[0]
    ta = np.broadcast_to(np.asarray(ta, np.float64), (n,))
    tb = np.broadcast_to(np.asarray(tb, np.float64), (n,))
    out = np.zeros(n)
    # a line through the light: h = 0 (or so small that the angle form loses precision)
    dist = np.linalg.norm(o - lp, axis=1)
    degenerate = h <= 1e-12 * np.maximum(dist, 1e-300)
    # the vectorised Gauss result: the answer for "gauss", and the scale of the absolute
    # tolerance of the quad methods (so pieces where the integrand underflows end early)
    nd = ~degenerate
    est = np.zeros(n)
    if np.any(nd):
        est[nd] = _segments_gauss(t_c[nd], h[nd], ta[nd], tb[nd], intensity, sigma_s, kappa, g)
    if method == "gauss":
        out[:] = est
    for i in range(n):
        if not tb[i] > ta[i]:
            continue
        if degenerate[i]:
            out[i] = _through_light(t_c[i], ta[i], tb[i], intensity, sigma_s, kappa, g, epsrel)
        elif method == "quad":
            out[i] = _segment_quad(t_c[i], h[i], ta[i], tb[i], intensity, sigma_s, kappa, g,
                                   epsrel, est[i])
        elif method == "quad_t":
            out[i] = _segment_quad_t(t_c[i], h[i], ta[i], tb[i], o[i], w[i], lp,
                                     intensity, sigma_s, kappa, g, epsrel, est[i])
    return out


def _through_light(t_c, ta, tb, intensity, sigma_s, kappa, g, epsrel):
    """A ray through the light: infinite if the light is on [ta, tb], else 1-D quad."""
    if ta <= t_c <= tb:
        return math.inf
    # d = |t - t_c|; before the light (t < t_c) light travels towards the camera: cos = +1
    cos = 1.0 if tb <= t_c else -1.0
    p = float(hg(cos, g))
    f = lambda t: sigma_s * p * intensity / (t - t_c) ** 2 * math.exp(-kappa * (abs(t - t_c) + t))
    return integrate.quad(f, ta, tb, epsabs=0.0, epsrel=epsrel, limit=200)[0]


def airlight_point(o, dirs, light_pos, intensity, sigma_s, kappa, g, t_max=np.inf,
                   method="quad", epsrel=1e-11):
    """Single scattering from a point light in an UNBOUNDED medium, no occluders: ``(N,)``.

    ``L = int_0^t_max sigma_s p(cos) I / d(t)^2 exp(-kappa d(t)) exp(-kappa t) dt`` with
    ``d(t) = |o + t w - light_pos|`` and ``cos = dot((x - light)/d, -w)``.

    ``method``:

    * ``"quad"`` (default): ``scipy.integrate.quad`` per ray, split at the peak
      ``t* = t_c`` (the closest approach, when inside [0, t_max]) and, on each side, at
      ``|t - t*| = h 10^k, 3 h 10^k`` and ``m / kappa``; each side is integrated in the
      angle ``phi = atan2(h, |t - t*|)`` (``h`` the distance of the line from the light),
      which turns ``I / d^2 dt`` into ``I / h dphi`` and removes the peak. Relative
      accuracy ~1e-10 even for ``h = 1e-6``.
    * ``"quad_t"``: quad directly in t, split at ``t* = clamp(t_c, 0, t_max)`` and at
      ``t* +- h 10^k`` (the independent cross-check; slower).
    * ``"gauss"``: vectorised composite Gauss-Legendre in the angle (no Python loop
      over rays, ~0.1 ms per ray instead of several ms; ~1e-12 relative for ordinary
      scenes, still < 1e-6 with extreme attenuation, kappa * length ~ 300), for whole
      images via :func:`pixel_average`.

    Performance: "quad" is ~2-10 ms per ray; for images use "gauss".

    ``t_max`` (scalar or ``(N,)``) ends the ray. A ray exactly through the light gives
    ``inf`` when the light lies on [0, t_max].
    """
    o, w, t_max = _rays(o, dirs, t_max)
    return _point_segments(o, w, light_pos, float(intensity), float(sigma_s), float(kappa),
                           float(g), 0.0, t_max, method, epsrel)


def airlight_point_closed_form(o, dirs, light_pos, intensity, sigma_s, t_max=np.inf):
    """The classic airlight integral (kappa = 0, g = 0), exact: ``(N,)``.

    ``int_0^t_max sigma_s / (4 pi) I / (h^2 + (t - t_c)^2) dt
    = sigma_s I / (4 pi h) [atan((t_max - t_c) / h) - atan((0 - t_c) / h)]``
    with ``t_c = dot(light - o, w)`` the (unclamped) closest approach and ``h`` the
    distance of the line from the light there. The bracket is evaluated per side of
    t_c as differences of ``atan2(h, |t - t_c|)``, which keeps full relative precision
    when both ends are far from the light on the same side.
    """
    o, w, t_max = _rays(o, dirs, t_max)
    t_c, h = _closest_approach(o, w, light_pos)
    ang = np.zeros_like(t_c)
    for _, u_lo, u_hi in _sides(t_c, np.zeros_like(t_c), t_max):
        ang += _phi(u_lo, h) - _phi(u_hi, h)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = ang / h
        # a line through the light (h = 0): int dt / (t - t_c)^2, infinite if it is hit
        u_near = np.where(t_c < 0, -t_c, t_c - t_max)
        u_far = np.where(t_c < 0, t_max - t_c, t_c)
        through = np.where((t_c >= 0) & (t_c <= t_max), np.inf, 1.0 / u_near - 1.0 / u_far)
        dist = np.linalg.norm(o - np.asarray(light_pos, np.float64), axis=1)
        out = np.where(h > 1e-12 * dist, out, through)
    return float(sigma_s) * float(intensity) / FOUR_PI * out


# --------------------------------------------------------------------------------------
# Spot light, unbounded medium
# --------------------------------------------------------------------------------------
def _cone_pieces(o, w, apex, axis, cos_cut, t_lo, t_hi):
    """Intervals of [t_lo, t_hi] inside the cone ``dot(x - apex, axis) >= cos_cut |x - apex|``.

    Returns ``(starts, ends)``, each ``(N, 4)``; unused pieces have ``start == end``.
    Break points are the real roots of ``(dot(D, a))^2 = c^2 |D|^2`` with
    ``D = o - apex + t w`` (both nappes; a midpoint test keeps the inside pieces), so any
    half-angle in (0, 180) degrees works.
    """
    n = w.shape[0]
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    D = o - np.asarray(apex, np.float64)
    c2 = cos_cut * cos_cut
    da = D @ a
    wa = w @ a
    A = wa * wa - c2
    B = 2.0 * (da * wa - c2 * np.einsum("ij,ij->i", D, w))
    C = da * da - c2 * np.einsum("ij,ij->i", D, D)
    roots = np.full((n, 3), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = B * B - 4.0 * A * C
        sq = np.sqrt(np.maximum(disc, 0.0))
        # stable quadratic formula
        q = -0.5 * (B + np.copysign(sq, B))
        quad_ok = (np.abs(A) > 1e-14) & (disc >= 0)
        roots[:, 0] = np.where(quad_ok, q / A, np.nan)
        roots[:, 1] = np.where(quad_ok, C / q, np.nan)
        # the vertex -B / 2A: a double root that roundoff may have pushed to disc < 0
        # (e.g. a 90 degree cone, a plane); an extra break point is harmless
        roots[:, 2] = np.where(np.abs(A) > 1e-14, -B / (2.0 * A), np.nan)
        lin = (np.abs(A) <= 1e-14) & (B != 0)
        roots[:, 0] = np.where(lin, -C / B, roots[:, 0])
    t_lo = np.broadcast_to(np.asarray(t_lo, np.float64), (n,))
    t_hi = np.broadcast_to(np.asarray(t_hi, np.float64), (n,))
    r = np.where(np.isfinite(roots), roots, t_lo[:, None])
    r = np.clip(r, t_lo[:, None], t_hi[:, None])
    r.sort(axis=1)
    edges = np.concatenate([t_lo[:, None], r, t_hi[:, None]], axis=1)   # (n, 5)
    starts, ends = edges[:, :-1], edges[:, 1:]
    # midpoint test (an infinite piece: test a point beyond its start)
    mid = np.where(np.isfinite(ends), 0.5 * (starts + ends), starts + 1.0 + np.abs(starts))
    x = D[:, None, :] + mid[..., None] * w[:, None, :]
    xn = np.linalg.norm(x, axis=-1)
    inside = (x @ a) >= cos_cut * xn
    ends = np.where(inside, ends, starts)
    return starts, ends


def airlight_spot(o, dirs, light_pos, axis, cutoff_deg, intensity, sigma_s, kappa, g,
                  t_max=np.inf, method="quad", epsrel=1e-11):
    """Single scattering from a hard-edged spot light, unbounded medium, no occluders.

    The point light of :func:`airlight_point` (intensity ``I`` uniform inside the cone)
    with ``L_i = 0`` where the angle between ``x - light_pos`` and ``axis`` exceeds
    ``cutoff_deg`` (the half-angle, degrees). The view ray's pieces inside the cone come
    from the quadratic cone intersection and are integrated separately. ``(N,)``.
    ``method`` / ``epsrel`` as for :func:`airlight_point` ("gauss" for images).
    """
    o, w, t_max = _rays(o, dirs, t_max)
    cos_cut = math.cos(math.radians(float(cutoff_deg)))
    starts, ends = _cone_pieces(o, w, light_pos, axis, cos_cut, 0.0, t_max)
    out = np.zeros(w.shape[0])
    for k in range(starts.shape[1]):
        out += _point_segments(o, w, light_pos, float(intensity), float(sigma_s), float(kappa),
                               float(g), starts[:, k], ends[:, k], method, epsrel)
    return out


# --------------------------------------------------------------------------------------
# Directional light, medium in a box
# --------------------------------------------------------------------------------------
def _exit_lines(o, w, light_dir, box_min, box_max):
    """s(t) = min_k (a_k + b_k t): distance from o + t w to the box boundary along -light_dir.

    Returns ``a, b`` of shape ``(N, 3)``; axes where the light travels parallel to the
    faces get ``a = inf, b = 0``.
    """
    ld = _normalize(np.asarray(light_dir, np.float64))
    u = -ld                                              # towards the light
    lo = np.asarray(box_min, np.float64)
    hi = np.asarray(box_max, np.float64)
    face = np.where(u > 0, hi, lo)                       # exit face per axis
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (face - o) / u                               # (N, 3)
        b = np.broadcast_to(-w / u, a.shape)
    par = np.broadcast_to(u == 0, a.shape)
    a = np.where(par, np.inf, a)
    b = np.where(par, 0.0, b)
    return a, b, ld


def _medium_interval(o, w, t_max, box_min, box_max):
    t_in, t_out, hit = ray_box(o, w, box_min, box_max)
    t0 = np.maximum(t_in, 0.0)
    t1 = np.minimum(t_out, t_max)
    hit = hit & (t1 > t0)
    return np.where(hit, t0, 0.0), np.where(hit, t1, 0.0), hit


def directional_slab(o, dirs, light_dir, irradiance, sigma_s, kappa, g, box_min, box_max,
                     t_max=np.inf):
    """Directional light, medium filling an axis-aligned box, no occluders: exact ``(N,)``.

    ``L = sigma_s p(cos) E int_{t0}^{t1} exp(-kappa ((t - t0) + s(t))) dt``, where
    ``[t0, t1]`` is the view ray's part inside the box (``t >= 0``, ``t <= t_max``; the
    camera may be inside or outside), ``cos = dot(light_dir, -w)`` is constant and
    ``s(t)`` is the distance from ``x(t)`` to the box boundary going towards the light
    (along ``-light_dir``). ``s(t) = min_k (a_k + b_k t)`` over the three exit faces, so it
    is piecewise linear with breaks where two face lines cross; on each piece the
    exponent is linear and the integral is exact::

        int_0^D exp(-(alpha + beta t)) dt
            = exp(-min(alpha, alpha + beta D)) * D * (1 - exp(-|beta| D)) / (|beta| D)

    Rays that miss the box give 0. ``light_dir`` is the travel direction (normalised).
    """
    o, w, t_max = _rays(o, dirs, t_max)
    t0, t1, hit = _medium_interval(o, w, t_max, box_min, box_max)
    a, b, ld = _exit_lines(o, w, light_dir, box_min, box_max)
    # crossings of the face lines (j, k)
    cand = [t0[:, None], t1[:, None]]
    with np.errstate(divide="ignore", invalid="ignore"):
        for j, k in ((0, 1), (0, 2), (1, 2)):
            tc = (a[:, j] - a[:, k]) / (b[:, k] - b[:, j])
            tc = np.where(np.isfinite(tc), tc, t0)
            cand.append(tc[:, None])
    ts = np.clip(np.concatenate(cand, axis=1), t0[:, None], t1[:, None])
    ts.sort(axis=1)                                       # (N, 5)
    with np.errstate(invalid="ignore"):
        s = np.min(a[:, None, :] + b[:, None, :] * ts[..., None], axis=2)
    s = np.maximum(s, 0.0)
    expo = kappa * ((ts - t0[:, None]) + s)               # exponent at the break points
    ea, eb = expo[:, :-1], expo[:, 1:]
    D = ts[:, 1:] - ts[:, :-1]
    x = np.abs(eb - ea)                                   # |beta| D
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(x > 1e-300, -np.expm1(-x) / x, 1.0)
    seg = np.exp(-np.minimum(ea, eb)) * D * ratio
    seg = np.where(D > 0, seg, 0.0)
    integral = seg.sum(axis=1)
    cos = -(w @ ld)
    out = float(sigma_s) * hg(cos, float(g)) * float(irradiance) * integral
    return np.where(hit, out, 0.0)


def _exit_distance(x, u, lo, hi):
    """Distance from a point x inside the box to its boundary along unit u (slab test)."""
    best = math.inf
    for k in range(3):
        if u[k] > 0:
            best = min(best, (hi[k] - x[k]) / u[k])
        elif u[k] < 0:
            best = min(best, (lo[k] - x[k]) / u[k])
    return max(best, 0.0)


def _shadow_edge_crossings(o, w, u, lo, hi):
    """t where the ray o + t w crosses a plane spanned by a box edge and u (the light's
    reverse direction): the only places where the exit face along u can change."""
    ts = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        n = np.cross(e, u)
        den = float(w @ n)
        if abs(den) < 1e-300 or not np.any(n):
            continue
        j, l = [m for m in range(3) if m != k]
        for cj in (lo[j], hi[j]):
            for cl in (lo[l], hi[l]):
                p = np.zeros(3)
                p[j], p[l] = cj, cl
                ts.append(float((p - o) @ n) / den)
    return ts


def directional_slab_quad(o, dirs, light_dir, irradiance, sigma_s, kappa, g, box_min, box_max,
                          t_max=np.inf, epsrel=1e-11):
    """:func:`directional_slab` by adaptive quadrature per ray (a cross-check): ``(N,)``.

    ``s(t)`` is computed pointwise by a per-point slab test; the integral is split where
    the view ray crosses the planes through a box edge parallel to the light (found
    geometrically, independently of the closed form's face-line crossings).
    """
    o, w, t_max = _rays(o, dirs, t_max)
    t0, t1, hit = _medium_interval(o, w, t_max, box_min, box_max)
    ld = _normalize(np.asarray(light_dir, np.float64))
    u = -ld
    lo = np.asarray(box_min, np.float64)
    hi = np.asarray(box_max, np.float64)
    out = np.zeros(w.shape[0])
    for i in np.flatnonzero(hit):
        oi, wi, a, b = o[i], w[i], t0[i], t1[i]
        f = lambda t: math.exp(-kappa * ((t - a) + _exit_distance(oi + t * wi, u, lo, hi)))
        pts = [a] + sorted(t for t in _shadow_edge_crossings(oi, wi, u, lo, hi) if a < t < b) + [b]
        val = 0.0
        for ta, tb in zip(pts[:-1], pts[1:]):
            val += _quad(f, ta, tb, 0.0, epsrel)
        out[i] = float(sigma_s) * float(hg(-(wi @ ld), float(g))) * float(irradiance) * val
    return out


# --------------------------------------------------------------------------------------
# Diffuse surfaces
# --------------------------------------------------------------------------------------
def diffuse_point_lit(albedo, intensity, cos_theta, d, kappa=0.0, d_light=None, t_cam=0.0):
    """Radiance reaching the camera from a Lambertian point lit by a point light.

    ``albedo / pi * I max(cos_theta, 0) / d^2 * exp(-kappa d_light) * exp(-kappa t_cam)``

    ``cos_theta``: cosine between the surface normal and the direction to the light;
    ``d``: distance surface point -> light; ``d_light``: length of the light path that
    lies inside the medium (default ``d``, an unbounded medium); ``t_cam``: length of the
    view path inside the medium. Broadcasts; use ``kappa = 0`` for vacuum. Only the
    surface term: add the in-scattering along the view ray separately.
    """
    d = np.asarray(d, np.float64)
    d_light = d if d_light is None else np.asarray(d_light, np.float64)
    cos_theta = np.maximum(np.asarray(cos_theta, np.float64), 0.0)
    return (np.asarray(albedo, np.float64) / math.pi * intensity * cos_theta / (d * d)
            * np.exp(-kappa * d_light) * np.exp(-kappa * np.asarray(t_cam, np.float64)))


def diffuse_directional_lit(albedo, irradiance, cos_theta, kappa=0.0, s_light=0.0, t_cam=0.0):
    """Lambertian point lit by a directional light:
    ``albedo / pi * E max(cos_theta, 0) * exp(-kappa (s_light + t_cam))``
    (``s_light``/``t_cam``: lengths of the light / view paths inside the medium)."""
    cos_theta = np.maximum(np.asarray(cos_theta, np.float64), 0.0)
    return (np.asarray(albedo, np.float64) / math.pi * irradiance * cos_theta
            * np.exp(-kappa * (np.asarray(s_light, np.float64) + np.asarray(t_cam, np.float64))))
