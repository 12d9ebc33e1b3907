#!/usr/bin/env python3
"""Benchmark: the epipolar method (Baran et al. 2010) against brute-force ``raymarch``.

For each scene of rising shadow complexity (``epi_window``, ``epi_grille``,
``epi_forest``; clscatter/scene/builtin/epipolar.py), plus a thick fog seen from
outside with the sun behind the camera (``epi_fog``: optical depth 4.4, where the method
raises its SVD terms/light rays on its own error estimate), at 1280 x 960, 1 spp:

* a converged reference: ``raymarch`` with ``--ref-steps`` steps per view segment
  (cached in bench_out/, keyed by scene, size and steps);
* time against error (relMSE of the medium image, clscatter.io.image.relmse) for raymarch
  over its step count and for epipolar over its quality levels (light rays per slice,
  shadow-map size and slice spacing scaled together);
* the speed-up at equal error: each epipolar point against the raymarch time that
  reaches the same error, interpolated log-log on raymarch's curve; beyond raymarch's
  most accurate point extrapolated with its fitted convergence (relMSE ~ a S^-p) after
  removing the reference's own error (its "floor", the same fit at S = ref steps), and
  reported as a lower bound where the epipolar error is within 2x of that floor (each
  record says which: ``equal_error``);
* on ``epi_forest`` the complexity: time against resolution W (160 .. 1280) with the
  slices (one-pixel spacing), rays per slice (the samples), light rays d = 2 W and
  raymarch steps = W / 10 all growing with W, and the log-log slope (the paper's slope
  is against log(s r d) / 3, which is log W up to a constant here);
* the stage breakdown of the epipolar runs (maps, rectify, integrate, unrectify, ring),
  plus one run of ``epi_sun`` (the epipole on screen: the ring is ray marched).

Raymarch's error depends only on its step count (deterministic seeds), its time is
linear in it; equal-error times therefore come from the error curve (steps) and a
linear time model fitted to min-of-repeats runs, not from single noisy timings.

Only the medium pass is timed (``render``); scene preparation and view-path
tracing are shared by both methods and done once. Epipolar times are reported twice:
``seconds`` (everything, the ray-traced shadow map included) and ``seconds_scatter``
(without tracing the maps, which is how the paper timed itself). Each timing is the
minimum of ``--repeats`` runs (the machine may be shared; raymarch runs above 64
steps once). Writes
bench_out/epipolar.json and .png and copies both to docs/bench/.

    python3 tools/bench_epipolar.py [--quick] [--scenes epi_window,epi_grille] [--repeats 2]
"""
from __future__ import annotations

import argparse
import math
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from clscatter.device import get_engine
from clscatter.io.image import relmse
from clscatter.io.stats import Stats, write_json
from clscatter.methods.epipolar import Epipolar
from clscatter.methods.epipolar import geometry as geo
from clscatter.methods.raymarch import RayMarch
from clscatter.scene.loader import load_scene  # noqa: E402
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

SCENES = ("epi_window", "epi_grille", "epi_forest", "epi_fog")
DEFAULT_LEVEL = 4          # index of the method's default settings in epi_levels()
OUT = REPO / "bench_out"
DOCS = REPO / "docs" / "bench"


def prepared(name: str, w: int, h: int, engine):
    scene = load_scene(f"builtin:{name}", [f"camera.resolution=[{w}, {h}]", "camera.spp=1"])
    ps = prepare_scene(scene, engine)
    paths = trace_view_paths(ps, show_progress=False)
    return ps, paths


def timed(method, ps, paths, repeats: int):
    """(image, seconds, stats) of method.render: the fastest of ``repeats``."""
    best = None
    for _ in range(max(1, repeats)):
        st = Stats()
        t = time.perf_counter()
        img = method.run(ps, paths, st, show_progress=False).radiance()
        dt = time.perf_counter() - t
        if best is None or dt < best[1]:
            best = (img, dt, st)
    return best


