"""Relighting sessions: change the light, camera, materials or geometry and re-render,
re-running only the stages whose inputs changed (Sun et al. 2008, sec. 3 and 6: "only
some of the stages need to be executed").

A :class:`Relighter` is a :class:`~clscatter.pipeline.session.RenderSession` with the ``voxel``
method and convenience setters; the session keeps the BVH, the device buffers and the view
paths, and the voxel method keeps its grid stages between renders (its slot in the
session, ``PassContext.cache``), so
there is one warm-path mechanism for every method.

=====================  ===========================================================
call                   voxel stages re-run on the next :meth:`Relighter.frame`
=====================  ===========================================================
``set_camera``         view
``set_light``          lighting, view
``set_volume``         material, lighting, view (ior, sigma_s, sigma_a of a volume)
``set_material``       material, lighting, view (a ``[materials]`` entry)
``set_geometry``       every stage (a volume's mesh moved or replaced); the voxelisation
                      of that volume only, while the grid's box stays the same
=====================  ===========================================================

``clscatter relight SCENE --frames N --orbit light|camera -o DIR`` runs the same session
over a light or camera orbit (:mod:`clscatter.animation`).
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np

from ..device import Engine
from ..errors import SceneError
from ..scene.model import Scene
from .session import RenderSession


def _rgb(value) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, np.float64), (3,)).copy()


class Relighter(RenderSession):
    """An interactive voxel-pipeline session over a private copy of ``scene``."""

    def __init__(self, scene: Scene, params: dict | None = None, engine: Engine | None = None,
                 device: str | None = None):
        scene = copy.deepcopy(scene)
        if params:
            scene.render.params["voxel"] = {**(scene.render.params.get("voxel") or {}), **params}
        super().__init__(scene, method="voxel", engine=engine, device=device)
        self.stats: dict[str, Any] = {}
        self.history: list[dict[str, Any]] = []

    def _changed(self, edit) -> None:
        scene = copy.deepcopy(self.scene)
        edit(scene)
        self.update(scene)

    # ---- changes ----
    def set_light(self, index: int = 0, position=None, direction=None, target=None,
                  intensity=None, irradiance=None, cutoff_angle: float | None = None) -> None:
        """Move / re-aim / recolour light ``index`` (scene units, as in the scene file)."""
        def edit(scene: Scene) -> None:
            L = scene.lights[index]
            if position is not None:
                L.position = np.asarray(position, np.float64)
            if target is not None:
                d = np.asarray(target, np.float64) - L.position
                L.direction = d / np.linalg.norm(d)
            if direction is not None:
                d = np.asarray(direction, np.float64)
                L.direction = d / np.linalg.norm(d)
            for value in (intensity, irradiance):
                if value is not None:
                    L.power = _rgb(value)
            if cutoff_angle is not None:
                L.cutoff_angle = float(cutoff_angle)
        self._changed(edit)

    def set_camera(self, origin=None, target=None, up=None, fov: float | None = None) -> None:
        """Move the camera (scene units)."""
        def edit(scene: Scene) -> None:
            for name, v in (("origin", origin), ("target", target), ("up", up)):
                if v is not None:
                    setattr(scene.camera, name, np.asarray(v, np.float64))
            if fov is not None:
                scene.camera.fov = float(fov)
        self._changed(edit)

    def set_volume(self, index: int = 0, ior: float | None = None, sigma_s=None, sigma_a=None) -> None:
        """Change volume ``index``'s material (its shape is kept)."""
        def edit(scene: Scene) -> None:
            v = scene.volumes[index]
            if ior is not None:
                v.ior = float(ior)
            if sigma_s is not None:
                v.sigma_s = _rgb(sigma_s)
            if sigma_a is not None:
                v.sigma_a = _rgb(sigma_a)
        self._changed(edit)

    def set_material(self, name: str, **values) -> None:
        """Change a ``[materials]`` entry (``albedo``, ``ior``, ``interior_sigma_a``, ...)."""
        def edit(scene: Scene) -> None:
            mat = scene.materials[name]
            for k, v in values.items():
                if not hasattr(mat, k):
                    raise SceneError(f"materials.{name}.{k}", "unknown material field")
                cur = getattr(mat, k)
                setattr(mat, k, _rgb(v) if isinstance(cur, np.ndarray) else type(cur)(v))
            for o in scene.objects:          # objects hold the material itself
                if o.material.name == name:
                    o.material = mat
        self._changed(edit)

    def set_geometry(self, index: int = 0, vertices=None, translate=None) -> None:
        """Replace (``vertices``, world space, same faces) or move (``translate``) volume
        ``index``'s mesh; a grid volume's bounds move with ``translate``."""
        def edit(scene: Scene) -> None:
            v = scene.volumes[index]
            if v.mesh is not None:
                if vertices is not None:
                    v.mesh.vertices = np.asarray(vertices, np.float64)
                if translate is not None:
                    v.mesh.vertices = v.mesh.vertices + np.asarray(translate, np.float64)
            elif translate is not None:
                t = np.asarray(translate, np.float64)
                v.grid_bounds = (v.grid_bounds[0] + t, v.grid_bounds[1] + t)
        self._changed(edit)

    # ---- frames ----
    def frame(self, show_progress: bool = False) -> np.ndarray:
        """Render the current state: (H, W, 3) linear radiance. :attr:`stats` says which
        voxel stages ran (``ran``), their seconds, the session's stages and the total."""
        res = self.render(show_progress=show_progress)
        st = res.stats
        self.stats = {"ran": list(st.get("voxel_stages_run", [])),
                      "stage_seconds": dict(st.get("voxel_stage_seconds", {})),
                      "session_stages_run": st["stages_run"], "reused": st["reused"],
                      "seconds": st["seconds_total"],
                      **{k: v for k, v in st.items() if k.startswith("voxel_")}}
        self.history.append(self.stats)
        return res.image
