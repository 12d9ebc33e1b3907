"""Fixed-radius surface estimates splatted from the segments' side
(``clscatter/estimators/disc_splat.py``, ``rm_splat`` in ``cl_kernels/estimators/raymap.cl``):
against a brute-force NumPy sum of the same maths, against the K-nearest kernel with a
radius per query, independent of the order the device adds in, and the tree's boxes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from clscatter.estimators.disc_splat import HitDiscs, flux_bound, splat_on_device
from clscatter.estimators.fixed_sum import fixed_scale
from clscatter.estimators.knn_queries import RayMap, plane_dist, qualifying_np
from clscatter.estimators.ray_density import DensitySettings, estimate_on_device
from clscatter.estimators.segment_tree import TreeParams


def _rays(rng, m):
    """Rays falling onto y = 0 from above: some end short of it, some pass it."""
    b = np.c_[rng.uniform(-0.5, 0.5, m), rng.uniform(-0.05, 0.02, m), rng.uniform(-0.5, 0.5, m)]
    d = np.c_[rng.normal(0, 0.4, m), -np.ones(m), rng.normal(0, 0.4, m)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = b - rng.uniform(0.1, 0.6, m)[:, None] * d
    return a, b, d, rng.uniform(0.5, 1.5, (m, 3))


def _hits(rng, nq):
    """Hits on y = 0 and on a tilted plane through the same region, normals varied."""
    x = np.c_[rng.uniform(-0.4, 0.4, nq), np.zeros(nq), rng.uniform(-0.4, 0.4, nq)]
    n = np.tile([0.0, 1.0, 0.0], (nq, 1))
    half = nq // 2
    x[half:, 1] = 0.3 * x[half:, 0]
    n[half:] = np.array([-0.3, 1.0, 0.0]) / math.hypot(0.3, 1.0)
    return x, n


def _splat_np(estimator, kernel, x, n, a, b, d, flux, R):
    """Eq. (1) at a fixed radius: every qualifying segment, float64, brute force."""
    metric = "hemidisc" if estimator == "raymap" else "segment"
    domain = "hemisphere" if estimator == "raymap" else "sphere"
    pa = b if estimator == "photonmap" else a
    v, ok = qualifying_np(metric, x, n, pa, b, d, domain, R, incoming=True)
    idx = np.flatnonzero(ok)
    if estimator == "raymap":
        v = plane_dist(np.broadcast_to(x, (len(a), 3)), np.broadcast_to(n, (len(a), 3)), a, d)
    t = np.minimum(v[idx] / R, 1.0)
    w = 2 * (1 - t * t) if kernel == "epanechnikov" else np.ones_like(t)
    return (w[:, None] * flux[idx]).sum(0) / (math.pi * R * R)


def _splat(engine, estimator, kernel, x, n, a, b, d, flux, radii):
    discs = HitDiscs.build(engine, x, n)
    try:
        e_buf, work = splat_on_device(discs, a, b, d, flux, radii, estimator, kernel)
        got = engine.read(e_buf, (len(x), 4), np.float32)
        engine.free(e_buf)
    finally:
        discs.release()
    return got, work


@pytest.mark.parametrize("estimator", ["raymap", "photonmap"])
@pytest.mark.parametrize("kernel", ["epanechnikov", "box"])
def test_splat_matches_numpy(engine, estimator, kernel):
    """3000 segments, 300 hits with radii 0.02-0.12 on two planes: every hit's estimate
    equals the brute-force sum within rtol 2e-4 (float32 distances near the boundary),
    the w channel is 0, and the tree culled: fewer hits tested than segments x hits / 4."""
    rng = np.random.default_rng(5)
    a, b, d, flux = _rays(rng, 3000)
    x, n = _hits(rng, 300)
    radii = rng.uniform(0.02, 0.12, len(x))
    got, work = _splat(engine, estimator, kernel, x, n, a, b, d, flux, radii)
    want = np.array([_splat_np(estimator, kernel, x[q], n[q], a, b, d, flux, radii[q])
                     for q in range(len(x))])
    assert np.mean(want.max(axis=1) > 0) > 0.8
    assert np.allclose(got[:, :3], want, rtol=2e-4, atol=1e-6 * want.max())
    assert np.all(got[:, 3] == 0)
    assert 0 < work[1] < len(a) * len(x) / 4


@pytest.mark.parametrize("estimator", ["raymap", "photonmap"])
def test_splat_agrees_with_the_k_nearest_kernel(engine, estimator):
    """Where fewer than K segments lie within a hit's radius the K-nearest kernel with a
    radius per query (rm_density) gathers all of them too: the two estimates agree to
    float32 rounding (rtol 1e-4)."""
    rng = np.random.default_rng(8)
    a, b, d, flux = _rays(rng, 2000)
    x, n = _hits(rng, 64)
    radii = rng.uniform(0.02, 0.06, len(x)).astype(np.float32)
    got, _ = _splat(engine, estimator, "epanechnikov", x, n, a, b, d, flux, radii)
    s = DensitySettings(k=256, kernel="epanechnikov", max_radius=0.5, batch=32,
                        tree=TreeParams(c_min=16, alpha_deg=10.0, dir_min_depth=2,
                                        dir_max_diag=1.0))
    rm = RayMap(engine, a, b, d, flux, s.tree, points=estimator == "photonmap", lazy=True)
    r_buf = engine.empty(4 * len(x))
    e_buf, w_buf = estimate_on_device(rm, x, n, estimator, s, radii=radii, out_r=r_buf)
    ref = engine.read(e_buf, (len(x), 4), np.float32)[:, :3]
    got_r = engine.read(r_buf, len(x), np.float32)
    engine.free(e_buf, w_buf, r_buf)
    rm.release()
    assert np.all(got_r == radii)                    # no heap filled: all gathered
    assert ref.max() > 0
    assert np.allclose(got[:, :3], ref, rtol=1e-4, atol=1e-6 * ref.max())


def test_splat_does_not_depend_on_the_order_of_adding(engine):
    """The fixed-point sums are exact: the same segments in reverse order give bit-equal
    estimates (a float sum would differ in its last bits)."""
    rng = np.random.default_rng(2)
    a, b, d, flux = _rays(rng, 5000)
    x, n = _hits(rng, 200)
    radii = np.full(len(x), 0.15)
    one, _ = _splat(engine, "raymap", "epanechnikov", x, n, a, b, d, flux, radii)
    rev, _ = _splat(engine, "raymap", "epanechnikov", x, n, a[::-1], b[::-1], d[::-1],
                    flux[::-1], radii)
    assert one[:, :3].max() > 0
    assert np.array_equal(one, rev)


def test_fixed_scale_bounds_every_sum():
    """No hit's sum (at most every segment's largest channel times the largest weight, 2)
    reaches 2^62 units, and a scene without light keeps the scale finite."""
    flux = np.array([[1.0, 2.0, 0.5], [3.0, 0.0, 0.0]])
    assert flux_bound(flux) == 2.0 * (2.0 + 3.0)
    assert flux_bound(flux) * fixed_scale(flux_bound(flux)) == pytest.approx(2.0 ** 62)
    for empty in (np.zeros((0, 3)), np.zeros((4, 3))):
        s = fixed_scale(flux_bound(empty))
        assert np.isfinite(s) and np.float32(s) < np.inf and np.float32(1 / s) > 0


def test_hit_boxes_hold_every_ball(engine):
    """Each leaf's box holds the balls x +- R of its hits (tree order) and every parent
    holds its children; no hits make one empty root."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(1000, 3))
    discs = HitDiscs.build(engine, x, np.tile([0.0, 0.0, 1.0], (1000, 1)))
    r = rng.uniform(0.01, 0.3, 1000)
    nodes = discs.boxes(r)
    first = (1 << discs.levels) - 1
    starts = (np.arange((1 << discs.levels) + 1) * 1000) >> discs.levels
    for j in range(1 << discs.levels):
        sl = slice(starts[j], starts[j + 1])
        assert np.all(nodes["bmin"][first + j] <= (discs.x[sl] - r[sl, None]).min(0))
        assert np.all(nodes["bmax"][first + j] >= (discs.x[sl] + r[sl, None]).max(0))
    child = np.arange(1, len(nodes))
    assert np.all(nodes["bmin"][(child - 1) // 2] <= nodes["bmin"][child])
    assert np.all(nodes["bmax"][(child - 1) // 2] >= nodes["bmax"][child])
    discs.release()
    empty = HitDiscs.build(engine, np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty.boxes(np.zeros(0))) == 1 and empty.boxes(np.zeros(0))["bmin"][0, 0] > 1e29
    empty.release()
