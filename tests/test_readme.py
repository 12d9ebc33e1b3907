"""The README's Python example runs as written (on a smaller copy of its scene: ``load`` is
wrapped to add overrides, so the suite stays quick), and its minimal scene file renders."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"
SMALL = ["camera.resolution=[32,24]", "camera.spp=1", "render.lsg.light_rays=4000",
         "render.raymap.photons=4000"]


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_python_example_runs(tmp_path, monkeypatch, capsys):
    import clscatter
    code = next(b for b in _blocks("python") if "clscatter.load" in b)
    real_load = clscatter.load
    monkeypatch.setattr(clscatter, "load", lambda spec, overrides=(), **kw:
                        real_load(spec, [*SMALL, *overrides], **kw))
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    result = ns["result"]
    assert np.isfinite(result.image).all() and result.image.shape == (24, 32, 3)
    assert {"bvh", "view_paths"} <= set(result.stats["reused"])      # the warm re-render
    assert (tmp_path / "sphere.exr").is_file() and (tmp_path / "sphere.png").is_file()
    assert capsys.readouterr().out.strip()                            # it prints what it says


def test_readme_minimal_scene_renders(tmp_path):
    import clscatter
    toml = next(b for b in _blocks("toml") if "[camera]" in b)
    path = tmp_path / "minimal.toml"
    path.write_text(toml)
    result = clscatter.render(clscatter.load(str(path), ["camera.resolution=[32,24]",
                                                         "camera.spp=1"]))
    assert np.isfinite(result.image).all() and result.image.mean() > 0
