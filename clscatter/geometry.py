"""Host-side geometry helpers used by several stages: unit vectors, box corners, slab
clipping. One copy of each (vectorised NumPy, float64); kernels have their own in
``cl_kernels/common.h``."""
from __future__ import annotations

import numpy as np


def unit(v) -> np.ndarray:
    """``v`` (one vector or rows of vectors) scaled to unit length; zero rows stay zero."""
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners of the box [lo, hi], corner i taking hi on axis k where bit k of i is
    set (the order ``cl_kernels`` and the BVH use)."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1
    return np.where(bits == 1, hi, lo)


def perpendicular_axes(d) -> tuple[np.ndarray, np.ndarray]:
    """Unit ``s1``, ``s2`` completing unit ``d`` to a right-handed orthonormal frame
    (``s1 = d x h / |d x h|`` with ``h`` the x axis, or the y axis when ``d`` is near x;
    ``s2 = d x s1``): the frame of a light's maps, grids and emission rectangles."""
    d = np.asarray(d, np.float64)
    h = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    s1 = np.cross(d, h)
    s1 = s1 / np.linalg.norm(s1)
    return s1, np.cross(d, s1)


def slab_interval(a: np.ndarray, d: np.ndarray, lo, hi, t_max) -> tuple[np.ndarray, np.ndarray]:
    """Row-wise parameters [enter, leave] of the part of ``a + t d``, t in [0, t_max], that
    lies in the closed box [lo, hi] (empty when enter > leave). Slab test in float64; a
    direction component of exactly 0 is handled without dividing (the ray is inside that
    slab for all t or for none)."""
    a = np.asarray(a, np.float64)
    d = np.asarray(d, np.float64)
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0, t1 = (lo - a) * inv, (hi - a) * inv
    par = d == 0.0
    inside = (a >= lo) & (a <= hi)
    near = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    far = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    # the three slabs combined elementwise (a reduction over a length-3 axis is ~10x slower)
    enter = np.maximum(np.maximum(np.maximum(near[..., 0], near[..., 1]), near[..., 2]), 0.0)
    leave = np.minimum(np.minimum(np.minimum(far[..., 0], far[..., 1]), far[..., 2]), t_max)
    return enter, leave


def edge_keys(a, b, n: int):
    """One integer per undirected edge between vertices ``a`` and ``b`` (arrays or ints) of
    a mesh of fewer than ``n`` vertices: the same for a -> b and b -> a. (np.unique(axis=0)
    on the pairs would compare structured arrays, which turns a KeyboardInterrupt raised
    by a signal meanwhile into a TypeError.)"""
    return np.minimum(a, b) * n + np.maximum(a, b)


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """``(3F, 2)`` the edges of every triangle, each as the triangle winds it (a -> b)."""
    f = np.asarray(faces, np.int64)
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """``(E, 2)`` edges of a triangle mesh (vertex indices, shared vertices merged) that
    only one triangle uses, each as that triangle winds it (a -> b): none for a closed
    surface."""
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return np.zeros((0, 2), np.int64)
    d = mesh_edges(f)
    key = edge_keys(d[:, 0], d[:, 1], int(f.max()) + 1)
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    return d[counts[inv.reshape(-1)] == 1]


def open_edges(faces: np.ndarray) -> int:
    """Edges of a triangle mesh (vertex indices, shared vertices merged) that only one
    triangle uses (:func:`boundary_edges`): 0 for a closed surface."""
    return int(len(boundary_edges(faces)))


#: the direction of the parity ray from the camera (no symmetry of a box or a sphere lies
#: along it, so it does not graze their edges)
PARITY_RAY = np.array([0.5312, 0.6217, 0.5755])


def ray_crossings(origin, direction, triangles: np.ndarray) -> int:
    """How many of ``triangles`` (F, 3, 3) the ray ``origin + t direction``, t > 0, crosses
    (Moller-Trumbore in float64): odd when the origin lies inside a closed surface."""
    tri = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    o, d = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - tri[:, 0]
    u = np.einsum("ij,ij->i", tv, p) * inv
    q = np.cross(tv, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return int(np.count_nonzero(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)))
