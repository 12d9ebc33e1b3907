"""A built-in scene at the scale of the LSG paper's Table 1 (Sun et al. 2010: 43K-93K
triangles, 0.7-8.9 M lighting rays, 512 x 512 with 2 x 2 supersampling).

Dicts in exactly the TOML schema of docs/scene_format.md, like the other built-ins. The
mesh is the Stanford bunny (Stanford 3D Scanning Repository, Turk & Levoy 1994; 69,451
triangles, 69,664 with its holes closed) committed as ``meshes/bunny.ply`` (see ``meshes/README.md``), referenced by
absolute path like the caustic scenes' meshes because built-in scenes are resolved against
the current directory.

==================  ===================================================================
``paper_bunny``     glass Stanford bunny in a fog box over a diffuse floor, under a point
                    light and a spot light; 512 x 512, 4 spp, 1 M lighting rays a pass
==================  ===================================================================

``tools/bench_paper_scale.py`` benchmarks it (LSG against VPM at equal error, and how
LSG's time and memory grow with triangles, lighting rays and pixels).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from .parts import RENDER as _RENDER
from .parts import floor as _floor

MESH_DIR = Path(__file__).resolve().parents[1] / "meshes"
BUNNY = MESH_DIR / "bunny.ply"
#: triangles of ``meshes/bunny.ply`` (and of the Stanford ``bun_zipper`` it was converted from)
BUNNY_TRIANGLES = 69_451
#: triangles of the scene's bunny: the file's, and 213 that close the five holes in its base
#: (``close_holes``)
BUNNY_CLOSED_TRIANGLES = 69_664
#: vertices in the file, 1,113 of them referenced by no triangle (dropped on loading)
BUNNY_VERTICES = 35_947

#: scale 6.5 makes the bunny ~1.0 unit tall; the rotation turns it three-quarters to the
#: camera and the translation centres it over the origin, 1 mm above the floor
BUNNY_TRANSFORM = {"translate": [0.15, -0.2134, 0.08], "rotate": [0.0, 1.0, 0.0, -20.0],
                   "scale": 6.5}


def paper_bunny() -> dict:
    """Glass Stanford bunny (69,664 triangles) in fog over a floor, under a point and a spot
    light: volumetric caustics at the scale of the LSG paper.

    512 x 512 at 4 spp (the paper's 2 x 2 supersampling) and 1 M lighting rays a pass
    (``[render.lsg] light_rays``). ``auto``'s default 10 s time budget sizes LSG's passes
    to fit and so uses fewer rays: ``--time-budget 0`` renders all of them. The scan has
    five holes in its base, which ``close_holes`` triangulates: glass needs a closed
    surface.
    """
    camera = {"origin": [0.0, 1.15, 3.4], "target": [0.0, 0.5, 0.0], "up": [0.0, 1.0, 0.0],
              "fov": 42.0, "fov_axis": "x", "resolution": [512, 512], "spp": 4}
    return {
        "camera": camera,
        "medium": {"sigma_s": 0.15, "sigma_a": 0.02, "g": 0.2,
                   "bounds": {"min": [-2.0, 0.0, -2.0], "max": [2.0, 2.6, 2.0]}},
        "lights": [
            {"type": "point", "position": [-0.7, 2.2, 0.4], "intensity": 10.0},
            {"type": "spot", "position": [1.5, 2.3, -0.7], "target": [0.0, 0.5, 0.0],
             "intensity": 30.0, "cutoff_angle": 22.0},
        ],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.55},
                      "glass": {"type": "dielectric", "ior": 1.5}},
        "objects": [
            _floor(2.0),
            {"shape": "mesh", "file": str(BUNNY), "smooth": True, "close_holes": True,
             "material": "glass", "transform": dict(BUNNY_TRANSFORM)},
        ],
        "render": {**_RENDER, "lsg": {"light_rays": 1_000_000}},
    }


PAPER_SCENES: dict[str, Callable[[], dict]] = {
    "paper_bunny": paper_bunny,
}
