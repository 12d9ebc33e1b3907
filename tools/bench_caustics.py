#!/usr/bin/env python3
"""Benchmark: line space gathering (``lsg``) against volumetric photon mapping (``vpm``)
on a caustic scene, as in Table 1 / Figure 5 of the LSG paper (Sun et al. 2010).

On one built-in caustic scene (default ``caustic_sphere``, 160 x 120, 1 spp), in one
process, with the scene prepared and the view paths traced once (both methods gather
the same view segments; only the medium pass ``render`` is timed):

* a converged reference, LSG with many lighting rays and a small radius (VPM when LSG is
  not available; ``--reference``), cached under bench_out/caustics/ and keyed by scene,
  size, method and parameters; in the full run a converged VPM too, and the relMSE
  between the two references (how far "converged" is);
* time, peak memory and relMSE (clscatter.io.image.relmse of the whole image against the
  reference) for LSG over (light_rays, radius) and VPM over (photons, knn, dx);
* the Pareto fronts (least time, least memory for a given error) of both methods and the
  VPM / LSG ratios of time and of memory at equal error, interpolated log-log along the
  fronts at error levels both fronts reach;
* LSG's culling: pair_tests / pair_tests_bruteforce and valid_pairs / pair_tests, and the
  paper's way (``lsg_cull_fraction_paper``: 1 - points in visited leaves / (segments
  kept after clipping x view segments); ``lsg_valid_fraction_paper``: valid / those);
* VPM's time split into photon tracing, deposition + tree build (NumPy) and gather
  (device) in the JSON, so algorithm can be compared with algorithm (LSG: tree build
  + gather); VPM photons are independent (one per ray on average) unless a sweep sets
  ``photons_per_ray``/``deposit``;
* gather-time scaling with the number of lighting rays (photons for VPM) and with the
  image size (log-log slopes).

Times are the minimum over ``--repeats`` runs (the machine may be shared). ``peak_bytes``
is the engine's peak during the medium pass (device buffers, including the prepared
scene's, plus the host working sets the methods report); ``method_bytes`` is that peak
minus what was live before the pass. Writes bench_out/caustics/bench_caustics.json and
.png and copies both to docs/bench/caustics.{json,png}.

    python3 tools/bench_caustics.py [--quick] [--scene caustic_sphere] [--size 160x120]
                                    [--reference lsg|vpm] [--repeats 1] [--no-copy]
"""
from __future__ import annotations

import argparse
import hashlib
import json
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

from clscatter import methods  # noqa: E402
from clscatter.device import get_engine  # noqa: E402
from clscatter.io.image import relmse, write_image
from clscatter.io.stats import Stats, write_json
from clscatter.scene import scene_from_dict  # noqa: E402
from clscatter.scene.builtin.caustics import CAUSTIC_SCENES  # noqa: E402
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

OUT = REPO / "bench_out" / "caustics"
DOCS = REPO / "docs" / "bench"

# ---- the sweeps ----------------------------------------------------------------------------
REFERENCE = {
    "lsg": {"light_rays": 3_200_000, "radius": 0.0007},
    "vpm": {"photons": 16_000_000, "knn": 64, "dx": 0.002},
}
REFERENCE_QUICK = {
    "lsg": {"light_rays": 800_000, "radius": 0.0012},
    "vpm": {"photons": 4_000_000, "knn": 64, "dx": 0.003},
}


