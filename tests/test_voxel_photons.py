"""Voxel pipeline, lighting stages: deposition (3-D DDA) and the ray equation marcher.

Deposition is compared with a dense supersampled line integral; the marcher with the
analytic solutions of the ray equation in a Luneburg lens and in a linear gradient.
"""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.methods.voxel.grid import make_box
from clscatter.methods.voxel.photons import (
    MarchSettings,
    march,
    start_state,
    upload_fields,
)


def _deposit(engine, box, kappa, a, b, flux):
    n = len(a)
    f4 = lambda x: np.concatenate([np.asarray(x, np.float32), np.zeros((n, 1), np.float32)], 1)
    bufs = [engine.to_device(f4(x)) for x in (a, b, flux)]
    kb = engine.to_device(kappa.astype(np.float32))
    rad, dirs, tr = engine.zeros(16 * box.size), engine.zeros(16 * box.size), engine.empty(16 * n)
    engine.launch(engine.kernel("voxel", "deposit_test"), n, *bufs, np.int32(n), box.lo4(),
                  box.dims4(), np.float32(box.h), kb, rad, dirs, tr)
    out = (engine.read(rad, (*box.dims, 4), np.float32), engine.read(dirs, (*box.dims, 4), np.float32),
           engine.read(tr, (n, 4), np.float32))
    engine.free(*bufs, kb, rad, dirs, tr)
    return out


def _reference(box, kappa, a, b, flux, m=20000):
    """Dense midpoint-rule line integral: m samples per segment, each assigned to the voxel
    floor((p - lo) / h) holds, flux decaying by the extinction of the voxels passed."""
    rad = np.zeros((*box.dims, 3))
    dirs = np.zeros((*box.dims, 3))
    dims = np.array(box.dims)
    for ai, bi, fi in zip(a, b, flux):
        d = bi - ai
        L = np.linalg.norm(d)
        ds = L / m
        p = ai + ((np.arange(m) + 0.5) * ds)[:, None] * d / L
        v = np.clip(np.floor((p - box.lo) / box.h).astype(int), 0, dims - 1)
        k = kappa[v[:, 0], v[:, 1], v[:, 2], :3]
        tau = np.cumsum(k, 0) * ds - 0.5 * k * ds          # optical depth at each midpoint
        e = fi[None, :] * np.exp(-tau) * ds
        np.add.at(rad, (v[:, 0], v[:, 1], v[:, 2]), e)
        np.add.at(dirs, (v[:, 0], v[:, 1], v[:, 2]), e.sum(1)[:, None] * (d / L)[None, :])
    return rad, dirs