def reference(name: str, ps, paths, w: int, h: int, steps: int) -> np.ndarray:
    OUT.mkdir(exist_ok=True)
    f = OUT / f"epipolar_ref_{name}_{w}x{h}_s{steps}.npy"
    if f.is_file():
        return np.load(f)
    print(f"  reference: raymarch {steps} steps ...", flush=True)
    t = time.perf_counter()
    img = RayMarch({"steps": steps}).run(ps, paths, Stats(), show_progress=True).radiance()
    print(f"  reference done in {time.perf_counter() - t:.1f} s", flush=True)
    np.save(f, img)
    return img


def auto_slices(ps, light: int = 0) -> int:
    cam = geo.CameraGeom.from_struct(ps.camera)
    axis = geo.make_axis(ps.lights[light], cam.origin)
    P, _ = geo.epipole(axis, cam)
    return len(geo.slice_points(P, cam.width, cam.height, 1.0))


def epi_levels(w: int, h: int, n_auto: int) -> list[dict]:
    """Quality levels: light rays, shadow map and slice spacing scaled together, from
    coarse (errors in raymarch's range) to the method's defaults (the fifth) and the
    paper's settings (the last: d = 4096 and a 4096^2 map at 1280 x 960)."""
    big = max(w, h)
    out = []
    for q, spacing in ((1 / 16, 8.0), (1 / 8, 4.0), (0.25, 2.0), (0.5, 1.5), (1.0, 1.0), (1.6, 1.0)):
        out.append({"light_rays": int(2 * big * q), "shadow_map": int(min(4096, max(128, 2 * big * q))),
                    "slices": int(round(n_auto / spacing)), "slice_spacing_px": spacing})
    return out


def raymarch_model(rm: list[dict], ref_steps: int) -> dict:
    """Raymarch's error and time as functions of its steps S, and the reference's floor.

    Errors are measured against a reference that is itself raymarch (``ref_steps``), so
    a measured relMSE is the test's own error plus the reference's, ``floor``. The
    convergence exponent p (relMSE ~ a S^-p; stratified jittered samples give p ~ 2) is
    fitted where the floor is negligible (8 <= S <= ref_steps / 8), the floor is that
    law at S = ref_steps. Time is linear in S by construction: t = t0 + c S, fitted to
    the repeated (min-of-repeats) runs, which a shared machine disturbs least."""
    S = np.array([r["steps"] for r in rm], float)
    e = np.array([r["relmse"] for r in rm])
    t = np.array([r["seconds"] for r in rm])
    use = (S >= 8) & (S <= ref_steps / 8)
    if use.sum() < 2:
        use = S >= 0
    p, loga = np.polyfit(np.log(S[use]), np.log(e[use]), 1)
    p = -p
    floor = float(math.exp(loga) * ref_steps ** -p)
    rep = np.array([r["repeats"] > 1 for r in rm])
    rep = rep if rep.sum() >= 2 else np.ones_like(rep)
    c, t0 = np.polyfit(S[rep], t[rep], 1)
    return {"p": float(p), "a": float(math.exp(loga)), "floor": floor, "t0": float(max(t0, 0.0)),
            "c": float(c)}


def equal_error(model: dict, rm: list[dict], err: float) -> dict:
    """Raymarch steps that reach the measured relMSE ``err`` (both measured against the
    same reference, so the floor cancels) and their time by the linear model: steps by
    log-log interpolation between measured raymarch points where ``err`` lies in their
    range; beyond the most accurate point by the fitted power law after removing the
    floor. Where ``err`` is within 2x of the floor the true error cannot be resolved:
    the steps are then the reference's own and the result is a lower bound."""
    pts = sorted((r["relmse"], r["steps"]) for r in rm)
    steps, how = None, ""
    if err > pts[-1][0]:          # worse than raymarch's coarsest point
        steps, how = pts[-1][1], "beyond raymarch's coarsest point (upper bound)"
    for (e0, s0), (e1, s1) in zip(pts, pts[1:]):
        if steps is None and e0 <= err <= e1 and e1 > e0:
            f = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0))
            steps, how = math.exp(math.log(s0) + f * (math.log(s1) - math.log(s0))), "interpolated"
    if steps is None:
        floor = model["floor"]
        how = "lower bound (error at the reference's floor)" if err <= 2.0 * floor else "extrapolated"
        steps = (model["a"] / max(err - floor, floor)) ** (1.0 / model["p"])
    return {"steps": steps, "seconds": model["t0"] + model["c"] * steps, "how": how}


