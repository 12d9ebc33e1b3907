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
    glass and volume surfaces that are not closed, and surfaces that reflect more light
    than reaches them (albedo or reflectance above
    1: allowed, as other renderers allow it, but not physical), and a camera inside a glass
    object."""
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
    return notes + _open_surface_notes(scene) + _camera_inside_notes(scene) + _range_notes(scene)


def open_edges(faces: np.ndarray) -> int:
    """Edges of a triangle mesh (vertex indices, shared vertices merged) that only one
    triangle uses: 0 for a closed surface."""
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return 0
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    # an integer key per edge (np.unique(axis=0) compares structured arrays, which turns
    # a KeyboardInterrupt raised by a signal meanwhile into a TypeError)
    _, counts = np.unique(e[:, 0] * (int(f.max()) + 1) + e[:, 1], return_counts=True)
    return int(np.count_nonzero(counts == 1))


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
                         "volumes need a closed surface; light crossing the gaps is wrong")
    return notes


#: the direction of the parity ray from the camera (no symmetry of a box or a sphere lies
#: along it, so it does not graze their edges)
PARITY_RAY = np.array([0.5312, 0.6217, 0.5755])


def crossings(origin, direction, triangles: np.ndarray) -> int:
    """How many of ``triangles`` (F, 3, 3) the ray ``origin + t direction``, t > 0, crosses
    (Moller-Trumbore in float64): odd when the origin lies inside a closed surface."""
    tri = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    o, d = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - tri[:, 0]
    u = np.einsum("ij,ij->i", tv, p) * inv
    q = np.cross(tv, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return int(np.count_nonzero(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)))


def _camera_inside_notes(scene: Scene) -> list[str]:
    """A note when the camera lies inside a closed glass object: view paths start in air
    (the engine's cameras, lights' rays and medium lie outside closed dielectrics), so
    what such a camera sees lacks the n^2 radiance gain of light entering the glass, and
    the glass's own interior is taken for the scene medium up to its surface."""
    origin = np.asarray(scene.camera.origin, np.float64)
    notes = []
    for o in scene.objects:
        if o.material.type != "dielectric" or not len(o.faces):
            continue
        lo, hi = o.vertices.min(axis=0), o.vertices.max(axis=0)
        if np.any(origin < lo) or np.any(origin > hi) or open_edges(o.faces):
            continue
        if crossings(origin, PARITY_RAY, o.vertices[o.faces]) % 2:
            notes.append(f"camera.origin is inside {o.key} (glass): cameras are taken to be in "
                         "air, so this image lacks the glass's n^2 radiance gain and treats its "
                         "inside as the scene medium up to its surface; move the camera out of it")
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