def test_deposition_matches_dense_line_integral(engine):
    """Random segments plus segments lying in grid planes, along grid lines and through
    voxel corners; absorbing and clear voxels. Per voxel within 2 dense samples' worth of
    the reference; totals equal flux x length (clear) to 1e-5."""
    box = make_box([0, 0, 0], [1.25, 1.0, 0.875], 10)          # h = 0.125, exact in binary
    assert box.h == 0.125 and box.dims == (10, 8, 7)
    rng = np.random.default_rng(7)
    kappa = np.zeros((*box.dims, 4), np.float32)
    kappa[..., :3] = rng.random((*box.dims, 3)) * 3.0
    kappa[:5] = 0.0                                             # a clear half
    hi = box.hi
    a = list(rng.random((12, 3)) * hi)
    b = list(rng.random((12, 3)) * hi)
    h = box.h
    special = [([0.0, 3 * h, 2 * h], [hi[0], 3 * h, 2 * h]),          # along a grid line
               ([2 * h, 0.0, 0.3], [2 * h, hi[1], 0.6]),               # in a grid plane x = 2h
               ([0.0, 0.0, 0.0], [7 * h, 7 * h, 7 * h]),               # through voxel corners
               ([hi[0], hi[1], 0.5], [0.0, 0.0, 0.5]),                 # from the far corner
               ([0.3, 0.4, 0.5], [0.3, 0.4, 0.5 + 1e-4])]              # tiny
    for p, q in special:
        a.append(np.array(p))
        b.append(np.array(q))
    a, b = np.array(a), np.array(b)
    flux = rng.random((len(a), 3)) + 0.5
    rad, dirs, trans = _deposit(engine, box, kappa, a, b, flux)
    ref, ref_dirs = _reference(box, kappa, a, b, flux)
    lens = np.linalg.norm(b - a, axis=1)
    tol = 2 * (lens.max() / 20000) * flux.max()
    assert np.max(np.abs(rad[..., :3] - ref)) < tol + 1e-5 * ref.max()
    assert np.max(np.abs(dirs[..., :3] - ref_dirs)) < 3 * (tol + 1e-5 * ref.max())
    assert np.all(np.isfinite(rad)) and np.all(rad[..., 3] == 0)

    # clear grid: total deposited = flux x length for every segment, transmittance 1
    clear = np.zeros_like(kappa)
    rad0, _, trans0 = _deposit(engine, box, clear, a, b, flux)
    assert abs(rad0[..., :3].sum() / (flux * lens[:, None]).sum() - 1) < 1e-5
    assert np.allclose(trans0[:, :3], 1.0)
    # segment along the grid line deposits only in its row of voxels
    r1, _, _ = _deposit(engine, box, clear, a[12:13], b[12:13], flux[12:13])
    nz = np.argwhere(r1[..., 0] > 0)
    assert set(map(tuple, nz[:, 1:])) == {(3, 2)} and len(nz) == 10
    # transmittance returned = exp(-optical depth) of the dense reference
    for i in (0, 14):
        d = b[i] - a[i]
        p = a[i] + ((np.arange(20000) + 0.5) / 20000)[:, None] * d
        v = np.clip(np.floor(p / h).astype(int), 0, np.array(box.dims) - 1)
        tau = kappa[v[:, 0], v[:, 1], v[:, 2], :3].sum(0) * lens[i] / 20000
        assert np.allclose(trans[i, :3], np.exp(-tau), rtol=2e-3)


def _fields(engine, box, n):
    z = np.zeros((*box.dims, 4), np.float32)
    return upload_fields(engine, box, n, z, z, 0.005, 0.02, 8.0)


def _beam(engine, fields, box, pos, d):
    """March a beam of unit-flux photons (pos (N,3), common direction d) through the grid."""
    N = len(pos)
    P = np.concatenate([pos, np.ones((N, 1))], 1)
    V = np.concatenate([np.tile(np.asarray(d, float), (N, 1)), np.zeros((N, 1))], 1)  # n = 1 there
    F = np.ones((N, 4))
    return start_state(engine, P, V, F)


def _run(engine, fields, box, pos, d, adaptive, ds_min=1.0):
    st = _beam(engine, fields, box, pos, d)
    rad, dirs = engine.zeros(16 * box.size), engine.zeros(16 * box.size)
    ms = MarchSettings(adaptive=adaptive, ds_min=ds_min, min_rel=0.0)
    c = march(engine, fields, st, rad, dirs, ms)
    p, v, f = st.host(engine)
    st.free(engine)
    engine.free(rad, dirs)
    return p, v, c


def luneburg(engine, res, adaptive):
    R = 0.3
    box = make_box([-0.4, -0.4, -0.4], [0.4, 0.4, 0.4], res)
    cx, cy, cz = box.centres()
    r2 = (cx[:, None, None] ** 2 + cy[None, :, None] ** 2 + cz[None, None, :] ** 2) / R ** 2
    n = np.where(r2 < 1, np.sqrt(np.maximum(2 - r2, 1.0)), 1.0).astype(np.float32)
    fields = _fields(engine, box, n)
    rng = np.random.default_rng(2)
    rr = 0.7 * R * np.sqrt(rng.random(400))
    ph = 2 * np.pi * rng.random(400)
    pos = np.stack([np.full(400, box.lo[0]), rr * np.cos(ph), rr * np.sin(ph)], 1)
    p, v, c = _run(engine, fields, box, pos, [1, 0, 0], adaptive)
    fields.free(engine)
    # back-project each final straight ray onto the sphere: the point where it left
    d = v[:, :3] / np.linalg.norm(v[:, :3], axis=1, keepdims=True)
    x = p[:, :3].astype(np.float64)
    bq = (x * d).sum(1)
    disc = bq ** 2 - ((x * x).sum(1) - R * R)
    t = bq - np.sqrt(np.maximum(disc, 0))                      # nearest crossing behind x
    exitp = x - t[:, None] * d
    err = np.linalg.norm(exitp - [R, 0, 0], axis=1)
    return np.sqrt(np.mean(err ** 2)), box.h, c


