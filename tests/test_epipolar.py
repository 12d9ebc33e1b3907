"""Epipolar method, kernel level: struct layout, the Fenwick tree against cumsum, the sinh
slice placement, the SVD, and every kernel of epipolar.cl against a NumPy version of the
same maths (clscatter/methods/epipolar, cl_kernels/epipolar.cl)."""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from layout import layout_mismatches

from clscatter.accel.bvh import build_bvh, trace
from clscatter.device import structs
from clscatter.methods.epipolar import geometry as geo
from clscatter.methods.epipolar import svd

EPI_STRUCTS = {"EpiFrame": geo.EPI_FRAME, "EpiSlice": geo.EPI_SLICE, "EpiFace": geo.EPI_FACE}
from clscatter.scene.model import Camera
from clscatter.scene.normalised import Frame, camera_struct

DEF1 = {"EPI_NT": 4, "EPI_NCH": 1}
F32_EPS = 2.0 ** -24


# ---------------------------------------------------------------------------------------
# helpers

def _camera(eye, target, w=64, h=48, fov=55.0):
    c = Camera(np.asarray(eye, float), np.asarray(target, float), np.array([0.0, 1.0, 0.0]),
               fov, "x", w, h, 1)
    s = camera_struct(c, Frame(np.zeros(3), 1.0))
    return s, geo.CameraGeom.from_struct(s)


def _light(kind, direction=None, position=None, cutoff=30.0):
    l = np.zeros((), structs.LIGHT)
    if kind == "dir":
        l["type"] = structs.LIGHT_DIRECTIONAL
        l["direction"] = structs.vec4(np.asarray(direction) / np.linalg.norm(direction))
    else:
        l["type"] = structs.LIGHT_SPOT
        l["position"] = structs.vec4(position)
        l["direction"] = structs.vec4(np.asarray(direction) / np.linalg.norm(direction))
        l["cos_cutoff"] = math.cos(math.radians(cutoff))
    l["power"] = structs.vec4([1.0, 1.0, 1.0])
    return l


def _medium(box=((-0.5, 0.0, -0.5), (0.5, 0.4, 0.5)), kappa=(0.8, 0.8, 0.8)):
    m = np.zeros((), structs.MEDIUM)
    m["present"], m["bounded"] = 1, 1
    m["bmin"], m["bmax"] = structs.vec4(box[0]), structs.vec4(box[1])
    m["kappa"] = structs.vec4(kappa)
    m["sigma_s"] = structs.vec4(kappa)
    return m


def _setup(kind="dir", eye=(0.1, 0.2, 1.2), target=(0.0, 0.15, 0.0), d=64, w=64, h=48, **kw):
    cam_s, cam = _camera(eye, target, w, h)
    if kind == "dir":
        light = _light("dir", direction=kw.get("direction", (0.5, -1.0, 0.3)))
    else:
        light = _light("spot", direction=kw.get("direction", (0.2, -1.0, -0.1)),
                       position=kw.get("position", (-0.1, 0.7, 0.05)), cutoff=kw.get("cutoff", 30.0))
    med = _medium()
    axis = geo.make_axis(light, cam.origin)
    slices = geo.make_slices(axis, cam, geo.medium_box(med), 1.0, kw.get("ring", 0.0))
    frame = geo.frame_struct(axis, med, d)
    return cam_s, cam, light, med, axis, slices, frame


# ---------------------------------------------------------------------------------------
# structs

def test_struct_layouts_match(engine):
    bad = layout_mismatches(engine, "epipolar.h", EPI_STRUCTS)
    assert not bad, f"layout mismatches (struct, field, host, device): {bad}"
    assert all(dt.itemsize % 16 == 0 for dt in EPI_STRUCTS.values())


# ---------------------------------------------------------------------------------------
# Fenwick tree

def _run_fenwick(engine, init, ops, nch):
    ntree, d, nv = init.shape
    nq = int((ops[:, 0] == 1).sum())
    from clscatter.device import add_kernel_dir
    add_kernel_dir(Path(__file__).parent / "kernels")      # the test-only hook, fenwick.cl
    k = engine.kernel("fenwick", "fenwick_test", {"EPI_NT": nv // nch, "EPI_NCH": nch})
    bufs = [engine.to_device(init), engine.to_device(ops), engine.empty(init.nbytes),
            engine.empty(init.nbytes), engine.empty(4 * ntree * nq * nv)]
    engine.launch(k, ntree, np.int32(ntree), np.int32(d), bufs[0], bufs[1], np.int32(len(ops)), np.int32(nq),
                  bufs[2], bufs[3], bufs[4])
    out = engine.read(bufs[4], (ntree, nq, nv), np.float32)
    engine.free(*bufs)
    return out


def _fenwick_reference(init, ops):
    """float64 replay: current leaves, prefix sums at continuous m by cumsum + lerp."""
    cur = init.astype(np.float64).copy()
    res = []
    d = init.shape[1]
    for kind, a, frac, _ in ops:
        if kind == 0:
            i = int(a)
            cur[:, i] = 0.0 if frac >= 1.0 else cur[:, i] * (1.0 - np.float64(np.float32(frac)))
        else:
            m = min(max(float(a), 0.0), d)
            k = int(math.floor(m))
            val = cur[:, :k].sum(axis=1)
            if k < d:
                val = val + (m - k) * cur[:, k]
            res.append(val)
    return np.stack(res, axis=1)


@pytest.mark.parametrize("d,nch", [(4096, 1), (1000, 3)])
def test_fenwick_long_sweep_matches_cumsum(engine, d, nch):
    """Every leaf removed in three fractional steps (1/4, then 1/3 of the rest, then all)
    in random order, a query at a random continuous index after every step. Bound on
    the float32 error: 8 log2(d) eps sum|b| per component (accumulation along the
    log2(d) nodes of a query, each node a sum that received up to d updates; measured
    about 2e-6 sum|b| at d = 4096, the bound is 5.7e-6)."""
    rng = np.random.default_rng(d)
    nv = 4 * nch
    init = rng.uniform(0.1, 1.0, (2, d, nv)).astype(np.float32)
    init[1, :, 1:] -= 0.55                                  # SVD terms change sign
    ops = []
    for i in rng.permutation(d):
        for frac in (0.25, 1.0 / 3.0, 1.0):
            ops.append((0, i, frac, 0))
            ops.append((1, rng.uniform(-1.0, d + 1.0), 0, 0))
    ops = np.array(ops, np.float32)
    got = _run_fenwick(engine, init, ops, nch)
    ref = _fenwick_reference(init, ops)
    scale = np.abs(init.astype(np.float64)).sum(axis=1)[:, None, :]
    err = np.abs(got - ref) / scale
    bound = 8 * math.log2(d) * F32_EPS
    assert err.max() <= bound, f"max error {err.max():.3g} sum|b| > bound {bound:.3g}"
    # the sweep ends with every leaf zeroed: queries must then be ~0
    assert np.abs(got[:, -1]).max() <= bound * scale.max()


def test_fenwick_exact_on_integers(engine):
    """Small integers add exactly in float32: build, zeroing updates and integer queries
    must equal cumsum to the last bit (d = 37, not a power of two)."""
    rng = np.random.default_rng(5)
    d = 37
    init = rng.integers(-50, 50, (3, d, 4)).astype(np.float32)
    ops = [(1, m, 0, 0) for m in range(d + 1)]
    for i in rng.permutation(d)[:20]:
        ops.append((0, i, 1.0, 0))
        ops += [(1, m, 0, 0) for m in (0, 5, 17, 36, 37)]
    ops = np.array(ops, np.float32)
    got = _run_fenwick(engine, init, ops, 1)
    ref = _fenwick_reference(init, ops)
    assert np.array_equal(got, ref.astype(np.float32))


# ---------------------------------------------------------------------------------------
# slice placement (Sec. 8)

_EPIPOLES = [(32, 24), (0.3, 0.2), (0, 0), (64, 48), (63.9, 0.1), (32, 48), (-10, 20),
             (100, -50), (-300, -200), (32, -1e6), (1e9, 3.0), (70, 24)]


@pytest.mark.parametrize("fov,aspect", [(40.0, 4 / 3), (100.0, 16 / 9), (10.0, 1.0)])
def test_min_angle_to_the_image_is_a_tight_lower_bound(fov, aspect):
    """CameraGeom.min_angle_to: 0 for directions in view; else at most, and within two
    border steps of, the least angle to directions on a fine grid over the image."""
    from clscatter.methods.epipolar.geometry import CameraGeom
    tx = math.tan(math.radians(fov) / 2)
    fwd, right, up = np.array([0.2, 0.1, 1.0]), np.array([1.0, 0.0, -0.2]), None
    fwd /= np.linalg.norm(fwd)
    right -= (right @ fwd) * fwd
    right /= np.linalg.norm(right)
    up = np.cross(fwd, right)
    w, h = 64, max(1, int(round(64 / aspect)))
    cam = CameraGeom(np.zeros(3), fwd, right * tx, up * tx / aspect, w, h)
    g = np.linspace(0.0, 1.0, 401)
    xy = np.stack(np.meshgrid(g * w, g * h), -1).reshape(-1, 2)
    dirs = cam.direction(xy)
    rng = np.random.default_rng(3)
    a_all = rng.normal(size=(300, 3))
    a_all /= np.linalg.norm(a_all, axis=1, keepdims=True)
    a_all = np.concatenate([a_all, [fwd, -fwd, cam.direction(np.array([[w, h]]))[0]]])
    step = 4 * (math.radians(fov) / 512)
    for a in a_all:
        got = cam.min_angle_to(a)
        grid = float(np.arccos(np.clip(dirs @ a, -1, 1)).min())
        if a @ fwd > 0:
            x, y = cam.project(a)[0]
            if 0 <= x <= w and 0 <= y <= h:
                assert got == 0.0
                continue
        assert got <= grid + 1e-12
        assert got >= grid - step - 2 * math.radians(fov) / 400, (a, got, grid)


@pytest.mark.parametrize("size", [(64, 48), (97, 61)])
def test_sinh_slices_half_pixel(size):
    """Every pixel centre lies within half a pixel of a slice line, for epipoles inside,
    in corners, on edges, just outside, far outside and at (near) infinity."""
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w]
    xy = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1).astype(np.float64)
    for P in _EPIPOLES:
        P = np.array(P, np.float64)
        pts = geo.slice_points(P, w, h)
        dist = geo.line_distance(P, pts, xy)
        assert dist.max() <= 0.5, f"epipole {P}: a pixel is {dist.max():.3f} px from every slice"


