#!/usr/bin/env python3
"""Benchmark: whole-render time budgets on a caustic scene, and the render's own error
estimate against its error measured against a converged render.

On ``tools/scenes/glass_ball_fog.toml`` (a glass ball over a floor in a fog box under a
25-degree spot light, 320x240, 4 spp; or ``--scene``), each run is ``clscatter render`` in a
fresh process, its wall time measured outside it:

* ``auto`` at its defaults (its 10 s budget), and with ``--time-budget`` 5 and 20 (or
  ``--budgets``);
* a converged reference: ``auto`` without a budget and with ``--reference-passes``
  progressive passes of ``--reference-rays`` lighting rays (cached under
  bench_out/budget/, keyed by the scene file and those settings).

Each row records the whole-process seconds, whether the budget held (within 20%), the
stages from ``--stats``, the passes LSG and the ray map ran and their sizes (and what sized
the ray map's: its first-pass cost learnt on this device by earlier renders, the default
run's included), ``error_estimate`` (noise and
blur parts) and the relMSE against the reference. Writes bench_out/budget/bench_budget.json
(and a copy in docs/bench/budget.json unless ``--no-copy``) and prints a markdown table.

    .venv/bin/python tools/bench_budget.py [--scene S.toml] [--budgets 5 20] [--out DIR]
        [--name NAME] [--no-copy] [--set KEY=VALUE ...]

The device is the engine's choice (``$CLSCATTER_DEVICE`` picks one) and is recorded.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clscatter.io.image import relmse  # noqa: E402

OUT = ROOT / "bench_out" / "budget"
PY = sys.executable


def run(scene: Path, tag: str, extra: list[str]) -> dict:
    """One ``clscatter render`` in a fresh process: wall seconds, stats, image."""
    img, st = OUT / f"{tag}.npy", OUT / f"{tag}.json"
    cmd = [PY, "-m", "clscatter", "render", str(scene), "-o", str(img), "--stats", str(st),
           "--no-progress", *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{tag}: {proc.stderr.strip()}")
    notes = [ln for ln in proc.stderr.splitlines() if "note:" in ln]
    return {"wall_seconds": wall, "stats": json.loads(st.read_text()), "image": np.load(img),
            "notes": notes}


def reference(scene: Path, rays: int, passes: int) -> np.ndarray:
    key = hashlib.sha1(scene.read_bytes() + f"{rays}/{passes}".encode()).hexdigest()[:12]
    path = OUT / f"reference_{key}.npy"
    if path.exists():
        return np.load(path)
    print(f"reference: {passes} passes of {rays} lighting rays (cached as {path.name}) ...",
          file=sys.stderr)
    r = run(scene, f"reference_{key}", ["--time-budget", "0",
                                        "--set", f"render.lsg.light_rays={rays}",
                                        "--set", f"render.lsg.passes={passes}"])
    np.save(path, r["image"])
    return r["image"]


def row(name: str, budget: float | None, r: dict, ref: np.ndarray) -> dict:
    s = r["stats"]
    held = budget is None or r["wall_seconds"] <= 1.2 * budget
    return {"run": name, "budget_seconds": budget, "wall_seconds": round(r["wall_seconds"], 3),
            "budget_held": held, "method": s["method"], "device": s.get("device"),
            "stages": {k: round(v, 3) for k, v in s["stages"].items() if v >= 0.01},
            "lsg_passes": s.get("lsg_passes"), "lsg_pass_rays": s.get("lsg_pass_rays"),
            "lsg_stopped_by": s.get("lsg_stopped_by"),
            "raymap_pass_rays": s.get("raymap_pass_rays"),
            "raymap_sized_from": s.get("raymap_sized_from"),
            "error_estimate": s.get("error_estimate"),
            "error_estimate_noise": s.get("error_estimate_noise"),
            "error_estimate_bias": s.get("error_estimate_bias"),
            "relmse": relmse(r["image"], ref), "notes": r["notes"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "tools" / "scenes" / "glass_ball_fog.toml"))
    ap.add_argument("--budgets", type=float, nargs="*", default=[5.0, 20.0])
    ap.add_argument("--reference-rays", type=int, default=200_000)
    ap.add_argument("--reference-passes", type=int, default=8)
    ap.add_argument("--no-copy", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="results folder (default bench_out/budget)")
    ap.add_argument("--name", default="budget", help="docs/bench/NAME.json to copy the results to")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene override for every budgeted run (not the reference)")
    args = ap.parse_args()
    global OUT
    if args.out is not None:
        OUT = args.out.resolve()
    OUT.mkdir(parents=True, exist_ok=True)
    scene = Path(args.scene).resolve()
    ref = reference(scene, args.reference_rays, args.reference_passes)
    sets = [x for kv in args.sets for x in ("--set", kv)]
    rows = [row("auto (default budget)", 10.0, run(scene, "auto_default", sets), ref)]
    for b in args.budgets:
        rows.append(row(f"auto --time-budget {b:g}", b,
                        run(scene, f"auto_{b:g}", ["--time-budget", str(b), *sets]), ref))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    record = {"scene": scene.name, "commit": commit, "device": rows[0]["device"], "machine": platform.processor() or
              platform.machine(), "cpu_count": __import__("os").cpu_count(),
              "reference": {"lsg_light_rays": args.reference_rays,
                            "lsg_passes": args.reference_passes}, "sets": args.sets,
              "rows": rows}
    (OUT / "bench_budget.json").write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(OUT / "bench_budget.json", ROOT / "docs" / "bench" / f"{args.name}.json")
    print("| run | whole process s | budget held | LSG passes (rays each) | ray-map passes (rays "
          "each; sized from) | error estimate (noise + blur) | relMSE vs reference |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        rays = ", ".join(str(x) for x in (r["lsg_pass_rays"] or []))
        rm = r["raymap_pass_rays"] or []
        rm_s = f"{len(rm)} ({', '.join(str(x) for x in rm)}; {r['raymap_sized_from']})"
        est = r["error_estimate"]
        est_s = "-" if est is None else (f"{est:.2g} ({r['error_estimate_noise']:.2g} + "
                                         f"{r['error_estimate_bias']:.2g})")
        print(f"| {r['run']} | {r['wall_seconds']:.1f} | {'yes' if r['budget_held'] else 'no'} "
              f"| {r['lsg_passes']} ({rays}) | {rm_s} | {est_s} | {r['relmse']:.2g} |")


if __name__ == "__main__":
    main()
