"""Benchmark of the voxel pipeline (Sun et al. 2008): per-stage and per-frame times, and
adaptive against fixed photon steps at equal caustic error.

Writes ``bench_out/voxel.json`` and ``bench_out/voxel.png``:

* ``table``: like the paper's Table 1: for grids 64^3 / 128^3, images 256^2 / 512^2 and
  2^16 .. 2^20 photons, the seconds of every stage of a first frame (geometry =
  voxelisation, material = mix + gradient + octree, lighting = photons, view) and of a
  light move (lighting + view; also the process's CPU seconds, which on a shared machine
  say more than wall time: wall ~ CPU / cores when the cores are free), with photon steps;
* ``adaptive_glass``: a voxelised glass ball (constant index, the paper's case) at 64^3:
  caustic error (deposited grid against 1/8-voxel steps, same photons), photon steps and
  seconds for the adaptive marcher and fixed steps of 1/2 .. 4 voxels, so the steps at
  equal error can be read off (the paper's point);
* ``adaptive_luneburg``: the Luneburg-lens beam of tests/test_voxel_photons.py at 64^3
  (index graded everywhere inside: the octree can only speed up the outside).

``--quick`` runs a small subset (~1 minute on two CPU cores). ``--grids``, ``--images`` and
``--photons`` (comma-separated) choose the table's rows instead (e.g. ``--grids 64,128,256
--images 256 --photons 65536``); ``--table-only`` skips the adaptive-step comparisons and
writes ``voxel_table.json``. Each row also has the process's peak resident memory so far
(``peak_rss_mib``: the largest grid's working set dominates it).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def stage_table(quick: bool, grids: tuple[int, ...] | None = None,
                images: tuple[int, ...] | None = None,
                photons: tuple[int, ...] | None = None) -> list[dict]:
    """Rows of per-stage seconds (first frame, best of two light moves) over ``grids`` x
    ``images`` x ``photons`` (defaults: the full table, or one row with ``quick``)."""
    from clscatter.methods.voxel import Voxel
    from clscatter.pipeline.relighter import Relighter
    from clscatter.scene.builtin.volumes import VOLUME_SCENES
    from clscatter.scene.loader import scene_from_dict
    grids = grids or ((64,) if quick else (64, 128))
    images = images or ((256,) if quick else (256, 512))
    photons = photons or ((1 << 16,) if quick else (1 << 16, 1 << 18, 1 << 20))
    rows = []
    for g in grids:
        for im in images:
            for ph in photons:
                d = VOLUME_SCENES["volume_sphere"]()
                d["camera"].update(resolution=[im, im], spp=1)
                d["render"]["voxel"] = {"resolution": g, "photons": ph}
                # every row's first frame voxelises from scratch (the engine keeps the
                # last scene's voxelised volumes for the next session otherwise)
                Voxel.release_cache()
                rl = Relighter(scene_from_dict(d))
                try:
                    rl.frame()
                    first = dict(rl.stats["stage_seconds"])
                    moves = []
                    for k in range(2):
                        rl.set_light(0, position=[0.1 + 0.15 * (k + 1), 3.3, 0.05 * k])
                        r0 = resource.getrusage(resource.RUSAGE_SELF)
                        rl.frame()
                        r1 = resource.getrusage(resource.RUSAGE_SELF)
                        cpu = r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime
                        moves.append(dict(rl.stats["stage_seconds"], total=rl.stats["seconds"],
                                          cpu_seconds=cpu))
                    row = {"grid": g, "image": im, "photons": ph, "first_frame": first,
                           "light_move": min(moves, key=lambda m: m["total"]),
                           "photon_steps": rl.stats["voxel_photon_steps"],
                           "photons_entering": rl.stats["voxel_photons_entering"],
                           "view_rays_into_grid": rl.stats["voxel_view_rays"],
                           "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
                finally:
                    rl.close()
                print(json.dumps(row), flush=True)
                rows.append(row)
    return rows


def adaptive_vs_fixed() -> list[dict]:
    import test_voxel_photons as tv

    from clscatter.device import get_engine
    from clscatter.methods.voxel.grid import make_box
    from clscatter.methods.voxel.photons import MarchSettings, march, start_state
    eng = get_engine()
    R = 0.3
    box = make_box([-0.4] * 3, [0.4] * 3, 64)
    cx, cy, cz = box.centres()
    r2 = (cx[:, None, None] ** 2 + cy[None, :, None] ** 2 + cz[None, None, :] ** 2) / R ** 2
    n = np.where(r2 < 1, np.sqrt(np.maximum(2 - r2, 1.0)), 1.0).astype(np.float32)
    fields = tv._fields(eng, box, n)
    rng = np.random.default_rng(2)
    N = 1 << 16
    rr = 0.9 * R * np.sqrt(rng.random(N))
    ph = 2 * np.pi * rng.random(N)
    pos = np.stack([np.full(N, box.lo[0]), rr * np.cos(ph), rr * np.sin(ph), np.ones(N)], 1)
    vel = np.tile([1.0, 0, 0, 0], (N, 1))
    out = []
    for name, adaptive, ds in (("adaptive", True, 1.0), ("fixed 1", False, 1.0),
                               ("fixed 1/2", False, 0.5), ("fixed 1/4", False, 0.25)):
        best = None
        for _ in range(2):
            st = start_state(eng, pos, vel, np.ones((N, 4)))
            rad, dirs = eng.zeros(16 * box.size), eng.zeros(16 * box.size)
            t = time.perf_counter()
            c = march(eng, fields, st, rad, dirs, MarchSettings(adaptive=adaptive, ds_min=ds, min_rel=0.0))
            sec = time.perf_counter() - t
            p, v, _ = st.host(eng)
            st.free(eng)
            eng.free(rad, dirs)
            best = sec if best is None else min(best, sec)
        d = v[:, :3] / np.linalg.norm(v[:, :3], axis=1, keepdims=True)
        x = p[:, :3].astype(np.float64)
        bq = (x * d).sum(1)
        t_ = bq - np.sqrt(np.maximum(bq ** 2 - ((x * x).sum(1) - R * R), 0))
        err = np.linalg.norm(x - t_[:, None] * d - [R, 0, 0], axis=1)
        row = {"marcher": name, "steps": c["steps"], "seconds": best,
               "rms_focal_error_voxels": float(np.sqrt((err ** 2).mean()) / box.h)}
        print(json.dumps(row), flush=True)
        out.append(row)
    fields.free(eng)
    return out


def adaptive_vs_fixed_glass(resolution: int = 64, photons: int = 1 << 16) -> list[dict]:
    """The paper's case: a constant-index glass ball (voxelised, blurred boundary) under a
    point light. Every marcher traces the same photons; the caustic error is the relative
    L1 difference of the deposited grid (below the ball's centre) from fixed 1/8-voxel
    steps, so it measures marching error only, not photon noise."""
    from clscatter.device import get_engine
    from clscatter.methods import configure
    from clscatter.methods.voxel import as_volume_scene
    from clscatter.methods.voxel.photons import MarchSettings, light_pass
    from clscatter.methods.voxel.pipeline import Pipeline
    from clscatter.scene.builtin.volumes import VOLUME_SCENES
    from clscatter.scene.loader import scene_from_dict
    from clscatter.transport.prepared import prepare_scene
    eng = get_engine()
    s = as_volume_scene(scene_from_dict(VOLUME_SCENES["volume_glass"]()), True)
    ps = prepare_scene(s, eng)
    pipe = Pipeline(configure("voxel", {"resolution": resolution, "margin": 0.5}))
    pipe._geometry(ps)
    pipe._material(ps)
    box = pipe.box
    cy = box.centres()[1]
    centre_y = ps.frame.point([0, 1.6, 0])[1]
    below = (cy < centre_y)[None, :, None]
    runs = [("reference", False, 0.125, 8.0), ("adaptive", True, 1.0, 8.0),
            ("adaptive, no step limit", True, 1.0, 1e6), ("fixed 1", False, 1.0, 8.0),
            ("fixed 2", False, 2.0, 8.0), ("fixed 4", False, 4.0, 8.0), ("fixed 1/2", False, 0.5, 8.0)]
    out, ref = [], None
    for name, adaptive, ds, smax in runs:
        if smax != 8.0:
            pipe.fields.free(eng)
            pipe.fields = None
            pipe.params = {**pipe.params, "step_max": smax}
            pipe._material(ps)
        best, grid = None, None
        for _ in range(1 if name == "reference" else 2):
            ms = MarchSettings(adaptive=adaptive, ds_min=ds, min_rel=1e-3)
            t = time.perf_counter()
            r = light_pass(eng, pipe.fields, ps, photons, ms, test_surfaces=True, smoothing=False)
            sec = time.perf_counter() - t
            grid = r.host(eng, box)[0][..., :3].sum(-1)
            steps = r.counters["voxel_photon_steps"]
            r.free(eng)
            best = sec if best is None else min(best, sec)
        if smax != 8.0:
            pipe.fields.free(eng)
            pipe.fields = None
            pipe.params = {**pipe.params, "step_max": 8.0}
            pipe._material(ps)
        if ref is None:
            ref = grid
        err = float(np.abs(grid - ref)[np.broadcast_to(below, grid.shape)].sum()
                    / ref[np.broadcast_to(below, grid.shape)].sum())
        row = {"marcher": name, "steps": steps, "seconds": best, "caustic_l1_error": err}
        print(json.dumps(row), flush=True)
        out.append(row)
    pipe.release(eng)
    ps.release()
    return out


def _ints(text: str) -> tuple[int, ...]:
    """'64,128,256' -> (64, 128, 256)."""
    return tuple(int(t) for t in text.split(",") if t.strip())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("-o", default="bench_out")
    ap.add_argument("--grids", type=_ints, help="table grid resolutions, e.g. 64,128,256")
    ap.add_argument("--images", type=_ints, help="table image sides, e.g. 256,512")
    ap.add_argument("--photons", type=_ints, help="table photon counts, e.g. 65536,262144")
    ap.add_argument("--table-only", action="store_true",
                    help="only the per-stage table (written to voxel_table.json)")
    a = ap.parse_args()
    from clscatter.device import get_engine
    res = {"device": get_engine().name, "cpu_cores": os.cpu_count(),
           "load_average_at_start": os.getloadavg()}
    if not a.table_only:
        res.update(adaptive_glass=adaptive_vs_fixed_glass(), adaptive_luneburg=adaptive_vs_fixed())
    res["table"] = stage_table(a.quick, a.grids, a.images, a.photons)
    res["load_average_at_end"] = os.getloadavg()
    out = Path(a.o)
    out.mkdir(exist_ok=True)
    if a.table_only:
        (out / "voxel_table.json").write_text(json.dumps(res, indent=2) + "\n")
        print(f"wrote {out / 'voxel_table.json'}")
        return
    (out / "voxel.json").write_text(json.dumps(res, indent=2) + "\n")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ad = [r for r in res["adaptive_glass"] if r["marcher"] != "reference"]
        ax[0].plot([r["steps"] for r in ad], [r["caustic_l1_error"] for r in ad], "o")
        for r in ad:
            ax[0].annotate(r["marcher"], (r["steps"], r["caustic_l1_error"]))
        ax[0].set_xlabel("photon steps")
        ax[0].set_ylabel("caustic L1 error vs 1/8-voxel steps")
        ax[0].set_xscale("log")
        ax[0].set_yscale("log")
        ax[0].set_title("glass ball (ior 1.5), 64^3, 2^16 photons")
        tab = res["table"]
        labels = [f"{r['grid']}^3 {r['image']}^2 {r['photons'] >> 10}k" for r in tab]
        ax[1].barh(labels, [r["light_move"]["lighting"] for r in tab], label="lighting")
        ax[1].barh(labels, [r["light_move"]["view"] for r in tab],
                   left=[r["light_move"]["lighting"] for r in tab], label="view")
        ax[1].set_xlabel("seconds per light move")
        ax[1].legend()
        fig.tight_layout()
        fig.savefig(out / "voxel.png", dpi=100)
    except ImportError:
        pass
    print(f"wrote {out / 'voxel.json'}")


if __name__ == "__main__":
    main()
