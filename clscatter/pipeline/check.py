"""Everything a render checks before it touches a device: method names and parameter
tables, the plan, the cost estimates, and one-line notes about the scene itself."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import open_edges
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
    glass and volume surfaces that are not closed, and surfaces that reflect more light
    than reaches them (albedo or reflectance above
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
    return notes + _open_surface_notes(scene) + _range_notes(scene)


def _open_surface_notes(scene: Scene) -> list[str]:
    """A note for every glass object and every mesh volume whose surface is not closed: an
    inside is not defined there, so rays crossing the gaps enter or leave the glass
    unpredictably (sparkling pixels along the gaps)."""
    notes = []
    shapes = [(o.key, o.faces) for o in scene.objects if o.material.type == "dielectric"]
    shapes += [(v.key, v.mesh.faces) for v in scene.volumes if v.mesh is not None]
    for key, faces in shapes:
        n = open_edges(faces)
        if n:
            notes.append(f"{key}: its surface is not closed ({n} open edges): glass and "
                         "volumes need a closed surface; light crossing the gaps is wrong "
                         "(close_holes = true on a mesh fills its holes)")
    return notes


SPAN_NOTE = 1e5     # a scene this many times wider than the camera's view distance is noted


def _range_notes(scene: Scene) -> list[str]:
    """Notes where the device's float32 may still not resolve what the camera sees. Far
    objects and volumes (:meth:`Scene.far_items`) leave the normalised frame as it is, so
    what is left is: the scene's bounding box (the near objects) spanning
    :data:`SPAN_NOTE` times or more the camera's distance to its target (one object
    reaching from near the camera to far off, such as a vast ground plane), naming the
    near object furthest from the target; and a far object in a directional light's beam
    into the near region (:meth:`Scene.far_in_beam`), as that light's lighting rays and
    shadow maps then start beyond it."""
    notes = []
    bb = scene.bbox()
    target = np.asarray(scene.camera.target, np.float64)
    view = float(np.linalg.norm(np.asarray(scene.camera.origin, np.float64) - target))
    span = float(np.max(bb[1] - bb[0])) if bb is not None else 0.0
    near = [o for o in scene.objects if len(o.vertices) and bb is not None  # the box holds
            and np.all(o.vertices >= bb[0]) and np.all(o.vertices <= bb[1])]  # no far one
    if span >= SPAN_NOTE * view and near:
        wide = max(near, key=lambda o: float(np.max(np.linalg.norm(o.vertices - target,
                                                                    axis=1))))
        notes.append(f"the scene spans {span:.3g} units, {span / view:.1e} times the camera's "
                     f"distance to its target: the device's float32 may not resolve what the "
                     f"camera sees ({wide.key} is furthest off)")
    for i, light in enumerate(scene.lights):
        if light.type == "directional":
            notes += [f"{key} is far off but in the way of lights[{i}] into the scene: that "
                      "light's lighting rays and shadow maps start beyond it, where float32 "
                      "resolves the scene less finely" for key, _, _ in
                      scene.far_in_beam(light.direction)]
    return notes
