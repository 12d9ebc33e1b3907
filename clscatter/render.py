"""One render: scene -> prepared device scene -> view paths -> medium method -> image."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .device import Engine, get_engine
from .methods import get_method
from .prepared import prepare_scene
from .view_paths import trace_view_paths
from .planner import plan
from .scene.model import Scene
from .stats import Stats


@dataclass
class RenderResult:
    image: np.ndarray            # (H, W, 3) float32 linear radiance
    stats: dict[str, Any]
    surface: np.ndarray          # the surface part alone
    medium: np.ndarray           # the medium part alone


def render(scene: Scene, method: str | None = None, engine: Engine | None = None,
           device: str | None = None, show_progress: bool = True) -> RenderResult:
    """Render ``scene`` with ``method`` (default: the scene's render.method)."""
    stats = Stats()
    requested = method or scene.render.method
    if requested != "auto":
        get_method(requested)  # fail early, before any device work, on a bad name
    engine = engine or get_engine(device)
    engine.reset_peak()
    ps = prepare_scene(scene, engine, stats)
    try:
        paths = trace_view_paths(ps, stats, show_progress)
        passes, notes = plan(ps, requested)
        cam = scene.camera
        medium = np.zeros((cam.height, cam.width, 3), np.float32)
        for p in passes:
            params = {**scene.render.params.get(p.method, {}), **p.params}
            m = get_method(p.method)(params)
            medium = medium + m.render_medium(ps, paths, stats, show_progress)
        chosen = "+".join(p.method for p in passes) or None
        image = paths.surface + medium
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
    return RenderResult(image.astype(np.float32), stats.to_dict(), paths.surface, medium)
