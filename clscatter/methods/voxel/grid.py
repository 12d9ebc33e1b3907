"""The voxel grid: where it lies, and the NumPy mirror of the kernels' shared struct.

Everything is in the normalised device frame (``clscatter/scene/normalised.py``). A grid has
cubic voxels of side ``h``; voxel (i, j, k) spans ``lo + [i, i+1) h`` and its values live
at the centre ``lo + (i + 0.5) h``. Host arrays have shape (nx, ny, nz) in C order, which
is exactly the device layout (``idx = (i * ny + j) * nz + k``, ``cl_kernels/voxel.cl``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...device import structs
from ...scene.model import Scene, Volume
from ...scene.normalised import Frame

F4 = (np.float32, 4)

# mirror of VoxRay in cl_kernels/voxel.h
VOX_RAY = structs.register_struct("voxel.h", "VoxRay", np.dtype([
    ("o", *F4), ("d", *F4), ("thr", *F4),
    ("pixel", np.int32), ("sample", np.int32), ("branch", np.int32), ("flags", np.int32),
], align=True))
VOX_SKIP_FIRST = 1


@dataclass(frozen=True)
class GridBox:
    """An axis-aligned grid of cubic voxels (normalised frame)."""

    lo: np.ndarray            # (3,) float64, the grid's minimum corner
    h: float                  # voxel side
    dims: tuple[int, int, int]

    @property
    def hi(self) -> np.ndarray:
        return self.lo + np.asarray(self.dims, np.float64) * self.h

    @property
    def size(self) -> int:
        return int(np.prod(self.dims))

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y and z (1-D arrays)."""
        return tuple(self.lo[a] + (np.arange(self.dims[a]) + 0.5) * self.h for a in range(3))

    # kernel arguments
    def lo4(self) -> np.ndarray:
        return np.array([*self.lo, 0.0], np.float32)

    def hi4(self) -> np.ndarray:
        return np.array([*self.hi, 0.0], np.float32)

    def dims4(self) -> np.ndarray:
        return np.array([*self.dims, 0], np.int32)

    def describe(self, frame: Frame | None = None) -> dict:
        """Extent and resolution, in scene units when ``frame`` is given (for --stats)."""
        lo, hi, h = self.lo, self.hi, self.h
        if frame is not None:
            lo, hi, h = lo * frame.scale + frame.centre, hi * frame.scale + frame.centre, h * frame.scale
        return {"min": [float(x) for x in lo], "max": [float(x) for x in hi],
                "dims": [int(d) for d in self.dims], "voxel_size": float(h)}


def make_box(lo, hi, resolution: int) -> GridBox:
    """The grid of ``resolution`` voxels along the longest side of [lo, hi], centred on it
    (other sides rounded up to whole voxels)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    ext = hi - lo
    h = float(ext.max()) / resolution
    dims = tuple(int(max(1, math.ceil(e / h - 1e-9))) for e in ext)
    centre = (lo + hi) / 2
    return GridBox(centre - np.asarray(dims) * h / 2, h, dims)


def volume_region(v: Volume, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """A volume's region's bounding box in the normalised frame."""
    if v.mesh is not None:
        p = frame.point(v.mesh.vertices)
        return p.min(axis=0), p.max(axis=0)
    return frame.point(v.grid_bounds[0]), frame.point(v.grid_bounds[1])


def scene_box(scene: Scene, frame: Frame, resolution: int, margin: float) -> GridBox:
    """The grid for a scene's volumes: their union's box grown by ``margin`` times its
    longest side on every side; ``resolution`` voxels along the longest side, but never
    finer than the finest voxel any shape volume's own ``resolution`` key asks for (the
    coarser of the two wins, so a volume may lower the cost, never raise it; a grid
    volume's data is resampled trilinearly at whatever resolution the grid has)."""
    regions = [volume_region(v, frame) for v in scene.volumes]
    lo = np.min([r[0] for r in regions], axis=0)
    hi = np.max([r[1] for r in regions], axis=0)
    ext = float(np.max(hi - lo))
    lo, hi = lo - margin * ext, hi + margin * ext
    full = float(np.max(hi - lo))
    h = full / resolution
    for v, (a, b) in zip(scene.volumes, regions):
        if v.resolution and v.mesh is not None:     # a grid volume's size is its data's
            h = max(h, float(np.max(b - a)) / v.resolution)
    return make_box(lo, hi, max(1, int(round(full / h))))
