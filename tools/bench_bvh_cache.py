#!/usr/bin/env python3
"""Benchmark: a large mesh's BVH built against read back from the cache on disk
(``clscatter/accel/bvh_cache.py``), as a user meets it: ``clscatter render`` of a scene
in a fresh process with an empty cache folder (the BVH is built and kept), then again
(it is read). ``--repeats`` such pairs, each with a new empty folder; the scene's
``bvh_build`` stage and the whole process's wall time from ``--stats``. The render
itself is kept small (``--method raymarch`` at 64 x 64, 1 spp) so that the preparation
shows.

Writes bench_out/bvh_cache.json (and docs/bench/bvh_cache.json unless ``--no-copy``).

    .venv/bin/python tools/bench_bvh_cache.py [--scene builtin:paper_bunny] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clscatter.device.cache import cache_dir  # noqa: E402


def render(scene: str, cache: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        st = Path(tmp) / "stats.json"
        cmd = [sys.executable, "-m", "clscatter", "render", scene, "--method", "raymarch",
               "-o", str(Path(tmp) / "img.npy"), "--stats", str(st), "--quiet",
               "--set", "camera.resolution=[64,64]", "--set", "camera.spp=1"]
        env = {**os.environ, "CLSCATTER_CACHE_DIR": str(cache)}
        t = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            raise SystemExit(proc.stderr.strip())
        s = json.loads(st.read_text())
    return {"wall_seconds": wall, "bvh_build_seconds": s["stages"]["bvh_build"],
            "bvh_cached": s["bvh_cached"], "triangles": s["triangles"], "device": s["device"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="builtin:paper_bunny")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-copy", action="store_true")
    args = ap.parse_args()
    render(args.scene, _kernel_cache())          # builds the kernels once, if need be
    pairs = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp)
            # the built kernels, not the BVHs: only the BVH is built in the first run
            shutil.copytree(_kernel_cache(), cache, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("bvh"))
            pairs.append({"first": render(args.scene, cache), "again": render(args.scene, cache)})
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    record = {"scene": args.scene, "commit": commit, "machine": platform.machine(),
              "cpus": os.cpu_count(), "pairs": pairs}
    out = ROOT / "bench_out" / "bvh_cache.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(out, ROOT / "docs" / "bench" / "bvh_cache.json")
    print(f"{args.scene}: {pairs[0]['first']['triangles']:,} triangles, commit {commit}")
    print("| run | bvh_build s (first, built) | again (read) | whole process s (first) | again |")
    print("|---|---|---|---|---|")
    for i, p in enumerate(pairs):
        f, a = p["first"], p["again"]
        assert not f["bvh_cached"] and a["bvh_cached"]
        print(f"| {i + 1} | {f['bvh_build_seconds']:.3f} | {a['bvh_build_seconds']:.3f} | "
              f"{f['wall_seconds']:.2f} | {a['wall_seconds']:.2f} |")


def _kernel_cache() -> Path:
    """The folder of built kernels this machine's renders use."""
    folder = cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    return folder


if __name__ == "__main__":
    main()
