"""Every method under a second OpenCL implementation: Oclgrind, a strict simulator that
also reports invalid memory accesses and data races. Each method renders a tiny built-in
scene (12 x 9, 1 spp; epipolar with a 64-texel shadow map and 32 light rays a slice, so
that its sweep still runs; the surface estimators in two passes, so that the second's
splat runs) with the simulator as its only device; any report, or a failed
or non-finite render, fails. The set-up installs Oclgrind (Debian's ``oclgrind``); without it
these tests are skipped, except where the set-up installs it (under CI, or as root with
apt-get): there its absence fails them."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from method_scenes import scene_for
from setup_installs import setup_installs_here

TINY = ["camera.resolution=[12,9]", "camera.spp=1", "render.lsg.light_rays=2000",
        "render.vpm.photons=1500", "render.raymap.photons=250", "render.photonmap.photons=250",
        "render.raymap.passes=2", "render.photonmap.passes=2",
        "render.voxel.resolution=8", "render.voxel.photons=256",
        "render.voxel.outer_resolution=8", "render.epipolar.shadow_map=64",
        "render.epipolar.light_rays=32"]
METHODS = ["raymarch", "epipolar", "lsg", "vpm", "raymap", "photonmap", "voxel"]
# every method at its defaults (lsg's queries: "screen"), and lsg once more with each of
# its other sides of queries
RUNS = [(m, []) for m in METHODS] + [("lsg", [f'render.lsg.queries="{q}"'])
                                     for q in ("lights", "views")]
# what Oclgrind prints when it finds a defect
REPORTS = ("Invalid read", "Invalid write", "data race", "Uninitialized", "error:",
           "Undefined external function", "Work-group divergence", "out-of-bounds")

pytestmark = pytest.mark.slow
NO_OCLGRIND = "oclgrind is not installed (scripts/setup.sh installs it: apt-get install oclgrind)"


@pytest.fixture(scope="module", autouse=True)
def oclgrind():
    """Oclgrind must be there where the set-up installs it; elsewhere its absence skips."""
    if shutil.which("oclgrind") is None:
        required = setup_installs_here()
        if required:
            pytest.fail(f"{NO_OCLGRIND}; it is required here ({required})", pytrace=False)
        pytest.skip(NO_OCLGRIND)


@pytest.mark.parametrize("method, extra", RUNS,
                         ids=[m + ("-" + e[0].split('"')[1] if e else "") for m, e in RUNS])
def test_method_runs_clean_under_oclgrind(method, extra, tmp_path):
    out = tmp_path / "img.npy"
    args = ["oclgrind", "--data-races", sys.executable, "-m", "clscatter", "render",
            scene_for(method), "--method", method, "--no-progress", "-o", str(out),
            "--stats", str(tmp_path / "stats.json")]
    for kv in TINY + extra:
        args += ["--set", kv]
    env = {**os.environ, "CLSCATTER_CACHE_DIR": str(tmp_path / "cache")}
    env.pop("CLSCATTER_DEVICE", None)
    r = subprocess.run(args, capture_output=True, text=True, timeout=600, env=env)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-3000:]
    assert "Oclgrind" in subprocess.run(
        ["oclgrind", sys.executable, "-m", "clscatter", "devices"], capture_output=True,
        text=True, timeout=120, env=env).stdout            # the simulator was the device
    found = [line for line in log.splitlines() if any(k in line for k in REPORTS)]
    assert not found, "\n".join(found[:20])
    img = np.load(out)
    assert img.shape == (9, 12, 3) and np.isfinite(img).all()
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["method"].split("+")[0] == method      # (raymap, photonmap: + the medium)
    if method in ("raymap", "photonmap"):         # the K-nearest pass and a splatted one
        assert stats[f"{method}_passes"] == 2 and stats[f"{method}_splat_hits_tested"] > 0
    if method == "epipolar":         # its own kernels ran: no light fell back to ray marching
        assert stats["epipolar_fallback"] == [] and stats["svd_terms"] >= 1
