"""Targeted emission for caustic passes: lighting rays sent only towards specular objects.

A caustic pass (``lsg`` with ``min_light_depth >= 1``, ``vpm`` likewise) uses only the
light that has been reflected or refracted at least once. A lighting ray whose first hit
is not a mirror or a dielectric contributes nothing to it, so the emission may skip every
direction (or, for a directional light, every start point) that cannot reach one, as
photon mappers do with projection maps (Jensen 2001, section 7.4), provided each ray is
weighted by ``1 / pdf`` of the density it was actually drawn from. The estimate of the
caustic light is then unchanged in expectation; only the number of rays it takes changes.

Targets (normalised frame)
    Every mirror or dielectric object is bounded by a sphere (centre of its vertex box,
    radius the farthest vertex, padded by 1e-3 relative + 1e-6 absolute: a triangle lies
    in the convex hull of its vertices, hence inside that sphere).

Point and spot lights: a mixture of cones
    Seen from the light at ``p``, sphere ``(c, R)`` lies in the cone of half-angle
    ``asin(R / |c - p|)`` around ``c - p`` (the whole sphere of directions when ``p`` is
    inside it). A spot light keeps only cones that meet its own cone, and replaces a
    cone by the spot cone when the latter is smaller (the spot cone then covers every
    direction that both allow). Cone ``k`` gets ``n_k`` of the light's ``N`` rays (in
    proportion to its solid angle ``Omega_k``, at least one), drawn stratified and
    uniformly in it. Overlapping cones make this a *multi-sample* mixture, so every ray
    is weighted with the balance heuristic (Veach 1997, section 9.2): a ray in direction
    ``w`` carries flux

        Phi(w) = I / sum_j n_j [w in cone_j] / Omega_j

    (``I``: intensity; ``[w in cone_k]`` always holds for its own cone k), which is
    exactly ``I / (N pdf(w))`` for the mixture pdf and unbiased for any ``n_k``. With a
    single cone covering the whole sphere this is ``4 pi I / N``, the untargeted flux.
    A spot ray outside the spot cone carries nothing and is not traced.

Directional lights: the objects' projected footprint
    The start rectangle (facing the light, as in :func:`emission`: across the beam that
    meets the medium's box and the near triangles, upstream of them and of any far object
    in that beam) is shrunk to the bounding rectangle of the
    spheres' projections onto it; every ray that can hit a specular object starts in it.
    Start points are uniform, so the flux per ray is ``E * area / N`` as before.

``cos`` of a cone is passed as ``1 - cos`` (float64 on the host): the kernel samples
``s = 1 - z = u (1 - cos)`` and forms ``sin = sqrt(s (2 - s))``, which keeps small cones
(a distant glass ball) accurate in float32 where ``1 - z`` would round to a few ulps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device import structs
from ..geometry import box_corners, perpendicular_axes

#: mixtures with more cones than this are merged into one cone per light (the kernel
#: tests every cone for every ray)
MAX_CONES = 8


@dataclass
class Emission:
    power: np.ndarray          # rgb, normalised units
    rect: np.ndarray           # (3, 4) float32: origin, u, v (directional lights only)


def _region(ps, d: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """What the rays of a directional light travelling along unit ``d`` must cover
    (normalised frame): the box of the medium's bounds and the near triangles
    (:meth:`~clscatter.transport.prepared.PreparedScene.near_box`), and the least axial
    coordinate ``x.d`` they must start before: that box's, or a far object's upstream in
    its beam (:meth:`~clscatter.scene.model.Scene.far_in_beam`), whose shadow then falls
    into the box (rays starting that far off place it to float32 steps of that distance)."""
    boxes = []
    if ps.medium["bounded"]:
        boxes.append((ps.medium["bmin"][:3], ps.medium["bmax"][:3]))
    near = ps.near_box()
    if near is not None:
        boxes.append(near)
    if not boxes:
        boxes.append((np.full(3, -1.0), np.full(3, 1.0)))
    lo = np.min([b[0] for b in boxes], axis=0).astype(np.float64)
    hi = np.max([b[1] for b in boxes], axis=0).astype(np.float64)
    far = [box_corners(ps.frame.point(a), ps.frame.point(b))
           for _, a, b in ps.scene.far_in_beam(d)]
    start = np.concatenate([box_corners(lo, hi)] + far) @ d
    return (lo, hi), start


def emission(ps, index: int) -> Emission:
    """Emitted power of light ``index`` and, for a directional light, its start rectangle."""
    L = ps.lights[index]
    I = L["power"][:3].astype(np.float64)
    rect = np.zeros((3, 4), np.float32)
    if L["type"] == structs.LIGHT_POINT:
        return Emission(4 * math.pi * I, rect)
    if L["type"] == structs.LIGHT_SPOT:
        return Emission(2 * math.pi * (1 - float(L["cos_cutoff"])) * I, rect)
    d = L["direction"][:3].astype(np.float64)
    d /= np.linalg.norm(d)
    e1, e2 = perpendicular_axes(d)
    (lo, hi), cd = _region(ps, d)
    corners = box_corners(lo, hi)
    c1, c2 = corners @ e1, corners @ e2
    pad = 1e-3 * float(np.max(hi - lo))
    origin = (c1.min() - pad) * e1 + (c2.min() - pad) * e2 + (cd.min() - pad) * d
    u = (c1.max() - c1.min() + 2 * pad) * e1
    v = (c2.max() - c2.min() + 2 * pad) * e2
    rect[0, :3], rect[1, :3], rect[2, :3] = origin, u, v
    area = float(np.linalg.norm(u) * np.linalg.norm(v))
    return Emission(I * area, rect)


@dataclass
class Targets:
    """The targeted emission of one light (normalised frame)."""

    cones: np.ndarray        # (K, 4) float32: unit axis xyz, w = 1 - cos(half-angle)
    share: np.ndarray        # (K,) float64: fraction of the light's rays per cone (sums to 1)
    power: np.ndarray        # rgb power the targeted rays carry in expectation (allocation)
    rect: np.ndarray | None  # (3, 4) float32 start rectangle (directional lights), else None
    solid_angle: float       # total solid angle of the cones (point/spot), sr

    def counts(self, n: int) -> np.ndarray:
        """Rays per cone for ``n`` rays of this light: largest remainder, >= 1 each when n allows."""
        k = len(self.share)
        if k == 0 or n <= 0:
            return np.zeros(k, np.int64)
        s = self.share * n
        c = np.floor(s).astype(np.int64)
        c[np.argsort(-(s - c))[:n - int(c.sum())]] += 1
        while n >= k and np.any(c == 0):     # every cone must be sampled (the pdf needs it)
            c[np.argmax(c)] -= 1
            c[np.argmin(c)] += 1
        return c


def specular_spheres(ps) -> list[tuple[np.ndarray, float]]:
    """Bounding spheres ``(centre, radius)`` of the mirror and dielectric objects, in the
    normalised frame of ``ps`` (a :class:`~clscatter.transport.prepared.PreparedScene`)."""
    out = []
    for obj in ps.scene.objects:
        if obj.material.type not in ("mirror", "dielectric") or not len(obj.vertices):
            continue
        v = ps.frame.point(obj.vertices)
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        r = float(np.linalg.norm(v - c, axis=1).max())
        out.append((c, r * (1 + 1e-3) + 1e-6))
    return out


def merge_spheres(spheres: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, float]:
    """One sphere holding all of ``spheres`` (centre of their box, farthest reach)."""
    lo = np.min([c - r for c, r in spheres], axis=0)
    hi = np.max([c + r for c, r in spheres], axis=0)
    c = 0.5 * (lo + hi)
    return c, max(float(np.linalg.norm(s - c)) + r for s, r in spheres)


def _cone(p: np.ndarray, c: np.ndarray, r: float) -> tuple[np.ndarray, float, float]:
    """(axis, half-angle, 1 - cos) of the cone from ``p`` holding sphere (c, r)."""
    d = c - p
    dist = float(np.linalg.norm(d))
    if dist <= r:
        return np.array([0.0, 0.0, 1.0]), math.pi, 2.0
    half = math.asin(r / dist)
    omc = (r / dist) ** 2 / (1 + math.sqrt(1 - (r / dist) ** 2))   # 1 - cos, no cancellation
    return d / dist, half, omc


def targets(ps, index: int, spheres: list[tuple[np.ndarray, float]] | None = None) -> Targets:
    """The targeted emission of light ``index`` towards the specular objects of ``ps``."""
    spheres = specular_spheres(ps) if spheres is None else spheres
    L = ps.lights[index]
    I = L["power"][:3].astype(np.float64)
    empty = Targets(np.zeros((0, 4), np.float32), np.zeros(0), np.zeros(3), None, 0.0)
    if not spheres:
        return empty
    if L["type"] == structs.LIGHT_DIRECTIONAL:
        em = emission(ps, index)
        o, u, v = (em.rect[i, :3].astype(np.float64) for i in range(3))
        e1, e2 = u / np.linalg.norm(u), v / np.linalg.norm(v)
        lo1, hi1 = min(float((c - o) @ e1) - r for c, r in spheres), max(float((c - o) @ e1) + r for c, r in spheres)
        lo2, hi2 = min(float((c - o) @ e2) - r for c, r in spheres), max(float((c - o) @ e2) + r for c, r in spheres)
        # within the full rectangle (nothing outside it is lit)
        lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        lo1, hi1, lo2, hi2 = max(lo1, 0.0), min(hi1, lu), max(lo2, 0.0), min(hi2, lv)
        if hi1 <= lo1 or hi2 <= lo2:
            return empty
        rect = np.zeros((3, 4), np.float32)
        rect[0, :3] = o + lo1 * e1 + lo2 * e2
        rect[1, :3] = (hi1 - lo1) * e1
        rect[2, :3] = (hi2 - lo2) * e2
        area = (hi1 - lo1) * (hi2 - lo2)
        return Targets(np.zeros((0, 4), np.float32), np.zeros(0), I * area, rect, 0.0)
    p = L["position"][:3].astype(np.float64)
    if len(spheres) > MAX_CONES:
        spheres = [merge_spheres(spheres)]
    cones = [_cone(p, c, r) for c, r in spheres]
    if L["type"] == structs.LIGHT_SPOT:
        sa = L["direction"][:3].astype(np.float64)
        sa /= np.linalg.norm(sa)
        cc = float(L["cos_cutoff"])
        s_half = math.acos(max(-1.0, min(1.0, cc)))
        s_omc = 1.0 - cc
        kept = []
        for axis, half, omc in cones:
            ang = math.acos(max(-1.0, min(1.0, float(axis @ sa))))
            if half < math.pi and ang >= half + s_half:
                continue                          # the object is outside the spot cone
            kept.append((sa, s_half, s_omc) if s_omc < omc else (axis, half, omc))
        cones = []
        for c in kept:                            # the spot cone once
            if not any(c[0] is d[0] and c[2] == d[2] for d in cones):
                cones.append(c)
    elif any(half >= math.pi for _, half, _ in cones):
        cones = [(np.array([0.0, 0.0, 1.0]), math.pi, 2.0)]   # the light is inside an object
    if not cones:
        return empty
    omega = np.array([2 * math.pi * max(omc, 1e-12) for _, _, omc in cones])
    arr = np.zeros((len(cones), 4), np.float32)
    for k, (axis, _, omc) in enumerate(cones):
        arr[k, :3] = axis
        arr[k, 3] = max(omc, 1e-12)      # > 0: the kernel divides by the cone's solid angle
    total = float(min(omega.sum(), 4 * math.pi))
    return Targets(arr, omega / omega.sum(), I * total, None, total)


def mixture_flux(I: np.ndarray, dirs: np.ndarray, cones: np.ndarray, counts: np.ndarray,
                 own: np.ndarray) -> np.ndarray:
    """NumPy reference of the kernel's flux per targeted ray (float64): ``I / sum_j n_j
    [w in cone_j] / Omega_j`` for unit ``dirs`` (N, 3) drawn from cone ``own`` (N,)."""
    axis = cones[:, :3].astype(np.float64)
    omc = cones[:, 3].astype(np.float64)
    inside = dirs @ axis.T >= 1.0 - omc[None, :]
    inside[np.arange(len(dirs)), own] = True
    dens = (inside * (counts / (2 * math.pi * omc))[None, :]).sum(axis=1)
    return np.asarray(I)[None, :] / dens[:, None]


def targeted_fraction(ps) -> float:
    """Share of all lights' emitted power (mean over rgb) that targeted emission sends
    towards the specular objects: ``light_rays * fraction`` targeted rays carry the same
    flux per ray as ``light_rays`` untargeted ones (the same caustic noise, without the
    rays that cannot make a caustic). 0 when nothing is specular."""
    sph = specular_spheres(ps)
    full = sum(float(emission(ps, i).power.mean()) for i in range(ps.num_lights))
    part = sum(float(targets(ps, i, sph).power.mean()) for i in range(ps.num_lights))
    return min(1.0, part / full) if full > 0 else 0.0
