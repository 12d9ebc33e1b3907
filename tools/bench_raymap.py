#!/usr/bin/env python3
"""Benchmark: ray maps (Havran et al. 2005) against photon maps for surface caustics.

On a built-in caustic scene (default ``caustic_sphere``, 160 x 120, 1 spp: the diffuse
points seen by the camera are the queries, in pixel order, as in the paper's direct
visualisation), in one process:

* **K-nearest query time against the number of rays** (the paper's Table 2) and **against
  K** (Table 3): the ray map's batched device query (hemisphere-disc metric, incoming rays,
  hemisphere domain of ``max_radius``) on a lazily built tree (refinement time included)
  and on a static tree (build time reported apart), a NumPy brute force over every
  segment (on a sample of queries), and scipy's ``cKDTree`` point kNN over the photons'
  hit points (the photon map's anchor; 1 thread); plus the share of tested references
  that qualified ("successful tests"). The alternative to device traversal, **candidate
  lists prepared on the host** (``knn_lists``: a vectorised walk collecting every leaf
  whose box meets a query's search box, then one kernel over the lists), on the same
  queries and trees: ``lists_lazy_ms`` (refinement + list building + kernel),
  ``lists_static_ms`` (list building + kernel; ``lists_static_host_ms`` the building
  alone).
* **Whole-image density estimation**, ray map against photon map from the same lighting
  rays: seconds (trace + build + estimate) and relMSE of the surface-caustic image
  against a converged reference (the ray map with ``--ref-factor`` x the largest ray
  count; the photon map's converged image is compared with it too), swept over the
  number of lighting rays; the time ratio ray map / photon map at each count (paper:
  2.1-4.7x) and the errors at equal time; candidate-list reuse on and off.

Times are the minimum over ``--repeats`` runs (the machine may be shared). Writes
bench_out/raymap/bench_raymap.json and .png and copies both to docs/bench/raymap.{json,png}.

``--boundary`` runs the **equal-time boundary study** instead: the paper's analytic bias
scenes (``tests/bias_scenes.py``; parallel rays, exact irradiance 1 on the lit faces, the
cosine of the slope on the wave), K = 200 nearest as in the paper, both estimators swept
over the number of rays. A free edge (the convex step), a concave corner and a surface
with no edge (the wave under parallel rays). Queries: points along the lit face towards
the edge (or over one period of the wave), each at 48 places along the extruded axis.
Reported per run: seconds to build the map and answer every query (ray generation, the
stand-in for tracing, is left out: it costs the same per ray for both, so leaving it out
favours the photon map, which gets more rays); the RMS of E / E_exact - 1 over the
queries within 0.02 of the edge and over those farther (noise and bias, what one pixel
shows) and the bias alone near the edge (the mean over the extruded axis). At each
ray-map run the photon map's errors at the same time are interpolated (log-log) along its
sweep. Writes bench_out/raymap/boundary.json and .png, copied to
docs/bench/raymap_boundary.{json,png}.

    python3 tools/bench_raymap.py [--quick] [--scene caustic_sphere] [--size 160x120]
                                  [--repeats 1] [--no-copy]
    python3 tools/bench_raymap.py --boundary [--repeats 2] [--no-copy]
"""
from __future__ import annotations

import argparse
import copy
import json
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from clscatter.device import get_engine  # noqa: E402
from clscatter.estimators.knn_queries import candidate_lists, knn, knn_lists, knn_np
from clscatter.estimators.ray_density import (
    DensitySettings,
    build_map,
    caustic_pieces,
    estimate,
    lazy_radius,
)
from clscatter.io.image import relmse
from clscatter.scene import scene_from_dict  # noqa: E402
from clscatter.scene.builtin.caustics import CAUSTIC_SCENES  # noqa: E402
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_diffuse_hits

OUT = REPO / "bench_out" / "raymap"
DOCS = REPO / "docs" / "bench"


def best(fn, repeats):
    """(min seconds, last result) over ``repeats`` calls."""
    times, res = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t)
    return min(times), res


def image_of(hits, e, w, h):
    v = hits["weight"][:, :3].astype(np.float64) * e
    img = np.zeros((3, w * h))
    for c in range(3):
        img[c] = np.bincount(hits["pixel"], weights=v[:, c], minlength=w * h)
    return img.T.reshape(h, w, 3).astype(np.float32)


