"""Animations as lists of ``--set`` overrides, one list per frame.

``orbit(scene, frames, "light")`` turns every light once around a vertical axis: the line
through the centre of the scene's bounding box (the camera's target when the scene has no
geometry) along the camera's ``up``. Point and spot lights move on a circle around that
axis at their own height (spots keep aiming at their target); directional lights turn
their direction about it. ``orbit(scene, frames, "camera")`` moves the camera once around
the same kind of axis through its target.

The circle is the light's own one when that is wide enough to see: its radius is the
light's horizontal distance from the axis. A light (nearly) on the axis would only wobble
in place (frames that look alike), so when that distance is under
:data:`MIN_RADIUS_FRACTION` (5 %) of the scene's extent (its bounding box's longest side,
or a bounded medium's if that is smaller), or the light, seen from the axis point, is
less than :data:`MIN_TILT_DEG` (10 degrees) off the axis, the orbit is widened to
:data:`WIDE_RADIUS_FRACTION` (a quarter) of the extent or :data:`WIDE_TILT_DEG` (20
degrees) off the axis, whichever is wider, keeping the light's height and the side it
leans to (the camera's right when it is exactly on the axis). Likewise a directional
light within 10 degrees of the axis is tilted to 20 degrees. :func:`orbit_path` returns
the axis and the radii, which ``clscatter relight`` records in ``frames.json``.

Frames are absolute overrides of the original scene, so any frame can be rendered on its
own (by any worker, in any order) and reproduces exactly. Frame 0 is the original scene
unless the orbit was widened (then the light starts at the widened position).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ClscatterError
from .scene.model import Scene

ORBITS = ("light", "camera")

#: a point or spot light closer to the axis than this fraction of the scene's extent, or
#: seen from the axis point less than MIN_TILT_DEG off the axis, ...
MIN_RADIUS_FRACTION = 0.05
#: ... orbits at this fraction of the extent (or WIDE_TILT_DEG off the axis, if wider)
WIDE_RADIUS_FRACTION = 0.25
#: a directional light closer to the axis than this (degrees) ...
MIN_TILT_DEG = 10.0
#: ... is tilted to this angle from it
WIDE_TILT_DEG = 20.0


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about the unit ``axis``."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(np.dot(axis, v)) * (1 - c)


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in v) + "]"


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@dataclass
class Mover:
    """One thing on the orbit: ``key`` is the override it gets (``lights[0].position``,
    ``lights[1].direction``, ``camera.origin``); ``start`` its value in frame 0."""

    key: str
    kind: str                      # "point", "spot", "directional" or "camera"
    start: np.ndarray
    radius: float | None = None    # distance from the axis (positions)
    height: float | None = None    # along the axis, from the axis point (positions)
    tilt_deg: float | None = None  # angle between the direction and the axis (directional)
    widened: bool = False          # the orbit was widened (see the module docstring)

    def record(self) -> dict:
        out: dict = {"key": self.key, "type": self.kind, "start": [float(x) for x in self.start],
                     "widened": self.widened}
        if self.radius is not None:
            out.update(radius=self.radius, height=self.height)
        if self.tilt_deg is not None:
            out["tilt_degrees"] = self.tilt_deg
        return out


@dataclass
class OrbitPath:
    """The axis everything turns about and what turns: ``point`` and unit ``direction`` of
    the axis, one :class:`Mover` per light (or the camera)."""

    what: str
    point: np.ndarray
    direction: np.ndarray
    movers: list[Mover] = field(default_factory=list)

    @property
    def radius(self) -> float | None:
        """The radius of the first thing that moves on a circle (None: directional only)."""
        return next((m.radius for m in self.movers if m.radius is not None), None)

    def overrides(self, angle: float) -> list[str]:
        """The ``--set`` overrides of the frame turned by ``angle`` radians."""
        out = []
        for m in self.movers:
            if m.kind == "directional":
                out.append(f"{m.key}={_vec(_rotate(m.start, self.direction, angle))}")
            else:
                p = self.point + _rotate(m.start - self.point, self.direction, angle)
                out.append(f"{m.key}={_vec(p)}")
        return out

    def record(self) -> dict:
        """What ``frames.json`` says about the orbit: ``axis`` (``point``, ``direction``),
        ``radius`` (see :attr:`radius`) and one entry per mover."""
        return {"axis": {"point": [float(x) for x in self.point],
                         "direction": [float(x) for x in self.direction]},
                "radius": self.radius,
                "movers": [m.record() for m in self.movers]}


def orbit_path(scene: Scene, what: str) -> OrbitPath:
    """The axis of a light or camera orbit of ``scene`` and where each mover starts."""
    if what not in ORBITS:
        raise ClscatterError(f"--orbit: expected one of {', '.join(ORBITS)} (got {what!r})")
    cam = scene.camera
    up = _unit(cam.up)
    target = np.asarray(cam.target, np.float64)
    if what == "camera":
        path = OrbitPath(what, target, up)
        origin = np.asarray(cam.origin, np.float64)
        off = origin - target
        along = float(np.dot(off, up))
        path.movers.append(Mover("camera.origin", "camera", origin,
                                 radius=float(np.linalg.norm(off - along * up)), height=along))
        return path
    bb = scene.bbox()
    centre = (bb[0] + bb[1]) / 2 if bb is not None else target
    extent = _extent(scene)
    # the side a light exactly on the axis is moved to: the camera's right
    right = np.cross(target - np.asarray(cam.origin, np.float64), up)
    right = _unit(right) if np.linalg.norm(right) > 1e-12 else _unit(np.cross(up, _any_perp(up)))
    path = OrbitPath(what, centre, up)
    for i, light in enumerate(scene.lights):
        if light.type == "directional":
            d = _unit(light.direction)
            tilt = math.degrees(math.acos(min(1.0, abs(float(np.dot(d, up))))))
            widened = tilt < MIN_TILT_DEG
            if widened:
                d = _tilted(d, up, right, WIDE_TILT_DEG)
                tilt = WIDE_TILT_DEG
            path.movers.append(Mover(f"lights[{i}].direction", "directional", d,
                                     tilt_deg=tilt, widened=widened))
            continue
        p = np.asarray(light.position, np.float64)
        off = p - centre
        along = float(np.dot(off, up))
        flat = off - along * up
        radius = float(np.linalg.norm(flat))
        widened = (radius < MIN_RADIUS_FRACTION * extent
                   or math.degrees(math.atan2(radius, abs(along))) < MIN_TILT_DEG)
        if widened:
            side = flat / radius if radius > 1e-9 * extent else right
            radius = max(WIDE_RADIUS_FRACTION * extent,
                         abs(along) * math.tan(math.radians(WIDE_TILT_DEG)))
            p = centre + along * up + radius * side
        path.movers.append(Mover(f"lights[{i}].position", light.type, p, radius=radius,
                                 height=along, widened=widened))
    return path


def _extent(scene: Scene) -> float:
    """The size the widened orbits are a fraction of: the scene's extent (its bounding
    box's longest side), or a bounded medium's longest side when that is smaller (a large
    floor under a small fog box should not push the light out of the fog)."""
    extent = scene.scene_extent()
    m = scene.medium
    if m is not None and m.bounds is not None:
        side = float(np.max(np.asarray(m.bounds[1]) - np.asarray(m.bounds[0])))
        if 0 < side < extent:
            extent = side
    return extent


def _any_perp(v: np.ndarray) -> np.ndarray:
    return np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])


def _tilted(d: np.ndarray, up: np.ndarray, right: np.ndarray, deg: float) -> np.ndarray:
    """``d`` turned to ``deg`` degrees from the axis ``up`` (on its side of the axis, or
    towards ``right`` when it is exactly on it), keeping whether it points up or down."""
    along = float(np.dot(d, up))
    flat = d - along * up
    n = float(np.linalg.norm(flat))
    side = flat / n if n > 1e-9 else right
    sign = 1.0 if along >= 0 else -1.0
    a = math.radians(deg)
    return _unit(sign * math.cos(a) * up + math.sin(a) * side)


def orbit(scene: Scene, frames: int, what: str) -> list[list[str]]:
    """Per-frame overrides turning the lights or the camera through one full turn."""
    if what not in ORBITS:
        raise ClscatterError(f"--orbit: expected one of {', '.join(ORBITS)} (got {what!r})")
    if frames < 1:
        raise ClscatterError(f"--frames: must be >= 1 (got {frames})")
    path = orbit_path(scene, what)
    return [path.overrides(2 * math.pi * k / frames) for k in range(frames)]
