"""Closing a mesh's holes (clscatter/scene/hole_fill.py, a mesh object's ``close_holes``):
against the closed shapes the holes were cut from, with the winding of the triangles
around each hole, on the scanned bunny, and through the scene file."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.geometry import open_edges
from clscatter.scene import load_scene
from clscatter.scene.hole_fill import boundary_loops, fill_holes
from clscatter.scene.shapes import box, sphere


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def directed_edges_once(f: np.ndarray) -> bool:
    """Every directed edge used by one triangle at most: a consistent winding."""
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return len(np.unique(d[:, 0] * (f.max() + 1) + d[:, 1])) == len(d)


def test_a_box_without_a_face_is_closed_again():
    v, f, _ = box(np.zeros(3), np.array([2.0, 1.0, 3.0]))
    open_box = f[2:]                                   # the -x face's two triangles cut off
    assert open_edges(open_box) == 4 and len(boundary_loops(open_box)) == 1
    v2, f2, holes = fill_holes(v, open_box)
    assert holes == 1 and len(v2) == len(v) and len(f2) == 12      # one quad: two triangles
    assert open_edges(f2) == 0 and directed_edges_once(f2)
    assert signed_volume(v2, f2) == pytest.approx(6.0, rel=1e-12)   # outward, as the box


def test_a_sphere_with_a_jagged_hole_keeps_its_volume_and_winding():
    """A cap cut from an icosphere along its triangles (a non-convex loop): the fill is
    planar-ish, adds k - 2 triangles and no vertex, and the volume falls only by the
    cap's thin sliver."""
    v, f, _ = sphere(np.zeros(3), 1.0, 3)
    keep = ~(v[f][:, :, 2].max(axis=1) > 0.8)          # the triangles reaching above z = 0.8
    cut = f[keep]
    loops = boundary_loops(cut)
    assert len(loops) == 1 and len(loops[0]) > 8
    v2, f2, holes = fill_holes(v, cut)
    assert holes == 1 and open_edges(f2) == 0 and directed_edges_once(f2)
    assert len(f2) - len(cut) == len(loops[0]) - 2 and len(v2) == len(v)
    full, filled = signed_volume(v, f), signed_volume(v2, f2)
    assert 0.95 * full < filled < full                  # the cap above the loop is gone


def test_two_holes_and_a_closed_mesh():
    v, f, _ = box(np.zeros(3), np.ones(3))
    two = np.delete(f, [0, 1, 2, 3], axis=0)           # the -x and +x faces
    v2, f2, holes = fill_holes(v, two)
    assert holes == 2 and open_edges(f2) == 0 and directed_edges_once(f2)
    assert signed_volume(v2, f2) == pytest.approx(1.0, rel=1e-12)
    same_v, same_f, none = fill_holes(v, f)            # closed: unchanged
    assert none == 0 and np.array_equal(same_f, f)


def test_random_holes_close_with_one_winding():
    """300 draws of triangles taken out of an icosphere (holes that touch at corners, share
    vertices with other holes, or leave a bridge of triangles between them): every hole
    closes, every directed edge is used once (no diagonal repeats an edge of the mesh,
    no corner fan spoke twice), and the volume stays the sphere's within the flattened
    holes."""
    v, f, _ = sphere(np.zeros(3), 1.0, 3)
    full = signed_volume(v, f)
    rng = np.random.default_rng(1)
    for _ in range(300):
        cut = np.delete(f, rng.choice(len(f), rng.integers(1, 60), replace=False), axis=0)
        v2, f2, holes = fill_holes(v, cut)
        assert holes >= 1 and open_edges(f2) == 0 and directed_edges_once(f2)
        assert 0.995 * full < signed_volume(v2, f2) <= full * (1 + 1e-12)


def test_the_bunny_scan_closes(tmp_path):
    """The Stanford bunny's five holes in its base, through the scene file's key."""
    from clscatter.scene.builtin.paper import BUNNY
    scene = tmp_path / "s.toml"
    for close in ("false", "true"):
        scene.write_text(f"""
[camera]
origin = [0.0, 0.5, 3.0]
target = [0.0, 0.1, 0.0]
resolution = [16, 12]
[[lights]]
type = "point"
position = [0.0, 2.0, 0.0]
intensity = 1.0
[materials.glass]
type = "dielectric"
[[objects]]
shape = "mesh"
file = "{BUNNY}"
material = "glass"
close_holes = {close}
""")
        bunny = load_scene(scene).objects[0]
        if close == "false":
            assert open_edges(bunny.faces) == 223 and len(boundary_loops(bunny.faces)) == 5
        else:
            assert open_edges(bunny.faces) == 0 and directed_edges_once(bunny.faces)
            assert signed_volume(bunny.vertices, bunny.faces) > 0
    # a volume's mesh takes the key too
    scene.write_text(scene.read_text() + f"""
[[volumes]]
shape = "mesh"
file = "{BUNNY}"
close_holes = true
ior = 1.1
transform = {{ scale = 2.0 }}
""")
    volume = load_scene(scene).volumes[0]
    assert open_edges(volume.mesh.faces) == 0 and directed_edges_once(volume.mesh.faces)
