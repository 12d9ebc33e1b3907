#!/usr/bin/env python3
"""Tile grids against the BVH for the ray families they serve, in one process.

For each scene at 640x480 (4 spp), the scene prepared twice, with its tile grids and with
none (``tile_grid.worth_it`` forced false, so every ray traverses the BVH):

- ``trace_view``: the camera paths (segments, diffuse hits and shading), seconds;
- ``shade_hits``: re-shading the recorded diffuse hits (a light move), seconds;
- ``shadow_map``: epipolar's 1280-texel shadow map of the first light (directional, or a
  spot's single face), seconds, and the grid's host build time;
- ``raymarch``: the ``raymarch`` stage of a whole ``--method raymarch`` render, seconds,
  and the relMSE of its image against the BVH-only one (expected ~0: the same hits; an
  orthographic grid's distances agree with the BVH's to float rounding, a perspective
  grid's to the bit);
- the grids' list statistics (``tile_grids`` of ``--stats``).

Each time is the best of two runs after a warm-up. Writes ``bench_out/tile_grids.json``
and copies it to ``docs/bench/``::

    .venv/bin/python tools/bench_tile_grids.py [--scenes shafts occluder] [--no-copy]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_output import publish  # noqa: E402

from clscatter.accel import tile_grid  # noqa: E402
from clscatter.device import get_engine  # noqa: E402
from clscatter.io.image import relmse
from clscatter.methods.epipolar import geometry as geo  # noqa: E402
from clscatter.methods.epipolar import maps
from clscatter.pipeline.render import render
from clscatter.scene import load_scene  # noqa: E402
from clscatter.transport import view_paths
from clscatter.transport.prepared import prepare_scene

SCENES = ("shafts", "epi_grille", "epi_window", "epi_forest", "epi_sun", "epi_spot",
          "occluder", "caustic_sphere")
SETTINGS = ["camera.resolution=[640,480]", "camera.spp=4"]
MAP_RES = 1280


def _best(fn, eng, runs: int = 2) -> float:
    fn()                                    # warm-up: program loading, first launches
    eng.finish()
    best = float("inf")
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        eng.finish()
        best = min(best, time.perf_counter() - t)
    return best


def _shadow_map(ps, use_grid: bool) -> tuple[float, float] | None:
    """(kernel seconds, host build seconds) of the first light's shadow map, or None
    for lights epipolar has no single map for."""
    eng = ps.engine
    light = ps.lights[0]
    if int(light["type"]) not in (1, 2):
        return None
    cam = geo.CameraGeom.from_struct(ps.camera)
    axis = geo.make_axis(light, cam.origin)
    frame = geo.frame_struct(axis, ps.medium, 1)
    faces = maps.setup_shadow_map(frame, axis, ps, MAP_RES)
    if int(frame["sm_faces"]) > 1:
        return None
    t = time.perf_counter()
    maps.shadow_map_grid(ps, frame, faces)
    build = time.perf_counter() - t if use_grid else 0.0
    fb = eng.to_device(frame.reshape(1))
    bufs = []

    def run():
        bufs.append(maps.trace_shadow_map(ps, fb, MAP_RES, {}, faces,
                                          frame=frame if use_grid else None))
    try:
        return _best(run, eng), build
    finally:
        eng.free(fb, *bufs)


def measure(name: str, use_grid: bool) -> dict:
    eng = get_engine()
    real = tile_grid.worth_it
    if not use_grid:
        tile_grid.worth_it = lambda grid: False
    try:
        scene = load_scene(f"builtin:{name}", SETTINGS)
        ps = prepare_scene(scene, eng)
        grids = {"camera": tile_grid.camera_grid(ps.bvh, ps.camera),
                 "light": tile_grid.light_grid(ps.bvh, ps.lights)}
        out: dict = {"grids": {k: g.stats() if g is not None else None
                               for k, g in grids.items()}}
        hits = []

        def trace():
            for h in hits:
                h.release()
            hits[:] = [view_paths._trace(ps, None, view_paths.SAMPLES_PER_LAUNCH, shade=True,
                                         want_segs=True, want_hits=True)[2]]
        out["trace_view"] = _best(trace, eng)
        out["shade_hits"] = _best(lambda: view_paths.shade_hits(ps, hits[0]), eng)
        sm = _shadow_map(ps, use_grid)
        out["shadow_map"], out["shadow_map_grid_build"] = sm if sm else (None, None)
        for h in hits:
            h.release()
        ps.release()
        res = render(scene, method="raymarch", engine=eng, show_progress=False)
        out["raymarch"] = float(res.stats["stages"]["raymarch"])
        out["image"] = res.image
        return out
    finally:
        tile_grid.worth_it = real


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--no-copy", action="store_true", help="do not copy the JSON to docs/bench")
    args = ap.parse_args()
    rows = {}
    print("| scene | trace_view s (BVH) | shade_hits s (BVH) | shadow map s (BVH; build) | "
          "raymarch s (BVH) | raymarch relMSE | light grid mean list |")
    print("|---|---|---|---|---|---|---|")
    for name in args.scenes:
        g, b = measure(name, True), measure(name, False)
        err = float(relmse(g.pop("image"), b.pop("image")))
        rows[name] = {"grid": g, "bvh": b, "raymarch_relmse_grid_vs_bvh": err}
        sm = (f"{g['shadow_map']:.3f} ({b['shadow_map']:.3f}; "
              f"{1e3 * g['shadow_map_grid_build']:.1f} ms)" if g["shadow_map"] is not None else "-")
        lg = g["grids"]["light"]
        print(f"| {name} | {g['trace_view']:.3f} ({b['trace_view']:.3f}) | "
              f"{g['shade_hits']:.3f} ({b['shade_hits']:.3f}) | {sm} | "
              f"{g['raymarch']:.2f} ({b['raymarch']:.2f}) | {err:.1e} | "
              f"{lg['mean_list'] if lg else '-'} |", flush=True)
    result = {"device": get_engine().name, "settings": SETTINGS, "scenes": rows}
    publish(result, "tile_grids", copy=not args.no_copy)


if __name__ == "__main__":
    main()
