"""Row-wise host work in chunks on threads (clscatter.estimators.row_chunks): the chunks
cover every row once, in order, and LSG's preparation of lighting segments (continuation
across the medium's faces, clipping, Plücker points, the tree, the rows in tree order)
gives bit for bit the arrays of one call over all rows."""
from __future__ import annotations

import numpy as np
import pytest

import clscatter.estimators.row_chunks as rc
from clscatter.device import structs
from clscatter.estimators.line_gather import (
    BuildStopped,
    clip_lines,
    continue_across_faces,
    continue_and_clip,
    prepare_lines,
)
from clscatter.estimators.line_tree import (
    POINT_LANES,
    node_boxes,
    plucker,
    point_blocks,
)


def test_host_threads_are_the_cores_this_process_may_use():
    assert 1 <= rc.host_threads() <= (rc.os.cpu_count() or 1)


@pytest.mark.parametrize("n, chunk", [(0, 4), (3, 4), (4, 4), (10, 4), (1000, 7)])
def test_chunks_cover_every_row_once_in_order(n, chunk):
    got = rc.map_row_chunks(lambda s, e: (s, e), n, chunk)
    starts = [s for s, _ in got]
    assert starts == sorted(starts) and got[0][0] == 0 and got[-1][1] == n
    assert all(e0 == s1 for (_, e0), (s1, _) in zip(got, got[1:]))
    assert all(0 < e - s <= chunk for s, e in got) or n == 0
    assert len(got) == max(1, -(-n // chunk))


def test_aligned_chunks_start_on_multiples():
    got = rc.map_row_chunks(lambda s, e: (s, e), 1001, 333, align=4)
    assert [s for s, _ in got] == [0, 336, 672] and got[-1][1] == 1001


def test_one_thread_runs_the_chunks_in_turn(monkeypatch):
    monkeypatch.setattr(rc, "host_threads", lambda: 1)
    assert rc.map_row_chunks(lambda s, e: e - s, 10, 4) == [4, 4, 2]


def _fog_and_segments(n: int, seed: int = 3):
    """A bounded fog box [-1, 1]^3 and lighting segments that start inside it, on its faces
    heading in, and end on its faces heading out (the cases the continuation changes),
    some of length 0 and some outside the view box (clipped away)."""
    rng = np.random.default_rng(seed)
    m = np.zeros((), structs.MEDIUM)
    m["sigma_s"] = structs.vec4([0.3, 0.2, 0.1])
    m["sigma_a"] = structs.vec4([0.05, 0.0, 0.1])
    m["kappa"] = structs.vec4([0.35, 0.2, 0.2])
    m["g"], m["present"], m["bounded"] = 0.3, 1, 1
    m["bmin"], m["bmax"] = structs.vec4([-1, -1, -1]), structs.vec4([1, 1, 1])
    a = rng.uniform(-1, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    on_face = rng.random(n) < 0.3                  # start on the face x = -1, heading in
    a[on_face, 0] = -1.0
    d[on_face, 0] = np.abs(d[on_face, 0])
    t_exit = np.min(np.where(d > 0, (1 - a) / d, np.where(d < 0, (-1 - a) / d, np.inf)), axis=1)
    exits = rng.random(n) < 0.5                    # end where light leaves the box
    length = np.where(exits, t_exit, rng.uniform(0, 1, n) * t_exit)
    length[rng.random(n) < 0.02] = 0.0
    segs = np.zeros(n, structs.LIGHT_SEGMENT)
    segs["a"][:, :3] = a
    segs["b"][:, :3] = a + length[:, None] * d
    segs["flux"][:, :3] = rng.uniform(0.1, 1, (n, 3))
    return m.reshape(1), segs


def test_chunked_preparation_is_the_whole_array_preparation(monkeypatch):
    medium, segs = _fog_and_segments(5000)
    kappa = medium[0]["kappa"]
    view_lo, view_hi, r = np.array([-0.9, -1.2, -0.8]), np.array([0.7, 1.2, 0.9]), 0.01
    whole = clip_lines(continue_across_faces(segs, medium, r), view_lo, view_hi, r, kappa)
    assert 0 < len(whole[0]) < len(segs)              # some rows are clipped away
    monkeypatch.setattr(rc, "ROW_CHUNK", 1 << 30)
    one = prepare_lines(segs, view_lo, view_hi, r, kappa, 4, clipped=whole)
    monkeypatch.setattr(rc, "ROW_CHUNK", 333)
    chunked = continue_and_clip(segs, medium, r, view_lo, view_hi, kappa)
    for x, y in zip(whole, chunked):
        assert x.dtype == y.dtype and np.array_equal(x, y)
    many = prepare_lines(segs, view_lo, view_hi, r, kappa, 4, clipped=chunked)
    assert one.tree.levels == many.tree.levels == 3
    for name in ("lines", "points", "ids", "boxes", "kids"):
        assert np.array_equal(getattr(one, name), getattr(many, name)), name
    assert np.array_equal(one.tree.order, many.tree.order)
    assert np.array_equal(one.frame.centre, many.frame.centre)
    assert one.frame.scale == many.frame.scale and one.max_m1 == many.max_m1
    # the rows really are in tree order: each line's start is its clipped segment's, the
    # Plücker blocks and the node boxes those of whole float64 arrays in that order
    ids, a, u, length, _ = chunked
    o = many.tree.order
    np.testing.assert_array_equal(many.lines["a"][:, :3], a[o].astype(np.float32))
    np.testing.assert_array_equal(many.lines["a"][:, 3], length[o].astype(np.float32))
    np.testing.assert_array_equal(many.ids, ids[o])
    u32 = u[o].astype(np.float32)
    pts = plucker(a[o], u32.astype(np.float64), many.frame).astype(np.float32)
    pts[:, :3] = u32
    np.testing.assert_array_equal(many.points, point_blocks(pts))
    ends = a + length[:, None] * u
    boxes = node_boxes(many.tree, np.minimum(a, ends)[o].T, np.maximum(a, ends)[o].T)
    np.testing.assert_array_equal(many.boxes, boxes)


@pytest.mark.parametrize("chunk", [5, 1 << 20])
def test_preparing_no_kept_lines(monkeypatch, chunk):
    """Every segment outside the view box: an empty preparation, not an error."""
    monkeypatch.setattr(rc, "ROW_CHUNK", chunk)
    medium, segs = _fog_and_segments(50)
    kappa = medium[0]["kappa"]
    lo, hi = np.full(3, 5.0), np.full(3, 6.0)
    clipped = continue_and_clip(segs, medium, 0.01, lo, hi, kappa)
    assert len(clipped[0]) == 0
    prep = prepare_lines(segs, lo, hi, 0.01, kappa, 4, clipped=clipped)
    assert len(prep.lines) == 0 and prep.max_m1 == 0.0 and prep.tree.levels == 0
    assert prep.points.shape == (1, 6, POINT_LANES) and not prep.points.any()


def test_a_tree_build_told_to_stop_ends_at_its_next_chunk(monkeypatch):
    """``prepare_lines(stop=...)`` (a build on a thread of its own, for a render that may be
    cancelled): asked before every chunk of rows and every step, it raises BuildStopped
    once told to, within the step it was in (its other chunks, already handed to the
    threads, each stop at their first question); a stop that never says so builds the
    same tree."""
    medium, segs = _fog_and_segments(5000)
    kappa = medium[0]["kappa"]
    view_lo, view_hi, r = np.array([-0.9, -1.2, -0.8]), np.array([0.7, 1.2, 0.9]), 0.01
    monkeypatch.setattr(rc, "ROW_CHUNK", 333)
    clipped = continue_and_clip(segs, medium, r, view_lo, view_hi, kappa)
    asked = []

    def after(n: int):
        return lambda: asked.append(1) or len(asked) > n

    chunks = -(-len(clipped[0]) // 333)
    with pytest.raises(BuildStopped):
        prepare_lines(segs, view_lo, view_hi, r, kappa, 4, clipped=clipped, stop=after(3))
    assert 4 <= len(asked) <= chunks                # the first step's chunks, no later step
    asked.clear()
    built = prepare_lines(segs, view_lo, view_hi, r, kappa, 4, clipped=clipped,
                          stop=after(10 ** 9))
    plain = prepare_lines(segs, view_lo, view_hi, r, kappa, 4, clipped=clipped)
    assert len(asked) > 3 * (len(clipped[0]) // 333)  # every chunk of three row steps asked
    for name in ("lines", "points", "ids", "boxes", "kids"):
        assert np.array_equal(getattr(built, name), getattr(plain, name)), name
