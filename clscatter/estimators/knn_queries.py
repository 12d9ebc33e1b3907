"""Ray-map queries: batched device kernels (``cl_kernels/raymap.cl``) and their NumPy
references (the same maths in float64, brute force over every segment).

A :class:`RayMap` holds the segments on the device and the kd-tree
(:mod:`.segment_tree`) on the host. Every query call first lets the tree refine lazily for
that batch (or not, for a static tree), uploads it if it changed, then runs one kernel over
all queries of the batch. The segments' end points also get a balanced point tree of the
same kind (:func:`kth_end_distance`: what the lazy refinement's reach is measured with).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..device import AppendBuffer
from .segment_tree import DIRECTIONAL, LEAF, SegmentTree, TreeParams, clip_segments

METRICS = {"plane": 0, "segment": 1, "line": 2, "hemidisc": 3}
DOMAINS = {"none": 0, "sphere": 1, "hemisphere": 2}
QUERIES = {"disc": 0, "hemisphere": 1, "sphere": 2, "box": 3}
HEAP_SIZES = (16, 64, 256, 1024)     # RM_K variants built on demand
END_LEAF_SIZE = 8                    # end points per leaf of their balanced tree (8-16)
#: consecutive queries of a batch that refine the lazy tree as one (SegmentTree.refine)
REFINE_GROUP = 16


def _f4(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64).reshape(-1, 3)
    out = np.zeros((max(len(v), 1), 4), np.float32)
    out[:len(v), :3] = v
    return out


@dataclass
class RayMap:
    """Segments (start ``a``, end ``b``, unit direction ``d``, rgb ``flux``) and the kd-tree
    over them. ``points=True`` indexes the end points only (a photon map: the tree and the
    queries see ``[b, b]``; ``d`` still tells where the light came from)."""

    engine: object
    a: np.ndarray
    b: np.ndarray
    d: np.ndarray
    flux: np.ndarray
    params: TreeParams = field(default_factory=TreeParams)
    points: bool = False
    lazy: bool = True
    scene_box: tuple | None = None

    def __post_init__(self):
        eng = self.engine
        if self.points:
            self.a = self.b
        lo, hi = self.scene_box if self.scene_box is not None else (None, None)
        self.tree = SegmentTree(self.a, self.b, self.d, self.params, lo, hi)
        if not self.lazy:
            self.tree.build_static()
        self.buf = {"seg_a": eng.to_device(_f4(self.a)), "seg_b": eng.to_device(_f4(self.b)),
                    "seg_d": eng.to_device(_f4(self.d)), "seg_flux": eng.to_device(_f4(self.flux))}
        self._tree_buf = None
        self._tree_key = None
        self._ends = None
        self.uploads = 0

    @property
    def cos_alpha(self) -> float:
        return self.tree.cos_alpha

    def prepare(self, x: np.ndarray, n: np.ndarray | None, radius) -> None:
        """Lazy refinement for a batch (no-op for a static tree), then upload if changed."""
        if self.lazy:
            self.tree.refine(x, n, radius, group=REFINE_GROUP)
        key = self.tree.version
        if key != self._tree_key:
            if self._tree_buf is not None:
                self.engine.free(*self._tree_buf)
            nodes, refs = self.tree.device_arrays()
            self._tree_buf = (self.engine.to_device(nodes), self.engine.to_device(refs))
            self._tree_key = key
            self.uploads += 1

    def tree_args(self) -> dict:
        return {"nodes": self._tree_buf[0], "refs": self._tree_buf[1], "seg_a": self.buf["seg_a"],
                "seg_b": self.buf["seg_b"], "seg_d": self.buf["seg_d"]}

    def end_points(self) -> tuple:
        """The balanced point tree over the segments' end points ``b`` (float32), made and
        uploaded once: (order, device end points float4 in leaf order, device
        POINT_NODE boxes, levels)."""
        if self._ends is None:
            tree = SegmentTree.balanced(self.b.astype(np.float32), END_LEAF_SIZE)
            order = tree.order
            self._ends = (order, self.engine.to_device(_f4(self.b[order])),
                          self.engine.to_device(tree.point_nodes()), tree.levels)
        return self._ends

    def release(self) -> None:
        eng = self.engine
        eng.free(*self.buf.values())
        if self._tree_buf is not None:
            eng.free(*self._tree_buf)
        if self._ends is not None:
            eng.free(*self._ends[1:3])
        self.buf = {}
        self._tree_buf = None
        self._ends = None


def heap_scratch(engine, k: int, items: int) -> tuple:
    """Global heap scratch for ``items`` work-items (used when the heap exceeds 256)."""
    h = heap_define(k)["RM_K"]
    n = items * h if h > 256 else 1
    return engine.empty(4 * n), engine.empty(4 * n)


def heap_define(k: int) -> dict:
    """The smallest compiled heap size holding ``k``."""
    for h in HEAP_SIZES:
        if k <= h:
            return {"RM_K": h}
    raise ValueError(f"K = {k} exceeds the largest heap ({HEAP_SIZES[-1]})")


def knn(rmap: RayMap, x: np.ndarray, n: np.ndarray, k: int, metric: str = "segment",
        domain: str = "none", radius: float = 0.0, incoming: bool = False,
        lazy_radius: np.ndarray | float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K nearest segments of every query (device). Returns (idx (Q, k) int, -1 past the
    count; dist (Q, k), ascending; work (Q, 2): nodes visited, references tested)."""
    eng = rmap.engine
    x = np.asarray(x, np.float64).reshape(-1, 3)
    nq = len(x)
    n = np.asarray(n, np.float64).reshape(-1, 3)
    rmap.prepare(x, n, radius if lazy_radius is None else lazy_radius)
    bufs = [eng.to_device(_f4(x)), eng.to_device(_f4(n)), eng.empty(4 * nq * k),
            eng.empty(4 * nq * k), eng.empty(4 * nq), eng.empty(8 * nq), *heap_scratch(eng, k, nq)]
    eng.call("raymap", "rm_knn_batch", nq, heap_define(k), **rmap.tree_args(), qx=bufs[0],
             scratch_d=bufs[6], scratch_x=bufs[7],
             qn=bufs[1], num_q=nq, k=k, metric=METRICS[metric], domain=DOMAINS[domain],
             radius=radius, incoming=int(incoming), cos_alpha=rmap.cos_alpha, out_idx=bufs[2],
             out_dist=bufs[3], out_count=bufs[4], out_work=bufs[5])
    idx = eng.read(bufs[2], (nq, k), np.int32)
    dist = eng.read(bufs[3], (nq, k), np.float32)
    work = eng.read(bufs[5], (nq, 2), np.int32)
    eng.free(*bufs)
    dist = np.where(idx >= 0, dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")
    return (np.take_along_axis(idx, order, 1), np.take_along_axis(dist, order, 1), work)


def kth_end_distance(rmap: RayMap, x: np.ndarray, k: int, reach: float) -> np.ndarray:
    """Per query, the distance (float64) to its ``k``-th nearest segment end point when
    at least ``k`` end points lie within ``reach`` of it, else inf. The device finds the
    point (``rm_kth_end``: the balanced point tree's k-nearest query, float32); the
    distance is measured here from the float64 end point."""
    eng = rmap.engine
    x = np.asarray(x, np.float64).reshape(-1, 3)
    nq = len(x)
    out = np.full(nq, np.inf)
    if nq == 0 or len(rmap.b) < k or k < 1:
        return out
    order, ends, nodes, levels = rmap.end_points()
    bufs = [eng.to_device(_f4(x)), eng.empty(4 * nq), *heap_scratch(eng, k, nq)]
    try:
        eng.call("raymap", "rm_kth_end", nq, heap_define(k), ends=ends, num_ends=len(order),
                 end_nodes=nodes, levels=levels, qx=bufs[0], num_q=nq, k=k,
                 r2_search=float(reach) ** 2, scratch_d=bufs[2], scratch_x=bufs[3],
                 out_idx=bufs[1])
        idx = eng.read(bufs[1], nq, np.int32)
    finally:
        eng.free(*bufs)
    found = idx >= 0
    out[found] = np.linalg.norm(x[found] - rmap.b[order[idx[found]]], axis=1)
    return out


def candidate_lists(rmap: RayMap, x: np.ndarray, n: np.ndarray, radius: float,
                    incoming: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-query candidate segments on the host: every leaf whose (float32, widened) box
    meets the query's search box (centre x, half-size ``radius``, plus a float margin)
    contributes its references; directional nodes are pruned as on the device (incoming
    queries covered by the reference direction take the back child only). A vectorised
    level-by-level walk over (query, node) pairs, then (query, segment) pairs made
    unique. Returns (offsets int32 (Q + 1), ids int32, nodes visited per query)."""
    nodes, refs = rmap.tree.device_arrays()
    nq = len(x)
    lo = nodes["lo"][:, :3].astype(np.float64)
    hi = nodes["hi"][:, :3].astype(np.float64)
    kind, child = nodes["kind"], nodes["child"]
    first, count = nodes["first"].astype(np.int64), nodes["count"].astype(np.int64)
    rdir = nodes["aux"][:, :3].astype(np.float64)
    pad = float(radius) * (1.0 + 1e-5) + 1e-6 * max(rmap.tree.diag, 1e-6)
    qlo, qhi = x - pad, x + pad
    q = np.arange(nq, dtype=np.int64)
    nd = np.zeros(nq, np.int64)
    visited = np.zeros(nq, np.int64)
    leaf_q, leaf_n = [], []
    while len(q):
        ok = np.all((lo[nd] <= qhi[q]) & (hi[nd] >= qlo[q]), axis=1)
        q, nd = q[ok], nd[ok]
        visited += np.bincount(q, minlength=nq)
        kd = kind[nd]
        leaf = kd == LEAF
        keep = leaf & (count[nd] > 0)
        leaf_q.append(q[keep])
        leaf_n.append(nd[keep])
        qi, ni = q[~leaf], nd[~leaf]
        c0 = child[ni].astype(np.int64)
        second = np.ones(len(ni), bool)
        if incoming:
            dn = kind[ni] == DIRECTIONAL
            if dn.any():
                cov = np.einsum("ij,ij->i", rdir[ni[dn]], n[qi[dn]]) >= rmap.cos_alpha
                second[np.nonzero(dn)[0][cov]] = False
        q = np.concatenate([qi, qi[second]])
        nd = np.concatenate([c0, c0[second] + 1])
    lq = np.concatenate(leaf_q) if leaf_q else np.zeros(0, np.int64)
    ln = np.concatenate(leaf_n) if leaf_n else np.zeros(0, np.int64)
    cnt = count[ln]
    total = int(cnt.sum())
    starts = np.cumsum(cnt) - cnt
    pos = np.repeat(first[ln] - starts, cnt) + np.arange(total, dtype=np.int64)
    nseg = max(len(rmap.b), 1)
    keys = np.repeat(lq, cnt) * nseg + refs[pos]
    keys.sort()                     # (np.unique's hash path is far slower at this size)
    if len(keys):
        keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]
    offsets = np.zeros(nq + 1, np.int64)
    np.cumsum(np.bincount(keys // nseg, minlength=nq), out=offsets[1:])
    return offsets.astype(np.int32), (keys % nseg).astype(np.int32), visited


def knn_lists(rmap: RayMap, x: np.ndarray, n: np.ndarray, k: int, metric: str = "segment",
              domain: str = "hemisphere", radius: float = 0.0, incoming: bool = False,
              lazy_radius: np.ndarray | float | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K nearest segments of every query with candidate lists prepared on the host
    (:func:`candidate_lists`) and one device kernel (``rm_knn_list``) doing the same
    per-candidate test and heap as :func:`knn`. Same return contract as :func:`knn`
    (work: host nodes visited, candidates tested). Domain queries only (finite radius)."""
    if domain not in ("sphere", "hemisphere") or not radius > 0:
        raise ValueError("knn_lists needs a domain (sphere or hemisphere) of finite radius > 0")
    eng = rmap.engine
    x = np.asarray(x, np.float64).reshape(-1, 3)
    nq = len(x)
    n = np.asarray(n, np.float64).reshape(-1, 3)
    if rmap.lazy:
        rmap.tree.refine(x, n, radius if lazy_radius is None else lazy_radius)
    off, ids, visited = candidate_lists(rmap, x, n, radius, incoming)
    bufs = [eng.to_device(off), eng.to_device(ids), eng.to_device(_f4(x)), eng.to_device(_f4(n)),
            eng.empty(4 * nq * k), eng.empty(4 * nq * k), eng.empty(4 * nq),
            *heap_scratch(eng, k, nq)]
    eng.call("raymap", "rm_knn_list", nq, heap_define(k), cand_off=bufs[0], cand_ids=bufs[1],
             seg_a=rmap.buf["seg_a"], seg_b=rmap.buf["seg_b"], seg_d=rmap.buf["seg_d"],
             qx=bufs[2], qn=bufs[3], num_q=nq, k=k, metric=METRICS[metric],
             domain=DOMAINS[domain], radius=radius, incoming=int(incoming),
             scratch_d=bufs[7], scratch_x=bufs[8], out_idx=bufs[4], out_dist=bufs[5],
             out_count=bufs[6])
    idx = eng.read(bufs[4], (nq, k), np.int32)
    dist = eng.read(bufs[5], (nq, k), np.float32)
    eng.free(*bufs)
    work = np.stack([visited, np.diff(off.astype(np.int64))], axis=1).astype(np.int32)
    dist = np.where(idx >= 0, dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")
    return (np.take_along_axis(idx, order, 1), np.take_along_axis(dist, order, 1), work)


def intersect(rmap: RayMap, kind: str, x: np.ndarray, n: np.ndarray, r: np.ndarray | float
              ) -> np.ndarray:
    """All (query, segment) pairs whose segment meets the query's domain (device), unique
    and sorted. ``kind``: disc, hemisphere, sphere (centre x, normal n, radius r) or box
    (x = min corner, n = max corner)."""
    eng = rmap.engine
    x = np.asarray(x, np.float64).reshape(-1, 3)
    nq = len(x)
    n = np.asarray(n, np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(r, np.float64), (nq,))
    if kind == "box":
        rmap.prepare(0.5 * (x + n), None, 0.5 * np.max(n - x, axis=1))
    else:
        rmap.prepare(x, n if kind in ("disc", "hemisphere") else None, r)
    bufs = [eng.to_device(_f4(x)), eng.to_device(_f4(n)),
            eng.to_device(np.ascontiguousarray(r, np.float32))]
    out = AppendBuffer(eng, np.dtype((np.int32, 2)), 4 * nq + 16)
    pairs = out.call("raymap", "rm_intersect", nq, None, **rmap.tree_args(), qx=bufs[0],
                     qn=bufs[1], qr=bufs[2], num_q=nq, qtype=QUERIES[kind],
                     cos_alpha=rmap.cos_alpha)
    out.release()
    eng.free(*bufs)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    return np.unique(pairs, axis=0) if len(pairs) else pairs


# ---- NumPy references (float64, every segment) ----
def _rows(v, m):
    return np.broadcast_to(np.asarray(v, np.float64).reshape(-1, 3), (m, 3))


def seg_dist(x, a, b) -> np.ndarray:
    ab = b - a
    l2 = np.einsum("ij,ij->i", ab, ab)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(l2 > 0, np.clip(np.einsum("ij,ij->i", x - a, ab) / np.where(l2 > 0, l2, 1), 0, 1), 0)
    return np.linalg.norm(a + t[:, None] * ab - x, axis=1)


def plane_dist(x, n, a, d) -> np.ndarray:
    dn = np.einsum("ij,ij->i", d, n)
    ok = np.abs(dn) >= 1e-7
    t = np.einsum("ij,ij->i", x - a, n) / np.where(ok, dn, 1.0)
    return np.where(ok, np.linalg.norm(a + t[:, None] * d - x, axis=1), np.inf)


def hemi_dist(x, n, a, b) -> np.ndarray:
    sa = np.einsum("ij,ij->i", a - x, n)
    sb = np.einsum("ij,ij->i", b - x, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        a2 = np.where((sa < 0)[:, None], a + (sa / (sa - sb))[:, None] * (b - a), a)
        b2 = np.where(((sa >= 0) & (sb < 0))[:, None], b + (sb / (sb - sa))[:, None] * (a - b), b)
    return np.where((sa < 0) & (sb < 0), np.inf, seg_dist(x, a2, b2))


def metric_np(metric: str, x, n, a, b, d) -> np.ndarray:
    """Distance of every segment to query (x, n) under ``metric`` (float64)."""
    m = len(a)
    x, n = _rows(x, m), _rows(n, m)
    if metric == "segment":
        return seg_dist(x, a, b)
    if metric == "line":
        return np.linalg.norm(np.cross(x - a, d), axis=1)
    if metric == "plane":
        return plane_dist(x, n, a, d)
    return np.maximum(plane_dist(x, n, a, d), hemi_dist(x, n, a, b))


def qualifying_np(metric: str, x, n, a, b, d, domain: str, radius: float, incoming: bool):
    """(distance, mask of segments that qualify) for one query, as rm_knn defines it."""
    v = metric_np(metric, x, n, a, b, d)
    m = len(a)
    ok = np.isfinite(v)
    if incoming:
        ok &= d @ np.asarray(n, np.float64) < 0
    if domain != "none":
        xx, nn = _rows(x, m), _rows(n, m)
        meet = seg_dist(xx, a, b) if domain == "sphere" else hemi_dist(xx, nn, a, b)
        ok &= (meet <= radius) & (v <= radius)
    return v, ok


def knn_np(metric: str, x, n, a, b, d, k: int, domain: str = "none", radius: float = 0.0,
           incoming: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force K nearest for one query: (indices, distances), ascending."""
    v, ok = qualifying_np(metric, x, n, a, b, d, domain, radius, incoming)
    idx = np.nonzero(ok)[0]
    order = np.argsort(v[idx], kind="stable")[:k]
    return idx[order], v[idx[order]]


def meets_np(kind: str, x, n, r, a, b, d) -> np.ndarray:
    """Brute-force domain test of every segment for one query (rm_meets)."""
    m = len(a)
    xx, nn = _rows(x, m), _rows(n, m)
    if kind == "sphere":
        return seg_dist(xx, a, b) <= r
    if kind == "box":
        return clip_segments(a, b, xx, nn)
    inc = np.einsum("ij,ij->i", d, nn) < 0
    if kind == "hemisphere":
        return inc & (hemi_dist(xx, nn, a, b) <= r)
    sa = np.einsum("ij,ij->i", a - xx, nn)
    sb = np.einsum("ij,ij->i", b - xx, nn)
    cross = (sa >= 0) & (sb <= 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(sa > sb, sa / (sa - sb), 0.0)
    p = a + t[:, None] * (b - a)
    return inc & cross & (np.linalg.norm(p - xx, axis=1) <= r)
