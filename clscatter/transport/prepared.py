"""The prepared scene: a scene in the normalised frame, flattened, with its BVH, on one device.

:func:`prepare_scene` runs once per render (or once per relighting session); every pass
reads the device buffers it holds.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Sequence

import numpy as np

from ..accel import tile_grid
from ..accel.bvh import BVH
from ..accel.bvh_cache import cached_bvh
from ..device import Engine, structs
from ..io.stats import Stats
from ..scene.model import Scene
from ..scene.normalised import (
    Frame,
    camera_struct,
    light_structs,
    medium_struct,
    triangle_soup,
)


@dataclass
class SceneBuffers:
    """The scene's device buffers; names match the kernels' parameter names (the camera
    binds as ``camera`` or ``cam``)."""

    nodes: object       # BVH nodes (structs.BVH_NODE)
    tris: object        # Woop-transformed triangles, BVH order
    normals: object     # per-vertex shading normals (float4 x 3 per triangle)
    tri_mat: object     # material index per triangle
    materials: object   # structs.MATERIAL
    lights: object      # structs.LIGHT (one dummy record when the scene has none)
    medium: object      # structs.MEDIUM
    camera: object      # structs.CAMERA
    light_grid: object  # tile grid for the first directional light's shadow rays (packed)
    camera_grid: object  # tile grid for the camera's primary rays (packed)

    def as_dict(self) -> dict[str, object]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


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
    dev: SceneBuffers | None    # device buffers (None once released)
    materials: np.ndarray | None = None   # structs.MATERIAL (host copy)

    @property
    def num_lights(self) -> int:
        return len(self.lights)

    @property
    def has_medium(self) -> bool:
        return bool(self.medium["present"])

    def near_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The box of the triangles near the camera, normalised frame: the BVH's root box
        limited to the scene's bounding box (:meth:`Scene.bbox`, which leaves far objects
        out), float32 values as float64 arrays; None when no triangle lies in it. Without
        far objects this is the BVH's root box exactly. What lighting rays, shadow maps and
        light grids must cover; far triangles stay in the BVH for every ray."""
        return near_box(self.bvh, self.frame, self.scene)

    def call(self, program: str, kernel: str, global_size: int | Sequence[int],
             defines: dict[str, object] | None = None, **args) -> None:
        """:meth:`Engine.call` with the scene filled in: every kernel parameter named like
        a :class:`SceneBuffers` field, and ``num_lights``, is bound from this scene unless
        given explicitly."""
        self.engine.call(program, kernel, global_size, defines,
                         **self.scene_args(program, kernel, **args), **args)

    def scene_args(self, program: str, kernel: str, **given) -> dict[str, object]:
        """The scene's part of a kernel's arguments (parameters not in ``given``)."""
        have = {**self.dev.as_dict(), "cam": self.dev.camera, "num_lights": self.num_lights}
        return {p.name: have[p.name] for p in self.engine.signature(program, kernel)
                if p.name in have and p.name not in given}

    def release(self) -> None:
        if self.dev is not None:
            self.engine.free(*self.dev.as_dict().values())
            self.dev = None


def near_box(bvh: BVH, frame: Frame, scene: Scene) -> tuple[np.ndarray, np.ndarray] | None:
    """:meth:`PreparedScene.near_box` of a scene's BVH, frame and scene."""
    root = bvh.nodes[0]
    lo, hi = np.asarray(root["bmin"], np.float64), np.asarray(root["bmax"], np.float64)
    bb = scene.bbox()
    if bb is not None:
        lo = np.maximum(lo, frame.point(bb[0]).astype(np.float32))
        hi = np.minimum(hi, frame.point(bb[1]).astype(np.float32))
    return (lo, hi) if np.all(lo <= hi) else None


def prepare_scene(scene: Scene, engine: Engine, stats: Stats | None = None) -> PreparedScene:
    """Normalise, flatten and upload ``scene``; build its BVH."""
    stats = stats or Stats()
    with stats.stage("scene_structs"):
        frame = Frame.for_scene(scene)
        soup = triangle_soup(scene, frame)
    with stats.stage("bvh_build"):
        bvh, bvh_cached = cached_bvh(soup.triangles)
    with stats.stage("scene_structs"):
        order = bvh.order
        normals = np.zeros((len(order), 3, 4), np.float32)
        normals[:, :, :3] = soup.normals[order]
        tri_mat = np.ascontiguousarray(soup.material[order], np.int32)
        medium = medium_struct(scene.medium, frame)
        camera = camera_struct(scene.camera, frame, scene)
        lights = light_structs(scene.lights, frame)
        lights_dev = lights if len(lights) else np.zeros(1, structs.LIGHT)
    with stats.stage("scene_grids"):
        grids = {"light_grid": _light_grid(bvh, lights, frame, scene),
                 "camera_grid": tile_grid.camera_grid(bvh, camera)}
    with stats.stage("upload"):
        dev = SceneBuffers(
            nodes=engine.to_device(bvh.nodes),
            tris=engine.to_device(bvh.triangles),
            normals=engine.to_device(normals),
            tri_mat=engine.to_device(tri_mat),
            materials=engine.to_device(soup.materials),
            lights=engine.to_device(lights_dev),
            medium=engine.to_device(medium.reshape(1)),
            camera=engine.to_device(camera.reshape(1)),
            **{k: tile_grid.upload(engine, g) for k, g in grids.items()},
        )
    stats.set(triangles=int(len(order)), bvh_nodes=int(len(bvh.nodes)), bvh_cached=bvh_cached,
              lights=int(len(lights)),
              tile_grids={k: g.stats() if g is not None else None for k, g in grids.items()})
    return PreparedScene(scene, engine, frame, bvh, medium, camera, lights, dev, soup.materials)


