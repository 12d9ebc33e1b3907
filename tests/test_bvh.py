"""BVH: host build invariants, and the OpenCL traversal (cl_kernels/bvh.h) against a
float64 brute-force reference; watertightness on closed meshes; any-hit; edge cases."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from clscatter.accel.bvh import MAX_DEPTH, MAX_LEAF, build_bvh, trace

trimesh = pytest.importorskip("trimesh")

REPO = Path(__file__).resolve().parents[1]
COW_PATHS = [REPO / "tests" / "data" / "cow.obj", REPO / "models" / "cow.obj"]

BARY_EPS = 1e-4     # rays this close (barycentric units) to an edge may go either way
T_TOL = 1e-4        # hit distance tolerance (scenes are ~unit size, |d| = 1)


# ---------------------------------------------------------------------------------------
# meshes (all normalised: centred, longest side 1)

def _normalise(v: np.ndarray) -> np.ndarray:
    lo, hi = v.min(axis=0), v.max(axis=0)
    return (v - 0.5 * (lo + hi)) / (hi - lo).max()


def _f32(v: np.ndarray) -> np.ndarray:
    """Round to float32 (what the device sees) but keep float64 for the reference."""
    return np.asarray(v, np.float32).astype(np.float64)


def mesh_soup(n=600, seed=3):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-0.5, 0.5, (n, 1, 3))
    return _f32(c + rng.normal(scale=0.06, size=(n, 3, 3)))


def mesh_icosphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    return m


def mesh_box():
    return trimesh.creation.box(extents=(1.0, 1.0, 1.0))


def mesh_cow():
    for p in COW_PATHS:
        if p.is_file():
            m = trimesh.load(p, force="mesh", process=True)
            m.vertices = _normalise(np.asarray(m.vertices))
            return m
    raise FileNotFoundError(f"cow.obj not found in {[str(p) for p in COW_PATHS]}")


def tris_of(m) -> np.ndarray:
    return _f32(np.asarray(m.vertices)[np.asarray(m.faces)])


# ---------------------------------------------------------------------------------------
# float64 Moeller-Trumbore reference (vectorised, broadcasting)

def mt(o, d, v0, v1, v2):
    """t, u, v and the barycentric margin min(1-u-v, u, v) (-inf when det == 0)."""
    e1x, e1y, e1z = (v1 - v0)[..., 0], (v1 - v0)[..., 1], (v1 - v0)[..., 2]
    e2x, e2y, e2z = (v2 - v0)[..., 0], (v2 - v0)[..., 1], (v2 - v0)[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        sx, sy, sz = (o - v0)[..., 0], (o - v0)[..., 1], (o - v0)[..., 2]
        u = (sx * px + sy * py + sz * pz) * inv
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
        v = (dx * qx + dy * qy + dz * qz) * inv
        t = (e2x * qx + e2y * qy + e2z * qz) * inv
        margin = np.minimum(np.minimum(u, v), 1.0 - u - v)
    margin = np.where(det == 0.0, -np.inf, margin)
    return t, u, v, np.nan_to_num(margin, nan=-np.inf)


def reference(tris, o, d, tmin=0.0, tmax=np.inf, chunk_pairs=2_000_000):
    """Per ray: closest strict hit (t, tri) (margin > eps) and closest tolerant hit
    (margin > -eps)."""
    n, nt = len(o), len(tris)
    st, stri = np.full(n, np.inf), np.full(n, -1)
    tt = np.full(n, np.inf)
    if nt == 0:
        return st, stri, tt
    v0, v1, v2 = (tris[None, :, k, :] for k in range(3))
    step = max(1, chunk_pairs // nt)
    for a in range(0, n, step):
        b = min(n, a + step)
        t, _, _, mg = mt(o[a:b, None, :], d[a:b, None, :], v0, v1, v2)
        inr = (t > tmin) & (t < tmax)
        ts = np.where(inr & (mg > BARY_EPS), t, np.inf)
        tl = np.where(inr & (mg > -BARY_EPS), t, np.inf)
        j = np.argmin(ts, axis=1)
        st[a:b] = ts[np.arange(b - a), j]
        stri[a:b] = np.where(np.isfinite(st[a:b]), j, -1)
        tt[a:b] = tl.min(axis=1)
    return st, stri, tt


def check_against_reference(engine, tris, o, d, tmin=0.0, tmax=np.inf, bvh=None,
                            max_ambiguous=0.01):
    """Closest hits of the kernel vs the reference; returns the number of hits."""
    bvh = bvh or build_bvh(tris)
    t, tri, uv = trace(engine, bvh, o, d, tmin, tmax, uv=True)
    st, stri, tt = reference(tris, o, d, tmin, tmax)
    hit = tri >= 0
    assert np.array_equal(hit, np.isfinite(t))
    strict, tolerant = np.isfinite(st), np.isfinite(tt)
    missed = strict & ~hit
    assert not missed.any(), \
        f"{missed.sum()} rays miss a clear hit, e.g. rays {np.flatnonzero(missed)[:5]}"
    phantom = hit & ~tolerant
    assert not phantom.any(), \
        f"{phantom.sum()} phantom hits, e.g. rays {np.flatnonzero(phantom)[:5]}"
    ambiguous = (strict != tolerant) | (hit & (tri != stri))
    assert ambiguous.mean() <= max_ambiguous, f"{ambiguous.sum()} ambiguous rays"
    # the reported triangle is really hit at the reported distance, and nothing is closer
    hi = np.flatnonzero(hit)
    k = tri[hi]
    tp, up, vp, mp = mt(o[hi], d[hi], tris[k, 0], tris[k, 1], tris[k, 2])
    assert (mp > -BARY_EPS).all(), "reported triangle is not hit"
    np.testing.assert_allclose(t[hi], tp, rtol=0, atol=T_TOL)
    assert (t[hi] <= st[hi] + T_TOL).all(), "a closer hit was skipped"
    assert (t[hi] >= tt[hi] - T_TOL).all()
    # barycentrics: the point they give lies on the ray at t (float32 edge functions
    # lose relative accuracy on small far triangles, so compare positions, not u, v)
    u, v = uv[hi, 0:1].astype(np.float64), uv[hi, 1:2].astype(np.float64)
    p_uv = (1 - u - v) * tris[k, 0] + u * tris[k, 1] + v * tris[k, 2]
    p_ray = o[hi] + tp[:, None] * d[hi]
    assert np.abs(p_uv - p_ray).max() < T_TOL
    assert (u > -1e-3).all() and (v > -1e-3).all() and (u + v < 1 + 1e-3).all()
    return int(hit.sum())


def random_rays(n, seed, inside_frac=0.3, radius=1.5, tris=None):
    """Rays from a sphere around the scene towards points in it (half of them towards
    random points on ``tris`` when given), plus rays starting inside the scene box in
    random directions. Unit directions."""
    rng = np.random.default_rng(seed)
    n_in = int(n * inside_frac)
    n_out = n - n_in
    s = rng.normal(size=(n_out, 3))
    o_out = radius * s / np.linalg.norm(s, axis=1, keepdims=True)
    target = rng.uniform(-0.5, 0.5, (n_out, 3))
    if tris is not None and len(tris):
        k = n_out // 2
        w = rng.dirichlet(np.ones(3), k)
        target[:k] = np.einsum("nk,nkj->nj", w, tris[rng.integers(0, len(tris), k)])
    o_in = rng.uniform(-0.5, 0.5, (n_in, 3))
    d_in = rng.normal(size=(n_in, 3))
    o = np.concatenate([o_out, o_in])
    d = np.concatenate([target - o_out, d_in])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return _f32(o), _f32(d)


def axis_rays(n, seed):
    """Axis-aligned rays and rays with exactly one zero direction component."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(-0.6, 0.6, (n, 3))
    d = np.zeros((n, 3))
    ax = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    half = n // 2
    d[np.arange(half), ax[:half]] = sign[:half]                 # along an axis
    d[half:] = rng.normal(size=(n - half, 3))
    d[np.arange(half, n), ax[half:]] = 0.0                      # one component zero
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[np.arange(half, n), ax[half:]] = 0.0
    return _f32(o), _f32(d)