def raymarch_curve(ps, paths, ref, steps_list, repeats) -> list[dict]:
    """Raymarch over its step counts; runs up to 64 steps are repeated (min time)."""
    rm = []
    for steps in steps_list:
        reps = repeats if steps <= 64 else 1
        img, dt, _ = timed(RayMarch({"steps": steps}), ps, paths, reps)
        rm.append({"steps": steps, "seconds": dt, "repeats": reps, "relmse": relmse(img, ref)})
        print(f"  raymarch {steps:4d} steps: {dt:7.2f} s  relMSE {rm[-1]['relmse']:.3g}", flush=True)
    return rm


def bench_scene(name, w, h, engine, args) -> dict:
    print(f"[{name}] {w} x {h}", flush=True)
    ps, paths = prepared(name, w, h, engine)
    try:
        ref = reference(name, ps, paths, w, h, args.ref_steps)
        res = {"scene": name, "width": w, "height": h,
               "view_segments": len(paths.segments), "ref_steps": args.ref_steps}
        # warm-up: kernel builds out of the timings
        Epipolar({"light_rays": 64, "shadow_map": 64, "slices": 64}).run(ps, paths, Stats(), False).radiance()
        RayMarch({"steps": 1}).run(ps, paths, Stats(), False).radiance()
        rm = raymarch_curve(ps, paths, ref, args.rm_steps, args.repeats)
        res["raymarch"] = rm
        model = raymarch_model(rm, args.ref_steps)
        res["raymarch_model"] = model
        print(f"  raymarch: relMSE ~ {model['a']:.3g} S^-{model['p']:.2f}, reference floor "
              f"~{model['floor']:.2g}; seconds ~ {model['t0']:.2f} + {model['c']:.4f} S", flush=True)
        ep = []
        for lvl in epi_levels(w, h, auto_slices(ps)):
            params = {k: v for k, v in lvl.items() if k != "slice_spacing_px"}
            img, dt, st = timed(Epipolar(params), ps, paths, args.repeats)
            err = relmse(img, ref)
            stages = {k: v for k, v in st.stages.items() if k.startswith("epipolar") or k == "raymarch"}
            maps = stages.get("epipolar_maps", 0.0)
            eq = equal_error(model, rm, err)
            t_eq = eq["seconds"]
            rec = {**lvl, "seconds": dt, "seconds_scatter": dt - maps, "relmse": err,
                   "slices_used": st.values.get("slices"), "tree_updates": st.values.get("tree_updates"),
                   "tree_queries": st.values.get("tree_queries"),
                   "svd_singular_values": st.values.get("svd_singular_values"),
                   # what the accuracy control chose and what it cost
                   "lights": [{k: li.get(k) for k in ("svd_terms", "svd_groups",
                                                      "svd_formulation", "light_ray_factor",
                                                      "slice_spacing_px", "fallback")}
                              | {"svd_error": (li.get("svd_error") or {}).get("rms")}
                              for li in st.values.get("epipolar_lights", [])],
                   "stages": stages, "raymarch_steps_equal_error": eq["steps"],
                   "raymarch_seconds_equal_error": t_eq, "equal_error": eq["how"],
                   "speedup": t_eq / dt, "speedup_scatter": t_eq / max(dt - maps, 1e-9)}
            ep.append(rec)
            print(f"  epipolar d={lvl['light_rays']:5d} map={lvl['shadow_map']:4d} "
                  f"slices={rec['slices_used']}: {dt:6.2f} s ({dt - maps:5.2f} s w/o maps) "
                  f"relMSE {err:.3g}  = raymarch {eq['steps']:.0f} steps: speed-up "
                  f"{rec['speedup']:.1f}x ({eq['how']}); {rec['lights']}; svd stage "
                  f"{stages.get('epipolar_svd', 0.0):.2f} s", flush=True)
        res["epipolar"] = ep
        return res
    finally:
        ps.release()


