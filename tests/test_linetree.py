"""The line-space hierarchy (clscatter/estimators/line_tree.py): the perfect 8-ary tree's
structure, and the Plücker plane-query bound that its culling rests on."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.estimators.line_tree import (
    LINE_NODE,
    POINT_LANES,
    WALK_LEVELS,
    LineTree,
    PluckerFrame,
    box_plane_range,
    build_linetree,
    canonical_signs,
    child_rows,
    node_boxes,
    plane_of,
    plucker,
    point_block_array,
    point_blocks,
    tree_levels,
)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------
# tree structure
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [0, 3, 700, 5000])
def test_gather_layouts_hold_the_tree_and_points_exactly(n):
    """What the gather kernel reads side by side: child_rows puts the root at column 0 of
    block 0 (its other columns empty boxes) and the 6-D and 3-D boxes of node 8g+1+c at
    column c of block g + 1 (rows lo 6, hi 6, box lo 3, box hi 3); point_blocks puts point
    Lb+j at column j of block b (L = POINT_LANES, 8), zeros after the last."""
    rng = np.random.default_rng(n)
    pts = rng.normal(size=(n, 6)).astype(np.float32)
    t = build_linetree(pts, 16)
    ends = rng.normal(size=(2, 3, n))
    boxes = node_boxes(t, np.minimum(*ends), np.maximum(*ends))
    kids = child_rows(t, boxes)
    assert kids.dtype == np.float32 and kids.flags.c_contiguous
    assert kids.shape == (t.first_leaf + 1, 18, 8)

    def column_is(block, c, node):
        col = kids[block, :, c]
        np.testing.assert_array_equal(col[:6], t.nodes["lo"][node])
        np.testing.assert_array_equal(col[6:12], t.nodes["hi"][node])
        np.testing.assert_array_equal(col[12:15], boxes[node, 0, :3])
        np.testing.assert_array_equal(col[15:], boxes[node, 1, :3])

    column_is(0, 0, 0)
    assert (kids[0, :6, 1:] > kids[0, 6:12, 1:]).all()          # empty 6-D boxes
    assert (kids[0, 12:15, 1:] > kids[0, 15:, 1:]).all()        # empty 3-D boxes
    for g in {0, t.first_leaf - 1} if t.first_leaf else ():
        for c in range(8):
            column_is(g + 1, c, 8 * g + 1 + c)
    blocks = point_blocks(pts[t.order])
    L = POINT_LANES
    assert L == 8                                   # block_near's float8 rows
    assert blocks.shape == (max(1, -(-n // L)), 6, L) and blocks.flags.c_contiguous
    flat = blocks.transpose(0, 2, 1).reshape(-1, 6)
    np.testing.assert_array_equal(flat[:n], pts[t.order])
    assert not flat[n:].any()
    # written piece by piece (pieces starting at multiples of L): the same blocks
    pieces = point_block_array(n)
    for s in range(0, n, 2 * L):
        point_blocks(pts[t.order][s:s + 2 * L], pieces, s)
    np.testing.assert_array_equal(pieces, blocks)
    with pytest.raises(ValueError, match=f"multiple of {L}"):
        point_blocks(pts[:3], pieces, 4)


def test_a_tree_deeper_than_the_walk_is_refused():
    """The gather's walk keeps a stack of WALK_LEVELS levels: child_rows refuses a deeper
    tree instead of handing the kernel one it would walk past its stack."""
    deep = LineTree(np.zeros(1, LINE_NODE), np.zeros((1, 2), np.int32), np.zeros(0, np.int64),
                    WALK_LEVELS + 1)
    with pytest.raises(ValueError, match="levels"):
        child_rows(deep, np.zeros((1, 2, 4), np.float32))


@pytest.mark.parametrize("n, leaf", [(0, 4), (3, 4), (4, 4), (31, 4), (32, 4), (1000, 4),
                                     (255, 4), (4099, 4), (20000, 4), (5000, 16)])
def test_tree_is_a_balanced_perfect_8ary_tree(n, leaf):
    rng = np.random.default_rng(n)
    pts = (rng.normal(size=(n, 6)) * [1, 2, 3, 0.5, 1e-3, 10]).astype(np.float32)
    t = build_linetree(pts, leaf)
    L = tree_levels(n, leaf)
    assert t.levels == L
    assert len(t.nodes) == (8 ** (L + 1) - 1) // 7
    assert t.first_leaf == (8 ** L - 1) // 7 and len(t.leaf_ranges) == 8 ** L
    if n == 0:
        assert t.leaf_ranges.tolist() == [[0, 0]]     # one empty leaf
        return
    assert np.array_equal(np.sort(t.order), np.arange(n))
    sizes = t.leaf_ranges[:, 1] - t.leaf_ranges[:, 0]
    # leaves tile the sorted points; balanced: sizes differ by at most one
    assert t.leaf_ranges[0, 0] == 0 and t.leaf_ranges[-1, 1] == n
    assert np.array_equal(t.leaf_ranges[1:, 0], t.leaf_ranges[:-1, 1])
    assert sizes.max() - sizes.min() <= 1
    if n >= leaf:
        assert sizes.min() >= leaf and sizes.max() <= 8 * leaf
    # every point lies in its leaf's box; every box holds its 8 children's boxes
    sp = pts[t.order]
    leaf_of = np.repeat(np.arange(8 ** L), sizes)
    g = t.first_leaf + leaf_of
    assert np.all(sp >= t.nodes["lo"][g]) and np.all(sp <= t.nodes["hi"][g])
    if L:
        child = np.arange(1, len(t.nodes))
        parent = (child - 1) // 8
        assert np.all(t.nodes["lo"][child] >= t.nodes["lo"][parent])
        assert np.all(t.nodes["hi"][child] <= t.nodes["hi"][parent])
        # boxes are tight: the root box is exactly the points' bounds
        assert np.array_equal(t.nodes["lo"][0], pts.min(0))
        assert np.array_equal(t.nodes["hi"][0], pts.max(0))


def test_median_splits_separate_children_on_their_axis():
    """Each collapsed kd split put the lower half of the values below the upper half:
    two sibling leaves of one kd split do not overlap on the axis of largest extent of
    their union (checked for the last kd level, pairs of leaves 2j, 2j+1)."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, size=(8 ** 3 * 6, 6)).astype(np.float32)
    t = build_linetree(pts, 4)
    lo, hi = t.nodes["lo"][t.first_leaf:], t.nodes["hi"][t.first_leaf:]
    a, b = slice(0, None, 2), slice(1, None, 2)
    ulo, uhi = np.minimum(lo[a], lo[b]), np.maximum(hi[a], hi[b])
    axis = np.argmax(uhi - ulo, axis=1)
    k = np.arange(len(axis))
    assert np.all(hi[a][k, axis] <= lo[b][k, axis])
    # and they are a real partition: the split shrinks the extent on that axis
    assert np.mean((hi[a][k, axis] - lo[a][k, axis]) < 0.75 * (uhi - ulo)[k, axis]) > 0.9


