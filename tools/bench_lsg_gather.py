#!/usr/bin/env python3
"""Benchmark: where LSG's gather spends its work, what the line tree's leaf size and its
spatial splits are worth, and which side should walk the tree, on the glass-ball caustic
(``tools/scenes/glass_ball_fog.toml``, or ``--scene``: a file or a built-in scene).

Each run is ``clscatter render --method lsg`` in a fresh process with the caustic
lighting segments only (``min_light_depth = 1``; ``--min-light-depth 0``: every lighting
segment, as ``lsg`` alone gathers them), one pass of each of ``--rays`` lighting
rays at ``--size``, with ``render.lsg.leaf_size`` set to each of ``--leaf-sizes``,
``render.lsg.spatial_split`` to each of ``--spatial-splits`` (0: the paper's tree, split
on the Plücker coordinates only) and ``render.lsg.queries`` to each of ``--queries``
(``views``: a tree over the lighting segments, a query per view segment; ``lights``: a
tree over the view segments, a query per lighting segment; its tree seconds are the view
tree's, built once per render; ``screen``: the camera's rays in screen cells, which each
lighting segment crosses, and the other view segments from the side with fewer segments;
its tree seconds hold the cells' build, once per render, and the tree the others need);
the settings take turns ``--repeats`` times, so drift on a shared machine falls on all
alike. Recorded from
``--stats`` for every run: the gather's and the tree build's seconds, the view and kept
lighting segments, the pairs an exhaustive gather would test, the points in the leaves
the walk reached (the culling of the tree: Plücker slabs and the nodes' 3-D boxes; for
the screen cells, the view segments of the cells visited), the exact pair tests and the
valid pairs. Prints a markdown table of the medians and writes
bench_out/<record>.json (and docs/bench/<record>.json unless ``--no-copy``; ``--record``,
default ``lsg_gather``).

    .venv/bin/python tools/bench_lsg_gather.py [--size 160 120] [--rays 50000]
        [--leaf-sizes 4 16] [--spatial-splits 0 8] [--queries views] [--repeats 2] [--no-copy]
"""
from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("gather_seconds", "tree_build_seconds", "view_segments", "lsg_screen_segments",
        "lsg_light_segments_kept",
        "pair_tests_bruteforce", "lsg_leaf_points_tested", "pair_tests", "valid_pairs")


def run(scene: Path, size: tuple[int, int], rays: int, leaf: int, split: float,
        queries: str = "views", depth: int = 1) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        st = Path(tmp) / "stats.json"
        cmd = [sys.executable, "-m", "clscatter", "render", str(scene), "--method", "lsg",
               "-o", str(Path(tmp) / "img.npy"), "--stats", str(st), "--no-progress",
               "--time-budget", "0", "--set", f"camera.resolution=[{size[0]},{size[1]}]",
               "--set", f"render.lsg.min_light_depth={depth}", "--set", f"render.lsg.light_rays={rays}",
               "--set", f"render.lsg.leaf_size={leaf}",
               "--set", f"render.lsg.spatial_split={split}",
               "--set", f"render.lsg.queries=\"{queries}\""]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(proc.stderr.strip())
        s = json.loads(st.read_text())
    return {k: s.get(k) for k in KEYS + ("device",)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "tools" / "scenes" / "glass_ball_fog.toml"))
    ap.add_argument("--size", type=int, nargs=2, default=[160, 120])
    ap.add_argument("--rays", type=int, nargs="+", default=[50_000])
    ap.add_argument("--leaf-sizes", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--spatial-splits", type=float, nargs="+", default=[0.0, 8.0])
    ap.add_argument("--queries", nargs="+", default=["views"],
                    choices=["views", "lights", "screen"])
    ap.add_argument("--min-light-depth", type=int, default=1,
                    help="render.lsg.min_light_depth (1: the caustic lighting segments only)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-copy", action="store_true")
    ap.add_argument("--record", default="lsg_gather",
                    help="name of the JSON written (bench_out/ and docs/bench/)")
    args = ap.parse_args()
    configs = [(n, ls, sp, q) for n in args.rays for ls in args.leaf_sizes
               for sp in args.spatial_splits for q in args.queries]
    runs: dict[tuple, list[dict]] = {c: [] for c in configs}
    for _ in range(args.repeats):
        for n, ls, sp, q in configs:
            runs[n, ls, sp, q].append(run(Path(args.scene), tuple(args.size), n, ls, sp, q,
                                             args.min_light_depth))
            print(f"rays {n}, leaf_size {ls}, spatial_split {sp:g}, queries {q}: gather "
                  f"{runs[n, ls, sp, q][-1]['gather_seconds']:.2f} s", file=sys.stderr)
    rows = []
    for (n, ls, sp, q), rs in runs.items():
        row = {"rays": n, "leaf_size": ls, "spatial_split": sp, "queries": q,
               **{k: rs[0][k] for k in KEYS if "seconds" not in k}}
        for k in ("gather_seconds", "tree_build_seconds"):
            row[k] = statistics.median(r[k] for r in rs)
            row[k + "_all"] = [r[k] for r in rs]
        rows.append(row)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    record = {"scene": Path(args.scene).name, "size": args.size, "rays": args.rays,
              "queries": args.queries, "min_light_depth": args.min_light_depth,
              "commit": commit, "machine": platform.processor() or platform.machine(),
              "device": next(iter(runs.values()))[0]["device"], "rows": rows}
    out = ROOT / "bench_out" / f"{args.record}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(out, ROOT / "docs" / "bench" / f"{args.record}.json")
    print("| rays | leaf_size | spatial_split | queries | gather s (median) | tree s | "
          "leaf points tested | exact pair tests | valid pairs | exhaustive pairs |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['rays']:,} | {r['leaf_size']} | {r['spatial_split']:g} | {r['queries']} | "
              f"{r['gather_seconds']:.2f} | "
              f"{r['tree_build_seconds']:.2f} | "
              f"{r['lsg_leaf_points_tested']:,} | {r['pair_tests']:,} | {r['valid_pairs']:,} | "
              f"{r['pair_tests_bruteforce']:,} |")


if __name__ == "__main__":
    main()
