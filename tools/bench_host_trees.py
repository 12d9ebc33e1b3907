#!/usr/bin/env python3
"""Benchmark: the host-side tree work that a GPU leaves: the shared median-split build
(``clscatter/estimators/median_split.py``) of LSG's line tree and of the photon maps'
balanced point tree, on one thread against its subtrees on threads, LSG's whole chunk
preparation (``prepare_lines``: clipping, Plücker points, the tree, the node boxes), and
the ray map's lazy refinement with coherent queries walking one at a time against in
groups (``knn_queries.REFINE_GROUP``).

* Trees: random points (lines through a unit cube for the line tree, with their start
  points as ``split_extra`` as LSG does; points in a cube for the point tree), built
  ``--repeats`` times per setting, the settings taking turns; the least time of each. The
  one-thread build is the same code with ``PARALLEL_MIN_POINTS`` and
  ``row_chunks.ROW_CHUNK`` above the size.
* The refinement: the table-edge scene of ``tools/bench_surface_equal_time.py`` (160x120,
  4 spp, ``raymap`` alone, 4 passes of 20,000 lighting rays, no budget), the stage
  ``raymap_refine`` summed over the passes and the tree's nodes at the end; group 1 and
  the default take turns ``--repeats`` times, and the images must agree.

Writes bench_out/host_trees.json (and docs/bench/host_trees.json unless ``--no-copy``)
and prints markdown tables.

    .venv/bin/python tools/bench_host_trees.py [--repeats 3] [--no-copy]
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import clscatter.estimators.knn_queries as knn_queries  # noqa: E402
import clscatter.estimators.median_split as median_split  # noqa: E402
import clscatter.estimators.row_chunks as row_chunks  # noqa: E402
from clscatter.device import structs  # noqa: E402
from clscatter.estimators.line_gather import LEAF_SIZE, SPATIAL_SPLIT, prepare_lines  # noqa: E402
from clscatter.estimators.line_tree import build_linetree  # noqa: E402
from clscatter.estimators.segment_tree import SegmentTree  # noqa: E402

OUT = ROOT / "bench_out"
NEVER = 1 << 62                   # PARALLEL_MIN_POINTS, ROW_CHUNK above any size: one thread


def _lines(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = rng.uniform(-1.0, 1.0, (n, 3))
    return a, u


def _least(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def trees(repeats: int) -> list[dict]:
    rows = []
    for n in (200_000, 1_160_000):
        a, u = _lines(n)
        pts = np.concatenate([u, np.cross(a, u)], axis=1).astype(np.float32)
        extra = (a * SPATIAL_SPLIT).astype(np.float32)
        rows.append({"tree": "line tree", "points": n,
                     **_threads(lambda: build_linetree(pts, LEAF_SIZE, extra), repeats)})
    for n in (1_000_000, 4_000_000):
        pts = np.random.default_rng(1).uniform(-1.0, 1.0, (n, 3)).astype(np.float32)
        rows.append({"tree": "balanced point tree", "points": n,
                     **_threads(lambda: SegmentTree.balanced(pts, 8), repeats)})
    n = 1_160_000
    a, u = _lines(n, 2)
    segs = np.zeros(n, structs.LIGHT_SEGMENT)
    segs["a"][:, :3] = a
    segs["b"][:, :3] = a + u * np.random.default_rng(3).uniform(0.1, 1.0, (n, 1))
    segs["flux"][:, :3] = 1.0
    prep = lambda: prepare_lines(segs, [-1, -1, -1], [1, 1, 1], 0.01, [0.1] * 3)  # noqa: E731
    rows.append({"tree": "prepare_lines (line tree and all)", "points": n,
                 **_threads(prep, repeats)})
    return rows


def _threads(fn, repeats: int) -> dict:
    """Least seconds of ``fn`` on one thread and with its subtrees and row chunks on
    threads, in turns."""
    one, many = np.inf, np.inf
    default, chunk = median_split.PARALLEL_MIN_POINTS, row_chunks.ROW_CHUNK
    try:
        for _ in range(repeats):
            median_split.PARALLEL_MIN_POINTS, row_chunks.ROW_CHUNK = NEVER, NEVER
            one = min(one, _least(fn, 1))
            median_split.PARALLEL_MIN_POINTS, row_chunks.ROW_CHUNK = default, chunk
            many = min(many, _least(fn, 1))
    finally:
        median_split.PARALLEL_MIN_POINTS, row_chunks.ROW_CHUNK = default, chunk
    return {"one_thread_seconds": one, "threads_seconds": many, "speedup": one / many}


def refinement(repeats: int) -> list[dict]:
    import bench_surface_equal_time as surface

    from clscatter.pipeline.render import render
    from clscatter.scene import scene_from_dict

    d = copy.deepcopy(surface.scenes((160, 120))["edge"])
    d.setdefault("render", {})
    d["render"].update(method="raymap", time_budget=0.0)
    d["render"]["raymap"] = {"medium": "none", "photons": 20_000, "passes": 4}
    default = knn_queries.REFINE_GROUP
    rows = {g: {"group": g, "refine_seconds": [], "tree_nodes": None} for g in (1, default)}
    images = {}
    try:
        render(scene_from_dict(copy.deepcopy(d), ROOT, "<bench>"), show_progress=False)   # warm
        for _ in range(repeats):
            for g in rows:
                knn_queries.REFINE_GROUP = g
                res = render(scene_from_dict(copy.deepcopy(d), ROOT, "<bench>"), show_progress=False)
                rows[g]["refine_seconds"].append(res.stats["stages"]["raymap_refine"])
                rows[g]["tree_nodes"] = res.stats["raymap_tree_nodes"]
                images[g] = res.image
    finally:
        knn_queries.REFINE_GROUP = default
    diff = float(np.abs(images[1] - images[default]).max() / max(np.abs(images[1]).max(), 1e-30))
    out = []
    for r in rows.values():
        r["refine_seconds_least"] = min(r["refine_seconds"])
        r["image_difference_of_peak"] = diff
        out.append(r)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-copy", action="store_true")
    args = ap.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    record = {"commit": commit, "machine": platform.machine(), "cpus": os.cpu_count(),
              "trees": trees(args.repeats), "refinement": refinement(args.repeats)}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "host_trees.json").write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(OUT / "host_trees.json", ROOT / "docs" / "bench" / "host_trees.json")
    print(f"commit {commit}, {record['cpus']} CPUs\n")
    print("| build | points | one thread s | subtrees on threads s | speed-up |")
    print("|---|---|---|---|---|")
    for r in record["trees"]:
        print(f"| {r['tree']} | {r['points']:,} | {r['one_thread_seconds']:.2f} | "
              f"{r['threads_seconds']:.2f} | {r['speedup']:.2f}x |")
    print("\n| ray-map refinement | refine s (4 passes, least of runs) | tree nodes | image difference (of peak) |")
    print("|---|---|---|---|")
    for r in record["refinement"]:
        print(f"| groups of up to {r['group']} | {r['refine_seconds_least']:.2f} | "
              f"{r['tree_nodes']:,} | {r['image_difference_of_peak']:.1e} |")


if __name__ == "__main__":
    main()
