"""BVHs of large meshes kept on disk: the same BVH as a build, a new one for other
triangles, nothing kept for small meshes, and a cache that cannot be used ignored."""
from __future__ import annotations

import os

import numpy as np
import pytest

import clscatter.accel.bvh_cache as bc
from clscatter.accel.bvh import build_bvh
from clscatter.device import get_engine
from clscatter.io.stats import Stats
from clscatter.scene import load_scene
from clscatter.transport.prepared import prepare_scene


def _mesh(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, size=(n, 1, 3))
    return centres + 0.05 * rng.normal(size=(n, 3, 3))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A cache folder of the test's own, and meshes of 50 triangles or more kept."""
    monkeypatch.setenv("CLSCATTER_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(bc, "MIN_TRIANGLES", 50)
    return tmp_path / "bvh"


def _same(a, b) -> None:
    for name in ("nodes", "triangles", "order"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes(), name
    assert (a.depth, a.n_valid) == (b.depth, b.n_valid)


def test_a_kept_bvh_is_the_built_one(cache):
    tri = _mesh(300)
    first, hit = bc.cached_bvh(tri)
    assert not hit and len(list(cache.glob("*.npz"))) == 1
    again, hit = bc.cached_bvh(tri)
    assert hit
    _same(again, build_bvh(tri))
    _same(first, again)


def test_other_triangles_or_settings_build_anew(cache):
    tri = _mesh(300)
    bc.cached_bvh(tri)
    moved = tri.copy()
    moved[7, 1, 2] += 1e-3
    bvh, hit = bc.cached_bvh(moved)
    assert not hit
    _same(bvh, build_bvh(moved))
    bvh, hit = bc.cached_bvh(tri, leaf_size=8)
    assert not hit
    _same(bvh, build_bvh(tri, leaf_size=8))
    assert len(list(cache.glob("*.npz"))) == 3


def test_a_changed_builder_builds_anew(cache, tmp_path, monkeypatch):
    """The key covers the builder's source: an edited bvh.py does not read old files."""
    tri = _mesh(300)
    bc.cached_bvh(tri)
    assert bc.cached_bvh(tri)[1]
    edited = tmp_path / "bvh_edited.py"
    edited.write_text(open(bc._builder.__file__).read() + "\n# edited\n")
    with monkeypatch.context() as m:
        m.setattr(bc._builder, "__file__", str(edited))
        bc._maker.cache_clear()
        try:
            assert not bc.cached_bvh(tri)[1]
        finally:
            bc._maker.cache_clear()
    assert bc.cached_bvh(tri)[1]                    # the original builder's file again


def test_small_meshes_are_built_not_kept(cache):
    bvh, hit = bc.cached_bvh(_mesh(49))
    assert not hit and not cache.exists()
    _same(bvh, build_bvh(_mesh(49)))


def test_a_damaged_file_is_built_again(cache):
    tri = _mesh(300)
    bc.cached_bvh(tri)
    (path,) = cache.glob("*.npz")
    path.write_bytes(path.read_bytes()[:100])
    bvh, hit = bc.cached_bvh(tri)
    assert not hit
    _same(bvh, build_bvh(tri))
    assert bc.cached_bvh(tri)[1]                  # written whole again


def test_a_cache_that_cannot_be_written_is_ignored(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("CLSCATTER_CACHE_DIR", str(blocker))
    monkeypatch.setattr(bc, "MIN_TRIANGLES", 50)
    tri = _mesh(300)
    bvh, hit = bc.cached_bvh(tri)
    assert not hit
    _same(bvh, build_bvh(tri))


def test_pruning_drops_the_least_recently_used(tmp_path):
    for i, size in enumerate((300, 200, 100)):
        p = tmp_path / f"{i}.npz"
        p.write_bytes(b"x" * size)
        os.utime(p, (1000 + i, 1000 + i))
    os.utime(tmp_path / "0.npz", (2000, 2000))      # used last
    bc.prune(tmp_path, 450)
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == ["0.npz", "2.npz"]


def test_a_scene_prepared_twice_reads_its_bvh_back(cache):
    """Through the renderer: the second preparation of the same scene reads the BVH (the
    stats say so) and has the same nodes."""
    scene = load_scene("builtin:caustic_sphere")
    eng = get_engine()
    runs = []
    for _ in range(2):
        st = Stats()
        ps = prepare_scene(scene, eng, st)
        runs.append((st.values["bvh_cached"], ps.bvh))
        ps.release()
    assert [hit for hit, _ in runs] == [False, True]
    _same(runs[0][1], runs[1][1])
