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