def test_sinh_slices_fewer_than_uniform():
    """The paper: fewer slices than one per border pixel (about half with the epipole in a
    corner, ~15 % fewer with it in the centre at 1280 x 960)."""
    w, h = 1280, 960
    per = 2 * (w + h)
    corner = len(geo.slice_points(np.array([50.0, 50.0]), w, h))
    centre = len(geo.slice_points(np.array([640.0, 480.0]), w, h))
    assert corner <= 0.6 * per
    assert centre <= 0.92 * per


@pytest.mark.parametrize("kind", ["dir", "spot"])
def test_slices_in_3d_match_image_lines(kind):
    """Each slice's view rays (any beta in its range) project onto its image half-line,
    and the direction -> (phi, beta) map finds the slice back."""
    _, cam, _, _, axis, slices, _ = _setup(kind)
    tab = slices.table
    P = slices.P
    for k in range(0, len(tab), 7):
        w = tab["w"][k, :3].astype(np.float64)
        for f in (0.1, 0.5, 0.9):
            b = float(tab["beta_lo"][k] + f * (tab["beta_hi"][k] - tab["beta_lo"][k]))
            v = math.cos(b) * axis.u + math.sin(b) * w
            xy = cam.project(v[None])[0]
            edge = slices.border[k] - P
            rel = xy - P
            cross = abs(rel[0] * edge[1] - rel[1] * edge[0]) / np.linalg.norm(edge)
            assert cross < 1e-3 and rel @ edge > 0
            phi, beta = axis.coords(v[None])
            assert abs(beta[0] - b) < 1e-6          # w is stored in float32
            k0, k1, fw = slices.bracket(phi)
            assert (k0[0] == k and fw[0] < 1e-3) or (k1[0] == k and fw[0] > 1 - 1e-3)


# ---------------------------------------------------------------------------------------
# the SVD (Sec. 6)

def _sweep_configs():
    """Every light direction / spot position x camera position x view direction of the
    sweep (no exclusions: spot lights behind the camera included)."""
    box = (np.array([-0.5, 0.0, -0.5]), np.array([0.5, 0.4, 0.5]))
    for kind, el, az, eye, look in itertools.product(
            ("dir", "spot"), (10, 35, 70), (0, 90, 180), ((0, 0.2, 0.9), (0.3, 0.15, 0.2)),
            (0, 90, 180, 270)):
        d = np.array([math.cos(math.radians(el)) * math.cos(math.radians(az)), -math.sin(math.radians(el)),
                      math.cos(math.radians(el)) * math.sin(math.radians(az))])
        eye = np.array(eye, float)
        target = eye + np.array([math.sin(math.radians(look)), -0.1, -math.cos(math.radians(look))])
        _, cam = _camera(eye, target)
        if kind == "dir":
            light = _light("dir", direction=d)
        else:
            light = _light("spot", direction=d, position=-0.8 * d + np.array([0.0, 0.1, 0.0]), cutoff=35)
        axis = geo.make_axis(light, eye)
        sl = geo.make_slices(axis, cam, box, 1.0, ring=3.0)
        t = sl.table
        ok = t["gamma_hi"] > t["gamma_lo"]
        if ok.any():
            yield kind, axis, sl, box, (t["gamma_lo"][ok].min(), t["gamma_hi"][ok].max()), \
                (t["beta_lo"].min(), t["beta_hi"].max())


def test_svd_fourth_singular_value_claim():
    """The paper: the 4th singular value never exceeds 1/40 of the first. Checked on the
    matrix the method decomposes first (the plain formulation, svd.py) over every
    configuration of the sweep (light directions and spot positions, spot lights behind
    the camera included, camera positions and orientations, ring 3 px), extinctions
    (kappa x extent 0.5 .. 6) and phase asymmetries g = 0 .. 0.8. Measured: the claim
    holds for directional lights (worst 0.020) and fails for spot lights seen with the
    light behind the camera (beta + gamma -> pi bounds the integrand along an
    anti-diagonal; worst 0.080). Where it fails (59 of 1071 matrices, 20 of them seen by
    no view ray of their camera), the method must not use 4 terms
    (svd.accepts: it raises the terms, references, or falls back to raymarch); the
    held-out error estimate of 4 terms there (view rays of the slices, Gauss nodes that
    are not the SVD's samples) is reported: it exceeds the tolerance in most but not all
    of those matrices (measured 0.004 .. 0.11), which is why the claim is checked too."""
    from clscatter.methods.epipolar.pipeline import _views
    from clscatter.methods.epipolar.settings import settings
    tol = settings().svd_tolerance
    rng = np.random.default_rng(3)
    worst = {"dir": 0.0, "spot": 0.0}
    fails, n, blind = [], 0, 0
    for (kind, axis, sl, box, gr, br), kap, g in itertools.product(
            _sweep_configs(), (0.5, 2.0, 6.0), (0.0, 0.3, 0.8)):
        T = svd.decompose(axis, np.array([kap]), g, gr, br, 4, 64, 64, 64)
        S = T.singular[0]
        ratio = S[3] / S[0]
        worst[kind] = max(worst[kind], ratio)
        n += 1
        if ratio > 1 / 40:
            tab = sl.table
            k = rng.integers(0, len(tab), 300)
            b = rng.uniform(tab["beta_lo"][k], tab["beta_hi"][k])
            w, b, _, ga, gb, k = _views(axis, box, None, sl, k, b)
            if len(b) == 0:          # the camera looks away from the medium: nothing to render
                blind += 1
                continue
            cone = (tab["cone_lo"][k].astype(float), tab["cone_hi"][k].astype(float)) if axis.spot else None
            refs = svd.references(axis, box, tab["w"][:, :3].astype(float),
                                  (tab["cone_lo"].astype(float), tab["cone_hi"].astype(float))
                                  if axis.spot else None, gr, br,
                                  svd.node_extremes(b, b * 0, *br, svd.REF_NODES, False),
                                  zero=True)
            T = svd.decompose(axis, np.array([kap]), g, gr, br, 4, 64, 512, 512, refs)
            err = svd.heldout_error(axis, box, [kap], g, T, refs, w, b, ga, gb, cone)
            fails.append((kind, round(ratio, 3), err["rms"], err["samples"], len(b),
                          svd.accepts(T.singular, 4, err, tol)))
    assert n > 1000
    print(f"s4/s1 > 1/40 in {len(fails) + blind} of {n} matrices ({blind} seen by no view "
          f"ray); worst {worst}; held-out error of 4 terms there: "
          f"{min(f[2] for f in fails):.3g} .. {max(f[2] for f in fails):.3g}")
    assert worst["dir"] <= 1 / 40, worst                   # the claim, directional
    assert fails and all(f[0] == "spot" for f in fails)  # ... and where it fails
    assert not any(f[5] for f in fails)                   # ... 4 terms are refused there
    assert sum(f[2] > tol for f in fails) >= 0.5 * len(fails)


