"""What a user gets at the defaults: whole-process time, warm re-renders, where time goes.

For every built-in scene (or ``--scenes``) and every method that applies to it, at the
scene's own settings (or ``--set`` overrides, e.g. 640x480 and 4 spp):

* **whole process**: ``clscatter render`` in a fresh Python process, wall time measured
  outside it (imports, device choice, scene loading, rendering, writing the image);
* **stages**: the ``--stats`` breakdown of that run, and the share outside every stage;
* **host share**: of the render's seconds (after device choice), those the host spent
  outside waits on the device (``host_seconds / render_seconds`` of ``--stats``);
* **warm re-render after a light move**: a :class:`~clscatter.pipeline.session.RenderSession` renders,
  then the first light moves by 5% of the scene size (or of its direction), back and forth,
  three times; the median re-render time, and the host share of that re-render;
* **the process floor**: a fresh Python process that only imports NumPy and PyOpenCL and
  makes a context and queue on the device the renders used (the least of several runs),
  and per scene the speed-up over ``raymarch`` that no method could beat there: raymarch's
  whole process over (floor + the view paths' seconds, which every method on these scenes
  pays before its own work), printed beside the speed-up measured;
* **error** against a converged reference (``raymarch`` with many steps and 4x the samples
  for direct-only scenes; for caustic scenes the reference is ``lsg`` with many rays), as
  relMSE of the whole image.

Writes ``bench_out/defaults.json`` and ``bench_out/defaults.png`` (time per scene and
method, whole process vs warm). Usage::

    .venv/bin/python tools/bench_defaults.py --scenes shafts occluder --set camera.resolution=[640,480]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clscatter.io.image import read_image, relmse
from clscatter.methods import all_methods  # noqa: E402
from clscatter.pipeline.planner import needed_terms
from clscatter.pipeline.render import render
from clscatter.pipeline.session import RenderSession
from clscatter.scene import BUILTIN, load_scene  # noqa: E402

WARM_MOVES = 3            # light moves per warm measurement (the median is reported)
FLOOR_RUNS = 5            # fresh processes timed for the process floor (the least is kept)

FLOOR_CODE = """
import sys, numpy, pyopencl as cl
plat, name = sys.argv[1].split(" / ", 1)
dev = [d for p in cl.get_platforms() if p.name.strip() == plat
       for d in p.get_devices() if d.name.strip() == name][0]