# ---------------------------------------------------------------------------------------
# structure

def check_structure(bvh, tris):
    nodes = bvh.nodes
    n = len(nodes)
    assert bvh.depth <= MAX_DEPTH
    T = len(tris)
    assert bvh.triangles.shape == (T, 3, 4) and bvh.triangles.dtype == np.float32
    assert np.array_equal(np.sort(bvh.order), np.arange(T))
    np.testing.assert_array_equal(bvh.triangles[:, :, :3], tris[bvh.order].astype(np.float32))
    assert (bvh.triangles[:, :, 3] == 0).all()
    # depth-first walk from the root: preorder visits nodes 0, 1, 2, ... exactly once
    seen = np.zeros(n, int)
    covered = np.zeros(T, int)
    expect = 0
    max_depth = 0
    stack = [(0, 0)]
    while stack:
        i, depth = stack.pop()
        assert i == expect, f"node {i} visited where {expect} was expected (not depth-first)"
        expect += 1
        seen[i] += 1
        max_depth = max(max_depth, depth)
        nd = nodes[i]
        lo, hi = nd["bmin"], nd["bmax"]
        if nd["count"] > 0:
            a, c = nd["left_first"], nd["count"]
            assert 0 <= a and a + c <= bvh.n_valid
            covered[a:a + c] += 1
            tv = bvh.triangles[a:a + c, :, :3]
            assert (tv >= lo).all() and (tv <= hi).all(), f"leaf {i} box misses a triangle"
        else:
            left, right = i + 1, int(nd["left_first"])
            assert left < right < n
            for ch in (left, right):
                assert (nodes[ch]["bmin"] >= lo).all() and (nodes[ch]["bmax"] <= hi).all(), \
                    f"child {ch} sticks out of parent {i}"
            stack.append((right, depth + 1))
            stack.append((left, depth + 1))
    assert expect == n and (seen == 1).all()
    assert max_depth == bvh.depth
    assert (covered[:bvh.n_valid] == 1).all(), "every usable triangle in exactly one leaf"
    assert (covered[bvh.n_valid:] == 0).all()
    return covered


