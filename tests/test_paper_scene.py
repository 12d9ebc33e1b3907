"""The paper-scale built-in scene ``paper_bunny`` (clscatter/scene/builtin/paper.py): the
committed bunny mesh against the original scan, the scene as the LSG paper's Table 1 sized
its scenes, and a tiny render with caustic light in it."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import trimesh
from conftest import MODELS

from clscatter.geometry import open_edges
from clscatter.pipeline.check import scene_notes
from clscatter.pipeline.render import render
from clscatter.scene import load_scene, scene_from_dict
from clscatter.scene.builtin import BUILTIN
from clscatter.scene.builtin.paper import (
    BUNNY,
    BUNNY_CLOSED_TRIANGLES,
    BUNNY_TRIANGLES,
    BUNNY_VERTICES,
    paper_bunny,
)
from clscatter.scene.shapes import read_obj


def test_mesh_file_is_the_stanford_bunny():
    assert BUNNY.suffix == ".ply" and BUNNY.stat().st_size < 1_500_000
    mesh = trimesh.load(str(BUNNY), force="mesh", process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    assert (len(v), len(f)) == (BUNNY_VERTICES, BUNNY_TRIANGLES) == (35_947, 69_451)
    ov, of = read_obj(MODELS / "stanford-bunny.obj")       # the scan as distributed
    assert (len(ov), len(of)) == (len(v), len(f))
    np.testing.assert_array_equal(f, of)                   # the same faces in the same order
    np.testing.assert_array_equal(np.round(v, 6), ov)      # float32 rounds back to the six decimals
    assert not trimesh.Trimesh(v, f).is_watertight          # holes in the base


def test_scene_loads_at_the_papers_scale():
    assert "paper_bunny" in BUILTIN
    s = load_scene("builtin:paper_bunny")
    assert s.triangle_count() == BUNNY_CLOSED_TRIANGLES + 2  # the bunny and the floor quad
    assert (s.camera.width, s.camera.height, s.camera.spp) == (512, 512, 4)
    assert paper_bunny()["render"]["lsg"]["light_rays"] >= 1_000_000
    assert sorted(light.type for light in s.lights) == ["point", "spot"]
    bunny = s.objects[1]
    assert len(bunny.faces) == BUNNY_CLOSED_TRIANGLES == BUNNY_TRIANGLES + 213
    assert open_edges(bunny.faces) == 0 and bunny.normals is not None    # holes closed
    assert not [n for n in scene_notes(s) if "not closed" in n]
    assert bunny.material.type == "dielectric" and bunny.material.ior == pytest.approx(1.5)
    lo, hi = bunny.vertices.min(0), bunny.vertices.max(0)
    assert hi[1] - lo[1] == pytest.approx(1.0, abs=0.01)    # about a unit tall
    assert 0.0 < lo[1] < 0.005                              # just above the floor
    mlo, mhi = s.medium.bounds
    assert np.all(mlo < lo) and np.all(hi < mhi)            # in the fog box
    for light in s.lights:
        assert np.all(light.position > mlo) and np.all(light.position < mhi)


def test_renders_tiny_with_caustic_light(engine):
    """32 x 32, 1 spp, 20k lighting rays, 4k ray-map rays, seed 7: ``auto`` plans ray
    marching, LSG caustics and ray-map floor caustics. Measured (seeds 1, 2, 7): the LSG
    caustic pass sums 6.98-7.42 (max 0.021-0.030), about 2.3 % of the ray-marched medium
    (311-314); the floor caustic 26.2-28.9 (max 0.78-0.98)."""
    d = copy.deepcopy(paper_bunny())
    d["camera"].update(resolution=[32, 32], spp=1)
    d["render"].update(time_budget=0, seed=7)
    d["render"]["lsg"]["light_rays"] = 20_000
    d["render"]["raymap"] = {"photons": 4_000}
    d["render"]["raymarch"] = {"steps": 16}
    res = render(scene_from_dict(d, ".", "paper_bunny"), "auto", engine=engine, show_progress=False)
    img = res.image
    assert img.shape == (32, 32, 3) and np.all(np.isfinite(img)) and img.min() >= 0
    assert res.stats.get("nonfinite_pixels_zeroed", 0) == 0
    assert res.stats["method"] == "raymarch+lsg+raymap"
    direct, caustic, floor = (res.parts[k] for k in (0, 1, 2))
    assert 250 < direct.sum() < 400
    assert 3.5 < caustic.sum() < 15 and caustic.max() > 0.01      # volumetric caustic
    assert 0.01 < caustic.sum() / direct.sum() < 0.05
    assert 13 < floor.sum() < 60 and floor.max() > 0.3              # caustic on the floor
    assert 0.1 < img.mean() < 0.4 and img.max() < 10            # measured 0.20, 1.04
