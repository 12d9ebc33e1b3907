"""Kernels of ``cl_kernels/shared/density.h`` against NumPy doing the same maths in float64:
the density at points (trilinear between voxel centres, clamped to the outermost centres
up to the box faces, 0 outside), sigma_s at points (the grids replace the scene medium in
their boxes, overlapping boxes add), the integral of the density along rays (exact:
piecewise cubic between centre planes; the reference integrates every piece with 3-point
Gauss-Legendre, exact to degree 5, an independent rule from the kernel's Simpson), the
scene medium's length outside the boxes, and the optical depth; and a linear density
ramp against the closed-form transmittance, optical depth 0.01 to 10.

Measured (PoCL CPU): densities and sigma_s at points within 2.3e-7 of the peak; integrals
within 2.6e-7 of max density x length, the medium's length within 2.6e-7; optical depths
within 6.2e-6 relative (floor 1e-3); the ramp's within 3.3e-7. Bounds (float32 rounding):
5e-7, 5e-7, 5e-7, 1.2e-5 and 1e-6."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from clscatter.device import add_kernel_dir
from clscatter.estimators.density_march import density_buffer
from clscatter.scene.model import Camera, Medium, Scene, Volume
from clscatter.scene.normalised import Frame, medium_struct

add_kernel_dir(Path(__file__).parent / "kernels")        # density_test.cl (test hooks)
GL = (np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]), np.array([5.0, 8.0, 5.0]) / 9.0)


# ---- NumPy reference --------------------------------------------------------------------

def ref_density(values, lo, hi, p):
    """Density of one grid at points p (N, 3), float64."""
    values = np.asarray(values, np.float64)
    n = np.array(values.shape)
    u = (p - lo) / (hi - lo) * n - 0.5
    u = np.clip(u, 0.0, n - 1)
    i0 = np.minimum(np.floor(u).astype(int), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    f = u - i0
    out = np.zeros(len(p))
    for corner in np.ndindex(2, 2, 2):
        idx = [np.where(c, i1[:, a], i0[:, a]) for a, c in enumerate(corner)]
        w = np.prod([np.where(c, f[:, a], 1.0 - f[:, a]) for a, c in enumerate(corner)], axis=0)
        out += w * values[idx[0], idx[1], idx[2]]
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    return np.where(inside, out, 0.0)


def clip(o, d, lo, hi, t0, t1):
    """The part of [t0, t1] of the ray o + t d inside the box [lo, hi] (None if empty)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    ta = np.where(np.isnan(ta), -np.inf, ta)
    tb = np.where(np.isnan(tb), np.inf, tb)
    a = max(t0, np.max(np.minimum(ta, tb)))
    b = min(t1, np.min(np.maximum(ta, tb)))
    return (a, b) if b > a else None


def ref_integral(values, lo, hi, o, d, t0, t1):
    """The density's integral along o + t d over [t0, t1]: Gauss-Legendre on every piece
    between the planes through voxel centres."""
    span = clip(o, d, lo, hi, t0, t1)
    if span is None:
        return 0.0
    a, b = span
    n = np.array(values.shape)
    scale = n / (hi - lo)
    cuts = [a, b]
    for ax in range(3):
        if d[ax] == 0:
            continue
        for k in range(n[ax]):
            t = ((k + 0.5) / scale[ax] + lo[ax] - o[ax]) / d[ax]
            if a < t < b:
                cuts.append(t)
    cuts = np.sort(cuts)
    x, w = GL
    total = 0.0
    for s, e in zip(cuts[:-1], cuts[1:]):
        t = 0.5 * (s + e) + 0.5 * (e - s) * x
        total += 0.5 * (e - s) * np.sum(w * ref_density(values, lo, hi, o + t[:, None] * d))
    return total


def ref_hom_length(med_lo, med_hi, boxes, o, d, t0, t1):
    """Length of [t0, t1] inside the medium's box and outside every grid box."""
    span = clip(o, d, med_lo, med_hi, t0, t1)
    if span is None:
        return 0.0
    h0, h1 = span
    pieces = sorted(p for p in (clip(o, d, lo, hi, h0, h1) for lo, hi in boxes) if p)
    covered, cs, ce = 0.0, h0, h0
    for s, e in pieces:
        if s > ce:
            covered += ce - cs
            cs, ce = s, e
        else:
            ce = max(ce, e)
    return h1 - h0 - (covered + ce - cs)


# ---- the scene under test ---------------------------------------------------------------

def scene_with(volumes, medium=None):
    cam = Camera(origin=np.array([0.0, 0.0, 5.0]), target=np.zeros(3), up=np.array([0.0, 1.0, 0.0]))
    return Scene(camera=cam, medium=medium, volumes=volumes)


