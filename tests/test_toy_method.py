"""A method from outside the package (tests/toy_method: one .py, one .cl, no other file
touched) is registered, chosen by ``auto`` and by ``--method``, and renders what its
kernel computes: the sum over a pixel's view segments of level x length x weight."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
TOY = HERE / "toy_method"
SMALL = ["camera.resolution=[24,18]", "camera.spp=1"]


@pytest.fixture(scope="module")
def toy():
    import clscatter.methods as methods
    sys.path.insert(0, str(TOY))
    try:
        import toyfog  # registers "toyfog"
        yield toyfog
    finally:
        sys.path.remove(str(TOY))
        methods._REGISTRY.pop("toyfog", None)


def _expected(ps, paths, level: float) -> np.ndarray:
    """NumPy reference of the kernel: level x |b - a| x weight, summed per pixel."""
    from clscatter.transport.view_paths import accumulate_segments
    s = paths.segments
    length = np.linalg.norm(s["b"][:, :3].astype(np.float64) - s["a"][:, :3], axis=1)
    vals = level * length[:, None] * s["weight"][:, :3]
    cam = ps.scene.camera
    return accumulate_segments(vals, s["pixel"], cam.width, cam.height)


def test_auto_and_explicit_run_the_toy(toy, engine):
    from clscatter.pipeline.session import RenderSession
    for method in ("auto", "toyfog"):
        with RenderSession.from_source("builtin:occluder", SMALL + ["render.toyfog.level=0.25"],
                                       method=method, engine=engine) as s:
            res = s.render(show_progress=False)
            assert res.stats["method"] == "toyfog"
            ref = _expected(s._ps, s._paths, 0.25)
            assert float(ref.mean()) > 0
            np.testing.assert_allclose(res.medium, ref, rtol=1e-4, atol=1e-7)


def test_the_command_line_runs_the_toy(tmp_path, toy):
    env = {**os.environ, "CLSCATTER_METHODS": "toyfog",
           "PYTHONPATH": os.pathsep.join([str(TOY), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "toy.npy"
    r = subprocess.run([sys.executable, "-m", "clscatter", "render", "builtin:occluder",
                        "--method", "toyfog", *(a for kv in SMALL for a in ("--set", kv)),
                        "-o", str(out), "--no-progress"],
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    img = np.load(out)
    assert img.shape == (18, 24, 3) and np.isfinite(img).all() and img.mean() > 0


def test_a_bad_toy_parameter_names_its_key(toy):
    from clscatter.errors import SceneError
    from clscatter.methods import configure
    with pytest.raises(SceneError) as e:
        configure("toyfog", {"level": -1.0})
    assert e.value.key == "render.toyfog.level"
