"""Built-in scenes for the epipolar method: light shafts of rising shadow complexity.

Dicts in the TOML schema of docs/scene_format.md (like ``builtin.py``), each with a bounded
medium; the lead registers :data:`EPIPOLAR_SCENES` in ``BUILTIN``. All render at
320 x 240, 4 spp; radiance roughly 0.05 .. 1 at exposure 0.

=================  =====================================================================
``epi_window``     a room with one window in its left wall: one sun shaft across the
                   room onto the floor (the simplest shadow)
``epi_grille``     sunlight through a ceiling grate of crossed bars: a lattice of shafts
``epi_forest``     low sun through a forest of 90 thin trunks: many thin shadow sheets
``epi_spot``       the grate lit by a spot light above it instead of the sun
``epi_sun``        the forest seen against the sun: the epipole on screen, rays
                   converging on it
``epi_fog``        a thick fog box (optical depth 4.4) seen from outside with the sun
                   behind the camera, four black pillars
``epi_wide_spot``  the grate under a 90-degree spot light (a hemisphere of light)
=================  =====================================================================
"""
from __future__ import annotations

import math
from collections.abc import Callable

_RENDER = {"method": "auto", "max_depth": 16, "seed": 0}


def _camera(origin, target, fov: float = 55.0) -> dict:
    return {"origin": origin, "target": target, "up": [0.0, 1.0, 0.0], "fov": fov,
            "fov_axis": "x", "resolution": [320, 240], "spp": 4}


def _box(lo, hi, material: str) -> dict:
    return {"shape": "box", "min": [round(x, 4) for x in lo], "max": [round(x, 4) for x in hi],
            "material": material}


def _floor(half: float, material: str = "floor") -> dict:
    return {"shape": "quad", "origin": [-half, 0.0, -half], "edge_u": [2 * half, 0.0, 0.0],
            "edge_v": [0.0, 0.0, 2 * half], "material": material}


def _materials() -> dict:
    return {"floor": {"type": "diffuse", "albedo": 0.5},
            "wall": {"type": "diffuse", "albedo": [0.6, 0.55, 0.5]},
            "dark": {"type": "diffuse", "albedo": 0.15},
            "bark": {"type": "diffuse", "albedo": [0.25, 0.18, 0.12]}}


def _lcg(seed: int):
    """A tiny deterministic generator (no NumPy state, identical everywhere)."""
    state = seed & 0xFFFFFFFF

    def nxt() -> float:
        nonlocal state
        state = (1664525 * state + 1013904223) & 0xFFFFFFFF
        return state / 2 ** 32
    return nxt


def epi_window() -> dict:
    """A room 8 x 4 x 8, open towards the camera; the sun enters through one window."""
    t = 0.2
    wl, wh, zl, zh = 1.2, 3.2, -2.8, -0.4        # the window in the wall x = -4
    objects = [
        _floor(4.2),
        _box([-4.2, 4.0, -4.2], [4.2, 4.2, 4.2], "wall"),               # ceiling
        _box([-4.2, 0.0, -4.2], [4.2, 4.0, -4.0], "wall"),              # back wall
        # left wall around the window
        _box([-4.0 - t, 0.0, -4.2], [-4.0, wl, 4.2], "wall"),
        _box([-4.0 - t, wh, -4.2], [-4.0, 4.0, 4.2], "wall"),
        _box([-4.0 - t, wl, -4.2], [-4.0, wh, zl], "wall"),
        _box([-4.0 - t, wl, zh], [-4.0, wh, 4.2], "wall"),
    ]
    return {
        "camera": _camera([2.0, 1.8, 7.5], [-0.8, 1.2, -1.0], 60.0),
        "medium": {"sigma_s": 0.15, "sigma_a": 0.02, "g": 0.3,
                   "bounds": {"min": [-4.0, 0.0, -4.0], "max": [4.0, 4.0, 4.0]}},
        "lights": [{"type": "directional", "direction": [0.75, -0.45, 0.35], "irradiance": 12.0}],
        "materials": _materials(),
        "objects": objects,
        "render": dict(_RENDER),
    }


