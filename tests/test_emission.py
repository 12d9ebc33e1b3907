"""Targeted emission (clscatter/transport/emission.py, light_paths.cl with targets): the kernel's
flux per ray against a float64 NumPy evaluation of the mixture pdf, the power the
targeted rays carry against a Monte Carlo solid angle, and whole caustic renders with
and without targeting (same image within the noise, far more caustic segments per ray)."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from clscatter.pipeline.render import render
from clscatter.scene import scene_from_dict
from clscatter.scene.builtin.caustics import CAUSTIC_SCENES
from clscatter.transport.emission import mixture_flux, specular_spheres, targets
from clscatter.transport.light_paths import trace_light_paths
from clscatter.transport.prepared import prepare_scene

HERE = Path(__file__).resolve().parent
CAM = {"origin": [0.0, 0.0, 6.0], "target": [0.0, 0.0, 0.0], "resolution": [8, 8], "spp": 1}
GLASS = {"type": "dielectric", "ior": 1.5}


def _prep(engine, d):
    return prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "t"), engine)


def _spheres_scene(light):
    """Two overlapping glass balls and a distant mirror ball, unbounded medium."""
    return {"camera": CAM, "medium": {"sigma_s": 0.01, "sigma_a": 0.0},
            "lights": [light],
            "objects": [{"shape": "sphere", "center": [0.0, -1.5, 0.0], "radius": 0.5, "material": GLASS},
                        {"shape": "sphere", "center": [0.4, -1.6, 0.2], "radius": 0.4, "material": GLASS},
                        {"shape": "sphere", "center": [2.5, 1.0, -1.0], "radius": 0.3,
                         "material": {"type": "mirror", "reflectance": 0.8}}]}


def _first_dirs(s):
    s0 = s[s["depth"] == 0]
    d = s0["b"][:, :3].astype(np.float64) - s0["a"][:, :3]
    return s0, d / np.linalg.norm(d, axis=1, keepdims=True)


def _hits(p, w, spheres):
    """Which unit directions w from p meet any of the spheres."""
    hit = np.zeros(len(w), bool)
    for c, r in spheres:
        oc = c - p
        tc = w @ oc
        q = oc - tc[:, None] * w
        hit |= (tc > 0) & (np.einsum("ij,ij->i", q, q) <= r * r)
    return hit


def _mc_solid_angle(p, spheres, n=250_000, spot=None, seed=1):
    """Solid angle of the directions from p that meet any of ``spheres`` (and lie in the
    spot cone): uniform directions in a cone around the spheres' centroid that holds
    them all, so the hit fraction is large and 250k samples give ~0.5% noise."""
    rng = np.random.default_rng(seed)
    axis = np.mean([c for c, _ in spheres], axis=0) - p
    axis /= np.linalg.norm(axis)
    half = max(math.acos(min(1.0, float((c - p) @ axis) / np.linalg.norm(c - p)))
               + math.asin(min(1.0, r / np.linalg.norm(c - p))) for c, r in spheres) + 0.01
    z = 1 - rng.random(n) * (1 - math.cos(half))
    phi = 2 * math.pi * rng.random(n)
    t = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    t /= np.linalg.norm(t)
    b = np.cross(axis, t)
    rr = np.sqrt(1 - z * z)
    w = (rr * np.cos(phi))[:, None] * t + (rr * np.sin(phi))[:, None] * b + z[:, None] * axis
    hit = _hits(p, w, spheres)
    if spot is not None:
        hit &= w @ spot[0] >= spot[1]
    return 2 * math.pi * (1 - math.cos(half)) * hit.mean()


@pytest.mark.parametrize("kind", ["point", "spot"])
def test_targeted_flux_matches_numpy_mixture(engine, kind):
    """Every targeted ray's flux equals I / sum_j n_j [w in cone_j] / Omega_j computed in
    float64 (relative 2e-4: float32 dot products on the cone boundaries), every ray lies
    in its own cone, and the flux of the rays towards the balls sums to I times the solid angle they
    cover (union of cones, within the spot cone)
    (Monte Carlo, ~0.5%; bound 1.5%). The cones overlap (two glass
    balls side by side), so the balance heuristic matters: with I / (n_k / Omega_k)
    instead, the total comes out ~10% high."""
    light = {"type": "point", "position": [0.1, 1.5, 0.0], "intensity": 3.0}
    if kind == "spot":
        light = {"type": "spot", "position": [0.1, 1.5, 0.0], "target": [0.2, -1.5, 0.0],
                 "intensity": 3.0, "cutoff_angle": 6.0}
    ps = _prep(engine, _spheres_scene(light))
    tg = targets(ps, 0)
    n = 10_000
    lp = trace_light_paths(ps, n, show_progress=False, targeted=True)
    ps_I = ps.lights[0]["power"][:3].astype(np.float64)
    p = ps.lights[0]["position"][:3].astype(np.float64)
    sph = specular_spheres(ps)
    ps.release()
    counts = tg.counts(int(lp.rays[0]))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    s0, w = _first_dirs(lp.segments)
    own = np.searchsorted(offsets, s0["ray"], side="right") - 1
    axis = tg.cones[own, :3].astype(np.float64)
    assert np.all(np.einsum("ij,ij->i", w, axis) >= 1 - tg.cones[own, 3] - 2e-6)
    ref = mixture_flux(ps_I, w, tg.cones, counts, own)
    got = s0["flux"][:, :3].astype(np.float64)
    same = np.isclose(got, ref, rtol=2e-4).all(axis=1)
    # directions within ~1e-5 of another cone's boundary may round either way (the
    # direction is re-derived here from float32 end points): either side is accepted
    edge = tg.cones.copy()
    for dc in (-2e-5, 2e-5):
        edge[:, 3] = tg.cones[:, 3] + dc
        same |= np.isclose(got, mixture_flux(ps_I, w, edge, counts, own), rtol=2e-4).all(axis=1)
    assert same.all() and np.isclose(got, ref, rtol=2e-4).all(axis=1).mean() > 0.999
    spot = None
    if kind == "spot":
        sa = ps.lights[0]["direction"][:3].astype(np.float64)
        spot = (sa / np.linalg.norm(sa), float(ps.lights[0]["cos_cutoff"]))
        assert len(tg.cones) == 1                  # the spot cone is smaller than the balls'
        assert np.all(w @ spot[0] >= spot[1] - 1e-6)
    # the light towards the two glass balls (their bounding spheres), and the mirror ball
    glass, mirror = sph[:2], sph[2:]
    total = s0["flux"][_hits(p, w, glass), 0].sum()
    assert total / (ps_I[0] * _mc_solid_angle(p, glass, spot=spot)) == pytest.approx(1.0, abs=0.015)
    if kind == "point":
        (c, r), = mirror
        omega = 2 * math.pi * (1 - math.sqrt(1 - (r / np.linalg.norm(c - p)) ** 2))
        total = s0["flux"][_hits(p, w, mirror), 0].sum()
        assert total / (ps_I[0] * omega) == pytest.approx(1.0, abs=0.015)
    # the balls' cones are far smaller than the sphere: most rays reach a specular surface
    assert lp.specular_rays.sum() / lp.rays.sum() > 0.8


def test_directional_footprint_rectangle(engine):
    """A directional light: the start rectangle covers the balls' projections and is
    inside the untargeted one; flux per ray E * area / N; >60% of rays hit glass
    (the projections of the two overlapping discs fill ~70% of their bounding box)."""
    d = _spheres_scene({"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0})
    d["objects"] = d["objects"][:2]
    d["medium"]["bounds"] = {"min": [-3, -3, -3], "max": [3, 3, 3]}
    ps = _prep(engine, d)
    tg = targets(ps, 0)
    lp = trace_light_paths(ps, 20_000, show_progress=False, targeted=True)
    ps.release()
    area = np.linalg.norm(tg.rect[1]) * np.linalg.norm(tg.rect[2])
    s0, w = _first_dirs(lp.segments)
    np.testing.assert_allclose(s0["flux"][:, 0], 2.0 * area / lp.rays[0], rtol=1e-5)
    # the balls span x in [-0.5, 0.8], z in [-0.5, 0.6] (world) -> 1.3 x 1.1 / scale^2
    assert area * ps.frame.scale ** 2 == pytest.approx(1.3 * 1.1, rel=0.01)
    assert lp.specular_rays[0] / lp.rays[0] > 0.6


def _caustic(name, light=None, w=32, h=24):
    d = CAUSTIC_SCENES[name]()
    d["camera"]["resolution"] = [w, h]
    d["camera"]["spp"] = 1
    if light is not None:
        d["lights"] = [light]
    return d


# scene, light, least gain in caustic segments per emitted ray (the gem's spot cone is
# already narrow: it only loses the part of the cone that misses the gem), light_rays
# untargeted / targeted (targeted traces only the part of light_rays aimed at the glass:
# 3x the light_rays give 3x the caustic rays of one untargeted run)
SCENES = {
    "point": ("caustic_sphere", None, 8.0, (120_000, 360_000)),
    "spot": ("caustic_gem", None, 1.1, (20_000, 60_000)),
    "directional": ("caustic_sphere", {"type": "directional", "direction": [0.15, -1.0, 0.1],
                                       "irradiance": 2.0}, 8.0, (120_000, 360_000)),
}


@pytest.mark.parametrize("kind", sorted(SCENES))
def test_targeted_and_untargeted_caustic_passes_agree(engine, kind):
    """The caustic pass (min_light_depth 1) with and without targeting, same radius:
    untargeted (two independent ray sets, same view paths: their MSE e_uu ~ 2 var_u)
    and targeted with >= 3x the caustic rays (var_t <= var_u / 3). If targeting is unbiased, MSE(targeted,
    untargeted) ~ var_u + var_t, well below e_uu; a bias the size of the noise would push
    it above. Bound 0.85 e_uu, and the totals within 3%. Measured e_tu / e_uu: 0.61
    (point), 0.54 (spot), 0.57 (directional), totals within 0.5%.
    Targeted rays make ~50x (point, directional) and 1.2x (spot: its cone is already
    narrow) more caustic segments per emitted ray."""
    name, light, gain, (n_u, n_t) = SCENES[kind]
    d = _caustic(name, light)
    lsg = {"min_light_depth": 1, "radius": 0.01}
    img, st = {}, {}
    for key, rays, tg, seed in (("u0", n_u, False, 0), ("u1", n_u, False, 1), ("t", n_t, True, 0)):
        dd = copy.deepcopy(d)
        dd["render"]["lsg"] = {**lsg, "light_rays": rays, "targeted": tg, "light_seed": seed}
        r = render(scene_from_dict(dd, ".", name), "lsg", engine=engine, show_progress=False)
        img[key], st[key] = r.medium, r.stats
    assert np.isfinite(img["t"]).all() and img["t"].max() > 0
    # MSE normalised by the image mean squared: the test compares the variances of two
    # estimators (no reference image), which relMSE's per-pixel weighting would reshuffle
    nmse = lambda a, b: float(((a - b) ** 2).mean() / b.mean() ** 2)
    e_uu, e_tu = nmse(img["u1"], img["u0"]), nmse(img["t"], img["u0"])
    assert e_tu < 0.85 * e_uu, (e_tu, e_uu)
    ratio = img["t"].sum() / (0.5 * (img["u0"].sum() + img["u1"].sum()))
    assert ratio == pytest.approx(1.0, abs=0.03)
    per_ray = {k: st[k]["light_segments"] / st[k]["light_rays"] for k in st}
    assert per_ray["t"] > gain * per_ray["u0"], per_ray
    # targeted traces only the rays aimed at the glass: ~3x the caustic rays of u0 from
    # 3x light_rays, at a fraction of the traced rays (point: ~2%)
    spec = {k: st[k]["light_rays_specular_fraction"] * st[k]["light_rays"] for k in st}
    assert spec["t"] == pytest.approx(3 * spec["u0"], rel=0.1), spec
    assert (st["t"]["light_rays_specular_fraction"]
            > min(0.9, gain * st["u0"]["light_rays_specular_fraction"]))
