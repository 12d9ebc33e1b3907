"""View segments on camera rays sorted by screen cell: the lighting side's candidates
without a tree (``lsg_splat`` in ``cl_kernels/estimators/lsg.cl``).

A view segment whose line passes through the eye (a pinhole camera's first segment of a
path, in whatever medium or glass the camera is in) is fixed by its direction; the cell
of a grid over the image plane that the direction falls in says which lighting segments
can come within the radius of it. :func:`build_screen_cells` picks those segments out of a
set, sorts them by cell and puts them on the device; the rest (segments after a mirror or
glass) stay with the tree (:class:`~clscatter.estimators.line_gather.ViewTree`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..device import Engine, structs
from ..transport import primitives as prim
from .fixed_sum import SCATTER_BYTES
from .line_tree import point_blocks
from .row_chunks import map_row_chunks

# Bytes one view segment on a camera ray costs in ScreenCells: its record (64), direction
# (12), index (4) and sums and count (SCATTER_BYTES, 32) on the device, a host copy of all
# but the sums and the build's float64 directions and cells (about 180) -- about 300.
BYTES_PER_SCREEN_VIEW = 296

# How far (normalised frame) a view segment's line may pass from the eye and still count
# as a camera ray: float32 ends of a segment traced from the eye miss it by far less; the
# kernel widens its reach by the largest miss of the segments taken.
ON_RAY = 1e-4


@dataclass
class ScreenCells:
    """View segments on camera rays in the order of their screen cells, on the device.
    ``bufs``: the records in cell order (``views``), their unit directions (``dirs``,
    :func:`~.line_tree.point_blocks` of x, y, z), their indices (``ids``), each cell's
    first segment (``start``, ``nx * ny + 1``) and the fixed-point sums and valid pairs
    (``acc``, a record of SCATTER_BYTES per segment). ``frame``: the eye and the camera's axes (float32 4-vectors, normalised
    frame); ``grid``: the lower corner of the cells in tangent coordinates (x / z, y / z)
    and the inverse cell sizes; ``reach``: the largest distance of a segment's line from
    the eye."""

    count: int
    nx: int
    ny: int
    frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    grid: np.ndarray
    reach: float
    weight_max: float
    bufs: dict
    nbytes: int

    def release(self, engine: Engine) -> None:
        engine.free(*self.bufs.values())
        self.bufs = {}


def camera_axes(camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(eye, x, y, z) of a CAMERA record in float64: z along ``forward``, x along the part
    of ``right`` across it, y = z x x."""
    cam = np.asarray(camera).reshape(-1)[0]
    eye = cam["origin"][:3].astype(np.float64)
    z = cam["forward"][:3].astype(np.float64)
    z = z / np.linalg.norm(z)
    x = cam["right"][:3].astype(np.float64)
    x = x - (x @ z) * z
    x = x / np.linalg.norm(x)
    return eye, x, np.cross(z, x), z


def on_camera_rays(views: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, float]:
    """Which of ``views`` (VIEW_SEGMENT) lie on camera rays (their line within
    :data:`ON_RAY` of the eye, heading away from it, in front of the camera, of positive
    length), and the largest distance of those lines from the eye (float32, in chunks of
    rows on threads: :func:`~.row_chunks.map_row_chunks`)."""
    eye, _, _, z = (x.astype(np.float32) for x in camera_axes(camera))
    n = len(views)
    ok = np.zeros(n, bool)

    def chunk(s: int, e: int) -> float:
        a = views["a"][s:e, :3]
        d = views["b"][s:e, :3] - a
        length = np.sqrt(np.einsum("ij,ij->i", d, d))
        w = a - eye
        c = np.cross(w, d)
        inv = 1.0 / np.maximum(length, np.float32(1e-30))
        miss = np.sqrt(np.einsum("ij,ij->i", c, c)) * inv
        ok[s:e] = ((length > 0) & (miss <= ON_RAY) & (np.einsum("ij,ij->i", w, d) * inv >= -ON_RAY)
                   & (d @ z > 1e-3 * length))
        return float(miss[ok[s:e]].max()) if ok[s:e].any() else 0.0
    return ok, max(map_row_chunks(chunk, n), default=0.0) if n else 0.0