def rel_err(img: np.ndarray, ref: np.ndarray) -> float:
    """relMSE with both images scaled so that the reference's mean is 1 (clscatter's
    relmse takes eps = 1e-2 in absolute units; the surface-caustic images are ~1e-2)."""
    s = float(ref.mean()) or 1.0
    return float(relmse(img / s, ref / s))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", default="caustic_sphere")
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--ref-factor", type=int, default=8)
    ap.add_argument("--no-copy", action="store_true")
    ap.add_argument("--boundary", action="store_true",
                    help="the equal-time study on the analytic edge, corner and wave")
    args = ap.parse_args()
    if args.boundary:
        return boundary_study(max(args.repeats, 2), not args.no_copy)
    w, h = (int(v) for v in args.size.split("x"))
    d = CAUSTIC_SCENES[args.scene]()
    d["camera"]["resolution"], d["camera"]["spp"] = [w, h], 1
    eng = get_engine()
    ps = prepare_scene(scene_from_dict(copy.deepcopy(d), REPO, args.scene), eng)
    rel = ps.scene.scene_extent() / ps.frame.scale
    hits = trace_diffuse_hits(ps)
    qx, qn = hits["p"][:, :3].astype(np.float64), hits["n"][:, :3].astype(np.float64)
    # lighting rays are targeted at the specular objects (clscatter.transport.emission): every one
    # can carry caustic light (about 5 stored segments per ray on caustic_sphere)
    ray_counts = [2_000, 4_000, 8_000] if args.quick else [2_000, 4_000, 8_000, 16_000]
    ks = [20, 50, 100, 200] if args.quick else [20, 50, 100, 200, 500]
    k_rays = ray_counts[2]                    # the K sweep (Table 3) at this ray count
    max_r = 0.05 * rel
    report: dict = {"scene": args.scene, "size": [w, h], "queries": int(len(hits)),
                    "device": eng.name, "machine": platform.processor() or platform.machine(),
                    "max_radius": 0.05, "knn_vs_rays": [], "knn_vs_k": [], "image": []}
    print(f"{args.scene} {w}x{h}: {len(hits)} diffuse hits (queries) on {eng.name}")

    # ---- K-nearest query time: rays (Table 2) and K (Table 3) ----
    from scipy.spatial import cKDTree
    pieces_by = {r: caustic_pieces(ps, r, show_progress=False) for r in ray_counts}
    sample = np.linspace(0, len(qx) - 1, 150).astype(int)

    def knn_row(r, k):
        pieces = pieces_by[r]
        s = DensitySettings(k=k, max_radius=max_r)
        row = {"light_rays": r, "segments": int(len(pieces)), "k": k}
        # lazy tree: refinement + queries, a fresh tree each repeat
        def lazy_run():
            rm = build_map(eng, pieces, "raymap", s)
            t = time.perf_counter()
            out = knn(rm, qx, qn, k, "hemidisc", "hemisphere", max_r, True,
                      lazy_radius=lazy_radius(rm, qx, k, max_r))
            tq = time.perf_counter() - t
            stats = (rm.tree.n, rm.tree.num_refs, rm.tree.peak_bytes)
            rm.release()
            return tq, out, stats
        t_lazy, (tq, (idx, dist, work), tstats) = best(lazy_run, args.repeats)
        # the same on host-built candidate lists (refinement + list building + kernel)
        def lazy_lists_run():
            rm = build_map(eng, pieces, "raymap", s)
            t = time.perf_counter()
            out = knn_lists(rm, qx, qn, k, "hemidisc", "hemisphere", max_r, True,
                            lazy_radius=lazy_radius(rm, qx, k, max_r))
            tq = time.perf_counter() - t
            rm.release()
            return tq, out
        _, (tq_l, (idx_l, dist_l, work_l)) = best(lazy_lists_run, args.repeats)
        row.update(lists_lazy_ms=1e3 * tq_l / len(qx), lists_candidates=float(work_l[:, 1].mean()),
                   lists_same_dist=bool(np.allclose(np.where(idx_l >= 0, dist_l, 0),
                                                    np.where(idx >= 0, dist, 0), rtol=1e-5, atol=1e-7)))
        found = (idx >= 0).sum(1)
        row.update(raymap_lazy_ms=1e3 * tq / len(qx), found=float(found.mean()),
                   refs_tested=float(work[:, 1].mean()), nodes_visited=float(work[:, 0].mean()),
                   successful_tests=float(found.sum() / max(work[:, 1].sum(), 1)),
                   tree_nodes=int(tstats[0]), tree_refs=int(tstats[1]), index_bytes=int(tstats[2]))
        # static tree: build apart, then queries
        t0 = time.perf_counter()
        rm = build_map(eng, pieces, "raymap", DensitySettings(k=k, max_radius=max_r, lazy=False))
        t_build = time.perf_counter() - t0
        t_static, _ = best(lambda: knn(rm, qx, qn, k, "hemidisc", "hemisphere", max_r, True), args.repeats)
        t_lists, _ = best(lambda: knn_lists(rm, qx, qn, k, "hemidisc", "hemisphere", max_r, True), args.repeats)
        t_build_lists, _ = best(lambda: candidate_lists(rm, qx, qn, max_r, True), args.repeats)
        row.update(static_build_s=t_build, raymap_static_ms=1e3 * t_static / len(qx),
                   static_tree_refs=int(rm.tree.num_refs), lists_static_ms=1e3 * t_lists / len(qx),
                   lists_static_host_ms=1e3 * t_build_lists / len(qx))
        a, b, dd = rm.a, rm.b, rm.d
        rm.release()
        # brute force (NumPy, every segment) on a sample of queries
        t_bf, _ = best(lambda: [knn_np("hemidisc", qx[q], qn[q], a, b, dd, k, "hemisphere", max_r, True)
                                for q in sample], 1)
        row["bruteforce_ms"] = 1e3 * t_bf / len(sample)
        # photon map anchor: scipy's point kd-tree over the diffuse hit points
        pts = pieces["b"][pieces["end"] == 0][:, :3].astype(np.float64)
        kk = min(k, len(pts))
        t0 = time.perf_counter()
        tree = cKDTree(pts)
        row["ckdtree_build_s"] = time.perf_counter() - t0
        t_ck, _ = best(lambda: tree.query(qx, k=kk, distance_upper_bound=max_r, workers=1), args.repeats)
        row["ckdtree_ms"] = 1e3 * t_ck / len(qx)
        row["photons"] = int(len(pts))
        print(f"  rays {r:>9,} segs {len(pieces):>8,} K {k:>3}: lazy {row['raymap_lazy_ms']:.4f} ms/q, "
              f"static {row['raymap_static_ms']:.4f} (+{t_build:.2f} s build), brute {row['bruteforce_ms']:.2f}, "
              f"cKDTree {row['ckdtree_ms']:.4f}; found {row['found']:.1f}, succ {100 * row['successful_tests']:.1f}%")
        print(f"      host lists: lazy {row['lists_lazy_ms']:.4f} ms/q, static {row['lists_static_ms']:.4f} "
              f"(list building {row['lists_static_host_ms']:.4f}); {row['lists_candidates']:.0f} candidates/q "
              f"vs {row['refs_tested']:.0f} refs tested by the walk; same answers {row['lists_same_dist']}")
        return row

    # build every kernel variant once, so that no timing includes a compilation
    warm = build_map(eng, pieces_by[ray_counts[0]], "raymap", DensitySettings(k=16, max_radius=max_r))
    for k in sorted(set(ks) | {64, 100}):
        knn(warm, qx[:1], qn[:1], k, "hemidisc", "hemisphere", max_r, True)
        knn_lists(warm, qx[:1], qn[:1], k, "hemidisc", "hemisphere", max_r, True)
        estimate(warm, qx[:1], qn[:1], "raymap", DensitySettings(k=k, max_radius=max_r))
    warm.release()
    for r in ray_counts:
        report["knn_vs_rays"].append(knn_row(r, 100))
    for k in ks:
        report["knn_vs_k"].append(knn_row(k_rays, k))

    # ---- whole-image density estimation, ray map vs photon map ----
    def image_run(est, rays, k=64, reuse=False):
        s = DensitySettings(k=k, max_radius=max_r, lazy=est == "raymap",
                            run=8 if reuse else 1, reuse_eps=0.002 * rel if reuse else 0.0)
        if est == "photonmap":
            s.tree.c_min, s.tree.r_min, s.tree.d_max, s.tree.alpha_deg = 16, 0.0, 40, 0.0
        t0 = time.perf_counter()
        pieces = caustic_pieces(ps, rays, show_progress=False)
        t1 = time.perf_counter()
        rm = build_map(eng, pieces, est, s)
        t2 = time.perf_counter()
        e, work = estimate(rm, qx, qn, est, s)
        t3 = time.perf_counter()
        rm.release()
        return {"trace_s": t1 - t0, "build_s": t2 - t1, "estimate_s": t3 - t2,
                "total_s": t3 - t0, "refs_tested": float(work[:, 1].mean())}, image_of(hits, e, w, h)

    ref_rays = ray_counts[-1] * args.ref_factor
    print(f"  reference: ray map with {ref_rays:,} rays")
    _, ref = image_run("raymap", ref_rays)
    _, ref_pm = image_run("photonmap", ref_rays)
    report["reference"] = {"estimator": "raymap", "light_rays": ref_rays, "k": 64,
                           "mean_radiance": float(ref.mean()),
                           "photonmap_ref_relmse": rel_err(ref_pm, ref)}
    for rays in ray_counts:
        for est, reuse in (("photonmap", False), ("raymap", False), ("raymap", True)):
            runs = [image_run(est, rays, reuse=reuse) for _ in range(args.repeats)]
            tm = min(runs, key=lambda x: x[0]["total_s"])
            row = {"estimator": est, "reuse": reuse, "light_rays": rays, **tm[0],
                   "relmse": rel_err(tm[1], ref)}
            report["image"].append(row)
            print(f"  {est:9s}{' reuse' if reuse else '      '} rays {rays:>9,}: {row['total_s']:.2f} s "
                  f"(estimate {row['estimate_s']:.2f}) relMSE {row['relmse']:.2e}")
    ratios = []
    for rays in ray_counts:
        rm_row = next(r for r in report["image"] if r["estimator"] == "raymap" and not r["reuse"]
                      and r["light_rays"] == rays)
        pm_row = next(r for r in report["image"] if r["estimator"] == "photonmap" and r["light_rays"] == rays)
        ratios.append({"light_rays": rays, "estimate_ratio": rm_row["estimate_s"] / pm_row["estimate_s"],
                       "total_ratio": rm_row["total_s"] / pm_row["total_s"]})
    report["raymap_over_photonmap_time"] = ratios
    ps.release()

    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bench_raymap.json").write_text(json.dumps(report, indent=1))
    plot(report, OUT / "bench_raymap.png")
    if not args.no_copy:
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copy(OUT / "bench_raymap.json", DOCS / "raymap.json")
        shutil.copy(OUT / "bench_raymap.png", DOCS / "raymap.png")
    print(f"wrote {OUT / 'bench_raymap.json'}")