@pytest.mark.parametrize("adaptive", [True, False])
def test_luneburg_focus(engine, adaptive):
    """A parallel beam (70% of the aperture) through a Luneburg lens n = sqrt(2 - (r/R)^2)
    leaves it at the antipodal point: RMS distance of the exit points from the antipode
    below 1 voxel at 48^3 and 96^3 (measured 0.41-0.52 voxel), and smaller in scene units
    at 96^3 (convergence)."""
    e48, h48, c48 = luneburg(engine, 48, adaptive)
    e96, h96, c96 = luneburg(engine, 96, adaptive)
    print(f"adaptive={adaptive}: rms focal error {e48 / h48:.3f} voxel (48^3, {c48['steps']} steps), "
          f"{e96 / h96:.3f} voxel (96^3, {c96['steps']} steps), R = {0.3 / h48:.0f} / {0.3 / h96:.0f} voxels")
    assert e48 < h48 and e96 < h96
    assert e96 < 0.8 * e48
    assert c48["live_at_end"] == 0


def _arc_error(engine, fields, box, a, adaptive, ds_min):
    y0 = np.linspace(0.1, 0.5, 9)
    pos = np.stack([np.full(9, box.lo[0]), y0, np.full(9, 0.125), np.ones(9)], 1)
    st = start_state(engine, pos, np.stack([1.2 + a * y0, 0 * y0, 0 * y0, 0 * y0], 1), np.ones((9, 4)))
    rad, dirs = engine.zeros(16 * box.size), engine.zeros(16 * box.size)
    c = march(engine, fields, st, rad, dirs, MarchSettings(adaptive=adaptive, ds_min=ds_min, min_rel=0.0))
    p, v, _ = st.host(engine)
    st.free(engine)
    engine.free(rad, dirs)
    cc = 1.2 + a * y0
    xf = p[:, 0]
    ycat = y0 + cc / a * (np.cosh(a * xf / cc) - 1)
    assert np.all(xf > 0.999 * box.hi[0])              # all left through the far face
    assert np.min(ycat - y0) / box.h > 9               # the bend is large against the bounds
    return np.max(np.abs(p[:, 1] - ycat)) / box.h, c["steps"]


def test_linear_gradient_arc(engine):
    """n = c0 + a y bends a horizontal ray on the catenary y - y0 = (c/a)(cosh(a x / c) - 1),
    c = n(y0) (n cos(theta) is conserved), rising ~10 voxels over the grid. The forward
    Euler scheme of the paper is first order: fixed steps of 1, 1/2, 1/4 voxel give errors
    below 0.2 voxel that halve with the step; adaptive steps (4-voxel octree nodes here,
    eps2 = 0.02) stay below 0.8 voxel with 3.5x fewer steps than the 1-voxel marcher."""
    box = make_box([0, 0, 0], [1, 1, 0.25], 64)
    a = 0.4
    n = (1.2 + a * box.centres()[1])[None, :, None] * np.ones(box.dims)
    fields = _fields(engine, box, n.astype(np.float32))
    e1, s1 = _arc_error(engine, fields, box, a, False, 1.0)
    e2, _ = _arc_error(engine, fields, box, a, False, 0.5)
    e4, _ = _arc_error(engine, fields, box, a, False, 0.25)
    ea, sa = _arc_error(engine, fields, box, a, True, 1.0)
    fields.free(engine)
    print(f"arc errors (voxels): fixed 1: {e1:.3f}, 1/2: {e2:.3f}, 1/4: {e4:.3f}; adaptive {ea:.3f} "
          f"({sa} steps vs {s1})")
    assert e1 < 0.2 and 1.7 < e1 / e2 < 2.3 and 1.7 < e2 / e4 < 2.3
    assert ea < 0.8 and sa * 3.5 < s1


