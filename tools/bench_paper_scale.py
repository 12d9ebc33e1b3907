#!/usr/bin/env python3
"""Benchmark: the paper-scale scene ``paper_bunny`` (a 69,664-triangle glass bunny, 1 M
lighting rays, 512 x 512 at 4 spp), laid out like Table 1 of the LSG paper (Sun et al.
2010: scenes of 43K-93K triangles, 0.7-8.9 M lighting rays, 512 x 512 with 2 x 2
supersampling; LSG 26-73 min at 229-404 MB where VPM took 7-14 h at 4.5-7.1 GB).

Every run is ``clscatter render`` in a fresh process with ``--time-budget 0`` (so no
budget cuts a measured run) and ``--stats``; its wall time is measured outside it and its
peak resident set by ``wait4``. Recorded per run: whole-process seconds, ``render_seconds``
and the stages from ``--stats``, ``peak_bytes`` (the engine's peak: device buffers and the
host working sets the methods report), the process's max RSS, and relMSE
(``clscatter.io.image.relmse``) against a converged reference.

* **Table 1.** ``auto`` and ``lsg`` under ``--max-memory 2G``, ``lsg`` also in progressive
  passes (each pass gathers one of a pixel's camera samples, the samples taking turns, and
  builds its tree over its own rays only), and ``vpm`` over a sweep of photon counts; VPM's time and memory at LSG's error are interpolated log-log along
  VPM's Pareto front (least cost for an error). ``lsg`` and ``vpm`` compute the same light
  (direct light and volumetric caustics; neither computes caustics on the floor), so both
  are measured against a converged ``lsg`` (many progressive passes of many rays);
  ``auto`` (ray marching + LSG caustics + the ray map's floor caustics) against a
  converged ``auto``. References are cached under bench_out/paper_scale/, keyed by the
  scene text and the settings.
* **Growth of LSG** (``--method lsg``), each with its log-log slope of render time, LSG
  time (light paths + tree + gather) and peak memory: triangles (the bunny decimated,
  with trimesh's ``simplify_quadric_decimation`` where ``fast_simplification`` is
  installed and else by vertex clustering, and subdivided with ``subdivide``); lighting
  rays; pixels.

``--quick`` (128 x 128, 1 spp, 100k lighting rays; about 3 minutes on 2 cores, references included)
is a smoke run of the same layout; the full mode (512 x 512, 4 spp, the scene's 1 M rays,
references with 8 passes of 4 M rays, VPM up to 16 M photons, up to 1.1 M triangles) takes
hours on a 2-core CPU. ``--parts`` runs some of the parts (table, rays, pixels,
triangles); the JSON is rewritten after each, so a run cut off keeps what it finished.
The device is the engine's choice (``$CLSCATTER_DEVICE`` picks one) and is recorded.
``--no-auto`` leaves out the ``auto`` row and its reference. ``--vpm-set KEY=VALUE`` gives
every VPM run a ``render.vpm`` setting (the engine's own by default; ``knn=128 dx=0.002``
are the paper's). ``--reference-seconds S``
runs the lsg row first and gives the references as many passes
as fit in about S seconds each (at least 2); ``--deadline`` skips VPM runs that would not
fit in the run's time.
Writes OUT/bench_paper_scale.json and .png (``--out``, default bench_out/paper_scale/),
copies them to docs/bench/NAME.{json,png} (``--name``, default paper_scale) unless
``--no-copy``, and prints markdown tables for docs/benchmarks.md.

    .venv/bin/python tools/bench_paper_scale.py [--quick] [--parts table,rays] [--out DIR]
        [--reference-seconds S] [--deadline S] [--name NAME] [--no-copy]
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import math
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

from bench_caustics import cost_at, equal_error, pareto, slope  # noqa: E402

from clscatter.io.image import relmse, write_image  # noqa: E402
from clscatter.scene.builtin import to_toml  # noqa: E402
from clscatter.scene.builtin.paper import BUNNY, paper_bunny  # noqa: E402

OUT = ROOT / "bench_out" / "paper_scale"
DOCS = ROOT / "docs" / "bench"
PY = sys.executable
MAX_MEMORY = "2G"

# ---- the settings of the two modes ------------------------------------------------------------
FULL = {
    "size": (512, 512), "spp": 4, "light_rays": 1_000_000,
    "ref_lsg": {"light_rays": 4_000_000, "passes": 8},
    "ref_auto": {"light_rays": 4_000_000, "raymap_photons": 800_000, "raymarch_steps": 128},
    "vpm_photons": [1_000_000, 2_000_000, 4_000_000, 8_000_000, 16_000_000],
    "rays": [250_000, 500_000, 1_000_000, 2_000_000, 4_000_000],
    "pixels": [(128, 128), (256, 256), (512, 512)],
    "triangles": [4_000, 17_000, None, "x4", "x16"],     # None: the bunny as it is
    "lsg_passes": [(4, 250_000), (4, 500_000), (8, 500_000)],   # (passes, rays a pass)
}
QUICK = {
    "size": (128, 128), "spp": 1, "light_rays": 100_000,
    "ref_lsg": {"light_rays": 400_000, "passes": 8},
    "ref_auto": {"light_rays": 400_000, "raymap_photons": 400_000, "raymarch_steps": 128},
    "vpm_photons": [6_250, 12_500, 25_000, 50_000, 100_000, 200_000, 400_000, 800_000, 1_600_000],
    "rays": [25_000, 50_000, 100_000, 200_000],
    "pixels": [(64, 64), (128, 128), (256, 256)],
    "triangles": [4_000, 17_000, None, "x4"],
    "lsg_passes": [(4, 25_000), (8, 25_000), (16, 25_000)],
}

# the parts of a run: Table 1 and the three growth sweeps of LSG
PARTS = ("table", "rays", "pixels", "triangles")
STAGES_LSG = ("light_paths", "lsg_auto_radius", "lsg_tree", "lsg_gather")
KEEP = ("method", "device", "render_seconds", "seconds_total", "peak_bytes", "estimated_peak_bytes",
        "triangles", "light_rays", "light_segments", "view_segments", "photons", "lsg_passes",
        "lsg_radius", "lsg_chunk_bytes_max", "chunks", "pair_tests", "valid_pairs",
        "lsg_cull_fraction", "photon_map_bytes", "photon_trace_seconds",
        "photon_build_seconds", "gather_seconds", "tree_build_seconds")


# ---- scenes and meshes -----------------------------------------------------------------------
def scene_dict(cfg: dict, size=None, mesh: Path | None = None) -> dict:
    d = copy.deepcopy(paper_bunny())
    d["camera"]["resolution"] = list(size or cfg["size"])
    d["camera"]["spp"] = cfg["spp"]
    d["render"]["lsg"]["light_rays"] = cfg["light_rays"]
    if mesh is not None:
        d["objects"][1]["file"] = str(mesh)
    return d


def write_scene(d: dict, name: str) -> Path:
    path = OUT / "scenes" / f"{name}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(to_toml(d))
    return path


def _cluster(v: np.ndarray, f: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering: vertices snapped to a grid of ``cell``, each cell's vertices
    merged into their mean, triangles that collapse dropped."""
    key = np.floor((v - v.min(0)) / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = inv.max() + 1
    vn = np.zeros((n, 3))
    np.add.at(vn, inv, v)
    vn /= np.bincount(inv, minlength=n)[:, None]
    fn = inv[f]
    fn = fn[(fn[:, 0] != fn[:, 1]) & (fn[:, 1] != fn[:, 2]) & (fn[:, 0] != fn[:, 2])]
    _, first = np.unique(np.sort(fn, axis=1), axis=0, return_index=True)   # duplicates once
    return vn, fn[np.sort(first)]


def bunny_variant(target) -> tuple[Path, str]:
    """The bunny with about ``target`` triangles (decimated), ``"xN"`` (subdivided to N
    times the triangles) or as it is (None): (mesh file, how it was made)."""
    import trimesh
    if target is None:
        return BUNNY, "original"
    path = OUT / "meshes" / f"bunny_{target}.ply"
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.load(str(BUNNY), force="mesh", process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if isinstance(target, str):                         # "x4", "x16": midpoint subdivision
        how = f"subdivide x{int(target[1:])}"
        m = trimesh.Trimesh(v, f, process=False)
        for _ in range(int(round(math.log(int(target[1:]), 4)))):
            m = m.subdivide()
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
    else:
        try:
            m = trimesh.Trimesh(v, f, process=False).simplify_quadric_decimation(face_count=target)
            v, f, how = np.asarray(m.vertices), np.asarray(m.faces), "quadric decimation"
        except (ImportError, ModuleNotFoundError, AttributeError):
            # vertex clustering: bisect the cell size for about ``target`` triangles
            lo, hi = 1e-4, 0.05
            for _ in range(30):
                mid = math.sqrt(lo * hi)
                vn, fn = _cluster(v, f, mid)
                lo, hi = (mid, hi) if len(fn) > target else (lo, mid)
                if abs(len(fn) - target) < 0.03 * target:
                    break
            v, f, how = vn, fn, "vertex clustering"
    if not path.exists():
        trimesh.Trimesh(v.astype(np.float32), f.astype(np.int32), process=False).export(str(path))
    return path, how


# ---- one render in a fresh process -------------------------------------------------------------
def run(scene: Path, tag: str, method: str, sets: list[str]) -> tuple:
    """(record, image) of one render in a fresh process; (None, the error line) when the
    render was refused for going beyond ``--max-memory``."""
    img, st = OUT / "runs" / f"{tag}.npy", OUT / "runs" / f"{tag}.json"
    img.parent.mkdir(parents=True, exist_ok=True)
    cmd = [PY, "-m", "clscatter", "render", str(scene), "--method", method, "-o", str(img),
           "--stats", str(st), "--no-progress", "--time-budget", "0", "--max-memory", MAX_MEMORY]
    for s in sets:
        cmd += ["--set", s]
    log = OUT / "runs" / f"{tag}.log"
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)      # this child's own peak RSS
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    rss = usage.ru_maxrss * 1024
    err = log.read_text()
    if proc.returncode == 2 and "--max-memory" in err:
        return None, err.strip().splitlines()[-1]       # refused: over the memory bound
    if proc.returncode != 0:
        raise SystemExit(f"{tag}: exit {proc.returncode}: {err.strip()}")
    stats = json.loads(st.read_text())
    rec = {"tag": tag, "method": method, "sets": sets, "wall_seconds": wall,
           "max_rss_bytes": rss, **{k: stats.get(k) for k in KEEP},
           "stages": {k: round(v, 4) for k, v in stats.get("stages", {}).items() if v >= 0.001},
           "notes": sorted({ln.split("note: ", 1)[1] for ln in err.splitlines() if "note:" in ln})}
    rec["lsg_seconds"] = sum(rec["stages"].get(k, 0.0) for k in STAGES_LSG)
    rec["method_requested"] = method
    return rec, np.load(img)


def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def reference(scene: Path, method: str, sets: list[str]) -> tuple[np.ndarray, dict]:
    key = _key(scene.read_text(), method, sets)
    path = OUT / f"reference_{method}_{key}.npy"
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        return np.load(path), {**json.loads(meta.read_text()), "cached": True}
    print(f"reference: {method} {sets} (cached as {path.name}) ...", flush=True)
    rec, img = run(scene, f"reference_{method}_{key}", method, sets)
    np.save(path, img)
    write_image(path.with_suffix(".png"), img)
    meta.write_text(json.dumps(rec, indent=1))
    return img, {**rec, "cached": False}


def _log(rec: dict, extra: str = "") -> None:
    print(f"{rec['tag']}: {rec['wall_seconds']:.1f} s process, render {rec['render_seconds']:.1f} s, "
          f"lsg stages {rec['lsg_seconds']:.1f} s, peak {rec['peak_bytes'] / 2**20:.0f} MiB"
          f"{extra}", flush=True)


# ---- the plot ---------------------------------------------------------------------------------
def _loglog(a, xlabel: str, ylabel: str) -> None:
    """Log-log axes with labels, a grid and the legend."""
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlabel(xlabel)
    a.set_ylabel(ylabel)
    a.grid(True, which="both", alpha=0.3)
    if a.get_legend_handles_labels()[0]:
        a.legend(fontsize=8)


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(20, 4.6))
    colours = {"lsg": "tab:blue", "vpm": "tab:red", "auto": "tab:green"}
    lsg = result["lsg_front"]
    vpm = [r for r in result.get("table", []) if r["method"] == "vpm"]
    for panel, (cost, scale, label) in enumerate((("render_seconds", 1.0, "render seconds"),
                                                  ("peak_bytes", 2.0 ** -20, "peak_bytes (MiB)"))):
        a = ax[panel]
        for m, rows in (("lsg", lsg), ("vpm", vpm)):
            pts = [(r["relmse"], r[cost] * scale) for r in rows]
            if not pts:
                continue
            a.scatter(*zip(*pts), color=colours[m], s=16, alpha=0.6)
            fr = pareto(pts)
            a.plot(*zip(*fr), "-o", color=colours[m], ms=4, label=f"{m} (Pareto front)")
        _loglog(a, "relMSE against the converged lsg", label)
    for panel, (cost, label) in enumerate((("render_seconds", "render seconds (relative)"),
                                           ("peak_bytes", "peak_bytes (relative)")), start=2):
        a = ax[panel]
        for name, sw in result["sweeps"].items():
            xs = [r["x"] for r in sw["runs"]]
            ys = [r[cost] for r in sw["runs"]]
            k = sw["slope_" + cost]
            a.plot(np.array(xs) / xs[0], np.array(ys) / ys[0], "-o", label=f"{name} (slope {k:.2f})")
        _loglog(a, "triangles / lighting rays / pixels, relative to the smallest", label)
    fig.suptitle(f"paper_bunny {result['size']} {result['spp']} spp: LSG growth, LSG vs VPM "
                 f"({'quick' if result['quick'] else 'full'})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---- main -------------------------------------------------------------------------------------
def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="128 x 128, 1 spp, 100k rays (minutes)")
    ap.add_argument("--no-copy", action="store_true", help="do not copy results to docs/bench/")
    ap.add_argument("--out", type=Path, default=None,
                    help="folder for runs, references and results (default bench_out/paper_scale)")
    ap.add_argument("--parts", default=",".join(PARTS),
                    help="comma-separated parts to run, of " + ", ".join(PARTS) +
                         " (the JSON is rewritten after each)")
    ap.add_argument("--reference-seconds", type=float, default=0.0,
                    help="size the references' passes to about this many seconds each, "
                         "from the lsg row's time (0: the mode's passes)")
    ap.add_argument("--deadline", type=float, default=None,
                    help="seconds for the whole run: VPM runs that would not fit are skipped")
    ap.add_argument("--no-auto", action="store_true",
                    help="leave out the table's auto row (and its reference)")
    ap.add_argument("--vpm-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a render.vpm setting for every VPM run (repeatable), e.g. knn=128 "
                         "dx=0.002, the LSG paper's; default: the engine's own")
    ap.add_argument("--name", default="paper_scale",
                    help="docs/bench/NAME.{json,png} that the results are copied to")
    args = ap.parse_args(argv)
    cfg = QUICK if args.quick else FULL
    bad = [kv for kv in args.vpm_set if "=" not in kv]
    if bad:
        ap.error(f"--vpm-set: expected KEY=VALUE, got {bad[0]!r}")
    vpm_sets = [f"render.vpm.{kv.strip()}" for kv in args.vpm_set]
    parts = [x.strip() for x in args.parts.split(",") if x.strip()]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        ap.error(f"--parts: unknown {', '.join(unknown)} (choose from {', '.join(PARTS)})")
    global OUT
    if args.out is not None:
        OUT = args.out.resolve()
    OUT.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    base = write_scene(scene_dict(cfg), "paper_bunny")
    w, h = cfg["size"]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    result = {"scene": "paper_bunny", "size": f"{w}x{h}", "spp": cfg["spp"], "quick": args.quick,
              "commit": commit, "machine": platform.processor() or platform.machine(),
              "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
              "load_average_start": os.getloadavg(), "max_memory": MAX_MEMORY,
              "light_rays": cfg["light_rays"], "vpm_settings": list(args.vpm_set)}

    def save() -> None:                 # after every part: a cut-off run keeps what it did
        result["seconds_total"] = time.perf_counter() - t_start
        result["load_average_end"] = os.getloadavg()
        (OUT / "bench_paper_scale.json").write_text(json.dumps(result, indent=1, default=float))

    def left() -> float:
        return math.inf if args.deadline is None else args.deadline - (time.perf_counter() - t_start)

    # ---- the lsg row first where the references are sized to a time ----
    rl = dict(cfg["ref_lsg"])
    ra = dict(cfg["ref_auto"])
    first = None
    if args.reference_seconds:
        first = run(base, "lsg", "lsg", [])
        # a pass of the reference's rays, from the row's time and LSG's growth (rays^(5/6))
        per_pass = first[0]["render_seconds"] * (rl["light_rays"] / cfg["light_rays"]) ** (5 / 6)
        rl["passes"] = int(min(rl["passes"], max(2, args.reference_seconds // max(per_pass, 1e-3))))
        ra["passes"] = rl["passes"]

    # ---- references (the auto reference only for the table's auto row) ----
    ref_lsg, ref_lsg_rec = reference(base, "lsg", [f"render.lsg.light_rays={rl['light_rays']}",
                                                   f"render.lsg.passes={rl['passes']}"])
    result["references"] = {"lsg": {"settings": rl, "render_seconds": ref_lsg_rec["render_seconds"],
                                    "cached": ref_lsg_rec["cached"]}}
    save()

    def lsg_row() -> dict:
        rec, img = first if first is not None else run(base, "lsg", "lsg", [])
        rec.update(relmse=relmse(img, ref_lsg), reference="lsg",
                   setting=f"{cfg['light_rays']:,} lighting rays")
        _log(rec, f", relMSE {rec['relmse']:.2e}")
        result["device"] = rec.get("device")
        return rec

    # ---- Table 1: auto, lsg, vpm ----
    lsg_main = None
    if "table" in parts:
        table = result["table"] = []
        lsg_main = lsg_row()
        table.append(lsg_main)
        save()
        for passes, rays in cfg["lsg_passes"]:
            rec, img = run(base, f"lsg_{passes}x{rays}", "lsg",
                           [f"render.lsg.passes={passes}", f"render.lsg.light_rays={rays}"])
            if rec is None:
                print(f"lsg_{passes}x{rays}: refused: {img}", flush=True)
                result.setdefault("refused", []).append({"run": f"lsg_{passes}x{rays}", "message": img})
                continue
            rec.update(relmse=relmse(img, ref_lsg), reference="lsg", x=passes * rays,
                       setting=f"{passes} passes of {rays:,} lighting rays")
            table.append(rec)
            _log(rec, f", relMSE {rec['relmse']:.2e}")
            save()
        last = None                      # (photons, seconds) of the last VPM run
        for p in cfg["vpm_photons"]:
            if last is not None and last[1] * p / last[0] > left():
                print(f"vpm_{p}: skipped (about {last[1] * p / last[0]:.0f} s, "
                      f"{left():.0f} s left)", flush=True)
                result.setdefault("skipped", []).append(f"vpm_{p}")
                continue
            rec, img = run(base, f"vpm_{p}", "vpm", [f"render.vpm.photons={p}", *vpm_sets])
            if rec is None:                  # beyond --max-memory: refused before it began
                print(f"vpm_{p}: refused: {img}", flush=True)
                result.setdefault("refused", []).append({"run": f"vpm_{p}", "message": img})
                save()
                continue
            rec.update(relmse=relmse(img, ref_lsg), reference="lsg",
                       setting=", ".join([f"{p:,} photons", *args.vpm_set]))
            table.append(rec)
            last = (p, rec["wall_seconds"])
            _log(rec, f", relMSE {rec['relmse']:.2e}")
            save()
    if "table" in parts and not args.no_auto:
        sets = [f"render.lsg.light_rays={ra['light_rays']}",
                f"render.raymap.photons={ra['raymap_photons']}",
                f"render.raymarch.steps={ra['raymarch_steps']}"]
        if "passes" in ra:
            sets.append(f"render.lsg.passes={ra['passes']}")
        ref_auto, ref_auto_rec = reference(base, "auto", sets)
        result["references"]["auto"] = {"settings": ra,
                                        "render_seconds": ref_auto_rec["render_seconds"],
                                        "cached": ref_auto_rec["cached"]}
        rec, img = run(base, "auto", "auto", [])
        rec.update(relmse=relmse(img, ref_auto), reference="auto",
                   setting=f"{cfg['light_rays']:,} lighting rays a pass")
        table.insert(0, rec)
        _log(rec, f", relMSE {rec['relmse']:.2e}")
        save()
    if lsg_main is None and set(parts) & {"rays", "triangles"}:
        lsg_main = lsg_row()

    # ---- growth of LSG ----
    sweeps = result["sweeps"] = {}
    front_keys = ("relmse", "render_seconds", "peak_bytes", "x")
    in_passes = [{k: r[k] for k in front_keys} for r in result.get("table", [])
                 if r["method"] == "lsg" and "x" in r]          # the rows run in passes
    result["lsg_front"] = ([{k: lsg_main[k] for k in front_keys[:3]} | {"x": cfg["light_rays"]}]
                           if lsg_main else []) + in_passes

    def finish(name: str, rows: list) -> None:
        xs = [r["x"] for r in rows]
        sw = {"runs": rows}
        for cost in ("render_seconds", "lsg_seconds", "peak_bytes"):
            sw["slope_" + cost] = slope(xs, [max(r[cost], 1e-9) for r in rows])
        sw["runs"] = [{k: r.get(k) for k in ("x", "tag", "wall_seconds", "render_seconds",
                                             "lsg_seconds", "peak_bytes", "triangles",
                                             "light_rays", "view_segments", "relmse", "mesh",
                                             "stages")} for r in rows]
        sweeps[name] = sw
        save()

    if "rays" in parts:
        rows = []
        for r in cfg["rays"]:
            if r == cfg["light_rays"]:
                rec = dict(lsg_main)
            else:
                rec, img = run(base, f"lsg_rays_{r}", "lsg", [f"render.lsg.light_rays={r}"])
                rec["relmse"] = relmse(img, ref_lsg)
                _log(rec, f", relMSE {rec['relmse']:.2e}")
            rec["x"] = r
            rows.append(rec)
        result["lsg_front"] = [{k: r[k] for k in front_keys} for r in rows] + in_passes
        finish("lighting rays", rows)
    if "pixels" in parts:
        rows = []
        for pw, ph in cfg["pixels"]:
            rec, _ = run(write_scene(scene_dict(cfg, size=(pw, ph)), f"paper_bunny_{pw}x{ph}"),
                         f"lsg_pixels_{pw}x{ph}", "lsg", [])
            rec["x"] = pw * ph * cfg["spp"]
            rows.append(rec)
            _log(rec)
        finish("pixels (camera samples)", rows)
    if "triangles" in parts:
        rows = []
        for t in cfg["triangles"]:
            mesh, how = bunny_variant(t)
            scene = base if t is None else write_scene(scene_dict(cfg, mesh=mesh), f"paper_bunny_tri_{t}")
            rec, _ = (dict(lsg_main), None) if t is None else run(scene, f"lsg_tri_{t}", "lsg", [])
            rec["x"] = rec["triangles"]
            rec["mesh"] = how
            rows.append(rec)
            _log(rec, f", {rec['triangles']} triangles ({how})")
        finish("triangles", rows)

    if "table" in parts:
        derive(result)
    save()
    plot(result, OUT / "bench_paper_scale.png")
    if not args.no_copy:
        DOCS.mkdir(parents=True, exist_ok=True)
        shutil.copy(OUT / "bench_paper_scale.json", DOCS / f"{args.name}.json")
        shutil.copy(OUT / "bench_paper_scale.png", DOCS / f"{args.name}.png")
    summary(result)
    return result


def derive(result: dict) -> None:
    """Equal-error figures from the runs: VPM's cost at the ``lsg`` row's error (along VPM's
    Pareto front), and VPM / LSG ratios where the two fronts overlap (LSG's front from the
    lighting-ray sweep; ``bench_caustics.equal_error``)."""
    table = result["table"]
    lsg_main = next(r for r in table if r["method"] == "lsg")
    vpm = [r for r in table if r["method"] == "vpm"]
    eq = {"relmse": lsg_main["relmse"], "lsg_render_seconds": lsg_main["render_seconds"],
          "lsg_peak_bytes": lsg_main["peak_bytes"]}
    for cost in ("render_seconds", "peak_bytes"):
        front = pareto([(r["relmse"], r[cost]) for r in vpm])
        c, upper = cost_at(front, lsg_main["relmse"])
        eq[f"vpm_{cost}"] = c
        eq[f"vpm_{cost}_upper_bound"] = upper
        eq[f"ratio_{cost}"] = None if c is None else c / lsg_main[cost]
    best = min(vpm, key=lambda r: r["relmse"])         # VPM's least error and what it cost
    eq["vpm_least_relmse"] = best["relmse"]
    eq["vpm_least_relmse_costs"] = {c: best[c] for c in ("render_seconds", "peak_bytes")}
    eq["rows"] = []                      # every lsg row: VPM's cost at its error, as a ratio
    for r in (r for r in table if r["method"] == "lsg"):
        row = {"setting": r["setting"], "relmse": r["relmse"]}
        for cost in ("render_seconds", "peak_bytes"):
            c, upper = cost_at(pareto([(v["relmse"], v[cost]) for v in vpm]), r["relmse"])
            row[f"ratio_{cost}"] = None if c is None else c / r[cost]
            row[f"vpm_{cost}_upper_bound"] = upper
            # not reached: what VPM's least error cost, against this row's
            row[f"vpm_least_relmse_over_{cost}"] = best[cost] / r[cost]
        eq["rows"].append(row)
    eq["vpm_reaches_lsg_error"] = eq["vpm_least_relmse"] <= lsg_main["relmse"]
    result["equal_error"] = eq
    fronts = [{"method": "lsg", **r} for r in result["lsg_front"]] + \
             [{"method": "vpm", **{k: r[k] for k in ("relmse", "render_seconds", "peak_bytes")}}
              for r in vpm]
    result["equal_error_fronts"] = {cost: equal_error(fronts, cost, levels=3)
                                    for cost in ("render_seconds", "peak_bytes")}


def summary(result: dict) -> None:
    mib = 2.0 ** -20
    print(f"\npaper_bunny {result['size']}, {result['spp']} spp, commit {result['commit']}, "
          f"device {result.get('device')}, "
          f"--max-memory {result['max_memory']}, --time-budget 0; VPM "
          + (", ".join(result["vpm_settings"]) if result.get("vpm_settings") else "at its defaults")
          + f"; total {result['seconds_total']:.0f} s\n")
    print("| method | setting | whole process s | render s | peak_bytes (MiB) | relMSE (reference) |")
    print("|---|---|---|---|---|---|")
    for r in result.get("table", []):
        print(f"| `{r['method_requested']}` ({r['method']}) | {r['setting']} | {r['wall_seconds']:.1f} | "
              f"{r['render_seconds']:.1f} | {r['peak_bytes'] * mib:.0f} | {r['relmse']:.2e} "
              f"(converged `{r['reference']}`) |")
    eq = result.get("equal_error")
    for cost, unit in (("render_seconds", "time"), ("peak_bytes", "peak memory")) if eq else ():
        if eq[f"ratio_{cost}"] is None:
            print(f"\nVPM / LSG {unit} at LSG's relMSE {eq['relmse']:.2e}: not reached "
                  f"(VPM's least relMSE {eq['vpm_least_relmse']:.2e})")
        else:
            flag = " (VPM: upper bound)" if eq[f"vpm_{cost}_upper_bound"] else ""
            print(f"\nVPM / LSG {unit} at LSG's relMSE {eq['relmse']:.2e}: "
                  f"{eq[f'ratio_{cost}']:.2f}x{flag}")
        for r in eq["rows"]:
            ratio = r[f"ratio_{cost}"]
            least = (f"not reached (VPM's least relMSE, {eq['vpm_least_relmse']:.2e}, took "
                     f"{r[f'vpm_least_relmse_over_{cost}']:.2f}x LSG's {unit})")
            print(f"  lsg {r['setting']} (relMSE {r['relmse']:.2e}): VPM / LSG {unit} "
                  + (least if ratio is None else f"{ratio:.2f}x")
                  + (" (VPM: upper bound)" if r[f"vpm_{cost}_upper_bound"] else ""))
        for r in result.get("equal_error_fronts", {}).get(cost, []):
            flag = " (lsg: upper bound)" if r["lsg_upper_bound"] else (
                " (vpm: upper bound)" if r["vpm_upper_bound"] else "")
            print(f"  along both fronts at relMSE {r['relmse']:.2e}: VPM / LSG {unit} "
                  f"{r['ratio_vpm_over_lsg']:.2f}x (lsg {r['lsg']:.4g}, vpm {r['vpm']:.4g}){flag}")
    print("\n| LSG grows with | values | render s | LSG stages s | peak_bytes (MiB) | "
          "slope: render s | slope: LSG stages | slope: peak memory |")
    print("|---|---|---|---|---|---|---|---|")
    for name, sw in result["sweeps"].items():
        rs = sw["runs"]
        cols = [" / ".join(f"{r['x']:,}" for r in rs),
                " / ".join(f"{r['render_seconds']:.1f}" for r in rs),
                " / ".join(f"{r['lsg_seconds']:.1f}" for r in rs),
                " / ".join(f"{r['peak_bytes'] * mib:.0f}" for r in rs)]
        print(f"| {name} | {' | '.join(cols)} | {sw['slope_render_seconds']:.2f} | "
              f"{sw['slope_lsg_seconds']:.2f} | {sw['slope_peak_bytes']:.2f} |")


if __name__ == "__main__":
    main()
