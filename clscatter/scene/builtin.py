"""Built-in scenes, generated in code as dicts in exactly the TOML schema of docs/scene_format.md.

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

import json
import math
from typing import Any, Callable

DEFAULT_BUILTIN = "shafts"

# _camera, _floor and _RENDER are shared with builtin_caustics.py: keep their signatures
_CAMERA = {"resolution": [320, 240], "spp": 4}
_RENDER = {"method": "auto", "max_depth": 16, "seed": 0}


def _camera(origin: list[float], target: list[float], fov: float) -> dict:
    return {"origin": origin, "target": target, "up": [0.0, 1.0, 0.0], "fov": fov,
            "fov_axis": "x", **_CAMERA}


def _floor(half: float = 4.0, material: str = "floor") -> dict:
    return {"shape": "quad", "origin": [-half, 0.0, -half], "edge_u": [2 * half, 0.0, 0.0],
            "edge_v": [0.0, 0.0, 2 * half], "material": material}


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


BUILTIN: dict[str, Callable[[], dict]] = {
    "shafts": shafts,
    "occluder": occluder,
    "spotlight": spotlight,
    "glass": glass,
    "airlight": airlight,
}


def _register_technique_scenes() -> None:
    """Add the scenes written for each technique (their modules import helpers from here)."""
    from .builtin_caustics import CAUSTIC_SCENES
    from .builtin_epipolar import EPIPOLAR_SCENES
    from .builtin_volumes import VOLUME_SCENES
    BUILTIN.update(CAUSTIC_SCENES)
    BUILTIN.update(EPIPOLAR_SCENES)
    BUILTIN.update(VOLUME_SCENES)


_register_technique_scenes()


# ---- A tiny TOML writer for the subset the scenes use -----------------------------------

# dicts under these keys are written inline ({ ... }) rather than as [table] headers
_INLINE_KEYS = frozenset({"bounds", "transform", "material"})


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)   # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) else json.dumps(k)


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _emit(table: dict, path: list[str], out: list[str]) -> None:
    """Write ``table``'s plain keys, then its sub-tables and arrays of tables in order."""
    def is_header(k: str, v: Any) -> bool:
        return (isinstance(v, dict) and k not in _INLINE_KEYS) or _is_table_array(v)

    for k, v in table.items():
        if not is_header(k, v):
            out.append(f"{_key(k)} = {_value(v)}")
    for k, v in table.items():
        if not is_header(k, v):
            continue
        name = ".".join(_key(p) for p in [*path, k])
        if isinstance(v, dict):
            # a table holding only sub-tables ([materials]) needs no header of its own
            if not v or any(not is_header(ik, iv) for ik, iv in v.items()):
                out.extend(["", f"[{name}]"])
            _emit(v, [*path, k], out)
            continue
        for item in v:
            out.extend(["", f"[[{name}]]"])
            # everything inside an array element is written inline: simple and unambiguous
            for ik, iv in item.items():
                out.append(f"{_key(ik)} = {_value(iv)}")


def to_toml(data: dict) -> str:
    """Serialise a scene dict (strings, numbers, booleans, arrays, tables) as TOML text."""
    out: list[str] = []
    _emit(data, [], out)
    return "\n".join(out).lstrip("\n") + "\n"


def builtin_toml(name: str) -> str:
    """The built-in scene ``name`` as the text of a TOML scene file."""
    from ..errors import SceneError

    if name not in BUILTIN:
        raise SceneError(f"builtin:{name}", f"unknown built-in scene (one of {', '.join(BUILTIN)})")
    return f"# clscatter built-in scene '{name}'\n" + to_toml(BUILTIN[name]())
