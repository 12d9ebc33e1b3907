"""Built-in scenes with graded-index ``[[volumes]]`` (the voxel pipeline, Sun et al. 2008).

Dicts in the TOML schema of docs/scene_format.md, like ``builtin/caustics.py``: a diffuse floor,
a medium box around everything, 320 x 240 at 4 spp.

==================  ===================================================================
``volume_sphere``   a refractive sphere volume (ior 1.3) in fog under a spot light: the
                    beam is focused inside the sphere and converges below it
``volume_lens``     a lens-shaped volume (flattened sphere, ior 1.5) under a directional
                    light: a focused sheet of light in the fog under it
``volume_glass``    the glass ball of ``caustic_sphere`` as a dielectric *object* with a
                    clear interior, for comparing ``voxel`` (which voxelises it) with
                    ``lsg`` (Snell refraction) in the same fog
==================  ===================================================================
"""
from __future__ import annotations

from typing import Callable

from .parts import RENDER as _RENDER
from .parts import camera as _camera
from .parts import floor as _floor

_BOX = {"min": [-2.0, 0.0, -2.0], "max": [2.0, 3.4, 2.0]}
_FOG = {"sigma_s": 0.15, "sigma_a": 0.02, "g": 0.2}


def _scene(camera: dict, lights: list, volumes: list, objects: list | None = None,
           materials: dict | None = None) -> dict:
    return {
        "camera": camera,
        "medium": {**_FOG, "bounds": dict(_BOX)},
        "lights": lights,
        "materials": {"floor": {"type": "diffuse", "albedo": 0.55}, **(materials or {})},
        "objects": [_floor(2.0), *(objects or [])],
        "volumes": volumes,
        "render": {**_RENDER, "method": "voxel"},
    }


def volume_sphere() -> dict:
    """Refractive sphere volume (ior 1.3) in fog under a spot light; fog carries on inside."""
    return _scene(
        _camera([0.0, 1.6, 5.5], [0.0, 1.3, 0.0], 50.0),
        [{"type": "spot", "position": [0.1, 3.3, 0.0], "target": [0.0, 1.5, 0.0],
          "intensity": 30.0, "cutoff_angle": 16.0}],
        [{"shape": "sphere", "center": [0.0, 1.6, 0.0], "radius": 0.5, "ior": 1.3,
          "sigma_s": _FOG["sigma_s"], "sigma_a": _FOG["sigma_a"]}])


def volume_lens() -> dict:
    """Flattened sphere (ior 1.5, slightly blue-absorbing) under a directional light."""
    return _scene(
        _camera([0.0, 1.5, 5.5], [0.0, 1.2, 0.0], 50.0),
        [{"type": "directional", "direction": [0.1, -1.0, 0.05], "irradiance": 2.0}],
        [{"shape": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "ior": 1.5,
          "sigma_s": 0.0, "sigma_a": [0.0, 0.05, 0.3],
          "transform": {"scale": [0.7, 0.25, 0.7], "translate": [0.0, 2.4, 0.0]}}])


def volume_glass() -> dict:
    """Clear glass ball (dielectric object, ior 1.5) under a point light, in fog."""
    return _scene(
        _camera([0.0, 1.6, 5.5], [0.0, 1.3, 0.0], 50.0),
        [{"type": "point", "position": [0.0, 3.2, 0.0], "intensity": 20.0}],
        [],
        [{"shape": "sphere", "center": [0.0, 1.6, 0.0], "radius": 0.5, "material": "glass"}],
        {"glass": {"type": "dielectric", "ior": 1.5}})


VOLUME_SCENES: dict[str, Callable[[], dict]] = {
    "volume_sphere": volume_sphere,
    "volume_lens": volume_lens,
    "volume_glass": volume_glass,
}