def test_svd_tables_reconstruct_core():
    """The Nyström-extended tables reproduce the core *between* the 64 samples as well as
    the truncated SVD does *at* them: the error at 1000 random (gamma, beta) stays within
    1.2 x the rank-4 error at the samples (here 5e-3 of the maximum, kappa gamma ~ 2.2,
    beta up to 150 degrees), so interpolation adds nothing to the truncation."""
    light = _light("dir", direction=(0.5, -1.0, 0.3))
    axis = geo.make_axis(light, np.array([0.1, 0.2, 1.2]))
    T = svd.decompose(axis, np.array([2.0]), 0.3, (0.0, 1.1), (0.2, 2.6), 4, 64)
    rng = np.random.default_rng(2)
    g = rng.uniform(0.0, 1.1, 1000)
    b = rng.uniform(0.2, 2.6, 1000)
    gi = np.interp(g, np.linspace(0, 1.1, len(T.gtab)), np.arange(len(T.gtab)))
    bi = np.interp(b, np.linspace(0.2, 2.6, len(T.btab)), np.arange(len(T.btab)))
    G = np.stack([np.interp(gi, np.arange(len(T.gtab)), T.gtab[:, n]) for n in range(4)], 1)
    B = np.stack([np.interp(bi, np.arange(len(T.btab)), T.btab[:, n]) for n in range(4)], 1)
    approx = (G * B).sum(1) / svd.pure_beta(axis, 0.3, b)
    exact = np.exp(-2.0 * g * np.tan(b / 2))
    K = svd.core(axis, 2.0, 0.3, np.linspace(0, 1.1, 64), np.linspace(0.2, 2.6, 64))
    U, S, Vt = np.linalg.svd(K)
    best = np.abs((U[:, :4] * S[:4]) @ Vt[:4] - K).max()
    assert np.abs(approx - exact).max() <= 1.2 * best
    assert best < 1e-2 * K.max()


def _held_samples(axis, sl, box, n, rng):
    """``n`` held-out camera samples of the slices ``sl`` (as pipeline._svd draws them)."""
    from clscatter.methods.epipolar.pipeline import _views
    tab = sl.table
    k = rng.integers(0, len(tab), n)
    b = rng.uniform(tab["beta_lo"][k], tab["beta_hi"][k])
    w, b, ta, ga, gb, k = _views(axis, box, None, sl, k, b)
    cone = (tab["cone_lo"][k].astype(float), tab["cone_hi"][k].astype(float)) if axis.spot else None
    cone_all = (tab["cone_lo"].astype(float), tab["cone_hi"].astype(float)) if axis.spot else None
    return w, b, ta, ga, gb, k, cone, cone_all


def test_float32_bound_exceeds_the_emulation():
    """svd.float32_bound (what the method uses instead of emulating the tree's float32
    sums, up to an optical depth of pipeline.F32_BOUND_DEPTH across the medium) is at
    least the emulated error (svd.float32_error) of every sample, over a quarter of the
    SVD sweep's configurations (directional and spot, camera inside and outside), both
    formulations, 4 and 16 terms, kappa 0.5 and 10 (optical depth ~15 along the box's
    diagonal); and useful: small enough to skip the emulation in 95% of the cases.
    Measured: the least per-sample ratio bound / emulation 1.15; the RMS ratio 4.3 .. 12 (median)
    .. 203, the bound at most 1.1e-3."""
    from clscatter.methods.epipolar.pipeline import (
        F32_BOUND_DEPTH,
        F32_BOUND_ENOUGH,
        _truncate,
    )
    from clscatter.methods.epipolar.settings import settings
    rng = np.random.default_rng(5)
    n, ratios = 0, []
    for i, (kind, axis, sl, box, gr, br) in enumerate(_sweep_configs()):
        if i % 4:
            continue
        w, b, ta, ga, gb, k, cone, cone_all = _held_samples(axis, sl, box, 40, rng)
        if len(b) < 5:
            continue
        tab = sl.table
        g0, g1 = tab["gamma_lo"][k].astype(float), tab["gamma_hi"][k].astype(float)
        for kap, zero in itertools.product((0.5, 10.0), (True, False)):
            assert kap * np.linalg.norm(box[1] - box[0]) <= F32_BOUND_DEPTH
            refs = svd.references(axis, box, tab["w"][:, :3].astype(float), cone_all, gr, br,
                                  svd.node_extremes(b, ta, *br, svd.REF_NODES, False), zero=zero)
            full = svd.decompose(axis, np.array([kap]), 0.3, gr, br, 16, 64, 512, 512, refs)
            for T in (4, 16):
                t = _truncate(full, 1, T)
                bound = svd.float32_bound(axis, box, [kap], t, refs, w, b, ga, gb, g0, 640, cone)
                emul = svd.float32_error(axis, box, [kap], t, refs, w, b, ga, gb, g0, g1, 640, cone)
                emul = emul[(gb > ga) & np.isfinite(ga) & np.isfinite(gb)]
                assert bound.shape == emul.shape
                assert np.all(bound >= emul), (kind, kap, zero, T, np.min(bound / emul))
                ratios.append((svd.rms(bound) / svd.rms(emul), svd.rms(bound)))
                n += 1
    assert n >= 100
    r = np.array(ratios)
    print(f"{n} cases: RMS bound / emulation {r[:, 0].min():.3g} .. {np.median(r[:, 0]):.3g} .. "
          f"{r[:, 0].max():.3g}; bound RMS up to {r[:, 1].max():.3g}")
    assert np.median(r[:, 0]) <= 20.0
    # useful: it settles the float32 question (the emulation is skipped) in these media
    assert np.mean(r[:, 1] <= F32_BOUND_ENOUGH * settings().svd_tolerance) >= 0.95


def test_riemann_sums_against_a_loop():
    """svd.riemann_sums (all samples' cells in one flat array) against a per-sample,
    per-cell loop of the same rule: the overlap of each of the slice's d cells with
    [g_a, g_b] times F K at the cell's centre, the cone as the cell's coverage; samples
    with more than max_cells cells are NaN. Directional and spot (box and cone)."""
    rng = np.random.default_rng(8)
    for kind, axis, sl, box, gr, br in itertools.islice(_sweep_configs(), 0, None, 37):
        w, b, ta, ga, gb, k, cone, cone_all = _held_samples(axis, sl, box, 12, rng)
        tab = sl.table
        g0, g1 = tab["gamma_lo"][k].astype(float), tab["gamma_hi"][k].astype(float)
        refs = svd.references(axis, box, tab["w"][:, :3].astype(float), cone_all, gr, br,
                              svd.node_extremes(b, ta, *br, svd.REF_NODES, False))
        d, kap = 48, 3.0
        got = svd.riemann_sums(axis, box, kap, 0.3, refs, w, b, ga, gb, g0, g1, d, cone,
                               max_cells=30)
        for j in range(len(b)):
            dg = (g1[j] - g0[j]) / d
            cells = [c for c in range(d)
                     if min(g0[j] + (c + 1) * dg, gb[j]) > max(g0[j] + c * dg, ga[j])]
            if len(cells) > 30:
                assert np.isnan(got[j])
                continue
            ref = 0.0
            for c in cells:
                lo, hi = g0[j] + c * dg, g0[j] + (c + 1) * dg
                gc = np.array([[0.5 * (lo + hi)]])
                le, _ = svd.light_entry(axis, box, w[j:j + 1], gc)
                cov = 1.0
                if cone is not None:
                    cov = np.clip((min(hi, cone[1][j]) - max(lo, cone[0][j])) / dg, 0.0, 1.0)
                lr = refs.l_at(gc)
                ex = kap * (le - lr) if axis.spot else kap * (lr - le)
                F = cov * np.exp(np.clip(ex, -refs.span * kap, refs.span * kap))
                ov = min(hi, gb[j]) - max(lo, ga[j])
                ref += float(ov * F[0, 0] * svd.k_at(axis, kap, 0.3, gc, b[j:j + 1], refs)[0, 0])
            assert got[j] == pytest.approx(ref, rel=1e-9, abs=1e-300), (kind, j)


