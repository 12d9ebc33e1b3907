"""Surface density estimation (rm_density) against a NumPy reference of the same maths, and
the glass-ball caustic: the power both estimators put on the floor equals the power the
ball refracts and reflects onto it, computed independently (exact sphere, NumPy)."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from clscatter.estimators.knn_queries import RayMap, knn_np, plane_dist
from clscatter.estimators.ray_density import (
    DensitySettings,
    build_map,
    caustic_pieces,
    estimate,
)
from clscatter.estimators.segment_tree import TreeParams
from clscatter.scene import scene_from_dict
from clscatter.transport.prepared import prepare_scene

HERE = Path(__file__).resolve().parent


def _density_np(estimator, x, n, a, b, d, flux, k, radius, kernel):
    """Eq. (1) with the kernel's conventions (raymap.cl header), float64, brute force."""
    metric = "hemidisc" if estimator == "raymap" else "segment"
    domain = "hemisphere" if estimator == "raymap" else "sphere"
    idx, dist = knn_np(metric, x, n, a, b, d, k, domain, radius, incoming=True)
    if len(idx) == 0:
        return np.zeros(3)
    full = len(idx) == k
    R = dist[-1] if full else radius
    if estimator == "raymap":
        dist = plane_dist(np.broadcast_to(x, (len(idx), 3)), np.broadcast_to(n, (len(idx), 3)),
                          a[idx], d[idx])
    t = np.minimum(dist / R, 1.0)
    w = 2 * (1 - t * t) if kernel == "epanechnikov" else np.ones_like(t)
    if full and kernel == "box":
        w[-1] = 0.0                                   # the K-th lies on the boundary
    return (w[:, None] * flux[idx]).sum(0) / (math.pi * R * R)


