"""Balanced median splits, level by level: the build shared by the line tree
(:mod:`.line_tree`, 6-D Plücker points) and the balanced point tree
(:meth:`.segment_tree.SegmentTree.balanced`, photon and ray end points).

kd node ``j`` of level ``k`` owns the points ``[j n >> k, (j + 1) n >> k)`` of the final
order (:func:`level_starts`); these ranges nest exactly, so every level's nodes hold
``floor`` or ``ceil`` of ``n / 2^k`` points and no padding is needed. Each level splits
every node at once: one ``argsort`` of all points by one float64 key (node index + the
point's place along the node's widest axis, scaled into [0, 0.5]); the sort moves points
only within their node. Coordinates are stored as rows, ``(width, n)``, so that every
node's run is contiguous for the reductions and the moves. From
:data:`PARALLEL_MIN_POINTS` points on, the levels above :data:`PARALLEL_LEVELS` split
node by node instead (an ``argpartition`` at the node's median along its widest axis,
the nodes of a level on threads), and the subtrees below are built on threads (NumPy's
sorts and gathers release the GIL); the split into nodes and subtrees does not depend on
the machine, so neither does the tree. Either way a node's lower half on its axis goes
to its first child; only points of equal value there may fall on either side."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .row_chunks import host_threads

#: levels split node by node before the subtrees below are built apart
PARALLEL_LEVELS = 4
#: points from which the subtrees are built on threads
PARALLEL_MIN_POINTS = 1 << 17


def level_starts(n: int, k: int) -> np.ndarray:
    """Where each of the ``2^k`` nodes of level ``k`` begins among ``n`` points (int64)."""
    return (np.arange(1 << k, dtype=np.int64) * n) >> k


def _split(cur: np.ndarray, order: np.ndarray, n: int, node: int, k_from: int, k_to: int,
           offset: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Levels ``k_from .. k_to - 1`` of the points ``cur`` (rows, (width, m)), which are
    node ``node`` of level ``k_from``: points ``[offset, offset + m)`` of all ``n``.
    Returns the points and ``order`` in the new order, and each level's split axes."""
    m = cur.shape[1]
    ar = np.arange(m, dtype=np.int64)
    axes = []
    for k in range(k_from, k_to):
        parts = 1 << (k - k_from)
        j = np.arange(parts)
        starts = ((node * parts + j) * n >> k) - offset             # this slice's nodes
        lo = np.minimum.reduceat(cur, starts, axis=1).astype(np.float64)   # (width, parts)
        ext = np.maximum.reduceat(cur, starts, axis=1).astype(np.float64) - lo
        axis = np.argmax(ext, axis=0)                                # split axis per node
        axes.append(axis.astype(np.int8))
        owner = np.repeat(j, np.diff(np.append(starts, m)))
        span = ext[axis, j]
        inv = 0.5 / np.where(span > 0, span, 1.0)
        val = cur.ravel()[axis[owner] * m + ar]
        perm = np.argsort(owner + np.clip((val - lo[axis, j][owner]) * inv[owner], 0.0, 0.5))
        cur = np.take(cur, perm, axis=1)
        order = np.take(order, perm)
    return cur, order, axes


def _widest(c: np.ndarray) -> int:
    """The axis (row) along which the points ``c`` (rows, (width, m)) extend furthest."""
    return int(np.argmax(c.max(axis=1).astype(np.float64) - c.min(axis=1).astype(np.float64)))


def _split_nodes(cur: np.ndarray, order: np.ndarray, n: int, top: int,
                 pool: ThreadPoolExecutor) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Levels ``0 .. top - 1`` of all ``n`` points, node by node: each node's points
    partitioned at its median along its widest axis (``argpartition``), the nodes of a
    level on ``pool``'s threads. Returns the points and ``order`` in the new order (new
    arrays: the inputs are not changed) and each level's split axes."""
    axes = []
    for k in range(top):
        if k == 0:                           # the root: into new arrays
            ax = _widest(cur)
            perm = np.argpartition(cur[ax], n >> 1) if 0 < n >> 1 < n else np.arange(n)
            cur, order = np.take(cur, perm, axis=1), np.take(order, perm)
            axes.append(np.array([ax], np.int8))
            continue
        parts = 1 << k
        bounds = level_starts(n, k).tolist() + [n]
        axis = np.zeros(parts, np.int8)

        def node(j: int) -> None:
            a, b = bounds[j], bounds[j + 1]
            mid = (2 * j + 1) * n >> (k + 1)        # where its second child begins
            if b - a == 0:
                return
            c = cur[:, a:b]
            axis[j] = ax = _widest(c)
            if a < mid < b:
                perm = np.argpartition(c[ax], mid - a)
                cur[:, a:b] = np.take(c, perm, axis=1)
                order[a:b] = np.take(order[a:b], perm)

        list(pool.map(node, range(parts)))
        axes.append(axis)
    return cur, order, axes


def median_levels(rows: np.ndarray, levels: int, order_dtype=np.int64
                  ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Split ``levels`` kd levels of the points ``rows`` (coordinates as rows, (width, n);
    their float type is kept): ``(rows in the final order, order (sorted position -> input
    index, ``order_dtype``), the split axis of every node of each level (int8))``."""
    cur = np.ascontiguousarray(rows)
    n = cur.shape[1]
    order = np.arange(n, dtype=order_dtype)
    if n < PARALLEL_MIN_POINTS or levels <= 0:
        cur, order, axes = _split(cur, order, n, 0, 0, levels, 0)
        return cur, order, axes
    top = min(levels, PARALLEL_LEVELS)
    with ThreadPoolExecutor(min(1 << top, host_threads())) as pool:
        cur, order, axes = _split_nodes(cur, order, n, top, pool)
        if top < levels:                     # the subtrees below, one thread each
            parts = 1 << top
            bounds = level_starts(n, top).tolist() + [n]
            below: list = [None] * parts

            def subtree(c: int) -> None:
                a, b = bounds[c], bounds[c + 1]
                cur[:, a:b], order[a:b], below[c] = _split(cur[:, a:b], order[a:b], n, c,
                                                           top, levels, a)

            list(pool.map(subtree, range(parts)))
            axes += [np.concatenate([below[c][i] for c in range(parts)])
                     for i in range(levels - top)]
    return cur, order, axes
