"""Line space gathering from the lighting side over a pinhole camera's rays: the view
segments on camera rays in screen cells (clscatter/estimators/screen_cells.py, lsg_splat
in cl_kernels/estimators/lsg.cl) must find exactly the pairs of the exhaustive test and
the same fixed-point sums as the tree over the same view segments."""
from __future__ import annotations

import numpy as np
import pytest
from test_lsg import _as_dict, _gather, _medium, _segments, _unit, reference_gather

from clscatter.device import structs
from clscatter.estimators.line_gather import Gatherer
from clscatter.estimators.screen_cells import (
    build_screen_cells,
    camera_axes,
    on_camera_rays,
    splat_order,
)

EYE = np.array([0.1, 0.2, 1.6])


def _camera(width: int = 24, height: int = 16, eye=EYE, target=(0.0, 0.0, 0.0),
            fov: float = 50.0) -> np.ndarray:
    """A CAMERA record (normalised frame): ``right`` spans half the image's width at unit
    distance, ``up`` half its height."""
    cam = np.zeros(1, structs.CAMERA)
    f = _unit(np.asarray(target, float) - eye)
    right = _unit(np.cross(f, [0.0, 1.0, 0.0]))
    up = np.cross(right, f)
    half = np.tan(np.radians(fov) / 2)
    cam["origin"][0] = structs.vec4(eye)
    cam["forward"][0] = structs.vec4(f)
    cam["right"][0] = structs.vec4(right * half)
    cam["up"][0] = structs.vec4(up * half * height / width)
    cam["width"], cam["height"], cam["spp"] = width, height, 4
    return cam


