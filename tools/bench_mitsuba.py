"""Equal time against Mitsuba 3: relMSE x seconds, clscatter against Mitsuba's volpath.

For each outside-reference scene of ``tests/data/mitsuba/`` (48x36; the committed image is
Mitsuba ``volpath``, ``max_depth = 2``, 65,536 spp), in one process:

* Mitsuba 3 (``scalar_rgb``, the conversion of ``tools/mitsuba_reference.py``) at increasing
  spp: seconds and relMSE against the reference;
* clscatter at increasing quality (``auto`` and ``raymarch``: spp x steps): seconds of a
  render (warm kernels, scene prepared; fastest of three seeds) and relMSE against the same
  reference. Mitsuba's time is the faster of two renders.

Printed and written to ``bench_out/mitsuba.json``: every run, and the efficiency
relMSE x seconds (lower is better; for an unbiased estimator it is roughly constant along
the run, so it compares renderers independently of the time spent), best per renderer and
scene. The reference's own noise (relMSE ~4e-6) floors what can be resolved.

Light that Mitsuba's unidirectional ``volpath`` cannot find is not compared: a point light
seen through glass (the caustic scenes) has no path from the camera that hits a delta light
through a specular surface, so its image lacks the caustic entirely; clscatter's caustic
methods (``lsg``, ``raymap``) are the only estimate there.

Usage: ``.venv/bin/python tools/bench_mitsuba.py`` (needs ``pip install mitsuba``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from clscatter.io.image import relmse
from clscatter.pipeline.session import RenderSession
from clscatter.scene import load_scene  # noqa: E402

DATA = ROOT / "tests" / "data" / "mitsuba"


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench_out"))
    ap.add_argument("--mitsuba-spp", type=int, nargs="*", default=[4, 16, 64, 256, 1024])
    args = ap.parse_args()
    from mitsuba_reference import render_mitsuba
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    record = {}
    for toml in sorted(DATA.glob("*.toml")):
        name = toml.stem
        ref = np.load(DATA / f"{name}.npy")
        scene = load_scene(toml)
        runs = []
        for spp in args.mitsuba_spp:
            sec, img = min((timed(lambda: render_mitsuba(scene, spp=spp, seed=1)) for _ in range(2)),
                           key=lambda t: t[0])
            runs.append({"renderer": "mitsuba", "setting": f"{spp} spp", "seconds": sec,
                         "relmse": float(relmse(img, ref))})
        for method, settings in (("auto", [(1, None), (4, None), (16, None)]),
                                 ("raymarch", [(1, 16), (4, 32), (16, 64), (64, 64)])):
            for spp, steps in settings:
                sets = [f"camera.spp={spp}"] + ([f"render.raymarch.steps={steps}"] if steps else [])
                with RenderSession.from_source(str(toml), sets, method=method) as s:
                    s.render(show_progress=False)                  # warm: kernels, BVH
                    best = None
                    for seed in (1, 2, 3):                         # fresh samples, same work
                        s.set([f"render.seed={seed}"])
                        t = timed(lambda: s.render(show_progress=False))
                        best = t if best is None or t[0] < best[0] else best
                    sec, res = best
                runs.append({"renderer": f"clscatter {method} ({res.stats['method']})",
                             "setting": f"{spp} spp" + (f", {steps} steps" if steps else ""),
                             "seconds": sec, "relmse": float(relmse(res.image, ref))})
        for r in runs:
            r["relmse_x_seconds"] = r["relmse"] * r["seconds"]
        best = {}
        for r in runs:
            key = r["renderer"]
            if key not in best or r["relmse_x_seconds"] < best[key]["relmse_x_seconds"]:
                best[key] = r
        record[name] = {"runs": runs, "best": best}
        print(name)
        for r in runs:
            print(f"  {r['renderer']:>28} {r['setting']:>18}: {r['seconds']:7.3f} s  relMSE "
                  f"{r['relmse']:.2e}  relMSE x s {r['relmse_x_seconds']:.2e}")
        m = best["mitsuba"]["relmse_x_seconds"]
        for k, r in best.items():
            if k != "mitsuba":
                print(f"  best {k}: {m / r['relmse_x_seconds']:.1f}x Mitsuba's efficiency")
    (out / "mitsuba.json").write_text(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
