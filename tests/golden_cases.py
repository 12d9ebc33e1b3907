"""The golden-image cases: every method (and ``auto``) on every built-in scene and the
scene-file tests' scene, tiny and quick, with fixed seeds. ``tests/golden/golden.npz``
holds the images (or the one-line refusal) the engine gave when they were recorded;
``tests/test_golden.py`` renders them again. Re-record with
``.venv/bin/python tests/golden_cases.py`` only for a documented change."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "golden" / "golden.npz"
METHODS = ["auto", "raymarch", "epipolar", "lsg", "vpm", "raymap", "photonmap", "voxel"]
SMALL = ["camera.resolution=[24,18]", "camera.spp=1", "render.seed=7"]
QUICK = {"lsg": ["render.lsg.light_rays=4000"],
         "vpm": ["render.vpm.photons=20000"],
         "raymap": ["render.raymap.photons=4000", "render.lsg.light_rays=4000"],
         "photonmap": ["render.photonmap.photons=4000", "render.lsg.light_rays=4000"],
         "voxel": ["render.voxel.resolution=16", "render.voxel.photons=1024",
                   "render.voxel.outer_resolution=16"],
         "auto": ["render.time_budget=0", "render.lsg.light_rays=4000", "render.raymap.photons=4000",
                  "render.voxel.resolution=16", "render.voxel.photons=1024",
                  "render.voxel.outer_resolution=16"]}


def sources() -> list[str]:
    from clscatter.scene.builtin import BUILTIN
    return [f"builtin:{n}" for n in sorted(BUILTIN)] + [str(HERE / "data" / "full_scene.toml")]


def key(source: str, method: str) -> str:
    return f"{Path(source).name}|{method}"


def render_case(source: str, method: str, engine=None) -> np.ndarray | str:
    """The image of one case, or the one-line error it gives."""
    from clscatter.errors import ClscatterError
    from clscatter.pipeline.session import RenderSession
    try:
        with RenderSession.from_source(source, SMALL + QUICK.get(method, []), method=method,
                                       engine=engine) as s:
            return s.render(show_progress=False).image
    except ClscatterError as e:
        return f"error: {e}"


if __name__ == "__main__":
    from clscatter.device import get_engine
    eng = get_engine(None)
    out = {}
    for src in sources():
        for m in METHODS:
            r = render_case(src, m, eng)
            out[key(src, m)] = np.asarray(r) if not isinstance(r, str) else np.array(r)
            print(key(src, m), "error" if isinstance(r, str) else f"{float(np.mean(r)):.4g}",
                  file=sys.stderr)
    GOLDEN.parent.mkdir(exist_ok=True)
    np.savez_compressed(GOLDEN, **out)