BOUNDARY_RAYS = {"raymap": [50_000, 100_000, 200_000],
                 "photonmap": [50_000, 100_000, 200_000, 400_000, 800_000, 1_600_000]}
NEAR = 0.02          # "near the edge": within this distance (the corners' estimation radii)


def boundary_scenes():
    """name -> (ray generator (n, rng), query points (P, 3), normals (P, 3), exact
    irradiance (P,), distance to the edge (P,): inf on the wave)."""
    import bias_scenes as bs
    s = np.linspace(0.0005, 0.15, 60)
    up = np.tile([0.0, 1.0, 0.0], (len(s), 1))
    xw = np.linspace(-0.25, 0.0, 41)                      # one period: crest, trough
    nw = np.c_[-bs.wave_dy(xw), np.ones_like(xw), np.zeros_like(xw)]
    nw /= np.linalg.norm(nw, axis=1, keepdims=True)
    return {
        "free edge (convex step)": (bs.convex_corner, np.c_[-s, 0 * s, 0 * s], up,
                                    np.ones_like(s), s),
        "concave corner": (bs.concave_corner, np.c_[s, 0 * s, 0 * s], up, np.ones_like(s), s),
        "no edge (wave, parallel rays)": (lambda n, rng: bs.wave(n, rng, False),
                                          np.c_[xw, bs.wave_y(xw), 0 * xw], nw, nw[:, 1],
                                          np.full(len(xw), np.inf)),
    }


