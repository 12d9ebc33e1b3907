"""Ray-map kd-tree and queries against brute force over every segment (NumPy, float64):
every intersection domain returns the same set, every K-nearest metric the same K, for
static, lazy, directional, LRU-collapsed and balanced trees alike; the K-th nearest end
point (the lazy refinement's reach) against NumPy and scipy."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.estimators.knn_queries import (
    RayMap,
    intersect,
    knn,
    knn_lists,
    knn_np,
    kth_end_distance,
    meets_np,
)
from clscatter.estimators.ray_density import lazy_radius
from clscatter.estimators.segment_tree import (
    DIRECTIONAL,
    LEAF,
    SegmentTree,
    TreeParams,
    _group_starts,
    leaf_ranges,
)


def _segments(n, seed=1):
    """Random segments in the unit cube: long and short, mostly falling downwards."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.5, 0.5, (n, 3))
    d = rng.normal(size=(n, 3))
    d[:, 1] = -np.abs(d[:, 1]) - 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    length = rng.exponential(0.15, n)
    b = a + length[:, None] * d
    return a, b, d


def _queries(q, seed=2):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.45, 0.45, (q, 3))
    n = rng.normal(size=(q, 3))
    n[:, 1] = np.abs(n[:, 1]) + 1.0          # roughly facing up: the rays come in
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return x, n


SMALL = TreeParams(c_min=8, r_min=1e-3, d_max=30, alpha_deg=10.0, dir_min_depth=3, dir_max_diag=0.6)


def test_static_tree_references_exactly_the_crossed_cells():
    a, b, d = _segments(600)
    t = SegmentTree(a, b, d, SMALL)
    t.build_static()
    assert t.n > 50
    t.check()
    counts = np.bincount(t.ref_node, minlength=t.n)
    leaves = t.kind[:t.n] == LEAF
    diag = np.linalg.norm(t.hi[:t.n] - t.lo[:t.n], axis=1)
    # every leaf stops for one of the paper's three criteria
    assert np.all((counts[leaves] <= 8) | (diag[leaves] <= 1e-3 * t.diag) | (t.depth[:t.n][leaves] >= 30))


@pytest.mark.parametrize("kind", ["disc", "hemisphere", "sphere", "box"])
def test_intersection_queries_match_brute_force(engine, kind):
    a, b, d = _segments(3000)
    x, n = _queries(200)
    r = np.random.default_rng(3).uniform(0.02, 0.12, len(x))
    if kind == "box":
        x, n = x - r[:, None], x + r[:, None] * np.array([1.0, 0.5, 2.0])
    results = []
    for lazy in (False, True):
        rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=lazy)
        results.append(intersect(rm, kind, x, n, r))
        if lazy:
            assert (rm.tree.kind[:rm.tree.n] == DIRECTIONAL).any() or kind in ("sphere", "box")
        rm.release()
    expect = [(q, s) for q in range(len(x)) for s in np.nonzero(meets_np(kind, x[q], n[q], r[q], a, b, d))[0]]
    expect = np.array(expect, np.int64).reshape(-1, 2)
    assert len(expect) > 3 * len(x)                         # the test has something to find
    for got in results:
        assert np.array_equal(got, expect)


@pytest.mark.parametrize("metric,domain,incoming", [
    ("segment", "none", False), ("hemidisc", "none", True), ("hemidisc", "hemisphere", True),
    ("plane", "sphere", True), ("line", "sphere", False), ("segment", "sphere", True)])
def test_knn_matches_brute_force(engine, metric, domain, incoming):
    a, b, d = _segments(3000)
    x, n = _queries(150)
    k, radius = 24, 0.15
    rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=True)
    idx, dist, work = knn(rm, x, n, k, metric, domain, radius, incoming, lazy_radius=0.05)
    rm.release()
    found = 0
    for q in range(len(x)):
        ei, ed = knn_np(metric, x[q], n[q], a, b, d, k, domain, radius, incoming)
        m = len(ei)
        found += m
        got = idx[q][idx[q] >= 0]
        assert len(got) == m
        # same distances (float32 vs float64) and the same segments up to near-ties
        assert np.allclose(dist[q, :m], ed, rtol=1e-4, atol=2e-6)
        kth = ed[-1] if m else 0.0
        sure = ed < kth - 1e-5
        assert set(ei[sure]) <= set(got)
    assert found > 0.8 * k * len(x)
    if metric in ("segment", "hemidisc"):
        # pruning works: far fewer references tested than segments
        assert work[:, 1].mean() < 0.25 * len(a)


