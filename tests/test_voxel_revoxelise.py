"""Voxel pipeline in a session: a geometry change voxelises again only the volumes whose
own shape (or the grid box) changed; a material edit voxelises nothing."""
from __future__ import annotations

import copy

import numpy as np

from clscatter.device import Engine
from clscatter.methods.voxel import Voxel, as_volume_scene
from clscatter.methods.voxel.grid import GridBox, scene_box
from clscatter.methods.voxel.pipeline import (
    Pipeline,
    contribution_key,
    kept_contributions,
)
from clscatter.methods.voxel.voxelise import blur, gaussian_taps, volume_weight
from clscatter.pipeline.relighter import Relighter
from clscatter.pipeline.render import render
from clscatter.scene.builtin.volumes import VOLUME_SCENES
from clscatter.scene.loader import scene_from_dict
from clscatter.scene.model import Scene
from clscatter.transport.prepared import prepare_scene

VOXEL = {"resolution": 20, "photons": 1 << 12, "margin": 0.25}


def _two_volumes() -> Scene:
    """A small refractive sphere volume (ior 1.3, radius 0.2) beside a larger voxelised
    glass ball (dielectric object, ior 1.5, radius 0.3) in fog under a wide spot light.
    The glass ball spans the union box in y and z, so the small volume moves inside the
    grid box along those axes without changing it; the floor fixes the normalised frame."""
    d = VOLUME_SCENES["volume_sphere"]()
    d["camera"].update(resolution=[40, 30], spp=1)
    d["lights"][0]["cutoff_angle"] = 30.0
    d["volumes"][0].update(center=[-0.45, 1.6, 0.0], radius=0.2)
    d["materials"]["glass"] = {"type": "dielectric", "ior": 1.5}
    d["objects"].append({"shape": "sphere", "center": [0.35, 1.6, 0.0], "radius": 0.3,
                         "material": "glass"})
    d["render"]["voxel"] = dict(VOXEL)
    return scene_from_dict(d)


def _pipe(rl: Relighter) -> Pipeline:
    return rl._caches["voxel"]["pipeline"].pipe


def _fresh_weights(scene: Scene, engine: Engine) -> list[np.ndarray]:
    """The blurred weights of a whole-scene voxelisation of ``scene``: every volume's
    coverage on the grid box, blurred, nothing kept (the geometry stage as it was before
    contributions were kept)."""
    ps = prepare_scene(as_volume_scene(scene, True), engine)
    try:
        box = scene_box(ps.scene, ps.frame, VOXEL["resolution"], VOXEL["margin"])
        return [blur(engine, volume_weight(engine, box, v, ps.frame), gaussian_taps())
                for v in ps.scene.volumes]
    finally:
        ps.release()


def test_moving_one_volume_revoxelises_only_it(engine):
    """Moving the small volume by (0, 0.05, 0.04) inside the grid box re-runs the geometry
    stage (the session re-prepares the scene and drops the method's cache) but voxelises
    only that volume (``voxel_revoxelised``); the glass ball's contribution is the same
    array as before, kept for the engine. The weights equal a fresh whole-scene
    voxelisation of the moved scene bit for bit, and the frame equals a fresh render of it
    to float tolerance (photon deposits are float atomics summed in any order: rtol 1e-4,
    atol 1e-5 of the maximum). Moving the volume out past the box's face (-0.3 in x)
    changes the box: every volume is voxelised again."""
    Voxel.release_cache(engine)
    rl = Relighter(_two_volumes(), engine=engine)
    try:
        rl.frame()
        assert rl.stats["ran"] == ["geometry", "material", "lighting", "view"]
        assert sorted(rl.stats["voxel_revoxelised"]) == ["objects[1]", "volumes[0]"]
        box0 = _pipe(rl).box
        small0, glass0 = _pipe(rl).weights

        rl.set_geometry(0, translate=[0.0, 0.05, 0.04])
        img = rl.frame()
        pipe = _pipe(rl)
        assert rl.stats["ran"] == ["geometry", "material", "lighting", "view"]
        assert rl.stats["voxel_revoxelised"] == ["volumes[0]"]
        assert np.array_equal(pipe.box.lo, box0.lo) and pipe.box.h == box0.h
        assert pipe.box.dims == box0.dims
        assert pipe.weights[1] is glass0
        assert len(kept_contributions(engine)) == 2

        moved = copy.deepcopy(rl.scene)
        fresh_w = _fresh_weights(moved, engine)
        assert len(fresh_w) == len(pipe.weights) == 2
        for a, b in zip(pipe.weights, fresh_w):
            assert a.shape == b.shape and np.array_equal(a, b)
        # the moved volume did move: its weight differs from before
        assert np.abs(pipe.weights[0] - small0).max() > 0.05   # 0.083: 0.66 voxel moved
        Voxel.release_cache(engine)
        fresh = render(moved, method="voxel", engine=engine, show_progress=False)
        assert sorted(fresh.stats["voxel_revoxelised"]) == ["objects[1]", "volumes[0]"]
        assert fresh.image.max() > 0
        diff = np.abs(img - fresh.image).max()
        print(f"moved volume: max |frame - fresh| {diff:.3e} of max {fresh.image.max():.3e}")
        assert np.allclose(img, fresh.image, rtol=1e-4, atol=1e-5 * fresh.image.max())

        rl.set_geometry(0, translate=[-0.3, 0.0, 0.0])
        rl.frame()
        assert sorted(rl.stats["voxel_revoxelised"]) == ["objects[1]", "volumes[0]"]
        assert not np.array_equal(_pipe(rl).box.lo, box0.lo)
        assert _pipe(rl).weights[1] is not glass0
        assert len(kept_contributions(engine)) == 2
    finally:
        rl.close()