def _light_scene(tmp_path, light):
    """A grid volume of n = 1 over [-0.5, 0.5]^3 (the medium's coefficients inside too) in
    a bounded absorbing medium; the voxel pipeline's fields and lighting pass only."""
    from clscatter.methods import configure
    from clscatter.methods.voxel.pipeline import Pipeline
    from clscatter.scene.loader import scene_from_dict
    from clscatter.transport.prepared import prepare_scene
    np.save(tmp_path / "ones.npy", np.ones((4, 4, 4)))
    d = {"camera": {"origin": [0, 0, 5], "target": [0, 0, 0], "resolution": [8, 8], "spp": 1},
         "medium": {"sigma_s": 0.0, "sigma_a": 0.3, "bounds": {"min": [-2, -2, -2], "max": [2, 2, 2]}},
         "lights": [light],
         "volumes": [{"grid": "ones.npy", "bounds": {"min": [-0.5] * 3, "max": [0.5] * 3},
                      "sigma_a": 0.3}]}
    s = scene_from_dict(d, base_dir=tmp_path)
    params = configure("voxel", {"resolution": 20, "margin": 0.0, "photons": 1 << 16})
    return s, Pipeline(params), prepare_scene


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_photon_fluence_is_analytic(engine, tmp_path, kind):
    """Emission + marching + deposition normalisation: deposited flux x length / voxel
    volume is the fluence rate, E exp(-kappa depth) under a directional light and
    I / d^2 exp(-kappa d) around a point light (d in scene units; I / d^2 per scene unit^2
    is I / d^2 / scale^2 per normalised unit^2, as frame.py rescales intensities)."""
    if kind == "directional":
        light = {"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}
    else:
        light = {"type": "point", "position": [0.2, 1.5, -0.1], "intensity": 3.0}
    s, pipe, prepare = _light_scene(tmp_path, light)
    ps = prepare(s, engine)
    try:
        pipe._geometry(ps)
        pipe._material(ps)
        pipe._lighting(ps)
        box = pipe.box
        rad, _ = pipe.radiance.host(engine, box)
        c = pipe.radiance.counters
        assert c["voxel_photons_unfinished"] == 0
        # nothing inside the grid stops a photon: every one counted entering (an atomic
        # in photon_emit) leaves it (appended by photon_exits)
        assert c["voxel_photons_entering"] == c["voxel_photons_leaving"] > 0.6 * c["voxel_photons"]
    finally:
        pipe.release(engine)
        ps.release()
    scale = ps.frame.scale
    fluence = rad[..., 0] / box.h ** 3                   # W per normalised unit^2
    cx, cy, cz = (c * scale + ps.frame.centre[a] for a, c in enumerate(box.centres()))
    X, Y, Z = np.meshgrid(cx, cy, cz, indexing="ij")
    if kind == "directional":
        ref = 2.0 * np.exp(-0.3 * (2.0 - Y))
    else:
        dist = np.sqrt((X - 0.2) ** 2 + (Y - 1.5) ** 2 + (Z + 0.1) ** 2)
        ref = 3.0 / dist ** 2 * np.exp(-0.3 * dist)      # the light is inside the medium
        ref = ref / scale ** 2                           # fluence per normalised unit^2
    inner = (slice(1, -1),) * 3                          # 3x3x3 smoothing clamps at the faces
    rel = fluence[inner] / ref[inner] - 1
    print(f"{kind}: fluence / analytic - 1: mean {rel.mean():.4f}, rms {np.sqrt((rel ** 2).mean()):.4f}, "
          f"max {np.abs(rel).max():.4f}")
    # measured: mean -0.0002 / 0.0010, rms 0.0039 / 0.0056, max 0.011 / 0.054
    # (directional / point); bounds about 2x
    assert abs(rel.mean()) < 0.003 and np.sqrt((rel ** 2).mean()) < 0.012 and np.abs(rel).max() < 0.1
