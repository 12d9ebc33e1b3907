"""One render: scene -> checked method parameters -> plan -> prepared device scene -> view
paths -> passes -> image (the stages themselves live in :mod:`clscatter.pipeline.session`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import budget
from ..device import Engine
from ..methods import configure_scene
from .planner import plan
from ..scene.model import Scene


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
    from the scene alone) and the cost estimates (:mod:`clscatter.pipeline.budget`)."""
    requested = method if method is not None else scene.render.method
    settings = configure_scene(scene, requested)
    passes, notes = plan(scene, requested)
    return Prepared(requested, passes, notes, budget.estimate(scene, passes, settings))


def render(scene: Scene, method: str | None = None, engine: Engine | None = None,
           device: str | None = None, show_progress: bool = True,
           max_memory: float | None = None, on_note=None, stats=None) -> RenderResult:
    """Render ``scene`` with ``method`` (default: the scene's render.method).

    :func:`check` runs first; a render whose estimated peak memory exceeds ``max_memory``
    (default: the device's and the machine's memory) is refused before anything is
    allocated. ``on_note`` receives one-line notes for the user (long work, dropped
    triangles). This is a :class:`~clscatter.pipeline.session.RenderSession` used once.
    """
    from .session import RenderSession

    with RenderSession(scene, method, engine=engine, device=device,
                       max_memory=max_memory, keep_hits=False) as session:
        return session.render(show_progress=show_progress, on_note=on_note, stats=stats)


def scene_notes(scene: Scene) -> list[str]:
    """One-line notes about the scene itself: zero-area triangles dropped when loading,
    and surfaces that reflect more light than reaches them (albedo or reflectance above
    1: allowed, as other renderers allow it, but not physical)."""
    notes = [f"{o.key}: {o.dropped_triangles} zero-area triangles dropped"
             for o in scene.objects if o.dropped_triangles]
    seen = set()
    for o in scene.objects:
        m = o.material
        value = {"diffuse": "albedo", "mirror": "reflectance"}.get(m.type)
        if value is None or id(m) in seen or float(np.max(m.color)) <= 1.0:
            continue
        seen.add(id(m))
        notes.append(f"{m.key or m.name}.{value}: {float(np.max(m.color)):g} > 1 reflects more light "
                     "than reaches it (not physical)")
    return notes + _range_notes(scene)


SPAN_NOTE = 1e5     # a scene this many times wider than the camera's view distance is noted


def _range_notes(scene: Scene) -> list[str]:
    """A note when the scene's bounding box is :data:`SPAN_NOTE` times or more the
    camera's distance to its target: the device works in float32 in a frame scaled to
    the box, so what the camera sees is then resolved to a few float32 steps (an object
    far off made images wrong from ~1e6 times on in an outside check), naming the object
    furthest from the target."""
    bb = scene.bbox()
    if bb is None:
        return []
    span = float(np.max(bb[1] - bb[0]))
    target = np.asarray(scene.camera.target, np.float64)
    view = float(np.linalg.norm(np.asarray(scene.camera.origin, np.float64) - target))
    if span < SPAN_NOTE * view or not scene.objects:
        return []
    far = max(scene.objects, key=lambda o: float(np.max(np.linalg.norm(o.vertices - target,
                                                                       axis=1))))
    return [f"the scene spans {span:.3g} units, {span / view:.1e} times the camera's distance "
            f"to its target: the device's float32 may not resolve what the camera sees "
            f"({far.key} is furthest off)"]
