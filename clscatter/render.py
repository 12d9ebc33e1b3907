"""One render: scene -> checked method parameters -> plan -> prepared device scene -> view
paths -> passes -> image."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import budget
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


@dataclass
class Prepared:
    """A checked render request: the plan and its cost estimates (no device work yet)."""

    requested: str
    passes: list
    notes: list[str]
    estimates: list


def check(scene: Scene, method: str | None = None) -> Prepared:
    """Everything a render checks before it touches a device: the method name, every
    ``[render.<method>]`` table (:func:`clscatter.methods.configure_scene`), the plan (made
    from the scene alone) and the cost estimates (:mod:`clscatter.budget`)."""
    requested = method if method is not None else scene.render.method
    settings = configure_scene(scene, requested)
    passes, notes = plan(scene, requested)
    return Prepared(requested, passes, notes, budget.estimate(scene, passes, settings))


def render(scene: Scene, method: str | None = None, engine: Engine | None = None,
           device: str | None = None, show_progress: bool = True,
           max_memory: float | None = None, on_note=None) -> RenderResult:
    """Render ``scene`` with ``method`` (default: the scene's render.method).

    :func:`check` runs first; a render whose estimated peak memory exceeds ``max_memory``
    (default: the device's and the machine's memory) is refused before anything is
    allocated. ``on_note`` receives one-line notes for the user (long work, dropped
    triangles).
    """
    stats = Stats()
    with stats.stage("configure"):
        req = check(scene, method)
    requested, passes, notes = req.requested, req.passes, req.notes
    with stats.stage("device"):
        engine = engine or get_engine(device)
    limit, source = budget.memory_budget(engine, max_memory)
    budget.check_budget(req.estimates, limit, source)
    for line in budget.long_work_notes(req.estimates) + _scene_notes(scene):
        if on_note is not None:
            on_note(line)
    if scene.dropped_triangles():
        stats.set(degenerate_triangles_dropped=scene.dropped_triangles())
    stats.set(estimated_peak_bytes=int(budget.peak_bytes(req.estimates)))
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


def _scene_notes(scene: Scene) -> list[str]:
    return [f"{o.key}: {o.dropped_triangles} zero-area triangles dropped"
            for o in scene.objects if o.dropped_triangles]
