"""The octree as a dense level grid (Sun et al. 2008, sec. 4.2 and 5.3), built by kernels.

A min/max pyramid of n (level 0 = the voxels, level k = cells of 2^k voxels per side,
aligned at the grid's corner, clipped at its far faces; ``oct_reduce``), then for every
voxel the coarsest level whose cell has ``n_max - n_min < eps2`` and the step limit in
that node: unlimited where the range is also below ``eps`` (march to the node's face),
``limit`` voxels where it lies in [eps, eps2) (``oct_levels``). The paper's values are
eps = 0.005, eps2 = 0.02 and an 8-voxel limit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...device import Engine
from .grid import GridBox


def level_dims(dims, k: int) -> tuple[int, int, int]:
    """Cells of pyramid level k: ceil(dims / 2^k)."""
    return tuple(-(-d // (1 << k)) for d in dims)


@dataclass
class Octree:
    level: object        # device uchar grid: octree level of the leaf holding each voxel
    smax: object         # device float grid: step limit in voxels (inf: none)
    levels: int          # pyramid levels (coarsest = levels - 1 is one cell)

    def free(self, eng: Engine) -> None:
        eng.free(self.level, self.smax)


def build_octree(eng: Engine, box: GridBox, n_buf, eps: float, eps2: float, limit: float) -> Octree:
    """Dense octree level and step-limit grids for the index grid ``n_buf`` (device)."""
    levels = 1 + max(0, math.ceil(math.log2(max(box.dims))))
    sizes = [int(np.prod(level_dims(box.dims, k))) for k in range(levels)]
    off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
    total = int(sum(sizes))
    pmin, pmax = eng.empty(4 * total), eng.empty(4 * total)
    off_buf = eng.to_device(off)
    level, smax = eng.empty(box.size), eng.empty(4 * box.size)
    try:
        cl = eng.cl
        cl.enqueue_copy(eng.queue, pmin, n_buf, byte_count=4 * box.size)
        cl.enqueue_copy(eng.queue, pmax, n_buf, byte_count=4 * box.size)
        for k in range(1, levels):
            sd, dd = level_dims(box.dims, k - 1), level_dims(box.dims, k)
            eng.call("voxel", "oct_reduce", sizes[k], pmin=pmin, pmax=pmax, soff=int(off[k - 1]),
                     sd=sd, doff=int(off[k]), dd=dd)
        eng.call("voxel", "oct_levels", box.size, pmin=pmin, pmax=pmax, off=off_buf, levels=levels,
                 dims=box.dims4(), eps=eps, eps2=eps2, limit=limit, level=level, smax=smax)
    finally:
        eng.free(pmin, pmax, off_buf)
    return Octree(level, smax, levels)


def octree_reference(n: np.ndarray, eps: float, eps2: float, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of :func:`build_octree` (for the tests): (level, smax) grids."""
    dims = n.shape
    levels = 1 + max(0, math.ceil(math.log2(max(dims))))
    level = np.full(dims, -1, np.int32)
    smax = np.zeros(dims, np.float32)
    idx = np.indices(dims)
    for k in range(levels - 1, -1, -1):
        cd = level_dims(dims, k)
        lo = np.full(cd, np.inf)
        hi = np.full(cd, -np.inf)
        cells = tuple(i >> k for i in idx)
        np.minimum.at(lo, cells, n)
        np.maximum.at(hi, cells, n)
        rng = (hi - lo)[cells]
        take = (level < 0) & ((rng < eps2) | (k == 0))
        level[take] = k
        smax[take] = np.where(rng[take] < eps, np.inf, limit)
    return level.astype(np.uint8), smax
