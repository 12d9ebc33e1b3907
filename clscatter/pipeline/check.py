"""Everything a render checks before it touches a device: method names and parameter
tables, the plan, the cost estimates, and one-line notes about the scene itself."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..methods import configure_scene
from ..scene.model import Scene
from . import budget
from .planner import plan


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
    far off made images wrong from about 1e6 times on), naming the object
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
