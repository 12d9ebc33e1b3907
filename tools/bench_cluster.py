"""Scale-out benchmark: one process against a Dask LocalCluster of 1 and 2 workers.

For one scene, in one process: the single-process render time (warm: kernels built, scene
prepared once before timing), then the same image on LocalClusters of 1 and 2 worker
processes (after one warm-up render per cluster, so workers have their device, programs and
scene session), split into ``--units`` camera-sample sets. Writes JSON and a plot into
``bench_out/`` and prints a model of N workers built from the measurements:

    T(N) = t_fixed + ceil(U / N) * t_unit

with t_unit the mean task time of the 1-worker run (that worker had the machine to itself)
and t_fixed the rest of its wall time (the scene scatter, scheduling latency, the summation):
a model of N workers on N machines like this one. The model says where adding workers stops
paying: when ceil(U / N) reaches 1, or when t_fixed dominates. On a 2-core machine PoCL
already runs one process on both cores, so two worker processes share them.

Usage: ``.venv/bin/python tools/bench_cluster.py [--scene builtin:shafts] [--units 8]``
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clscatter.cluster import Cluster  # noqa: E402
from clscatter.pipeline.render import render
from clscatter.scene import load_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="builtin:occluder")
    ap.add_argument("--set", dest="overrides", action="append",
                    default=["camera.resolution=[320,240]", "camera.spp=4"])
    ap.add_argument("--units", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "bench_out"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(exist_ok=True)

    scene = load_scene(args.scene, args.overrides)
    render(scene, show_progress=False)                       # warm: programs built
    single = min(_timed(lambda: render(scene, show_progress=False))[0] for _ in range(args.repeats))
    ref = render(scene, show_progress=False).image
    rows = [{"workers": 0, "seconds": single, "label": "single process"}]
    for n in (1, 2):
        with Cluster(workers=n) as c:
            c.render(args.scene, args.overrides, units=args.units, show_progress=False)  # warm-up
            best = None
            for _ in range(args.repeats):
                t, res = _timed(lambda: c.render(args.scene, args.overrides, units=args.units,
                                                 show_progress=False))
                if best is None or t < best[0]:
                    best = (t, res)
            t, res = best
            st = res.stats
            err = float(np.abs(res.image - ref).max() / max(ref.max(), 1e-30))
            rows.append({"workers": n, "seconds": t, "label": f"{n} worker(s)",
                         "task_seconds": st["cluster_task_seconds"],
                         "bytes_in": st["cluster_bytes_in"], "bytes_out": st["cluster_bytes_out"],
                         "max_rel_diff_vs_single": err})
    # T(N) = t_fixed + ceil(U / N) * t_unit with t_unit the mean task time of the 1-worker run
    # (that worker had the machine to itself) and t_fixed the rest of its wall time: a model
    # of N workers on N machines like this one
    one = rows[1]
    t_unit = float(np.mean(one["task_seconds"]))
    t_fixed = max(one["seconds"] - args.units * t_unit, 0.0)
    t_sched = 0.0
    model = {n: t_fixed + math.ceil(args.units / n) * t_unit for n in (1, 2, 4, 8, 16, 32)}
    record = {"scene": args.scene, "overrides": args.overrides, "units": args.units,
              "rows": rows, "model": {"t_unit": t_unit, "t_fixed": t_fixed, "t_sched": t_sched,
                                      "predicted_seconds": model}}
    (out / "cluster.json").write_text(json.dumps(record, indent=2))
    for r in rows:
        print(f"{r['label']:>16}: {r['seconds']:.3f} s" +
              (f"  (max rel. diff vs single {r['max_rel_diff_vs_single']:.1e})" if r["workers"] else ""))
    print(f"model: t_unit {t_unit:.3f} s, t_fixed {t_fixed:.3f} s; N workers on N machines, "
          "each as fast as this one")
    for n, t in model.items():
        print(f"  N = {n:>2}: {t:.3f} s predicted")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(5, 3.2))
        ax.plot(list(model), list(model.values()), "o--", label="model")
        ax.plot([r["workers"] for r in rows[1:]], [r["seconds"] for r in rows[1:]], "s",
                label="measured")
        ax.axhline(single, color="grey", lw=0.8, label="single process")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("workers")
        ax.set_ylabel("seconds")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "cluster.png", dpi=120)
    except ImportError:
        pass


def _timed(fn):
    t = time.perf_counter()
    r = fn()
    return time.perf_counter() - t, r


if __name__ == "__main__":
    main()
