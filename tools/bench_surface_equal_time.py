#!/usr/bin/env python3
"""Benchmark: the ray map against the photon map at equal time, on a floor caustic with no
edge and on a caustic whose peak lies on a table's free edge.

Both surface density estimators run progressive passes (fresh rays each pass, radii
shrinking by the progressive photon mapping rule) under the same time budget
(``render.<m>.time_budget``; ``medium = "none"``: the surface term alone), so the
comparison is at equal time by construction. Scenes: ``floor`` is ``builtin:caustic_sphere``
(the glass ball's caustic on an open floor); ``edge`` is the same ball over a table whose
edge runs under the ball's centre, so the caustic's peak straddles the edge (half on the
table top, the rest falls past it). Each run is a fresh render in this process; the error
is relMSE (``clscatter.io.image.relmse``) of the surface caustic (the pass's own image,
direct light excluded) against a long ray-map run
(``--ref-passes`` passes of ``--ref-photons``), over the whole image and over the pixels
within 3 of the table edge's image (``edge`` only).

Writes bench_out/surface_equal_time/bench.json (and docs/bench/surface_equal_time.json
unless ``--no-copy``) and prints a markdown table.

    .venv/bin/python tools/bench_surface_equal_time.py [--budgets 2 4 8] [--size 160x120]
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

from caustic_tracer import Camera  # noqa: E402  the tests' independent camera model

from clscatter.device import get_engine  # noqa: E402
from clscatter.io.image import relmse  # noqa: E402
from clscatter.pipeline.render import render  # noqa: E402
from clscatter.scene import scene_from_dict  # noqa: E402
from clscatter.scene.builtin import BUILTIN  # noqa: E402

OUT = REPO / "bench_out" / "surface_equal_time"
TABLE_TOP = 0.45         # near the ball's focus; the edge is the line x = 0, z in [-1.5, 1.5]


def scenes(size: tuple[int, int]) -> dict[str, dict]:
    floor = BUILTIN["caustic_sphere"]()
    floor["camera"].update(resolution=list(size), spp=1)
    floor.pop("medium", None)
    edge = copy.deepcopy(floor)
    edge["lights"][0]["position"] = [0.0, 3.25, 0.0]
    edge["objects"].append({"shape": "box", "min": [-1.8, TABLE_TOP - 0.06, -1.5],
                            "max": [0.0, TABLE_TOP, 1.5], "material": "floor"})
    return {"floor": floor, "edge": edge}


def edge_mask(d: dict, shape: tuple[int, int]) -> np.ndarray:
    """Pixels within 3 of the image of the table's free edge (x = 0, y = TABLE_TOP)."""
    cam = d["camera"]
    h, w = shape
    c = Camera(cam["origin"], cam["target"], cam.get("up", [0.0, 1.0, 0.0]), cam["fov"], w, h)
    mask = np.zeros(shape, bool)
    for z in np.linspace(-1.5, 1.5, 400):
        at = c.project([0.0, TABLE_TOP, z])
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
    ap.add_argument("--budgets", type=float, nargs="*", default=[2.0, 4.0, 8.0])
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--photons", type=int, default=20_000)
    ap.add_argument("--ref-photons", type=int, default=200_000)
    ap.add_argument("--ref-passes", type=int, default=12)
    ap.add_argument("--no-copy", action="store_true")
    args = ap.parse_args()
    size = tuple(int(x) for x in args.size.split("x"))
    engine = get_engine(None)
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, d in scenes(size).items():
        ref, _ = surface(d, "raymap", {"photons": args.ref_photons, "passes": args.ref_passes},
                         engine)
        mask = edge_mask(d, ref.shape[:2]) if name == "edge" else None
        for budget in args.budgets:
            for method in ("raymap", "photonmap"):
                img, st = surface(d, method, {"photons": args.photons, "passes": 1024,
                                              "time_budget": budget}, engine)
                row = {"scene": name, "method": method, "budget_seconds": budget,
                       "seconds": st["stages"].get(f"{method}_estimate", 0.0),
                       "passes": st.get(f"{method}_passes"), "relmse": relmse(img, ref),
                       "pass_seconds_total": float(sum(st.get(f"{method}_pass_seconds", []))),
                       "error_estimate": st.get("error_estimate")}
                if mask is not None:
                    row["relmse_edge"] = relmse(img[mask], ref[mask])
                rows.append(row)
                print(row, file=sys.stderr)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    record = {"commit": commit, "machine": platform.machine(), "size": args.size,
              "photons": args.photons, "reference": {"photons": args.ref_photons,
                                                     "passes": args.ref_passes}, "rows": rows}
    (OUT / "bench.json").write_text(json.dumps(record, indent=1))
    if not args.no_copy:
        shutil.copy(OUT / "bench.json", REPO / "docs" / "bench" / "surface_equal_time.json")
    print("| scene | budget s | method | passes | time in passes s | relMSE | relMSE near the edge |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        edge = f"{r['relmse_edge']:.2g}" if "relmse_edge" in r else "-"
        print(f"| {r['scene']} | {r['budget_seconds']:g} | {r['method']} | {r['passes']} | "
              f"{r['pass_seconds_total']:.2f} | {r['relmse']:.2g} | {edge} |")


if __name__ == "__main__":
    main()
