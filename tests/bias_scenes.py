"""Analytic scenes of the ray-map bias study (Havran et al. 2005, Sec. 4.3, Fig. 4): a
convex step edge and a concave corner lit by parallel rays, and a wave-shaped height field
lit by parallel or cosine-distributed rays. Each returns the rays' origins, their hit
points, directions, the flux each carries and which hits land on the lit face the
estimates are taken on. Parallel rays are scaled so that a horizontal face receives
irradiance exactly 1 (on the wave: the cosine of the slope). Shared by the bias tests and
``tools/bench_raymap.py``."""
from __future__ import annotations

import math

import numpy as np

Z = 0.5              # the ray sources span |z| <= Z (the scenes are extruded along z)
D_PAR = np.array([-1.0, -2.0, 0.0]) / math.sqrt(5.0)     # parallel rays, slanting to -x


def _parallel(n, x_lo, x_hi, y0, rng):
    """Rays of direction D_PAR starting on the plane y = y0; flux so that a horizontal
    surface receives irradiance 1."""
    o = np.c_[rng.uniform(x_lo, x_hi, n), np.full(n, y0), rng.uniform(-Z, Z, n)]
    return o, np.tile(D_PAR, (n, 1)), (x_hi - x_lo) * 2 * Z / n


def convex_corner(n, rng):
    """Step edge: top y = 0 (x < 0), side x = 0 (y in [-1, 0], facing +x), ground y = -1."""
    o, d, f = _parallel(n, -1.0, 1.5, 0.5, rng)
    t_top = (0.0 - o[:, 1]) / d[:, 1]
    x_top = o[:, 0] + t_top * d[:, 0]
    t_side = (0.0 - o[:, 0]) / d[:, 0]
    y_side = o[:, 1] + t_side * d[:, 1]
    t_gnd = (-1.0 - o[:, 1]) / d[:, 1]
    t = np.where(x_top <= 0, t_top, np.where((y_side <= 0) & (y_side >= -1), t_side, t_gnd))
    on_top = x_top <= 0
    return o, o + t[:, None] * d, d, f, on_top


def concave_corner(n, rng):
    """Floor y = 0 (x > 0) and wall x = 0 (y in [0, 1], facing +x)."""
    o, d, f = _parallel(n, -0.5, 1.5, 1.0, rng)
    t_floor = (0.0 - o[:, 1]) / d[:, 1]
    x_floor = o[:, 0] + t_floor * d[:, 0]
    t_wall = (0.0 - o[:, 0]) / d[:, 0]
    t = np.where(x_floor >= 0, t_floor, t_wall)
    ok = (x_floor >= 0) | (o[:, 0] >= 0)                  # rays starting behind the wall: none
    return o[ok], (o + t[:, None] * d)[ok], d[ok], f, (x_floor >= 0)[ok]


WAVE_L, WAVE_A = 0.25, 0.03


def wave_y(x):
    return WAVE_A * np.sin(2 * math.pi * x / WAVE_L)


def wave_dy(x):
    return WAVE_A * 2 * math.pi / WAVE_L * np.cos(2 * math.pi * x / WAVE_L)


def wave(n, rng, cosine, roi=None):
    """Height field y = A sin(2 pi x / L) over x in [-1, 1]; rays from y = 0.2, straight down
    (parallel) or cosine-distributed (an area light's indirect-like distribution). ``roi``
    (x0, x1): keep only the rays whose crossing of the slab |y| <= A overlaps it (the
    reference needs only those)."""
    o = np.c_[rng.uniform(-1.0, 1.0, n), np.full(n, 0.2), rng.uniform(-Z, Z, n)]
    if cosine:
        u1, u2 = rng.random(n), rng.random(n)
        r, phi = np.sqrt(u1), 2 * math.pi * u2
        d = np.c_[r * np.cos(phi), -np.sqrt(1 - u1), r * np.sin(phi)]
    else:
        d = np.tile([0.0, -1.0, 0.0], (n, 1))
    flux = 2 * 2 * Z / n
    if roi is not None:
        xa = o[:, 0] + (0.2 - WAVE_A) / -d[:, 1] * d[:, 0]
        xb = o[:, 0] + (0.2 + WAVE_A) / -d[:, 1] * d[:, 0]
        keep = (np.maximum(xa, xb) >= roi[0]) & (np.minimum(xa, xb) <= roi[1])
        o, d = o[keep], d[keep]
        n = len(o)
    # first crossing of the height field: 48 samples across the slab |y| <= A (the wave's
    # phase advances 2 A k tan(theta) there: < pi/4 per sample below 88 degrees), bisection
    t = np.empty(n)
    frac = np.linspace(0.0, 1.0, 49)
    for c in range(0, n, 1 << 17):
        oc, dc = o[c:c + (1 << 17)], d[c:c + (1 << 17)]
        t0 = (0.2 - WAVE_A) / -dc[:, 1]
        t1 = (0.2 + WAVE_A) / -dc[:, 1]
        ts = t0[:, None] + (t1 - t0)[:, None] * frac[None]
        below = oc[:, 1, None] + ts * dc[:, 1, None] <= wave_y(oc[:, 0, None] + ts * dc[:, 0, None])
        first = np.argmax(below, axis=1)
        rows = np.arange(len(oc))
        lo, hi = ts[rows, np.maximum(first - 1, 0)], ts[rows, first]
        for _ in range(25):
            mid = 0.5 * (lo + hi)
            bb = oc[:, 1] + mid * dc[:, 1] <= wave_y(oc[:, 0] + mid * dc[:, 0])
            hi, lo = np.where(bb, mid, hi), np.where(bb, lo, mid)
        t[c:c + (1 << 17)] = hi
    return o, o + t[:, None] * d, d, flux, np.ones(n, bool)