@pytest.mark.parametrize("name", ["soup", "icosphere", "box", "cow", "coincident"])
def test_structure(name):
    if name == "soup":
        tris = mesh_soup(3000)
    elif name == "coincident":       # all centroids equal: median splits by index
        tris = np.repeat(mesh_soup(1), 100, axis=0)
    else:
        tris = tris_of({"icosphere": mesh_icosphere, "box": mesh_box, "cow": mesh_cow}[name]())
    bvh = build_bvh(tris)
    check_structure(bvh, tris)
    assert bvh.n_valid == len(tris)
    counts = bvh.nodes["count"][bvh.nodes["count"] > 0]
    assert counts.max() <= MAX_LEAF
    if name == "coincident":
        assert bvh.n_leaves > 1
    if len(tris) > 1000:              # SAH is doing its job: far cheaper than one leaf
        assert bvh.stats()["sah_cost"] < 0.05 * len(tris)


def test_leaf_size_and_bins_options():
    tris = mesh_soup(2000)
    for leaf_size, bins in [(1, 4), (8, 32), (2, 2)]:
        bvh = build_bvh(tris, leaf_size=leaf_size, bins=bins)
        check_structure(bvh, tris)


def test_depth_guard(engine, monkeypatch):
    """Exponentially spaced triangles give a deep, lopsided SAH tree (depth 43 here); with
    the depth limit lowered, the builder must switch to halving splits and stay below
    it (the same code keeps real trees below the kernel's 64-entry stack)."""
    import clscatter.accel.bvh as bvh_mod
    c = 1.2 ** np.arange(400)
    base = np.array([[1.0, 0, 0], [1.05, 0, 0], [1.0, 0.05, 0]])
    tris = _f32(base[None] * c[:, None, None])
    deep = build_bvh(tris, leaf_size=1)
    check_structure(deep, tris)
    assert deep.depth > 24
    monkeypatch.setattr(bvh_mod, "MAX_DEPTH", 16)
    bvh = build_bvh(tris, leaf_size=1)
    check_structure(bvh, tris)
    assert bvh.depth <= 15
    # and it still traces right: rays down onto the triangles (those up to 1e6: beyond,
    # the float32 edge-function products overflow; device scenes are unit-size)
    small = np.flatnonzero(c < 1e6)
    cen = tris[small].mean(axis=1)
    o = cen + np.array([0.0, 0.0, 1.0]) * c[small, None]
    d = np.tile([0.0, 0.0, -1.0], (len(small), 1))
    t, tri = trace(engine, bvh, o, d)
    np.testing.assert_array_equal(tri, small)
    np.testing.assert_allclose(t, c[small], rtol=1e-6)


