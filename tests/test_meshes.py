"""Meshes in the usual formats (OBJ, PLY binary and ASCII, STL, glTF binary) load through one
path and give the same image; a glass object or volume whose surface is not closed gets one
note naming it and counting its open edges."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from clscatter.pipeline.check import open_edges, scene_notes
from clscatter.pipeline.render import render
from clscatter.scene.loader import scene_from_dict
from clscatter.scene.shapes import load_mesh

REPO = Path(__file__).resolve().parents[1]
COW = REPO / "models" / "cow.obj"
TEAPOT = REPO / "models" / "teapot.obj"
FORMATS = {"obj": {}, "ply": {"encoding": "binary"}, "ascii.ply": {"encoding": "ascii"},
           "stl": {}, "glb": {}}


def _scene(mesh_file: Path, material: str = "grey") -> dict:
    return {
        "camera": {"origin": [0.0, 0.6, 3.0], "target": [0.0, 0.2, 0.0], "fov": 40.0,
                   "resolution": [32, 24], "spp": 1},
        "medium": {"sigma_s": 0.1, "sigma_a": 0.01},
        "lights": [{"type": "point", "position": [1.0, 3.0, 2.0], "intensity": 20.0}],
        "materials": {"grey": {"type": "diffuse", "albedo": 0.6},
                      "glass": {"type": "dielectric", "ior": 1.5}},
        "objects": [{"shape": "mesh", "file": str(mesh_file), "material": material}],
        "render": {"method": "raymarch"},
    }


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("meshes")
    v, f, _ = load_mesh(COW, "cow")
    mesh = trimesh.Trimesh(v, f, process=False)
    files = {}
    for suffix, kw in FORMATS.items():
        path = out / f"cow.{suffix}"
        if suffix == "obj":
            path.write_bytes(COW.read_bytes())
        else:
            mesh.export(str(path), file_type=suffix.split(".")[-1], **kw)
        files[suffix] = path
    return files


def test_every_format_loads_the_same_triangles(exported):
    ref_v, ref_f, _ = load_mesh(exported["obj"], "obj")
    ref = np.sort(np.sort(ref_v[ref_f].round(5), axis=1).reshape(len(ref_f), -1), axis=0)
    for suffix, path in exported.items():
        v, f, _ = load_mesh(path, suffix)
        got = np.sort(np.sort(v[f].round(5), axis=1).reshape(len(f), -1), axis=0)
        assert got.shape == ref.shape, suffix
        np.testing.assert_allclose(got, ref, atol=2e-5, err_msg=suffix)
        assert open_edges(f) == 0, suffix          # shared vertices merged in every format


def test_every_format_gives_the_same_image(exported, engine):
    images = {s: render(scene_from_dict(_scene(p)), engine=engine, show_progress=False).image
              for s, p in exported.items()}
    ref = images["obj"]
    assert ref.mean() > 0
    for suffix, img in images.items():
        diff = float(np.max(np.abs(img - ref))) / float(np.max(ref))
        assert diff < 1e-4, f"{suffix}: {diff:.3g} of the peak"


def test_an_open_glass_mesh_is_noted():
    """The classic teapot is not closed (its lid and spout leave 160 open edges)."""
    notes = scene_notes(scene_from_dict(_scene(TEAPOT, "glass")))
    lines = [n for n in notes if "not closed" in n]
    assert len(lines) == 1 and lines[0].startswith("objects[0]: ") and "160 open edges" in lines[0]
    assert not [n for n in scene_notes(scene_from_dict(_scene(COW, "glass"))) if "not closed" in n]
    assert not [n for n in scene_notes(scene_from_dict(_scene(TEAPOT))) if "not closed" in n]