def test_extra_coordinates_steer_the_splits_but_stay_out_of_the_boxes():
    """split_extra (lsg: where the segments start): 8 clusters far apart in the extra
    coordinates, and Plücker points spread alike in all of them. The first 8-ary level
    splits on the extra coordinates (each child holds one whole cluster), the boxes are
    those of the Plücker points alone (every point inside its leaf's box, the root's box
    their bounds), and without the extra coordinates the clusters mix."""
    rng = np.random.default_rng(9)
    n = 8 ** 3 * 4
    pts = rng.uniform(-1, 1, size=(n, 6)).astype(np.float32)
    cluster = rng.permutation(np.arange(n) % 8)
    corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) * 10
    extra = corners[cluster] + rng.uniform(-1, 1, size=(n, 3))
    t = build_linetree(pts, 4, extra)
    assert t.levels == 3 and t.nodes["lo"].shape == (len(t.nodes), 6)
    first = cluster[t.order].reshape(8, -1)             # the points of each level-1 node
    assert all(len(np.unique(row)) == 1 for row in first)
    assert sorted(first[:, 0]) == list(range(8))
    np.testing.assert_array_equal(t.nodes["lo"][0], pts.min(0))
    np.testing.assert_array_equal(t.nodes["hi"][0], pts.max(0))
    sp = pts[t.order]
    g = t.first_leaf + np.repeat(np.arange(8 ** 3), np.diff(t.leaf_ranges, axis=1)[:, 0])
    assert np.all(sp >= t.nodes["lo"][g]) and np.all(sp <= t.nodes["hi"][g])
    plain = cluster[build_linetree(pts, 4).order].reshape(8, -1)
    assert all(len(np.unique(row)) > 1 for row in plain)