def refresh(ps: PreparedScene, scene: Scene, stats: Stats | None = None) -> list[str]:
    """Bring ``ps`` to ``scene`` *with the same geometry*, re-uploading only the device
    buffers whose contents changed (lights, camera, medium, materials); the BVH and the
    triangle buffers are kept. Returns the names of the buffers replaced.

    The caller guarantees that objects and volumes are unchanged (and so is the normalised
    frame; :func:`same_frame` checks it): otherwise prepare the scene anew.
    """
    stats = stats or Stats()
    eng = ps.engine
    frame = ps.frame
    fresh = {"medium": medium_struct(scene.medium, frame),
             "camera": camera_struct(scene.camera, frame, scene),
             "lights": light_structs(scene.lights, frame)}
    changed = []
    with stats.stage("upload"):
        for name, host in fresh.items():
            if host.tobytes() == np.asarray(getattr(ps, name)).tobytes():
                continue
            dev_host = host.reshape(-1) if host.size else np.zeros(1, structs.LIGHT)
            eng.free(getattr(ps.dev, name))
            setattr(ps.dev, name, eng.to_device(dev_host))
            setattr(ps, name, host)
            changed.append(name)
        materials = triangle_soup(scene, frame, materials_only=True).materials
        if materials.tobytes() != ps.materials.tobytes():
            eng.free(ps.dev.materials)
            ps.dev.materials = eng.to_device(materials)
            ps.materials = materials
            changed.append("materials")
    ps.scene = scene
    for name in changed:
        _refresh_grid(ps, name, stats)
    return changed


def _light_grid(bvh: BVH, lights: np.ndarray, frame: Frame, scene: Scene):
    """The scene's light grid (:func:`tile_grid.light_grid`) over its near triangles; none
    when every triangle is far (shadow rays then use the BVH)."""
    box = near_box(bvh, frame, scene)
    return None if box is None else tile_grid.light_grid(bvh, lights, box)


_GRID_OF = {"lights": ("light_grid", lambda ps: _light_grid(ps.bvh, ps.lights, ps.frame,
                                                            ps.scene)),
            "camera": ("camera_grid", lambda ps: tile_grid.camera_grid(ps.bvh, ps.camera))}


def _refresh_grid(ps: PreparedScene, changed: str, stats: Stats) -> None:
    """Rebuild the tile grid that follows the buffer ``changed`` (lights or camera)."""
    if changed not in _GRID_OF:
        return
    field, build = _GRID_OF[changed]
    with stats.stage("scene_grids"):
        grid = build(ps)
    ps.engine.free(getattr(ps.dev, field))
    setattr(ps.dev, field, tile_grid.upload(ps.engine, grid))


def geometry_key(scene: Scene) -> tuple:
    """Identity of the geometry: the objects' and volumes' shapes and grids (values, not
    object ids). Materials, a volume's coefficients and everything else are left out: a
    prepared scene is refreshed for those (:func:`refresh`), and a method's cached stages
    check what they read themselves."""
    parts = []
    for o in scene.objects:
        parts.append((o.vertices.tobytes(), o.faces.tobytes(),
                      None if o.normals is None else o.normals.tobytes()))
    for v in scene.volumes:
        parts.append((repr(v.key), None if v.mesh is None else v.mesh.vertices.tobytes(),
                      None if v.mesh is None else v.mesh.faces.tobytes(),
                      None if v.grid is None else v.grid.tobytes(), repr(v.grid_bounds)))
    return tuple(parts)


def same_frame(ps: PreparedScene, scene: Scene) -> bool:
    """True when ``scene`` maps to the same normalised frame as ``ps``."""
    f = Frame.for_scene(scene)
    return f.scale == ps.frame.scale and bool(np.all(f.centre == ps.frame.centre))
