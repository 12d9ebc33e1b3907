"""Relighting sessions: change the light, camera, materials or geometry and re-render,
re-running only the voxel pipeline's stages whose inputs changed (Sun et al. 2008, sec. 3
and 6: "only some of the stages need to be executed").

=====================  ===========================================================
call                   stages re-run on the next :meth:`Relighter.frame`
=====================  ===========================================================
``set_camera``         view
``set_light``          lighting, view
``set_volume``         material, lighting, view (ior, sigma_s, sigma_a of a volume)
``set_material``       material, lighting, view (a ``[materials]`` entry; the scene is
                       re-uploaded, its BVH rebuilt; voxelisation is kept)
``set_geometry``       everything (a volume's mesh moved or replaced)
=====================  ===========================================================

``clscatter relight SCENE --frames N --orbit light|camera -o DIR`` is :func:`run_session`.
"""
from __future__ import annotations

import copy
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...device import Engine, get_engine
from ...errors import SceneError
from ...prepared import prepare_scene
from ...scene.frame import camera_struct, light_structs
from ...scene.model import Scene
from ...stats import Stats, progress, write_json
from ..base import configure
from . import Voxel, as_volume_scene
from .pipeline import Pipeline


class Relighter:
    """An interactive session over one scene on one device (a private copy of ``scene``)."""

    def __init__(self, scene: Scene, params: dict | None = None, engine: Engine | None = None,
                 device: str | None = None):
        self.scene = copy.deepcopy(scene)
        table = {**(self.scene.render.params.get("voxel") or {}), **(params or {})}
        self.params = configure(Voxel, table)
        self.engine = engine or get_engine(device)
        self.ps = None
        self.pipe = Pipeline(self.params)
        self.stats: dict[str, Any] = {}
        self.history: list[dict[str, Any]] = []
        self._prepare()

    # ---- state ----
    def _prepare(self) -> None:
        if self.ps is not None:
            self.ps.release()
        vscene = as_volume_scene(self.scene, self.params["voxelise_dielectrics"])
        if not vscene.volumes:
            raise SceneError("volumes", "a relighting session needs [[volumes]] (or dielectric objects)")
        self.ps = prepare_scene(vscene, self.engine)

    def _upload(self, buf, array: np.ndarray) -> None:
        self.engine.cl.enqueue_copy(self.engine.queue, buf, np.ascontiguousarray(array))

    def close(self) -> None:
        """Free the device buffers."""
        self.pipe.release(self.engine)
        if self.ps is not None:
            self.ps.release()
            self.ps = None

    # ---- changes ----
    def set_light(self, index: int = 0, position=None, direction=None, target=None,
                  intensity=None, irradiance=None, cutoff_angle: float | None = None) -> None:
        """Move / re-aim / recolour light ``index`` (scene units, as in the scene file)."""
        L = self.scene.lights[index]
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
                L.power = np.broadcast_to(np.asarray(value, np.float64), (3,)).copy()
        if cutoff_angle is not None:
            L.cutoff_angle = float(cutoff_angle)
        self.ps.scene.lights[index] = L
        self.ps.lights = light_structs(self.ps.scene.lights, self.ps.frame)
        self._upload(self.ps.dev.lights, self.ps.lights)
        self.pipe.invalidate("lighting", self.engine)

    def set_camera(self, origin=None, target=None, up=None, fov: float | None = None) -> None:
        """Move the camera (scene units)."""
        c = self.scene.camera
        for name, v in (("origin", origin), ("target", target), ("up", up)):
            if v is not None:
                setattr(c, name, np.asarray(v, np.float64))
        if fov is not None:
            c.fov = float(fov)
        self.ps.scene.camera = c
        self.ps.camera = camera_struct(c, self.ps.frame)
        self._upload(self.ps.dev.camera, self.ps.camera.reshape(1))

    def set_volume(self, index: int = 0, ior: float | None = None, sigma_s=None, sigma_a=None) -> None:
        """Change volume ``index``'s material (its shape is kept)."""
        v = self.scene.volumes[index]
        if ior is not None:
            v.ior = float(ior)
        if sigma_s is not None:
            v.sigma_s = np.broadcast_to(np.asarray(sigma_s, np.float64), (3,)).copy()
        if sigma_a is not None:
            v.sigma_a = np.broadcast_to(np.asarray(sigma_a, np.float64), (3,)).copy()
        self.ps.scene.volumes[index] = v
        self.pipe.invalidate("material", self.engine)

    def set_material(self, name: str, **values) -> None:
        """Change a ``[materials]`` entry (``albedo``, ``ior``, ``interior_sigma_a``, ...)."""
        mat = self.scene.materials[name]
        for k, v in values.items():
            if not hasattr(mat, k):
                raise SceneError(f"materials.{name}.{k}", "unknown material field")
            cur = getattr(mat, k)
            setattr(mat, k, np.broadcast_to(np.asarray(v, np.float64), (3,)).copy()
                    if isinstance(cur, np.ndarray) else type(cur)(v))
        self._prepare()
        self.pipe.invalidate("material", self.engine)

    def set_geometry(self, index: int = 0, vertices=None, translate=None) -> None:
        """Replace (``vertices``, world space, same faces) or move (``translate``) volume
        ``index``'s mesh; a grid volume's bounds move with ``translate``."""
        v = self.scene.volumes[index]
        if v.mesh is not None:
            if vertices is not None:
                v.mesh.vertices = np.asarray(vertices, np.float64)
            if translate is not None:
                v.mesh.vertices = v.mesh.vertices + np.asarray(translate, np.float64)
        elif translate is not None:
            t = np.asarray(translate, np.float64)
            v.grid_bounds = (v.grid_bounds[0] + t, v.grid_bounds[1] + t)
        self.pipe.invalidate("geometry", self.engine)
        self._prepare()

    # ---- frames ----
    def frame(self, show_progress: bool = False) -> np.ndarray:
        """Render the current state: (H, W, 3) linear radiance. :attr:`stats` says which
        stages ran and how long each took."""
        t = time.perf_counter()
        st = Stats()
        out = self.pipe.update(self.ps, st, show_progress)
        image = out["surface"] + out["medium"]
        image = np.where(np.isfinite(image), image, 0.0).astype(np.float32)
        self.stats = {"ran": list(self.pipe.ran), "stage_seconds": dict(self.pipe.timings),
                      "seconds": time.perf_counter() - t,
                      **{k: v for k, v in self.pipe.counters.items()}}
        self.history.append(self.stats)
        return image