def test_build_is_vectorised_and_quick_for_large_sets(monkeypatch):
    """200k points in a few kd levels with no per-point Python: the Python and C calls the
    build makes (counted with ``sys.setprofile``, not timed; all levels on one thread) grow
    with the levels, not the points or the nodes (measured 762 calls for 25k points, 943
    for 200k points and 37k nodes)."""
    from call_count import count_calls

    import clscatter.estimators.median_split as ms
    monkeypatch.setattr(ms, "PARALLEL_MIN_POINTS", 1 << 40)

    def calls(n):
        pts = np.random.default_rng(1).normal(size=(n, 6)).astype(np.float32)
        return count_calls(build_linetree, pts, 4)

    small, _ = calls(25_000)
    large, t = calls(200_000)
    assert large < 5_000 and large < 1.5 * small, (small, large)
    assert t.levels == 5          # 8^5 * 4 <= 200000 < 8^6 * 4


def test_subtrees_on_threads_build_the_same_tree(monkeypatch):
    """Above PARALLEL_MIN_POINTS the subtrees below kd level PARALLEL_LEVELS are built on
    threads: the same node boxes and leaf ranges as the build on one thread, and every
    leaf holds the same points (their order inside a leaf may differ)."""
    import clscatter.estimators.median_split as ms
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(20_000, 6)).astype(np.float32)
    extra = rng.uniform(-1, 1, (20_000, 3)).astype(np.float32)
    trees = {}
    for least in (1 << 40, 1000):
        monkeypatch.setattr(ms, "PARALLEL_MIN_POINTS", least)
        trees[least] = build_linetree(pts, 4, extra)
    one, many = trees[1 << 40], trees[1000]
    assert many.levels == one.levels == 4          # 8^4 * 4 <= 20000 < 8^5 * 4
    assert np.array_equal(one.nodes, many.nodes)
    assert np.array_equal(one.leaf_ranges, many.leaf_ranges)
    for a, b in one.leaf_ranges:
        assert set(one.order[a:b]) == set(many.order[a:b])
    assert np.array_equal(np.sort(many.order), np.arange(len(pts)))


def test_levels_split_node_by_node_put_each_lower_half_first(monkeypatch):
    """Above PARALLEL_LEVELS (from PARALLEL_MIN_POINTS points on) a level splits node by
    node (argpartition): at every kd level, each node's first child holds the node's
    smaller values on the recorded split axis (the largest extent of the node), the
    children hold the node's halves, and the build below is unchanged."""
    import clscatter.estimators.median_split as ms
    monkeypatch.setattr(ms, "PARALLEL_MIN_POINTS", 1000)
    rng = np.random.default_rng(11)
    n = 5000
    rows = (rng.normal(size=(4, n)) * [[1.0], [3.0], [0.5], [2.0]]).astype(np.float32)
    before = rows.copy()
    cur, order, axes = ms.median_levels(rows, 7)
    assert np.array_equal(rows, before)                 # the input rows are not changed
    assert np.array_equal(cur, rows[:, order]) and np.array_equal(np.sort(order), np.arange(n))
    assert [len(a) for a in axes] == [1 << k for k in range(7)]
    for k in range(7):
        starts = ms.level_starts(n, k).tolist() + [n]
        for j in range(1 << k):
            a, b = starts[j], starts[j + 1]
            mid = (2 * j + 1) * n >> (k + 1)
            node = rows[:, order[a:b]]
            ax = int(axes[k][j])
            assert ax == int(np.argmax(node.max(1).astype(np.float64) - node.min(1)))
            assert cur[ax, a:mid].max() <= cur[ax, mid:b].min()


# --------------------------------------------------------------------------------------
# Plücker coordinates and the plane-query bound
# --------------------------------------------------------------------------------------
SEEDS = {"random": 1, "near_parallel": 2, "near_intersecting": 3, "far": 4}


