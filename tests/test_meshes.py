"""Meshes in the usual formats (OBJ, PLY binary and ASCII, STL, glTF binary) load through one
path and give the same image; a glass object or volume whose surface is not closed gets one
note naming it and counting its open edges."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from clscatter.geometry import PARITY_RAY, open_edges, ray_crossings
from clscatter.pipeline.check import scene_notes
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



def _winding(tris: np.ndarray, p: np.ndarray) -> float:
    """The winding number of the closed surface ``tris`` (F, 3, 3) about ``p``: the solid
    angles its triangles subtend there (Van Oosterom and Strackee), summed, over 4 pi."""
    a, b, c = (tris[:, i] - p for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
           + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb)
    return float(np.sum(2 * np.arctan2(num, den)) / (4 * np.pi))


def test_crossings_tell_inside_from_outside_a_closed_mesh():
    """The parity of the ray's crossings against a closed mesh (the cow) agrees with the
    surface's winding number at 400 random points of its bounding box."""
    vertices, faces, _ = load_mesh(COW, "cow")
    tris = vertices[faces]
    rng = np.random.default_rng(5)
    points = rng.uniform(vertices.min(axis=0), vertices.max(axis=0), (400, 3))
    want = np.array([abs(_winding(tris, p)) > 0.5 for p in points])
    got = np.array([ray_crossings(p, PARITY_RAY, tris) % 2 == 1 for p in points])
    assert 20 < want.sum() < 380
    assert np.array_equal(got, want)


@pytest.mark.parametrize("shape", ["sphere", "box", "mesh"])
def test_the_glass_a_camera_is_inside(shape):
    """A camera inside a closed glass object (a sphere, a box, the cow) is found inside it;
    inside a diffuse one, or outside, in air."""
    obj = {"sphere": {"shape": "sphere", "center": [0.0, 0.3, 0.0], "radius": 0.3},
           "box": {"shape": "box", "min": [-0.3, 0.0, -0.3], "max": [0.3, 0.6, 0.3]},
           "mesh": {"shape": "mesh", "file": str(COW)}}[shape]
    d = _scene(COW, "glass")
    d["objects"] = [dict(obj, material="glass")]
    o = scene_from_dict(d).objects[0]
    tris = o.vertices[o.faces]
    lo, hi = o.vertices.min(axis=0), o.vertices.max(axis=0)
    # a point inside (by the winding number): along the vertical through the box's centre
    line = [np.array([(lo[0] + hi[0]) / 2, y, (lo[2] + hi[2]) / 2])
            for y in np.linspace(lo[1], hi[1], 41)[1:-1]]
    inside = [p for p in line if abs(_winding(tris, p)) > 0.5]
    centre = inside[len(inside) // 2]
    d["camera"]["origin"] = [float(x) for x in centre]
    d["camera"]["target"] = [float(centre[0]), float(centre[1]), float(centre[2]) - 1.0]
    s = scene_from_dict(d)
    assert s.camera_glass() is s.objects[0]
    d["objects"][0]["material"] = "grey"
    assert scene_from_dict(d).camera_glass() is None
    d["objects"][0]["material"] = "glass"
    d["camera"]["origin"], d["camera"]["target"] = [0.0, 0.6, 3.0], [0.0, 0.2, 0.0]
    assert scene_from_dict(d).camera_glass() is None
