"""How the engine behaves on one OpenCL device: every golden case's agreement with the
images recorded on the reference CPU device, and whole-process render times.

    .venv/bin/python tools/bench_device.py [--device SPEC] [--out FILE.json] [--quick]

Part one renders every case of ``tests/golden_cases.py`` (every method and ``auto`` on every
built-in scene, 24 x 18, 1 spp, fixed seeds) on the device and compares it with
``tests/golden/golden.npz``: the largest and the mean absolute difference relative to the
recorded image's peak, the ratio of the image means, non-finite pixels. The tests require
1e-6 of the peak on the CPU device the images were recorded on; another device's
arithmetic (its exp, division, fused multiply-adds) moves them by more, and this shows by
how much. Part two times three renders as whole processes (``clscatter render``), first
with an empty kernel cache (programs compiled) and then with the cache warm: shafts by
epipolar and by raymarch at 640 x 480, caustic_sphere by auto at 320 x 240 with 4 spp. The
JSON records the device, the commit and every number.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

from golden_cases import GOLDEN, METHODS, key, render_case, sources  # noqa: E402

from clscatter.device import get_engine  # noqa: E402

RENDERS = [("shafts_epipolar", "builtin:shafts", "epipolar", ["camera.resolution=[640,480]"]),
           ("shafts_raymarch", "builtin:shafts", "raymarch", ["camera.resolution=[640,480]"]),
           ("caustic_sphere_auto", "builtin:caustic_sphere", "auto",
            ["camera.resolution=[320,240]", "camera.spp=4"])]


def agreement(engine) -> list[dict]:
    """Every golden case on ``engine`` against the recorded image."""
    golden = np.load(GOLDEN)
    rows = []
    for src in sources():
        for m in METHODS:
            k = key(src, m)
            ref = golden[k]
            t0 = time.perf_counter()
            got = render_case(src, m, engine)
            row = {"case": k, "seconds": round(time.perf_counter() - t0, 3)}
            if ref.dtype.kind == "U" or isinstance(got, str):
                row["same_refusal"] = isinstance(got, str) and got == str(ref)
            else:
                peak = max(float(np.max(np.abs(ref))), 1e-30)
                d = np.abs(got.astype(np.float64) - ref)
                row.update(rel_max=float(np.max(d)) / peak, rel_mean=float(np.mean(d)) / peak,
                           mean_ratio=float(np.mean(got)) / max(float(np.mean(ref)), 1e-30),
                           nonfinite=int(np.count_nonzero(~np.isfinite(got))))
            rows.append(row)
            print(k, {x: y for x, y in row.items() if x != "case"}, file=sys.stderr)
    return rows


def timed_render(name: str, scene: str, method: str, sets: list[str], env: dict,
                 tmp: Path) -> dict:
    """One ``clscatter render`` as a whole process: wall seconds and its statistics."""
    stats = tmp / f"{name}.json"
    cmd = [sys.executable, "-m", "clscatter", "render", scene, "--method", method,
           "--no-progress", "-o", str(tmp / f"{name}.png"), "--stats", str(stats)]
    for kv in sets:
        cmd += ["--set", kv]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        return {"name": name, "error": r.stderr.strip()[-500:]}
    s = json.loads(stats.read_text())
    top = sorted(s.get("stages", {}).items(), key=lambda kv: -kv[1])[:6]
    return {"name": name, "wall_seconds": round(wall, 3),
            "render_seconds": round(float(s["render_seconds"]), 3),
            "method": s["method"], "stages": {k: round(v, 3) for k, v in top}}


def timings(device: str | None) -> dict:
    """The renders of :data:`RENDERS`, cold (empty kernel cache) and warm."""
    out = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        env = {**os.environ, "CLSCATTER_CACHE_DIR": str(tmp / "kernels")}
        if device:
            env["CLSCATTER_DEVICE"] = device
        for when in ("cold", "warm"):
            out[when] = [timed_render(*r, env, tmp) for r in RENDERS]   # cold fills the cache
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="OpenCL device: P:D or a name substring")
    ap.add_argument("--out", default=str(REPO / "bench_out" / "device.json"))
    ap.add_argument("--quick", action="store_true", help="agreement only, no timings")
    args = ap.parse_args()
    engine = get_engine(args.device)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip() or None
    rows = agreement(engine)
    images = [r for r in rows if "rel_max" in r]
    record = {
        "device": engine.info.label, "commit": commit,
        "cases": len(rows),
        "within_1e-6": sum(r["rel_max"] <= 1e-6 and r["nonfinite"] == 0 for r in images),
        "refusals_same": sum(r.get("same_refusal", False) for r in rows),
        "worst": sorted(images, key=lambda r: -r["rel_max"])[:10],
        "rows": rows,
        "timings": None if args.quick else timings(args.device),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=1) + "\n")
    print(f"{record['device']}: {record['within_1e-6']}/{len(images)} images within 1e-6 of "
          f"the peak; worst {record['worst'][0]['case']} {record['worst'][0]['rel_max']:.3g}")
    for when, runs in (record["timings"] or {}).items():
        for t in runs:
            print(when, t)


if __name__ == "__main__":
    main()
