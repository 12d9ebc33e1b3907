"""The basic built-in scenes (dicts in the TOML schema of docs/scene_format.md).

``load_scene("builtin:NAME")`` validates them through the same ``scene_from_dict`` as a
file; ``builtin_toml(NAME)`` writes one out as a TOML file to start from. All render at
320 x 240, 4 spp, and are lit so that radiance is roughly 0.05 .. 1 at exposure 0.

==============  ========================================================================
``shafts``      the demo: a directional light slanting down through a grille of bars
                into a bounded medium box; light shafts and striped shadows on the floor
``occluder``    point light in an unbounded medium, a diffuse sphere casting a
                volumetric shadow, floor quad
``spotlight``   spot light in a bounded medium with a box occluder, floor quad
``glass``       glass sphere and a mirror panel on a diffuse floor, point light, thin
                unbounded medium (specular chains, caustics)
``airlight``    point light in an unbounded medium, nothing else (the analytic case)
==============  ========================================================================
"""
from __future__ import annotations

from .parts import RENDER as _RENDER
from .parts import camera as _camera
from .parts import floor as _floor


def shafts() -> dict:
    """The demo: sun shafts through a grille of bars into a medium box, striped floor.

    Bars run along z and the light slants in x (and a little towards the camera, for
    some forward scattering), so the shafts are sheets of light seen edge-on."""
    bars = []
    # the grille overhangs the medium box so that, at this slant, every light path into
    # the medium passes through it (no unshadowed light through the box's sides)
    width, gap, n = 0.42, 0.33, 14
    x0 = -((n - 1) * (width + gap) + width) / 2
    for i in range(n):
        x = x0 + i * (width + gap)
        bars.append({"shape": "box", "min": [round(x, 4), 2.5, -5.0],
                     "max": [round(x + width, 4), 2.6, 5.0], "material": "grille"})
    return {
        "camera": _camera([0.0, 1.3, 7.5], [0.0, 1.05, 0.0], 50.0),
        "medium": {"sigma_s": 0.25, "sigma_a": 0.02, "g": 0.2,
                   "bounds": {"min": [-3.5, 0.0, -3.5], "max": [3.5, 2.45, 3.5]}},
        "lights": [{"type": "directional", "direction": [0.45, -1.0, 0.3],
                    "irradiance": 3.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.6},
                      "grille": {"type": "black"}},
        "objects": [_floor(5.0), *bars],
        "render": dict(_RENDER),
    }


def occluder() -> dict:
    """Point light in an unbounded medium; a diffuse sphere casts a volumetric shadow."""
    return {
        "camera": _camera([0.0, 1.5, 6.0], [0.0, 1.1, 0.0], 55.0),
        "medium": {"sigma_s": 0.1, "sigma_a": 0.02, "g": 0.0},
        "lights": [{"type": "point", "position": [-0.6, 2.6, -0.5], "intensity": 10.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                      "ball": {"type": "diffuse", "albedo": [0.7, 0.45, 0.3]}},
        "objects": [
            _floor(4.0),
            {"shape": "sphere", "center": [0.0, 1.7, 0.0], "radius": 0.45, "material": "ball"},
        ],
        "render": dict(_RENDER),
    }


def spotlight() -> dict:
    """Spot light in a bounded medium; a rotated box cuts a shadow out of the cone."""
    return {
        "camera": _camera([0.0, 1.6, 7.0], [0.0, 1.2, 0.0], 50.0),
        "medium": {"sigma_s": 0.2, "sigma_a": 0.02, "g": 0.3,
                   "bounds": {"min": [-3.5, 0.0, -3.5], "max": [3.5, 4.0, 3.5]}},
        "lights": [{"type": "spot", "position": [-0.8, 3.5, -0.3], "target": [0.3, 0.0, 0.0],
                    "intensity": 25.0, "cutoff_angle": 25.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.6},
                      "block": {"type": "diffuse", "albedo": [0.3, 0.5, 0.7]}},
        "objects": [
            _floor(4.0),
            {"shape": "box", "min": [-0.45, -0.35, -0.35], "max": [0.45, 0.35, 0.35],
             "material": "block",
             "transform": {"translate": [-0.05, 1.8, -0.1], "rotate": [0.0, 1.0, 0.0, 30.0]}},
        ],
        "render": dict(_RENDER),
    }


def glass() -> dict:
    """Glass sphere and a mirror panel on a floor, point light, thin unbounded medium."""
    return {
        "camera": _camera([0.0, 1.8, 6.5], [0.0, 0.8, 0.0], 50.0),
        "medium": {"sigma_s": 0.04, "sigma_a": 0.005, "g": 0.0},
        "lights": [{"type": "point", "position": [1.2, 4.0, 1.0], "intensity": 30.0}],
        "materials": {
            "floor": {"type": "diffuse", "albedo": 0.6},
            "glass": {"type": "dielectric", "ior": 1.5,
                      "interior_sigma_a": [0.0, 0.05, 0.1], "interior_sigma_s": 0.0},
            "chrome": {"type": "mirror", "reflectance": 0.9},
        },
        "objects": [
            _floor(4.0),
            {"shape": "sphere", "center": [0.0, 0.8, 0.0], "radius": 0.8, "material": "glass"},
            {"shape": "quad", "origin": [-2.5, 0.0, -2.0], "edge_u": [2.0, 0.0, -0.8],
             "edge_v": [0.0, 2.2, 0.0], "material": "chrome"},
        ],
        "render": dict(_RENDER),
    }


def airlight() -> dict:
    """Point light in an unbounded medium and nothing else: the analytic airlight case."""
    return {
        "camera": _camera([0.0, 1.0, 5.0], [0.0, 1.0, 0.0], 60.0),
        "medium": {"sigma_s": 0.1, "sigma_a": 0.05, "g": 0.0},
        "lights": [{"type": "point", "position": [0.0, 1.0, 0.0], "intensity": 10.0}],
        "render": dict(_RENDER),
    }


BASIC_SCENES = {
    "shafts": shafts,
    "occluder": occluder,
    "spotlight": spotlight,
    "glass": glass,
    "airlight": airlight,
}