def test_empty_and_degenerate_build():
    for tris in (np.zeros((0, 3, 3)), np.zeros((5, 3, 3)),
                 np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2]]], float)):
        bvh = build_bvh(tris)
        assert len(bvh) == 1 and bvh.nodes["count"][0] == 0
        assert (bvh.nodes["bmin"][0] > bvh.nodes["bmax"][0]).all()
        assert bvh.n_valid == 0 and len(bvh.order) == len(tris)
    with pytest.raises(ValueError):
        build_bvh(np.zeros((3, 3)))


def test_build_speed_100k():
    """The build is vectorised: the Python and C calls it makes (counted with
    ``sys.setprofile``, not timed) grow with the tree's depth, not the triangles or nodes
    (measured 3,333 calls for 12.5k triangles, 3,993 for 100k and 66k nodes; ~1 s)."""
    from call_count import count_calls

    def calls(n):
        rng = np.random.default_rng(0)
        c = rng.uniform(-0.5, 0.5, (n, 1, 3))
        return count_calls(build_bvh, c + rng.normal(scale=0.004, size=(n, 3, 3)))

    small, _ = calls(12_500)
    large, bvh = calls(100_000)
    assert large < 10_000 and large < 1.5 * small, (small, large)
    assert bvh.depth <= MAX_DEPTH and len(bvh) > 50_000


# ---------------------------------------------------------------------------------------
# kernel vs reference

@pytest.mark.parametrize("name,n", [("soup", 3000), ("icosphere", 3000), ("box", 3000),
                                    ("cow", 2000)])
def test_closest_hit_matches_reference(engine, name, n):
    tris = mesh_soup() if name == "soup" else tris_of(
        {"icosphere": mesh_icosphere, "box": mesh_box, "cow": mesh_cow}[name]())
    o, d = random_rays(n, seed=len(name), tris=tris)
    hits = check_against_reference(engine, tris, o, d)
    assert hits > 0.3 * n                # the test is not vacuous


@pytest.mark.parametrize("name", ["soup", "icosphere", "cow"])
def test_axis_aligned_rays(engine, name):
    tris = mesh_soup() if name == "soup" else tris_of(
        {"icosphere": mesh_icosphere, "cow": mesh_cow}[name]())
    o, d = axis_rays(2000, seed=7)
    hits = check_against_reference(engine, tris, o, d)
    assert hits > 100


def test_tmin_tmax_window(engine):
    tris = tris_of(mesh_icosphere())
    o, d = random_rays(2000, seed=11, inside_frac=0.0)
    check_against_reference(engine, tris, o, d, tmin=1.0, tmax=1.8)


def test_rays_from_inside_closed_mesh_always_hit(engine):
    tris = tris_of(mesh_icosphere())
    rng = np.random.default_rng(5)
    o = _f32(rng.uniform(-0.25, 0.25, (3000, 3)))
    d = _f32(rng.normal(size=(3000, 3)))
    t, tri = trace(engine, build_bvh(tris), o, d)
    assert (tri >= 0).all()
    assert np.isfinite(t).all()


# ---------------------------------------------------------------------------------------
# watertightness: rays through vertices and edges of closed meshes

