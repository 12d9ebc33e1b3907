"""Shape triangulation and transforms: every object becomes a world-space triangle mesh.

Pure geometry, no scene parsing (that is ``loader.py``). Each builder returns
``(vertices (V,3) float64, faces (F,3) int64, normals (V,3) float64 | None)``; normals
are per-vertex unit shading normals for smooth shapes, None for flat shading.

* ``sphere``  an icosphere (``subdivisions`` levels, 4 -> 5120 triangles) whose vertices
  lie exactly on the sphere, with exact normals (p - c) / r.
* ``box``     12 triangles, outward-facing counter-clockwise winding, flat.
* ``quad``    2 triangles origin, origin + edge_u, origin + edge_u + edge_v, origin + edge_v
  (geometric normal edge_u x edge_v; the quad is two-sided anyway), flat.
* ``mesh``    OBJ files read with NumPy, any other format trimesh reads (vertices merged),
  flat unless ``smooth`` (area-weighted vertex normals); ``close_holes`` triangulates the
  holes of an open surface (``hole_fill.py``).

A transform ``{translate, rotate = [ax, ay, az, degrees], scale}`` is applied in the order
scale, rotate, translate (M = T R S). Normals go through the inverse transpose of the
linear part and are renormalised; a mirroring transform (det < 0) flips the winding so
closed shapes stay outward-facing.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..geometry import edge_keys, mesh_edges
from .hole_fill import fill_holes
from .ply import read_ply

Mesh = tuple[np.ndarray, np.ndarray, "np.ndarray | None"]

# corners of the unit box indexed by bits (x = bit 0, y = bit 1, z = bit 2); each face's
# triangles wind counter-clockwise seen from outside (normal = (b - a) x (c - a) outward)
_BOX_FACES = np.array([
    [0, 4, 6], [0, 6, 2],   # -x
    [1, 3, 7], [1, 7, 5],   # +x
    [0, 1, 5], [0, 5, 4],   # -y
    [2, 6, 7], [2, 7, 3],   # +y
    [0, 2, 3], [0, 3, 1],   # -z
    [4, 5, 7], [4, 7, 6],   # +z
], dtype=np.int64)


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


# ---- Transforms -----------------------------------------------------------------------

def rotation_matrix(axis: np.ndarray, degrees: float) -> np.ndarray:
    """3x3 right-handed rotation by ``degrees`` about ``axis`` (Rodrigues' formula)."""
    axis = np.asarray(axis, dtype=np.float64)
    n = float(np.linalg.norm(axis))
    if n == 0.0:
        return np.eye(3)
    x, y, z = axis / n
    t = math.radians(degrees)
    c, s = math.cos(t), math.sin(t)
    C = 1.0 - c
    return np.array([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ])


def transform_matrix(translate=(0.0, 0.0, 0.0), rotate=(0.0, 1.0, 0.0, 0.0),
                     scale=1.0) -> np.ndarray:
    """4x4 affine matrix M = T R S (scale first, then rotate, then translate)."""
    S = np.diag(np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    R = rotation_matrix(np.asarray(rotate[:3], dtype=np.float64), float(rotate[3]))
    M = np.eye(4)
    M[:3, :3] = R @ S
    M[:3, 3] = np.asarray(translate, dtype=np.float64)
    return M


def apply_transform(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None,
                    M: np.ndarray) -> Mesh:
    """Transform a mesh by the affine 4x4 ``M``; normals by the inverse transpose."""
    A = M[:3, :3]
    v = vertices @ A.T + M[:3, 3]
    n = None
    if normals is not None:
        n = normals @ np.linalg.inv(A)          # (A^-T n^T)^T = n A^-1
        n = _normalise_rows(n)
    f = faces
    if np.linalg.det(A) < 0.0:                   # mirroring: keep outward winding
        f = faces[:, ::-1].copy()
    return v, f, n


def _normalise_rows(n: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(n, axis=1, keepdims=True)
    bad = length[:, 0] == 0.0
    out = n / np.where(length == 0.0, 1.0, length)
    out[bad] = (0.0, 0.0, 1.0)                   # isolated vertex: any unit vector will do
    return out


# ---- Builders -------------------------------------------------------------------------

def unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: the icosahedron with every triangle split into four at the edge
    midpoints ``subdivisions`` times, vertices projected onto the sphere; faces wind
    counter-clockwise seen from outside. 20 * 4^s triangles, 10 * 4^s + 2 vertices."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(int(subdivisions)):
        edges = mesh_edges(f)
        keys, inv = np.unique(edge_keys(edges[:, 0], edges[:, 1], len(v)), return_inverse=True)
        uniq = np.stack([keys // len(v), keys % len(v)], axis=1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(v) + inv.reshape(3, -1)            # midpoint of edge (0,1), (1,2), (2,0)
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([b, m[1], m[0]], 1),
                            np.stack([c, m[2], m[1]], 1), np.stack([m[0], m[1], m[2]], 1)])
        v = np.concatenate([v, mid])
    return v, f


def sphere(center: np.ndarray, radius: float, subdivisions: int = 4) -> Mesh:
    """Icosphere with vertices exactly on the sphere and exact unit normals."""
    u, f = unit_icosphere(subdivisions)
    v = np.asarray(center, dtype=np.float64) + radius * u
    return v, f, u.copy()


def box(lo: np.ndarray, hi: np.ndarray) -> Mesh:
    """Axis-aligned box from ``lo`` to ``hi``: 8 vertices, 12 outward-facing triangles."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    bits = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], dtype=bool)
    v = np.where(bits, hi, lo)
    return v, _BOX_FACES.copy(), None


def quad(origin: np.ndarray, edge_u: np.ndarray, edge_v: np.ndarray) -> Mesh:
    """Parallelogram origin + s edge_u + t edge_v, s, t in [0, 1], as two triangles."""
    o = np.asarray(origin, dtype=np.float64)
    u = np.asarray(edge_u, dtype=np.float64)
    w = np.asarray(edge_v, dtype=np.float64)
    v = np.array([o, o + u, o + u + w, o + w])
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64), None


_MESH_CACHE: dict[tuple, Mesh] = {}
_MESH_CACHE_SIZE = 8


def load_mesh(path: Path, key: str, smooth: bool = False, close_holes: bool = False) -> Mesh:
    """Load any mesh trimesh reads (OBJ and PLY by this package's own readers, which do not
    import trimesh); SceneError ``key`` naming the file on any failure. ``close_holes``:
    every hole (a loop of edges that one triangle alone uses) triangulated
    (:func:`~clscatter.scene.hole_fill.fill_holes`) before the normals are formed.

    Parsed meshes are cached by (path, size, mtime, smooth, close_holes), so a relighting
    session that re-validates its scene after each change does not parse the file again."""
    path = Path(path)
    if not path.exists():
        raise SceneError(key, f"mesh file not found: {path}")
    if not path.is_file():
        raise SceneError(key, f"mesh path is not a file: {path}")
    st = path.stat()
    ck = (str(path.resolve()), st.st_size, st.st_mtime_ns, bool(smooth), bool(close_holes))
    if ck not in _MESH_CACHE:
        if len(_MESH_CACHE) >= _MESH_CACHE_SIZE:
            _MESH_CACHE.pop(next(iter(_MESH_CACHE)))
        _MESH_CACHE[ck] = _read_mesh(path, key, smooth, close_holes)
    v, f, n = _MESH_CACHE[ck]
    return v.copy(), f.copy(), None if n is None else n.copy()


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a Wavefront OBJ file, read with NumPy (trimesh's import
    alone costs seconds). ``v`` lines give positions, ``f`` lines polygons (``i``, ``i/t``,
    ``i/t/n``, ``i//n``; negative indices count from the end), fanned into triangles;
    everything else is ignored. ValueError when a line cannot be read."""
    verts: list[list[float]] = []
    tris: list[list[int]] = []
    with open(path, "r", errors="strict") as fh:
        for line in fh:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
                if len(verts[-1]) != 3:
                    raise ValueError(f"vertex line with fewer than 3 numbers: {line.strip()!r}")
            elif parts[0] == "f":
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                if len(idx) < 3:
                    raise ValueError(f"face with fewer than 3 vertices: {line.strip()!r}")
                tris += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    return np.array(verts, np.float64).reshape(-1, 3), np.array(tris, np.int64).reshape(-1, 3)


def _merge_vertices(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices with identical positions merged (so smooth normals average across faces
    that a file stored with separate copies of a corner); unused vertices dropped."""
    used = np.unique(f)
    uniq, inv = np.unique(v[used], axis=0, return_inverse=True)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = inv.reshape(-1)
    return uniq, remap[f]


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (the sum of the unnormalised face normals)."""
    t = v[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return _normalise_rows(n)


def _read_mesh(path: Path, key: str, smooth: bool, close_holes: bool = False) -> Mesh:
    try:
        suffix = path.suffix.lower()
        read = read_obj(path) if suffix == ".obj" else read_ply(path) if suffix == ".ply" else None
        if read is not None:
            v, f = read
        else:
            import trimesh
            # process=False: trimesh's processing would silently drop NaN vertices, and with
            # them the faces that use them; a file with NaN coordinates is an error instead
            mesh = trimesh.load(str(path), force="mesh", process=False)
            faces = getattr(mesh, "faces", None)
            v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
            f = np.asarray(faces if faces is not None else np.zeros((0, 3)), np.int64).reshape(-1, 3)
    except Exception as exc:  # a parser raises many kinds; all mean "cannot read this file"
        raise SceneError(key, _one_line(f"cannot read mesh {path}: {exc}")) from None
    if len(f) == 0:
        raise SceneError(key, f"mesh {path} has no triangles")
    if not np.all(np.isfinite(v)):
        bad = int((~np.isfinite(v)).any(axis=1).sum())
        raise SceneError(key, f"mesh {path} has {bad} vertices with NaN or infinite coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise SceneError(key, f"mesh {path} has faces that index missing vertices")
    v, f = _merge_vertices(v, f)
    if close_holes:
        v, f, _ = fill_holes(v, f)
    n = vertex_normals(v, f) if smooth else None
    return v, f, n


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """``faces`` without zero-area triangles (repeated vertices, collinear corners), and how
    many were dropped. Zero area means below 1e-12 of the mesh's extent squared: such a
    triangle has no normal and is hit by no ray; keeping it only risks NaN normals."""
    if len(faces) == 0:
        return faces, 0
    t = vertices[faces]
    area2 = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    ext = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    keep = area2 > 1e-12 * max(ext * ext, 1e-300)
    return faces[keep], int((~keep).sum())