def boundary_run(eng, est: str, gen, n: int, seed: int, pts, nrm, exact, dist) -> dict:
    """One estimate of ``est`` from ``n`` rays of ``gen`` at every query point, repeated at
    48 places along z: seconds (map + queries) and the errors named in the module doc."""
    from bias_scenes import Z

    from clscatter.estimators.knn_queries import RayMap
    zs = np.linspace(-0.7 * Z, 0.7 * Z, 48)               # the sources are finite in z
    q = np.repeat(pts, len(zs), axis=0)
    q[:, 2] = np.tile(zs, len(pts))
    qn = np.repeat(nrm, len(zs), axis=0)
    o, b, d, f, on = gen(n, np.random.default_rng(seed))
    flux = np.full((len(o), 3), f)
    s = DensitySettings(k=200, kernel="epanechnikov", max_radius=0.2, batch=4096)
    t = time.perf_counter()
    if est == "photonmap":
        rm = RayMap(eng, b[on], b[on], d[on], flux[on], s.tree, points=True, lazy=True)
    else:
        rm = RayMap(eng, o, b, d, flux, s.tree, lazy=True)
    e, _ = estimate(rm, q, qn, est, s)
    seconds = time.perf_counter() - t
    rm.release()
    rel = e[:, 0].reshape(len(pts), len(zs)) / exact[:, None] - 1.0
    near = dist <= NEAR
    out = {"seconds": seconds, "rms_far": float(np.sqrt(np.mean(rel[~near] ** 2)))}
    if near.any():
        out["rms_near"] = float(np.sqrt(np.mean(rel[near] ** 2)))
        out["bias_near"] = float(np.mean(np.abs(rel[near].mean(1))))
    return out


