"""A warm light move, taken apart: per-kernel device time, page faults, and what each of
the warm path's optimisations (one BLAS thread beside a CPU device, the buffer pool, no
epipole ring where it misses the image, small event-sort buckets) is worth, switched off
one at a time.

One process, one :class:`~clscatter.pipeline.session.RenderSession` on ``--scene`` (default the
demo, ``builtin:shafts``, at 640x480, 4 spp, by epipolar). The first light moves back and
forth; the variants take turns move by move, so the machine's drift (10-40% here) falls
on all of them alike:

* ``final``: the engine as it is;
* ``blas_threads``: NumPy's BLAS back to the machine's core count (the engine otherwise
  limits it to one thread beside a CPU device: its workers spin after the SVD);
* ``no_pool``: no buffer pool (every scratch buffer freshly allocated, page faults);
* ``ring_forced``: the epipole ring's kernel, compaction and read-back run even where
  the ring misses the image;
* ``buckets_32``: event-sort buckets of ~32 samples (heapsorted) instead of ~4.

For each variant: the median wall time of a move, the least and largest, and the minor
page faults per move (``getrusage``; taking turns mixes the variants' buffer sizes, so
the pool's effect shows in ``page_faults_consecutive``). Then, per variant, three
consecutive moves with a finish after every kernel: each kernel's least time over them
(the kernel profile) and the median page faults of those moves.
Writes ``bench_out/warm_move.json`` (and ``docs/bench/``). Usage::

    .venv/bin/python tools/bench_warm_move.py [--scene builtin:shafts] [--moves 8]
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from bench_output import publish  # noqa: E402

from clscatter import device as dev  # noqa: E402
from clscatter.device import buffers  # noqa: E402
from clscatter.device import engine as engine_mod  # noqa: E402
from clscatter.methods.epipolar import pipeline  # noqa: E402
from clscatter.pipeline.session import RenderSession


@contextlib.contextmanager
def variant(name: str, session: RenderSession):
    """The engine with one optimisation switched off (``final``: none)."""
    eng = session.engine
    saved = (buffers.POOL_MIN_BYTES, pipeline.EVENTS_PER_BIN, pipeline._ring_in_view,
             eng.quiet_host_threads)
    try:
        if name == "blas_threads":
            import os

            from threadpoolctl import threadpool_limits
            eng.quiet_host_threads = lambda: None
            threadpool_limits(os.cpu_count(), user_api="blas")
        elif name == "no_pool":
            buffers.POOL_MIN_BYTES = 1 << 62
            eng.drain_pool()
        elif name == "ring_forced":
            pipeline._ring_in_view = lambda *a: True
        elif name == "buckets_32":
            pipeline.EVENTS_PER_BIN = 32
        yield
    finally:
        buffers.POOL_MIN_BYTES, pipeline.EVENTS_PER_BIN, pipeline._ring_in_view = saved[:3]
        eng.quiet_host_threads = saved[3]
        if name == "blas_threads":
            engine_mod._BLAS_MODULES = -1          # set the one-thread limit again
            eng.quiet_host_threads()


class KernelClock:
    """While on: a finish before and after every launch, each kernel's seconds listed."""

    def __init__(self):
        self.times: dict[str, list[float]] = collections.defaultdict(list)
        self._launch = dev.Engine.launch

    @contextlib.contextmanager
    def on(self):
        real = self._launch
        times = self.times

        def launch(eng, kernel, global_size, *args, **kw):
            eng.queue.finish()
            t = time.perf_counter()
            real(eng, kernel, global_size, *args, **kw)
            eng.queue.finish()
            times[kernel.function_name].append(time.perf_counter() - t)

        dev.Engine.launch = launch
        try:
            yield
        finally:
            dev.Engine.launch = real


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="builtin:shafts")
    ap.add_argument("--method", default="epipolar")
    ap.add_argument("--set", dest="overrides", action="append",
                    default=["camera.resolution=[640,480]"])
    ap.add_argument("--moves", type=int, default=8, help="timed moves per variant")
    ap.add_argument("--no-copy", action="store_true")
    args = ap.parse_args()
    # no_pool last in each round, then one unmeasured move that refills the pool, so that
    # the next round's first variant does not pay no_pool's fresh allocations
    names = ["final", "blas_threads", "ring_forced", "buckets_32", "no_pool"]
    s = RenderSession.from_source(args.scene, args.overrides, method=args.method)
    s.render(show_progress=False)
    light = s.scene.lights[0]
    key = "direction" if light.type == "directional" else "position"
    base = np.asarray(getattr(light, key), float)
    count = [0]

    def move() -> tuple[float, int]:
        count[0] += 1
        p = base + np.array([0.05 * (count[0] % 2), 0.0, 0.0])
        s.set([f"lights[0].{key}=[{p[0]:.6g}, {p[1]:.6g}, {p[2]:.6g}]"], replace=True)
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t = time.perf_counter()
        s.render(show_progress=False)
        return time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0

    walls = {n: [] for n in names}
    faults = {n: [] for n in names}
    for n in names:                         # one unmeasured move each: pools, caches
        with variant(n, s):
            move()
    for _ in range(args.moves):
        for n in names:
            with variant(n, s):
                w, f = move()
            walls[n].append(w)
            faults[n].append(f)
        move()
    kernels, steady_faults = {}, {}
    for n in names:
        clock = KernelClock()
        with variant(n, s):
            move()                          # unmeasured: the variant's pool state
            with clock.on():
                steady_faults[n] = int(np.median([move()[1] for _ in range(3)]))
        per_move = collections.defaultdict(list)
        for k, ts in clock.times.items():
            calls = len(ts) // 3
            for r in range(3):
                per_move[k].append(sum(ts[r * calls:(r + 1) * calls]))
        kernels[n] = {k: min(v) for k, v in sorted(per_move.items(), key=lambda kv: -min(kv[1]))}
    s.close()
    rows = []
    print(f"{args.scene} by {args.method}, {args.overrides}: {args.moves} moves a variant")
    for n in names:
        row = {"variant": n, "median_s": float(np.median(walls[n])),
               "min_s": float(min(walls[n])), "max_s": float(max(walls[n])),
               "walls_s": walls[n], "page_faults_median": int(np.median(faults[n])),
               "page_faults_consecutive": steady_faults[n],
               "kernels_s": kernels[n], "kernels_total_s": float(sum(kernels[n].values()))}
        rows.append(row)
        top = ", ".join(f"{k} {1e3 * v:.1f}" for k, v in list(kernels[n].items())[:6])
        print(f"  {n:13s} median {row['median_s']:.3f} s (min {row['min_s']:.3f}, max "
              f"{row['max_s']:.3f}), faults {row['page_faults_consecutive']}, kernels "
              f"{1e3 * row['kernels_total_s']:.0f} ms: {top} ms")
    publish({"scene": args.scene, "method": args.method, "overrides": args.overrides,
             "moves": args.moves, "rows": rows}, "warm_move", copy=not args.no_copy)


if __name__ == "__main__":
    main()