def sweeps(quick: bool) -> dict[str, list[dict]]:
    if quick:
        lsg = [{"light_rays": n, "radius": r} for n in (50_000, 200_000) for r in (0.002, 0.004)]
        vpm = [{"photons": p, "knn": 32, "dx": 0.004} for p in (250_000, 1_000_000)]
        vpm += [{"photons": 1_000_000, "knn": 32, "dx": 0.008}]
        return {"lsg": lsg, "vpm": vpm}
    lsg = [{"light_rays": n, "radius": r}
           for n in (50_000, 100_000, 200_000, 400_000, 800_000, 1_600_000)
           for r in (0.001, 0.002, 0.004)]
    vpm = [{"photons": p, "knn": k, "dx": 0.004}
           for p in (250_000, 500_000, 1_000_000, 2_000_000, 4_000_000) for k in (16, 32, 64)]
    vpm += [{"photons": p, "knn": 32, "dx": 0.008}
            for p in (500_000, 1_000_000, 2_000_000, 4_000_000, 8_000_000)]
    vpm += [{"photons": 1_000_000, "knn": 32, "dx": 0.002}, {"photons": 4_000_000, "knn": 64, "dx": 0.002}]
    # fewer photons per ray: less regular photon sets, less kNN bias, more noise
    vpm += [{"photons": p, "knn": 64, "dx": 0.004, "photons_per_ray": 8} for p in (4_000_000, 8_000_000)]
    return {"lsg": lsg, "vpm": vpm}


SCALING = {"lsg": {"light_rays": 200_000, "radius": 0.002},
           "vpm": {"photons": 1_000_000, "knn": 32, "dx": 0.004}}

# statistics kept per run
KEEP = ("light_rays", "light_segments", "view_segments", "pair_tests", "pair_tests_bruteforce",
        "valid_pairs", "lsg_cull_fraction", "lsg_valid_fraction", "tree_build_seconds",
        "gather_seconds", "chunks", "lsg_chunk_bytes_max", "photons", "gather_steps",
        "photon_build_seconds", "photon_trace_seconds", "photon_map_bytes",
        "knn_photons_tested", "knn_boxes_tested", "lsg_leaf_points_tested", "lsg_light_segments_kept",
        "lsg_cull_fraction_paper", "lsg_valid_fraction_paper", "lsg_radius")


# ---- one scene, prepared once ----------------------------------------------------------------
class Bench:
    def __init__(self, engine, scene_name: str, width: int, height: int, spp: int):
        d = CAUSTIC_SCENES[scene_name]()
        d["camera"]["resolution"] = [width, height]
        d["camera"]["spp"] = spp
        self.scene = scene_from_dict(d, REPO, f"builtin:{scene_name}")
        self.engine = engine
        self.ps = prepare_scene(self.scene, engine)
        self.paths = trace_view_paths(self.ps, show_progress=False)
        self.size = (width, height, spp)

    def run(self, method: str, params: dict, repeats: int = 1) -> tuple[np.ndarray, dict]:
        """Render the medium with ``method``; (image, record) with the fastest repeat."""
        best = None
        for _ in range(max(1, repeats)):
            eng = self.engine
            eng.reset_peak()
            live = eng.bytes_live
            stats = Stats()
            m = methods.get_method(method)(dict(params))
            t = time.perf_counter()
            medium = m.render(self.ps, self.paths, stats, show_progress=False)
            seconds = time.perf_counter() - t
            rec = {"method": method, "params": dict(params), "seconds": seconds,
                   "peak_bytes": int(eng.bytes_peak), "method_bytes": int(eng.bytes_peak - live),
                   **{k: v for k, v in stats.to_dict().items() if k in KEEP}}
            if best is None or seconds < best[1]["seconds"]:
                best = (self.paths.surface + medium, rec)
        return best

    def release(self) -> None:
        self.ps.release()


def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def reference(bench: Bench, scene_name: str, method: str, params: dict,
              out: Path) -> tuple[np.ndarray, dict]:
    """The cached reference image in ``out`` (rendering it on a miss)."""
    key = _key(scene_name, bench.size, method, params, bench.scene.render.seed)
    path = out / f"ref_{scene_name}_{method}_{key}.npy"
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        return np.load(path), json.loads(meta.read_text())
    print(f"reference: {method} {params} ...", flush=True)
    img, rec = bench.run(method, params)
    np.save(path, img)
    write_json(meta, rec)
    write_image(path.with_suffix(".png"), img)
    return img, rec


# ---- Pareto fronts and equal-error ratios ------------------------------------------------------
def pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """(error, cost) points on the lower-left front: sorted by error, cost strictly falling."""
    front = []
    for e, c in sorted(points):
        if not front or c < front[-1][1]:
            front.append((e, c))
    return front


