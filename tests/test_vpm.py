"""Volumetric photon mapping (``vpm``): photon packing, the photon map (the estimators'
balanced point tree), the kNN query and
the gather kernel against plain NumPy/scipy references, photon deposition, and the whole
method against the analytic references (point light in an unbounded medium, directional
light in a bounded box)."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
from reference_checks import assert_matches_reference
from scipy.spatial import cKDTree

from clscatter.device import structs
from clscatter.estimators.segment_tree import POINT_NODE, leaf_ranges
from clscatter.io.stats import Stats
from clscatter.methods.vpm import (
    DevicePhotonMap,
    VolumetricPhotonMapping,
    deposit_photons,
    gather,
    knn_points,
)
from clscatter.methods.vpm import photons as pt
from clscatter.scene import scene_from_dict
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import accumulate_segments, trace_view_paths

try:
    import analytic as A
    from layout import layout_mismatches
except ImportError:  # pragma: no cover
    from tests import analytic as A
    from tests.layout import layout_mismatches

HERE = Path(__file__).resolve().parent


# ---- packing --------------------------------------------------------------------------------
def test_struct_layouts_match(engine):
    assert layout_mismatches(engine, "vpm.h", {"Photon": pt.PHOTON, "PointNode": POINT_NODE}) == []
    assert pt.PHOTON.itemsize == 20 and POINT_NODE.itemsize == 24


def test_rgb9e5_round_trip():
    rng = np.random.default_rng(1)
    # the format's normal range (shared exponent -15..15); the map stores power / W ~ 1
    rgb = rng.random((20000, 3))
    rgb *= np.exp2(rng.uniform(-14, 15, (20000, 1))) / rgb.max(axis=1, keepdims=True)
    rgb[:100, 1:] = 0.0                  # one channel only
    rgb[100] = 0.0
    back = pt.decode_rgb9e5(pt.encode_rgb9e5(rgb))
    # rounding to nearest: error at most half a unit of the shared exponent's 9-bit
    # mantissa, i.e. <= 2^-9 of the largest channel
    err = np.abs(back - rgb).max(axis=1) / np.maximum(rgb.max(axis=1), 1e-300)
    assert err[:100].max() <= 2 ** -9 and err[101:].max() <= 2 ** -9
    assert np.all(back[100] == 0)
    ok = np.arange(len(rgb)) != 100
    assert abs(np.mean((back - rgb)[ok, 0] / rgb[ok].max(axis=1))) < 1e-4   # no systematic bias
    # below the range: absolute error <= half the smallest step, 2^-25
    tiny = rng.random((1000, 3)) * 1e-6
    assert np.abs(pt.decode_rgb9e5(pt.encode_rgb9e5(tiny)) - tiny).max() <= 2 ** -25


def test_octahedral_direction_round_trip():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(20000, 3))
    d = np.concatenate([d, np.eye(3), -np.eye(3), [[1, 1, 1], [-1, -1, -1]]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    back = pt.decode_direction(pt.encode_direction(d))
    ang = np.arccos(np.clip((back * d).sum(1), -1, 1))
    assert ang.max() < 1e-4


# ---- the tree -------------------------------------------------------------------------------
def _random_photons(n, rng, clustered=True):
    pos = rng.random((n, 3))
    if clustered:   # half the photons along a few lines, as lighting rays deposit them
        m = n // 2
        o = rng.random((8, 3))
        d = rng.normal(size=(8, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        k = rng.integers(0, 8, m)
        pos[:m] = o[k] + rng.uniform(-0.5, 0.5, (m, 1)) * d[k] + rng.normal(0, 2e-3, (m, 3))
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    power = rng.uniform(0.2, 1.0, (n, 3)) * 1e-6
    return pos, dirs, power


@pytest.mark.parametrize("n,leaf", [(0, 8), (1, 8), (7, 8), (1000, 1), (5000, 8), (4099, 16)])
def test_tree_structure(n, leaf):
    rng = np.random.default_rng(n)
    pos, dirs, power = _random_photons(n, rng)
    tree = pt.photon_map_of(pos, dirs, power, leaf)
    assert tree.count == n and len(tree.nodes) == 2 ** (tree.levels + 1) - 1
    # the photons are a permutation of the input
    got = tree.positions()
    assert np.array_equal(np.sort(got.view(np.float32).reshape(-1, 3), axis=0),
                          np.sort(pos.astype(np.float32), axis=0))
    if n == 0:
        assert tree.levels == 0
        return
    r = leaf_ranges(n, tree.levels)
    sizes = np.diff(r)
    assert sizes.min() >= min(leaf, n) and sizes.max() <= 2 * leaf
    first = 2 ** tree.levels - 1
    leaf_of = np.repeat(np.arange(2 ** tree.levels), sizes)
    box = tree.nodes[first + leaf_of]
    assert np.all(got >= box["bmin"]) and np.all(got <= box["bmax"])
    inner = np.arange(first)
    for c in (2 * inner + 1, 2 * inner + 2):       # parents contain their children
        assert np.all(tree.nodes["bmin"][inner] <= tree.nodes["bmin"][c])
        assert np.all(tree.nodes["bmax"][inner] >= tree.nodes["bmax"][c])
    # kd split: the two halves of the root are separated along its widest axis
    if tree.levels >= 1:
        ax = np.argmax(pos.max(0) - pos.min(0))
        half = r[2 ** (tree.levels - 1)]
        assert got[:half, ax].max() <= got[half:, ax].min()


# ---- kNN query vs scipy ---------------------------------------------------------------------
def _reference_estimate(tree, kd, q, wo, knn, max_r, g):
    """NumPy version of knn_estimate (vpm.h) with scipy's exact kNN."""
    dist, idx = kd.query(q, k=knn, distance_upper_bound=max_r)
    dist, idx = np.atleast_2d(dist), np.atleast_2d(idx)
    found = np.isfinite(dist)
    count = found.sum(1)
    full = count == knn
    powers, dirs = tree.powers(), tree.directions()
    est = np.zeros((len(q), 3))
    for k in range(knn):                       # over heap slots, vectorised over queries
        use = found[:, k] & ~(full & (k == knn - 1))
        j = np.where(use, idx[:, k], 0)
        f = A.hg((dirs[j] * wo).sum(1), g)
        est += np.where(use[:, None], powers[j] * f[:, None], 0.0)
    r = np.where(full, dist[:, -1], max_r)
    est /= (4 / 3 * math.pi * r ** 3)[:, None]
    return count, np.where(found, idx, -1), est, r