@pytest.mark.parametrize("zero", [True, False])
def test_riemann_kernel_matches_the_host(engine, zero):
    """epi_riemann (the error estimate's light-ray sums on the device, float32 with
    compensated sums) against svd.riemann_sums (float64) for held-out samples of a sweep of
    directional and spot configurations, both formulations, two extinctions and two light-ray
    counts: within 2e-4 relative (of the largest sum of the set); samples over max_cells
    cells are NaN in both. The estimate built from them (svd.riemann_rel) agrees to 1e-4."""
    from clscatter.methods.epipolar.pipeline import DeviceRiemann
    rng = np.random.default_rng(9)
    n = 0
    for kind, axis, sl, box, gr, br in itertools.islice(_sweep_configs(), 3, None, 13):
        w, b, ta, ga, gb, k, cone, cone_all = _held_samples(axis, sl, box, 30, rng)
        if len(b) == 0:
            continue
        tab = sl.table
        g0, g1 = tab["gamma_lo"][k].astype(float), tab["gamma_hi"][k].astype(float)
        refs = svd.references(axis, box, tab["w"][:, :3].astype(float), cone_all, gr, br,
                              svd.node_extremes(b, ta, *br, svd.REF_NODES, False), zero=zero)
        for kap in (0.8, 4.0):
            med = _medium(kappa=(kap, kap, kap))
            fb = engine.to_device(geo.frame_struct(axis, med, 64).reshape(1))
            sb = engine.to_device(tab)
            try:
                dev = DeviceRiemann(engine, fb, sb, DEF1, 0.3)
                got = dev.sums(refs, k, b, ga, gb, [64, 640], max_cells=400)
            finally:
                engine.free(fb, sb)
            host = [svd.riemann_sums(axis, box, kap, 0.3, refs, w, b, ga, gb, g0, g1, d, cone,
                                     max_cells=400) for d in (64, 640)]
            for gd, hd in zip(got, host):
                gd = gd[:, 0]
                assert np.array_equal(np.isnan(gd), np.isnan(hd)), (kind, kap)
                ok = ~np.isnan(hd)
                scale = max(float(np.abs(hd[ok]).max(initial=0.0)), 1e-30)
                np.testing.assert_allclose(gd[ok], hd[ok], rtol=2e-4, atol=2e-4 * scale,
                                           err_msg=f"{kind} kappa {kap}")
            ok = ~np.isnan(host[0]) & ~np.isnan(host[1])
            e_dev = svd.riemann_rel(got[0][ok], got[1][ok])
            e_host = svd.riemann_rel(host[0][ok], host[1][ok])
            np.testing.assert_allclose(e_dev, e_host, rtol=0, atol=1e-4)
            n += int(ok.sum())
    assert n > 100


def test_table_at_interpolates_as_the_device():
    """svd._table_at (one np.interp per column) against epi_table's formula in float64:
    ``(1 - f) tab[i] + f tab[i + 1]`` with ``s = (x - lo) / (hi - lo) (n - 1)`` clamped to
    the ends; x outside the range, at the ends, and a table of one row."""
    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 2048):
        tab = rng.uniform(-1, 1, (n, 5)).astype(np.float32)
        x = np.concatenate([rng.uniform(-0.5, 2.5, (30,)), [0.3, 1.7, -1.0, 5.0]]).reshape(2, 17)
        got = svd._table_at(tab, 0.3, 1.7, x)
        s = np.clip((x - 0.3) / 1.4 * (n - 1), 0.0, n - 1)
        i = np.minimum(s.astype(int), max(n - 2, 0))
        f = (s - i)[..., None]
        ref = (1 - f) * tab[i].astype(float) + f * tab[np.minimum(i + 1, n - 1)].astype(float)
        assert got.shape == (2, 17, 5)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------
# maps

def _upload_scene(engine, tris):
    bvh = build_bvh(tris)
    nodes = engine.to_device(bvh.nodes)
    t = engine.to_device(np.ascontiguousarray(bvh.triangles, np.float32).reshape(-1, 4))
    return bvh, nodes, t


def _quad_tris(y, half=0.3, cx=0.0):
    a = np.array([[cx - half, y, -half], [cx + half, y, -half], [cx + half, y, half], [cx - half, y, half]])
    return np.array([[a[0], a[1], a[2]], [a[0], a[2], a[3]]])


def _face_dirs(faces):
    """Unit directions of every texel centre of spot faces (maps.spot_faces), in order."""
    out = []
    for f in faces:
        nx, ny = int(f["c"][3]), int(f["e1"][3])
        r = f["rect"].astype(np.float64)
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
        x1 = r[0] + (ix.ravel() + 0.5) * (r[2] - r[0]) / nx
        x2 = r[1] + (iy.ravel() + 0.5) * (r[3] - r[1]) / ny
        d = f["c"][:3] + x1[:, None] * f["e1"][:3] + x2[:, None] * f["e2"][:3]
        out.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return np.concatenate(out)


def _np_face_lookup(faces, l):
    """NumPy copy of epi_face_of and the face projection of epi_blocker: texel index of
    directions l (N, 3), -1 where none holds them."""
    lc = np.stack([l @ f["c"][:3].astype(np.float64) for f in faces], 1)
    best = np.argmax(np.where(lc > 1e-6, lc, -np.inf), axis=1)
    ok = lc[np.arange(len(l)), best] > 1e-6
    idx = np.full(len(l), -1)
    for k, f in enumerate(faces):
        m = ok & (best == k)
        c = lc[m, k]
        x1 = (l[m] @ f["e1"][:3].astype(np.float64)) / c
        x2 = (l[m] @ f["e2"][:3].astype(np.float64)) / c
        r = f["rect"].astype(np.float64)
        nx, ny = int(f["c"][3]), int(f["e1"][3])
        fx = (x1 - r[0]) / (r[2] - r[0]) * nx
        fy = (x2 - r[1]) / (r[3] - r[1]) * ny
        inside = (fx >= 0) & (fx < nx) & (fy >= 0) & (fy < ny)
        idx[np.flatnonzero(m)[inside]] = (int(f["e2"][3]) + fy.astype(int) * nx + fx.astype(int))[inside]
    return idx


@pytest.mark.parametrize("kind,cutoff,with_grid", [("dir", 0, False), ("dir", 0, True),
                                                   ("spot", 55, True), ("spot", 65, False),
                                                   ("spot", 85, False)])
def test_shadow_map_kernel_matches_bvh_trace(engine, kind, cutoff, with_grid):
    """Every texel against the BVH tracer: the orthographic map (through the BVH, and
    through a tile grid), a single perspective map (55 degrees through a perspective
    tile grid, 65 through the BVH) and the five cube faces of a wide cone (85 degrees)."""
    from clscatter.accel import tile_grid
    from clscatter.methods.epipolar.maps import face_texels, spot_faces
    tris = np.concatenate([_quad_tris(0.3, 0.2, 0.1), _quad_tris(0.0, 0.6)])
    bvh, nodes, tb = _upload_scene(engine, tris)
    *_, axis, _, frame = _setup(kind, cutoff=cutoff or 30.0)
    res = 48
    frame["sm_res"] = res
    # the map setup of maps.setup_shadow_map needs a PreparedScene; reproduce its fields
    faces = np.zeros(1, geo.EPI_FACE)
    if kind == "dir":
        rel = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (0.0, 0.4) for z in (-0.5, 0.5)]) - axis.eye
        c1, c2 = rel @ axis.b1, rel @ axis.b2
        frame["sm_s1"], frame["sm_s2"] = structs.vec4(axis.b1), structs.vec4(axis.b2)
        frame["sm_rect"] = [c1.min(), c2.min(), c1.max(), c2.max()]
        frame["z_start"] = 2.0
        n = res * res
    else:
        faces = spot_faces(axis, res)
        assert len(faces) == (1 if cutoff <= 60 else 5)
        frame["sm_faces"] = len(faces)
        n = face_texels(faces)
    grid = None
    if with_grid and kind == "dir":
        grid = tile_grid.build_grid(bvh, axis.eye, axis.b1, axis.b2, -axis.u,
                                    frame["sm_rect"], 6, 5)
    elif with_grid:
        f = faces[0]
        grid = tile_grid.build_grid(bvh, axis.light, f["e1"], f["e2"], f["c"], f["rect"], 6, 5,
                                    perspective=True)
    assert grid is not None or not with_grid
    gb = tile_grid.upload(engine, grid)
    fb = engine.to_device(frame.reshape(1))
    fcb = engine.to_device(faces)
    out = engine.empty(4 * n)
    engine.launch(engine.kernel("epipolar", "epi_shadow_map", DEF1), n, nodes, tb, fb, fcb,
                  gb, np.int32(n), out)
    engine.free(gb)
    got = engine.read(out, n, np.float32)
    if kind == "dir":
        r = frame["sm_rect"].astype(np.float64)
        ix, iy = np.meshgrid(np.arange(res), np.arange(res))
        x1 = r[0] + (ix.ravel() + 0.5) * (r[2] - r[0]) / res
        x2 = r[1] + (iy.ravel() + 0.5) * (r[3] - r[1]) / res
        o = axis.eye + x1[:, None] * axis.b1 + x2[:, None] * axis.b2 + 2.0 * axis.u
        t, _ = trace(engine, bvh, o, np.broadcast_to(-axis.u, o.shape))
        ref = np.where(np.isfinite(t), 2.0 - t, 1e30)
    else:
        dirs = _face_dirs(faces)
        t, _ = trace(engine, bvh, np.broadcast_to(axis.light, dirs.shape), dirs)
        ref = np.where(np.isfinite(t), t, 1e30)
        # each texel's own direction is looked up in that very texel
        assert np.array_equal(_np_face_lookup(faces, dirs), np.arange(n))
    hit = ref < 1e29
    assert 0.1 < hit.mean() < 1.0
    assert np.array_equal(got >= 1e29, ~hit)
    assert np.allclose(got[hit], ref[hit], atol=1e-5)
    engine.free(nodes, tb, fb, fcb, out)
    bvh.release()


