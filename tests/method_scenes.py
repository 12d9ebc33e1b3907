"""One small, quick scene per method, for tests that run every method (the stage
accounting through the command line, the buffer pool's reuse test)."""
from __future__ import annotations

SCENES = {"raymarch": "builtin:occluder", "epipolar": "builtin:shafts",
          "lsg": "builtin:caustic_sphere", "vpm": "builtin:caustic_sphere"}
SMALL = ["camera.resolution=[48,36]", "camera.spp=1"]
QUICK = {"lsg": ["render.lsg.light_rays=20000"], "vpm": ["render.vpm.photons=100000"]}


def scene_for(method: str) -> str:
    """The built-in scene a test renders ``method`` on."""
    return SCENES.get(method, "builtin:caustic_sphere")


def overrides_for(method: str) -> list[str]:
    """``--set`` overrides that make the scene small and the method quick."""
    return SMALL + QUICK.get(method, [])
