"""The engine's buffer pool (``Engine.empty`` / ``free`` / ``trim_pool``) and its BLAS
thread limit: released scratch buffers are reused by size, stale ones are released after
a render, and no kernel depends on what a reused buffer held before."""
from __future__ import annotations

import ast
import subprocess
import sys

import numpy as np
import pyopencl as cl
import pytest
from method_scenes import SMALL, overrides_for, scene_for

from clscatter import device as dev
from clscatter.device import buffers
from clscatter.methods import all_methods
from clscatter.pipeline.render import render
from clscatter.pipeline.session import RenderSession
from clscatter.scene import load_scene

MB = 1 << 20


@pytest.fixture
def pool(engine):
    """The shared engine with an empty pool, emptied again afterwards."""
    engine.drain_pool()
    yield engine
    engine.drain_pool()


def test_a_released_buffer_serves_requests_of_a_fitting_size(pool):
    live = pool.bytes_live
    a = pool.empty(MB)
    assert pool.bytes_live == live + MB
    pool.free(a)
    assert pool.bytes_live == live
    b = pool.empty(int(MB / 1.2))               # within POOL_SLACK: the same buffer
    assert b.int_ptr == a.int_ptr and b.size == MB
    assert pool.bytes_live == live + MB         # counted at its real size
    pool.free(b)
    c = pool.empty(int(MB / 1.3))               # beyond the slack: a new one
    d = pool.empty(2 * MB)                      # larger: a new one
    assert c.int_ptr != a.int_ptr and d.int_ptr != a.int_ptr
    e = pool.empty(MB)                          # the pooled one again
    assert e.int_ptr == a.int_ptr
    pool.free(c, d, e)
    assert pool.bytes_live == live