def _grate(n: int = 7, half: float = 3.6, bar: float = 0.22, y: float = 3.6) -> list[dict]:
    """A square grate of n crossed bars each way, spanning [-half, half]^2 at height y."""
    out = []
    pitch = 2 * half / n
    for i in range(n + 1):
        c = -half + i * pitch
        out.append(_box([c - bar / 2, y, -half - bar / 2], [c + bar / 2, y + 0.12, half + bar / 2], "dark"))
        out.append(_box([-half - bar / 2, y + 0.12, c - bar / 2], [half + bar / 2, y + 0.24, c + bar / 2], "dark"))
    # a solid rim around the grate so no light slips past it into the medium
    r, R = half + bar / 2, half + 4.0
    out += [_box([-R, y, -R], [-r, y + 0.24, R], "dark"), _box([r, y, -R], [R, y + 0.24, R], "dark"),
            _box([-r, y, -R], [r, y + 0.24, -r], "dark"), _box([-r, y, r], [r, y + 0.24, R], "dark")]
    return out


def epi_grille() -> dict:
    """Sun through a ceiling grate: a lattice of slanted shafts and a chequered floor."""
    return {
        "camera": _camera([0.0, 1.4, 8.5], [0.0, 1.5, 0.0], 55.0),
        "medium": {"sigma_s": 0.15, "sigma_a": 0.02, "g": 0.25,
                   "bounds": {"min": [-4.0, 0.0, -4.0], "max": [4.0, 3.6, 4.0]}},
        "lights": [{"type": "directional", "direction": [0.35, -1.0, 0.15], "irradiance": 4.0}],
        "materials": _materials(),
        "objects": [_floor(6.0), *_grate()],
        "render": dict(_RENDER),
    }


def _trunks(n: int = 90, half: float = 5.5, seed: int = 7) -> list[dict]:
    rnd = _lcg(seed)
    out = []
    for _ in range(n):
        x, z = (2 * rnd() - 1) * half, (2 * rnd() - 1) * half
        w = 0.06 + 0.1 * rnd()
        out.append(_box([x - w, 0.0, z - w], [x + w, 5.0 + 2 * rnd(), z + w], "bark"))
    return out


def epi_forest() -> dict:
    """Low sun, slanting towards the camera, through 90 thin trunks."""
    return {
        "camera": _camera([0.5, 1.7, 9.5], [-0.5, 1.6, 0.0], 55.0),
        "medium": {"sigma_s": 0.12, "sigma_a": 0.015, "g": 0.3,
                   "bounds": {"min": [-6.0, 0.0, -6.0], "max": [6.0, 4.6, 6.0]}},
        "lights": [{"type": "directional", "direction": [0.8, -0.35, 0.6], "irradiance": 5.0}],
        "materials": _materials(),
        "objects": [_floor(8.0), *_trunks()],
        "render": dict(_RENDER),
    }


def epi_spot() -> dict:
    """The grate of ``epi_grille`` lit by a spot light above it: diverging shafts."""
    scene = epi_grille()
    scene["lights"] = [{"type": "spot", "position": [-0.6, 6.5, 0.4], "target": [0.4, 0.0, -0.3],
                        "intensity": 120.0, "cutoff_angle": 32.0}]
    return scene


def epi_sun() -> dict:
    """The forest of ``epi_forest`` from inside, looking towards the low sun: the epipole
    is on screen (left of and above the image centre) and the shafts converge on it."""
    scene = epi_forest()
    d = scene["lights"][0]["direction"]
    eye = [7.5, 1.5, 6.5]
    # aim 10 degrees right of and 6 degrees below the sun
    yaw = math.atan2(-d[0], -d[2]) - math.radians(10.0)
    pitch = math.asin(-d[1] / math.sqrt(sum(x * x for x in d))) - math.radians(6.0)
    look = [math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)]
    scene["camera"] = _camera(eye, [eye[k] + look[k] for k in range(3)], 65.0)
    return scene


def _unit3(v) -> list[float]:
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


_FOG_BOX = ([-2.0, 0.0, -2.0], [2.0, 3.0, 2.0])
_FOG_PILLARS = [(-1.0, -0.5), (0.4, 0.6), (1.1, -1.2), (-0.3, -1.5)]


