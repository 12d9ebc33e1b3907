"""The ray map's kd-tree over ray segments (Havran et al. 2005, Sec. 5-6), in flat arrays.

Every leaf holds *references* to the segments that cross its cell (a segment is listed
in every leaf it passes through, Sec. 5.1). Nodes are split at the spatial median of the
longest axis (Sec. 5.2) while all three of the paper's criteria hold: more than
``c_min`` references (C_min = 32), a cell diagonal longer than ``r_min`` times the scene
diagonal (R_min = 0.1 %), depth below ``d_max`` (D_max = 30).

Construction is *static* (:meth:`SegmentTree.build_static`: refine everywhere) or *lazy*
(:meth:`SegmentTree.refine`, Sec. 6.1: refine only the leaves a batch of queries reaches;
leaves no query touches stay coarse). Lazy refinement may insert *directional nodes*
(Sec. 6.2): the node keeps its cell and sorts its references by the sign of
``d . r - sin(alpha)`` (r = the normal of the first query that reached it); a query whose
normal is within ``alpha`` of r needs only the rays with ``d . r < sin(alpha)`` (any ray
with ``d . n < 0`` is among them), the others are culled. Memory is bounded by an LRU
policy (Sec. 6.4): every node carries the number of the last batch that reached it; before
a refinement step that would exceed ``max_bytes``, the least recently used subtrees that
the current batch did not reach are collapsed back into leaves (their references merged).

Query answers never depend on the shape of the tree (every query is exact), so static,
lazy and collapsed trees answer identically; only the work differs. Everything is NumPy,
vectorised over all (query, node) or (node, reference) pairs of one tree level at a time;
the arrays are uploaded as they are (:meth:`SegmentTree.device_arrays`, ``raymap.h``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device.structs import register_struct
from ..geometry import slab_interval

# node kinds (RM_LEAF ... in raymap.h)
LEAF, SPATIAL, DIRECTIONAL = 0, 1, 2

# device node record (raymap.h RMNode): box, split or reference direction, kind/child/refs
RM_NODE = np.dtype([("lo", np.float32, 4), ("hi", np.float32, 4), ("aux", np.float32, 4),
                    ("kind", np.int32), ("child", np.int32), ("first", np.int32),
                    ("count", np.int32)], align=True)
register_struct("raymap.h", "RMNode", RM_NODE)
NODE_BYTES = RM_NODE.itemsize          # 64
REF_BYTES = 4


@dataclass
class TreeParams:
    """Subdivision criteria and options (defaults: the paper's values)."""

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


class SegmentTree:
    """A kd-tree of references to segments ``[a_i, b_i]`` (points when a_i = b_i).

    ``dirs`` are the segments' unit travel directions (for directional nodes; they may
    differ from b - a, e.g. a photon map indexes the hit points b only but keeps the
    direction the light came from).
    """

    def __init__(self, a: np.ndarray, b: np.ndarray, dirs: np.ndarray, params: TreeParams,
                 scene_lo: np.ndarray | None = None, scene_hi: np.ndarray | None = None):
        self.a = np.ascontiguousarray(a, np.float64).reshape(-1, 3)
        self.b = np.ascontiguousarray(b, np.float64).reshape(-1, 3)
        self.dirs = np.ascontiguousarray(dirs, np.float64).reshape(-1, 3)
        self.p = params
        n = len(self.a)
        if n:
            lo = np.minimum(self.a.min(0), self.b.min(0))
            hi = np.maximum(self.a.max(0), self.b.max(0))
        else:
            lo, hi = np.zeros(3), np.zeros(3)
        if scene_lo is not None:
            lo, hi = np.minimum(lo, scene_lo), np.maximum(hi, scene_hi)
        pad = 1e-6 * max(float(np.max(hi - lo)), 1e-6)
        lo, hi = lo - pad, hi + pad
        self.diag = float(np.linalg.norm(hi - lo))
        self.cos_alpha = math.cos(math.radians(params.alpha_deg))
        self.sin_alpha = math.sin(math.radians(params.alpha_deg))
        cap = 1024
        self.lo = np.zeros((cap, 3))
        self.hi = np.zeros((cap, 3))
        self.kind = np.zeros(cap, np.int8)
        self.axis = np.zeros(cap, np.int8)
        self.split = np.zeros(cap)
        self.rdir = np.zeros((cap, 3))
        self.child = np.full(cap, -1, np.int64)
        self.parent = np.full(cap, -1, np.int64)
        self.depth = np.zeros(cap, np.int64)
        self.has_dir = np.zeros(cap, bool)
        self.stamp = np.zeros(cap, np.int64)
        self.n = 1
        self.lo[0], self.hi[0] = lo, hi
        # references of the leaves: (node, segment) pairs
        self.ref_node = np.zeros(n, np.int64)
        self.ref_seg = np.arange(n, dtype=np.int64)
        self._frozen: list[tuple[np.ndarray, np.ndarray]] = []   # see _freeze_settled
        self.now = 0                          # batch counter (LRU clock)
        self.collapses = 0                    # subtrees collapsed so far
        self.peak_bytes = self.nbytes
        self._flat = None
        self.version = 0

    # ---- sizes ----
    @property
    def num_refs(self) -> int:
        return len(self.ref_seg) + sum(len(f[1]) for f in self._frozen)

    # ---- working set: references of leaves that can still be split ----
    def _freeze_settled(self, frontier: np.ndarray | None = None) -> None:
        """Set aside the references of leaves that fail the subdivision criteria (no split
        can ever move them: leaves only lose references to new children) or, during a
        lazy refinement, that lie in no subtree of the ``frontier`` nodes (the walk only
        goes down, so it never reaches them again). Each refinement level then touches
        only the references that may still move."""
        n = self.n
        leaves = np.nonzero(self.kind[:n] == LEAF)[0]
        settled = np.ones(n, bool)
        settled[leaves] = ~self._splittable(leaves, self._ref_counts())
        if frontier is not None:
            reach = np.zeros(n, bool)
            cur = np.unique(frontier)
            while len(cur):                       # mark the frontier's subtrees
                reach[cur] = True
                cur = cur[self.kind[cur] != LEAF]
                cur = np.concatenate([self.child[cur], self.child[cur] + 1])
            settled |= ~reach
        move = settled[self.ref_node]
        if move.any():
            self._frozen.append((self.ref_node[move], self.ref_seg[move]))
            self.ref_node, self.ref_seg = self.ref_node[~move], self.ref_seg[~move]

    def _thaw(self) -> None:
        """Bring the set-aside references back (all of them in ref_node / ref_seg)."""
        if self._frozen:
            self.ref_node = np.concatenate([f[0] for f in self._frozen] + [self.ref_node])
            self.ref_seg = np.concatenate([f[1] for f in self._frozen] + [self.ref_seg])
            self._frozen = []

    @property
    def nbytes(self) -> int:
        """The index's size on the device: nodes and references (not the segments)."""
        return self.n * NODE_BYTES + self.num_refs * REF_BYTES

    def _grow(self, need: int) -> None:
        cap = len(self.kind)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("lo", "hi", "kind", "axis", "split", "rdir", "child", "parent", "depth",
                     "has_dir", "stamp"):
            old = getattr(self, name)
            arr = np.zeros((new,) + old.shape[1:], old.dtype)
            if name in ("child", "parent"):
                arr[:] = -1
            arr[:cap] = old
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

    # ---- splitting ----
    def _split(self, leaves: np.ndarray, normals: np.ndarray | None) -> None:
        """Split ``leaves`` (spatial median of the longest axis, or directional where
        ``normals`` has a finite row and the directional criteria hold)."""
        if len(leaves) == 0:
            return
        self._flat = None
        self.version += 1
        p = self.p
        m = len(leaves)
        first = self.n
        self._grow(first + 2 * m)
        kids = first + 2 * np.arange(m)
        ext = self.hi[leaves] - self.lo[leaves]
        diag = np.linalg.norm(ext, axis=1)
        directional = np.zeros(m, bool)
        if normals is not None and p.alpha_deg > 0:
            directional = (np.isfinite(normals[:, 0]) & ~self.has_dir[leaves]
                           & (self.depth[leaves] >= p.dir_min_depth)
                           & (diag <= p.dir_max_diag * self.diag))
        axis = np.argmax(ext, axis=1)
        mid = 0.5 * (self.lo[leaves, axis] + self.hi[leaves, axis])
        self.kind[leaves] = np.where(directional, DIRECTIONAL, SPATIAL)
        self.axis[leaves] = axis
        self.split[leaves] = mid
        if normals is not None:
            self.rdir[leaves] = np.where(directional[:, None], np.nan_to_num(normals), 0.0)
        self.child[leaves] = kids
        for side in (0, 1):
            k = kids + side
            self.lo[k] = self.lo[leaves]
            self.hi[k] = self.hi[leaves]
            sp = ~directional
            if side == 0:
                self.hi[k[sp], axis[sp]] = mid[sp]
            else:
                self.lo[k[sp], axis[sp]] = mid[sp]
            self.kind[k] = LEAF
            self.child[k] = -1
            self.parent[k] = leaves
            self.depth[k] = self.depth[leaves] + 1
            self.has_dir[k] = self.has_dir[leaves] | directional
            self.stamp[k] = self.now
        self.n = first + 2 * m
        # distribute the references of the split leaves to the children they cross
        slot = np.full(self.n, -1, np.int64)
        slot[leaves] = np.arange(m)
        moving = slot[self.ref_node] >= 0
        keep_node, keep_seg = self.ref_node[~moving], self.ref_seg[~moving]
        rn, rs = self.ref_node[moving], self.ref_seg[moving]
        j = slot[rn]
        out_n, out_s = [keep_node], [keep_seg]
        dirn = directional[j]
        if dirn.any():
            # back child: d . r < sin(alpha) holds every ray a covered query can use
            back = np.einsum("ij,ij->i", self.dirs[rs[dirn]], self.rdir[rn[dirn]]) < self.sin_alpha
            out_n.append(kids[j[dirn]] + np.where(back, 0, 1))
            out_s.append(rs[dirn])
        sp = ~dirn
        if sp.any():
            # the piece of each segment inside the parent's cell, then which side(s) of the
            # split plane it reaches: the same as a slab test against each child's cell
            rs_s, j_s = rs[sp], j[sp]
            a, b = self.a[rs_s], self.b[rs_s]
            par = leaves[j_s]
            t0, t1 = clip_interval(a, b, self.lo[par], self.hi[par])
            ax = axis[j_s]
            rows = np.arange(len(rs_s))
            c0 = a[rows, ax] + t0 * (b[rows, ax] - a[rows, ax])
            c1 = a[rows, ax] + t1 * (b[rows, ax] - a[rows, ax])
            m = mid[j_s]
            for side, hit in ((0, np.minimum(c0, c1) <= m), (1, np.maximum(c0, c1) >= m)):
                k = kids[j_s] + side
                out_n.append(k[hit])
                out_s.append(rs_s[hit])
        self.ref_node = np.concatenate(out_n)
        self.ref_seg = np.concatenate(out_s)
        self.peak_bytes = max(self.peak_bytes, self.nbytes)

    def build_static(self) -> None:
        """Refine every leaf that meets the subdivision criteria (Sec. 5.2), level by level."""
        try:
            while True:
                self._freeze_settled()
                counts = self._ref_counts()
                leaves = np.nonzero(self.kind[:self.n] == LEAF)[0]
                leaves = leaves[self._splittable(leaves, counts)]
                if len(leaves) == 0:
                    return
                self._split(leaves, None)
        finally:
            self._thaw()

    # ---- lazy construction driven by a batch of queries ----
    def refine(self, x: np.ndarray, normals: np.ndarray | None, radius: np.ndarray | float) -> None:
        """Lazy construction (Sec. 6.1) for one batch of queries: walk the boxes
        ``x +- radius`` down the tree, split every reached leaf that meets the criteria,
        continue into the new children; stamp every reached node with this batch's
        number (the LRU clock, Sec. 6.4). ``normals``: the queries' normals (they place
        directional nodes and let covered queries skip the infeasible child), or None."""
        self.now += 1
        x = np.asarray(x, np.float64).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radius, np.float64), (len(x),))
        qlo, qhi = x - r[:, None], x + r[:, None]
        q = np.arange(len(x))
        node = np.zeros(len(x), np.int64)
        inside = np.all((qhi >= self.lo[0]) & (qlo <= self.hi[0]), axis=1)
        q, node = q[inside], node[inside]
        try:
            self._refine_pairs(q, node, qlo, qhi, normals)
        finally:
            self._thaw()
        self.peak_bytes = max(self.peak_bytes, self.nbytes)

    def _refine_pairs(self, q, node, qlo, qhi, normals) -> None:
        """The level-by-level walk of :meth:`refine` over (query, node) pairs."""
        while len(q):
            self._freeze_settled(node)
            self.stamp[np.unique(node)] = self.now
            kind = self.kind[node]
            leaf = kind == LEAF
            if leaf.any():
                counts = self._ref_counts()
                cand = np.unique(node[leaf])
                cand = cand[self._splittable(cand, counts)]
                if len(cand):
                    before = self.collapses
                    cand = self._within_budget(cand, counts)
                    if self.collapses != before:      # nodes were renumbered
                        node = self._remap[node]
                ln = node[leaf]
                if len(cand):
                    nrm = None
                    if normals is not None:
                        # the normal of the first (lowest-numbered) query reaching each leaf
                        lq = q[leaf]
                        order = np.lexsort((lq, ln))
                        ln_s, lq_s = ln[order], lq[order]
                        firsts = np.searchsorted(ln_s, cand)
                        nrm = np.asarray(normals, np.float64)[lq_s[firsts]]
                    self._split(cand, nrm)
                    kind = self.kind[node]
                    leaf = kind == LEAF
            # pairs at leaves are done; pairs at interior nodes go to the children they reach
            q, node, kind = q[~leaf], node[~leaf], kind[~leaf]
            if not len(q):
                break
            child = self.child[node]
            spatial = kind == SPATIAL
            ax = self.axis[node]
            sp = self.split[node]
            go_l = np.where(spatial, qlo[q, ax] <= sp, True)
            go_r = np.where(spatial, qhi[q, ax] >= sp, True)
            if normals is not None:
                dn = kind == DIRECTIONAL
                if dn.any():
                    cov = np.einsum("ij,ij->i", np.asarray(normals, np.float64)[q], self.rdir[node]) \
                        >= self.cos_alpha
                    go_r = np.where(dn & cov, False, go_r)   # covered: the back child only
            q = np.concatenate([q[go_l], q[go_r]])
            node = np.concatenate([child[go_l], child[go_r] + 1])

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
        self._thaw()
        n = self.n
        if n <= 1:
            return 0
        interior = self.kind[:n] != LEAF
        old = self.stamp[:n] < self.now
        par = self.parent[:n]
        parent_new = np.ones(n, bool)
        parent_new[1:] = ~old[par[1:]] if n > 1 else True
        cand = np.nonzero(interior & old & parent_new)[0]
        cand = cand[cand > 0]
        if len(cand) == 0:
            return 0
        # the candidate above every node (candidates' subtrees are disjoint)
        anc = np.full(n, -1, np.int64)
        anc[cand] = cand
        for d in range(1, int(self.depth[:n].max()) + 1):
            at = np.nonzero((self.depth[:n] == d) & (anc == -1))[0]
            if len(at):
                anc[at] = anc[par[at]]
        under = anc[self.ref_node]
        sel = under >= 0
        # bytes freed by collapsing each candidate: its nodes, its duplicate references
        key = under[sel] * (len(self.a) + 1) + self.ref_seg[sel]
        uniq = np.unique(key)
        refs_total = np.bincount(under[sel], minlength=n)[cand]
        refs_unique = np.bincount(uniq // (len(self.a) + 1), minlength=n)[cand]
        nodes_under = np.bincount(anc[anc >= 0], minlength=n)[cand] - 1
        freed = nodes_under * NODE_BYTES + (refs_total - refs_unique) * REF_BYTES
        order = np.lexsort((-freed, self.stamp[cand]))      # least recently used first
        cum = np.cumsum(freed[order])
        take = order[:int(np.searchsorted(cum, need_bytes)) + 1]
        chosen = cand[take]
        is_chosen = np.zeros(n, bool)
        is_chosen[chosen] = True
        # merge the chosen subtrees' references into their roots
        gone = sel & is_chosen[np.where(under >= 0, under, 0)]
        merged_key = np.unique(under[gone] * (len(self.a) + 1) + self.ref_seg[gone])
        ref_node = np.concatenate([self.ref_node[~gone], merged_key // (len(self.a) + 1)])
        ref_seg = np.concatenate([self.ref_seg[~gone], merged_key % (len(self.a) + 1)])
        # drop the nodes strictly below chosen roots and renumber the rest
        drop = (anc >= 0) & is_chosen[np.where(anc >= 0, anc, 0)] & ~is_chosen
        keep = ~drop
        before = self.nbytes
        new_index = np.cumsum(keep) - 1
        self.kind[chosen] = LEAF
        self.child[chosen] = -1
        self.rdir[chosen] = 0.0
        for name in ("lo", "hi", "kind", "axis", "split", "rdir", "child", "parent", "depth",
                     "has_dir", "stamp"):
            arr = getattr(self, name)
            kept = arr[:n][keep]
            arr[:len(kept)] = kept
        m = int(keep.sum())
        ch = self.child[:m]
        self.child[:m] = np.where(ch >= 0, new_index[np.maximum(ch, 0)], -1)
        pa = self.parent[:m]
        self.parent[:m] = np.where(pa >= 0, new_index[np.maximum(pa, 0)], -1)
        self.n = m
        self.ref_node = new_index[ref_node]
        self.ref_seg = ref_seg
        self.collapses += len(chosen)
        self._remap = new_index                 # old node index -> new (for callers)
        self._flat = None
        self.version += 1
        return before - self.nbytes

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
        """Invariants (tests): every leaf lists exactly the segments crossing its cell
        (directional leaves: those on their side), children partition their parent."""
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