def density_volume(values, lo, hi, ss, sa):
    return Volume(ior=1.0, sigma_s=np.asarray(ss, float), sigma_a=np.asarray(sa, float),
                  grid_bounds=(np.asarray(lo, float), np.asarray(hi, float)),
                  density=np.asarray(values, np.float32), key="volumes[0]")


def upload(engine, scene):
    frame = Frame(centre=np.zeros(3), scale=1.0)        # the normalised frame is the world
    return engine.to_device(density_buffer(scene, frame, medium_struct(scene.medium, frame)))


def run_rays(engine, buf, o, d, span):
    n = len(o)

    def f4(a):
        return np.concatenate([a, np.zeros((n, 1))], 1).astype(np.float32)

    ins = [engine.to_device(f4(o)), engine.to_device(f4(d)),
           engine.to_device(np.asarray(span, np.float32))]
    outs = [engine.empty(4 * n), engine.empty(4 * n), engine.empty(16 * n)]
    try:
        engine.call("density_test", "density_rays", n, medium=buf, o=ins[0], d=ins[1],
                    span=ins[2], n=n, integral=outs[0], hom_len=outs[1], tau=outs[2])
        return (engine.read(outs[0], n, np.float32), engine.read(outs[1], n, np.float32),
                engine.read(outs[2], (n, 4), np.float32))
    finally:
        engine.free(*ins, *outs)


@pytest.fixture(scope="module")
def grids_scene():
    rng = np.random.default_rng(5)
    g1 = rng.uniform(0.0, 2.0, (5, 7, 4))
    g2 = rng.uniform(0.0, 1.0, (3, 1, 6))                  # one voxel along y: clamped
    # boxes on float32-exact coordinates: points on their faces are on them on the device too
    v1 = density_volume(g1, [-0.5, -0.375, -0.25], [0.25, 0.5, 0.125], [0.7, 0.8, 0.9],
                        [0.1, 0.0, 0.2])
    v2 = density_volume(g2, [0.0, -0.25, -0.125], [0.625, 0.25, 0.5], [0.3, 0.2, 0.1], 0.4)
    med = Medium(sigma_s=np.full(3, 0.25), sigma_a=np.full(3, 0.05), g=0.3,
                 bounds=(np.array([-0.75, -0.625, -0.25]), np.array([0.375, 0.4375, 0.625])))
    return scene_with([v1, v2], med)


def test_density_and_sigma_s_at_points(engine, grids_scene):
    """Points inside, on the faces of, and outside both boxes and the medium."""
    v1, v2 = grids_scene.volumes
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.8, 0.8, (4000, 3))
    p[:200] = v1.grid_bounds[0] + rng.integers(0, 2, (200, 3)) * (v1.grid_bounds[1] - v1.grid_bounds[0])
    p = p.astype(np.float32).astype(np.float64)            # exactly what the kernel gets
    buf = upload(engine, grids_scene)
    n = len(p)
    pts = engine.to_device(np.concatenate([p, np.zeros((n, 1))], 1).astype(np.float32))
    dens, ss = engine.empty(4 * n), engine.empty(16 * n)
    try:
        engine.call("density_test", "density_points", n, medium=buf, p=pts, n=n, dens=dens,
                    sigma_s=ss)
        got_d = engine.read(dens, n, np.float32)
        got_s = engine.read(ss, (n, 4), np.float32)[:, :3]
    finally:
        engine.free(buf, pts, dens, ss)
    d1 = ref_density(v1.density, *v1.grid_bounds, p)
    d2 = ref_density(v2.density, *v2.grid_bounds, p)
    assert np.max(np.abs(got_d - d1)) <= 5e-7 * v1.density.max()
    in1 = np.all((p >= v1.grid_bounds[0]) & (p <= v1.grid_bounds[1]), axis=1)
    in2 = np.all((p >= v2.grid_bounds[0]) & (p <= v2.grid_bounds[1]), axis=1)
    med = grids_scene.medium
    in_med = np.all((p >= med.bounds[0]) & (p <= med.bounds[1]), axis=1)
    ref_s = d1[:, None] * v1.sigma_s + d2[:, None] * v2.sigma_s
    ref_s = np.where((in_med & ~in1 & ~in2)[:, None], med.sigma_s, ref_s)
    assert in1.sum() > 300 and in2.sum() > 100 and (in_med & ~in1 & ~in2).sum() > 300
    assert np.max(np.abs(got_s - ref_s)) <= 5e-7 * float(np.max(ref_s))