@pytest.mark.parametrize("cutoff", [10.0, 30.0, 60.0, 61.0, 80.0, 89.0, 90.0])
def test_spot_faces_cover_the_cone(cutoff):
    """No unshadowed light rays: every direction of the cone, up to a hemisphere, falls in
    a texel of some face; the texel pitch (angle between neighbouring texel centres, in the
    face that holds the direction) stays within 1.1 x of a 45-degree map's 2 / res at any
    cutoff (the single map grows with the cone; five faces beyond 60 degrees)."""
    from clscatter.methods.epipolar.maps import spot_faces
    light = _light("spot", direction=(0.3, -1.0, 0.2), position=(0.0, 1.0, 0.0), cutoff=cutoff)
    axis = geo.make_axis(light, np.array([0.5, 0.5, 1.5]))
    res = 256
    faces = spot_faces(axis, res)
    rng = np.random.default_rng(4)
    # directions uniform in the cone, plus its rim
    cosc = math.cos(math.radians(cutoff))
    ct = np.concatenate([rng.uniform(cosc, 1.0, 20000), np.full(2000, cosc)])
    ph = rng.uniform(0, 2 * math.pi, len(ct))
    a = axis.cone_axis
    s1 = np.cross(a, [1.0, 0.0, 0.0]); s1 /= np.linalg.norm(s1)
    s2 = np.cross(a, s1)
    st = np.sqrt(1 - ct ** 2)
    l = ct[:, None] * a + (st * np.cos(ph))[:, None] * s1 + (st * np.sin(ph))[:, None] * s2
    idx = _np_face_lookup(faces, l)
    assert (idx >= 0).all(), f"{(idx < 0).sum()} unshadowed directions"
    # pitch at the direction: angle to the next texel centre along x
    dirs = _face_dirs(faces)
    offs = np.array([int(f["e2"][3]) for f in faces])
    nxs = np.array([int(f["c"][3]) for f in faces])
    k = np.searchsorted(offs, idx, side="right") - 1
    last = (idx - offs[k]) % nxs[k] == nxs[k] - 1         # the texel beside it in its row
    nxt = np.where(last, idx - 1, idx + 1)
    pitch = np.arccos(np.clip((dirs[idx] * dirs[nxt]).sum(1), -1, 1))
    assert pitch.max() <= 1.1 * 2.0 / res, pitch.max() * res


def test_depth_map_kernel_matches_bvh_trace(engine):
    import analytic
    tris = np.concatenate([_quad_tris(0.3, 0.2, 0.1), _quad_tris(0.0, 0.6)])
    bvh, nodes, tb = _upload_scene(engine, tris)
    c = Camera(np.array([0.1, 0.5, 1.2]), np.array([0.0, 0.1, 0.0]), np.array([0.0, 1.0, 0.0]),
               50.0, "x", 40, 30, 1)
    cb = engine.to_device(camera_struct(c, Frame(np.zeros(3), 1.0)).reshape(1))
    out = engine.empty(4 * 40 * 30)
    engine.launch(engine.kernel("epipolar", "epi_depth_map", DEF1), 40 * 30, nodes, tb, cb,
                  np.int32(40), np.int32(30), out)
    got = engine.read(out, (30, 40), np.float32)
    d = analytic.camera_rays(**analytic.camera_kwargs(c)).reshape(-1, 3)
    t, _ = trace(engine, bvh, np.broadcast_to(c.origin, d.shape), d)
    ref = np.where(np.isfinite(t), t, 1e30).reshape(30, 40)
    assert np.array_equal(got >= 1e29, ref >= 1e29)
    assert np.allclose(got[ref < 1e29], ref[ref < 1e29], atol=1e-5)
    engine.free(nodes, tb, cb, out)
    bvh.release()


# ---------------------------------------------------------------------------------------
# rectification of the shadow map

def _np_blocker(frame, axis, w, gamma, smap, faces=None):
    """NumPy copy of epi_blocker: the map value for light rays (gamma, slice w)."""
    if axis.spot:
        l = -np.cos(gamma)[..., None] * axis.u + np.sin(gamma)[..., None] * w
        idx = _np_face_lookup(faces, l.reshape(-1, 3)).reshape(gamma.shape)
        return np.where(idx >= 0, smap.ravel()[np.maximum(idx, 0)].astype(np.float64), 1e30)
    res = int(frame["sm_res"])
    r = frame["sm_rect"].astype(np.float64)
    x1 = gamma * (w @ axis.b1)
    x2 = gamma * (w @ axis.b2)
    fx = (x1 - r[0]) / (r[2] - r[0]) * res
    fy = (x2 - r[1]) / (r[3] - r[1]) * res
    inside = (fx >= 0) & (fx < res) & (fy >= 0) & (fy < res)
    ix = np.clip(fx.astype(int), 0, res - 1)
    iy = np.clip(fy.astype(int), 0, res - 1)
    v = smap[iy, ix].astype(np.float64)
    return np.where(inside, v, 1e30)


