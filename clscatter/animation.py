"""Animations as lists of ``--set`` overrides, one list per frame.

``orbit(scene, frames, "light")`` turns every light once around the vertical axis (the
camera's ``up``) through the centre of the scene's bounding box: point and spot lights move
(spots keep aiming at their target), directional lights turn their direction.
``orbit(scene, frames, "camera")`` moves the camera once around its target. Frames are
absolute overrides of the original scene, so any frame can be rendered on its own (by any
worker, in any order) and reproduces exactly.
"""
from __future__ import annotations

import math

import numpy as np

from .errors import ClscatterError
from .scene.model import Scene

ORBITS = ("light", "camera")


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about the unit ``axis``."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(np.dot(axis, v)) * (1 - c)


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in v) + "]"


def orbit(scene: Scene, frames: int, what: str) -> list[list[str]]:
    """Per-frame overrides turning the lights or the camera through one full turn."""
    if what not in ORBITS:
        raise ClscatterError(f"--orbit: expected one of {', '.join(ORBITS)} (got {what!r})")
    if frames < 1:
        raise ClscatterError(f"--frames: must be >= 1 (got {frames})")
    up = np.asarray(scene.camera.up, np.float64)
    up = up / np.linalg.norm(up)
    bb = scene.bbox()
    centre = (bb[0] + bb[1]) / 2 if bb is not None else np.asarray(scene.camera.target, np.float64)
    out = []
    for k in range(frames):
        a = 2 * math.pi * k / frames
        sets: list[str] = []
        if what == "camera":
            t = np.asarray(scene.camera.target, np.float64)
            sets.append(f"camera.origin={_vec(t + _rotate(scene.camera.origin - t, up, a))}")
        else:
            for i, light in enumerate(scene.lights):
                if light.type == "directional":
                    sets.append(f"lights[{i}].direction={_vec(_rotate(np.asarray(light.direction), up, a))}")
                else:
                    p = centre + _rotate(np.asarray(light.position) - centre, up, a)
                    sets.append(f"lights[{i}].position={_vec(p)}")
        out.append(sets)
    return out