def winding_number(q, tris):
    """Generalised winding number of points q (Q, 3) w.r.t. a closed mesh (float64)."""
    w = np.zeros(len(q))
    for i in range(0, len(q), 64):
        a, b, c = (tris[None, :, k, :] - q[i:i + 64, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        num = np.einsum("qtj,qtj->qt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("qtj,qtj->qt", a, b) * lc
               + np.einsum("qtj,qtj->qt", b, c) * la + np.einsum("qtj,qtj->qt", c, a) * lb)
        w[i:i + 64] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return w


def _targets(m, rng):
    """Vertices, edge midpoints and random edge points (float32-rounded), with normals."""
    v = _f32(m.vertices)
    vn = np.asarray(m.vertex_normals)
    edges = np.asarray(m.edges_unique)
    en = vn[edges].sum(axis=1)
    en /= np.linalg.norm(en, axis=1, keepdims=True)
    s = np.concatenate([np.full(len(edges), 0.5), rng.uniform(0.01, 0.99, len(edges))])
    e2 = np.concatenate([edges, edges])
    ep = _f32(v[e2[:, 0]] + s[:, None] * (v[e2[:, 1]] - v[e2[:, 0]]))
    return np.concatenate([v, ep]), np.concatenate([vn, en, en])


def _outside_rays(m, seed):
    """Convex meshes: rays from outside aimed exactly (up to float32 rounding of o and
    d) at vertices and edge points, against the normal tilted by < 25 degrees (inside
    the tangent cone even at a cube corner); plus axis-aligned rays through the targets
    (exact in float32). Each ray's first hit is its target: t = t_target."""
    rng = np.random.default_rng(seed)
    targets, normals = _targets(m, rng)
    tilt = rng.normal(size=normals.shape)
    tilt -= (tilt * normals).sum(1, keepdims=True) * normals
    tilt *= rng.uniform(0, np.tan(np.radians(25)), (len(tilt), 1)) / np.linalg.norm(
        tilt, axis=1, keepdims=True)
    inc = -(normals + tilt)
    inc /= np.linalg.norm(inc, axis=1, keepdims=True)
    dist = rng.uniform(0.3, 2.0, len(targets))
    o1 = _f32(targets - inc * dist[:, None])
    d1 = _f32(targets - o1)
    ax = np.argmax(np.abs(normals), axis=1)
    nax = normals[np.arange(len(normals)), ax]
    ok = np.abs(nax) > 0.6                                     # well inside the cone
    d2 = np.zeros_like(targets)
    d2[np.arange(len(d2)), ax] = -np.sign(nax)
    o2 = targets - 2.0 * d2
    return (np.concatenate([o1, o2[ok]]), np.concatenate([d1, d2[ok]]),
            np.concatenate([np.ones(len(o1)), np.full(ok.sum(), 2.0)]))


def _inside_rays(m, tris, seed, n_origins=300, max_targets=5000):
    """Rays from points inside the closed mesh (winding number 1) towards vertices and
    edge points, and axis-aligned rays from just inside through them (exact in float32):
    a ray from inside a closed surface must hit it, at or before its target."""
    rng = np.random.default_rng(seed)
    targets, normals = _targets(m, rng)
    if len(targets) > max_targets:     # the winding numbers below cost O(targets * tris)
        pick = rng.choice(len(targets), max_targets, replace=False)
        targets, normals = targets[pick], normals[pick]
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    cand = _f32(rng.uniform(lo, hi, (4 * n_origins, 3)))
    inner = cand[np.abs(winding_number(cand, tris)) > 0.99][:n_origins]
    assert len(inner) > 50
    o1 = inner[rng.integers(0, len(inner), len(targets))]
    d1 = _f32(targets - o1)
    # axis rays: origin 0.004 behind the target along the axis nearest the normal
    ax = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(normals)), ax])
    o2 = targets.copy()
    o2[np.arange(len(o2)), ax] -= 0.004 * sign
    o2 = _f32(o2)
    d2 = np.zeros_like(o2)
    d2[np.arange(len(d2)), ax] = sign
    keep = np.abs(winding_number(o2, tris)) > 0.99
    t2 = np.abs(targets - o2)[np.arange(len(o2)), ax]
    return (np.concatenate([o1, o2[keep]]), np.concatenate([d1, d2[keep]]),
            np.concatenate([np.ones(len(o1)), t2[keep]]))


