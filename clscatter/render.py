"""One render: scene -> checked method parameters -> plan -> prepared device scene -> view
paths -> passes -> image."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .device import Engine, get_engine
from .methods import configure_scene, get_method
from .planner import plan
from .prepared import prepare_scene
from .scene.model import Scene
from .stats import Stats
from .view_paths import trace_view_paths


@dataclass
class RenderResult:
    image: np.ndarray            # (H, W, 3) float32 linear radiance
    stats: dict[str, Any]
    surface: np.ndarray          # the surface part alone (direct light + surface caustics)
    medium: np.ndarray           # the medium part alone


def render(scene: Scene, method: str | None = None, engine: Engine | None = None,
           device: str | None = None, show_progress: bool = True) -> RenderResult:
    """Render ``scene`` with ``method`` (default: the scene's render.method).

    Every method name and ``[render.<method>]`` table is checked before any device work
    (:func:`clscatter.methods.configure_scene`); the plan is made from the scene alone.
    """
    stats = Stats()
    requested = method if method is not None else scene.render.method
    with stats.stage("configure"):
        configure_scene(scene, requested)
        passes, notes = plan(scene, requested)
    with stats.stage("device"):
        engine = engine or get_engine(device)
    engine.reset_peak()
    ps = prepare_scene(scene, engine, stats)
    try:
        paths = trace_view_paths(ps, stats, show_progress)
        cam = scene.camera
        surface = paths.surface.copy()
        medium = np.zeros((cam.height, cam.width, 3), np.float32)
        for p in passes:
            m = get_method(p.method)({**(scene.render.params.get(p.method) or {}), **p.params})
            out = m.render(ps, paths, stats, show_progress)
            if p.role == "surface_caustics":
                surface = surface + out
            elif isinstance(out, dict):      # a method that splits its own terms
                surface = surface + out.get("surface", 0.0)
                medium = medium + out.get("medium", 0.0)
            else:
                medium = medium + out
        chosen = "+".join(p.method for p in passes) or None
        image = surface + medium
        bad = ~np.isfinite(image)
        if bad.any():
            stats.set(nonfinite_pixels_zeroed=int(bad.any(axis=-1).sum()))
            image = np.where(bad, 0.0, image).astype(np.float32)
        stats.set(method=chosen or "none", requested_method=requested, plan=notes,
                  passes=[{"method": p.method, "role": p.role} for p in passes],
                  device=engine.name, width=cam.width, height=cam.height, spp=cam.spp,
                  peak_bytes=int(engine.bytes_peak))
    finally:
        ps.release()
    return RenderResult(image.astype(np.float32), stats.to_dict(), surface.astype(np.float32),
                        medium.astype(np.float32))