def test_grouped_refinement_answers_as_per_query(engine, monkeypatch):
    """Coherent queries (a grid on a floor in row order, as a batch of diffuse hits comes)
    refine the lazy tree in groups of up to 16 of one grid cell: the K nearest are the same
    as with one query at a time (sorted distances equal), and the groups are formed."""
    import clscatter.estimators.knn_queries as kq
    a, b, d = _segments(4000, seed=5)
    gx, gz = np.meshgrid(np.linspace(-0.4, 0.4, 48), np.linspace(-0.4, 0.4, 12))
    x = np.stack([gx.ravel(), np.full(gx.size, -0.2), gz.ravel()], axis=1)
    n = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    out = {}
    for group in (1, 16):
        monkeypatch.setattr(kq, "REFINE_GROUP", group)
        rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=True)
        idx, dist, _ = knn(rm, x, n, 16, "hemidisc", "hemisphere", 0.2, True, lazy_radius=0.05)
        out[group] = (np.sort(dist, axis=1), rm.tree.n)
        rm.release()
    assert np.array_equal(out[1][0], out[16][0])
    assert (out[1][0] >= 0).sum() > 0.8 * 16 * len(x)
    starts = _group_starts(x, 0.1, 16)             # cells of 0.1: runs of 6 grid points
    assert len(x) / 7 < len(starts) < len(x) / 5
    assert np.array_equal(_group_starts(x[:40], 0.0, 16), [0, 16, 32])


def test_lru_bound_collapses_and_answers_unchanged(engine):
    """Batches of queries in different corners; a bound far below the full tree forces
    collapses of the least recently used subtrees; answers equal the static tree's."""
    a, b, d = _segments(4000, seed=5)
    x, n = _queries(400, seed=6)
    full = SegmentTree(a, b, d, SMALL)
    full.build_static()
    budget = full.nbytes // 3
    assert budget > len(a) * 4 * 2            # the root's references alone fit
    lru = TreeParams(**{**SMALL.__dict__, "max_bytes": budget})
    rm_lru = RayMap(engine, a, b, d, np.ones_like(a), lru, lazy=True)
    rm_static = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=False)
    order = np.argsort(x[:, 0])                 # sweep left to right: old regions go cold
    for batch in np.array_split(order, 8):
        i1, d1, _ = knn(rm_lru, x[batch], n[batch], 16, "hemidisc", "hemisphere", 0.2, True,
                        lazy_radius=0.08)
        i2, d2, _ = knn(rm_static, x[batch], n[batch], 16, "hemidisc", "hemisphere", 0.2, True)
        assert np.array_equal(i1, i2) and np.array_equal(d1, d2)
        assert rm_lru.tree.nbytes <= budget
    t = rm_lru.tree
    assert t.collapses > 0 and t.peak_bytes <= budget
    t.check()                                   # collapsed leaves hold their cells' segments
    rm_lru.release()
    rm_static.release()


def test_collapse_restores_the_unsplit_references():
    a, b, d = _segments(800, seed=7)
    t = SegmentTree(a, b, d, SMALL)
    t.build_static()
    refs_full, nodes_full = t.num_refs, t.n
    t.now += 1                                  # everything is older than "now" ...
    t.stamp[0] = t.now                          # ... but the root, reached by every query
    freed = t.collapse(10 ** 12)                # collapse all it can: the root's children
    assert freed > 0 and t.n == 3 and t.num_refs < refs_full and nodes_full > 3
    t.check()