def epi_sweep(depth: float = 4.4, light: str = "behind", camera: str = "outside",
              kind: str = "directional", resolution=(320, 240), cutoff: float = 40.0) -> dict:
    """A 4 x 3 x 4 box of fog (albedo 0.9, isotropic) with four black pillars, thin to
    thick, lit and seen from several sides: ``depth`` the optical depth across the box
    (kappa x 4), ``camera`` ``"outside"`` (5 units in front of the box, looking in) or
    ``"inside"``, ``light`` relative to the view direction ``f``: ``"behind"`` (light
    travelling roughly along ``f``: the anti-solar point on screen, off centre), ``"axis"``
    (exactly along ``f``: the anti-solar point at the image centre), ``"beside"`` (across
    the view) or ``"front"`` (towards the camera: the light/epipole on screen); ``kind``
    ``"directional"`` or ``"spot"`` (placed on the same side, aimed at the box centre,
    cone half-angle ``cutoff``)."""
    kappa = depth / 4.0
    if camera == "outside":
        eye, target = [0.3, 1.4, 7.0], [0.0, 1.2, 0.0]
    else:
        eye, target = [0.9, 1.6, 1.6], [-0.6, 1.1, -1.0]
    f = _unit3([target[k] - eye[k] for k in range(3)])
    side = _unit3([-f[2], 0.0, f[0]])
    d = {"behind": _unit3([f[0] + 0.25 * side[0], f[1] - 0.35, f[2] + 0.25 * side[2]]),
         "axis": f,
         "beside": _unit3([side[0] + 0.1 * f[0], -0.5, side[2] + 0.1 * f[2]]),
         "front": _unit3([-f[0] + 0.3 * side[0], -0.35, -f[2] + 0.3 * side[2]])}[light]
    centre = [0.0, 1.5, 0.0]
    if kind == "directional":
        lights = [{"type": "directional", "direction": d, "irradiance": 1.0}]
    else:
        if light == "axis":
            pos = [eye[k] - 1.5 * f[k] for k in range(3)]
            aim = [pos[k] + f[k] for k in range(3)]
        else:
            pos = [centre[k] - 6.0 * d[k] for k in range(3)]
            aim = centre
        lights = [{"type": "spot", "position": pos, "target": aim, "intensity": 20.0,
                   "cutoff_angle": cutoff}]
    return {
        "camera": {"origin": eye, "target": target, "up": [0.0, 1.0, 0.0], "fov": 55.0,
                   "fov_axis": "x", "resolution": list(resolution), "spp": 1},
        "medium": {"sigma_s": 0.9 * kappa, "sigma_a": 0.1 * kappa, "g": 0.0,
                   "bounds": {"min": _FOG_BOX[0], "max": _FOG_BOX[1]}},
        "lights": lights,
        "materials": {"black": {"type": "black"}},
        "objects": [_box([x - 0.15, 0.0, z - 0.15], [x + 0.15, 2.5, z + 0.15], "black")
                    for x, z in _FOG_PILLARS],
        "render": dict(_RENDER),
    }


def epi_fog() -> dict:
    """A box of thick fog (optical depth 4.4 across it, albedo 0.9) with four black
    pillars, seen from outside with the sun behind the camera."""
    scene = epi_sweep(4.4, "behind", "outside", "directional")
    scene["camera"]["spp"] = 4
    return scene


def epi_wide_spot(cutoff: float = 90.0, resolution=(320, 240)) -> dict:
    """The grate of ``epi_grille`` under a spot light just above it whose cone is a
    hemisphere (half-angle ``cutoff``, 90 degrees): shafts fanning out to the medium's
    walls."""
    scene = epi_grille()
    scene["lights"] = [{"type": "spot", "position": [0.2, 4.4, -0.3], "target": [0.2, 0.0, -0.3],
                        "intensity": 30.0, "cutoff_angle": float(cutoff)}]
    scene["camera"]["resolution"] = list(resolution)
    return scene


EPIPOLAR_SCENES: dict[str, Callable[[], dict]] = {
    "epi_fog": epi_fog,
    "epi_wide_spot": epi_wide_spot,
    "epi_window": epi_window,
    "epi_grille": epi_grille,
    "epi_forest": epi_forest,
    "epi_spot": epi_spot,
    "epi_sun": epi_sun,
}