def cost_at(front: list[tuple[float, float]], err: float) -> tuple[float | None, bool]:
    """Least cost for error <= err, interpolated log-log between front points: (cost,
    whether it is only an upper bound because err lies beyond the front's largest error,
    where a cheaper run might have reached it). (None, False) below the front's least error."""
    if not front or err < front[0][0]:
        return None, False
    for (e0, c0), (e1, c1) in zip(front, front[1:]):
        if e0 <= err <= e1:
            f = math.log(err / e0) / math.log(e1 / e0) if e1 > e0 else 0.0
            return math.exp(math.log(c0) + f * (math.log(c1) - math.log(c0))), False
    return front[-1][1], err > front[-1][0]


def equal_error(records: list[dict], cost: str, levels: int = 5) -> list[dict]:
    """VPM / LSG cost ratios at equal error: at ``levels`` errors (geometric spacing) from
    the larger of the two fronts' least errors up to the smaller of their largest (or just
    the former where they do not overlap; a cost beyond its front's range is an upper
    bound and flagged)."""
    fronts = {m: pareto([(r["relmse"], r[cost]) for r in records if r["method"] == m])
              for m in ("lsg", "vpm")}
    if not fronts["lsg"] or not fronts["vpm"]:
        return []
    lo = max(fronts["lsg"][0][0], fronts["vpm"][0][0])
    hi = max(lo, min(fronts["lsg"][-1][0], fronts["vpm"][-1][0]))
    out = []
    for e in (np.geomspace(lo, hi, levels) if hi > lo else [lo]):
        (cl, bl), (cv, bv) = cost_at(fronts["lsg"], float(e)), cost_at(fronts["vpm"], float(e))
        if cl and cv:
            out.append({"relmse": float(e), "lsg": cl, "vpm": cv, "ratio_vpm_over_lsg": cv / cl,
                        "lsg_upper_bound": bl, "vpm_upper_bound": bv})
    return out