@pytest.mark.parametrize("knn", [2, 8, 33])
def test_knn_kernel_matches_ckdtree(engine, knn):
    rng = np.random.default_rng(knn)
    pos, dirs, power = _random_photons(6000, rng)
    tree = pt.photon_map_of(pos, dirs, power, 8)
    pmap = DevicePhotonMap.upload(engine, tree)
    q = np.concatenate([rng.random((1500, 3)), rng.uniform(-1, 2, (300, 3)),   # some far out
                        tree.positions()[:200] + 1e-4])                      # on photons
    wo = rng.normal(size=q.shape)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    max_r, g = 0.06, 0.5
    count, idx, est = knn_points(engine, pmap, q, wo, knn, max_r, g)
    pmap.free(engine)
    kd = cKDTree(tree.positions().astype(np.float64))
    rcount, ridx, rest, _ = _reference_estimate(tree, kd, q.astype(np.float32).astype(np.float64),
                                             wo, knn, max_r, g)
    assert np.array_equal(count, rcount)
    assert 0 < (count == knn).mean() < 1 and (count == 0).any()      # every regime is exercised
    assert np.array_equal(np.sort(idx, axis=1), np.sort(ridx, axis=1))   # the same neighbours
    np.testing.assert_allclose(est, rest, rtol=2e-4, atol=1e-12 * rest.max())