def at_time(rows: list[dict], seconds: float, key: str) -> tuple[float, str]:
    """``key`` of a sweep interpolated log-log at ``seconds``: (value, "" or the bound's
    sign where ``seconds`` lies outside the sweep's times, the nearest end then)."""
    t = np.log([r["seconds"] for r in rows])
    v = np.log([r[key] for r in rows])
    order = np.argsort(t)
    t, v = t[order], v[order]
    x = np.log(seconds)
    side = "<=" if x > t[-1] else (">=" if x < t[0] else "")
    return float(np.exp(np.interp(x, t, v))), side


def boundary_study(repeats: int, copy_docs: bool) -> None:
    tests = REPO / "tests"
    if str(tests) not in sys.path:
        sys.path.insert(0, str(tests))
    eng = get_engine()
    scenes = boundary_scenes()
    gen, pts, nrm, exact, dist = next(iter(scenes.values()))
    boundary_run(eng, "raymap", gen, 20_000, 0, pts, nrm, exact, dist)       # build the kernels
    boundary_run(eng, "photonmap", gen, 20_000, 0, pts, nrm, exact, dist)
    import subprocess
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    report = {"commit": commit, "device": eng.name,
              "machine": platform.processor() or platform.machine(), "k": 200, "near": NEAR, "repeats": repeats, "scenes": {}}
    for name, (gen, pts, nrm, exact, dist) in scenes.items():
        sweeps = {}
        for est, counts in BOUNDARY_RAYS.items():
            sweeps[est] = []
            for n in counts:
                runs = [boundary_run(eng, est, gen, n, 100 + i, pts, nrm, exact, dist)
                        for i in range(repeats)]
                row = {"rays": n, "seconds": float(np.median([r["seconds"] for r in runs])),
                       **{k: float(np.mean([r[k] for r in runs])) for k in runs[0]
                          if k != "seconds"}}
                sweeps[est].append(row)
                print(f"{name}: {est} {n:,} rays {row['seconds']:.2f} s "
                      + " ".join(f"{k} {v:.3g}" for k, v in row.items()
                                 if k not in ("rays", "seconds")), flush=True)
        equal = []
        for r in sweeps["raymap"]:
            row = {"raymap_rays": r["rays"], "seconds": r["seconds"]}
            for key in ("rms_near", "bias_near", "rms_far"):
                if key in r:
                    pm, side = at_time(sweeps["photonmap"], r["seconds"], key)
                    row[key] = {"raymap": r[key], "photonmap": pm, "photonmap_bound": side}
            equal.append(row)
        report["scenes"][name] = {"sweeps": sweeps, "equal_time": equal}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "boundary.json").write_text(json.dumps(report, indent=1))
    plot_boundary(report, OUT / "boundary.png")
    if copy_docs:
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copy(OUT / "boundary.json", DOCS / "raymap_boundary.json")
        shutil.copy(OUT / "boundary.png", DOCS / "raymap_boundary.png")
    print("\n| surface | ray-map rays | seconds | RMS near the edge: ray map | photon map "
          "| bias near the edge: ray map | photon map | RMS away from it: ray map | photon map |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, sc in report["scenes"].items():
        for r in sc["equal_time"]:
            cells = []
            for key in ("rms_near", "bias_near", "rms_far"):
                if key in r:
                    c = r[key]
                    cells += [f"{c['raymap']:.3f}", f"{c['photonmap_bound']}{c['photonmap']:.3f}"]
                else:
                    cells += ["-", "-"]
            print(f"| {name} | {r['raymap_rays']:,} | {r['seconds']:.2f} | " + " | ".join(cells) + " |")


def plot_boundary(report: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, NullFormatter
    names = list(report["scenes"])
    fig, ax = plt.subplots(1, len(names), figsize=(5 * len(names), 4.2))
    for a, name in zip(np.atleast_1d(ax), names):
        sw = report["scenes"][name]["sweeps"]
        key = "rms_near" if "rms_near" in sw["raymap"][0] else "rms_far"
        for est, m in (("raymap", "o-"), ("photonmap", "s-")):
            a.loglog([r["seconds"] for r in sw[est]], [r[key] for r in sw[est]], m,
                     label=f"{est} ({'near the edge' if key == 'rms_near' else 'every point'})")
            if key == "rms_near":
                a.loglog([r["seconds"] for r in sw[est]], [r["rms_far"] for r in sw[est]],
                         m[0] + ":", label=f"{est} (away from the edge)")
        a.set_title(name)
        a.set_xticks([0.1, 0.2, 0.5, 1, 2, 5])
        a.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("seconds (map + queries)")
        a.set_ylabel("RMS of E / E_exact - 1")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot(report: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    for key, x, a in (("knn_vs_rays", "segments", ax[0]), ("knn_vs_k", "k", ax[1])):
        rows = report[key]
        xs = [r[x] for r in rows]
        for name, lab in (("raymap_lazy_ms", "ray map (lazy, incl. refinement)"),
                          ("raymap_static_ms", "ray map (static tree)"),
                          ("lists_lazy_ms", "host candidate lists (lazy)"),
                          ("lists_static_ms", "host candidate lists (static tree)"),
                          ("bruteforce_ms", "brute force (NumPy)"), ("ckdtree_ms", "cKDTree points (photon map)")):
            if all(name in r for r in rows):
                a.loglog(xs, [r[name] for r in rows], "o-", label=lab)
        a.set_xlabel(x)
        a.set_ylabel("ms per query")
        a.grid(True, which="both", alpha=0.3)
    ax[0].set_title("K = 100 nearest vs stored segments")
    ax[1].set_title("K nearest vs K")
    ax[0].legend(fontsize=7)
    for est, reuse, m in (("photonmap", False, "s-"), ("raymap", False, "o-"), ("raymap", True, "^--")):
        rows = [r for r in report["image"] if r["estimator"] == est and r["reuse"] == reuse]
        ax[2].loglog([r["total_s"] for r in rows], [r["relmse"] for r in rows], m,
                     label=est + (" (list reuse)" if reuse else ""))
    ax[2].set_xlabel("seconds (trace + build + estimate)")
    ax[2].set_ylabel("relMSE vs reference")
    ax[2].set_title("surface caustic image")
    ax[2].legend(fontsize=7)
    ax[2].grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