def bench_ring(w, h, engine, args) -> dict:
    """Stage breakdown with the epipole on screen (``epi_sun``, default settings): the
    ring around it is ray marched (no reference needed, timings only)."""
    ps, paths = prepared("epi_sun", w, h, engine)
    try:
        Epipolar({"light_rays": 64, "shadow_map": 64, "slices": 64}).run(ps, paths, Stats(), False).radiance()
        _, dt, st = timed(Epipolar({}), ps, paths, args.repeats)
        li = st.values["epipolar_lights"][0]
        prim = int((paths.segments["depth"] == 0).sum())
        rec = {"scene": "epi_sun", "width": w, "height": h, "seconds": dt,
               "stages": {k: v for k, v in st.stages.items() if k.startswith("epipolar")},
               "ring_samples": li["ring_samples"], "ring_fraction": li["ring_samples"] / max(prim, 1),
               "ring_degrees": li.get("ring_degrees"), "ring_band_samples": li.get("ring_band_samples"),
               "epipole_px": li["epipole_px"]}
        print(f"  epi_sun: {dt:.2f} s, ring {rec['ring_fraction'] * 100:.2f} % of samples, stages "
              + ", ".join(f"{k[9:]} {v:.2f}" for k, v in rec["stages"].items()), flush=True)
        return rec
    finally:
        ps.release()


