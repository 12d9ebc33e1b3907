#!/usr/bin/env python3
"""Benchmark: the ray map against the photon map at equal time, on a floor caustic with no
edge, on a caustic whose peak lies on a table's free edge, and on a narrow plank.

Both surface density estimators run progressive passes (fresh rays each pass, radii
shrinking by the progressive photon mapping rule) under the same time budget
(``render.<m>.time_budget``; ``medium = "none"``: the surface term alone), so the
comparison is at equal time by construction. Scenes: ``floor`` is the glass ball of
``builtin:caustic_sphere`` over its open floor, seen from close by (the caustic spans tens
of pixels); ``edge`` is the same ball lit from straight above, over a table top at its
focus whose free edge runs under the ball's centre, so the caustic's peak straddles the
edge (half on the table top, the rest falls past it to the floor); ``strip`` is the same
ball and light over a plank ``STRIP_WIDTH`` wide at the focus, running under the ball's
centre, so that every lit point of the plank lies near one of its two free edges (where a
photon map's disc overhangs the surface). 160x120, 4 spp (stratified), so that a pixel's
own sampling adds little to the error.

The reference is independent of both estimators: the tests' NumPy light tracer
(``tests/caustic_tracer.py``: exact sphere, Snell, Fresnel, internal reflections) lands
``--ref-photons`` photons on the floor and the table and projects each into the pixel
that sees it (``surface_image``: the box-filtered pixel radiance, no density estimation,
no blur, no boundary bias). Compared are the pixels whose view misses the ball
(``pixels_missing_sphere``); the reference's own noise (from one half of its photons
against the other) is reported beside. Each run is a fresh render in this
process; the error is relMSE (``clscatter.io.image.relmse``) of the surface caustic (the
pass's own image, direct light excluded) over those pixels and over the pixels within 3
of the images of the free edges (``edge`` and ``strip``).

Writes bench_out/surface_equal_time/bench.json (and docs/bench/surface_equal_time.json
unless ``--no-copy``) and prints a markdown table.

Beside the equal-time runs, both run ``--equal-passes`` passes with no budget (equal work:
the estimators' own accuracy), with the seconds per pass of each stage (the lighting
rays; the diffuse hits and the pieces' bookkeeping; ``build``: the tree's root or the photons' balanced
tree; ``radius``: how far the ray map's lazy tree refines in the first pass; ``refine``: the
lazy refinement on the host; ``estimate``: the first pass's K-nearest queries on the device
and every pass's weighing of the hits; ``splat``: the later passes' fixed-radius estimates
from the segments' side, with the hits' tree built once).

    .venv/bin/python tools/bench_surface_equal_time.py [--budgets 4 8 16] [--size 160x120]
"""
from __future__ import annotations

import argparse
import copy
import json
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "tests"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import caustic_tracer as ct  # noqa: E402  the tests' independent light tracer

from clscatter.device import get_engine  # noqa: E402
from clscatter.io.image import relmse  # noqa: E402
from clscatter.pipeline.render import render  # noqa: E402
from clscatter.scene import scene_from_dict  # noqa: E402
from clscatter.scene.builtin import BUILTIN  # noqa: E402

OUT = REPO / "bench_out" / "surface_equal_time"
TABLE_TOP = 0.45         # near the ball's focus; the edge is the line x = 0, z in [-1.5, 1.5]
TABLE = ([-1.8, TABLE_TOP - 0.06, -1.5], [0.0, TABLE_TOP, 1.5])
STRIP_WIDTH = 0.12       # the plank: x in [-STRIP_WIDTH / 2, STRIP_WIDTH / 2]
PLANK = ([-STRIP_WIDTH / 2, TABLE_TOP - 0.06, -1.5], [STRIP_WIDTH / 2, TABLE_TOP, 1.5])
#: the free edges' x in each scene (lines at y = TABLE_TOP along z)
EDGES = {"edge": (0.0,), "strip": (-STRIP_WIDTH / 2, STRIP_WIDTH / 2)}
ALBEDO = 0.55            # builtin:caustic_sphere's floor
#: close to the caustic, from the table's side of its edge (the edge face turned away)
CAMERA = {"origin": [-0.3, 1.1, 2.4], "target": [0.0, 0.4, 0.0], "fov": 36.0}


def scenes(size: tuple[int, int]) -> dict[str, dict]:
    floor = BUILTIN["caustic_sphere"]()
    floor["camera"].update(resolution=list(size), spp=4, **CAMERA)
    floor.pop("medium", None)
    edge = copy.deepcopy(floor)
    edge["lights"][0]["position"] = [0.0, 3.25, 0.0]
    strip = copy.deepcopy(edge)
    edge["objects"].append({"shape": "box", "min": TABLE[0], "max": TABLE[1],
                            "material": "floor"})
    strip["objects"].append({"shape": "box", "min": PLANK[0], "max": PLANK[1],
                             "material": "floor"})
    return {"floor": floor, "edge": edge, "strip": strip}