@pytest.mark.parametrize("name", ["icosphere", "box"])
def test_watertight_from_outside_convex(engine, name):
    m = {"icosphere": mesh_icosphere, "box": mesh_box}[name]()
    assert m.is_watertight
    bvh = build_bvh(tris_of(m))
    o, d, t_target = _outside_rays(m, seed=1)
    t, tri = trace(engine, bvh, o, d)
    leaks = np.flatnonzero(tri < 0)
    assert len(leaks) == 0, f"{len(leaks)} of {len(o)} rays leak through the closed mesh"
    np.testing.assert_allclose(t, t_target, rtol=1e-5, atol=1e-6)
    for tt in (1.0, 2.0):
        sel = t_target == tt
        assert trace(engine, bvh, o[sel], d[sel], tmax=tt * 1.0001, closest=False).all()
        assert not trace(engine, bvh, o[sel], d[sel], tmax=tt * 0.9999, closest=False).any()


@pytest.mark.parametrize("name", ["icosphere", "box", "cow"])
def test_watertight_from_inside(engine, name):
    m = {"icosphere": mesh_icosphere, "box": mesh_box, "cow": mesh_cow}[name]()
    assert m.is_watertight
    tris = tris_of(m)
    bvh = build_bvh(tris)
    o, d, t_target = _inside_rays(m, tris, seed=2, max_targets=2500 if name == "cow" else 5000)
    t, tri = trace(engine, bvh, o, d)
    leaks = np.flatnonzero(tri < 0)
    assert len(leaks) == 0, f"{len(leaks)} of {len(o)} rays escape the closed mesh"
    # convex: the first hit is the target itself. (Not so on the cow: a ray from inside
    # can touch the surface at its target vertex without crossing it and go on.)
    if name != "cow":
        np.testing.assert_allclose(t, t_target, rtol=1e-5, atol=1e-6)
    assert trace(engine, bvh, o, d, closest=False).all()


def test_box_exact_corner_and_diagonal_rays(engine):
    """Rays exactly through box corners, edge midpoints and face diagonals (all exact in
    float32): the zero-edge-function case of the watertight test."""
    m = mesh_box()
    tris = tris_of(m)
    bvh = build_bvh(tris)
    corners = np.array(np.meshgrid([-.5, .5], [-.5, .5], [-.5, .5])).reshape(3, -1).T
    mids = np.array([[x, y, 0] for x in (-.5, .5) for y in (-.5, .5)]
                    + [[x, 0, z] for x in (-.5, .5) for z in (-.5, .5)]
                    + [[0, y, z] for y in (-.5, .5) for z in (-.5, .5)], float)
    pts = np.concatenate([corners, mids])
    o1, d1 = 3.0 * pts, -pts                       # through the point, then the centre
    # axis rays hitting both diagonals of every face at exact points
    s = np.array([-0.375, -0.25, -0.125, 0.0, 0.125, 0.25, 0.375])
    o2, d2 = [], []
    for ax in range(3):
        for sign in (-1.0, 1.0):
            for a in s:
                for b in (a, -a):
                    p = np.zeros(3)
                    p[ax] = 2.0 * sign
                    p[(ax + 1) % 3], p[(ax + 2) % 3] = a, b
                    q = np.zeros(3)
                    q[ax] = -sign
                    o2.append(p)
                    d2.append(q)
    o = np.concatenate([o1, np.array(o2)])
    d = np.concatenate([d1, np.array(d2)])
    t, tri = trace(engine, bvh, o, d)
    assert (tri >= 0).all(), f"leaks: {np.flatnonzero(tri < 0)}"
    np.testing.assert_allclose(t[:len(o1)], 2.0, rtol=1e-6)
    np.testing.assert_allclose(t[len(o1):], 1.5, rtol=1e-6)


# ---------------------------------------------------------------------------------------
# any-hit