def slope(x, y) -> float:
    """Least-squares slope of log y against log x."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    return float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 else float("nan")


# ---- the plot ---------------------------------------------------------------------------------
def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result["runs"]
    colours = {"lsg": "tab:blue", "vpm": "tab:red"}
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.8))
    for panel, (cost, label) in enumerate((("seconds", "medium pass time (s)"),
                                           ("peak_bytes", "peak memory (MB)"))):
        a = ax[panel]
        for m in ("lsg", "vpm"):
            rs = [r for r in runs if r["method"] == m]
            if not rs:
                continue
            scale = 1e-6 if cost == "peak_bytes" else 1.0
            a.scatter([r["relmse"] for r in rs], [r[cost] * scale for r in rs], s=14,
                      color=colours[m], alpha=0.5)
            fr = pareto([(r["relmse"], r[cost] * scale) for r in rs])
            a.plot([e for e, _ in fr], [c for _, c in fr], "-o", color=colours[m], ms=4,
                   label=f"{m} (Pareto front)")
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_xlabel("relMSE against the reference")
        a.set_ylabel(label)
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    a = ax[2]
    sc = result["scaling"]
    for m in ("lsg", "vpm"):
        rows = sc["lights"].get(m, [])
        if rows:
            a.plot([r["x"] for r in rows], [r["gather_seconds"] for r in rows], "-o",
                   color=colours[m], label=f"{m}: vs {'light rays' if m == 'lsg' else 'photons'} "
                   f"(slope {sc['lights_slope'][m]:.2f})")
        rows = sc["image"].get(m, [])
        if rows:
            a.plot([r["view_segments"] for r in rows], [r["gather_seconds"] for r in rows], "--s",
                   color=colours[m], label=f"{m}: vs view segments (slope {sc['image_slope'][m]:.2f})")
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlabel("lighting rays / photons / view segments")
    a.set_ylabel("gather seconds")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=8)
    fig.suptitle(f"{result['scene']} {result['size']}: LSG vs VPM, reference {result['reference']['method']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- main ------------------------------------------------------------------------------------
def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a few points only (a smoke run)")
    ap.add_argument("--scene", default="caustic_sphere", choices=sorted(CAUSTIC_SCENES))
    ap.add_argument("--size", default="160x120", help="W x H")
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--reference", choices=("lsg", "vpm"), default=None)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-copy", action="store_true", help="do not copy results to docs/bench/")
    ap.add_argument("--out", default=None, help="output folder (default bench_out/caustics)")
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else OUT
    out.mkdir(parents=True, exist_ok=True)
    w, h = (int(x) for x in args.size.lower().split("x"))
    have = [m for m in ("lsg", "vpm") if m in methods.available()]
    ref_method = args.reference or ("lsg" if "lsg" in have else "vpm")
    if ref_method not in have:
        raise SystemExit(f"reference method {ref_method} is not available")
    t_start = time.perf_counter()
    eng = get_engine()
    bench = Bench(eng, args.scene, w, h, args.spp)
    print(f"{args.scene} {w}x{h} spp {args.spp}: {len(bench.paths.segments)} view segments; "
          f"methods {have}", flush=True)
    ref_params = (REFERENCE_QUICK if args.quick else REFERENCE)[ref_method]
    ref_img, ref_rec = reference(bench, args.scene, ref_method, ref_params, out)
    result = {"scene": args.scene, "size": f"{w}x{h}", "spp": args.spp, "quick": args.quick,
              "device": eng.name, "machine": platform.platform(), "cpus": _cpus(),
              "reference": {"method": ref_method, "params": ref_params, "seconds": ref_rec["seconds"],
                            "peak_bytes": ref_rec["peak_bytes"]}}
    cross = None
    if not args.quick and len(have) == 2:      # how converged is "converged"
        other = "vpm" if ref_method == "lsg" else "lsg"
        cross, o_rec = reference(bench, args.scene, other, REFERENCE[other], out)
        result["reference"]["cross_check"] = {"method": other, "params": REFERENCE[other],
                                              "relmse_vs_reference": relmse(cross, ref_img),
                                              "seconds": o_rec["seconds"]}

    # warm-up: build every kernel variant before timing anything
    for m, plist in sweeps(args.quick).items():
        if m in have:
            for k in sorted({p.get("knn") for p in plist} - {None}) or [None]:
                tiny = {"light_rays": 2000, "radius": 0.01} if m == "lsg" else {"photons": 20_000, "knn": k}
                bench.run(m, tiny)

    runs = []
    for m, plist in sweeps(args.quick).items():
        if m not in have:
            continue
        for p in plist:
            img, rec = bench.run(m, p, args.repeats)
            rec["relmse"] = relmse(img, ref_img)
            rec["relmse_medium"] = relmse(img - bench.paths.surface, ref_img - bench.paths.surface)
            if cross is not None:    # the same against the other method's reference
                rec["relmse_cross"] = relmse(img, cross)
            runs.append(rec)
            print(f"{m} {p}: {rec['seconds']:.2f} s, peak {rec['peak_bytes'] / 1e6:.0f} MB, "
                  f"relMSE {rec['relmse']:.3e}", flush=True)
    result["runs"] = runs
    result["equal_error"] = {cost: equal_error(runs, cost) for cost in ("seconds", "peak_bytes",
                                                                          "method_bytes")}
    if cross is not None:    # the ratios again with errors against the other reference
        swapped = [{**r, "relmse": r["relmse_cross"]} for r in runs]
        result["equal_error_cross"] = {cost: equal_error(swapped, cost)
                                       for cost in ("seconds", "peak_bytes")}
    lsg_runs = [r for r in runs if r["method"] == "lsg" and r.get("pair_tests_bruteforce")]
    result["culling"] = [{"light_rays": r["params"]["light_rays"], "radius": r["params"]["radius"],
                          "pair_tests": r["pair_tests"], "pair_tests_bruteforce": r["pair_tests_bruteforce"],
                          "valid_pairs": r["valid_pairs"],
                          "tested_fraction": r["pair_tests"] / r["pair_tests_bruteforce"],
                          "valid_fraction": r["valid_pairs"] / max(r["pair_tests"], 1),
                          # the paper's way (sec. 4.3): what the hierarchy alone leaves of
                          # (segments kept after clipping x view segments), valid of that
                          "cull_fraction_paper": r.get("lsg_cull_fraction_paper"),
                          "valid_fraction_paper": r.get("lsg_valid_fraction_paper")}
                         for r in lsg_runs]

    # ---- scaling ----
    scaling = {"lights": {}, "image": {}, "lights_slope": {}, "image_slope": {}}
    r_fix = SCALING["lsg"]["radius"]
    rows = [r for r in runs if r["method"] == "lsg" and r["params"]["radius"] == r_fix]
    scaling["lights"]["lsg"] = [{"x": r["params"]["light_rays"], "gather_seconds": r["gather_seconds"]}
                                for r in rows]
    rows = [r for r in runs if r["method"] == "vpm" and r["params"]["knn"] == 32
            and r["params"]["dx"] == 0.004]
    scaling["lights"]["vpm"] = [{"x": r["params"]["photons"], "gather_seconds": r["gather_seconds"]}
                                for r in rows]
    bench.release()
    sizes = [(80, 60), (160, 120)] if args.quick else [(80, 60), (160, 120), (320, 240)]
    for sw, sh in sizes:
        b = Bench(eng, args.scene, sw, sh, args.spp)
        for m in have:
            _, rec = b.run(m, SCALING[m], args.repeats)
            scaling["image"].setdefault(m, []).append(
                {"size": f"{sw}x{sh}", "view_segments": rec["view_segments"] if "view_segments" in rec
                 else int(len(b.paths.segments)), "gather_seconds": rec["gather_seconds"],
                 "seconds": rec["seconds"], "peak_bytes": rec["peak_bytes"]})
            print(f"scaling {m} {sw}x{sh}: gather {rec['gather_seconds']:.2f} s", flush=True)
        b.release()
    for key in ("lights", "image"):
        for m, rows in scaling[key].items():
            xs = [r["x"] if key == "lights" else r["view_segments"] for r in rows]
            scaling[f"{key}_slope"][m] = slope(xs, [r["gather_seconds"] for r in rows])
    result["scaling"] = scaling
    result["seconds_total"] = time.perf_counter() - t_start

    write_json(out / "bench_caustics.json", result)
    plot(result, out / "bench_caustics.png")
    if not args.no_copy:
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "bench_caustics.json", DOCS / "caustics.json")
        shutil.copy(out / "bench_caustics.png", DOCS / "caustics.png")
    summary(result)
    return result


def _cpus() -> int:
    import os
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 0)


def summary(result: dict) -> None:
    print(f"\nreference: {result['reference']}")
    tables = [("", result["equal_error"])]
    if "equal_error_cross" in result:
        tables.append((f"[vs the {result['reference']['cross_check']['method']} reference] ",
                       result["equal_error_cross"]))
    for label, table in tables:
        for cost, rows in table.items():
            for r in rows:
                flag = " (lsg: upper bound)" if r["lsg_upper_bound"] else (
                    " (vpm: upper bound)" if r["vpm_upper_bound"] else "")
                print(f"{label}equal error {r['relmse']:.2e}: {cost} vpm/lsg = "
                      f"{r['ratio_vpm_over_lsg']:.2f} (lsg {r['lsg']:.4g}, vpm {r['vpm']:.4g}){flag}")
    for c in result["culling"]:
        print(f"culling lsg {c['light_rays']} r={c['radius']}: tested {c['tested_fraction']:.4%} of "
              f"all pairs, valid {c['valid_fraction']:.1%} of tested")
        if c.get("cull_fraction_paper") is not None:
            print(f"   paper's way: hierarchy culls {c['cull_fraction_paper']:.2%} of kept x view, "
                  f"valid {c['valid_fraction_paper']:.1%} of the rest")
    sc = result["scaling"]
    print("gather-time slopes: vs rays/photons", {m: round(v, 2) for m, v in sc["lights_slope"].items()},
          "vs view segments", {m: round(v, 2) for m, v in sc["image_slope"].items()})
    print(f"total {result['seconds_total']:.0f} s")


if __name__ == "__main__":
    main()
