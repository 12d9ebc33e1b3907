"""Voxel pipeline, grid stages: voxelisation, blur, gradient, octree, struct layout.

Each kernel is checked against a plain NumPy/trimesh/scipy computation of the same maths.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from layout import layout_mismatches
from scipy.ndimage import convolve1d

from clscatter.methods.voxel.grid import VOX_RAY, make_box
from clscatter.methods.voxel.octree import build_octree, octree_reference
from clscatter.methods.voxel.voxelise import (
    SMOOTH_TAPS,
    blur,
    box_coverage,
    gaussian_taps,
    gradient,
    inside_grid,
    mesh_coverage,
)


def test_voxray_layout(engine):
    assert layout_mismatches(engine, "voxel.h", {"VoxRay": VOX_RAY}) == []


def winding_inside(mesh: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    """Independent inside test: generalised winding number (sum of the solid angles of the
    triangles seen from each point, Van Oosterom & Strackee), > 1/2 inside. trimesh's own
    ``contains`` needs the optional rtree package, which this environment lacks."""
    tri = mesh.vertices[mesh.faces]
    out = np.empty(len(pts), bool)
    for s in range(0, len(pts), 512):
        p = pts[s:s + 512]
        a, b, c = (tri[None, :, k, :] - p[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc
               + np.einsum("ptk,ptk->pt", b, c) * la + np.einsum("ptk,ptk->pt", c, a) * lb)
        w = 2 * np.arctan2(det, den).sum(axis=1) / (4 * np.pi)
        out[s:s + 512] = np.abs(w) > 0.5
    return out


def _meshes():
    rot = trimesh.transformations.rotation_matrix(0.5, [1, 2, 3])
    box = trimesh.creation.box(extents=[0.7, 0.45, 0.3], transform=rot)
    torus = trimesh.creation.torus(major_radius=0.3, minor_radius=0.12, major_sections=32,
                                   minor_sections=12)
    torus.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1, 0, 0.3]))
    return {"sphere": trimesh.creation.icosphere(3, radius=0.37), "box": box, "torus": torus}


@pytest.mark.parametrize("name", ["sphere", "box", "torus"])
def test_voxelisation_matches_trimesh(engine, name):
    """Inside test at the centres equals a winding-number test's; coverage of mixed voxels equals the
    4^3 sub-sample fraction by an independent winding-number inside test;
    total covered volume within 1.5% of the mesh volume."""
    mesh = _meshes()[name]
    box = make_box(mesh.bounds[0] - 0.05, mesh.bounds[1] + 0.05, 16)
    tris = mesh.vertices[mesh.faces]
    cx, cy, cz = box.centres()
    pts = np.stack(np.meshgrid(cx, cy, cz, indexing="ij"), -1).reshape(-1, 3)
    ref_in = winding_inside(mesh, pts).reshape(box.dims)
    got_in = inside_grid(engine, box, tris)
    assert np.array_equal(got_in.astype(bool), ref_in), int((got_in.astype(bool) != ref_in).sum())

    cov = mesh_coverage(engine, box, tris)
    full = mesh_coverage(engine, box, tris, refine_all=True)
    assert np.array_equal(cov, full)          # refining only mixed neighbourhoods loses nothing
    mixed = np.argwhere((cov > 0) & (cov < 1))
    assert len(mixed) > 50
    sel = mixed[np.random.default_rng(1).choice(len(mixed), min(60, len(mixed)), replace=False)]
    off = (np.arange(4) + 0.5) / 4
    sub = np.stack(np.meshgrid(off, off, off, indexing="ij"), -1).reshape(-1, 3)
    sp = (box.lo + (sel[:, None, :] + sub[None]) * box.h).reshape(-1, 3)
    ref_cov = winding_inside(mesh, sp).reshape(len(sel), 64).mean(axis=1)
    err = np.abs(cov[tuple(sel.T)] - ref_cov)
    assert err.max() <= 1.0 / 64 + 1e-6, err.max()    # at most one sub-sample on the surface
    assert err.mean() < 2e-3
    vol = cov.sum() * box.h ** 3
    assert abs(vol / mesh.volume - 1) < 0.015, (vol, mesh.volume)


def test_box_coverage_exact():
    box = make_box([0, 0, 0], [1, 1, 1], 10)
    c = box_coverage(box, [0.15, 0.2, 0.0], [0.55, 0.63, 0.35])
    assert abs(c.sum() * box.h ** 3 - 0.4 * 0.43 * 0.35) < 1e-6
    assert c[2, 3, 0] == 1.0 and abs(c[1, 2, 3] - 0.5 * 1.0 * 0.5) < 1e-6


@pytest.mark.parametrize("channels", [3, 4])
def test_blur_matches_numpy(engine, channels):
    """Gaussian 9 taps (sigma 1.5) and the 3-tap smoothing, 3 channels (vox_blur) and
    float4 grids (vox_blur4), against scipy with clamped ('nearest') edges."""
    rng = np.random.default_rng(3)
    g = rng.random((13, 9, 11, channels)).astype(np.float32)
    taps = gaussian_taps(9)
    assert abs(taps.sum() - 1) < 1e-6 and abs(taps[4] / taps[3] - np.exp(0.5 / 1.5 ** 2)) < 1e-5
    for w in (taps, SMOOTH_TAPS):
        ref = g.astype(np.float64)
        for axis in range(3):
            ref = convolve1d(ref, w.astype(np.float64), axis=axis, mode="nearest")
        got = blur(engine, g, w)
        assert np.max(np.abs(got - ref)) < 2e-6


def test_gradient_matches_numpy(engine):
    rng = np.random.default_rng(4)
    box = make_box([0, 0, 0], [1.0, 0.7, 0.5], 14)
    n = (1 + 0.3 * rng.random(box.dims)).astype(np.float32)
    nb = engine.to_device(n)
    gb = gradient(engine, box, nb)
    got = engine.read(gb, (*box.dims, 4), np.float32)
    engine.free(nb, gb)
    ref = np.stack(np.gradient(n.astype(np.float64), box.h), -1)   # one-sided at faces
    assert np.max(np.abs(got[..., :3] - ref)) < 1e-3 * np.abs(ref).max()
    assert np.all(got[..., 3] == 0)


@pytest.mark.parametrize("dims", [(16, 16, 16), (21, 13, 9)])
def test_octree_matches_numpy(engine, dims):
    """Level and step-limit grids equal the NumPy reference (flat regions, a smooth bump
    with ranges between eps and eps2, and noise)."""
    box = make_box([0, 0, 0], np.array(dims, float) / max(dims), max(dims))
    assert box.dims == dims
    idx = np.indices(dims).astype(np.float64)
    r = np.sqrt(sum((i - d / 2) ** 2 for i, d in zip(idx, dims)))
    n = 1 + 0.3 * np.clip(1 - r / (0.4 * max(dims)), 0, 1) ** 2
    n[:3, :3, :3] += 0.004 * np.random.default_rng(5).random((3, 3, 3))
    n = n.astype(np.float32)
    nb = engine.to_device(n)
    oc = build_octree(engine, box, nb, 0.005, 0.02, 8.0)
    level = engine.read(oc.level, dims, np.uint8)
    smax = engine.read(oc.smax, dims, np.float32)
    oc.free(engine)
    engine.free(nb)
    ref_level, ref_smax = octree_reference(n, 0.005, 0.02, 8.0)
    assert np.array_equal(level, ref_level)
    assert np.array_equal(smax, ref_smax)
    # the test is not vacuous: several levels and both kinds of step limit occur
    assert len(np.unique(level)) >= 3 and np.isinf(smax).any() and (smax == 8).any()


def test_grid_volume_fields():
    """A grid volume's n (and per-voxel sigma grids, when the volume carries them) at the
    voxel centres: trilinear between its data's centres (exact for a linear field), the
    nearest centre's value beyond the outermost ones; sigma converted to the frame's units."""
    from clscatter.methods.voxel.voxelise import volume_fields
    from clscatter.scene.model import Volume
    from clscatter.scene.normalised import Frame
    bmin, bmax = np.array([-1.0, -0.5, -0.5]), np.array([1.0, 0.5, 0.5])
    shape = (8, 4, 4)
    c = [bmin[a] + (np.arange(shape[a]) + 0.5) * (bmax[a] - bmin[a]) / shape[a] for a in range(3)]
    lin = lambda x, y, z: 1.2 + 0.1 * x - 0.05 * y + 0.02 * z
    data = lin(*np.meshgrid(*c, indexing="ij"))
    v = Volume(ior=float(data.max()), sigma_s=np.full(3, 0.1), sigma_a=np.zeros(3), grid=data,
               grid_bounds=(bmin, bmax))
    v.sigma_s_grid = 0.5 * np.ones(shape)
    frame = Frame(centre=np.zeros(3), scale=2.0)              # normalised = world / 2
    box = make_box(bmin / 2, bmax / 2, 24)
    n, ss, sa = volume_fields(box, v, frame)
    X, Y, Z = np.meshgrid(*(cc * 2 for cc in box.centres()), indexing="ij")   # world units
    cl = [np.clip(q, cc[0], cc[-1]) for q, cc in zip((X, Y, Z), c)]
    assert np.max(np.abs(n - lin(*cl))) < 1e-5
    assert np.allclose(ss, 0.5 * 2.0) and ss.shape == (*box.dims, 3)   # sigma' = sigma * scale
    assert np.allclose(sa, 0.0)
