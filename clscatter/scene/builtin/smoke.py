"""Built-in scenes with heterogeneous media: ``[[volumes]]`` with a density grid.

Dicts in the TOML schema of docs/scene_format.md, like the other families: 320 x 240 at
4 spp. The grid is the committed ``scene/data/smoke.npy``, written by
``tools/make_smoke.py`` (which also writes the same grid as ``smoke.vdb``, OpenVDB; the
scene reads the ``.npy`` so that it renders where ``pyopenvdb`` is not installed).

==================  ===================================================================
``smoke_plume``     a smoke plume rising from a floor under a spot light, no other
                    medium: light scattered in the smoke, and its soft shadow on the
                    floor (``raymarch``, which ``auto`` picks)
==================  ===================================================================
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from .parts import RENDER as _RENDER
from .parts import camera as _camera
from .parts import floor as _floor

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
#: the plume's box (tools/make_smoke.py: BOUNDS)
SMOKE_BOUNDS = {"min": [-0.6, 0.0, -0.6], "max": [0.6, 1.8, 0.6]}


def smoke_plume() -> dict:
    """A smoke plume rising from a floor under a spot light: its glow and its soft shadow
    on the floor."""
    return {
        "camera": _camera([0.0, 1.3, 4.2], [0.0, 0.7, 0.0], 45.0),
        "lights": [{"type": "spot", "position": [2.0, 2.5, -0.9], "target": [-0.3, 0.35, 0.3],
                    "intensity": 22.0, "cutoff_angle": 34.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.6}},
        "objects": [_floor(2.5)],
        "volumes": [{"density": str(DATA_DIR / "smoke.npy"), "bounds": dict(SMOKE_BOUNDS),
                     "sigma_s": [5.0, 5.2, 5.5], "sigma_a": 0.8}],
        "render": dict(_RENDER),
    }


SMOKE_SCENES: dict[str, Callable[[], dict]] = {"smoke_plume": smoke_plume}