def test_large_k_uses_global_heaps(engine):
    """K above 256 keeps its heaps in a global scratch buffer (RM_K = 1024): same answers."""
    a, b, d = _segments(3000, seed=8)
    x, n = _queries(40, seed=9)
    rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=True)
    idx, dist, _ = knn(rm, x, n, 300, "segment", "none", 0.0, False, lazy_radius=0.1)
    rm.release()
    for q in range(len(x)):
        ei, ed = knn_np("segment", x[q], n[q], a, b, d, 300)
        assert np.allclose(dist[q], ed, rtol=1e-4, atol=2e-6)
        assert set(ei[ed < ed[-1] - 1e-5]) <= set(idx[q])


@pytest.mark.parametrize("metric,domain,incoming", [
    ("hemidisc", "hemisphere", True), ("segment", "sphere", False), ("segment", "hemisphere", True),
    ("plane", "sphere", True), ("line", "hemisphere", False)])
@pytest.mark.parametrize("lazy", [True, False])
def test_knn_lists_match_brute_force_and_device_walk(engine, metric, domain, incoming, lazy):
    """Host-built candidate lists (knn_lists) give the brute-force K nearest and the
    device walk's, on lazy and static trees."""
    a, b, d = _segments(3000)
    x, n = _queries(150)
    k, radius = 24, 0.15
    rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=lazy)
    il, dl, wl = knn_lists(rm, x, n, k, metric, domain, radius, incoming, lazy_radius=0.05)
    it, dt, _ = knn(rm, x, n, k, metric, domain, radius, incoming, lazy_radius=0.05)
    rm.release()
    found = 0
    for q in range(len(x)):
        ei, ed = knn_np(metric, x[q], n[q], a, b, d, k, domain, radius, incoming)
        m = len(ei)
        found += m
        got = il[q][il[q] >= 0]
        assert len(got) == m and (it[q] >= 0).sum() == m
        assert np.allclose(dl[q, :m], ed, rtol=1e-4, atol=2e-6)
        assert np.allclose(dl[q, :m], dt[q, :m], rtol=1e-6, atol=1e-7)
        kth = ed[-1] if m else 0.0
        sure = ed < kth - 1e-5
        assert set(ei[sure]) <= set(got)
        assert set(got[dl[q, :m] < kth - 1e-5]) == set(it[q, :m][dt[q, :m] < kth - 1e-5])
    assert found > 0.8 * k * len(x)
    assert np.all(wl[:, 1] < len(a))                  # the lists are bounded by the domain


def test_knn_lists_k_above_candidates_and_no_domain(engine):
    """K larger than every query's candidate count: all qualifying segments, -1 after."""
    a, b, d = _segments(400, seed=11)
    x, n = _queries(60, seed=12)
    k, radius = 300, 0.08
    rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL, lazy=True)
    il, dl, wl = knn_lists(rm, x, n, k, "segment", "sphere", radius)
    assert wl[:, 1].max() < k
    for q in range(len(x)):
        ei, ed = knn_np("segment", x[q], n[q], a, b, d, k, "sphere", radius)
        assert len(ei) < k
        assert set(il[q][il[q] >= 0]) == set(ei)
        assert np.allclose(dl[q, :len(ei)], ed, rtol=1e-4, atol=2e-6)
        assert np.all(il[q, len(ei):] == -1) and np.all(np.isinf(dl[q, len(ei):]))
    with pytest.raises(ValueError):
        knn_lists(rm, x, n, 8, "segment", "none", 0.0)
    rm.release()


# ---- the one tree: balanced point trees and the lazy refinement's reach ----
def test_balanced_tree_invariants_and_rm_node_queries(engine):
    """A balanced tree over points (vpm's photons, the ray map's end points) holds every
    point once, in a leaf whose box contains it, and exported as RMNode records it answers
    the photon map's K-nearest queries exactly like the spatial tree (brute force)."""
    rng = np.random.default_rng(21)
    p = rng.uniform(-0.5, 0.5, (5000, 3))
    p[:800, 1] = 0.1                                    # ties along one axis
    for n_pts, leaf in ((0, 8), (5, 8), (5000, 8), (5000, 1)):
        t = SegmentTree.balanced(p[:n_pts], leaf)
        assert t.n == 2 ** (t.levels + 1) - 1
        if n_pts:
            assert np.diff(leaf_ranges(n_pts, t.levels)).min() >= min(leaf, n_pts)
        t.check()
    a, b, d = _segments(3000, seed=22)
    x, n = _queries(80, seed=23)
    rm = RayMap(engine, b, b, d, np.ones_like(a), SMALL, points=True, lazy=False)
    rm.tree = SegmentTree.balanced(b, 8)                # the balanced tree in RMNode form
    idx, dist, _ = knn(rm, x, n, 16, "segment", "sphere", 0.2, True)
    rm.release()
    for q in range(len(x)):
        ei, ed = knn_np("segment", x[q], n[q], b, b, d, 16, "sphere", 0.2, True)
        assert np.allclose(dist[q, :len(ei)], ed, rtol=1e-4, atol=2e-6)
        assert set(ei[ed < ed[-1] - 1e-5]) <= set(idx[q]) if len(ei) else (idx[q] == -1).all()


