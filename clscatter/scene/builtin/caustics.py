"""Built-in caustic scenes: glass and mirror objects in a thin medium, in the spirit of the
statuettes of the LSG paper (Sun et al. 2010): volumetric caustics seen directly and
through the refractors, light-source glows, a reflected caustic.

Dicts in exactly the TOML schema of docs/scene_format.md, like ``builtin.py``; every scene has
a diffuse floor, a medium box around everything (so lighting and viewing rays end at its
walls) and renders at 320 x 240, 4 spp. The meshes are small committed OBJ files in
``meshes/`` (written by ``tools/make_caustic_meshes.py`` from ``procedural.py``),
referenced by absolute path because built-in scenes are resolved against the current
directory.

==================  ===================================================================
``caustic_sphere``  glass ball under a point light: the focused cone of light below it,
                    the light's glow, the ball's shadow cut by its own caustic
``caustic_gem``     faceted gem (ior 2.0) under a spot light: beams from the facets
``caustic_torus``   tilted glass torus under a spot light: ring and axial caustics
``caustic_mirror``  concave mirror dish reflecting a spot light: the reflected beam
                    converges to a focus in the medium and spreads to the floor
``caustic_blob``    amber marching-cubes metaball blob under a point light
==================  ===================================================================
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from .parts import RENDER as _RENDER
from .parts import camera as _camera
from .parts import floor as _floor

MESH_DIR = Path(__file__).resolve().parents[1] / "meshes"

_FLOOR = {"type": "diffuse", "albedo": 0.55}
_BOX = {"min": [-2.5, 0.0, -2.5], "max": [2.5, 3.6, 2.5]}


def _mesh(name: str, material: str, transform: dict, smooth: bool = True) -> dict:
    return {"shape": "mesh", "file": str(MESH_DIR / f"{name}.obj"), "smooth": smooth,
            "material": material, "transform": transform}


def _scene(camera: dict, lights: list, materials: dict, objects: list,
           sigma_s: float = 0.12, sigma_a: float = 0.02, g: float = 0.1) -> dict:
    return {
        "camera": camera,
        "medium": {"sigma_s": sigma_s, "sigma_a": sigma_a, "g": g, "bounds": dict(_BOX)},
        "lights": lights,
        "materials": {"floor": dict(_FLOOR), **materials},
        "objects": [_floor(2.5), *objects],
        "render": dict(_RENDER),
    }


def caustic_sphere() -> dict:
    """Glass ball under a point light: focused cone of light below it, the light's glow."""
    return _scene(
        _camera([0.0, 1.6, 6.0], [0.0, 1.35, 0.0], 50.0),
        [{"type": "point", "position": [0.25, 3.25, -0.15], "intensity": 20.0}],
        {"glass": {"type": "dielectric", "ior": 1.5, "interior_sigma_a": [0.0, 0.02, 0.05]}},
        [{"shape": "sphere", "center": [0.0, 1.3, 0.0], "radius": 0.55, "material": "glass"}])


def caustic_gem() -> dict:
    """Faceted gem (ior 2.0) under a spot light: beams from the facets."""
    return _scene(
        _camera([0.0, 1.7, 6.0], [0.0, 1.3, 0.0], 50.0),
        [{"type": "spot", "position": [0.2, 3.4, 0.1], "target": [0.0, 1.2, 0.0],
          "intensity": 40.0, "cutoff_angle": 18.0}],
        {"diamond": {"type": "dielectric", "ior": 2.0, "interior_sigma_a": [0.02, 0.02, 0.0]}},
        [_mesh("gem", "diamond", {"translate": [0.0, 1.25, 0.0], "rotate": [1.0, 0.0, 0.3, 14.0],
                                  "scale": 0.6}, smooth=False)])


def caustic_torus() -> dict:
    """Tilted glass torus under a spot light: ring and axial caustics."""
    return _scene(
        _camera([0.0, 1.8, 6.0], [0.0, 1.2, 0.0], 50.0),
        [{"type": "spot", "position": [-0.3, 3.4, 0.2], "target": [0.0, 1.3, 0.0],
          "intensity": 40.0, "cutoff_angle": 24.0}],
        {"glass": {"type": "dielectric", "ior": 1.5, "interior_sigma_a": [0.05, 0.0, 0.05]}},
        [_mesh("torus", "glass", {"translate": [0.0, 1.4, 0.0], "rotate": [1.0, 0.0, 0.0, 25.0],
                                  "scale": 0.7})])


def caustic_mirror() -> dict:
    """Concave mirror dish reflecting a spot light to a focus in the medium."""
    return _scene(
        _camera([0.0, 1.6, 6.0], [0.0, 1.3, 0.0], 52.0),
        [{"type": "spot", "position": [-1.6, 2.7, 0.6], "target": [1.8, 1.4, 0.0],
          "intensity": 40.0, "cutoff_angle": 14.0}],
        {"chrome": {"type": "mirror", "reflectance": 0.9}},
        [_mesh("dish", "chrome", {"translate": [1.9, 1.4, 0.0], "rotate": [0.0, 1.0, 0.0, -90.0],
                                  "scale": 0.9})])


def caustic_blob() -> dict:
    """Amber marching-cubes metaball blob under a point light."""
    return _scene(
        _camera([0.0, 1.6, 6.0], [0.0, 1.3, 0.0], 50.0),
        [{"type": "point", "position": [0.5, 3.2, 0.3], "intensity": 20.0}],
        {"amber": {"type": "dielectric", "ior": 1.55, "interior_sigma_a": [0.0, 0.25, 0.6]}},
        [_mesh("blob", "amber", {"translate": [0.0, 1.3, 0.0], "rotate": [0.0, 1.0, 0.0, 20.0]})])


CAUSTIC_SCENES: dict[str, Callable[[], dict]] = {
    "caustic_sphere": caustic_sphere,
    "caustic_gem": caustic_gem,
    "caustic_torus": caustic_torus,
    "caustic_mirror": caustic_mirror,
    "caustic_blob": caustic_blob,
}
