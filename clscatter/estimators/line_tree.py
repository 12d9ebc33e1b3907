"""Line space hierarchy for line space gathering: Plücker points in a perfect 8-ary tree.

Plücker coordinates (Sun et al. 2010, section 4.1)
    A line through ``p`` with unit direction ``u`` is the 6-D point ``P = (u, m)`` with
    moment ``m = p x u`` (independent of which ``p`` on the line). Two lines
    ``(u1, m1)``, ``(u2, m2)`` satisfy the *side relation*

        u1 . m2 + m1 . u2 = (p1 - p2) . (u1 x u2),   so   |u1 . m2 + m1 . u2| = d sin(theta)

    with ``d`` the distance between the lines and ``theta`` their angle. With unit
    directions this is the paper's eq. (13)-(15) with ``c = 1``: the view line, written
    as the hyperplane ``w = (m_v, u_v)`` through the 6-D origin, has ``|P . w| = d sin
    theta <= d``. Hence **a lighting line with |P . w| > r is farther than r from the view
    line**, and so is every segment on it: the plane query culls only pairs that cannot
    be within r. Over a 6-D box ``[lo, hi]`` the linear function ``P . w`` ranges over
    ``[sum_i min(w_i lo_i, w_i hi_i), sum_i max(w_i lo_i, w_i hi_i)]`` (exactly), so a
    node is culled when that interval misses ``[-r, r]``. The kernel widens ``r`` by a
    float32 rounding allowance (``cl_kernels/lsg.h``, ``lsg_threshold``).

Normalisation (:class:`PluckerFrame`)
    The moments are formed in a frame centred on the region where pairs can occur and
    scaled to ``[-1, 1]``: ``p' = (p - centre) / scale``. Moments of the lines that matter
    are then O(1), like the directions, so the 6 coordinates have comparable ranges for
    the median splits and the float32 rounding of ``u . m_v + m . u_v`` (terms of size
    |m| that cancel to ``d sin theta``) stays far below ``r``. Distances scale by
    ``1 / scale`` (``r' = r / scale``).

Canonical sign
    ``(u, m)`` and ``(-u, -m)`` are the same unoriented line. Points are stored with the
    sign that makes the dominant axis of the whole set (largest mean |u_k|) non-negative,
    so nearly identical lines of opposite orientation land next to each other instead of
    at antipodes of the 6-D set (smaller boxes, better culling). This is safe for the
    plane query because the test uses ``|P . w|``, which is invariant under ``P -> -P``;
    the segments themselves keep their orientation for the radiance estimate.

The tree (:func:`build_linetree`, paper section 4.3)
    A balanced kd-tree with median splits on the axis of largest extent (of the six
    Plücker coordinates, and of any ``split_extra`` coordinates: they steer the splits
    but are not in the nodes' boxes), ``3 L`` levels deep, where ``L`` is the largest
    integer with ``8^L * leaf_size <= N``; every three kd levels are collapsed into one,
    giving a *perfect* 8-ary tree with ``8^L`` leaves.
    kd node ``j`` of level ``k`` owns the points ``[j N // 2^k, (j + 1) N // 2^k)`` of the
    final order; these ranges nest exactly (``2 j N // 2^(k+1) = j N // 2^k``), so 8-ary
    node ``j`` of level ``l`` is kd node ``j`` of level ``3 l`` and no padding is needed:
    every leaf holds ``floor`` or ``ceil`` of ``N / 8^L`` points, i.e. between
    ``leaf_size`` and ``8 leaf_size`` (fewer only when ``N < leaf_size``: then the
    root is the only leaf). Nodes are stored breadth-first (heap order): level ``l``
    starts at ``(8^l - 1) / 7``; node ``g`` has children ``8 g + 1 .. 8 g + 8``, parent
    ``(g - 1) // 8``, and a next sibling ``g + 1`` unless ``g % 8 == 0``. Each node holds
    its 12-float 6-D box; leaves also get an index range into the points, which are
    sorted by leaf.

    Build cost: the kd levels are :func:`~.median_split.median_levels` (one ``argsort``
    of all N points per kd level; for large N the top levels node by node and the
    subtrees below on threads), shared with the balanced point tree;
    ``np.minimum.reduceat`` for the 8-ary boxes. No Python loop runs over points, nor
    over nodes but the few of the top levels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .median_split import level_starts, median_levels

# A node of the tree: its 6-D box (the kernels read the boxes as child_rows blocks)
LINE_NODE = np.dtype([("lo", np.float32, 6), ("hi", np.float32, 6)], align=True)

# The most 8-ary levels a gather's walk descends (``LSG_MAX_LEVELS`` in
# cl_kernels/estimators/lsg.cl, the depth of its stack)
WALK_LEVELS = 12


# Half the side of the box around the normalised frame's origin (where the scene is:
# [-0.5, 0.5]^3) that a Plücker frame for long segments is fitted to
# (PluckerFrame.for_segments).
SCENE_REACH = 1.0


@dataclass(frozen=True)
class PluckerFrame:
    """The frame the Plücker moments are formed in: ``p' = (p - centre) / scale``."""

    centre: np.ndarray
    scale: float

    @staticmethod
    def for_box(lo, hi) -> "PluckerFrame":
        """Centre of the box, half its longest side (so the box maps into [-1, 1]^3)."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        half = 0.5 * float(np.max(hi - lo))
        if not np.isfinite(half) or half <= 0:
            half = 1.0
        return PluckerFrame(0.5 * (lo + hi), half)

    @staticmethod
    def for_segments(lo, hi) -> "PluckerFrame":
        """The frame for segments whose box is [lo, hi] (normalised frame): :meth:`for_box`
        of the part of that box within [-SCENE_REACH, SCENE_REACH]^3, or of the whole box
        if none of it is. The scene's box is [-0.5, 0.5]^3 there, while segments in an
        unbounded medium run on to where its transmittance is 1e-5, tens of units away:
        their moments and the tree's spatial split (``split_extra``) are then measured on
        the scale of the scene they start in, not of where they end. Any frame gives the
        same pairs; this one culls far better there (docs/benchmarks.md, "Unbounded
        media: the trees' Plücker frame")."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        clo, chi = np.maximum(lo, -SCENE_REACH), np.minimum(hi, SCENE_REACH)
        if np.all(chi >= clo):
            return PluckerFrame.for_box(clo, chi)
        return PluckerFrame.for_box(lo, hi)


def plucker(a, u, frame: PluckerFrame) -> np.ndarray:
    """``(N, 6)`` float64 Plücker points ``(u, m)`` of lines through ``a`` along unit ``u``,
    the moment ``m = ((a - centre) / scale) x u`` taken in ``frame``."""
    a = np.asarray(a, np.float64)
    u = np.asarray(u, np.float64)
    m = np.cross((a - frame.centre) / frame.scale, u)
    return np.concatenate([u, m], axis=1)


def canonical_signs(u) -> np.ndarray:
    """+-1 per line: the sign that makes the set's dominant direction axis non-negative."""
    u = np.asarray(u, np.float64)
    if len(u) == 0:
        return np.ones(0, np.float32)
    axis = int(np.argmax(np.abs(u).sum(axis=0)))
    return np.where(u[:, axis] < 0, -1.0, 1.0).astype(np.float32)


@dataclass
class LineTree:
    """A perfect 8-ary tree over 6-D points (see the module docstring)."""

    nodes: np.ndarray        # LINE_NODE, breadth-first, (8^(levels+1) - 1) / 7 nodes
    leaf_ranges: np.ndarray  # (8^levels, 2) int32: [start, end) into the sorted points
    order: np.ndarray        # (N,) int64: sorted position -> input index
    levels: int              # L: leaves are at 8-ary level L (0: the root is the leaf)

    @property
    def first_leaf(self) -> int:
        return (8 ** self.levels - 1) // 7

    @property
    def nbytes(self) -> int:
        return int(self.nodes.nbytes + self.leaf_ranges.nbytes + self.order.nbytes)


def tree_levels(n: int, leaf_size: int) -> int:
    """L = the largest integer with 8^L * leaf_size <= n (0 for small n)."""
    leaf_size = max(1, int(leaf_size))
    levels = 0
    while 8 ** (levels + 1) * leaf_size <= n:
        levels += 1
    return levels


def build_linetree(points, leaf_size: int = 4, split_extra=None) -> LineTree:
    """Balanced median-split kd-tree over ``points`` (N, 6), collapsed to a perfect 8-ary
    tree. ``points`` should be the float32 values the kernel reads: the boxes are computed
    from them exactly, so every stored point lies inside its nodes' boxes.
    ``split_extra`` (N, k): more coordinates a node may be split on (the axis of largest
    extent among all 6 + k), which do not enter the boxes."""
    pts = np.ascontiguousarray(points, np.float32)
    n = len(pts)
    cols = [pts] if split_extra is None else [pts, np.asarray(split_extra, np.float32).reshape(n, -1)]
    return linetree_from_rows(np.concatenate(cols, axis=1).T, leaf_size)


def linetree_from_rows(rows: np.ndarray, leaf_size: int = 4) -> LineTree:
    """:func:`build_linetree` of points given as rows, ``(6 + k, N)`` float32: the six
    Plücker coordinates, then the ``k`` extra split coordinates (no copy is made of a
    C-contiguous array, and it is not changed)."""
    rows = np.ascontiguousarray(rows, np.float32)
    n = rows.shape[1]
    if n == 0:
        nodes = np.zeros(1, LINE_NODE)
        nodes["lo"], nodes["hi"] = 1e30, -1e30     # empty box: always culled
        return LineTree(nodes, np.zeros((1, 2), np.int32), np.zeros(0, np.int64), 0)
    levels = tree_levels(n, leaf_size)
    # ---- kd levels: every node of a level split at its median at once ----
    cur, order, _ = median_levels(rows, 3 * levels)
    # ---- 8-ary levels: boxes of every node, breadth-first ----
    sorted_pts = cur[:6]
    total = (8 ** (levels + 1) - 1) // 7
    nodes = np.zeros(total, LINE_NODE)
    for lvl in range(levels + 1):
        starts = level_starts(n, 3 * lvl)
        off = (8 ** lvl - 1) // 7
        nodes["lo"][off:off + len(starts)] = np.minimum.reduceat(sorted_pts, starts, axis=1).T
        nodes["hi"][off:off + len(starts)] = np.maximum.reduceat(sorted_pts, starts, axis=1).T
    starts = level_starts(n, 3 * levels)
    ranges = np.stack([starts, np.append(starts[1:], n)], axis=1).astype(np.int32)
    return LineTree(nodes, ranges, order, levels)


def node_boxes(tree: LineTree, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """3-D bounding boxes of every node's segments, ``(nodes, 2, 4)`` float32 (lo, hi;
    w unused), breadth-first like ``tree.nodes``: ``lo``/``hi`` are each segment's own
    box in tree order, as rows (3, N). The boxes are rounded outwards to float32, so every
    segment the kernel reads lies inside its nodes' boxes; an empty node's box is empty
    (lo > hi)."""
    lo, hi = np.ascontiguousarray(lo), np.ascontiguousarray(hi)
    n = lo.shape[1]
    total = len(tree.nodes)
    out = np.zeros((total, 2, 4), np.float32)
    out[:, 0, :3], out[:, 1, :3] = 1e30, -1e30
    if n == 0:
        return out
    for lvl in range(tree.levels + 1):
        starts = level_starts(n, 3 * lvl)
        off = (8 ** lvl - 1) // 7
        nonempty = np.diff(np.append(starts, n)) > 0
        rows = off + np.flatnonzero(nonempty)
        s = starts[nonempty]
        out[rows, 0, :3] = np.nextafter(np.minimum.reduceat(lo, s, axis=1).T.astype(np.float32),
                                        np.float32(-np.inf))
        out[rows, 1, :3] = np.nextafter(np.maximum.reduceat(hi, s, axis=1).T.astype(np.float32),
                                        np.float32(np.inf))
    return out


#: Points per block of the plane tests (``block_near`` and ``dir_block_near`` in
#: cl_kernels/estimators/lsg.cl test a block's points at once, one per vector lane).
POINT_LANES = 8


def point_block_array(n: int, coords: int = 6) -> np.ndarray:
    """Zeroed blocks for ``n`` points of ``coords`` coordinates (6: Plücker points) in
    :func:`point_blocks`' layout: ``(ceil(n / L), coords, L)`` float32 (L =
    :data:`POINT_LANES`), one block for no points."""
    return np.zeros((max(1, -(-int(n) // POINT_LANES)), coords, POINT_LANES), np.float32)


def point_blocks(points, out: np.ndarray | None = None, start: int = 0) -> np.ndarray:
    """Points ``(N, C)`` (Plücker points in tree order, C = 6; or the screen cells' unit
    directions in cell order, C = 3) as blocks of L = :data:`POINT_LANES` for a plane test
    of L at once (``block_near``, ``dir_block_near`` in cl_kernels/estimators/lsg.cl):
    ``(ceil(N / L), C, L)`` float32, block ``b`` holding points ``L b .. L b + L - 1`` as
    columns and their C coordinates as rows; the last block padded with zeros, and one
    block of zeros for no points. With ``out`` (:func:`point_block_array`), the points are
    written there as points ``start`` (a multiple of L) onwards, and ``out`` is returned."""
    lanes = POINT_LANES
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2:
        pts = pts.reshape(-1, 6)
    if out is None:
        out = point_block_array(len(pts), pts.shape[1])
    if start % lanes:
        raise ValueError(f"point blocks start at a multiple of {lanes}, not {start}")
    b, whole = start // lanes, len(pts) // lanes * lanes
    out[b:b + whole // lanes] = pts[:whole].reshape(-1, lanes, pts.shape[1]).transpose(0, 2, 1)
    if whole < len(pts):                     # the last, padded block
        out[b + whole // lanes, :, :len(pts) - whole] = pts[whole:].T
    return out


def child_rows(tree: LineTree, boxes: np.ndarray) -> np.ndarray:
    """The tree's nodes 8 side by side, as the gather's walk reads them (it tests a block's
    8 at once: ``block_visited`` in cl_kernels/estimators/lsg.cl): ``(internal + 1, 18, 8)``
    float32. Block 0 holds the root in column 0 (its other columns empty boxes, which no
    walk enters); block ``g + 1`` the children ``8 g + 1 .. 8 g + 8`` of internal node
    ``g``, column ``c`` child ``8 g + 1 + c``. Rows: the 6-D box (lo 6, hi 6), then the 3-D
    box of the node's segments (lo 3, hi 3; ``boxes``: :func:`node_boxes`)."""
    if tree.levels > WALK_LEVELS:
        raise ValueError(f"a line tree of {tree.levels} levels: the gather walks at most "
                         f"{WALK_LEVELS}")
    rows = np.concatenate([tree.nodes["lo"], tree.nodes["hi"], boxes[:, 0, :3],
                           boxes[:, 1, :3]], axis=1)               # (nodes, 18), node order
    empty = np.concatenate([np.full(6, 1e30), np.full(6, -1e30), np.full(3, 1e30),
                            np.full(3, -1e30)])
    root = np.vstack([rows[:1], np.tile(empty, (7, 1))])
    blocks = np.concatenate([root, rows[1:]]).reshape(-1, 8, 18)  # children are contiguous
    return np.ascontiguousarray(blocks.transpose(0, 2, 1), np.float32)


def box_plane_range(lo, hi, w) -> tuple[np.ndarray, np.ndarray]:
    """Exact range ``[min, max]`` of ``P . w`` over the 6-D boxes ``[lo, hi]`` (float64;
    broadcasts): the node test of the gather kernel, for tests and analysis."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    w = np.asarray(w, np.float64)
    a, b = w * lo, w * hi
    return np.minimum(a, b).sum(axis=-1), np.maximum(a, b).sum(axis=-1)


def plane_of(a, u, frame: PluckerFrame) -> np.ndarray:
    """The hyperplane coefficients ``w = (m, u)`` of lines (their Plücker coefficients in
    the paper's eq. 11, up to the permutation that matches :func:`plucker`)."""
    p = plucker(a, u, frame)
    return np.concatenate([p[:, 3:], p[:, :3]], axis=1)
