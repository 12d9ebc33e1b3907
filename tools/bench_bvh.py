#!/usr/bin/env python3
"""Benchmark: our BVH (NumPy build, OpenCL traversal) against Intel Embree (embreex).

The Stanford bunny, subdivided once (> 100k triangles) and normalised to unit size, is
rendered with a pinhole camera (primary rays, closest hit) and the primary hits are
tested against a point light (shadow rays, any hit, ``tmax`` = the light). The same rays
go to our ``closest_hit`` / ``any_hit`` kernels (cl_kernels/bvh.cl) and to Embree
(``EmbreeScene.run``; ``query='OCCLUDED'`` for shadow rays). Rays per second are the
median over ``--repeats`` timed runs after a warm-up; ours are timed with the rays
already on the device (kernel launch + finish; the end-to-end ``trace()`` rate with
transfers is reported too). Embree runs single-threaded per ``run`` call; it is also
timed with the rays split over as many Python threads as there are CPU cores
(embreex releases the GIL), which is the fair comparison with the OpenCL CPU device.

Writes a JSON record (``--out``) and a bar plot next to it (``.png``).

    python3 tools/bench_bvh.py [--mesh PATH] [--size 512] [--repeats 5]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from clscatter.accel.bvh import build_bvh, trace  # noqa: E402
from clscatter.device import get_engine  # noqa: E402

SHADOW_EPS = 1e-4   # shadow ray origin offset along the normal (normalised units)


def load_mesh(path: Path, subdivide: int) -> np.ndarray:
    import trimesh
    m = trimesh.load(path, force="mesh", process=True)
    for _ in range(subdivide):
        m = m.subdivide()
    v = np.asarray(m.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - 0.5 * (lo + hi)) / (hi - lo).max()
    return v[np.asarray(m.faces)]


def camera_rays(size: int, eye, target, fov_deg: float = 40.0):
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    tan = np.tan(np.radians(fov_deg) / 2)
    s = (np.arange(size) + 0.5) / size * 2 - 1
    sx, sy = np.meshgrid(s, -s)
    d = fwd + tan * (sx[..., None] * right + sy[..., None] * up)
    d = d.reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape).copy()
    return o.astype(np.float32), d.astype(np.float32)


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


class Ours:
    """Rays resident on the device; timing = launch + finish."""

    def __init__(self, engine, bvh):
        self.e, self.bvh = engine, bvh
        self.bufs = bvh.upload(engine)

    def prepare(self, o, d):
        e = self.e
        n = len(o)
        o4 = np.zeros((n, 4), np.float32)
        d4 = np.zeros((n, 4), np.float32)
        o4[:, :3], d4[:, :3] = o, d
        return n, e.to_device(o4), e.to_device(d4), e.empty(4 * n), e.empty(4 * n)

    def closest(self, rays, tmax=np.inf):
        n, ob, db, tb, ib = rays
        k = self.e.kernel("bvh", "closest_hit")
        self.e.launch(k, n, self.bufs.nodes, self.bufs.triangles, ob, db, np.float32(0.0),
                      np.float32(tmax), np.int32(n), tb, ib)
        self.e.queue.finish()

    def any(self, rays, tmax):
        n, ob, db, tb, ib = rays
        k = self.e.kernel("bvh", "any_hit")
        self.e.launch(k, n, self.bufs.nodes, self.bufs.triangles, ob, db, np.float32(0.0),
                      np.float32(tmax), np.int32(n), ib)
        self.e.queue.finish()

    def free(self, rays):
        self.e.free(*rays[1:])


def embree_runner(tris32: np.ndarray):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, tris32)
    return scene


def embree_threaded(scene, o, d, threads, **kw):
    """Split the rays over ``threads`` Python threads (embreex releases the GIL)."""
    if threads <= 1:
        return scene.run(o, d, **kw)
    parts = np.array_split(np.arange(len(o)), threads)

    def job(ix):
        kk = dict(kw)
        if isinstance(kk.get("dists"), np.ndarray):
            kk["dists"] = kk["dists"][ix].copy()
        return scene.run(np.ascontiguousarray(o[ix]), np.ascontiguousarray(d[ix]), **kk)

    with ThreadPoolExecutor(threads) as ex:
        return np.concatenate(list(ex.map(job, parts)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh", type=Path,
                    default=REPO / "models" / "stanford-bunny.obj")
    ap.add_argument("--subdivide", type=int, default=1)
    ap.add_argument("--size", type=int, default=512, help="image side (rays = size^2)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                    help="threads for the multi-threaded Embree timing")
    ap.add_argument("--device", default=None, help="OpenCL device (see clscatter devices)")
    ap.add_argument("--out", type=Path, default=REPO / "bench_out" / "bvh.json")
    args = ap.parse_args(argv)

    tris = load_mesh(args.mesh, args.subdivide)
    tris32 = tris.astype(np.float32)
    print(f"mesh {args.mesh.name} x{args.subdivide} subdivision: {len(tris):,} triangles")

    t0 = time.perf_counter()
    bvh = build_bvh(tris32)
    build_s = time.perf_counter() - t0
    st = bvh.stats()
    print(f"our BVH build: {build_s:.2f} s  ({st['nodes']:,} nodes, depth {st['depth']}, "
          f"mean leaf {st['mean_leaf_size']:.2f}, SAH cost {st['sah_cost']:.1f})")

    engine = get_engine(args.device)
    ours = Ours(engine, bvh)

    scene = embree_runner(tris32)
    t0 = time.perf_counter()
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commit = build
    embree_build_s = time.perf_counter() - t0

    # ---- primary rays ----
    o, d = camera_rays(args.size, eye=(0.0, 0.15, 1.9), target=(0.0, 0.0, 0.0))
    n = len(o)
    rays = ours.prepare(o, d)
    t_ours_p = median_time(lambda: ours.closest(rays), args.repeats)
    t_hit = engine.read(rays[3], n, np.float32)
    slot = engine.read(rays[4], n, np.int32)
    ours.free(rays)
    tri_ours = np.where(slot >= 0, bvh.order[np.maximum(slot, 0)], -1)
    t0 = time.perf_counter()
    t_trace, _ = trace(engine, bvh, o, d)
    e2e_p = time.perf_counter() - t0

    t_emb_p = median_time(lambda: scene.run(o, d), args.repeats)
    t_emb_p_mt = median_time(lambda: embree_threaded(scene, o, d, args.threads), args.repeats)
    emb = scene.run(o, d, output=1)
    hit_o, hit_e = slot >= 0, emb["geomID"] != -1
    agree_p = float(np.mean(hit_o == hit_e))
    both = hit_o & hit_e
    same_tri = float(np.mean(tri_ours[both] == emb["primID"][both]))
    tdiff = np.abs(t_hit[both] - emb["tfar"][both])
    print(f"primary: {n:,} rays, {hit_o.sum():,} hits; hit/miss agreement {agree_p:.6f}, "
          f"same triangle {same_tri:.5f}, max |dt| {tdiff.max():.2e}")

    # ---- shadow rays from the primary hits towards a point light ----
    light = np.array([0.8, 1.2, 1.4])
    hi = np.flatnonzero(hit_o)
    p = o[hi].astype(np.float64) + t_hit[hi, None] * d[hi]
    v = tris[tri_ours[hi]]
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm *= -np.sign((nrm * d[hi]).sum(axis=1, keepdims=True))      # towards the camera
    so = (p + SHADOW_EPS * nrm).astype(np.float32)
    sd = (light - so).astype(np.float32)                           # t = 1 at the light
    ns = len(so)
    srays = ours.prepare(so, sd)
    t_ours_s = median_time(lambda: ours.any(srays, 1.0), args.repeats)
    occ_o = engine.read(srays[4], ns, np.int32) != 0
    ours.free(srays)
    t0 = time.perf_counter()
    trace(engine, bvh, so, sd, tmax=1.0, closest=False)
    e2e_s = time.perf_counter() - t0

    def emb_shadow(threads=1):
        return embree_threaded(scene, so, sd, threads, dists=np.ones(ns, np.float32),
                               query="OCCLUDED")
    t_emb_s = median_time(emb_shadow, args.repeats)
    t_emb_s_mt = median_time(lambda: emb_shadow(args.threads), args.repeats)
    occ_e = emb_shadow() != -1
    agree_s = float(np.mean(occ_o == occ_e))
    print(f"shadow: {ns:,} rays, {occ_o.sum():,} occluded (embree {occ_e.sum():,}); "
          f"agreement {agree_s:.6f}")

    rec = {
        "mesh": str(args.mesh), "subdivide": args.subdivide, "triangles": len(tris),
        "image": [args.size, args.size],
        "device": engine.name, "host": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "embree_threads_mt": args.threads,
        "build_seconds": build_s, "embree_build_seconds": embree_build_s, "bvh": st,
        "primary": {
            "rays": n, "hits": int(hit_o.sum()),
            "ours_rays_per_s": n / t_ours_p, "ours_end_to_end_rays_per_s": n / e2e_p,
            "embree_rays_per_s": n / t_emb_p, "embree_mt_rays_per_s": n / t_emb_p_mt,
            "hit_agreement": agree_p, "same_triangle": same_tri,
            "max_abs_t_diff": float(tdiff.max()),
        },
        "shadow": {
            "rays": ns, "occluded": int(occ_o.sum()),
            "ours_rays_per_s": ns / t_ours_s, "ours_end_to_end_rays_per_s": ns / e2e_s,
            "embree_rays_per_s": ns / t_emb_s, "embree_mt_rays_per_s": ns / t_emb_s_mt,
            "hit_agreement": agree_s,
        },
        "repeats": args.repeats,
    }
    for k in ("primary", "shadow"):
        r = rec[k]
        r["ratio_ours_over_embree"] = r["ours_rays_per_s"] / r["embree_rays_per_s"]
        r["ratio_ours_over_embree_mt"] = r["ours_rays_per_s"] / r["embree_mt_rays_per_s"]

    print()
    print(f"{'rays':8s} {'ours Mray/s':>12s} {'ours e2e':>9s} {'embree 1t':>10s} "
          f"{'embree ' + str(args.threads) + 't':>10s} {'ours/emb1':>9s} {'ours/embN':>9s} "
          f"{'agree':>9s}")
    for k in ("primary", "shadow"):
        r = rec[k]
        print(f"{k:8s} {r['ours_rays_per_s'] / 1e6:12.3f} "
              f"{r['ours_end_to_end_rays_per_s'] / 1e6:9.3f} "
              f"{r['embree_rays_per_s'] / 1e6:10.3f} {r['embree_mt_rays_per_s'] / 1e6:10.3f} "
              f"{r['ratio_ours_over_embree']:9.3f} {r['ratio_ours_over_embree_mt']:9.3f} "
              f"{r['hit_agreement']:9.5f}")
    print(f"build: ours {build_s:.2f} s, embree {embree_build_s:.2f} s")
    ok = agree_p > 0.999 and agree_s > 0.999
    print("hit/miss agreement > 99.9%:", "yes" if ok else "NO")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rec, indent=2))
    png = args.out.with_suffix(".png")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(7, 4))
        labels = ["ours (OpenCL)", "embree 1 thread", f"embree {args.threads} threads"]
        keys = ["ours_rays_per_s", "embree_rays_per_s", "embree_mt_rays_per_s"]
        x = np.arange(2)
        w = 0.27
        for i, (lab, key) in enumerate(zip(labels, keys)):
            vals = [rec[k][key] / 1e6 for k in ("primary", "shadow")]
            bars = ax.bar(x + (i - 1) * w, vals, w, label=lab)
            ax.bar_label(bars, fmt="%.2f", fontsize=8)
        ticks = []
        for k, lab in (("primary", "primary (closest hit)"), ("shadow", "shadow (any hit)")):
            r = rec[k]
            ticks.append(f"{lab}\nours/embree: {r['ratio_ours_over_embree']:.2f} (1 thread), "
                         f"{r['ratio_ours_over_embree_mt']:.2f} ({args.threads})")
        ax.set_xticks(x, ticks, fontsize=8)
        ax.set_ylabel("Mrays / s")
        ax.set_title(f"{args.mesh.stem}, {len(tris):,} triangles, {args.size}x{args.size}\n"
                     f"{engine.name[:60]}", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(png, dpi=110)
        plt.close(fig)
    except Exception as e:  # the plot is a nice-to-have; the JSON record is the result
        print(f"plot skipped: {e}")
    print(f"wrote {args.out} and {png}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