def _pairs_at_distance(rng, n, d, theta, centre_scale=1.0):
    """n line pairs with known distance d and angle theta: line 1 through p1 along u1,
    line 2 through p1 + d nrm along u2, nrm the common perpendicular."""
    p1 = rng.normal(size=(n, 3)) * centre_scale
    u1 = _unit(rng.normal(size=(n, 3)))
    nrm = _unit(np.cross(u1, rng.normal(size=(n, 3))))
    v = np.cross(nrm, u1)                              # unit, perpendicular to u1 and nrm
    th = np.broadcast_to(theta, (n,))[:, None]
    u2 = np.cos(th) * u1 + np.sin(th) * v
    p2 = p1 + np.broadcast_to(d, (n,))[:, None] * nrm
    # move the points along their lines: the Plücker point must not care
    p1 = p1 + rng.uniform(-3, 3, size=(n, 1)) * u1
    p2 = p2 + rng.uniform(-3, 3, size=(n, 1)) * u2
    return p1, u1, p2, u2


@pytest.mark.parametrize("kind", ["random", "near_parallel", "near_intersecting", "far"])
def test_side_product_is_distance_times_sine(kind):
    rng = np.random.default_rng(SEEDS[kind])
    n = 4000
    frame = PluckerFrame(np.array([0.3, -0.2, 0.1]), 1.7)
    d = rng.uniform(0, 0.05, n)
    theta = rng.uniform(0, np.pi, n)
    scale = 1.0
    if kind == "near_parallel":
        theta = 10.0 ** rng.uniform(-9, -2, n) * rng.choice([-1, 1], n) + rng.choice([0, np.pi], n)
    elif kind == "near_intersecting":
        d = 10.0 ** rng.uniform(-12, -4, n)
    elif kind == "far":
        scale = 1e3
    p1, u1, p2, u2 = _pairs_at_distance(rng, n, d, theta, scale)
    P = plucker(p1, u1, frame)
    W = plane_of(p2, u2, frame)
    side = np.einsum("ij,ij->i", P, W)
    expect = d / frame.scale * np.abs(np.sin(theta))
    tol = 2e-14 * (1 + scale / frame.scale)     # float64 rounding of terms of size |m|
    np.testing.assert_allclose(np.abs(side), expect, rtol=1e-9, atol=tol)
    # the sign of a line does not matter to the bound
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", -P, W)), np.abs(side), rtol=0, atol=0)


@pytest.mark.parametrize("kind", ["random", "near_parallel", "near_intersecting", "far"])
def test_plane_query_never_culls_a_line_within_r(kind):
    """Any 6-D box that holds the Plücker point of a line within r of the view line
    meets the slab |P . w| <= r' (r' = r / frame scale), for random boxes around the
    point: boxes of canonical-sign points included."""
    rng = np.random.default_rng(100 + SEEDS[kind])
    n = 3000
    r = 0.01
    frame = PluckerFrame(np.zeros(3), 0.5)
    theta = rng.uniform(0, np.pi, n)
    d = r * rng.uniform(0, 1, n) ** 0.5
    scale = 1.0
    if kind == "near_parallel":
        theta = 10.0 ** rng.uniform(-9, -3, n)
    elif kind == "near_intersecting":
        d = r * 10.0 ** rng.uniform(-12, -1, n)
    elif kind == "far":
        scale = 300.0
    p1, u1, p2, u2 = _pairs_at_distance(rng, n, d, theta, scale)
    P = plucker(p1, u1, frame) * canonical_signs(u1)[:, None]
    W = plane_of(p2, u2, frame)
    rr = r / frame.scale
    for _ in range(5):
        lo = P - rng.exponential(0.3, size=P.shape) * rng.integers(0, 2, size=P.shape)
        hi = P + rng.exponential(0.3, size=P.shape) * rng.integers(0, 2, size=P.shape)
        fmin, fmax = box_plane_range(lo, hi, W)
        slack = 1e-13 * (1 + scale / frame.scale)
        assert np.all(fmin <= rr + slack) and np.all(fmax >= -rr - slack)
    # and the bound is not vacuous: lines farther than r with sin(theta) ~ 1 are culled
    p1, u1, p2, u2 = _pairs_at_distance(rng, n, 3 * r, np.full(n, np.pi / 2), scale)
    P = plucker(p1, u1, frame)
    W = plane_of(p2, u2, frame)
    fmin, fmax = box_plane_range(P, P, W)
    assert np.all((fmin > rr) | (fmax < -rr))


def test_canonical_signs_follow_the_dominant_axis():
    u = _unit(np.array([[0.1, 0.9, 0.0], [0.2, -0.8, 0.1], [-0.3, 0.7, 0.2], [0.0, -1.0, 0.0]]))
    s = canonical_signs(u)
    assert np.all(s * u[:, 1] > 0)
