"""Tile grid (clscatter/accel/tile_grid.py, cl_kernels/tile_grid.h): the host binning
against a float64 point-in-triangle reference, the grid_hit kernel against the BVH for
rays along the grid's direction (an orthographic grid tests its triangles projected once
on the host: the same hits, distances to float rounding) or from its origin (a
perspective grid runs the BVH's own test: the same bits), and the shadow maps traced
both ways."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.accel import tile_grid
from clscatter.accel.bvh import build_bvh, trace
from clscatter.device import structs
from clscatter.geometry import perpendicular_axes

trimesh = pytest.importorskip("trimesh")

DIR = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])


S1, S2 = perpendicular_axes(DIR)


def _soup(seed=5, n=300):
    """Random small and large triangles, and some seen edge-on (a vertex moved only along
    the grid's direction) or nearly so, in [-0.6, 0.6]^3."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-0.5, 0.5, (n, 1, 3))
    tris = c + rng.normal(scale=0.05, size=(n, 3, 3))
    big = rng.uniform(-0.6, 0.6, (20, 3, 3))
    edge_on = c[:30] + rng.normal(scale=0.08, size=(30, 3, 3))
    edge_on[:, 2] = edge_on[:, 0] + rng.uniform(0.05, 0.3, (30, 1)) * DIR
    near_edge_on = edge_on[:10].copy()
    near_edge_on[:, 2] += 1e-6 * S1
    return np.concatenate([tris, big, edge_on, near_edge_on]).astype(np.float32)


def _grid(bvh, n=24, rect=(-0.7, -0.7, 0.7, 0.7)):
    return tile_grid.build_grid(bvh, np.zeros(3), S1, S2, DIR, rect, n, n)


def _projected(bvh):
    v = bvh.triangles[: bvh.n_valid, :, :3].astype(np.float64)
    return v @ S1, v @ S2, v @ DIR


def _inside(p1, p2, x, y):
    """(points, triangles) containment of 2-D points in projected triangles, float64,
    edges included."""
    e = []
    for k in range(3):
        a1, a2 = p1[:, k], p2[:, k]
        b1, b2 = p1[:, (k + 1) % 3], p2[:, (k + 1) % 3]
        e.append((b1 - a1)[None] * (y[:, None] - a2[None]) - (b2 - a2)[None] * (x[:, None] - a1[None]))
    e = np.stack(e)
    return (e >= 0).all(axis=0) | (e <= 0).all(axis=0)


def test_every_covering_triangle_is_listed_in_sorted_order():
    bvh = build_bvh(_soup())
    n = 24
    grid = _grid(bvh, n)
    p1, p2, z = _projected(bvh)
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.7, 0.7, 4000)
    y = rng.uniform(-0.7, 0.7, 4000)
    # and points on tile borders and corners
    edges = -0.7 + 1.4 * np.arange(n + 1) / n
    x = np.concatenate([x, np.repeat(edges[:-1], n), rng.uniform(-0.7, 0.7, n * n)])
    y = np.concatenate([y, np.tile(edges[:-1], n), np.repeat(edges[:-1], n)])
    cover = _inside(p1, p2, x, y)
    tx = np.minimum(((x + 0.7) / 1.4 * n).astype(int), n - 1)
    ty = np.minimum(((y + 0.7) / 1.4 * n).astype(int), n - 1)
    missing = 0
    for i in np.nonzero(cover.any(axis=1))[0]:
        t = ty[i] * n + tx[i]
        listed = set(grid.items[grid.starts[t]:grid.starts[t + 1]].tolist())
        missing += len(set(np.nonzero(cover[i])[0].tolist()) - listed)
    assert missing == 0
    # near keys: sorted within each tile, never beyond a vertex of their triangle; no
    # triangle twice in a tile
    for t in range(n * n):
        k = grid.keys[grid.starts[t]:grid.starts[t + 1]]
        assert np.all(np.diff(k) >= 0)
        listed = grid.items[grid.starts[t]:grid.starts[t + 1]]
        assert len(np.unique(listed)) == len(listed)
    assert np.all(grid.keys <= z.min(axis=1)[grid.items])
    assert grid.record["items"] == len(grid.items) == grid.starts[-1]


