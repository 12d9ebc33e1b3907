#!/usr/bin/env python3
"""Two measurements behind epipolar's kernel and default choices, in one process.

1. **Built-in costs on the device**: nanoseconds per work-item of kernels that call
   ``atan2`` (the builtin and ``atan2_fast`` of ``cl_kernels/common.h``), ``fmod``, the
   floor-based remainder that replaced it, ``exp``, and ``sin``/``cos`` (the builtins and
   ``sincos_fast``, which the spot-light rectification uses), against a plain
   copy (4 M items, group size 64, median of 5 launches after a warm-up). Why the epipolar
   kernels avoid the builtin ``atan2``/``fmod``.
2. **Sensitivity of the image to epipolar's resolution settings**: each built-in
   directional-light scene at 640x480 rendered at the defaults (1280 shadow-map texels,
   640 light rays per slice at this size) and with the shadow map at 768 / 2048 texels and
   the light rays at 1280 (the previous default, two per pixel) / 320: the relMSE of each
   variant against the default image. Why the default light rays are one per pixel while
   the shadow map keeps its resolution (its texels dominate the error).

Writes ``bench_out/epipolar_costs.json`` and copies it to ``docs/bench/``::

    .venv/bin/python tools/bench_epipolar_costs.py [--scenes shafts epi_sun] [--no-copy]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_output import publish  # noqa: E402

from clscatter.device import get_engine, kernel_dir  # noqa: E402
from clscatter.io.image import relmse
from clscatter.pipeline.render import render
from clscatter.scene import load_scene  # noqa: E402

SOURCE = """
#include "common.h"
#define K(name, expr) __kernel void name(__global const float *x, __global float *y, int n) { \\
    int i = get_global_id(0); if (i >= n) return; float a = x[i]; y[i] = (expr); }
K(copy, 2.0f * a)
K(atan2_builtin, atan2(a, 1.0f - a))
K(atan2_poly, atan2_fast(a, 1.0f - a))
K(fmod_builtin, fmod(10.0f * a - 3.0f, 6.2831853f))
K(floor_remainder, (10.0f * a - 3.0f) - 6.2831853f * floor((10.0f * a - 3.0f) / 6.2831853f))
K(exp_builtin, exp(-a))
K(sin_cos_builtin, sin(a) + cos(a))
__kernel void sin_cos_poly(__global const float *x, __global float *y, int n) {
    int i = get_global_id(0); if (i >= n) return;
    float c, s = sincos_fast(x[i], &c); y[i] = s + c; }
"""
KERNELS = ("copy", "atan2_builtin", "atan2_poly", "fmod_builtin", "floor_remainder",
           "exp_builtin", "sin_cos_builtin", "sin_cos_poly")
DIRECTIONAL = ("shafts", "epi_grille", "epi_window", "epi_forest", "epi_sun")
VARIANTS = {"shadow_map_768": "render.epipolar.shadow_map=768",
            "shadow_map_2048": "render.epipolar.shadow_map=2048",
            "light_rays_1280": "render.epipolar.light_rays=1280",
            "light_rays_320": "render.epipolar.light_rays=320"}


def builtin_costs(n: int = 1 << 22, repeats: int = 5) -> dict[str, float]:
    """ns per work-item of each kernel of SOURCE (median of ``repeats`` timed launches)."""
    eng = get_engine()
    cl = eng.cl
    prog = cl.Program(eng.ctx, SOURCE).build(options=["-I", str(kernel_dir() / "shared")])
    x = np.random.default_rng(1).random(n).astype(np.float32)
    xb, yb = eng.to_device(x), eng.empty(4 * n)
    out = {}
    try:
        for name in KERNELS:
            k = getattr(prog, name)
            times = []
            for r in range(repeats + 1):
                t = time.perf_counter()
                eng.launch(k, n, xb, yb, np.int32(n))
                eng.finish()
                if r:
                    times.append(time.perf_counter() - t)
            out[name] = statistics.median(times) / n * 1e9
    finally:
        eng.free(xb, yb)
    return out


def sensitivity(scenes) -> dict[str, dict[str, float]]:
    """relMSE of each VARIANTS image against the default epipolar image, per scene."""
    base = ["camera.resolution=[640,480]", "render.method=epipolar"]
    out = {}
    for name in scenes:
        spec = f"builtin:{name}"
        ref = render(load_scene(spec, base), show_progress=False).image
        out[name] = {v: float(relmse(render(load_scene(spec, base + [s]), show_progress=False).image,
                                     ref)) for v, s in VARIANTS.items()}
        print(name, {k: f"{v:.2e}" for k, v in out[name].items()}, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=list(DIRECTIONAL))
    ap.add_argument("--no-copy", action="store_true", help="do not copy the JSON to docs/bench")
    args = ap.parse_args()
    costs = builtin_costs()
    print("ns per work-item:", {k: round(v, 2) for k, v in costs.items()}, flush=True)
    result = {"device": get_engine().name, "ns_per_item": costs,
              "relmse_vs_default": sensitivity(args.scenes)}
    publish(result, "epipolar_costs", copy=not args.no_copy)


if __name__ == "__main__":
    main()