def test_integrals_and_optical_depths(engine, grids_scene):
    """Random rays (some axis-aligned, some starting inside), random spans: the density
    integral of the first grid, the medium's length outside the boxes, and the optical
    depth of everything."""
    v1, v2 = grids_scene.volumes
    med = grids_scene.medium
    rng = np.random.default_rng(2)
    n = 600
    o = rng.uniform(-1.0, 1.0, (n, 3))
    d = rng.uniform(-0.4, 0.4, (n, 3)) - o                   # through the boxes, mostly
    d[:60, 1:] = 0.0                                         # along x
    o[:60, 1:] = rng.uniform(-0.3, 0.3, (60, 2))
    d[60:120, 0] = 0.0                                       # in a yz plane
    o[60:120, 0] = rng.uniform(-0.4, 0.2, 60)
    o[120:200] = rng.uniform(0.0, 0.1, (80, 3))              # inside both
    d[120:200] = rng.normal(size=(80, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    span = np.sort(rng.uniform(-0.5, 2.5, (n, 2)), axis=1)
    span[:100] = [0.0, 10.0]
    span = span.astype(np.float32).astype(np.float64)
    buf = upload(engine, grids_scene)
    try:
        integral, hom, tau = run_rays(engine, buf, o, d, span)
    finally:
        engine.free(buf)
    boxes = [v1.grid_bounds, v2.grid_bounds]
    ref_i = np.array([ref_integral(v1.density.astype(np.float64), *v1.grid_bounds, o[i], d[i], *span[i])
                      for i in range(n)])
    ref_i2 = np.array([ref_integral(v2.density.astype(np.float64), *v2.grid_bounds, o[i], d[i], *span[i])
                       for i in range(n)])
    ref_h = np.array([ref_hom_length(*med.bounds, boxes, o[i], d[i], *span[i]) for i in range(n)])
    ref_t = (ref_i[:, None] * (v1.sigma_s + v1.sigma_a) + ref_i2[:, None] * (v2.sigma_s + v2.sigma_a)
             + ref_h[:, None] * med.kappa)
    assert (ref_i > 0).sum() > 200 and (ref_h > 0).sum() > 200
    scale = float(v1.density.max()) * np.maximum(span[:, 1] - span[:, 0], 1e-3)
    err_i = np.abs(integral - ref_i) / scale
    assert err_i.max() <= 5e-7, f"integral error {err_i.max():.3g} of max density x length"
    assert np.max(np.abs(hom - ref_h)) <= 5e-7
    err_t = np.abs(tau[:, :3] - ref_t) / (np.abs(ref_t) + 1e-3)
    assert err_t.max() <= 1.2e-5, f"optical depth relative error {err_t.max():.3g}"


@pytest.mark.parametrize("depth", [0.01, 0.1, 1.0, 10.0])
def test_linear_ramp_transmittance_closed_form(engine, depth):
    """density = a + b i along x (constant in y, z) over [0, 2] x [0, 1]^2, 16 voxels
    along x: along any ray through both x faces, the integral is (F / |d_x|) with F the
    closed-form integral of the clamped ramp over x (half a voxel of v_0, the trapezoids
    between centres, half a voxel of v_15); kappa is set so kappa F = ``depth``, and
    exp(-optical depth) is compared with exp(-depth / |d_x|)."""
    nx, h = 16, 2.0 / 16
    v = 0.2 + 0.1 * np.arange(nx)
    grid = np.broadcast_to(v[:, None, None], (nx, 3, 2)).copy()
    F = h / 2 * v[0] + h * np.sum((v[1:] + v[:-1]) / 2) + h / 2 * v[-1]
    kappa = depth / F
    scene = scene_with([density_volume(grid, [0, 0, 0], [2, 1, 1], 0.0, kappa)])
    rng = np.random.default_rng(3)
    m = 64
    o = np.column_stack([np.full(m, -1.0), rng.uniform(0.3, 0.7, m), rng.uniform(0.3, 0.7, m)])
    d = np.column_stack([np.ones(m), rng.uniform(-0.1, 0.1, m), rng.uniform(-0.1, 0.1, m)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    buf = upload(engine, scene)
    try:
        _, _, tau = run_rays(engine, buf, o, d, np.tile([0.0, 10.0], (m, 1)))
    finally:
        engine.free(buf)
    expected = depth / d[:, 0]
    rel = np.abs(tau[:, 0] - expected) / expected
    assert rel.max() <= 1e-6, f"optical depth {depth}: relative error {rel.max():.3g}"
    T = np.exp(-tau[:, 0].astype(np.float64))
    assert np.allclose(T, np.exp(-expected), rtol=1e-4, atol=0.0)