def test_tiles_sort_first_whatever_the_keys():
    """Keys all positive and equal (a plane facing the rays): the lists are still grouped
    by tile, each triangle in the tiles it covers once."""
    quad = np.array([[[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5]], [[-0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]])
    pos = quad[..., :1] * S1 + quad[..., 1:] * S2 + 0.7 * DIR
    grid = _grid(build_bvh(pos.astype(np.float32)), 8)
    assert np.ptp(grid.keys) == 0 and grid.keys[0] > 0
    bvh = build_bvh(pos.astype(np.float32))
    p1, p2, _ = _projected(bvh)
    c = -0.7 + 1.4 * (np.arange(8) + 0.5) / 8                 # tile centres
    cx, cy = np.meshgrid(c, c)
    cover = _inside(p1, p2, cx.ravel(), cy.ravel())           # (tiles, triangles)
    for t in range(64):
        listed = grid.items[grid.starts[t]:grid.starts[t + 1]]
        assert len(np.unique(listed)) == len(listed)
        assert set(np.nonzero(cover[t])[0].tolist()) <= set(listed.tolist())
        # and nothing from far away: every listed triangle's box reaches the tile
        for i in listed:
            assert p1[i].min() <= c[t % 8] + 0.1 and p1[i].max() >= c[t % 8] - 0.1
            assert p2[i].min() <= c[t // 8] + 0.1 and p2[i].max() >= c[t // 8] - 0.1


def test_lists_are_tight():
    """Exact row-by-row binning: a triangle seen edge-on (a segment) is listed along its
    line only, and a large triangle in no more tiles than its area plus a border."""
    n = 64
    seg = np.array([[[-0.5, 0, 0], [0.5, 0, 0], [0.5, 0, 0]]], np.float64)
    seg[0, 2] += 0.3 * DIR
    seg = seg - (seg[0, 0] @ S2) * S2 + 0.013 * S2        # off tile borders
    bvh = build_bvh(seg.astype(np.float32))
    grid = _grid(bvh, n)
    # the segment spans 1.0 / 1.4 of the rectangle's width in a direction oblique to s1
    assert 0 < len(grid.items) <= 3 * n
    big = np.array([[[-0.7, -0.7, 0], [0.7, -0.7, 0], [-0.7, 0.7, 0]]]) @ np.stack([S1, S2, DIR])
    grid = _grid(build_bvh(big.astype(np.float32)), n)
    assert n * n / 2 <= len(grid.items) <= n * n / 2 + 2 * n


def test_grid_hits_equal_the_bvh(engine):
    bvh = build_bvh(_soup())
    grid = _grid(bvh)
    rng = np.random.default_rng(2)
    m = 20000
    o = rng.uniform(-0.7, 0.7, (m, 1)) * S1 + rng.uniform(-0.7, 0.7, (m, 1)) * S2 - 1.5 * DIR
    t_bvh, tri_bvh = trace(engine, bvh, o, np.tile(DIR, (m, 1)))
    t_grid, slot = tile_grid.trace_grid(engine, bvh, grid, o)
    assert np.mean(np.isfinite(t_bvh)) > 0.3           # the rays do meet the soup
    assert np.array_equal(np.isfinite(t_grid), np.isfinite(t_bvh))
    hit = np.isfinite(t_bvh)
    # the same watertight test, its projection done once on the host: the distances
    # agree to float rounding, which the soup's near-edge-on slivers amplify in both
    # (a steep depth across a thin projected triangle: measured against float64, at
    # most 1.1e-5 relative through the grid and 3.6e-6 through the BVH, medians 4e-8)
    np.testing.assert_allclose(t_grid[hit], t_bvh[hit], rtol=2e-5)
    assert np.median(np.abs(t_grid[hit] / t_bvh[hit] - 1.0)) < 2e-7
    # any hit, and a window that starts inside the soup
    any_grid = tile_grid.trace_grid(engine, bvh, grid, o, tmin=1.2, tmax=1.9, any_hit=True)
    any_bvh = trace(engine, bvh, o, np.tile(DIR, (m, 1)), tmin=1.2, tmax=1.9, closest=False)
    assert np.array_equal(any_grid, any_bvh)
    t_win, _ = tile_grid.trace_grid(engine, bvh, grid, o, tmin=1.2, tmax=1.9)
    t_ref, _ = trace(engine, bvh, o, np.tile(DIR, (m, 1)), tmin=1.2, tmax=1.9)
    np.testing.assert_allclose(t_win, t_ref, rtol=2e-5)


def test_big_orthographic_grids_run_the_bvh_test(engine, monkeypatch):
    """Past MAX_RASTER triangles an orthographic grid stores no projection and its rays
    run the BVH's own test: the BVH's distances to the bit."""
    monkeypatch.setattr(tile_grid, "MAX_RASTER", 10)
    bvh = build_bvh(_soup())
    grid = _grid(bvh)
    assert grid.raster is None and grid.packed()[:tile_grid.HEAD_WORDS].view(
        tile_grid.TILE_GRID)["raster_at"] == 0
    rng = np.random.default_rng(3)
    m = 5000
    o = rng.uniform(-0.7, 0.7, (m, 1)) * S1 + rng.uniform(-0.7, 0.7, (m, 1)) * S2 - 1.5 * DIR
    t_bvh, _ = trace(engine, bvh, o, np.tile(DIR, (m, 1)))
    t_grid, _ = tile_grid.trace_grid(engine, bvh, grid, o)
    hit = np.isfinite(t_bvh)
    assert hit.mean() > 0.3 and np.array_equal(np.isfinite(t_grid), hit)
    assert np.mean(t_grid[hit] == t_bvh[hit]) > 0.999


def test_perspective_grid_hits_equal_the_bvh(engine):
    """Rays from one origin (a camera) through a perspective grid: the soup in front, a
    floor that passes behind the origin (listed everywhere) and triangles wholly behind it
    (listed nowhere)."""
    eye = -1.2 * DIR
    floor = np.array([[[-3, -3], [3, -3], [3, 3]], [[-3, -3], [3, 3], [-3, 3]]], np.float64)
    floor = floor[..., :1] * DIR + floor[..., 1:] * S1 - 0.55 * S2
    behind = _soup(seed=9, n=40)[:40].astype(np.float64) - 2.5 * DIR
    bvh = build_bvh(np.concatenate([_soup(), floor, behind]).astype(np.float32))
    half = np.tan(np.radians(35.0))
    grid = tile_grid.build_grid(bvh, eye, S1, S2, DIR, (-half, -half, half, half), 16, 16,
                                perspective=True)
    rng = np.random.default_rng(4)
    m = 20000
    tan = rng.uniform(-half, half, (m, 2))
    d = DIR + tan[:, :1] * S1 + tan[:, 1:] * S2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    t_grid, _ = tile_grid.trace_grid(engine, bvh, grid, o, dirs=d)
    t_bvh, _ = trace(engine, bvh, o, d)
    assert not np.isnan(t_grid).any()
    assert np.array_equal(np.isfinite(t_grid), np.isfinite(t_bvh))
    hit = np.isfinite(t_bvh)
    assert 0.3 < hit.mean() < 1.0
    np.testing.assert_allclose(t_grid[hit], t_bvh[hit], rtol=1e-6)
    # outside the field of view, or backwards: no tile
    t_out, slot = tile_grid.trace_grid(engine, bvh, grid, eye[None].repeat(2, 0),
                                       dirs=np.stack([S1, -DIR]))
    assert np.isnan(t_out).all() and (slot == -2).all()


def test_walls_around_the_origin_are_clipped_not_listed_everywhere(engine):
    """A camera inside a box room: the walls beside and behind it cross the plane through
    the camera, are clipped to their part in front and listed only where that part
    projects (a room needs ~2 triangles per tile, not all 12), and every ray still hits
    what the BVH hits. A wall through the camera itself stays listed everywhere."""
    box = trimesh.creation.box(extents=[2.0, 1.6, 3.0])
    room = box.vertices[box.faces]
    eye = np.array([0.3, -0.2, 0.4])
    bvh = build_bvh(room.astype(np.float32))
    half = np.tan(np.radians(40.0))
    grid = tile_grid.build_grid(bvh, eye, S1, S2, DIR, (-half, -half, half, half), 16, 16,
                                perspective=True)
    assert grid.mean_list < 4.0
    rng = np.random.default_rng(12)
    tan = rng.uniform(-half, half, (20000, 2))
    d = DIR + tan[:, :1] * S1 + tan[:, 1:] * S2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape)
    t_grid, _ = tile_grid.trace_grid(engine, bvh, grid, o, dirs=d)
    t_bvh, _ = trace(engine, bvh, o, d)
    assert np.all(np.isfinite(t_bvh))                      # closed room: every ray hits
    np.testing.assert_allclose(t_grid, t_bvh, rtol=1e-6)
    # a wall plane through the camera: that wall's triangles in every tile
    flat = tile_grid.build_grid(bvh, np.array([1.0, 0.1, 0.2]), S1, S2, DIR,
                                (-half, -half, half, half), 16, 16, perspective=True)
    counts = np.bincount(flat.items, minlength=bvh.n_valid)
    assert counts.max() == 16 * 16


def test_shadow_rays_towards_a_spot_light_equal_the_bvh(engine):
    """Rays from points of the soup's space (and of the surfaces: points on triangles)
    to a light at the grid's origin: blocked exactly where the BVH says, with the same
    (tmin, (1 - 1e-5) dist) window; points outside the cone's grid report -1."""
    light = -1.3 * DIR
    bvh = build_bvh(_soup())
    half = np.tan(np.radians(40.0))
    grid = tile_grid.build_grid(bvh, light, S1, S2, DIR, (-half, -half, half, half), 24, 24,
                                perspective=True)
    rng = np.random.default_rng(8)
    pts = rng.uniform(-0.7, 0.7, (30000, 3))
    v = bvh.triangles[: bvh.n_valid, :, :3].astype(np.float64)
    w = rng.dirichlet(np.ones(3), 5000)
    on = np.einsum("nk,nkc->nc", w, v[rng.integers(0, len(v), 5000)])
    pts = np.concatenate([pts, on + 1e-4 * rng.normal(size=on.shape)])
    got = tile_grid.trace_toward(engine, bvh, grid, pts, tmin=1e-6)
    to = light - pts
    dist = np.linalg.norm(to, axis=1)
    inside = got >= 0
    rel = to / dist[:, None]
    assert inside.mean() > 0.5
    ref = trace(engine, bvh, pts[inside], rel[inside], tmin=1e-6)[0]
    blocked = ref < (dist[inside] * (1 - 1e-5)).astype(np.float32)
    assert 0.2 < blocked.mean() < 0.95
    assert np.array_equal(got[inside] == 1, blocked)
    # outside the cone's rectangle: -1
    cosang = -(rel @ DIR)
    tan_off = np.sqrt(np.maximum(1 - cosang ** 2, 0)) / np.maximum(cosang, 1e-9)
    assert np.all(got[(cosang > 0) & (tan_off > 1.5 * half)] == -1)


def test_shadow_rays_towards_a_point_light_through_its_cube(engine):
    """A point light inside the soup: six face grids, every point in one of them (none
    reports -1), blocked exactly where the BVH says; cube edges and corners included."""
    light = np.array([0.05, -0.02, 0.03])
    bvh = build_bvh(_soup())
    lights = np.zeros(1, structs.LIGHT)
    lights[0]["type"] = structs.LIGHT_POINT
    lights[0]["position"] = structs.vec4(light)
    cube = tile_grid.light_grid(bvh, lights)
    assert isinstance(cube, tile_grid.CubeGrid) and len(cube.faces) == 6
    assert cube.packed()[:tile_grid.HEAD_WORDS].view(tile_grid.TILE_GRID)["faces"] == 6
    rng = np.random.default_rng(11)
    pts = rng.uniform(-0.8, 0.8, (30000, 3))
    diag = light + np.array([[1, 1, 0], [1, -1, 1], [-1, -1, -1], [0, 1, -1]]) * 0.4
    pts = np.concatenate([pts, diag])
    got = tile_grid.trace_toward(engine, bvh, cube, pts, tmin=1e-6)
    assert np.all(got >= 0)
    to = light - pts
    dist = np.linalg.norm(to, axis=1)
    t, _ = trace(engine, bvh, pts, to / dist[:, None], tmin=1e-6)
    blocked = t < (dist * (1 - 1e-5)).astype(np.float32)
    assert 0.2 < blocked.mean() < 0.95
    assert np.array_equal(got == 1, blocked)


def test_a_point_light_far_above_a_ball(engine):
    """A ball on the axis of a far point light's cube (a scene that once crashed every
    method): for the four side faces the ball lies in front of the light
    by less than the clipping distance, with nothing left to project; it is left out
    there (no ray of those faces meets it; it was projected through a zero depth), the
    build raises no floating-point warning, and shadow rays through the cube are blocked exactly where the BVH says."""
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.45)
    floor = np.array([[[-3, 0, -3], [3, 0, -3], [3, 0, 3]], [[-3, 0, -3], [3, 0, 3], [-3, 0, 3]]])
    tris = np.concatenate([ball.vertices[ball.faces] + [0.0, 1.7, 0.0], floor])
    bvh = build_bvh(tris.astype(np.float32))
    for height in (300.0, 1e4):
        lights = np.zeros(1, structs.LIGHT)
        lights[0]["type"] = structs.LIGHT_POINT
        lights[0]["position"] = structs.vec4([0.0, height, 0.0])
        with np.errstate(all="raise"):
            cube = tile_grid.light_grid(bvh, lights)
        assert isinstance(cube, tile_grid.CubeGrid)
        down = cube.faces[3]                     # axis y, negative side: towards the ball
        assert down.record["items"] >= len(ball.faces)
        if height == 300.0:     # at 1e4 the clipping distance (1e-4 of it) exceeds the
            # ball's radius: its side facets' planes pass that close, so they are listed
            # everywhere on the side faces (a superset; the rays below still agree)
            assert all(f.record["items"] == 0 for k, f in enumerate(cube.faces) if k != 3)
        rng = np.random.default_rng(4)
        pts = np.concatenate([rng.uniform([-2, 0, -2], [2, 0, 2], (20000, 3)),
                              rng.uniform([-1, 0.5, -1], [1, 3, 1], (5000, 3))])
        got = tile_grid.trace_toward(engine, bvh, cube, pts, tmin=1e-6)
        assert np.all(got >= 0)
        to = np.array([0.0, height, 0.0]) - pts
        dist = np.linalg.norm(to, axis=1)
        t, _ = trace(engine, bvh, pts, to / dist[:, None], tmin=1e-6)
        blocked = t < (dist * (1 - 1e-5)).astype(np.float32)
        assert 0.01 < blocked.mean() < 0.5
        assert np.array_equal(got == 1, blocked)


