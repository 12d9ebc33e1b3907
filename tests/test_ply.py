"""The package's own PLY reader against trimesh's and against hand-written files: byte
orders, ASCII, polygons of several sizes, extra properties and elements, and files it
leaves to trimesh or refuses."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from clscatter.errors import SceneError
from clscatter.scene.ply import read_ply
from clscatter.scene.shapes import load_mesh

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO / "clscatter" / "scene" / "meshes" / "bunny.ply"

# a unit square as one quad and a triangle on top: 5 vertices, faces of 4 and 3 corners
VERTS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 2, 0.25]], np.float64)
POLYS = [[0, 1, 2, 3], [3, 2, 4]]
TRIS = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4]])


def _binary(order: str, polys=POLYS, extra_first: bool = False) -> bytes:
    """A binary PLY with a normal per vertex (skipped), double positions, an ``edge``
    element with a list before the vertices when ``extra_first``, and a ``material``
    element after the faces (never read)."""
    head = [b"ply", b"format %s 1.0" % (b"binary_little_endian" if order == "<"
                                         else b"binary_big_endian"), b"comment test"]
    body = b""
    if extra_first:
        head += [b"element edge 2", b"property list uchar int vertex_index", b"property uchar flag"]
        for e in ([0, 1], [1, 2, 3]):
            body += struct.pack(order + "B%di" % len(e), len(e), *e) + struct.pack("B", 7)
    head += [b"element vertex %d" % len(VERTS), b"property float nx", b"property double x",
             b"property double y", b"property double z", b"property uchar red"]
    for v in VERTS:
        body += struct.pack(order + "f3dB", 0.5, *v, 200)
    head += [b"element face %d" % len(polys), b"property list uchar int vertex_indices",
             b"property short tag"]
    for p in polys:
        body += struct.pack(order + "B%dih" % len(p), len(p), *p, -3)
    head += [b"element material 1", b"property list uchar float values", b"end_header"]
    return b"\n".join(head) + b"\n" + body + b"\x03garbage-that-is-never-read"


def test_bunny_matches_trimesh():
    v, f = read_ply(BUNNY)
    m = trimesh.load(str(BUNNY), force="mesh", process=False)
    assert v.shape == (35947, 3) and f.shape == (69451, 3)
    np.testing.assert_array_equal(v, np.asarray(m.vertices))
    np.testing.assert_array_equal(f, np.asarray(m.faces))


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("extra_first", [False, True])
def test_binary_polygons_and_extra_properties(tmp_path, order, extra_first):
    path = tmp_path / "m.ply"
    path.write_bytes(_binary(order, extra_first=extra_first))
    v, f = read_ply(path)
    np.testing.assert_array_equal(v, VERTS)
    np.testing.assert_array_equal(f, TRIS)


def test_binary_faces_of_one_size_read_at_once_match_row_by_row(tmp_path):
    quads = [[0, 1, 2, 3], [1, 2, 4, 0]]
    a = tmp_path / "same.ply"
    a.write_bytes(_binary("<", polys=quads))
    v, f = read_ply(a)
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3], [1, 2, 4], [1, 4, 0]])


def test_ascii_matches_binary(tmp_path):
    text = ("ply\nformat ascii 1.0\ncomment hi\nelement vertex 5\nproperty float x\n"
            "property float y\nproperty float z\nproperty float confidence\n"
            "element face 2\nproperty list uchar uint vertex_index\nend_header\n"
            + "".join(f"{x} {y} {z} 1\n" for x, y, z in VERTS)
            + "\n4 0 1 2 3\n3 3 2 4\n")
    path = tmp_path / "a.ply"
    path.write_text(text)
    v, f = read_ply(path)
    np.testing.assert_allclose(v, VERTS.astype(np.float32))
    np.testing.assert_array_equal(f, TRIS)


def test_load_mesh_reads_ply_without_trimesh_results(tmp_path):
    path = tmp_path / "m.ply"
    path.write_bytes(_binary("<"))
    v, f, n = load_mesh(path, "objects[0].file")
    assert len(f) == 3 and n is None and np.isfinite(v).all()


def test_a_point_cloud_is_left_to_trimesh_and_refused(tmp_path):
    path = tmp_path / "cloud.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                    "property float y\nproperty float z\nend_header\n0 0 0\n1 1 1\n")
    assert read_ply(path) is None
    with pytest.raises(SceneError, match=r"objects\[0\]\.file.*no triangles"):
        load_mesh(path, "objects[0].file")


@pytest.mark.parametrize("data, message", [
    (b"plx\nend_header\n", "not a PLY file"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown PLY format"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "unknown PLY property type"),
])
def test_bad_headers_raise(tmp_path, data, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=message):
        read_ply(path)


@pytest.mark.parametrize("cut", [40, 100, 160])
def test_a_file_cut_short_is_an_error_naming_the_key(tmp_path, cut):
    whole = _binary("<")
    body_at = whole.index(b"end_header\n") + len(b"end_header\n")
    path = tmp_path / "cut.ply"
    path.write_bytes(whole[:body_at + cut])
    with pytest.raises(ValueError, match="ends before"):
        read_ply(path)
    with pytest.raises(SceneError, match=r"objects\[0\]\.file.*cannot read mesh"):
        load_mesh(path, "objects[0].file")