def _camera_rays(rng, cam: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Ends of n segments on camera rays through the image: some from the eye, the rest
    from up to 0.8 in front of it, 0.05-1.8 long."""
    eye, ex, ey, ez = camera_axes(cam)
    c = cam[0]
    hx = np.linalg.norm(c["right"][:3])
    hy = np.linalg.norm(c["up"][:3])
    tx = rng.uniform(-hx, hx, n)
    ty = rng.uniform(-hy, hy, n)
    d = _unit(tx[:, None] * ex + ty[:, None] * ey + ez)
    t0 = np.where(rng.random(n) < 0.2, 0.0, rng.uniform(0.0, 0.8, n))
    t1 = t0 + rng.uniform(0.05, 1.8, n)
    return eye + t0[:, None] * d, eye + t1[:, None] * d


def _lighting(rng, cam: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Lighting segments where the screen cells are weakest: anywhere in and around the
    view (random), from behind the camera to far in front (depth ratios far beyond 2,
    the near part within a few r of the eye), passing the eye within 0-5 r, along the
    view direction (a point on screen), behind the camera, beside the frustum."""
    eye, ex, ey, ez = camera_axes(cam)
    parts = []
    n = 900
    a = rng.uniform(-1.0, 1.0, (n, 3))
    parts.append((a, a + rng.uniform(0.05, 1.5, (n, 1)) * _unit(rng.normal(size=(n, 3)))))
    n = 300                                   # through the camera's plane, into the view
    a = eye - rng.uniform(0.05, 0.5, (n, 1)) * ez + rng.uniform(-0.3, 0.3, (n, 3))
    b = eye + rng.uniform(1.0, 3.0, (n, 1)) * ez + rng.uniform(-1.0, 1.0, (n, 3))
    parts.append((a, b))
    n = 200                                   # passing the eye within 0-5 r
    d = _unit(rng.normal(size=(n, 3)))
    off = _unit(np.cross(d, rng.normal(size=(n, 3)))) * rng.uniform(0.0, 5.0 * r, (n, 1))
    s = rng.uniform(0.1, 1.0, (n, 1))
    parts.append((eye + off - s * d, eye + off + rng.uniform(0.1, 2.0, (n, 1)) * d))
    n = 100                                   # along the view direction: a point on screen
    a = eye + rng.uniform(0.1, 1.0, (n, 1)) * ez + rng.uniform(-0.2, 0.2, (n, 2)) @ np.stack([ex, ey])
    parts.append((a, a + rng.uniform(0.2, 1.5, (n, 1)) * ez * rng.choice([-1, 1], (n, 1))))
    n = 100                                   # behind the camera, and beside the frustum
    a = eye - rng.uniform(0.1, 1.0, (n, 1)) * ez + rng.uniform(-0.5, 0.5, (n, 3))
    parts.append((a, a + 0.5 * _unit(rng.normal(size=(n, 3)))))
    a = eye + rng.uniform(0.2, 1.5, (n, 1)) * (ez + 1.2 * ex)
    parts.append((a, a + 0.8 * _unit(rng.normal(size=(n, 3)))))
    la = np.concatenate([p[0] for p in parts])
    lb = np.concatenate([p[1] for p in parts])
    return la, lb


def _scene_set(rng, cam, r, n_rays=1200, n_other=150):
    va, vb = _camera_rays(rng, cam, n_rays)
    oa = rng.uniform(-1.0, 1.0, (n_other, 3))          # after a mirror or glass: anywhere
    ob = oa + rng.uniform(0.05, 1.0, (n_other, 1)) * _unit(rng.normal(size=(n_other, 3)))
    views = _segments(rng, n_rays + n_other, "view", np.concatenate([va, oa]),
                      np.concatenate([vb, ob]))
    la, lb = _lighting(rng, cam, r)
    return _segments(rng, len(la), "light", la, lb), views


def test_camera_rays_are_told_from_other_segments():
    """on_camera_rays takes the segments on lines through the eye that head away from it
    (from the eye or beyond), and none of the others: segments after a mirror, segments
    behind the camera, a camera ray's segment turned round."""
    rng = np.random.default_rng(3)
    cam = _camera()
    va, vb = _camera_rays(rng, cam, 400)
    oa = rng.uniform(-1.0, 1.0, (100, 3))
    ob = oa + 0.3 * _unit(rng.normal(size=(100, 3)))
    eye, _, _, ez = camera_axes(cam)
    back = eye - 0.5 * ez                                 # behind the camera, on its axis
    views = _segments(rng, 503, "view", np.concatenate([va, oa, [back], [vb[0]], [va[1]]]),
                      np.concatenate([vb, ob, [back - 0.3 * ez], [va[0]], [va[1]]]))
    ok, reach = on_camera_rays(views, cam)
    assert ok[:400].all()
    assert not ok[400:].any()                # others, behind, turned round, of length 0
    assert 0.0 <= reach < 1e-6


@pytest.mark.parametrize("r, size, others", [(0.002, (24, 16), 150), (0.02, (24, 16), 150),
                                             (0.08, (24, 16), 150), (0.01, (7, 31), 2500)])
def test_screen_cells_find_exactly_the_exhaustive_pairs(engine, r, size, others):
    """``queries = "screen"``: lsg_splat (camera rays in screen cells) and, for the other
    view segments, a query per view segment (150 of them, fewer than the lighting
    segments) or per lighting segment (2500, more) find every pair of the exhaustive test,
    each once, on segments chosen where the cells are weakest (_lighting), at radii from a
    fraction of a cell to several cells; on the camera rays the sums are bit for bit those
    of the tree over every view segment (exact fixed-point sums), and the estimate is the
    float64 reference's."""
    rng = np.random.default_rng(int(r * 1000) + size[1])
    cam = _camera(*size)
    lights, views = _scene_set(rng, cam, r, n_other=others)
    med = _medium()
    ok, _ = on_camera_rays(views, cam)
    assert ok.sum() == 1200
    v_cells, res = _gather(engine, lights, views, r, med, queries="screen", camera=cam)
    v_tree, res_tree = _gather(engine, lights, views, r, med, queries="lights")
    v_all, res_all = _gather(engine, lights, views, r, med, bruteforce=True)
    got = set(map(tuple, res.pairs.tolist()))
    want = set(map(tuple, res_all.pairs.tolist()))
    assert len(want) > 300
    assert len(got) == len(res.pairs)                    # no pair twice
    assert got == want, f"missed {len(want - got)}, extra {len(got - want)}"
    # pairs with a camera ray: many, including ones near the eye and far beyond it
    on_ray = np.isin(res.pairs[:, 0], np.flatnonzero(ok))
    assert on_ray.sum() > 200
    assert res.valid_pairs == res_tree.valid_pairs == len(want)
    assert np.array_equal(v_cells[ok], v_tree[ok])
    if others > len(lights):                 # the rest from the lighting side too
        assert np.array_equal(v_cells, v_tree)
    ref, _ = reference_gather(_as_dict(lights, "light"), _as_dict(views, "view"), r,
                              med["kappa"], med["sigma_s"], float(med["g"]))
    scale = np.abs(ref).max()
    np.testing.assert_allclose(v_cells[:, :3], ref, rtol=1e-4, atol=1e-5 * scale)
    # the cells test far fewer pairs than light x view (at r = 0.08, 4% of the pairs
    # are valid: a fifth of them still to test)
    assert res.pair_tests < (0.2 if r <= 0.02 else 0.4) * res_all.pair_tests


def test_splat_order_keeps_the_sums(engine):
    """The lighting segments are reordered for the cells' sake (splat_order: neighbours on
    screen together); a permutation of the input gives the same pairs and, on the camera
    rays, the same sums bit for bit."""
    rng = np.random.default_rng(8)
    cam = _camera()
    lights, views = _scene_set(rng, cam, 0.02)
    med = _medium()
    v1, r1 = _gather(engine, lights, views, 0.02, med, queries="screen", camera=cam)
    perm = rng.permutation(len(lights))
    v2, r2 = _gather(engine, lights[perm], views, 0.02, med, queries="screen", camera=cam)
    assert r1.valid_pairs == r2.valid_pairs > 300
    ok = on_camera_rays(views, cam)[0]
    assert np.array_equal(v1[ok], v2[ok])
    np.testing.assert_allclose(v1, v2, rtol=1e-5, atol=1e-6 * np.abs(v1).max())
    sc = build_screen_cells(engine, views, np.flatnonzero(on_camera_rays(views, cam)[0]), cam,
                            0.0)
    try:
        a = lights["a"][:, :3].astype(np.float64)
        d = lights["b"][:, :3].astype(np.float64) - a
        ln = np.linalg.norm(d, axis=1)
        o = splat_order(sc, a, d / ln[:, None], ln)
        assert sorted(o.tolist()) == list(range(len(lights)))
        assert sc.count == 1200 and sc.nx * sc.ny == 24 * 16
    finally:
        sc.release(engine)


def test_cells_hold_the_unit_directions_in_blocks_of_the_cell_order(engine):
    """The splat's plane test reads the directions 8 segments at once (POINT_LANES): block b
    holds rows x, y, z of the unit directions of segments 8b .. 8b + 7 of the cell order
    (the order of ``ids``), float32 within 1e-6 of float64's, the last block padded with
    zeros (1203 segments: a partial block)."""
    from clscatter.estimators.line_tree import POINT_LANES
    rng = np.random.default_rng(3)
    cam = _camera()
    va, vb = _camera_rays(rng, cam, 1203)
    views = _segments(rng, len(va), "view", va, vb)
    idx = np.flatnonzero(on_camera_rays(views, cam)[0])
    assert len(idx) == 1203
    sc = build_screen_cells(engine, views, idx, cam, 0.0)
    try:
        blocks = -(-1203 // POINT_LANES)
        dirs = engine.read(sc.bufs["dirs"], (blocks, 3, POINT_LANES), np.float32)
        ids = engine.read(sc.bufs["ids"], (1203,), np.int32)
        assert sorted(ids.tolist()) == sorted(idx.tolist())
        d = views["b"][ids, :3].astype(np.float64) - views["a"][ids, :3]
        unit = d / np.linalg.norm(d, axis=1)[:, None]
        got = dirs.transpose(0, 2, 1).reshape(-1, 3)
        np.testing.assert_allclose(got[:1203], unit, atol=1e-6)
        assert not got[1203:].any()
    finally:
        sc.release(engine)


def test_prepare_builds_the_cells_before_the_first_gather(engine):
    """Gatherer.prepare builds the screen cells (what the automatic radius's pilot calls
    before it times a gather); the gather after it is the same."""
    rng = np.random.default_rng(12)
    cam = _camera()
    lights, views = _scene_set(rng, cam, 0.02)
    med = _medium()
    gat = Gatherer(engine, views, med, 0.02, queries="screen", camera=cam)
    try:
        assert gat.screen_segments == 0
        gat.prepare()
        assert gat.screen_segments == 1200
        res = gat.add(lights)
        got = gat.values()
    finally:
        gat.release()
    want, res_plain = _gather(engine, lights, views, 0.02, med, queries="screen", camera=cam)
    assert res.valid_pairs == res_plain.valid_pairs > 300
    assert np.array_equal(got, want)