def test_watertight_through_shared_edges_and_vertices(engine):
    """A plane tessellated into grid-aligned quads: rays through its vertices and along
    its edges (on tile borders too) all hit, as with the BVH."""
    k = 16
    u = np.linspace(-0.6, 0.6, k + 1)
    tris = []
    for i in range(k):
        for j in range(k):
            a, b, c, d = ((u[i], u[j]), (u[i + 1], u[j]), (u[i + 1], u[j + 1]), (u[i], u[j + 1]))
            tris += [(a, b, c), (a, c, d)]
    tris = np.array(tris, np.float64)                       # (T, 3, 2) plane coordinates
    pos = tris[..., :1] * S1 + tris[..., 1:] * S2 + 0.2 * DIR
    bvh = build_bvh(pos.astype(np.float32))
    grid = tile_grid.build_grid(bvh, np.zeros(3), S1, S2, DIR, (-0.6, -0.6, 0.6, 0.6), 8, 8)
    g = np.linspace(-0.6, 0.6, 2 * k + 1)[1:-1]               # vertices and edge midpoints
    x, y = np.meshgrid(g, g)
    o = x.reshape(-1, 1) * S1 + y.reshape(-1, 1) * S2 - DIR
    t, _ = tile_grid.trace_grid(engine, bvh, grid, o)
    assert np.all(np.isfinite(t))
    np.testing.assert_allclose(t, 1.2, rtol=1e-5)
    # and densely along every quad's diagonal (shared by its two triangles): on or
    # within rounding of the edge, never between them
    s = (np.arange(1, 40) / 40.0)[None, :, None]
    a, c = tris[::2, 0][:, None, :], tris[::2, 2][:, None, :]
    p = (a + s * (c - a)).reshape(-1, 2)
    o = p[:, :1] * S1 + p[:, 1:] * S2 - DIR
    t, _ = tile_grid.trace_grid(engine, bvh, grid, o)
    assert np.all(np.isfinite(t)), int(np.sum(~np.isfinite(t)))