@pytest.mark.parametrize("name", ["soup", "cow"])
def test_any_hit_agrees_with_closest(engine, name):
    tris = mesh_soup() if name == "soup" else tris_of(mesh_cow())
    bvh = build_bvh(tris)
    o, d = random_rays(3000, seed=21, tris=tris)
    t, tri = trace(engine, bvh, o, d)
    hit = tri >= 0
    assert hit.sum() > 500
    np.testing.assert_array_equal(trace(engine, bvh, o, d, closest=False), hit)
    # shadow rays: unnormalised d = light - o, tmax = 1, with the light at a fraction f
    # of the closest hit distance (occluded only when f > 1)
    ht = np.flatnonzero(hit)
    for f, expect in ((0.5, False), (0.999, False), (1.001, True), (2.0, True)):
        ds = d[ht] * (t[ht, None] * f)        # the closest hit is at t = 1 / f
        got = trace(engine, bvh, o[ht], ds, tmax=1.0, closest=False)
        assert (got == expect).all(), f"f = {f}: {np.sum(got != expect)} disagree"
    # a tmin beyond the closest hit: any-hit == closest-hit with the same window
    t2, tri2 = trace(engine, bvh, o, d, tmin=0.3, tmax=0.9)
    np.testing.assert_array_equal(trace(engine, bvh, o, d, 0.3, 0.9, closest=False), tri2 >= 0)


# ---------------------------------------------------------------------------------------
# empty and degenerate

def test_empty_bvh_all_miss(engine):
    o, d = random_rays(500, seed=2)
    for tris in (np.zeros((0, 3, 3)), np.zeros((4, 3, 3))):
        bvh = build_bvh(tris)
        t, tri = trace(engine, bvh, o, d)
        assert (tri == -1).all() and np.isinf(t).all()
        assert not trace(engine, bvh, o, d, closest=False).any()


def test_degenerate_triangles_never_hit(engine):
    rng = np.random.default_rng(8)
    good = mesh_soup(200, seed=9)
    # exactly degenerate in float32 (dyadic coordinates): points, collinear segments
    # (axis-aligned and oblique) and a repeated vertex
    pts = rng.integers(-512, 512, (100, 3)) / 1024.0
    dirs = rng.integers(-64, 64, (25, 3)) / 1024.0
    a = pts[:25, None, :].repeat(3, axis=1)
    b = pts[25:50, None, :] + np.array([0.0, 0.5, 1.0])[None, :, None] * dirs[:, None, :]
    c = pts[50:75, None, :] + np.array([0.0, 0.25, 1.0])[None, :, None] * np.array([0.125, 0, 0])
    e = np.stack([pts[75:], pts[75:] + 0.125, pts[75:]], axis=1)
    degen = np.concatenate([a, b, c, e])
    assert np.array_equal(_f32(degen), degen)
    tris = np.concatenate([good, degen])
    perm = rng.permutation(len(tris))
    tris = tris[perm]
    is_degen = perm >= len(good)
    bvh = build_bvh(tris)
    check_structure(bvh, tris)
    assert bvh.n_valid == len(good)
    assert is_degen[bvh.order[bvh.n_valid:]].all()
    # rays aimed at the degenerate triangles' vertices and midpoints, axis-aligned too
    tg = np.concatenate([degen[:, 0], degen[:, 1], degen.mean(axis=1)])
    o = _f32(tg + rng.normal(size=tg.shape))
    d = _f32(tg - o)
    oa = tg.copy()
    oa[:, 2] -= 2.0
    da = np.tile([0.0, 0.0, 1.0], (len(tg), 1))
    o, d = np.concatenate([o, oa]), np.concatenate([d, da])
    t, tri = trace(engine, bvh, o, d)
    assert not is_degen[tri[tri >= 0]].any()
    check_against_reference(engine, tris, o, d, bvh=bvh, max_ambiguous=0.05)


def test_single_triangle_and_rays_inside_boxes(engine):
    tri = _f32(np.array([[[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0]]]))
    bvh = build_bvh(tri)
    assert len(bvh) == 1 and bvh.nodes["count"][0] == 1
    # from the plane of the (flat) root box, along its normal, both directions
    o = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.5],
                  [0.9, 0.0, 0.5], [0.0, -0.5, 0.5], [0.0, 0.0, 0.5]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0],
                  [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t, tri_id = trace(engine, bvh, o, d)
    # origin on the triangle: t = 0 is not in (0, inf)
    np.testing.assert_array_equal(tri_id, [-1, 0, 0, -1, -1, 0, -1])
    np.testing.assert_allclose(t[[1, 2, 5]], 0.5)