def test_balanced_tree_on_threads_is_the_same_tree(monkeypatch):
    """The balanced point tree shares the line tree's median splits (median_split): built
    with its subtrees on threads it has the same boxes, split axes and leaf point sets as
    built on one thread."""
    import clscatter.estimators.median_split as ms
    p = np.random.default_rng(26).uniform(-0.5, 0.5, (20_000, 3)).astype(np.float32)
    trees = {}
    for least in (1 << 40, 1000):
        monkeypatch.setattr(ms, "PARALLEL_MIN_POINTS", least)
        trees[least] = SegmentTree.balanced(p, 8)
    one, many = trees[1 << 40], trees[1000]
    assert one.levels == many.levels == 11
    n = one.n
    assert np.array_equal(one.lo[:n], many.lo[:n]) and np.array_equal(one.hi[:n], many.hi[:n])
    assert np.array_equal(one.axis[:n], many.axis[:n])
    r = leaf_ranges(len(p), one.levels)
    for a, b in zip(r[:-1], r[1:]):
        assert set(one.order[a:b]) == set(many.order[a:b])
    many.check()


@pytest.mark.parametrize("k", [1, 24, 300])
def test_kth_end_distance_matches_brute_force(engine, k):
    """rm_kth_end (the balanced point tree's k-nearest query over the segments' end points)
    against NumPy: the k-th nearest end point's float64 distance where k lie within reach,
    inf elsewhere (K = 300: the global heaps)."""
    a, b, d = _segments(4000, seed=24)
    x, _ = _queries(300, seed=25)
    dist = np.sort(np.linalg.norm(x[:, None, :] - b[None, :, :], axis=2), axis=1)[:, k - 1]
    reach = float(np.median(dist))                     # half the queries find k in reach
    rm = RayMap(engine, a, b, d, np.ones_like(a), SMALL)
    got = kth_end_distance(rm, x, k, reach)
    rm.release()
    want = np.where(dist < reach, dist, np.inf)
    clear = np.abs(dist - reach) > 1e-5 * reach        # float32 at the boundary aside
    assert clear.mean() > 0.99 and np.isfinite(want).mean() > 0.2 and np.isinf(want).any()
    assert np.array_equal(got[clear], want[clear])


def test_lazy_radius_is_the_kth_end_point_distance(engine):
    """The lazy refinement's reach: 1.01 x the K-th nearest end point's distance, at most
    max_radius, as scipy's point kd-tree gives it (also with fewer end points than K)."""
    from scipy.spatial import cKDTree
    a, b, d = _segments(3000, seed=26)
    x, _ = _queries(400, seed=27)
    below = []
    for m, k, max_r in ((3000, 32, 0.15), (3000, 8, 0.5), (20, 32, 0.6)):
        rm = RayMap(engine, a[:m], b[:m], d[:m], np.ones((m, 3)), SMALL)
        got = lazy_radius(rm, x, k, max_r)
        rm.release()
        dist, _ = cKDTree(b[:m]).query(x, k=[min(k, m)])
        want = np.minimum(dist[:, 0] * 1.01, max_r)
        assert np.allclose(got, want, rtol=1e-12, atol=0)
        below.append((got < max_r).mean())
    assert 0 < below[0] < 1 and below[1] == 1 and below[2] == 0     # every regime
