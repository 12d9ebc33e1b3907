"""The estimators' kd-tree: one tree over segments and points, in flat NumPy arrays.

Items are segments ``[a_i, b_i]`` (the ray map's lighting rays) or points (``a_i = b_i``:
the photons of ``photonmap`` and ``vpm``, the ray map's ray end points). Every node has an
axis-aligned box; an interior node has two children (``child`` and ``child + 1``); a leaf
lists its items by *references* (a segment in every leaf whose cell it crosses, Sec. 5.1 of
Havran et al. 2005). The tree is built in one of two ways, the parameterisation each user
needs:

* **spatial** (``raymap``; ``photonmap`` over points): a node is split at the spatial median
  of its longest axis while all three of the paper's criteria hold (Sec. 5.2, :class:`TreeParams`):
  more than ``c_min`` references (C_min = 32), a cell diagonal longer than ``r_min`` times
  the scene diagonal (R_min = 0.1 %), depth below ``d_max`` (D_max = 30). *Static*
  (:meth:`SegmentTree.build_static`: refine everywhere) or *lazy* (:meth:`SegmentTree.refine`,
  Sec. 6.1: refine only the leaves a batch of queries reaches). Lazy refinement may insert
  *directional nodes* (Sec. 6.2): the node keeps its cell and sorts its references by the
  sign of ``d . r - sin(alpha)`` (r = the normal of the first query that reached it); a
  query whose normal is within ``alpha`` of r needs only the rays with ``d . r <
  sin(alpha)`` (any ray with ``d . n < 0`` is among them). Memory is bounded by an LRU
  policy (Sec. 6.4): every node carries the number of the last batch that reached it;
  before a refinement step that would exceed ``max_bytes``, the least recently used
  subtrees that the current batch did not reach are collapsed back into leaves.
* **balanced** (:meth:`SegmentTree.balanced`, points only: ``vpm``'s photons, the ray map's
  end points): every node's points are split at their median along the widest axis of
  their bounds, ``levels`` times, so that each of the ``2^levels`` leaves holds
  ``leaf_size`` to ``2 leaf_size`` points; node boxes are the points' bounds. The tree is
  perfect and breadth-first (node i has children 2i+1 and 2i+2), and leaf j holds the
  points ``[floor(j N / 2^levels), floor((j + 1) N / 2^levels))`` of :attr:`order`
  (:func:`leaf_ranges`), exactly as the medians cut them.

Query answers never depend on the shape of the tree (every query is exact), so static,
lazy, collapsed and balanced trees answer identically; only the work differs. Two device
layouts: :meth:`SegmentTree.device_arrays` (``RMNode`` records and references,
``raymap.h``; any tree) and :meth:`SegmentTree.point_nodes` (``PointNode`` boxes,
``point_tree.h``; a balanced tree over its points sorted by leaf: no child pointers, split
planes or ranges needed).

Everything is NumPy, vectorised over all (query, node) or (node, reference) pairs of one
tree level at a time. A reference carries the parameter interval of its segment inside its
leaf's cell, so a split clips against the one plane that changed (the same float64
values a slab test against the child's cell gives, see :meth:`SegmentTree._divide`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device.structs import register_struct
from ..geometry import slab_interval
from .median_split import level_starts, median_levels

# node kinds (RM_LEAF ... in raymap.h)
LEAF, SPATIAL, DIRECTIONAL = 0, 1, 2

# device node record (raymap.h RMNode): box, split or reference direction, kind/child/refs
RM_NODE = np.dtype([("lo", np.float32, 4), ("hi", np.float32, 4), ("aux", np.float32, 4),
                    ("kind", np.int32), ("child", np.int32), ("first", np.int32),
                    ("count", np.int32)], align=True)
register_struct("raymap.h", "RMNode", RM_NODE)
NODE_BYTES = RM_NODE.itemsize          # 64
REF_BYTES = 4
#: queries refining as one group use their first normal where every normal of the group
#: lies within about 2.6 degrees of it (none otherwise)
GROUP_NORMAL_COS = 0.999

# compact node of a balanced point tree (point_tree.h PointNode): its points' bounds
POINT_NODE = register_struct("point_tree.h", "PointNode",
                             np.dtype([("bmin", np.float32, 3), ("bmax", np.float32, 3)]))
EMPTY = 1e30                           # an empty balanced tree: one root box (+EMPTY, -EMPTY)

_NODE_FIELDS = {"lo": (np.float64, 3, 0.0), "hi": (np.float64, 3, 0.0),
                "kind": (np.int8, 0, LEAF), "axis": (np.int8, 0, 0), "split": (np.float64, 0, 0.0),
                "rdir": (np.float64, 3, 0.0), "child": (np.int64, 0, -1),
                "parent": (np.int64, 0, -1), "depth": (np.int64, 0, 0),
                "has_dir": (bool, 0, False), "stamp": (np.int64, 0, 0)}
_REF_FIELDS = ("ref_node", "ref_seg", "ref_t0", "ref_t1")


@dataclass
class TreeParams:
    """Subdivision criteria and options of a spatial tree (defaults: the paper's values)."""

    c_min: int = 32              # split only nodes with more references than this
    r_min: float = 1e-3          # ... whose cell diagonal exceeds r_min * scene diagonal
    d_max: int = 30              # ... and whose depth is below d_max
    alpha_deg: float = 10.0      # directional nodes: alpha extension (0 = none)
    dir_min_depth: int = 6       # directional nodes only at or below this depth
    dir_max_diag: float = 0.1    # ... in cells whose diagonal is at most this * scene diagonal
    max_bytes: int = 0           # LRU bound on the index (nodes + references); 0 = none


def clip_segments(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether segments [a, b] meet closed boxes [lo, hi] (row-wise, float64 slab test)."""
    enter, leave = clip_interval(a, b, lo, hi)
    return enter <= leave


def clip_interval(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Parameters [enter, leave] of the part of a + t (b - a), t in [0, 1], inside closed
    boxes [lo, hi] (empty when enter > leave); row-wise float64 slab test."""
    return slab_interval(a, b - a, lo, hi, 1.0)


def leaf_ranges(n: int, levels: int) -> np.ndarray:
    """Start of every leaf's range of a balanced tree of ``n`` points, plus n: leaf j holds
    sorted points [r[j], r[j + 1])."""
    return np.append(level_starts(n, levels), n)


def balanced_levels(n: int, leaf_size: int) -> int:
    """Depth of the leaves of a balanced tree of ``n`` points: the largest with at least
    ``leaf_size`` points per leaf (0: the root alone)."""
    return max(0, math.floor(math.log2(max(n / max(1, int(leaf_size)), 1.0))))


def level_boxes(lo: np.ndarray, hi: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of every node of a balanced tree whose items (sorted by leaf) have the boxes
    ``[lo, hi]`` (N, 3; points: ``lo is hi``), breadth-first: the leaves' by one
    reduction, then pairwise up to the root."""
    n = len(lo)
    if n:
        starts = leaf_ranges(n, levels)[:-1]
        lv_min = [np.minimum.reduceat(lo, starts, axis=0)]
        lv_max = [np.maximum.reduceat(hi, starts, axis=0)]
    else:
        lv_min = [np.full((1, 3), EMPTY, lo.dtype)]
        lv_max = [np.full((1, 3), -EMPTY, hi.dtype)]
    while len(lv_min[-1]) > 1:
        lv_min.append(lv_min[-1].reshape(-1, 2, 3).min(axis=1))
        lv_max.append(lv_max[-1].reshape(-1, 2, 3).max(axis=1))
    return np.concatenate(lv_min[::-1]), np.concatenate(lv_max[::-1])


def _group_starts(x: np.ndarray, cell: float, group: int) -> np.ndarray:
    """Where the groups of consecutive points ``x`` begin: a new group at every change of
    grid cell (side ``cell``) and after every ``group`` points of one run."""
    n = len(x)
    if not cell > 0 or not np.isfinite(cell):
        return np.arange(0, n, group)
    key = np.floor(x / cell).astype(np.int64)
    new_run = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
    pos = np.arange(n) - np.flatnonzero(new_run)[np.cumsum(new_run) - 1]
    return np.flatnonzero(pos % group == 0)


class SegmentTree:
    """A kd-tree of references to segments ``[a_i, b_i]`` (points when a_i = b_i).

    ``dirs`` are the segments' unit travel directions (for directional nodes; they may
    differ from b - a, e.g. a photon map indexes the hit points b only but keeps the
    direction the light came from; None: no directional nodes). This constructor makes the
    root of a spatial tree; :meth:`balanced` builds a balanced tree over points.
    """

    def __init__(self, a: np.ndarray, b: np.ndarray, dirs: np.ndarray | None, params: TreeParams,
                 scene_lo: np.ndarray | None = None, scene_hi: np.ndarray | None = None):
        self.a = np.ascontiguousarray(a, np.float64).reshape(-1, 3)
        self.b = np.ascontiguousarray(b, np.float64).reshape(-1, 3)
        self.dirs = None if dirs is None else np.ascontiguousarray(dirs, np.float64).reshape(-1, 3)
        n = len(self.a)
        if n:
            lo = np.minimum(self.a.min(0), self.b.min(0))
            hi = np.maximum(self.a.max(0), self.b.max(0))
        else:
            lo, hi = np.zeros(3), np.zeros(3)
        if scene_lo is not None:
            lo, hi = np.minimum(lo, scene_lo), np.maximum(hi, scene_hi)
        pad = 1e-6 * max(float(np.max(hi - lo)), 1e-6)
        self._setup(params, lo - pad, hi + pad, 1024)
        # references of the leaves: (node, segment) pairs, with the segment's parameter
        # interval inside the node's cell
        self.ref_node = np.zeros(n, np.int64)
        self.ref_seg = np.arange(n, dtype=np.int64)
        self.ref_t0, self.ref_t1 = clip_interval(self.a, self.b, self.lo[0], self.hi[0])
        self.peak_bytes = self.nbytes

    def _setup(self, params: TreeParams, lo: np.ndarray, hi: np.ndarray, cap: int) -> None:
        """The node arrays (``cap`` nodes) with the root's box, and the bookkeeping."""
        self.p = params
        self.diag = float(np.linalg.norm(hi - lo))
        self.cos_alpha = math.cos(math.radians(params.alpha_deg))
        self.sin_alpha = math.sin(math.radians(params.alpha_deg))
        for name, (dtype, width, fill) in _NODE_FIELDS.items():
            setattr(self, name, np.full((cap, width) if width else cap, fill, dtype))
        self.n = 1
        self.lo[0], self.hi[0] = lo, hi
        self.levels: int | None = None        # a balanced tree's leaf depth
        self._frozen: list[tuple[np.ndarray, ...]] = []   # see _freeze_settled
        self.now = 0                          # batch counter (LRU clock)
        self.collapses = 0                    # subtrees collapsed so far
        self._flat = None
        self._rows = None
        self.version = 0

    # ---- the balanced build over points ----
    @classmethod
    def balanced(cls, points: np.ndarray, leaf_size: int = 8) -> "SegmentTree":
        """A balanced tree over ``points`` (N, 3), kept in their float type (the photon
        maps' float32 positions: no float64 copy). ``levels`` is the largest with at least
        ``leaf_size`` points per leaf; no points make one empty root (box +EMPTY..-EMPTY,
        farther than any query). The levels are :func:`~.median_split.median_levels`, as
        the line tree's. Working set while sorting: the coordinate rows twice, the float64
        sort key and the permutation (about 40 bytes per point); kept: the node arrays and
        the references."""
        pts = np.asarray(points)
        if pts.dtype not in (np.float32, np.float64):
            pts = pts.astype(np.float64)
        pts = pts.reshape(-1, 3)
        n, leaf_size = len(pts), max(1, int(leaf_size))
        levels = balanced_levels(n, leaf_size)
        rows, order, axes = median_levels(pts.T, levels,
                                          np.int32 if n < 2 ** 31 else np.int64)
        sorted_pts = np.ascontiguousarray(rows.T)
        box_lo, box_hi = level_boxes(sorted_pts, sorted_pts, levels)
        del rows, sorted_pts
        tree = cls.__new__(cls)
        tree.a = tree.b = pts
        tree.dirs = None
        # the criteria it meets: at most 2 leaf_size points per leaf, depth levels
        params = TreeParams(c_min=2 * leaf_size, r_min=0.0, d_max=levels, alpha_deg=0.0)
        tree._setup(params, box_lo[0].astype(np.float64), box_hi[0].astype(np.float64),
                    len(box_lo))
        tree._link_perfect(levels, box_lo, box_hi, axes)
        tree.levels, tree.leaf_size = levels, leaf_size
        leaves = np.arange((1 << levels) - 1, len(box_lo), dtype=np.int64)
        tree.ref_node = np.repeat(leaves, np.diff(leaf_ranges(n, levels)))
        tree.ref_seg = order
        # every point lies inside its leaf: its interval is [0, 1] (read-only broadcasts)
        tree.ref_t0 = np.broadcast_to(np.float64(0.0), (n,))
        tree.ref_t1 = np.broadcast_to(np.float64(1.0), (n,))
        tree.peak_bytes = tree.nbytes
        return tree

    def _link_perfect(self, levels: int, box_lo: np.ndarray, box_hi: np.ndarray,
                      axes: list[np.ndarray]) -> None:
        """Fill the node arrays of a perfect breadth-first tree: boxes, kinds, children,
        parents, depths; the split axis of every interior node and, as its split
        position, the upper bound of its first child along that axis."""
        nn = len(box_lo)
        idx = np.arange(nn, dtype=np.int64)
        first_leaf = (1 << levels) - 1
        self.n = nn
        self.lo[:nn], self.hi[:nn] = box_lo, box_hi
        interior = idx < first_leaf
        self.kind[:nn] = np.where(interior, SPATIAL, LEAF)
        self.child[:nn] = np.where(interior, 2 * idx + 1, -1)
        self.parent[:nn] = np.where(idx > 0, (idx - 1) // 2, -1)
        self.depth[:nn] = np.floor(np.log2(idx + 1.0)).astype(np.int64)
        if first_leaf:
            ax = np.concatenate(axes).astype(np.int64)
            self.axis[:first_leaf] = ax
            self.split[:first_leaf] = self.hi[2 * idx[:first_leaf] + 1, ax]

    @property
    def order(self) -> np.ndarray:
        """A balanced tree's points in leaf order (indices into the points)."""
        if self.levels is None:
            raise ValueError("order: only a balanced tree keeps its points in leaf order")
        return self.ref_seg

    def point_nodes(self) -> np.ndarray:
        """A balanced tree's boxes as :data:`POINT_NODE` records, breadth-first (the
        ``point_tree.h`` layout over the points sorted by :attr:`order`)."""
        if self.levels is None:
            raise ValueError("point_nodes: only a balanced tree has the compact layout")
        nodes = np.zeros(self.n, POINT_NODE)
        nodes["bmin"] = self.lo[:self.n]
        nodes["bmax"] = self.hi[:self.n]
        return nodes

    # ---- sizes ----
    @property
    def num_refs(self) -> int:
        return len(self.ref_seg) + sum(len(f[1]) for f in self._frozen)

    @property
    def nbytes(self) -> int:
        """The index's size on the device: nodes and references (not the segments)."""
        return self.n * NODE_BYTES + self.num_refs * REF_BYTES

    # ---- the references ----
    def _refs(self) -> list[np.ndarray]:
        return [getattr(self, f) for f in _REF_FIELDS]

    def _set_refs(self, arrays) -> None:
        for name, arr in zip(_REF_FIELDS, arrays):
            setattr(self, name, arr)

    def _freeze_settled(self, counts: np.ndarray, frontier: np.ndarray | None = None) -> None:
        """Set aside the references of leaves that fail the subdivision criteria (no split
        can ever move them: leaves only lose references to new children) or, during a
        lazy refinement, that lie in no subtree of the ``frontier`` nodes (the walk only
        goes down, so it never reaches them again). Each refinement level then touches
        only the references that may still move. ``counts``: references per node."""
        n = self.n
        leaves = np.nonzero(self.kind[:n] == LEAF)[0]
        settled = np.ones(n, bool)
        settled[leaves] = ~self._splittable(leaves, counts)
        if frontier is not None:
            reach = np.zeros(n, bool)
            cur = self._distinct(frontier)
            while len(cur):                       # mark the frontier's subtrees
                reach[cur] = True
                cur = cur[self.kind[cur] != LEAF]
                cur = np.concatenate([self.child[cur], self.child[cur] + 1])
            settled |= ~reach
        move = settled[self.ref_node]
        if move.any():
            refs = self._refs()
            go, stay = np.flatnonzero(move), np.flatnonzero(~move)
            self._frozen.append(tuple(r[go] for r in refs))
            self._set_refs([r[stay] for r in refs])

    def _thaw(self) -> None:
        """Bring the set-aside references back (all of them in the reference arrays)."""
        if self._frozen:
            self._set_refs([np.concatenate([f[i] for f in self._frozen] + [r])
                            for i, r in enumerate(self._refs())])
            self._frozen = []

    def _grow(self, need: int) -> None:
        cap = len(self.kind)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name, (dtype, width, fill) in _NODE_FIELDS.items():
            arr = np.full((new, width) if width else new, fill, dtype)
            arr[:cap] = getattr(self, name)
            setattr(self, name, arr)

    # ---- criteria ----
    def _ref_counts(self) -> np.ndarray:
        return np.bincount(self.ref_node, minlength=self.n)

    def _splittable(self, nodes: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """The paper's three subdivision criteria (Sec. 5.2) for leaves ``nodes``."""
        p = self.p
        diag = np.linalg.norm(self.hi[nodes] - self.lo[nodes], axis=1)
        return ((self.kind[nodes] == LEAF) & (counts[nodes] > p.c_min)
                & (diag > p.r_min * self.diag) & (self.depth[nodes] < p.d_max))

    def _spatial_only(self, what: str) -> None:
        if self.levels is not None:
            raise ValueError(f"{what}: a balanced tree is complete as built")

    # ---- splitting ----
    def _split(self, leaves: np.ndarray, normals: np.ndarray | None) -> None:
        """Split ``leaves`` (spatial median of the longest axis, or directional where
        ``normals`` has a finite row and the directional criteria hold)."""
        if len(leaves) == 0:
            return
        self._flat = None
        self.version += 1
        directional = self._directional(leaves, normals)
        kids, axis, mid = self._add_children(leaves, directional, normals)
        self._distribute(leaves, kids, axis, mid, directional)
        self.peak_bytes = max(self.peak_bytes, self.nbytes)

    def _directional(self, leaves: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """Which of ``leaves`` are split by direction (Sec. 6.2: a query's normal to refer
        to, deep and small enough, no directional node above)."""
        p = self.p
        if normals is None or p.alpha_deg <= 0 or self.dirs is None:
            return np.zeros(len(leaves), bool)
        diag = np.linalg.norm(self.hi[leaves] - self.lo[leaves], axis=1)
        return (np.isfinite(normals[:, 0]) & ~self.has_dir[leaves]
                & (self.depth[leaves] >= p.dir_min_depth) & (diag <= p.dir_max_diag * self.diag))

    def _add_children(self, leaves, directional, normals):
        """Append two children per leaf (cells halved at the longest axis' midpoint, or the
        parent's cell for a directional split) and turn the leaves into interior nodes.
        Returns (first child, axis, split position) per leaf."""
        m = len(leaves)
        first = self.n
        self._grow(first + 2 * m)
        kids = first + 2 * np.arange(m)
        ext = self.hi[leaves] - self.lo[leaves]
        axis = np.argmax(ext, axis=1)
        mid = 0.5 * (self.lo[leaves, axis] + self.hi[leaves, axis])
        self.kind[leaves] = np.where(directional, DIRECTIONAL, SPATIAL)
        self.axis[leaves] = axis
        self.split[leaves] = mid
        if normals is not None:
            self.rdir[leaves] = np.where(directional[:, None], np.nan_to_num(normals), 0.0)
        self.child[leaves] = kids
        sp = ~directional
        for side in (0, 1):
            k = kids + side
            self.lo[k] = self.lo[leaves]
            self.hi[k] = self.hi[leaves]
            (self.hi if side == 0 else self.lo)[k[sp], axis[sp]] = mid[sp]
            self.kind[k] = LEAF
            self.child[k] = -1
            self.parent[k] = leaves
            self.depth[k] = self.depth[leaves] + 1
            self.has_dir[k] = self.has_dir[leaves] | directional
            self.stamp[k] = self.now
        self.n = first + 2 * m
        return kids, axis, mid

    def _distribute(self, leaves, kids, axis, mid, directional) -> None:
        """Move the references of the split ``leaves`` to the children they reach; every
        child keeps its parent's order of references."""
        slot = np.full(self.n, -1, np.int64)
        slot[leaves] = np.arange(len(leaves))
        j = slot[self.ref_node]
        moving = j >= 0
        refs = self._refs()
        parts = []
        if not moving.all():
            stay, go = np.flatnonzero(~moving), np.flatnonzero(moving)
            parts.append([r[stay] for r in refs])
            refs, j = [r[go] for r in refs], j[go]
        _, rs, t0, t1 = refs
        dirn = directional[j]
        if dirn.any():
            dn, sp = np.flatnonzero(dirn), np.flatnonzero(~dirn)
            # back child: d . r < sin(alpha) holds every ray a covered query can use
            back = np.einsum("ij,ij->i", self.dirs[rs[dn]],
                             self.rdir[leaves[j[dn]]]) < self.sin_alpha
            parts.append([kids[j[dn]] + np.where(back, 0, 1), rs[dn], t0[dn], t1[dn]])
            rs, t0, t1, j = rs[sp], t0[sp], t1[sp], j[sp]
        if len(rs):
            for side, hit, hit_t0, hit_t1 in self._divide(rs, j, t0, t1, leaves, axis, mid):
                parts.append([kids[j[hit]] + side, rs[hit], hit_t0, hit_t1])
        self._set_refs([np.concatenate([p[i] for p in parts]) for i in range(len(_REF_FIELDS))])

    def _segment_rows(self):
        """Flat rows of the segments' starts, directions b - a, 1 / (b - a) and
        ``b - a == 0`` (index 3 * segment + axis), made once for the splits."""
        if self._rows is None:
            d = self.b - self.a
            with np.errstate(divide="ignore"):
                inv = 1.0 / d
            self._rows = (self.a.ravel(), d.ravel(), inv.ravel(), (d == 0.0).ravel())
        return self._rows

    def _divide(self, rs, j, t0, t1, leaves, axis, mid):
        """For references ``rs`` of split leaf ``leaves[j]`` whose segments lie in the
        leaf's cell on ``[t0, t1]``: which side(s) of the split plane they reach (the
        points at t0 and t1 along the axis against the plane) and their intervals in each
        child's cell. Yields (side, indices of the hits, their t0, t1) for both sides.

        A child's cell differs from its parent's on the split axis only, and the slab
        test's per-axis entry (exit) parameter can only grow (shrink) with the cell, so the
        child's interval is ``[max(t0, near), min(t1, far)]`` with (near, far) the slab
        parameters of the child's extent on that axis: bit for bit the float64 slab test
        against the child's whole cell (:func:`clip_interval`)."""
        a_row, d_row, inv_row, par_row = self._segment_rows()
        at = 3 * rs + axis[j]
        a0, d0, inv = a_row[at], d_row[at], inv_row[at]
        m = mid[j]
        c0 = a0 + t0 * d0
        c1 = a0 + t1 * d0
        with np.errstate(invalid="ignore"):
            t_lo = (self.lo[leaves, axis][j] - a0) * inv
            t_m = (m - a0) * inv
            t_hi = (self.hi[leaves, axis][j] - a0) * inv
        hits = (np.minimum(c0, c1) <= m, np.maximum(c0, c1) >= m)
        par = par_row[at]
        for side, (u, v) in enumerate(((t_lo, t_m), (t_m, t_hi))):
            hit = np.flatnonzero(hits[side])
            u, v = u[hit], v[hit]
            near, far = np.minimum(u, v), np.maximum(u, v)
            p = par[hit]
            if p.any():        # parallel to the axis: inside the child's slab for every t
                near[p], far[p] = -np.inf, np.inf
            yield side, hit, np.maximum(t0[hit], near), np.minimum(t1[hit], far)

    def build_static(self) -> None:
        """Refine every leaf that meets the subdivision criteria (Sec. 5.2), level by level."""
        self._spatial_only("build_static")
        try:
            while True:
                counts = self._ref_counts()
                self._freeze_settled(counts)
                leaves = np.nonzero(self.kind[:self.n] == LEAF)[0]
                leaves = leaves[self._splittable(leaves, counts)]
                if len(leaves) == 0:
                    return
                self._split(leaves, None)
        finally:
            self._thaw()

    # ---- lazy construction driven by a batch of queries ----
    def refine(self, x: np.ndarray, normals: np.ndarray | None, radius: np.ndarray | float,
               group: int = 1) -> None:
        """Lazy construction (Sec. 6.1) for one batch of queries: walk the boxes
        ``x +- radius`` down the tree, split every reached leaf that meets the criteria,
        continue into the new children; stamp every reached node with this batch's
        number (the LRU clock, Sec. 6.4). ``normals``: the queries' normals (they place
        directional nodes and let covered queries skip the infeasible child), or None.

        ``group`` > 1: up to ``group`` consecutive queries in one cell of a grid of twice
        their median radius walk as one, their boxes' union with their common normal (none
        where their normals differ; :func:`_group_starts`). The queries of a batch come in
        pixel order, so a group's boxes overlap and the walk visits up to ``group`` times
        fewer (query, node) pairs for a slightly larger refined region; what a query finds
        does not depend on the tree, only the work it takes does."""
        self._spatial_only("refine")
        self.now += 1
        x = np.asarray(x, np.float64).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radius, np.float64), (len(x),))
        qlo, qhi = x - r[:, None], x + r[:, None]
        if normals is not None:
            normals = np.asarray(normals, np.float64).reshape(-1, 3)
        group = max(1, int(group))
        if group > 1 and len(x) > 1:
            starts = _group_starts(x, 2.0 * float(np.median(r)), group)
            qlo = np.minimum.reduceat(qlo, starts, axis=0)
            qhi = np.maximum.reduceat(qhi, starts, axis=0)
            if normals is not None:
                first = np.repeat(normals[starts], np.diff(np.append(starts, len(x))), axis=0)
                near = np.einsum("ij,ij->i", normals, first) >= GROUP_NORMAL_COS
                normals = np.where(np.logical_and.reduceat(near, starts)[:, None],
                                   normals[starts], np.nan)
        q = np.arange(len(qlo))
        node = np.zeros(len(qlo), np.int64)
        inside = np.flatnonzero(np.all((qhi >= self.lo[0]) & (qlo <= self.hi[0]), axis=1))
        q, node = q[inside], node[inside]
        try:
            self._refine_pairs(q, node, np.ascontiguousarray(qlo).ravel(),
                               np.ascontiguousarray(qhi).ravel(), normals)
        finally:
            self._thaw()
        self.peak_bytes = max(self.peak_bytes, self.nbytes)

    def _refine_pairs(self, q, node, qlo, qhi, normals) -> None:
        """The level-by-level walk of :meth:`refine` over (query, node) pairs."""
        while len(q):
            self.stamp[node] = self.now
            kind = self.kind[node]
            leaf = kind == LEAF
            if leaf.any():             # (levels that only pass through need no counts)
                counts = self._ref_counts()
                self._freeze_settled(counts, node)
                cand = self._distinct(node[leaf])
                cand = cand[self._splittable(cand, counts)]
                if len(cand):
                    before = self.collapses
                    cand = self._within_budget(cand, counts)
                    if self.collapses != before:      # nodes were renumbered
                        node = self._remap[node]
                if len(cand):
                    at = np.flatnonzero(leaf)
                    self._split(cand, self._first_normals(cand, q[at], node[at], normals))
                    kind = self.kind[node]
                    leaf = kind == LEAF
            # pairs at leaves are done; pairs at interior nodes go to the children they reach
            inner = np.flatnonzero(~leaf)
            if not len(inner):
                break
            q, node = self._descend(q[inner], node[inner], kind[inner], qlo, qhi, normals)

    def _distinct(self, nodes: np.ndarray) -> np.ndarray:
        """The distinct node numbers of ``nodes``, ascending (np.unique by marks)."""
        mark = np.zeros(self.n, bool)
        mark[nodes] = True
        return np.flatnonzero(mark)

    def _first_normals(self, cand, lq, ln, normals):
        """The normal of the first (lowest-numbered) query reaching each leaf of ``cand``
        (``lq``, ``ln``: the (query, leaf) pairs), or None without normals."""
        if normals is None:
            return None
        first = np.full(self.n, np.iinfo(np.int64).max)
        np.minimum.at(first, ln, lq)
        return normals[first[cand]]

    def _descend(self, q, node, kind, qlo, qhi, normals):
        """(query, interior node) pairs -> the (query, child) pairs whose boxes meet;
        covered queries take only the back child of a directional node. ``qlo``, ``qhi``:
        the queries' boxes, flat rows (index 3 * query + axis)."""
        child = self.child[node]
        at = 3 * q + self.axis[node]
        sp = self.split[node]
        other = kind != SPATIAL
        go_l = other | (qlo[at] <= sp)
        go_r = other | (qhi[at] >= sp)
        if normals is not None:
            dn = np.flatnonzero(kind == DIRECTIONAL)
            if len(dn):
                cov = np.einsum("ij,ij->i", normals[q[dn]], self.rdir[node[dn]]) >= self.cos_alpha
                go_r[dn[cov]] = False                    # covered: the back child only
        il, ir = np.flatnonzero(go_l), np.flatnonzero(go_r)
        return np.concatenate([q[il], q[ir]]), np.concatenate([child[il], child[ir] + 1])

    # ---- LRU memory bound ----
    def _within_budget(self, cand: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """The leaves of ``cand`` that may be split now: before splitting, collapse least
        recently used subtrees until the estimated size fits ``max_bytes`` (Sec. 6.4);
        when nothing more can be collapsed, split only what fits."""
        budget = self.p.max_bytes
        if budget <= 0:
            return cand
        # a split adds two nodes and, at most, duplicates the leaf's references
        cost = 2 * NODE_BYTES + REF_BYTES * counts[cand]
        need = self.nbytes + int(cost.sum()) - budget
        if need > 0:
            before = self.collapses
            self.collapse(need)
            if self.collapses != before:
                cand = self._remap[cand]
            need = self.nbytes + int(cost.sum()) - budget
        if need > 0:
            fits = np.cumsum(cost) <= budget - self.nbytes
            cand = cand[fits]
        return cand

    def collapse(self, need_bytes: int) -> int:
        """Collapse the least recently used subtrees not reached by the current batch
        (oldest stamp first) until ``need_bytes`` are freed or none is left; returns the
        bytes freed. A collapsed node becomes a leaf holding the union of its leaves'
        references: exactly the segments crossing its cell, as if never split."""
        self._spatial_only("collapse")
        self._thaw()
        n = self.n
        if n <= 1:
            return 0
        cand, anc = self._collapse_candidates()
        if len(cand) == 0:
            return 0
        nseg = len(self.a) + 1
        under = anc[self.ref_node]
        sel = under >= 0
        # bytes freed by collapsing each candidate: its nodes, its duplicate references
        key = under[sel] * nseg + self.ref_seg[sel]
        uniq = np.unique(key)
        refs_total = np.bincount(under[sel], minlength=n)[cand]
        refs_unique = np.bincount(uniq // nseg, minlength=n)[cand]
        nodes_under = np.bincount(anc[anc >= 0], minlength=n)[cand] - 1
        freed = nodes_under * NODE_BYTES + (refs_total - refs_unique) * REF_BYTES
        order = np.lexsort((-freed, self.stamp[cand]))      # least recently used first
        cum = np.cumsum(freed[order])
        chosen = cand[order[:int(np.searchsorted(cum, need_bytes)) + 1]]
        is_chosen = np.zeros(n, bool)
        is_chosen[chosen] = True
        # merge the chosen subtrees' references into their roots, clipped to their cells
        gone = sel & is_chosen[np.where(under >= 0, under, 0)]
        merged = np.unique(under[gone] * nseg + self.ref_seg[gone])
        m_node, m_seg = merged // nseg, merged % nseg
        m_t0, m_t1 = clip_interval(self.a[m_seg], self.b[m_seg], self.lo[m_node], self.hi[m_node])
        refs = [np.concatenate([r[~gone], new])
                for r, new in zip(self._refs(), (m_node, m_seg, m_t0, m_t1))]
        before = self.nbytes
        # drop the nodes strictly below chosen roots and renumber the rest
        drop = (anc >= 0) & is_chosen[np.where(anc >= 0, anc, 0)] & ~is_chosen
        new_index = self._drop_nodes(chosen, ~drop)
        refs[0] = new_index[refs[0]]
        self._set_refs(refs)
        self.collapses += len(chosen)
        self._remap = new_index                 # old node index -> new (for callers)
        self._flat = None
        self.version += 1
        return before - self.nbytes

    def _collapse_candidates(self) -> tuple[np.ndarray, np.ndarray]:
        """Interior nodes not reached by this batch whose parent was (the roots of the
        cold subtrees), and per node the candidate above it (-1: none)."""
        n = self.n
        interior = self.kind[:n] != LEAF
        old = self.stamp[:n] < self.now
        par = self.parent[:n]
        parent_new = np.ones(n, bool)
        parent_new[1:] = ~old[par[1:]]
        cand = np.nonzero(interior & old & parent_new)[0]
        cand = cand[cand > 0]
        anc = np.full(n, -1, np.int64)
        anc[cand] = cand
        for d in range(1, int(self.depth[:n].max()) + 1):
            at = np.nonzero((self.depth[:n] == d) & (anc == -1))[0]
            if len(at):
                anc[at] = anc[par[at]]
        return cand, anc

    def _drop_nodes(self, roots: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Make ``roots`` leaves, keep the nodes ``keep`` (renumbered in order); returns
        the map old index -> new."""
        n = self.n
        new_index = np.cumsum(keep) - 1
        self.kind[roots] = LEAF
        self.child[roots] = -1
        self.rdir[roots] = 0.0
        for name in _NODE_FIELDS:
            arr = getattr(self, name)
            kept = arr[:n][keep]
            arr[:len(kept)] = kept
        m = int(keep.sum())
        for name in ("child", "parent"):
            v = getattr(self, name)[:m]
            v[:] = np.where(v >= 0, new_index[np.maximum(v, 0)], -1)
        self.n = m
        return new_index

    # ---- device layout ----
    def device_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(nodes RM_NODE[n], refs int32[m])``: references sorted by leaf; a leaf's
        ``first``/``count`` index them, an interior node's ``child`` is its first child
        (the second is child + 1); ``aux`` holds the split position (x) and axis (y) of
        a spatial node, the reference direction and sin(alpha) of a directional one."""
        if self._flat is not None:
            return self._flat
        n = self.n
        order = np.argsort(self.ref_node, kind="stable")
        refs = self.ref_seg[order].astype(np.int32)
        sorted_nodes = self.ref_node[order]
        first = np.searchsorted(sorted_nodes, np.arange(n))
        count = np.bincount(self.ref_node, minlength=n)
        nodes = np.zeros(n, RM_NODE)
        nodes["lo"][:, :3] = self.lo[:n]
        nodes["hi"][:, :3] = self.hi[:n]
        kind = self.kind[:n]
        nodes["kind"] = kind
        nodes["child"] = self.child[:n]
        nodes["first"] = np.where(kind == LEAF, first, 0)
        nodes["count"] = np.where(kind == LEAF, count, 0)
        aux = np.zeros((n, 4), np.float32)
        sp = kind == SPATIAL
        aux[sp, 0] = self.split[:n][sp]
        aux[sp, 1] = self.axis[:n][sp]
        dn = kind == DIRECTIONAL
        aux[dn, :3] = self.rdir[:n][dn]
        aux[dn, 3] = self.sin_alpha
        nodes["aux"] = aux
        # float32 boxes, widened by one ulp-scale margin so that no float64 reference
        # falls outside its float32 cell
        eps = 1e-6 * max(self.diag, 1e-6)
        nodes["lo"][:, :3] -= eps
        nodes["hi"][:, :3] += eps
        self._flat = (nodes, refs)
        return self._flat

    def check(self) -> None:
        """Invariants (tests). Spatial trees: every leaf lists exactly the segments
        crossing its cell (directional leaves: those on their side). Balanced trees: every
        point is listed once, in a leaf whose box holds it, and parents' boxes hold their
        children's."""
        if self.levels is not None:
            self._check_balanced()
            return
        n = self.n
        leaves = np.nonzero(self.kind[:n] == LEAF)[0]
        for leaf in leaves:
            mine = np.sort(self.ref_seg[self.ref_node == leaf])
            lo = np.repeat(self.lo[leaf][None], len(self.a), 0)
            hi = np.repeat(self.hi[leaf][None], len(self.a), 0)
            expect = clip_segments(self.a, self.b, lo, hi)
            node = leaf
            while self.parent[node] >= 0:
                par = self.parent[node]
                if self.kind[par] == DIRECTIONAL:
                    back = self.dirs @ self.rdir[par] < self.sin_alpha
                    expect &= back if node == self.child[par] else ~back
                node = par
            assert np.array_equal(mine, np.nonzero(expect)[0]), f"leaf {leaf} references differ"

    def _check_balanced(self) -> None:
        n, pts = self.n, np.asarray(self.a, np.float64)
        assert np.array_equal(np.sort(self.ref_seg), np.arange(len(pts))), "not a permutation"
        p = pts[self.ref_seg]
        assert np.all(p >= self.lo[self.ref_node]) and np.all(p <= self.hi[self.ref_node])
        inner = np.nonzero(self.kind[:n] != LEAF)[0]
        for c in (self.child[inner], self.child[inner] + 1):
            assert np.all(self.lo[inner] <= self.lo[c]) and np.all(self.hi[inner] >= self.hi[c])