cl.CommandQueue(cl.Context([dev]))
"""


def methods_for(scene) -> list[str]:
    """``auto`` plus every method whose terms cover something the scene needs and whose
    assumptions hold."""
    terms, _ = needed_terms(scene)
    out = ["auto"]
    for name, cls in all_methods().items():
        if set(terms) & set(cls.TERMS) and not cls.suits(scene):
            out.append(name)
    return out


def whole_process(spec: str, method: str, sets: list[str]) -> tuple[float, dict, np.ndarray]:
    with tempfile.TemporaryDirectory() as tmp:
        out, st = Path(tmp) / "o.npy", Path(tmp) / "s.json"
        cmd = [sys.executable, "-m", "clscatter", "render", spec, "--method", method, "-o",
               str(out), "--stats", str(st), "--no-progress"]
        for s in sets:
            cmd += ["--set", s]
        t = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                           env={**os.environ, "PYTHONPATH": os.pathsep.join(
                               [str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])})
        wall = time.perf_counter() - t
        if r.returncode != 0:
            raise RuntimeError(r.stderr)
        return wall, json.loads(st.read_text()), read_image(out)


def process_floor(device: str, runs: int = FLOOR_RUNS) -> list[float]:
    """Wall seconds of ``runs`` fresh Python processes that import NumPy and PyOpenCL and
    make a context and queue on ``device`` (``"platform / device"`` as ``--stats`` names
    it), and nothing else: what any render in a process of its own pays first."""
    walls = []
    for _ in range(runs):
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", FLOOR_CODE, device], check=True, cwd=ROOT)
        walls.append(time.perf_counter() - t)
    return walls


def speedups(rows: list[dict], floor: float) -> None:
    """Per scene, each row's whole-process speed-up over ``raymarch`` (``speedup``) and the
    most any method could reach there with this engine's view paths (``speedup_bound``:
    raymarch's whole process over the process floor plus the row's view paths, which every
    method pays before its own work); ``raymarch_wall`` is the time they divide."""
    by_scene = {r["scene"]: r["wall"] for r in rows if r["method"] == "raymarch"}
    for r in rows:
        base = by_scene.get(r["scene"])
        if base is None:
            continue
        r["raymarch_wall"] = base
        r["speedup"] = base / r["wall"]
        r["speedup_bound"] = base / (floor + r["stages"].get("view_paths", 0.0))


def warm_light_move(spec: str, method: str, sets: list[str],
                    moves: int = WARM_MOVES) -> tuple[float, list[str], dict, list[float]]:
    """Render once, then move the first light ``moves`` times (by 5% of the scene size,
    or of its direction, back and forth) and time each re-render: returns the median
    time, the stages it ran and its ``--stats`` (the run of the median time), and every
    time. One re-render alone moves by 10-20% with the machine's state."""
    scene = load_scene(spec, sets)
    if not scene.lights:
        return float("nan"), [], {}, []
    bb = scene.bbox()
    size = float(np.max(bb[1] - bb[0])) if bb is not None else 1.0
    light = scene.lights[0]
    runs = []
    with RenderSession.from_source(spec, sets, method=method) as s:
        s.render(show_progress=False)
        for k in range(moves):
            step = 0.05 * (1 + k % 2)          # 1 and 2 steps from the start, alternately
            if light.type == "directional":
                d = np.asarray(light.direction, float) + np.array([step, 0.0, 0.0])
                s.set([f"lights[0].direction=[{d[0]:.6g}, {d[1]:.6g}, {d[2]:.6g}]"])
            else:
                p = np.asarray(light.position, float) + np.array([step * size, 0.0, 0.0])
                s.set([f"lights[0].position=[{p[0]:.6g}, {p[1]:.6g}, {p[2]:.6g}]"])
            t = time.perf_counter()
            res = s.render(show_progress=False)
            runs.append((time.perf_counter() - t, res.stats))
    order = sorted(range(len(runs)), key=lambda i: runs[i][0])
    t_med, st = runs[order[len(runs) // 2]]
    return t_med, st["stages_run"], st, [r[0] for r in runs]


def reference(spec: str, sets: list[str], caustic: bool) -> np.ndarray:
    if caustic:
        extra = ["render.method=lsg", "render.lsg.light_rays=4000000"]
    else:
        extra = ["render.method=raymarch", "render.raymarch.steps=512"]
    return render(load_scene(spec, sets + extra), show_progress=False).image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=sorted(BUILTIN))
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out", default=str(ROOT / "bench_out"))
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--methods", nargs="*", default=None, help="only these (default: all that apply)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    rows = []
    for name in args.scenes:
        spec = f"builtin:{name}"
        scene = load_scene(spec, args.overrides)
        terms, _ = needed_terms(scene)
        ref = None if args.no_reference else reference(spec, args.overrides, "caustics" in terms)
        for method in methods_for(scene):
            if args.methods and method not in args.methods:
                continue
            wall, st, img = whole_process(spec, method, args.overrides)
            warm, ran, wst, warm_all = warm_light_move(spec, method, args.overrides)
            covered = sum(st["stages"].values())
            row = {"scene": name, "method": method, "ran": st["method"], "wall": wall,
                   "device": st["device"],
                   "seconds_total": st["seconds_total"], "stages": st["stages"],
                   "outside_stages": st["seconds_total"] - covered,
                   "process_overhead": wall - st["seconds_total"], "warm_light_move": warm,
                   "warm_light_moves": warm_all, "warm_stages_run": ran,
                   # host time outside device waits, as a share of the render (--stats)
                   "render_seconds": st.get("render_seconds"),
                   "host_seconds": st.get("host_seconds"),
                   "host_fraction": st["host_seconds"] / max(st["render_seconds"], 1e-9)
                   if "host_seconds" in st else None,
                   "warm_stages": wst.get("stages", {}),
                   "warm_host_fraction": wst["host_seconds"] / max(wst["render_seconds"], 1e-9)
                   if "host_seconds" in wst else None,
                   "relmse": None if ref is None else float(relmse(img, ref))}
            rows.append(row)
            print(f"{name:>16} {method:>9} ({st['method']}): whole {wall:6.2f} s, in-process "
                  f"{st['seconds_total']:6.2f} s (host {row['host_fraction'] or 0:.0%}), warm "
                  f"light move {warm:6.3f} s (host {row['warm_host_fraction'] or 0:.0%})"
                  + ("" if ref is None else f", relMSE {row['relmse']:.2e}"), flush=True)
    floors = process_floor(rows[0]["device"]) if rows else []
    floor = min(floors, default=0.0)
    speedups(rows, floor)
    if floors:
        print(f"\nprocess floor (Python, NumPy, PyOpenCL, a context on {rows[0]['device']}): "
              f"{floor:.3f} s (least of {len(floors)}; all: "
              + ", ".join(f"{f:.3f}" for f in floors) + ")")
    for r in rows:
        if "speedup" in r and r["method"] != "raymarch":
            print(f"{r['scene']:>16} {r['method']:>9}: {r['speedup']:.1f}x raymarch's whole "
                  f"process; at most {r['speedup_bound']:.1f}x with floor + view paths "
                  f"({floor:.2f} + {r['stages'].get('view_paths', 0.0):.2f} s) and no time "
                  f"of its own; 10x needs {r['raymarch_wall'] / 10:.2f} s")
    (out / "defaults.json").write_text(json.dumps(
        {"overrides": args.overrides, "process_floor": floors, "rows": rows}, indent=2))
    print("\n| scene | method | whole process s | vs raymarch (at most) | host share | "
          "warm light move s | warm host share | relMSE |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        rel = "" if r["relmse"] is None else f"{r['relmse']:.1e}"
        vs = (f"{r['speedup']:.1f}x ({r['speedup_bound']:.1f}x)"
              if "speedup" in r and r["method"] != "raymarch" else "")
        print(f"| {r['scene']} | {r['method']} | {r['wall']:.2f} | {vs} "
              f"| {r['host_fraction'] or 0:.0%} | {r['warm_light_move']:.2f} "
              f"| {r['warm_host_fraction'] or 0:.0%} | {rel} |")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        labels = [f"{r['scene']}\n{r['method']}" for r in rows]
        x = np.arange(len(rows))
        fig, ax = plt.subplots(figsize=(max(6, 0.55 * len(rows)), 3.6))
        ax.bar(x - 0.2, [r["wall"] for r in rows], 0.4, label="whole process")
        ax.bar(x + 0.2, [r["warm_light_move"] for r in rows], 0.4, label="warm, light moved")
        ax.set_xticks(x, labels, rotation=90, fontsize=6)
        ax.set_ylabel("seconds")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "defaults.png", dpi=120)
    except ImportError:
        pass


if __name__ == "__main__":
    main()