def test_material_edit_voxelises_nothing(engine):
    """A volume's ior and sigma_a, then the glass's ior, edited: material, lighting and
    view run, no volume is voxelised again and the weights are the same arrays; the
    images change."""
    rl = Relighter(_two_volumes(), engine=engine)
    try:
        img0 = rl.frame()
        weights = list(_pipe(rl).weights)
        rl.set_volume(0, ior=1.1, sigma_a=[0.0, 0.1, 0.2])
        img1 = rl.frame()
        assert rl.stats["ran"] == ["material", "lighting", "view"]
        assert rl.stats["voxel_revoxelised"] == []
        rl.set_material("glass", ior=1.3)
        img2 = rl.frame()
        assert rl.stats["ran"] == ["material", "lighting", "view"]
        assert rl.stats["voxel_revoxelised"] == []
        assert all(a is b for a, b in zip(_pipe(rl).weights, weights))
        assert not np.allclose(img0, img1) and not np.allclose(img1, img2)
    finally:
        rl.close()


def test_contribution_key_reads_the_shape_box_and_frame(engine):
    """The key changes with the volume's vertices, the box (corner, voxel side, dims) and
    the frame, and not with its index or coefficients."""
    scene = as_volume_scene(_two_volumes(), True)
    ps = prepare_scene(scene, engine)
    try:
        box = scene_box(ps.scene, ps.frame, 20, 0.25)
        v = copy.deepcopy(ps.scene.volumes[0])
        k = contribution_key(box, v, ps.frame)
        v2 = copy.deepcopy(v)
        v2.ior, v2.sigma_a = 1.7, np.array([1.0, 2.0, 3.0])
        assert contribution_key(box, v2, ps.frame) == k
        v2.mesh.vertices = v2.mesh.vertices + np.array([0.0, 1e-9, 0.0])
        assert contribution_key(box, v2, ps.frame) != k
        assert contribution_key(GridBox(box.lo + 1e-9, box.h, box.dims), v, ps.frame) != k
        assert contribution_key(GridBox(box.lo, box.h * (1 + 1e-12), box.dims), v, ps.frame) != k
        assert contribution_key(GridBox(box.lo, box.h, (box.dims[0] + 1, *box.dims[1:])),
                                v, ps.frame) != k
        f2 = type(ps.frame)(centre=ps.frame.centre, scale=ps.frame.scale * 2)
        assert contribution_key(box, v, f2) != k
    finally:
        ps.release()


def test_grid_values_are_the_material_stages():
    """``stage_keys``: an index grid's values are read by the material stage only (a new
    grid of the same bounds changes the material key and not the geometry key); moving its
    bounds changes the geometry key; a grid volume's contribution key follows its bounds."""
    from types import SimpleNamespace

    from clscatter.methods.voxel import stage_keys
    from clscatter.scene.model import Volume
    from clscatter.scene.normalised import Frame

    rng = np.random.default_rng(1)
    bounds = (np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.0, 0.5]))
    vol = Volume(ior=1.2, sigma_s=np.zeros(3), sigma_a=np.zeros(3), resolution=8,
                 grid=(1.0 + 0.2 * rng.random((8, 8, 8))).astype(np.float32), grid_bounds=bounds,
                 key="volumes[0]")
    scene = _two_volumes()
    params = {**{p.name: p.default for p in Voxel.PARAMS}, **VOXEL}

    def keys(v):
        frame = Frame(centre=np.zeros(3), scale=2.0)
        ps = SimpleNamespace(scene=SimpleNamespace(volumes=[v], render=scene.render), frame=frame,
                             medium=np.zeros(1, np.float32), lights=np.zeros(1, np.float32),
                             bvh=SimpleNamespace(triangles=np.zeros((0, 3), np.float32)))
        return stage_keys(ps, params)

    g, m, light = keys(vol)
    v2 = copy.deepcopy(vol)
    v2.grid = v2.grid * np.float32(1.01)
    g2, m2, l2 = keys(v2)
    assert g2 == g and m2 != m and l2 != light
    v3 = copy.deepcopy(vol)
    v3.grid_bounds = (bounds[0] + 0.01, bounds[1] + 0.01)
    g3, m3, _ = keys(v3)
    assert g3 != g and m3 != m
    frame = Frame(centre=np.zeros(3), scale=2.0)
    box = GridBox(np.full(3, -0.5), 0.05, (20, 20, 20))
    assert contribution_key(box, v2, frame) == contribution_key(box, vol, frame)
    assert contribution_key(box, v3, frame) != contribution_key(box, vol, frame)