def bench_complexity(engine, args) -> dict:
    name = "epi_forest"
    out = {"scene": name, "points": []}
    for w in args.sizes:
        h = w * 3 // 4
        ps, paths = prepared(name, w, h, engine)
        try:
            Epipolar({"light_rays": 64, "shadow_map": 64, "slices": 64}).run(ps, paths, Stats(), False).radiance()
            steps = max(2, w // 10)
            _, t_rm, _ = timed(RayMarch({"steps": steps}), ps, paths, args.repeats if w < 1280 else 2)
            _, t_ep, st = timed(Epipolar({"light_rays": 2 * w, "shadow_map": 2 * w}), ps, paths,
                                args.repeats)
            maps = st.stages.get("epipolar_maps", 0.0)
            out["points"].append({"width": w, "height": h, "raymarch_steps": steps, "light_rays": 2 * w,
                                  "slices": st.values.get("slices"), "raymarch_seconds": t_rm,
                                  "epipolar_seconds": t_ep, "epipolar_seconds_scatter": t_ep - maps})
            print(f"  complexity W={w}: raymarch {t_rm:.3f} s, epipolar {t_ep:.3f} s "
                  f"({t_ep - maps:.3f} s w/o maps)", flush=True)
        finally:
            ps.release()
    W = np.log([p["width"] for p in out["points"]])
    for key in ("raymarch_seconds", "epipolar_seconds", "epipolar_seconds_scatter"):
        T = np.log([p[key] for p in out["points"]])
        out["slope_" + key.replace("_seconds", "")] = float(np.polyfit(W, T, 1)[0])
    # the largest two sizes only (small sizes are dominated by fixed costs)
    for key in ("raymarch_seconds", "epipolar_seconds_scatter"):
        T = np.log([p[key] for p in out["points"][-2:]])
        out["slope_top_" + key.replace("_seconds", "")] = float((T[1] - T[0]) / (W[-1] - W[-2]))
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scenes = result["scenes"]
    fig, axes = plt.subplots(1, len(scenes) + 2, figsize=(5 * (len(scenes) + 2), 4.2))
    for ax, s in zip(axes, scenes):
        ax.loglog([r["seconds"] for r in s["raymarch"]], [r["relmse"] for r in s["raymarch"]],
                  "o-", label="raymarch")
        m = s["raymarch_model"]
        S = np.geomspace(4, 4 * s["ref_steps"], 40)
        ax.loglog(m["t0"] + m["c"] * S, m["a"] * S ** -m["p"] + m["floor"], ":", color="C0",
                  alpha=0.6, label=f"raymarch fit (S^-{m['p']:.2f}) + ref floor")
        ax.axhline(m["floor"], color="gray", lw=0.8, ls=":")
        for r in s["raymarch"]:
            ax.annotate(str(r["steps"]), (r["seconds"], r["relmse"]), fontsize=7)
        ax.loglog([r["seconds"] for r in s["epipolar"]], [r["relmse"] for r in s["epipolar"]],
                  "s-", label="epipolar")
        ax.loglog([r["seconds_scatter"] for r in s["epipolar"]], [r["relmse"] for r in s["epipolar"]],
                  "s--", alpha=0.6, label="epipolar w/o maps")
        ax.set_title(f"{s['scene']} {s['width']}x{s['height']}")
        ax.set_xlabel("seconds (medium pass)")
        ax.set_ylabel("relMSE vs reference")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    c = result["complexity"]
    ax = axes[len(scenes)]
    W = [p["width"] for p in c["points"]]
    ax.loglog(W, [p["raymarch_seconds"] for p in c["points"]], "o-",
              label=f"raymarch (slope {c['slope_raymarch']:.2f})")
    ax.loglog(W, [p["epipolar_seconds_scatter"] for p in c["points"]], "s-",
              label=f"epipolar w/o maps (slope {c['slope_epipolar_scatter']:.2f})")
    ax.loglog(W, [p["epipolar_seconds"] for p in c["points"]], "s--", alpha=0.6,
              label=f"epipolar (slope {c['slope_epipolar']:.2f})")
    ax.set_xlabel("image width W (s, r, d all ~ W)")
    ax.set_ylabel("seconds")
    ax.set_title("complexity, " + c["scene"])
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[len(scenes) + 1]
    keys = ["epipolar_maps", "epipolar_rectify", "epipolar_svd", "epipolar_integrate",
            "epipolar_unrectify", "epipolar_ring"]
    runs = [s["epipolar"][DEFAULT_LEVEL]["stages"] for s in scenes] + [result["ring"]["stages"]]
    names = [s["scene"] for s in scenes] + ["epi_sun\n(epipole on)"]
    bottom = np.zeros(len(runs))
    for k in keys:
        vals = np.array([r.get(k, 0.0) for r in runs])
        ax.bar(names, vals, bottom=bottom, label=k.replace("epipolar_", ""))
        bottom += vals
    ax.set_ylabel("seconds (default level)")
    ax.set_title("epipolar stages")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="320 x 240, smaller sweeps")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--repeats", type=int, default=3,
                    help="runs per timing (min taken): every epipolar point, raymarch up to 64 steps")
    ap.add_argument("--no-copy", action="store_true", help="do not copy the results to docs/bench")
    args = ap.parse_args(argv)
    w, h = (320, 240) if args.quick else (1280, 960)
    args.ref_steps = 1024 if args.quick else 512
    args.rm_steps = [4, 8, 16, 32, 64, 128, 256]
    args.sizes = [80, 160, 320] if args.quick else [160, 320, 640, 1280]
    engine = get_engine()
    t0 = time.perf_counter()
    result = {"device": engine.name, "host": platform.node(), "python": platform.python_version(),
              "quick": bool(args.quick), "scenes": []}
    for name in args.scenes.split(","):
        result["scenes"].append(bench_scene(name.strip(), w, h, engine, args))
    print("[epipole on screen]", flush=True)
    result["ring"] = bench_ring(w, h, engine, args)
    print("[complexity]", flush=True)
    result["complexity"] = bench_complexity(engine, args)
    result["seconds_total"] = time.perf_counter() - t0
    OUT.mkdir(exist_ok=True)
    stem = "epipolar_quick" if args.quick else "epipolar"
    write_json(OUT / f"{stem}.json", result)
    plot(result, OUT / f"{stem}.png")
    if not args.no_copy:
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copy(OUT / f"{stem}.json", DOCS / f"{stem}.json")
        shutil.copy(OUT / f"{stem}.png", DOCS / f"{stem}.png")
    c = result["complexity"]
    print(f"complexity slopes: raymarch {c['slope_raymarch']:.2f}, epipolar {c['slope_epipolar']:.2f} "
          f"(w/o maps {c['slope_epipolar_scatter']:.2f}); paper 2.83 vs 1.94")
    print(f"total {result['seconds_total']:.0f} s; wrote {OUT / (stem + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
