#!/usr/bin/env python3
"""Benchmark: where epipolar meets its tolerance, and whether ``auto`` knows it beforehand.

The regime sweep of ``epi_sweep`` (clscatter/scene/builtin/epipolar.py: a 4 x 3 x 4 fog
box with four black pillars) over optical depth across the box (0.1 .. 30), camera
outside / inside the medium, light behind / beside / in front of the camera / along the
view axis, directional and spot lights. For every configuration, on the same view paths:

* ``epipolar`` at its defaults: whether its own error estimate sent the light to the ray
  marcher (``fell_back``), the estimate, time and relMSE;
* ``raymarch`` at its defaults (32 steps): time and relMSE;
* the reference: ``raymarch`` with ``--ref-steps`` steps;
* what ``auto`` decides from the scene alone (``Epipolar.unreliable``: '' when it may
  pick epipolar) and whether that was right: ``auto_picks_a_fallback`` lists the
  configurations where auto would pick epipolar and epipolar then falls back (it must be
  empty), ``passed_over_but_swept`` the ones auto passes over although epipolar would
  have met its tolerance (the rule's conservatism).

Only the medium pass is timed (scene preparation and view paths are shared). Writes
bench_out/epipolar_regimes.json and .png (``epipolar_regimes_WxH`` at another ``--res``)
and copies both to docs/bench/.

    python3 tools/bench_epipolar_regimes.py [--res 160x120] [--depths 0.1,1,3,5,7,10,15,30]
"""
from __future__ import annotations

import argparse
import itertools
import platform
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from clscatter.device import get_engine  # noqa: E402
from clscatter.io.image import relmse
from clscatter.io.stats import Stats, progress, write_json
from clscatter.methods.epipolar import Epipolar  # noqa: E402
from clscatter.methods.raymarch import RayMarch  # noqa: E402
from clscatter.scene.builtin.epipolar import epi_sweep  # noqa: E402
from clscatter.scene.loader import scene_from_dict  # noqa: E402
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

OUT = REPO / "bench_out"
DOCS = REPO / "docs" / "bench"
KINDS = ("directional", "spot")
CAMERAS = ("outside", "inside")
LIGHTS = ("behind", "beside", "front", "axis")


def timed(method, ps, paths):
    """(image, seconds, stats) of one render of ``method``."""
    st = Stats()
    t = time.perf_counter()
    img = method.run(ps, paths, st, show_progress=False).radiance()
    return img, time.perf_counter() - t, st.values


def run_config(engine, kind, cam, light, depth, res, ref_steps) -> dict:
    d = epi_sweep(depth, light, cam, kind, res)
    scene = scene_from_dict(d)
    reason = Epipolar.unreliable(scene)
    ps = prepare_scene(scene, engine)
    try:
        paths = trace_view_paths(ps, show_progress=False)
        ref = RayMarch({"steps": ref_steps}).run(ps, paths, Stats(), False).radiance()
        rm, t_rm, _ = timed(RayMarch({}), ps, paths)
        ep, t_ep, st = timed(Epipolar({}), ps, paths)
    finally:
        ps.release()
    info = st["epipolar_lights"][0]
    return {"kind": kind, "camera": cam, "light": light, "depth": depth,
            "fell_back": "fallback" in info,
            "estimate": float(info["svd_error"]["rms"]) if "svd_error" in info else None,
            "auto_passes_over": reason,
            "epipolar": {"seconds": t_ep, "relmse": relmse(ep, ref)},
            "raymarch": {"seconds": t_rm, "relmse": relmse(rm, ref)}}


def plot(result: dict, path: Path) -> None:
    """One row per (kind, camera, light), one column per depth: green swept, red fell
    back; a cross where auto passes epipolar over."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = list(itertools.product(KINDS, CAMERAS, LIGHTS))
    depths = result["depths"]
    grid = np.full((len(rows), len(depths)), np.nan)
    fig, ax = plt.subplots(figsize=(3.0 + 0.7 * len(depths), 0.4 * len(rows) + 1.5))
    for r in result["configs"]:
        i = rows.index((r["kind"], r["camera"], r["light"]))
        j = depths.index(r["depth"])
        grid[i, j] = 1.0 if r["fell_back"] else 0.0
        if r["auto_passes_over"]:
            ax.plot(j, i, "kx", ms=9)
    ax.imshow(grid, cmap=matplotlib.colors.ListedColormap(["#8c8", "#e77"]), vmin=0, vmax=1,
              aspect="auto")
    ax.set_xticks(range(len(depths)), [f"{x:g}" for x in depths])
    ax.set_yticks(range(len(rows)), [" ".join(r) for r in rows], fontsize=8)
    ax.set_xlabel("optical depth across the box")
    ax.set_title(f"epipolar at {result['resolution']}: green swept, red fell back; "
                 "x: auto picks raymarch", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", default="160x120", help="image size WxH (1 spp)")
    ap.add_argument("--depths", default="0.1,1,3,5,7,10,15,30")
    ap.add_argument("--ref-steps", type=int, default=256)
    ap.add_argument("--no-copy", action="store_true", help="do not copy the results to docs/bench")
    args = ap.parse_args(argv)
    res = tuple(int(x) for x in args.res.lower().split("x"))
    depths = [float(x) for x in args.depths.split(",")]
    engine = get_engine()
    t0 = time.perf_counter()
    configs = []
    todo = list(itertools.product(KINDS, CAMERAS, LIGHTS, depths))
    with progress(len(todo), "regimes", True) as bar:
        for kind, cam, light, depth in todo:
            configs.append(run_config(engine, kind, cam, light, depth, res, args.ref_steps))
            bar.update(1)
    name = lambda r: f"{r['kind']} {r['camera']} {r['light']} depth {r['depth']:g}"
    result = {
        "device": engine.name, "host": platform.node(), "python": platform.python_version(),
        "resolution": f"{res[0]}x{res[1]}", "depths": depths, "ref_steps": args.ref_steps,
        "tolerance": Epipolar({}).settings.svd_tolerance, "configs": configs,
        "fell_back": [name(r) for r in configs if r["fell_back"]],
        "auto_picks_a_fallback": [name(r) for r in configs
                                  if r["fell_back"] and not r["auto_passes_over"]],
        "passed_over_but_swept": [name(r) for r in configs
                                  if r["auto_passes_over"] and not r["fell_back"]],
        "raymarch_relmse_max": max(r["raymarch"]["relmse"] for r in configs),
        "epipolar_relmse_max": max(r["epipolar"]["relmse"] for r in configs),
    }
    result["seconds_total"] = time.perf_counter() - t0
    OUT.mkdir(exist_ok=True)
    stem = "epipolar_regimes" + ("" if res == (160, 120) else f"_{res[0]}x{res[1]}")
    write_json(OUT / f"{stem}.json", result)
    plot(result, OUT / f"{stem}.png")
    if not args.no_copy:
        for ext in ("json", "png"):
            shutil.copy(OUT / f"{stem}.{ext}", DOCS / f"{stem}.{ext}")
    print(f"{len(configs)} configurations, {len(result['fell_back'])} fell back; auto picks a "
          f"fallback in {len(result['auto_picks_a_fallback'])} "
          f"{result['auto_picks_a_fallback']}; passed over but swept: "
          f"{len(result['passed_over_but_swept'])}; relMSE max: raymarch "
          f"{result['raymarch_relmse_max']:.2e}, epipolar {result['epipolar_relmse_max']:.2e}")
    print(f"total {result['seconds_total']:.0f} s; wrote {OUT / (stem + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
