"""Bounding volume hierarchy: binned-SAH build in vectorised NumPy, traversal in OpenCL.

Build (:func:`build_bvh`)
    Top-down, one tree *level* at a time: every open node of a level is binned at once
    (``bins`` bins over the node's centroid bounds, per axis; bin counts with
    ``np.bincount`` and bin bounds with ``np.minimum.at``/``np.maximum.at`` over combined
    (node, axis, bin) indices), the surface area heuristic is evaluated for all split
    planes of all nodes with prefix/suffix sweeps on reshaped arrays, and each node's
    triangles are partitioned in place by a stable sort on the (node, side) key. There
    is no Python loop over triangles or nodes, only over levels.

    SAH cost model: traversal 1, intersection 1, i.e. a split costs
    ``1 + (A_L N_L + A_R N_R) / A`` against ``N`` for a leaf. A node becomes a leaf when
    ``count <= leaf_size``, or when SAH finds no split worth it and
    ``count <= max_leaf`` (16). Larger nodes are always split: by SAH if it has any
    split with both sides non-empty, else (all centroids coincide) in the middle by
    index.

    Depth: the kernel's traversal stack has 64 entries (``BVH_STACK_SIZE`` in
    ``cl_kernels/bvh.h``), which suffices for trees of depth <= 64 (root at depth 0).
    The builder switches a node to median splits by index as soon as
    ``depth + ceil(log2(count)) >= MAX_DEPTH - 1``, which bounds the final depth by
    ``MAX_DEPTH - 1 = 63`` for any input; the result is also asserted.

    Degenerate triangles (exactly zero area in float64 from the float32 vertices) and
    triangles with non-finite vertices are left out of every leaf: they can never be
    hit. They still occupy the last slots of :attr:`BVH.triangles` / :attr:`BVH.order`
    so both keep one entry per input triangle.

Layout (``BVHNode`` in ``cl_kernels/common.h``)
    Depth-first: an interior node (``count == 0``) has its left child at the next index
    and its right child at ``left_first``; a leaf (``count > 0``) holds the triangles
    ``[left_first, left_first + count)`` of the reordered triangle array. An empty BVH
    (no usable triangles) is one node with an empty box (``bmin = +1e30``,
    ``bmax = -1e30``) and ``count == 0``; traversal misses at once.

Device use
    :meth:`BVH.upload` gives the two buffers the kernels of ``bvh.h`` take: the nodes and
    the triangles as ``3 * T`` float4 (v0, v1, v2 of each reordered triangle).
    :func:`trace` runs the test kernels of ``cl_kernels/bvh.cl`` for a batch of rays.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..device.structs import BVH_NODE

MAX_DEPTH = 64   # == BVH_STACK_SIZE in cl_kernels/bvh.h
MAX_LEAF = 16    # largest leaf SAH may choose; bigger nodes are always split
EMPTY_BOX = 1e30


@dataclass
class BVHBuffers:
    """Device buffers of an uploaded BVH (pass ``nodes``, ``triangles`` to kernels)."""

    nodes: object
    triangles: object
    n_nodes: int
    n_triangles: int

    def free(self, engine) -> None:
        engine.free(self.nodes, self.triangles)


@dataclass
class BVH:
    """A built BVH.

    ``nodes``: structured array of :data:`clscatter.device.structs.BVH_NODE`, depth-first.
    ``triangles``: (T, 3, 4) float32, the reordered triangles (xyz, w = 0), the array
    the device gets (3 float4 per triangle).
    ``order``: (T,) int64, the input index of each reordered slot.
    ``depth``: maximum depth (root = 0). ``n_valid``: triangles referenced by leaves
    (the first ``n_valid`` slots); the rest are degenerate and never hit.
    """

    nodes: np.ndarray
    triangles: np.ndarray
    order: np.ndarray
    depth: int
    n_valid: int
    build_seconds: float = 0.0
    _device: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.nodes)

    @property
    def n_triangles(self) -> int:
        return len(self.order)

    @property
    def n_leaves(self) -> int:
        return int(np.count_nonzero(self.nodes["count"] > 0))

    def stats(self) -> dict:
        """Summary numbers (node/leaf counts, depth, leaf sizes, SAH cost, build time)."""
        leaf = self.nodes["count"] > 0
        counts = self.nodes["count"][leaf]
        return {
            "triangles": self.n_triangles,
            "valid_triangles": self.n_valid,
            "degenerate_triangles": self.n_triangles - self.n_valid,
            "nodes": len(self.nodes),
            "leaves": int(leaf.sum()),
            "depth": int(self.depth),
            "mean_leaf_size": float(counts.mean()) if len(counts) else 0.0,
            "max_leaf_size": int(counts.max()) if len(counts) else 0,
            "sah_cost": sah_cost(self),
            "build_seconds": float(self.build_seconds),
        }

    def upload(self, engine) -> BVHBuffers:
        """New device buffers (nodes, triangles); the caller owns them (``.free``)."""
        nodes = engine.to_device(self.nodes)
        tris = engine.to_device(np.ascontiguousarray(self.triangles, np.float32).reshape(-1, 4))
        return BVHBuffers(nodes, tris, len(self.nodes), self.n_triangles)

    def device_buffers(self, engine) -> BVHBuffers:
        """Buffers uploaded once per engine and kept with this BVH (used by :func:`trace`)."""
        key = id(engine)
        if key not in self._device:
            self._device[key] = (engine, self.upload(engine))
        return self._device[key][1]

    def release(self) -> None:
        """Free the buffers :meth:`device_buffers` kept."""
        for engine, bufs in self._device.values():
            bufs.free(engine)
        self._device.clear()


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    e = hi - lo
    return 2.0 * (e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0])


def sah_cost(bvh: BVH) -> float:
    """SAH cost of the tree (traversal 1, intersection 1), relative to the root area."""
    n = bvh.nodes
    if len(n) == 0 or not (n["bmin"][0, 0] <= n["bmax"][0, 0]):
        return 0.0
    lo = n["bmin"].astype(np.float64)
    hi = n["bmax"].astype(np.float64)
    a = _area(lo, hi)
    root = a[0] if a[0] > 0 else 1.0
    leaf = n["count"] > 0
    return float((a[~leaf].sum() + (a[leaf] * n["count"][leaf]).sum()) / root)


def _empty_bvh(tri32: np.ndarray, order: np.ndarray, t0: float) -> BVH:
    nodes = np.zeros(1, BVH_NODE)
    nodes["bmin"] = EMPTY_BOX
    nodes["bmax"] = -EMPTY_BOX
    tris = np.zeros((len(tri32), 3, 4), np.float32)
    tris[:, :, :3] = tri32[order]
    return BVH(nodes, tris, order.astype(np.int64), 0, 0, time.perf_counter() - t0)


def _depth_first(lv_lo, lv_hi, lv_start, lv_count, lv_left, lv_right) -> np.ndarray:
    """The BVH_NODE array in depth-first order from the per-level arrays of the
    breadth-first build (node ids contiguous per level; a leaf has left = -1)."""
    bounds = np.cumsum([0] + [len(x) for x in lv_start])
    n_nodes = int(bounds[-1])
    lo_all = np.concatenate(lv_lo)
    hi_all = np.concatenate(lv_hi)
    start_all = np.concatenate(lv_start)
    count_all = np.concatenate(lv_count)
    left_all = np.concatenate(lv_left)
    right_all = np.concatenate(lv_right)
    size = np.ones(n_nodes, np.int64)
    for li in range(len(lv_start) - 1, -1, -1):
        ids = np.arange(bounds[li], bounds[li + 1])
        ids = ids[left_all[ids] >= 0]
        size[ids] += size[left_all[ids]] + size[right_all[ids]]
    dfs = np.zeros(n_nodes, np.int64)
    for li in range(len(lv_start)):
        ids = np.arange(bounds[li], bounds[li + 1])
        ids = ids[left_all[ids] >= 0]
        dfs[left_all[ids]] = dfs[ids] + 1
        dfs[right_all[ids]] = dfs[ids] + 1 + size[left_all[ids]]

    nodes = np.zeros(n_nodes, BVH_NODE)
    nodes["bmin"][dfs] = lo_all.astype(np.float32)
    nodes["bmax"][dfs] = hi_all.astype(np.float32)
    leaf = left_all < 0
    nodes["left_first"][dfs] = np.where(leaf, start_all, dfs[np.maximum(right_all, 0)])
    nodes["count"][dfs] = count_all

    return nodes


def build_bvh(triangles: np.ndarray, leaf_size: int = 4, bins: int = 16,
              max_leaf: int = MAX_LEAF) -> BVH:
    """Build a binned-SAH BVH over ``triangles`` ((T, 3, 3) vertex positions).

    Coordinates are used as float32 (what the device sees), so node boxes contain the
    device triangles exactly. See the module docstring for the algorithm and layout.

    One long function on purpose: each pass of its loop handles every open node of one
    level at once (NumPy over all their primitives), and the binning, the prefix and
    suffix unions, the SAH choice and the partition share a dozen per-level arrays.
    """
    t0 = time.perf_counter()
    tri = np.asarray(triangles)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (T, 3, 3), got {tri.shape}")
    if leaf_size < 1 or bins < 2:
        raise ValueError("leaf_size must be >= 1 and bins >= 2")
    max_leaf = max(int(max_leaf), int(leaf_size))
    tri32 = np.ascontiguousarray(tri, dtype=np.float32)
    v = tri32.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(v).all(axis=(1, 2))
        cr = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        usable = finite & (cr != 0.0).any(axis=1)
    valid = np.flatnonzero(usable)
    degenerate = np.flatnonzero(~usable)
    n_prims = len(valid)
    if n_prims == 0:
        return _empty_bvh(tri32, degenerate, t0)

    pv = v[valid]
    plo_all = pv.min(axis=1)
    phi_all = pv.max(axis=1)
    cen_all = 0.5 * (plo_all + phi_all)
    del pv, v, cr

    perm = np.arange(n_prims)
    ax3 = np.arange(3)
    # per level (BFS, ids contiguous per level): arrays of the nodes closed on that level
    lv_lo, lv_hi, lv_start, lv_count, lv_left, lv_right = [], [], [], [], [], []
    o_start = np.zeros(1, np.int64)
    o_count = np.array([n_prims], np.int64)
    next_id = 1
    level = 0
    while len(o_start):
        k_open = len(o_start)
        offs = np.cumsum(o_count) - o_count
        m = int(o_count.sum())
        seg = np.repeat(np.arange(k_open), o_count)
        pos = np.arange(m) - offs[seg] + o_start[seg]
        p = perm[pos]
        plo, phi, pc = plo_all[p], phi_all[p], cen_all[p]
        nlo = np.minimum.reduceat(plo, offs, axis=0)
        nhi = np.maximum.reduceat(phi, offs, axis=0)

        split = np.zeros(k_open, bool)
        n_left = np.zeros(k_open, np.int64)
        side_all = np.zeros(m, bool)
        want = o_count > leaf_size
        if want.any():
            kw = int(want.sum())
            wsel = np.flatnonzero(want[seg])          # prims of the nodes that may split
            wmap = np.cumsum(want) - 1
            sseg = wmap[seg[wsel]]
            wcount = o_count[want]
            woffs = np.cumsum(wcount) - wcount
            wc = pc[wsel]
            cmin = np.minimum.reduceat(wc, woffs, axis=0)
            cmax = np.maximum.reduceat(wc, woffs, axis=0)
            ext = cmax - cmin
            with np.errstate(divide="ignore"):
                scale = np.where(ext > 0, bins / np.where(ext > 0, ext, 1.0), 0.0)
            b = ((wc - cmin[sseg]) * scale[sseg]).astype(np.int64)
            np.clip(b, 0, bins - 1, out=b)
            idx = ((sseg[:, None] * 3 + ax3) * bins + b).ravel()
            nb = kw * 3 * bins
            cnt = np.bincount(idx, minlength=nb).reshape(kw, 3, bins)
            blo = np.full((3, nb), np.inf)
            bhi = np.full((3, nb), -np.inf)
            wlo, whi = plo[wsel], phi[wsel]
            for j in range(3):
                np.minimum.at(blo[j], idx, np.repeat(wlo[:, j], 3))
                np.maximum.at(bhi[j], idx, np.repeat(whi[:, j], 3))
            blo = blo.reshape(3, kw, 3, bins).transpose(1, 2, 3, 0)   # (node, axis, bin, xyz)
            bhi = bhi.reshape(3, kw, 3, bins).transpose(1, 2, 3, 0)
            # prefix (left of a plane) and suffix (right) unions
            l_lo = np.minimum.accumulate(blo, axis=2)[:, :, :-1]
            l_hi = np.maximum.accumulate(bhi, axis=2)[:, :, :-1]
            l_n = np.cumsum(cnt, axis=2)[:, :, :-1]
            r_lo = np.minimum.accumulate(blo[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
            r_hi = np.maximum.accumulate(bhi[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
            r_n = wcount[:, None, None] - l_n
            with np.errstate(invalid="ignore", over="ignore"):
                cost = (np.where(l_n > 0, _area(l_lo, l_hi), 0.0) * l_n
                        + np.where(r_n > 0, _area(r_lo, r_hi), 0.0) * r_n)
            cost = np.where((l_n > 0) & (r_n > 0), cost, np.inf).reshape(kw, -1)
            best = np.argmin(cost, axis=1)
            bcost = cost[np.arange(kw), best]
            baxis = best // (bins - 1)
            bplane = best % (bins - 1)        # left side: bins <= bplane
            parea = _area(nlo[want], nhi[want])
            sah_ok = np.isfinite(bcost)
            do_sah = sah_ok & ((bcost < (wcount - 1) * parea) | (wcount > max_leaf))
            do_med = ~sah_ok & (wcount > max_leaf)
            # depth guard: from here on only halving splits fit below MAX_DEPTH
            force = level + np.ceil(np.log2(wcount)) >= MAX_DEPTH - 1
            do_med |= do_sah & force
            do_sah &= ~force
            wsplit = do_sah | do_med
            side_sah = b[np.arange(len(wsel)), baxis[sseg]] > bplane[sseg]
            side_med = (np.arange(len(wsel)) - woffs[sseg]) >= (wcount // 2)[sseg]
            side = np.where(do_sah[sseg], side_sah, side_med) & wsplit[sseg]
            side_all[wsel] = side
            split[want] = wsplit
            n_left[want] = np.bincount(sseg[~side], minlength=kw)
            if split.any():
                key = seg * 2 + side_all
                perm[pos] = p[np.argsort(key, kind="stable")]

        s = np.flatnonzero(split)
        ns = len(s)
        left = np.full(k_open, -1, np.int64)
        right = np.full(k_open, -1, np.int64)
        left[s] = next_id + 2 * np.arange(ns)
        right[s] = left[s] + 1
        lv_lo.append(nlo)
        lv_hi.append(nhi)
        lv_start.append(o_start)
        lv_count.append(np.where(split, 0, o_count))
        lv_left.append(left)
        lv_right.append(right)
        next_id += 2 * ns
        c_start = np.stack([o_start[s], o_start[s] + n_left[s]], axis=1).ravel()
        c_count = np.stack([n_left[s], o_count[s] - n_left[s]], axis=1).ravel()
        o_start, o_count = c_start, c_count
        level += 1

    depth = level - 1
    if depth > MAX_DEPTH:  # cannot happen with the depth guard above
        raise AssertionError(f"BVH depth {depth} exceeds the kernel stack ({MAX_DEPTH})")

    nodes = _depth_first(lv_lo, lv_hi, lv_start, lv_count, lv_left, lv_right)
    order = np.concatenate([valid[perm], degenerate]).astype(np.int64)
    tris = np.zeros((len(order), 3, 4), np.float32)
    tris[:, :, :3] = tri32[order]
    return BVH(nodes, tris, order, int(depth), n_prims, time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------
# tracing batches of rays with the test kernels of cl_kernels/bvh.cl

def _as_float4(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] not in (3, 4):
        raise ValueError(f"rays must have shape (N, 3), got {a.shape}")
    out = np.zeros((len(a), 4), np.float32)
    out[:, :3] = a[:, :3]
    return out


def trace(engine, bvh: BVH, origins: np.ndarray, dirs: np.ndarray, tmin: float = 0.0,
          tmax: float = np.inf, closest: bool = True, uv: bool = False):
    """Trace rays ``origins + t * dirs`` (N, 3) against ``bvh`` on ``engine``.

    Closest hit (``closest=True``): returns ``(t, tri)``, ``t`` (N,) float32 with inf for
    a miss (in units of ``|dirs|``), ``tri`` (N,) int64 input triangle ids, -1 for a
    miss; with ``uv=True`` also ``uv`` (N, 2) float32, barycentrics of v1 and v2 (NaN on
    a miss). Any hit (``closest=False``): a (N,) bool array. Only hits with
    ``tmin < t < tmax`` count. The BVH buffers are uploaded once per engine and kept
    (``bvh.release()`` frees them); ray and result buffers are freed before returning.
    """
    o = _as_float4(origins)
    d = _as_float4(dirs)
    if len(o) != len(d):
        raise ValueError("origins and dirs differ in length")
    n = len(o)
    if n == 0:
        if not closest:
            return np.zeros(0, bool)
        empty = (np.zeros(0, np.float32), np.zeros(0, np.int64))
        return empty + (np.zeros((0, 2), np.float32),) if uv else empty
    bufs = bvh.device_buffers(engine)
    ob, db = engine.to_device(o), engine.to_device(d)
    args = dict(nodes=bufs.nodes, tris=bufs.triangles, orig=ob, dir=db, tmin=tmin, tmax=tmax, n=n)
    if not closest:
        hb = engine.empty(4 * n)
        try:
            engine.call("bvh", "any_hit", n, **args, hit_out=hb)
            return engine.read(hb, n, np.int32) != 0
        finally:
            engine.free(ob, db, hb)
    tb, ib = engine.empty(4 * n), engine.empty(4 * n)
    ub = engine.empty(8 * n) if uv else None
    try:
        if uv:
            engine.call("bvh", "closest_hit_uv", n, **args, t_out=tb, tri_out=ib, uv_out=ub)
        else:
            engine.call("bvh", "closest_hit", n, **args, t_out=tb, tri_out=ib)
        t = engine.read(tb, n, np.float32)
        slot = engine.read(ib, n, np.int32)
        uvs = engine.read(ub, (n, 2), np.float32) if uv else None
    finally:
        engine.free(ob, db, tb, ib, *([ub] if uv else []))
    order = bvh.order if len(bvh.order) else np.zeros(1, np.int64)
    tri = np.where(slot >= 0, order[np.maximum(slot, 0)], -1).astype(np.int64)
    return (t, tri, uvs) if uv else (t, tri)