@pytest.mark.parametrize("kind,prefilter", [("dir", 1), ("dir", 0), ("spot", 1)])
def test_rectify_shadow_kernel(engine, kind, prefilter):
    """Blocker betas and prefilter modes against NumPy: per light ray, the sub-samples'
    blocker betas sorted; modes are runs within the tolerance; weights sum to the
    blocked fraction."""
    *_, axis, slices, frame = _setup(kind, d=40)
    res = 32
    rng = np.random.default_rng(3)
    # a blocky map: blocker depths constant on 4x4 texel blocks, a quarter of blocks empty
    blocks = rng.uniform(0.0, 0.3, (res // 4, res // 4)) if kind == "dir" else rng.uniform(0.2, 0.9, (res // 4, res // 4))
    blocks[rng.uniform(size=blocks.shape) < 0.25] = 1e30
    smap = np.kron(blocks, np.ones((4, 4))).astype(np.float32)
    frame["sm_res"] = res
    frame["prefilter"] = prefilter
    frame["beta_tol"] = 0.01
    if kind == "dir":
        g_hi = float(slices.table["gamma_hi"].max())
        frame["sm_s1"], frame["sm_s2"] = structs.vec4(axis.b1), structs.vec4(axis.b2)
        frame["sm_rect"] = [-g_hi, -g_hi, g_hi, g_hi]
    faces = np.zeros(1, geo.EPI_FACE)
    if kind != "dir":
        from clscatter.methods.epipolar.maps import spot_faces
        faces = spot_faces(axis, res)
        frame["sm_faces"] = len(faces)
        assert int(faces[0]["c"][3]) == res and len(faces) == 1
    S, d = len(slices), 40
    bufs = [engine.to_device(frame.reshape(1)), engine.to_device(slices.table),
            engine.to_device(smap), engine.empty(8 * S * d * 4), engine.to_device(faces)]
    engine.launch(engine.kernel("epipolar", "epi_rectify_shadow", DEF1), S * d, bufs[0], bufs[1],
                  np.int32(0), np.int32(S), bufs[4], bufs[2], bufs[3])
    got = engine.read(bufs[3], (S, d, 4, 2), np.float32)
    engine.free(*bufs)
    tab = slices.table
    dg = (tab["gamma_hi"] - tab["gamma_lo"]).astype(np.float64) / d
    ns = 4 if prefilter else 1
    offs = (np.arange(ns) + 0.5) / ns if prefilter else np.array([0.5])
    g = tab["gamma_lo"][:, None, None] + (np.arange(d)[None, :, None] + offs[None, None, :]) * dg[:, None, None]
    w = tab["w"][:, :3].astype(np.float64)[:, None, None, :]
    v = _np_blocker(frame, axis, np.broadcast_to(w, g.shape + (3,)), g, smap, faces)
    hit = v < 1e29
    if axis.spot:
        beta = np.arctan2(v * np.sin(g), axis.D - v * np.cos(g))
    else:
        beta = np.arctan2(g, v)
    blocked = hit.mean(axis=2)                             # fraction of sub-samples blocked
    got_beta, got_frac = got[..., 0], got[..., 1]
    # the fractions (relative to the remainder) multiply out to the blocked fraction
    left = np.ones((S, d))
    for m in range(4):
        left *= 1.0 - got_frac[..., m]
    assert np.allclose(1.0 - left, blocked, atol=1e-6)
    # each mode's beta lies within the betas of the blocked sub-samples of its light ray
    lo = np.where(hit, beta, np.inf).min(axis=2)
    hi = np.where(hit, beta, -np.inf).max(axis=2)
    used = got_frac > 0
    assert np.all((got_beta >= lo[..., None] - 1e-4) | ~used)
    assert np.all((got_beta <= hi[..., None] + 1e-4) | ~used)
    # single sub-sample: exactly its beta
    if not prefilter:
        assert np.allclose(got_beta[..., 0][hit[..., 0]], beta[..., 0][hit[..., 0]], atol=2e-6)
    # modes are sorted and separated by more than the tolerance (in beta, first order)
    b = np.where(used, got_beta, np.nan)
    gaps = np.diff(b, axis=2)
    assert np.all((gaps >= -1e-7) | np.isnan(gaps))
    assert used.sum(axis=2).max() <= 4 and (used.sum(axis=2) >= 1)[blocked > 0].all()
    if prefilter:
        assert (used.sum(axis=2) > 1).any()                # some rays see two depths


# ---------------------------------------------------------------------------------------
# the sweep

def _np_light_factor(frame, axis, sl, g, dg, lref):
    """NumPy copy of epi_light_factor for one channel (kappa.x): the light ray's entry
    relative to the reference ``lref`` (svd.py), clamped to +-lspan."""
    kap = float(frame["kappa"][0])
    span = float(frame["lspan"])
    bmin, bmax = frame["bmin"][:3].astype(np.float64), frame["bmax"][:3].astype(np.float64)
    w = sl["w"][:3].astype(np.float64)
    if axis.spot:
        a = np.maximum(g - dg / 2, sl["cone_lo"])
        b = np.minimum(g + dg / 2, sl["cone_hi"])
        cov = np.clip((b - a) / dg, 0, 1)
        l = -np.cos(g)[:, None] * axis.u + np.sin(g)[:, None] * w
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (bmin - axis.light) / l
            tb = (bmax - axis.light) / l
        t0 = np.maximum(np.nanmax(np.minimum(ta, tb), axis=1), 0.0)
        return cov * np.exp(kap * np.clip(t0 - lref, -span, span))
    o = axis.eye + g[:, None] * w
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (bmin - o) / axis.u
        tb = (bmax - o) / axis.u
    z_exit = np.nanmin(np.maximum(ta, tb), axis=1)
    return np.exp(kap * np.clip(lref - z_exit, -span, span))


def _prefix(b: np.ndarray, m: float) -> np.ndarray:
    """Sum of the first m rows of b, m continuous (the last one fractional)."""
    d = len(b)
    m = min(max(m, 0.0), d)
    i = math.floor(m)
    return b[:i].sum(0) + ((m - i) * b[i] if i < d else 0.0)


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000, 4097])
def test_lower_bound_from_a_hint_matches_searchsorted(engine, n):
    """epi_lower_bound (galloping from a hint) equals np.searchsorted(side="left") on the
    events' betas for every hint (before, at and past the answer, out of range), betas
    below, between, equal to and above the events, runs of equal betas, and NaN betas
    sorted last (never below a number)."""
    rng = np.random.default_rng(n)
    beta = np.sort(rng.choice(np.linspace(0.0, 3.0, max(n // 3, 1) + 1), n)).astype(np.float32)
    if n > 10:
        beta[-3:] = np.nan
    ev = np.zeros((max(n, 1), 4), np.float32)
    ev[:n, 0] = beta
    finite = beta[np.isfinite(beta)]
    qs = np.concatenate([rng.uniform(-0.5, 3.5, 400), finite[::max(len(finite) // 50, 1)],
                         [-np.inf, np.inf]]).astype(np.float32)
    hints = rng.integers(-3, n + 4, len(qs))
    qs = np.repeat(qs, 3)
    hints = np.concatenate([hints, np.searchsorted(finite, qs[::3]), np.full(len(hints), n)])
    hints = hints.reshape(3, -1).T.ravel().astype(np.int32)
    bufs = [engine.to_device(ev), engine.to_device(qs), engine.to_device(hints),
            engine.empty(4 * len(qs))]
    try:
        engine.call("epipolar", "epi_lower_bound_test", len(qs), DEF1, ev=bufs[0], n=n,
                    b=bufs[1], h=bufs[2], m=len(qs), out=bufs[3])
        got = engine.read(bufs[3], len(qs), np.int32)
    finally:
        engine.free(*bufs)
    assert np.array_equal(got, np.searchsorted(finite, qs, side="left"))


@pytest.mark.parametrize("kind,two_runs,wrap", [("dir", 0, 0), ("spot", 0, 0), ("dir", 1, 0),
                                                ("spot", 1, 1), ("dir", 1, 1)])
def test_integrate_kernel_matches_bruteforce(engine, kind, two_runs, wrap):
    """epi_integrate against the O(events x d) Riemann sum of Eq. (3): each light ray's
    value F Gamma dgamma scaled by its termination modes with beta <= the event's beta,
    summed over [gamma0, gamma1] with fractional end cells, times B(beta)
    exp(kappa (t_a - t_ref(beta))); F relative to the light-side reference l_ref(gamma),
    tables per SVD group of the slice. One run per slice (out[p]), or two (the segment
    lookup: slice k sweeps run k merged with run k - 1, wrapping to the last run for
    slice 0 of a full fan; out[2 p + side]), with equal betas across the two runs."""
    *_, axis, slices, frame = _setup(kind, d=53)
    S, d, nt = 5, 53, 4
    valid = np.flatnonzero(slices.table["gamma_hi"] > slices.table["gamma_lo"] + 1e-3)
    tab = slices.table[valid[np.linspace(0, len(valid) - 1, S).astype(int)]].copy()
    frame["d"] = d
    rng = np.random.default_rng(11)
    # termination modes: up to 3 per ray, sorted betas, fractions relative to the remainder
    term = np.zeros((S, d, 4, 2), np.float32)
    nm = rng.integers(0, 4, (S, d))
    for m in range(3):
        term[..., m, 0] = rng.uniform(0.1, 2.9, (S, d))
        term[..., m, 1] = np.where(m < nm, rng.choice([0.25, 0.5, 1.0], (S, d)), 0.0)
    term[..., :3, 0] = np.sort(term[..., :3, 0], axis=-1)
    # events: sorted betas, random gamma intervals inside and beyond the slice's range
    n_ev = rng.integers(5, 40, S)
    off = np.concatenate([[0], np.cumsum(n_ev)]).astype(np.int32)
    ev = np.zeros((off[-1], 4), np.float32)
    for k in range(S):
        lo, hi = float(tab["gamma_lo"][k]), float(tab["gamma_hi"][k])
        e = ev[off[k]:off[k + 1]]
        e[:, 0] = np.sort(rng.uniform(0.0, 3.0, n_ev[k]))
        a = rng.uniform(lo - 0.1 * (hi - lo), hi, n_ev[k])
        e[:, 1] = a
        e[:, 2] = a + rng.uniform(0.0, hi - lo, n_ev[k])
        e[:, 3] = rng.uniform(0.0, 0.5, n_ev[k])
    e[-1, 2] = e[-1, 1]                       # an empty interval
    ev[off[1], 0] = ev[off[0], 0]             # a beta in two runs (ties in the merge)
    ev[off[1]:off[2], 0] = np.sort(ev[off[1]:off[2], 0])
    # what each slice sweeps: (event, side) pairs of its own run, and of the previous one
    sweeps = []
    for k in range(S):
        pairs = [(q, 0) for q in range(off[k], off[k + 1])]
        if two_runs and (k > 0 or wrap):
            pk = k - 1 if k > 0 else S - 1
            pairs += [(q, 1) for q in range(off[pk], off[pk + 1])]
        sweeps.append(pairs)
    cnt_off = np.concatenate([[0], np.cumsum([len(p) for p in sweeps])]).astype(np.int32)
    n_out = 2 * off[-1] if two_runs else off[-1]
    # two SVD groups (slices alternate between them), each with signed terms as from an
    # SVD (the first dominant; the kernel clamps results at 0), its own ranges and its
    # references l_ref (light side, gtab's grid) and t_ref (view side, btab's grid)
    tab["group"] = np.arange(S) % 2
    frame["lspan"] = 0.3
    n_g, n_b, ng = 20, 30, 2
    gtab = rng.uniform(-0.3, 0.3, (ng, n_g, nt)).astype(np.float32)
    btab = rng.uniform(-0.3, 0.3, (ng, n_b, nt)).astype(np.float32)
    gtab[..., 0] += 1.0
    btab[..., 0] += 1.0
    ranges = np.array([[0.0, float(tab["gamma_hi"].max()), 0.0, 3.0],
                       [0.05, 1.1 * float(tab["gamma_hi"].max()), 0.2, 2.8]], np.float32)
    gref = rng.uniform(-0.2, 0.6, (ng, n_g)).astype(np.float32)
    bref = rng.uniform(0.0, 0.4, (ng, n_b)).astype(np.float32)
    bufs = {"fr": engine.to_device(frame.reshape(1)), "sl": engine.to_device(tab),
            "term": engine.to_device(term), "off": engine.to_device(off), "ev": engine.to_device(ev),
            "gt": engine.to_device(gtab), "bt": engine.to_device(btab),
            "gr": engine.to_device(gref), "br": engine.to_device(bref),
            "rg": engine.to_device(ranges),
            "tree": engine.empty(4 * S * d * nt), "leaf": engine.empty(4 * S * d * nt),
            "cnt_off": engine.to_device(cnt_off),
            "cnt": engine.empty(4 * (cnt_off[-1] + S)), "srt": engine.empty(8 * S * d * 4),
            "mev": engine.empty(16 * (cnt_off[-1] + S)), "dst": engine.empty(4 * (cnt_off[-1] + S)),
            "out": engine.zeros(16 * n_out), "work": engine.empty(8 * S)}
    engine.call("epipolar", "epi_integrate", S, DEF1, fr=bufs["fr"], slices=bufs["sl"],
                slice0=0, nbatch=S, term=bufs["term"], ev_off=bufs["off"], two_runs=two_runs,
                wrap=wrap, nslices=S, cnt_off=bufs["cnt_off"], events=bufs["ev"],
                gtab_all=bufs["gt"], n_g=n_g, btab_all=bufs["bt"], n_b=n_b,
                gref_all=bufs["gr"], bref_all=bufs["br"], groups=bufs["rg"], tree=bufs["tree"],
                leaf=bufs["leaf"], cnt_all=bufs["cnt"], merged_all=bufs["mev"],
                dst_all=bufs["dst"], sorted_all=bufs["srt"], out=bufs["out"], work=bufs["work"])
    got = engine.read(bufs["out"], (n_out, 4), np.float32)[:, 0]
    work = engine.read(bufs["work"], (S, 2), np.int32)
    engine.free(*bufs.values())
    kap = float(frame["kappa"][0])
    ref = np.zeros(n_out)
    written = np.zeros(n_out, bool)
    for k_ in range(S):
        sl = tab[k_]
        q_ = int(sl["group"])
        g_lo, g_hi, b_lo, b_hi = (float(x) for x in ranges[q_])
        dg = (float(sl["gamma_hi"]) - float(sl["gamma_lo"])) / d
        gi = float(sl["gamma_lo"]) + (np.arange(d) + 0.5) * dg
        gx = np.linspace(g_lo, g_hi, n_g)
        G = np.stack([np.interp(gi, gx, gtab[q_, :, n]) for n in range(nt)], 1)
        lref = np.interp(gi, gx, gref[q_])
        b0 = G * (_np_light_factor(frame, axis, sl, gi, dg, lref) * dg)[:, None]
        for q, side in sweeps[k_]:
            o = 2 * q + side if two_runs else q
            written[o] = True
            beta, g0, g1, ta = (float(x) for x in ev[q])
            frac = np.ones(d)
            for m in range(4):
                f = term[k_, :, m, 1].astype(np.float64)
                applies = (f > 0) & (term[k_, :, m, 0] <= ev[q, 0])
                frac = np.where(applies, np.where(f >= 1, 0.0, frac * (1 - f)), frac)
            b = b0 * frac[:, None]
            lo = float(sl["gamma_lo"])
            bx = np.linspace(b_lo, b_hi, n_b)
            B = np.array([np.interp(beta, bx, btab[q_, :, n]) for n in range(nt)])
            tref = float(np.interp(beta, bx, bref[q_]))
            dq = _prefix(b, (g1 - lo) / dg) - _prefix(b, (g0 - lo) / dg)
            ref[o] = max((B * dq).sum(), 0.0) * math.exp(kap * (ta - tref)) if g1 > g0 else 0.0
    scale = np.abs(ref).max()
    assert scale > 0 and (ref[written] > 0).mean() > 0.5
    assert np.allclose(got[written], ref[written], atol=2e-5 * scale, rtol=1e-4)
    assert np.all(got[~written] == 0.0)          # no stray writes
    swept = [q for pairs in sweeps for q, _ in pairs]
    assert work[:, 1].sum() == 2 * int((ev[swept, 2] > ev[swept, 1]).sum())


# ---------------------------------------------------------------------------------------
# view rays: samples, depth rectification, image round trip

@pytest.mark.parametrize("kind", ["dir", "spot"])
def test_samples_kernel(engine, kind):
    cam_s, cam, _, _, axis, slices, frame = _setup(kind, ring=6.0)
    rng = np.random.default_rng(4)
    n = 500
    xy = np.stack([rng.uniform(0, 64, n), rng.uniform(0, 48, n)], 1)
    v = cam.direction(xy)
    t_a = rng.uniform(0.0, 0.5, n)
    t_b = t_a + rng.uniform(0.01, 1.0, n)
    segs = np.zeros(n, structs.VIEW_SEGMENT)
    segs["a"][:, :3] = cam.origin + t_a[:, None] * v
    segs["b"][:, :3] = cam.origin + t_b[:, None] * v
    phis = slices.phi.astype(np.float32)
    ring = np.array([slices.P[0], slices.P[1], 6.0, 0.0], np.float32)
    lut = slices.lookup_table()
    bufs = [engine.to_device(frame.reshape(1)), engine.to_device(phis),
            engine.to_device(cam_s.reshape(1)), engine.to_device(segs), engine.empty(16 * n),
            engine.empty(16 * n), engine.to_device(lut), engine.empty(16 * n),
            engine.empty(4 * n)]
    engine.call("epipolar", "epi_view_dirs", n, DEF1, segs=bufs[3], n=n, eye=frame["eye"],
                dirs=bufs[7], ta=bufs[8])
    dirs = engine.read(bufs[7], (n, 4), np.float32)
    ta = engine.read(bufs[8], n, np.float32)
    engine.launch(engine.kernel("epipolar", "epi_samples", DEF1), n, bufs[0], bufs[1],
                  np.int32(len(phis)), np.int32(slices.full), bufs[6], np.int32(len(lut) - 1),
                  bufs[2], ring, bufs[7], bufs[8], np.int32(n), bufs[4], bufs[5])
    g = engine.read(bufs[4], (n, 4), np.float32)
    idx = engine.read(bufs[5], (n, 4), np.int32)
    engine.free(*bufs)
    # epi_view_dirs: the unit direction and both distances from the eye
    np.testing.assert_allclose(dirs[:, :3], v, atol=2e-6)
    np.testing.assert_allclose(dirs[:, 3], t_b, rtol=2e-6)
    np.testing.assert_allclose(ta, t_a, atol=2e-6)
    phi, beta = axis.coords(v)
    k0, k1, f = slices.bracket(phi)
    assert np.allclose(g[:, 0], beta, atol=2e-6)
    assert np.allclose(g[:, 1], axis.gamma(t_a, beta), atol=2e-5)
    assert np.allclose(g[:, 2], axis.gamma(t_b, beta), atol=2e-5)
    assert np.allclose(g[:, 3], t_a, atol=2e-6)
    # slice brackets: the same pair, or (float32 phi) the neighbouring pair at a boundary
    fk = idx[:, 2].view(np.float32)
    same = (idx[:, 0] == k0) & (idx[:, 1] == k1)
    assert same.mean() > 0.97
    assert np.allclose(fk[same], f[same], atol=2e-3)
    ring_ref = np.hypot(*(cam.project(v) - slices.P).T) < 6.0
    assert np.array_equal(idx[:, 3] != 0, ring_ref)
    assert ring_ref.any() if (0 <= slices.P[0] <= 64 and 0 <= slices.P[1] <= 48) else True


def test_rectify_depth_kernel(engine):
    """Grid view rays: beta at the cell centre of the slice's range, the medium interval
    cut at the depth map's nearest pixel, converted to gamma."""
    cam_s, cam, _, med, axis, slices, frame = _setup("dir")
    R, dw, dh = 16, 32, 24
    frame["rays"] = R
    rng = np.random.default_rng(8)
    depth = rng.uniform(0.8, 2.0, (dh, dw)).astype(np.float32)
    depth[rng.uniform(size=depth.shape) < 0.2] = 1e30
    S = len(slices)
    bufs = [engine.to_device(frame.reshape(1)), engine.to_device(slices.table),
            engine.to_device(med.reshape(1)), engine.to_device(cam_s.reshape(1)),
            engine.to_device(depth), engine.empty(16 * S * R)]
    engine.launch(engine.kernel("epipolar", "epi_rectify_depth", DEF1), S * R, bufs[0], bufs[1],
                  np.int32(0), np.int32(S), bufs[2], bufs[3], bufs[4], np.int32(dw), np.int32(dh),
                  bufs[5])
    got = engine.read(bufs[5], (S, R, 4), np.float32)
    engine.free(*bufs)
    tab = slices.table
    beta = tab["beta_lo"][:, None] + (np.arange(R) + 0.5) / R * (tab["beta_hi"] - tab["beta_lo"])[:, None]
    w = tab["w"][:, None, :3].astype(np.float64)
    v = np.cos(beta)[..., None] * axis.u + np.sin(beta)[..., None] * w
    xy = cam.project(v.reshape(-1, 3)) * np.array([dw / 64, dh / 48])
    t_hit = depth[np.clip(xy[:, 1].astype(int), 0, dh - 1), np.clip(xy[:, 0].astype(int), 0, dw - 1)]
    import analytic
    t_in, t_out, hit = analytic.ray_box(cam.origin, v.reshape(-1, 3), med["bmin"][:3], med["bmax"][:3])
    t0 = np.maximum(t_in, 0.0)
    t1 = np.minimum(t_out, t_hit)
    ok = hit & (t1 > t0)
    ref_g0 = np.where(ok, t0 * np.sin(beta.ravel()), 0.0)
    ref_g1 = np.where(ok, t1 * np.sin(beta.ravel()), 0.0)
    got = got.reshape(-1, 4)
    assert np.allclose(got[:, 0], beta.ravel(), atol=2e-6)
    assert ok.mean() > 0.3
    assert np.allclose(got[:, 1], ref_g0, atol=1e-5)
    assert np.allclose(got[:, 2], ref_g1, atol=1e-5)


@pytest.mark.parametrize("eye,target", [((0.1, 0.2, 1.2), (0.0, 0.15, 0.0)),        # epipole off screen
                                        ((0.2, 0.1, 1.0), (-0.35, 0.8, 0.0))])      # on screen
def test_rectify_unrectify_roundtrip(engine, eye, target):
    """unrectify(rectify(image)) reproduces a smooth image away from the epipole: the
    two bilinear resamplings through slices <= 1 px apart and rays ~1 px apart lose
    < 2 % of the pattern's range beyond 4 px from the epipole."""
    w, h = 64, 48
    cam_s, cam, _, _, _, slices, frame = _setup("dir", eye=eye, target=target,
                                                 direction=(0.5, -1.0, 0.3))
    R = int(math.ceil(float(slices.length.max()))) + 1
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    img = np.zeros((h, w, 4), np.float32)
    img[..., 0] = np.sin(xs / 6.0) * np.cos(ys / 9.0)
    img[..., 1] = xs / w
    S = len(slices)
    xy = np.stack([xs.ravel(), ys.ravel()], 1)
    dirs = np.zeros((w * h, 4), np.float32)
    dirs[:, :3] = cam.direction(xy)
    bufs = {"fr": engine.to_device(frame.reshape(1)), "sl": engine.to_device(slices.table),
            "cam": engine.to_device(cam_s.reshape(1)), "img": engine.to_device(img),
            "grid": engine.empty(16 * S * R), "phis": engine.to_device(slices.phi.astype(np.float32)),
            "dirs": engine.to_device(dirs), "out": engine.empty(16 * w * h),
            "lut": engine.to_device(slices.lookup_table())}
    engine.launch(engine.kernel("epipolar", "epi_rectify_image", DEF1), S * R, bufs["fr"],
                  bufs["sl"], np.int32(S), np.int32(R), bufs["cam"], bufs["img"], np.int32(w),
                  np.int32(h), bufs["grid"])
    engine.launch(engine.kernel("epipolar", "epi_unrectify", DEF1), w * h, bufs["fr"], bufs["sl"],
                  bufs["phis"], np.int32(S), np.int32(slices.full), bufs["lut"], np.int32(4 * S),
                  np.int32(R), bufs["grid"],
                  bufs["dirs"], np.int32(w * h), bufs["out"])
    back = engine.read(bufs["out"], (h, w, 4), np.float32)
    engine.free(*bufs.values())
    far = np.hypot(xs - slices.P[0], ys - slices.P[1]) > 4.0
    err = np.abs(back[..., :2] - img[..., :2])[far]
    assert err.max() < 0.02 * 2.0, err.max()
    assert err.mean() < 0.003


@pytest.mark.parametrize("full", [True, False])
@pytest.mark.parametrize("bins", [None, 1, 3, 7])
def test_bracket_lookup_table_finds_the_binary_search_answer(engine, full, bins):
    """epi_bracket searches only the window the lookup table gives an angle's bin (one bin
    of slack each way): the slices it finds equal a float32 search over all of them (what
    it did before), for a full fan (wrapping) and an open fan (cut in its gap, clamped),
    angles anywhere in (-4 pi, 4 pi), exactly on slices and on the table's bin edges,
    with the default 4 n bins and with very few."""
    rng = np.random.default_rng(int(full) * 10 + (bins or 0))
    n = 300
    span = 2 * np.pi - 0.3 if full else 2.2
    phi = np.sort(rng.uniform(0.0, span, n)) + 1.0
    phi[5:12] = phi[5]                                   # equal angles
    sl = geo.Slices(np.zeros(n, geo.EPI_SLICE), phi, full, np.zeros(2), True,
                    np.zeros((n, 2)), np.ones(n))
    lut = sl.lookup_table(bins)
    B = len(lut) - 1
    p32 = phi.astype(np.float32)
    two_pi = np.float32(2 * np.pi)
    base = p32[0] if full else np.float32(p32[0] - np.float32(0.5) * (two_pi - (p32[-1] - p32[0])))
    q = np.concatenate([rng.uniform(-4 * np.pi, 4 * np.pi, 20000), p32,
                        base + np.arange(B) * (2 * np.pi / B)]).astype(np.float32)
    bufs = [engine.to_device(p32), engine.to_device(lut), engine.to_device(q), engine.empty(16 * len(q))]
    try:
        engine.call("epipolar", "epi_bracket_test", len(q), DEF1, phis=bufs[0], n=n, full=int(full),
                    lut=bufs[1], bins=B, phi=bufs[2], m=len(q), out=bufs[3])
        got = engine.read(bufs[3], (len(q), 4), np.int32)
    finally:
        engine.free(*bufs)
    r = (q - base).astype(np.float32)
    r = (r - two_pi * np.floor(r / two_pi)).astype(np.float32)
    r = np.where(r >= two_pi, r - two_pi, np.maximum(r, 0)).astype(np.float32)
    x = (base + r).astype(np.float32)
    count = np.searchsorted(p32, x, side="right")
    k0 = np.clip(count - 1, 0, n - 1)
    if full:
        want = k0
    else:
        want = np.where(count - 1 < 0, 0, k0)
    assert np.array_equal(got[:, 0], want)


def test_summarize_p99_matches_numpy_percentile():
    from clscatter.methods.epipolar.svd import summarize
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 7, 200, 401):
        x = rng.exponential(size=n)
        s = summarize(x)
        assert s["samples"] == n and s["nonfinite"] == 0
        assert s["p99"] == pytest.approx(np.percentile(x, 99), rel=1e-12)
        assert s["rms"] == pytest.approx(np.sqrt(np.mean(x ** 2)), rel=1e-12)
    assert summarize(np.zeros(0))["p99"] == 0.0


def test_summarize_counts_non_finite_errors_as_failures():
    """An overflowed sample (NaN or inf: a thick medium's exponentials) is an error far
    above any tolerance, not a sample to drop: dropped, an estimate whose samples all
    overflowed would read 0 and pass."""
    from clscatter.methods.epipolar.svd import NONFINITE_ERROR, summarize
    x = np.array([1e-3, np.nan, np.inf, 2e-3])
    s = summarize(x)
    assert s["samples"] == 4 and s["nonfinite"] == 2
    assert s["rms"] == pytest.approx(np.sqrt((1e-6 + 4e-6 + 2 * NONFINITE_ERROR ** 2) / 4))
    assert summarize(np.full(3, np.nan))["rms"] == NONFINITE_ERROR
    again = summarize(s["errors"])                 # summarized twice: still counted
    assert again["nonfinite"] == 2 and again["rms"] == s["rms"]