def build_screen_cells(engine: Engine, views: np.ndarray, idx: np.ndarray, camera: np.ndarray,
                       reach: float, views_buf=None) -> ScreenCells:
    """The :class:`ScreenCells` of ``views[idx]`` (segments on camera rays,
    :func:`on_camera_rays`), on a grid of the camera's pixels over the tangent range of
    their directions. ``views_buf``: the same view segments on the device, from which the
    records are gathered there (else they are uploaded)."""
    cam = np.asarray(camera).reshape(-1)[0]
    eye, ex, ey, ez = camera_axes(camera)
    idx = np.asarray(idx, np.int64)
    n = len(idx)
    # the records as rows of 16 floats (a: 0-3, b: 4-7, weight: 8-11): columns of chosen
    # rows are read far faster than a structured array's fields
    rows = np.ascontiguousarray(views).view(np.float32).reshape(len(views), -1)
    d = rows[idx, 4:7] - rows[idx, 0:3]
    zc = d @ ez.astype(np.float32)
    tx, ty = (d @ ex.astype(np.float32)) / zc, (d @ ey.astype(np.float32)) / zc
    nx, ny = max(int(cam["width"]), 1), max(int(cam["height"]), 1)
    if n:
        lo = np.array([tx.min(), ty.min()])
        span = np.maximum(np.array([tx.max(), ty.max()]) - lo, 1e-9)
    else:
        lo, span = np.zeros(2), np.ones(2)
    # the grid a little wider than the directions, so that none is on its far edge; the
    # cells from the float32 values the kernel reads
    grid = np.array([lo[0], lo[1], *(np.array([nx, ny]) / (span * (1.0 + 1e-6)))], np.float32)
    lo, inv = grid[:2].astype(np.float64), grid[2:].astype(np.float64)
    cx = np.clip(np.floor((tx - lo[0]) * inv[0]), 0, nx - 1).astype(np.int64)
    cy = np.clip(np.floor((ty - lo[1]) * inv[1]), 0, ny - 1).astype(np.int64)
    cell = cy * nx + cx
    order = np.argsort(cell, kind="stable")
    start = np.zeros(nx * ny + 1, np.int32)
    np.cumsum(np.bincount(cell, minlength=nx * ny), out=start[1:])
    # unit directions for the plane test, in the cell order, as blocks of POINT_LANES (rows
    # x, y, z): the kernel tests a block at once
    if n:
        d = d[order]
        d = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
    dirs = point_blocks(d if n else np.zeros((0, 3), np.float32))
    ids = idx[order].astype(np.int32) if n else np.zeros(1, np.int32)
    bufs = {"dirs": engine.to_device(dirs), "ids": engine.to_device(ids),
            "start": engine.to_device(start)}
    if views_buf is not None and n:
        bufs["views"] = prim.gather(engine, views_buf, bufs["ids"], n, views.dtype.itemsize)
    else:
        bufs["views"] = engine.to_device(views[ids] if n else np.zeros(1, views.dtype))
    bufs["acc"] = engine.zeros(SCATTER_BYTES * max(n, 1))
    frame = (structs.vec4(eye), structs.vec4(ex), structs.vec4(ey), structs.vec4(ez))
    w_max = float(rows[idx, 8:11].max()) if n else 0.0
    return ScreenCells(n, nx, ny, frame, grid, float(reach), max(w_max, 0.0), bufs,
                       int(dirs.nbytes + ids.nbytes + start.nbytes + (64 + SCATTER_BYTES) * n))


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """The low 16 bits of ``v`` spread to the even bits of a 32-bit code."""
    v = v.astype(np.uint32) & 0xFFFF
    v = (v | (v << 8)) & 0x00FF00FF
    v = (v | (v << 4)) & 0x0F0F0F0F
    v = (v | (v << 2)) & 0x33333333
    return (v | (v << 1)) & 0x55555555


def splat_order(sc: ScreenCells, a: np.ndarray, u: np.ndarray, length: np.ndarray) -> np.ndarray:
    """An order of lighting segments (start ``a``, unit ``u``, ``length``; normalised
    frame) in which neighbours cross nearby cells: by the Morton code of the cell their
    midpoint projects to (behind the camera: the corner cell). Consecutive work-items then
    read the same view segments while they are in cache."""
    eye, ex, ey, ez = (x[:3].astype(np.float64) for x in sc.frame)
    w = a + 0.5 * length[:, None] * u - eye
    z = w @ ez
    safe = np.where(z > 1e-9, z, 1.0)
    cx = np.clip((w @ ex / safe - sc.grid[0]) * sc.grid[2], 0, sc.nx - 1)
    cy = np.clip((w @ ey / safe - sc.grid[1]) * sc.grid[3], 0, sc.ny - 1)
    code = _spread_bits(np.where(z > 1e-9, cx, 0)) | (_spread_bits(np.where(z > 1e-9, cy, 0)) << 1)
    return np.argsort(code, kind="stable")