def test_outside_and_empty_grids(engine):
    bvh = build_bvh(_soup())
    grid = _grid(bvh)
    o = np.array([[2.0, 2.0, 2.0]]) @ np.eye(3)
    o = 2.0 * S1[None] - DIR[None]
    t, slot = tile_grid.trace_grid(engine, bvh, grid, o)
    assert np.isnan(t[0]) and slot[0] == -2              # outside the rectangle
    # no triangles in the rectangle: empty lists, every ray misses
    far = tile_grid.build_grid(bvh, np.zeros(3), S1, S2, DIR, (5.0, 5.0, 6.0, 6.0), 4, 4)
    assert len(far.items) == 0 and far.starts[-1] == 0
    t, _ = tile_grid.trace_grid(engine, bvh, far, 5.5 * S1[None] + 5.5 * S2[None] - DIR[None])
    assert np.isinf(t[0])
    assert not tile_grid.worth_it(None)
    # a cap on the entries: no grid
    assert tile_grid.build_grid(bvh, np.zeros(3), S1, S2, DIR, (-0.7, -0.7, 0.7, 0.7),
                                4096, 4096) is None


@pytest.mark.parametrize("name,kind", [("epi_grille", "grid"), ("epi_window", "grid"),
                                       ("epi_spot", "grid"), ("epi_wide_spot", "bvh")])
