"""Procedural meshes for the caustic scenes: torus, faceted gem, concave dish, metaball blob.

Each generator returns ``(vertices (V, 3) float64, faces (F, 3) int64)``; closed meshes
are wound counter-clockwise seen from outside (the renderer decides entering/leaving a
dielectric by the winding). ``tools/make_caustic_meshes.py`` writes them as the small
OBJ files in ``clscatter/scene/meshes/`` that ``builtin/caustics.py`` references, so
scenes load without regenerating anything; :func:`write_obj` is that writer.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _outward(v: np.ndarray, f: np.ndarray) -> Mesh:
    """Flip the winding of a closed mesh whose signed volume is negative."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    return (v, f[:, ::-1].copy()) if vol < 0 else (v, f)


def _grid_faces(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Two triangles per cell of an (nu x nv) vertex grid (index u * nv + v)."""
    us = np.arange(nu if wrap_u else nu - 1)
    vs = np.arange(nv if wrap_v else nv - 1)
    u, w = np.meshgrid(us, vs, indexing="ij")
    u, w = u.ravel(), w.ravel()
    u1, w1 = (u + 1) % nu, (w + 1) % nv
    i00, i10, i01, i11 = u * nv + w, u1 * nv + w, u * nv + w1, u1 * nv + w1
    return np.concatenate([np.stack([i00, i10, i11], 1), np.stack([i00, i11, i01], 1)]).astype(np.int64)


def torus(major: float = 1.0, minor: float = 0.35, nu: int = 48, nv: int = 24) -> Mesh:
    """Torus around the y axis: ring radius ``major``, tube radius ``minor``."""
    u = np.linspace(0, 2 * math.pi, nu, endpoint=False)[:, None]
    v = np.linspace(0, 2 * math.pi, nv, endpoint=False)[None, :]
    ring = major + minor * np.cos(v)
    x = ring * np.cos(u)
    z = ring * np.sin(u)
    y = np.broadcast_to(minor * np.sin(v), x.shape)
    verts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    return _outward(verts, _grid_faces(nu, nv, True, True))


def gem(facets: int = 8, girdle: float = 1.0, table: float = 0.55, crown: float = 0.32,
        pavilion: float = 0.85) -> Mesh:
    """A faceted gem in the spirit of a brilliant cut, the girdle in the plane y = 0:
    a table of ``facets`` sides at height ``crown``, a girdle of 2 * facets vertices, a
    ring of pavilion facets and a culet point at ``-pavilion``; the convex hull of these
    points (so every facet is a plane and the winding is outward)."""
    import trimesh

    k = np.arange(facets)
    a_t = 2 * math.pi * k / facets
    a_g = math.pi * np.arange(2 * facets) / facets + math.pi / (2 * facets)
    a_p = a_t + math.pi / facets
    pts = [np.stack([table * np.cos(a_t), np.full(facets, crown), table * np.sin(a_t)], 1),
           np.stack([girdle * np.cos(a_g), np.zeros(2 * facets), girdle * np.sin(a_g)], 1),
           np.stack([0.5 * girdle * np.cos(a_p), np.full(facets, -0.45 * pavilion),
                     0.5 * girdle * np.sin(a_p)], 1),
           np.array([[0.0, -pavilion, 0.0]])]
    hull = trimesh.convex.convex_hull(np.concatenate(pts))
    return _outward(np.asarray(hull.vertices, np.float64), np.asarray(hull.faces, np.int64))


def dish(radius: float = 1.0, curvature_radius: float = 2.2, rings: int = 16,
         segments: int = 48) -> Mesh:
    """A concave spherical cap (open surface) of rim radius ``radius``, opening towards
    +z, its focus on the +z axis at about ``curvature_radius / 2`` from the vertex (the
    vertex sits at the origin)."""
    half = math.asin(min(radius / curvature_radius, 1.0))
    th = np.linspace(0, half, rings + 1)[1:, None]
    ph = np.linspace(0, 2 * math.pi, segments, endpoint=False)[None, :]
    x = curvature_radius * np.sin(th) * np.cos(ph)
    y = curvature_radius * np.sin(th) * np.sin(ph)
    z = curvature_radius * (1 - np.cos(th)) * np.ones_like(ph)
    ring_verts = np.stack([x, y, z], -1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 0.0]], ring_verts])
    centre = np.stack([np.zeros(segments, np.int64), 1 + np.arange(segments),
                       1 + (np.arange(segments) + 1) % segments], 1)
    rest = _grid_faces(rings, segments, False, True)[:, [0, 2, 1]] + 1
    return verts, np.concatenate([centre, rest])


def blob(centres=((-0.45, 0.0, 0.0), (0.4, 0.15, 0.1), (0.0, 0.5, -0.15), (0.05, -0.35, 0.3)),
         radii=(0.55, 0.5, 0.42, 0.38), level: float = 0.5, resolution: int = 34) -> Mesh:
    """Metaballs: the level set ``sum_i exp(-|x - c_i|^2 / r_i^2) = level`` by marching
    cubes (scikit-image) on a ``resolution``^3 grid, wound outward."""
    from skimage import measure

    c = np.asarray(centres, np.float64)
    r = np.asarray(radii, np.float64)
    lo = (c - 2 * r[:, None]).min(axis=0)
    hi = (c + 2 * r[:, None]).max(axis=0)
    axes = [np.linspace(lo[i], hi[i], resolution) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    P = np.stack([X, Y, Z], -1)
    field = np.zeros(X.shape)
    for ci, ri in zip(c, r):   # a handful of balls: a loop over balls, not over voxels
        field += np.exp(-((P - ci) ** 2).sum(-1) / ri ** 2)
    spacing = tuple((hi - lo) / (resolution - 1))
    verts, faces, _, _ = measure.marching_cubes(field, level, spacing=spacing)
    return _outward(verts + lo, faces.astype(np.int64))


def write_obj(path: Path | str, vertices: np.ndarray, faces: np.ndarray, digits: int = 5) -> None:
    """A minimal Wavefront OBJ (v and f lines only, 1-based indices)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64) + 1
    lines = [f"v {x:.{digits}f} {y:.{digits}f} {z:.{digits}f}" for x, y, z in v]
    lines += [f"f {a} {b} {c}" for a, b, c in f]
    Path(path).write_text("\n".join(lines) + "\n")


# name -> generator with the parameters of the committed OBJ files
MESHES = {"torus": torus, "gem": gem, "dish": dish, "blob": blob}
