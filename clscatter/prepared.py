"""The prepared scene: a scene in the normalised frame, flattened, with its BVH, on one device.

:func:`prepare_scene` runs once per render (or once per relighting session); every pass
reads the device buffers it holds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import structs
from .accel.bvh import BVH, build_bvh
from .device import Engine
from .scene.frame import Frame, camera_struct, light_structs, medium_struct, triangle_soup
from .scene.model import Scene
from .stats import Stats


@dataclass
class PreparedScene:
    """A scene in the normalised frame, uploaded to one device."""

    scene: Scene
    engine: Engine
    frame: Frame
    bvh: BVH
    medium: np.ndarray          # structs.MEDIUM (host copy)
    camera: np.ndarray          # structs.CAMERA (host copy)
    lights: np.ndarray          # structs.LIGHT array (host copy)
    buf: dict                   # name -> device buffer

    @property
    def num_lights(self) -> int:
        return len(self.lights)

    @property
    def has_medium(self) -> bool:
        return bool(self.medium["present"])

    def release(self) -> None:
        self.engine.free(*self.buf.values())
        self.buf.clear()


def prepare_scene(scene: Scene, engine: Engine, stats: Stats | None = None) -> PreparedScene:
    """Normalise, flatten and upload ``scene``; build its BVH."""
    stats = stats or Stats()
    frame = Frame.for_scene(scene)
    with stats.stage("bvh_build"):
        soup = triangle_soup(scene, frame)
        bvh = build_bvh(soup.triangles)
    order = bvh.order
    normals = np.zeros((len(order), 3, 4), np.float32)
    normals[:, :, :3] = soup.normals[order]
    tri_mat = np.ascontiguousarray(soup.material[order], np.int32)
    medium = medium_struct(scene.medium, frame)
    camera = camera_struct(scene.camera, frame)
    lights = light_structs(scene.lights, frame)
    lights_dev = lights if len(lights) else np.zeros(1, structs.LIGHT)
    with stats.stage("upload"):
        buf = {
            "nodes": engine.to_device(bvh.nodes),
            "tris": engine.to_device(bvh.triangles),
            "normals": engine.to_device(normals),
            "tri_mat": engine.to_device(tri_mat),
            "materials": engine.to_device(soup.materials),
            "lights": engine.to_device(lights_dev),
            "medium": engine.to_device(medium.reshape(1)),
            "camera": engine.to_device(camera.reshape(1)),
        }
    stats.set(triangles=int(len(order)), bvh_nodes=int(len(bvh.nodes)), lights=int(len(lights)))
    return PreparedScene(scene, engine, frame, bvh, medium, camera, lights, buf)