def test_a_second_free_leaves_the_pooled_buffer_alone(pool):
    live = pool.bytes_live
    a = pool.empty(MB)
    pool.free(a)
    pool.free(a)                                # must not release what the pool holds
    assert len(pool._pool) == 1 and pool._pool_bytes == MB and pool.bytes_live == live
    b = pool.empty(MB)
    assert b.int_ptr == a.int_ptr
    pool.cl.enqueue_fill_buffer(pool.queue, b, np.full(1, 7, np.uint32), 0, MB)
    assert np.all(pool.read(b, MB // 4, np.uint32) == 7)
    pool.free(b)


def test_small_and_uploaded_buffers_are_not_pooled(pool):
    small = pool.empty(1000)
    up = pool.to_device(np.zeros(MB // 4, np.float32), writable=True)
    pool.free(small, up)
    assert pool._pool == [] and pool._pool_bytes == 0


def test_trim_releases_what_nothing_took_since_the_last_trim(pool):
    a, b = pool.empty(MB), pool.empty(3 * MB)
    pool.free(a, b)
    pool.trim_pool()                            # freed in this generation: kept
    assert {e[0] for e in pool._pool} == {MB, 3 * MB}
    c = pool.empty(MB)                          # the next "render" takes one of them
    pool.free(c)
    pool.trim_pool()                            # the other was not taken: released
    assert [e[0] for e in pool._pool] == [MB]
    assert pool._pool_bytes == MB


def test_an_allocation_failure_empties_the_pool_and_retries(pool, monkeypatch):
    pool.free(pool.empty(MB))
    real, calls = cl.Buffer, []

    def failing_once(*args, **kw):
        calls.append(1)
        if len(calls) == 1:
            raise cl.MemoryError("clCreateBuffer", cl.status_code.MEM_OBJECT_ALLOCATION_FAILURE,
                                 "out of memory")
        return real(*args, **kw)

    monkeypatch.setattr(cl, "Buffer", failing_once)
    buf = pool.empty(4 * MB)
    assert len(calls) == 2 and pool._pool == [] and buf.size == 4 * MB
    pool.free(buf)




@pytest.mark.parametrize("method", sorted(all_methods()))
def test_no_kernel_reads_what_a_reused_buffer_held(method, pool, monkeypatch):
    """Every buffer the pool keeps is overwritten with 0xff bytes (NaN floats, -1 ints);
    a session's next render, which takes them (another seed: camera paths and passes all
    run again), gives the image of a one-off render from fresh memory (PoCL's fresh
    allocations read as zeros, which could hide a kernel that reads scratch it never
    wrote). Closing the session empties the pool."""
    spec, sets = scene_for(method), overrides_for(method)
    monkeypatch.setattr(buffers, "POOL_MIN_BYTES", 1 << 62)         # the reference: no pool
    fresh = render(load_scene(spec, sets + ["render.seed=7"]), engine=pool, method=method,
                   show_progress=False)
    monkeypatch.setattr(buffers, "POOL_MIN_BYTES", 4096)
    free = pool.free

    def poisoning_free(*bufs):
        for b in bufs:
            if b.size >= dev.POOL_MIN_BYTES and b.flags == cl.mem_flags.READ_WRITE:
                cl.enqueue_fill_buffer(pool.queue, b, np.full(1, 0xFFFFFFFF, np.uint32), 0,
                                       b.size)
        free(*bufs)

    monkeypatch.setattr(pool, "free", poisoning_free)
    with RenderSession.from_source(spec, sets, engine=pool, method=method) as s:
        s.render(show_progress=False)
        assert pool._pool, "the first render left nothing in the pool"
        s.set(["render.seed=7"])
        reused = s.render(show_progress=False)
        assert "view_paths" in reused.stats["stages_run"]
    assert pool._pool == []
    assert np.isfinite(reused.image).all()
    assert fresh.image.max() > 0.0
    np.testing.assert_allclose(reused.image, fresh.image, rtol=1e-4,
                               atol=1e-6 * float(fresh.image.max()))


def test_pooled_bytes_fit_the_render_budget(pool):
    """fit_pool: idle pooled bytes stay within a quarter of the budget and within what
    the coming render leaves free, the oldest released first."""
    bufs = [pool.empty(k * MB) for k in (1, 2, 3)]
    pool.free(*bufs)
    assert pool._pool_bytes == 6 * MB
    pool.fit_pool(limit=100 * MB, need=10 * MB)          # room: min(25, 90) MB
    assert pool._pool_bytes == 6 * MB
    pool.fit_pool(limit=100 * MB, need=95 * MB - pool.bytes_live)   # room: 5 MB
    assert [e[0] for e in pool._pool] == [2 * MB, 3 * MB]
    pool.fit_pool(limit=12 * MB, need=0 - pool.bytes_live)          # room: 3 MB
    assert [e[0] for e in pool._pool] == [3 * MB] and pool._pool_bytes == 3 * MB


BLAS_CHECK = """
import threadpoolctl
from clscatter.device import get_engine
from clscatter.pipeline.render import render
from clscatter.scene import load_scene
def threads():
    return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
engine = get_engine()
import scipy.linalg  # brings its own OpenBLAS, after the engine was made
threadpoolctl.threadpool_limits(2, user_api="blas")
before = threads()
render(load_scene("builtin:shafts", {sets!r}), engine=engine, show_progress=False)
print(repr((engine.shares_host_cores, before, threads())))
"""


def test_blas_runs_one_thread_beside_a_cpu_device():
    """OpenBLAS threads spinning after the SVD would take the cores the kernels run on:
    beside a CPU device every BLAS, also one a library imported after the engine brings
    (SciPy's own), runs one thread once a render started; beside a GPU the render leaves
    them alone (in a fresh process, whichever device it chooses)."""
    out = subprocess.run([sys.executable, "-c", BLAS_CHECK.format(sets=SMALL)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    cpu, before, after = ast.literal_eval(out.stdout.strip().splitlines()[-1])
    assert before == [2] * len(before) and len(before) >= 1   # NumPy's BLAS, at least
    assert after == ([1] * len(before) if cpu else before)