def reference(d: dict, photons: int, chunk: int = 1_000_000) -> tuple[np.ndarray, float]:
    """The tracer's surface caustic of ``d`` (``photons`` from its point light, in chunks of
    independent seeds) and its own noise: relMSE of one half against the other over the
    compared pixels, divided by 4 (the difference of two halves has twice the variance of
    a half, which has twice that of the mean)."""
    ball, clear, cam, pos, inten, _ = ct.from_scene_dict(d)
    boxes = [(o["min"], o["max"]) for o in d["objects"] if o["shape"] == "box"]
    parts = []
    for seed in range(max(2, photons // chunk)):
        beams = ct.trace(pos, inten, ball, clear, chunk, seed)
        parts.append(ct.surface_image(beams, cam, ball, ALBEDO, boxes=boxes))
    half = len(parts) // 2
    keep = compared(d)
    a, b = np.mean(parts[:half], 0), np.mean(parts[half:], 0)
    return np.mean(parts, 0), relmse(a[keep], b[keep]) / 4


def compared(d: dict) -> np.ndarray:
    """The pixels compared: those whose view misses the ball (the tracer sees the surfaces
    directly only)."""
    ball, _, cam, *_ = ct.from_scene_dict(d)
    return ct.pixels_missing_sphere(cam, ball)


def edge_mask(d: dict, shape: tuple[int, int], edges=(0.0,)) -> np.ndarray:
    """Pixels within 3 of the images of the free edges (x in ``edges``, y = TABLE_TOP)."""
    c = ct.from_scene_dict(d)[2]
    mask = np.zeros(shape, bool)
    for x, z in ((x, z) for x in edges for z in np.linspace(-1.5, 1.5, 400)):
        at = c.project([x, TABLE_TOP, z])
        if at is None:
            continue
        r0, c0 = int(at[1]), int(at[0])
        mask[max(r0 - 3, 0):r0 + 4, max(c0 - 3, 0):c0 + 4] = True
    return mask


def surface(d: dict, method: str, table: dict, engine) -> tuple[np.ndarray, dict]:
    d = copy.deepcopy(d)
    d.setdefault("render", {})
    d["render"].update(method=method, time_budget=0.0)
    d["render"][method] = {"medium": "none", **table}
    res = render(scene_from_dict(d, REPO, "<bench>"), engine=engine, show_progress=False)
    return sum(res.parts.values()), res.stats           # the caustic on surfaces alone


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budgets", type=float, nargs="*", default=[4.0, 8.0, 16.0])
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--photons", type=int, default=20_000)
    ap.add_argument("--ref-photons", type=int, default=16_000_000,
                    help="the tracer's photons for the reference")
    ap.add_argument("--equal-passes", type=int, default=8,
                    help="passes of the equal-work runs (no budget)")
    ap.add_argument("--scenes", default="floor,edge,strip",
                    help="comma-separated scenes to run, of floor, edge, strip")
    ap.add_argument("--no-copy", action="store_true")
    args = ap.parse_args()
    size = tuple(int(x) for x in args.size.split("x"))
    engine = get_engine(None)
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    wanted = [x.strip() for x in args.scenes.split(",") if x.strip()]
    for name, d in ((k, v) for k, v in scenes(size).items() if k in wanted):
        ref, noise = reference(d, args.ref_photons)
        keep = compared(d)
        mask = edge_mask(d, ref.shape[:2], EDGES[name]) & keep if name in EDGES else None
        print(f"{name}: reference noise {noise:.2g}", file=sys.stderr)
        # equal time (each budget), then equal work (--equal-passes passes, no budget)
        runs = [(b, 1024) for b in args.budgets] + [(0.0, args.equal_passes)]
        for budget, passes in runs:
            for method in ("raymap", "photonmap"):
                img, st = surface(d, method, {"photons": args.photons, "passes": passes,
                                              "time_budget": budget}, engine)
                stages = st["stages"]
                row = {"scene": name, "method": method, "budget_seconds": budget,
                       "stage_seconds": {"light_paths": stages.get("light_paths", 0.0),
                                         **{k: stages.get(f"{method}_{k}", 0.0) for k in
                                            ("trace", "build", "radius", "refine",
                                             "estimate", "splat")}},
                       "seconds": st["stages"].get(f"{method}_estimate", 0.0),
                       "passes": st.get(f"{method}_passes"),
                       "relmse": relmse(img[keep], ref[keep]), "reference_noise": noise,
                       "pass_seconds_total": float(sum(st.get(f"{method}_pass_seconds", []))),
                       "error_estimate": st.get("error_estimate")}
                if mask is not None:
                    row["relmse_edge"] = relmse(img[mask], ref[mask])
                rows.append(row)
                print(row, file=sys.stderr)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    record = {"commit": commit, "machine": platform.machine(), "size": args.size,
              "photons": args.photons, "reference": {"tracer_photons": args.ref_photons},
              "rows": rows}
    (OUT / "bench.json").write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(OUT / "bench.json", REPO / "docs" / "bench" / "surface_equal_time.json")
    print("| scene | budget s | method | passes | time in passes s | relMSE | relMSE near the edge "
          "| reference's own noise |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        edge = f"{r['relmse_edge']:.2g}" if "relmse_edge" in r else "-"
        budget = f"{r['budget_seconds']:g}" if r["budget_seconds"] > 0 else "none"
        print(f"| {r['scene']} | {budget} | {r['method']} | {r['passes']} | "
              f"{r['pass_seconds_total']:.2f} | {r['relmse']:.2g} | {edge} | "
              f"{r['reference_noise']:.1g} |")
    print("\n| scene | method | seconds per pass: lighting rays | diffuse hits and pieces | "
          "build | radius | refine | queries | splats |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["budget_seconds"] == 0:
            per = {k: v / max(r["passes"] or 1, 1) for k, v in r["stage_seconds"].items()}
            print(f"| {r['scene']} | {r['method']} | {per['light_paths']:.3f} | "
                  f"{per['trace']:.3f} | {per['build']:.3f} | "
                  f"{per['radius']:.3f} | {per['refine']:.3f} | {per['estimate']:.3f} | "
                  f"{per.get('splat', 0.0):.3f} |")


if __name__ == "__main__":
    main()