def _rotate_y(p: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    d = np.asarray(p, np.float64) - centre
    return centre + np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])


def run_session(scene: Scene, frames: int, orbit: str, out_dir: str | Path, device: str | None = None,
                show_progress: bool = True, write_png: bool = True) -> dict:
    """Orbit the first light (``orbit="light"``) or the camera (``"camera"``) once around
    the vertical axis through the volumes' centre in ``frames`` frames; write every frame
    (``frame_0000.png`` and ``.npy``) and ``timings.json`` (per frame: stages run, seconds
    per stage, total) into ``out_dir``. Returns the timings object."""
    from ...image import write_image
    if orbit not in ("light", "camera"):
        raise SceneError("--orbit", f"must be 'light' or 'camera' (got {orbit!r})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rl = Relighter(scene, device=device)
    try:
        desc = (rl.pipe.box or _box(rl)).describe(rl.ps.frame)     # scene units
        centre = (np.array(desc["min"]) + np.array(desc["max"])) / 2
        L0 = copy.deepcopy(rl.scene.lights[0]) if rl.scene.lights else None
        cam0 = copy.deepcopy(rl.scene.camera)
        records = []
        with progress(frames, "relight", show_progress) as bar:
            for k in range(frames):
                a = 2 * math.pi * k / max(frames, 1)
                if k > 0 and orbit == "light" and L0 is not None:
                    if L0.position is not None:
                        rl.set_light(0, position=_rotate_y(L0.position, centre, a))
                        if L0.type == "spot":
                            rl.set_light(0, direction=_rotate_y(L0.direction, np.zeros(3), a))
                    else:
                        rl.set_light(0, direction=_rotate_y(L0.direction, np.zeros(3), a))
                elif k > 0 and orbit == "camera":
                    rl.set_camera(origin=_rotate_y(cam0.origin, cam0.target, a))
                img = rl.frame()
                np.save(out / f"frame_{k:04d}.npy", img)
                if write_png:
                    write_image(out / f"frame_{k:04d}.png", img)
                records.append({"frame": k, **{key: rl.stats[key] for key in ("ran", "stage_seconds", "seconds")}})
                bar.update(1)
        result = {"scene": scene.source, "orbit": orbit, "frames": records,
                  "grid": rl.pipe.counters.get("voxel_grid"), "device": rl.engine.name,
                  "params": rl.params}
        write_json(out / "timings.json", result)
        return result
    finally:
        rl.close()


def _box(rl: Relighter):
    from .grid import scene_box
    return scene_box(rl.ps.scene, rl.ps.frame, rl.params["resolution"], rl.params["margin"])