def test_shadow_map_through_the_grid_equals_the_bvh(engine, name, kind):
    """Directional maps and a spot's single map through a grid; the five faces of a wide
    cone through the BVH."""
    from clscatter.methods.epipolar import geometry as geo
    from clscatter.methods.epipolar import maps
    from clscatter.scene.loader import load_scene
    from clscatter.transport.prepared import prepare_scene

    ps = prepare_scene(load_scene(f"builtin:{name}", ["camera.resolution=[64,48]"]), engine)
    try:
        cam = geo.CameraGeom.from_struct(ps.camera)
        axis = geo.make_axis(ps.lights[0], cam.origin)
        frame = geo.frame_struct(axis, ps.medium, 1)
        res = 512
        faces = maps.setup_shadow_map(frame, axis, ps, res)
        n = maps.face_texels(faces) if axis.spot else res * res
        fb = engine.to_device(frame.reshape(1))
        info: dict = {}
        via_grid = maps.trace_shadow_map(ps, fb, res, {}, faces, frame=frame, info=info)
        via_bvh = maps.trace_shadow_map(ps, fb, res, {}, faces)
        a = engine.read(via_grid, n, np.float32)
        b = engine.read(via_bvh, n, np.float32)
        engine.free(fb, via_grid, via_bvh)
    finally:
        ps.release() if hasattr(ps, "release") else None
    assert info["shadow_map_caster"]["kind"] == kind
    if kind == "grid":
        assert info["shadow_map_caster"]["mean_list"] <= tile_grid.MAX_MEAN_LIST
    lit = b < maps.T_INF
    assert 0.05 < lit.mean()
    assert np.array_equal(a < maps.T_INF, lit)
    np.testing.assert_allclose(a[lit], b[lit], rtol=1e-6, atol=1e-6)
    if axis.spot:           # a perspective grid runs the BVH's own test: the same bits
        assert np.mean(a == b) > 0.999