@pytest.mark.parametrize("estimator", ["raymap", "photonmap"])
@pytest.mark.parametrize("kernel", ["epanechnikov", "box"])
def test_density_kernel_matches_numpy(engine, estimator, kernel):
    rng = np.random.default_rng(11)
    m = 4000
    # rays falling onto the plane y = 0 from above (some end short of it, some pass it)
    b = np.c_[rng.uniform(-0.5, 0.5, m), rng.uniform(-0.05, 0.02, m), rng.uniform(-0.5, 0.5, m)]
    d = np.c_[rng.normal(0, 0.4, m), -np.ones(m), rng.normal(0, 0.4, m)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = b - rng.uniform(0.1, 0.6, m)[:, None] * d
    flux = rng.uniform(0.5, 1.5, (m, 3))
    x = np.c_[rng.uniform(-0.4, 0.4, 64), np.zeros(64), rng.uniform(-0.4, 0.4, 64)]
    n = np.tile([0.0, 1.0, 0.0], (64, 1))
    s = DensitySettings(k=32, kernel=kernel, max_radius=0.08, batch=40,
                        tree=TreeParams(c_min=16, alpha_deg=10.0, dir_min_depth=2, dir_max_diag=1.0))
    rm = RayMap(engine, a, b, d, flux, s.tree, points=estimator == "photonmap", lazy=True)
    got, work = estimate(rm, x, n, estimator, s)
    rm.release()
    pts_a = b if estimator == "photonmap" else a
    want = np.array([_density_np(estimator, x[q], n[q], pts_a, b, d, flux, 32, 0.08, kernel)
                     for q in range(len(x))])
    assert want.min() > 0
    assert np.allclose(got, want, rtol=2e-4, atol=0)
    assert np.all(work[:, 1] < m / 4)                  # the tree prunes


# ---- the glass ball over a floor ----
E_SUN, R_BALL, Y_BALL, IOR, HALF = 1.0, 0.5, 1.0, 1.5, 1.0
BALL = {"camera": {"origin": [0.0, 3.0, 3.0], "target": [0.0, 0.0, 0.0], "resolution": [8, 8], "spp": 1},
        "lights": [{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": E_SUN}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                      "glass": {"type": "dielectric", "ior": IOR}},
        "objects": [{"shape": "quad", "origin": [-HALF, 0.0, -HALF], "edge_u": [2 * HALF, 0.0, 0.0],
                     "edge_v": [0.0, 0.0, 2 * HALF], "material": "floor"},
                    {"shape": "sphere", "center": [0.0, Y_BALL, 0.0], "radius": R_BALL,
                     "material": "glass"}],
        "render": {"max_depth": 16}}


def _fresnel(cos_i, eta):
    sin2_t = eta * eta * np.maximum(0.0, 1 - cos_i * cos_i)
    tir = sin2_t >= 1
    cos_t = np.sqrt(np.maximum(0.0, 1 - sin2_t))
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp)), cos_t


def ball_power_on_floor(n_rings=4000, max_depth=16, min_flux=1e-4):
    """Power (W) that reaches the floor quad from the sun through an exact glass sphere
    (any number of internal bounces, Fresnel split, no absorption), by deterministic
    rings over the ball's cross-section (each ring's rays are equivalent by symmetry,
    except for where they land on the square floor: 64 azimuths per ring)."""
    r = np.sqrt((np.arange(n_rings) + 0.5) / n_rings) * R_BALL        # equal-area rings
    phi = (np.arange(64) + 0.5) / 64 * 2 * np.pi
    rr, pp = np.meshgrid(r, phi, indexing="ij")
    rr, pp = rr.ravel(), pp.ravel()
    flux = np.full(len(rr), E_SUN * math.pi * R_BALL ** 2 / len(rr))
    c = np.array([0.0, Y_BALL, 0.0])
    o = np.c_[rr * np.cos(pp), np.full(len(rr), Y_BALL + 2 * R_BALL), rr * np.sin(pp)]
    d = np.tile([0.0, -1.0, 0.0], (len(rr), 1))
    inside = np.zeros(len(rr), bool)
    depth = np.zeros(len(rr), int)
    total = 0.0
    f0 = flux[0]                    # children below min_flux of a ray's flux are dropped, as
    while len(o):                   # in specular_children
        # the sphere along each ray (far root inside, near root outside)
        oc = o - c
        bq = np.einsum("ij,ij->i", oc, d)
        cq = np.einsum("ij,ij->i", oc, oc) - R_BALL ** 2
        disc = bq * bq - cq
        sq = np.sqrt(np.maximum(disc, 0))
        t = np.where(inside, -bq + sq, -bq - sq)
        hit = (disc > 0) & (t > 1e-9)
        # rays that miss the sphere: onto the floor (if going down and landing on the quad)
        gone = ~hit
        down = gone & (d[:, 1] < 0) & (depth >= 1)
        tf = -o[down, 1] / d[down, 1]
        land = o[down] + tf[:, None] * d[down]
        on = (np.abs(land[:, 0]) <= HALF) & (np.abs(land[:, 2]) <= HALF)
        total += flux[down][on].sum()
        keep = hit & (depth < max_depth)
        o, d, flux, inside, depth, t = o[keep], d[keep], flux[keep], inside[keep], depth[keep], t[keep]
        p = o + t[:, None] * d
        nrm = (p - c) / R_BALL
        nf = np.where(inside[:, None], -nrm, nrm)          # facing the incoming ray
        cos_i = -np.einsum("ij,ij->i", d, nf)
        eta = np.where(inside, IOR, 1 / IOR)
        F, cos_t = _fresnel(cos_i, eta)
        refl = d + 2 * cos_i[:, None] * nf
        refr = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * nf
        kr = flux * F > min_flux * f0
        kt = (F < 1) & (flux * (1 - F) > min_flux * f0)
        o = np.concatenate([p[kr], p[kt]])
        d = np.concatenate([refl[kr], refr[kt]])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        inside = np.concatenate([inside[kr], ~inside[kt]])
        depth = np.concatenate([depth[kr] + 1, depth[kt] + 1])
        flux = np.concatenate([flux[kr] * F[kr], flux[kt] * (1 - F[kt])])
    return total


def test_exact_ball_power_is_plausible():
    p = ball_power_on_floor(n_rings=400)
    # most of what enters the ball leaves it downwards: between the first-surface
    # transmission of normal incidence (96%) and the Fresnel-averaged transmission (~90%)
    # of pi R^2 E, less what misses the floor
    assert 0.8 * math.pi * R_BALL ** 2 < p < 0.96 * math.pi * R_BALL ** 2


def test_glass_ball_caustic_power_matches_independent_trace(engine):
    expected = ball_power_on_floor(n_rings=1500)
    ps = prepare_scene(scene_from_dict(copy.deepcopy(BALL), HERE, "t"), engine)
    pieces = caustic_pieces(ps, 40_000, show_progress=False)     # targeted: all hit the ball
    s = ps.frame.scale
    y0 = ps.frame.point([0.0, 0.0, 0.0])[1]
    # a grid of floor points (the whole quad), each with its area
    h = 2 * HALF / 120
    g = (np.arange(120) + 0.5) * h - HALF
    X, Z = np.meshgrid(g, g)
    x = np.c_[X.ravel() / s, np.full(X.size, y0), Z.ravel() / s]
    x[:, [0, 2]] -= ps.frame.centre[[0, 2]] / s
    n = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    totals = {}
    for est in ("photonmap", "raymap"):
        st = DensitySettings(k=64, max_radius=0.05 / s)
        rm = build_map(engine, pieces, est, st)
        e, _ = estimate(rm, x, n, est, st)
        rm.release()
        totals[est] = e[:, 0].sum() * (h / s) ** 2 * s ** 2       # normalised flux -> W
    ps.release()
    # the light tracer's own tally of what lands on the floor (same rays as the estimates)
    traced = pieces["flux"][pieces["end"] == 0, 0].sum() * s ** 2
    assert abs(traced / expected - 1) < 0.01          # icosphere vs exact sphere
    for est, tot in totals.items():
        assert abs(tot / expected - 1) < 0.015, (est, tot, expected)


@pytest.mark.parametrize("estimator", ["raymap", "photonmap"])
def test_candidate_list_reuse_is_exact(engine, estimator):
    """Coherent queries (a fine line of points) reusing the first query's leaf list give
    the estimates of independent queries; most of them skip the tree walk."""
    rng = np.random.default_rng(12)
    m = 6000
    b = np.c_[rng.uniform(-0.5, 0.5, m), np.zeros(m), rng.uniform(-0.5, 0.5, m)]
    d = np.c_[rng.normal(0, 0.3, m), -np.ones(m), rng.normal(0, 0.3, m)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = b - 0.3 * d
    flux = rng.uniform(0.5, 1.5, (m, 3))
    t = np.linspace(-0.3, 0.3, 512)
    x = np.c_[t, np.zeros_like(t), 0.1 * np.sin(7 * t)]
    n = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    out = []
    for run, eps in ((1, 0.0), (8, 0.01)):
        s = DensitySettings(k=32, max_radius=0.1, run=run, reuse_eps=eps, lazy=False)
        rm = RayMap(engine, a, b, d, flux, s.tree, points=estimator == "photonmap", lazy=False)
        out.append(estimate(rm, x, n, estimator, s))
        rm.release()
    (e1, w1), (e2, w2) = out
    assert np.allclose(e1, e2, rtol=1e-5, atol=0)
    reused = w2[:, 0] == 0
    assert reused.mean() > 0.5 and np.all(w1[:, 0] > 0)
