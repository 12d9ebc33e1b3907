"""Epipolar against ray marching under spot lights of growing half-angle, at equal samples.

    .venv/bin/python tools/bench_epipolar_wide_spot.py [--out FILE.json]

``epi_wide_spot`` (the grate of ``epi_grille`` under a spot light just above it) at 64 x 48
for half-angles 30 .. 90 degrees: epipolar and raymarch at 16 spp, each against a ray-marched
reference at 64 spp and 128 steps (another seed). The error is the relative MSE with a floor
scaled to the reference, ``mean((a - b)^2 / (b^2 + 0.01 mean(b)^2))``; it includes the
reference's own noise, which both methods share. Where epipolar's error exceeds ray
marching's, ``auto`` passes it over (``Epipolar.unreliable``, ``WIDE_SPOT``).
"""
from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np

from clscatter.device import get_engine
from clscatter.pipeline.session import RenderSession
from clscatter.scene.builtin.epipolar import epi_wide_spot

REPO = Path(__file__).resolve().parents[1]
CUTOFFS = (30, 50, 60, 70, 80, 90)
RUNS = {"reference": ("raymarch", ["camera.spp=64", "render.raymarch.steps=128", "render.seed=3"]),
        "epipolar": ("epipolar", ["camera.spp=16"]),
        "raymarch": ("raymarch", ["camera.spp=16"])}


def error(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.mean((a - ref) ** 2 / (ref ** 2 + 0.01 * np.mean(ref) ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(REPO / "docs" / "bench" / "epipolar_wide_spot.json"))
    args = ap.parse_args()
    eng = get_engine()
    rows = []
    for cut in CUTOFFS:
        scene = epi_wide_spot(cut, (64, 48))
        imgs = {}
        for name, (method, sets) in RUNS.items():
            with RenderSession.from_data(scene, ".", "epi_wide_spot", sets, method=method,
                                         engine=eng) as s:
                imgs[name] = s.render(show_progress=False).medium
        ref = imgs["reference"]
        row = {"cutoff": cut, "epipolar": error(imgs["epipolar"], ref),
               "raymarch": error(imgs["raymarch"], ref),
               "epipolar_mean_ratio": float(imgs["epipolar"].mean() / ref.mean())}
        rows.append(row)
        print(row, flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    Path(args.out).write_text(json.dumps({"commit": commit, "device": eng.info.label,
                                          "resolution": [64, 48], "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