@pytest.mark.parametrize("name,method", [("shafts", "epipolar"), ("epi_grille", "raymarch"),
                                         ("volume_lens", "voxel"), ("epi_spot", "epipolar"),
                                         ("spotlight", "raymarch"), ("occluder", "raymarch")])
def test_renders_equal_with_and_without_the_grids(engine, monkeypatch, name, method):
    """The scene grids (camera rays; a directional, spot or point light's shadow rays) and
    the shadow map's grid change how hits are found, not which: the image equals the BVH-only one to
    float tolerance (a ray exactly on an edge shared by two triangles may report either)."""
    from clscatter.pipeline.render import render
    from clscatter.scene.loader import load_scene

    scene = load_scene(f"builtin:{name}", ["camera.resolution=[48,36]", "camera.spp=2"])
    with_grids = render(scene, method=method, engine=engine, show_progress=False)
    grids = with_grids.stats["tile_grids"]
    assert grids["light_grid"] is not None
    # the occluder's ball, a detailed mesh over 8 x 8 tiles of a 48 x 36 image: the camera
    # rays keep the BVH there
    assert (grids["camera_grid"] is None) == (name == "occluder")
    monkeypatch.setattr(tile_grid, "worth_it", lambda grid: False)
    without = render(scene, method=method, engine=engine, show_progress=False)
    assert without.stats["tile_grids"] == {"camera_grid": None, "light_grid": None}
    a, b = with_grids.image, without.image
    assert np.all(np.isfinite(a)) and a.max() > 0
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-5 * float(b.max()))