# ---- photon deposition ----------------------------------------------------------------------
def _segments(n, rng, flux_scale=1.0):
    s = np.zeros(n, structs.LIGHT_SEGMENT)
    a = rng.random((n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = rng.uniform(0.05, 2.0, n)
    s["a"][:, :3] = a
    s["b"][:, :3] = a + L[:, None] * d
    s["flux"][:, :3] = flux_scale * rng.uniform(0.2, 1.0, (n, 1)) * rng.uniform(0.7, 1.0, (n, 3))
    s["ray"] = np.arange(n)
    return s, L


@pytest.mark.parametrize("independent", [False, True])
def test_deposition_is_an_unbiased_track_length_estimate(independent):
    """Both placements are unbiased track-length estimates (first and zeroth moments
    within 4 standard errors over 40 seeds); stratified: total within 1% of the target
    count and power spread < 1%; independent: a Poisson total (mean within 4 standard
    errors of the target, variance = mean within 50%: 40 samples)."""
    rng = np.random.default_rng(3)
    segs, L = _segments(400, rng)
    kappa = np.array([0.8, 1.2, 2.0])
    flux = segs["flux"][:, :3].astype(np.float64)
    a = segs["a"][:, :3].astype(np.float64)
    d = (segs["b"][:, :3] - segs["a"][:, :3]).astype(np.float64) / L[:, None]
    # exact int_0^L Phi(s) ds per channel, and the first moment int Phi(s) x(s) ds
    e = np.exp(-kappa * L[:, None])
    m0 = flux * (1 - e) / kappa
    m1 = flux * (1 - e * (1 + kappa * L[:, None])) / kappa ** 2
    exact = np.concatenate([m0.sum(0), (m0[:, :, None] * a[:, None, :]
                                        + m1[:, :, None] * d[:, None, :]).sum(0).ravel()])
    sums, counts = [], []
    for seed in range(40):
        ph, W = deposit_photons(segs, kappa, 20000, seed, independent=independent)
        power = pt.decode_rgb9e5(ph["power"]) * W
        counts.append(len(ph))
        x = np.stack([ph["x"], ph["y"], ph["z"]], 1).astype(np.float64)
        sums.append(np.concatenate([power.sum(0), (power[:, :, None] * x[:, None, :]).sum(0).ravel()]))
        if seed == 0 and not independent:
            assert abs(len(ph) - 20000) < 0.01 * 20000     # stratified: close to the target
    sums = np.array(sums)
    mean, sem = sums.mean(0), sums.std(0) / math.sqrt(len(sums))
    assert np.all(np.abs(mean - exact) < 4 * sem + 1e-3 * np.abs(exact).max())
    if independent:      # Poisson total: mean 20000, variance 20000
        assert abs(np.mean(counts) - 20000) < 4 * math.sqrt(20000 / len(counts))
        assert np.var(counts) / 20000 == pytest.approx(1.0, abs=0.5)
    else:
        assert np.all(sums[:, :3].std(0) / exact[:3] < 0.01)   # stratified: a small spread


def test_deposition_grey_photons_have_equal_power_and_lie_on_their_segments():
    rng = np.random.default_rng(4)
    segs, L = _segments(300, rng)
    segs["flux"][:, :3] = segs["flux"][:, :1]
    ph, W = deposit_photons(segs, np.array([0.5, 0.5, 0.5]), 5000, 0)
    np.testing.assert_allclose(pt.decode_rgb9e5(ph["power"]) * W, W, rtol=2 ** -9)
    x = np.stack([ph["x"], ph["y"], ph["z"]], 1).astype(np.float64)
    a = segs["a"][:, :3].astype(np.float64)
    d = (segs["b"][:, :3] - segs["a"][:, :3]).astype(np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = np.clip(np.einsum("psk,sk->ps", x[:, None, :] - a[None], d), 0, L)      # (photon, segment)
    dist = np.linalg.norm(x[:, None, :] - (a[None] + s[..., None] * d[None]), axis=2)
    seg = np.argmin(dist, axis=1)
    assert dist[np.arange(len(x)), seg].max() < 1e-5                      # on a segment
    sin = np.linalg.norm(np.cross(pt.decode_direction(ph["dir"]), d[seg]), axis=1)
    assert sin.max() < 1e-4 and np.all(np.einsum("pk,pk->p", pt.decode_direction(ph["dir"]),
                                                 d[seg]) > 0)          # its direction


# ---- the gather kernel vs NumPy -------------------------------------------------------------
def _pcg(v):
    v = np.asarray(v, np.uint64) & 0xFFFFFFFF
    state = (v * 747796405 + 2891336453) & 0xFFFFFFFF
    word = (((state >> ((state >> 28) + 4)) ^ state) * 277803737) & 0xFFFFFFFF
    return ((word >> 22) ^ word) & 0xFFFFFFFF


def _first_uniform(seed, sample, branch):
    s = _pcg(np.uint64(seed) ^ _pcg(np.asarray(sample, np.uint64) ^ _pcg(
        (np.asarray(branch, np.uint64) ^ 0x7F4A7C15) & 0xFFFFFFFF)))
    s = _pcg(s)
    return (s >> 8).astype(np.float64) / 16777216.0


def _ball_in_box(c, r, lo, hi):
    """NumPy version of ball_volume_in_box (vpm.h): the ball's volume times, per axis, the
    fraction left after the caps beyond the box's two faces."""
    ball = 4 / 3 * math.pi * r ** 3
    R = r[:, None]
    c_lo = R - np.clip(c - lo, 0, R)        # cap heights beyond each face
    c_hi = R - np.clip(hi - c, 0, R)
    caps = math.pi * (c_lo ** 2 * (3 * R - c_lo) + c_hi ** 2 * (3 * R - c_hi)) / 3
    return ball * np.prod(np.maximum(1 - caps / ball[:, None], 0), axis=1)


@pytest.mark.parametrize("bounded", [False, True])
def test_gather_kernel_matches_numpy_march(engine, bounded):
    rng = np.random.default_rng(5)
    pos, dirs, power = _random_photons(4000, rng)
    tree = pt.photon_map_of(pos, dirs, power, 8)
    n = 60
    segs = np.zeros(n, structs.VIEW_SEGMENT)
    a = rng.uniform(-0.3, 1.3, (n, 3))
    b = a + rng.normal(size=(n, 3)) * 1.5    # some leave the photons far behind
    segs["a"][:, :3], segs["b"][:, :3] = a, b
    segs["weight"][:, :3] = rng.uniform(0.5, 1.0, (n, 3))
    segs["sample"] = rng.integers(0, 10 ** 6, n)
    segs["branch"] = rng.integers(0, 4, n)
    med = np.zeros((), structs.MEDIUM)
    med["sigma_s"][:3] = [0.3, 0.4, 0.5]
    med["kappa"][:3] = [0.6, 0.9, 1.3]
    med["g"], med["present"] = -0.3, 1
    lo, hi = np.array([0.0, 0.05, 0.0]), np.array([1.0, 0.95, 1.1])
    if bounded:    # the kernel divides by the part of the ball inside this box
        med["bounded"] = 1
        med["bmin"][:3], med["bmax"][:3] = lo, hi
    knn, dx, max_r, seed = 6, 0.05, 0.08, 12345
    pmap = DevicePhotonMap.upload(engine, tree)
    out, work = gather(engine, med, pmap, segs, knn, dx, max_r, seed, per_launch=16)
    pmap.free(engine)

    kd = cKDTree(tree.positions().astype(np.float64))
    u = _first_uniform(seed, segs["sample"], segs["branch"])
    ref = np.zeros((n, 3))
    near = np.zeros(n, int)
    box_lo, box_hi = tree.nodes["bmin"][0] - max_r, tree.nodes["bmax"][0] + max_r
    for i in range(n):     # a handful of segments: the reference loops over them
        L = np.linalg.norm(b[i] - a[i])
        w = (b[i] - a[i]) / L
        t = (np.arange(int(L / dx) + 2) + u[i]) * dx
        t = t[t < L]       # every sample (the kernel skips those far from all photons)
        x = (segs["a"][i, :3] + t[:, None] * w.astype(np.float32)).astype(np.float64)
        _, _, est, r = _reference_estimate(tree, kd, x, np.broadcast_to(-w, x.shape), knn,
                                           max_r, -0.3)
        if bounded:
            est *= (4 / 3 * math.pi * r ** 3 / _ball_in_box(x, r, lo, hi))[:, None]
        T = np.exp(-np.outer(t, med["kappa"][:3]))
        ref[i] = (est * T).sum(0) * dx * med["sigma_s"][:3] * segs["weight"][i, :3]
        near[i] = np.all((x >= box_lo) & (x <= box_hi), axis=1).sum()
    assert (ref > 0).any(axis=1).sum() > n // 3
    np.testing.assert_allclose(out[:, :3], ref, rtol=5e-4, atol=1e-6 * ref.max())
    # samples taken: those within max_r of the photons' box (float rounding at its faces)
    assert np.abs(out[:, 3] - near).max() <= 1 and out[:, 3].sum() < 0.9 * sum(
        len(np.arange(int(np.linalg.norm(b[i] - a[i]) / dx))) for i in range(n))
    assert np.all(work[:, 1] >= 0) and work[:, 1].sum() >= out[:, 3].sum()


# ---- analytic cases -------------------------------------------------------------------------
# The references are evaluated per view segment (the same camera samples the renderer
# traced, in world units) and summed into pixels, so the comparison measures the photon
# map's error alone, not the pixel-sampling noise of 4 spp.
def _vpm_vs_segment_reference(engine, d, reference, **params):
    ps = prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "t"), engine)
    try:
        vp = trace_view_paths(ps, show_progress=False)
        stats = Stats()
        img = VolumetricPhotonMapping(params).run(ps, vp, stats, False).radiance()
    finally:
        ps.release()
    s, fr = vp.segments, ps.frame
    a = s["a"][:, :3] * fr.scale + fr.centre
    b = s["b"][:, :3] * fr.scale + fr.centre
    L = np.linalg.norm(b - a, axis=1)
    val = reference(a, (b - a) / L[:, None], L)[:, None] * s["weight"][:, :3]
    cam = ps.scene.camera
    return img, accumulate_segments(val, s["pixel"], cam.width, cam.height), stats.to_dict()


def test_point_light_unbounded_medium_vs_airlight(engine):
    """kappa = 1 so that the unbounded medium's paths end after ~11.5 units."""
    ss, sa, g, I = 0.5, 0.5, 0.3, 2.0
    light = np.array([0.2, 1.0, 0.1])
    d = {"camera": {"origin": [0.0, 0.6, 3.0], "target": [0.0, 1.0, 0.0], "fov": 60.0,
                    "resolution": [24, 18], "spp": 4},
         "medium": {"sigma_s": ss, "sigma_a": sa, "g": g},
         "lights": [{"type": "point", "position": light.tolist(), "intensity": I}]}
    # no geometry: relative sizes are multiples of 1 scene unit
    img, ref, st = _vpm_vs_segment_reference(
        engine, d, lambda o, w, L: A.airlight_point(o, w, light, I, ss, ss + sa, g, t_max=L,
                                                    method="gauss"),
        photons=600_000, photons_per_ray=4, knn=24, dx=0.02, max_radius=0.5, deposit="stratified")
    assert np.all(np.isfinite(img)) and ref.max() > 0.2        # the light is in view
    # the pixels next to the light hold the 1/h peak of the glow: their value depends on
    # the few photons closest to the light (and the kernel blurs the peak), so they are
    # checked loosely and kept out of the error measure
    iy, ix = np.unravel_index(np.argmax(ref[..., 0]), ref.shape[:2])
    near = np.zeros(ref.shape[:2], bool)
    near[max(iy - 1, 0):iy + 2, max(ix - 1, 0):ix + 2] = True
    assert np.abs(img[near] / ref[near] - 1).max() < 0.3       # measured 3-4% (seeds 0-3)
    # measured relMSE 2.1e-3, the typical lit pixel 2.7 % off, the total 1.4 % high (seed
    # 0; -0.5 % .. +1.4 % over seeds 0-3): 600k photons leave the dim pixels far from the
    # light about as noisy as the planted 5 % noise, and the kernel's excess near the light
    # is as large as the planted 2 % bias, so neither can be caught here (both are, on the
    # bounded box below)
    assert_matches_reference(img[~near], ref[~near], 4e-3, "airlight", exempt={
        "noise": "600k photons: the typical pixel is 2.7 % off",
        "bias": "the kernel's excess near the light is up to 1.4 %, seed to seed"})
    # the kernel averages the 1/d^2 field over its ball, a slight excess near the light
    assert abs(img[~near].sum() / ref[~near].sum() - 1) < 0.03    # measured -0.5% .. +1.4%
    assert st["photons"] > 0.99 * 600_000 and st["gather_steps"] > 0


def test_directional_light_bounded_box_vs_closed_form(engine):
    ss, sa, g, E = 0.8, 0.4, -0.2, 1.5
    lo, hi = np.array([-1.0, 0.0, -0.8]), np.array([1.0, 1.0, 0.8])
    ldir = np.array([0.3, -1.0, -0.2])
    d = {"camera": {"origin": [2.2, 1.6, 3.4], "target": [0.0, 0.4, 0.0], "fov": 45.0,
                    "resolution": [24, 18], "spp": 4},
         "medium": {"sigma_s": ss, "sigma_a": sa, "g": g,
                    "bounds": {"min": lo.tolist(), "max": hi.tolist()}},
         "lights": [{"type": "directional", "direction": ldir.tolist(), "irradiance": E}]}
    ref_fn = lambda o, w, L: A.directional_slab(o, w, ldir, E, ss, ss + sa, g, lo, hi, t_max=L)
    img, ref, _ = _vpm_vs_segment_reference(engine, d, ref_fn, photons=400_000, photons_per_ray=4,
                                            knn=32, dx=0.01, max_radius=0.2, deposit="stratified")
    # measured relMSE 6.5e-4, the typical lit pixel 1.34 % off, the mean 0.7 % low
    assert_matches_reference(img, ref, 1.3e-3, "directional box", per_pixel=0.025, mean_tol=0.015)
    # the kernel's volume is the part of its ball inside the medium box: no deficit along
    # the walls (dividing by the whole ball loses 5-9% here, proportional to r)
    assert abs(img.sum() / ref.sum() - 1) < 0.015              # measured 0.5% low


def test_params_are_validated():
    from clscatter.errors import SceneError

    with pytest.raises(SceneError, match="render.vpm.knn"):
        VolumetricPhotonMapping({"knn": 1})
    with pytest.raises(SceneError, match="render.vpm.dx"):
        VolumetricPhotonMapping({"dx": 0.0})


@pytest.mark.parametrize("depth", [0.01, 0.1, 1.0, 3.0, 10.0])
def test_direct_light_over_optical_depth_against_closed_form(engine, depth):
    """VPM (200k photons, knn 32) on LSG's regime scene (tests/test_lsg.py: a directional
    light through a box of fog of optical depth ``depth`` across, camera outside and
    inside, light along and across the view) against analytic.directional_slab. The
    tolerances follow the spread of the image means over six light seeds (0-5): seen from
    outside within 2 % at every depth (measured 0.988 .. 1.003), from inside within 4 %
    up to optical depth 1 (0.981 .. 1.032) and 10 % at depth 3 (0.948 .. 1.052). From
    inside at depth 10 the camera sees the lit layer, 1/kappa deep, end on through few
    lighting rays, and the mean moved between 0.78 and 1.19 over the seeds (noise, not a
    bias: the kNN estimate uses k - 1 photons over the k-th photon's ball clipped to the
    box): there only that band, widened by its own spread, is asserted."""
    from test_lsg import _slab_mean_ratio, _slab_regime
    for camera, light in [(c, lt) for c in ("outside", "inside") for lt in ("behind", "side")]:
        d = _slab_regime(depth, camera, light)
        d["render"] = {"method": "vpm", "vpm": {"photons": 200_000}}
        ratio = _slab_mean_ratio(engine, d)
        print(f"depth {depth:g} {camera} {light}: mean {ratio:.4f}")
        if camera == "outside":
            assert abs(ratio - 1.0) <= 0.02, (camera, light)
        elif depth > 3.0:
            assert 0.65 <= ratio <= 1.35, (camera, light)     # the noise band 0.78 .. 1.19
        else:
            assert abs(ratio - 1.0) <= (0.04 if depth <= 1.0 else 0.10), (camera, light)


def test_automatic_gather_cap_shrinks_like_the_photon_spacing():
    """``auto_max_radius`` on a Poisson set of photons: AUTO_RADIUS_FACTOR times the median
    distance to the knn-th nearest, whose closed form for density lam is (m / (lam 4/3 pi))^(1/3)
    with m the median of Gamma(knn) (within 10 %: the sample's edges); 8x the photons halve
    it (within 5 %), so a shadow's leak converges. A fixed cap did not shrink: on
    builtin:epi_sun (64 x 48) VPM's mean stayed 11-16 % above ray marching from 250k to 4M
    photons; with the automatic cap 7-10 % (measured), with a cap of 0.003 0.5 %."""
    from scipy.stats import gamma

    from clscatter.methods.vpm import AUTO_RADIUS_FACTOR, auto_max_radius
    rng = np.random.default_rng(3)
    caps = {}
    for n in (20_000, 160_000):
        pts = rng.uniform(-1.0, 1.0, (n, 3))
        caps[n] = auto_max_radius(pts, 32)
        closed = AUTO_RADIUS_FACTOR * (gamma(32).median() / (n / 8.0 * 4.0 / 3.0 * np.pi)) ** (1 / 3)
        assert caps[n] == pytest.approx(closed, rel=0.1), (n, caps[n], closed)
    assert caps[160_000] / caps[20_000] == pytest.approx(0.5, rel=0.05)
    assert auto_max_radius(np.zeros((1, 3)), 32) == 0.0


def test_photons_are_deposited_part_by_part(engine, monkeypatch):
    """Traced and deposited in interleaved parts, the photon map holds the same light as
    in one part: its photon count a Poisson total of the target, its power (the track
    length of the lighting rays' flux) the same within Poisson noise; the working set
    (a deposition's segments and arrays, or the tree build) shrinks."""
    import clscatter.methods.vpm as V

    d = {"camera": {"origin": [0.0, 0.6, 3.0], "target": [0.0, 0.5, 0.0], "fov": 50.0,
                    "resolution": [8, 6], "spp": 1},
         "medium": {"sigma_s": 0.5, "sigma_a": 0.5,
                    "bounds": {"min": [-1.0, 0.0, -1.0], "max": [1.0, 1.0, 1.0]}},
         "lights": [{"type": "spot", "position": [0.0, 2.0, 0.0], "target": [0.0, 0.0, 0.0],
                     "cutoff_angle": 40.0, "intensity": 3.0}]}
    target = 40_000
    out = {}
    for per_part in (1 << 20, 10_000):        # 4 parts, made 5: an odd stride
        monkeypatch.setattr(V, "RAYS_PER_PART", per_part)
        ps = prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "t"), engine)
        try:
            engine.reset_peak()
            stats = Stats()
            tree = VolumetricPhotonMapping({"photons": target}).build_photon_map(ps, stats, False)
            power = pt.decode_rgb9e5(tree.photons["power"]).sum(0) * tree.power_scale
            out[per_part] = (stats.to_dict(), tree.count, power, engine.bytes_peak)
        finally:
            ps.release()
    (one, n1, p1, peak1), (parts, n5, p5, peak5) = out[1 << 20], out[10_000]
    assert one["vpm_parts"] == 1 and parts["vpm_parts"] == 5
    assert one["light_rays"] == parts["light_rays"] == target
    for n in (n1, n5):                                  # Poisson: sd = sqrt(40k) = 200
        assert abs(n - target) < 5 * math.sqrt(target)
    # the power of each photon set is a Poisson sum: relative sd 1/sqrt(40k) = 0.5 %
    np.testing.assert_allclose(p5, p1, rtol=5 * math.sqrt(2.0 / target))
    # measured 0.51x: what stays is the tracer's own append buffer (2 launches of records)
    assert peak5 < 0.6 * peak1
