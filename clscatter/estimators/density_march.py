"""Heterogeneous media by ray marching: a scene's density grids on the device, and the
``raymarch`` estimator over them (docs/scene_format.md, "What a volume means": Density).

The grids go to the device in the layout of ``cl_kernels/shared/density.h``: one buffer
holding the scene's Medium record (its ``present`` flags the grids behind it), a void
Medium record, a :data:`DENSITY_HEAD`, one :data:`DENSITY_GRID` per density volume and
the float32 values of them all. Bound as the kernels' ``medium``, it turns
``view_paths.cl`` into ``density_view.cl`` (segments across the grid boxes, view and
shadow rays attenuated through them: the smoke's shadows on surfaces) and ``raymarch.cl``
into ``density_march.cl`` (sigma_s(x), exact optical depths, mid-stratum samples).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..device import structs
from ..errors import SceneError
from ..io.stats import Stats
from ..scene.grids import MAX_DENSITY_VOLUMES
from ..scene.model import Scene
from ..scene.normalised import Frame
from ..transport.prepared import PreparedScene
from ..transport.view_paths import trace_view_paths
from .segment_march import march_segments

F4 = (np.float32, 4)

#: the bits of Medium.present in a density buffer (density.h)
MEDIUM_HOMOGENEOUS, MEDIUM_DENSITY = 1, 2

DENSITY_GRID = structs.register_struct("density.h", "DensityGrid", np.dtype([
    ("bmin", *F4), ("bmax", *F4), ("sigma_s", *F4), ("kappa", *F4),
    ("nx", np.int32), ("ny", np.int32), ("nz", np.int32), ("offset", np.int32),
], align=True))
DENSITY_HEAD = structs.register_struct("density.h", "DensityHead", np.dtype([
    ("count", np.int32), ("pad0", np.int32), ("pad1", np.int32), ("pad2", np.int32),
], align=True))


def has_density(scene: Scene) -> bool:
    """True when ``scene`` has a volume with a density grid."""
    return bool(scene.density_volumes())


def density_buffer(scene: Scene, frame: Frame, medium: np.ndarray) -> np.ndarray:
    """The host bytes (uint8) of ``scene``'s density buffer in ``frame`` (density.h's
    layout), ``medium`` being the prepared scene's Medium record. Raises
    :class:`SceneError` for more than ``MAX_DENSITY_VOLUMES`` density volumes or coefficients
    beyond float32 in the normalised frame (the loader refuses more volumes first)."""
    vols = scene.density_volumes()
    if len(vols) > MAX_DENSITY_VOLUMES:
        raise SceneError(f"{vols[MAX_DENSITY_VOLUMES].key}.density", f"at most "
                         f"{MAX_DENSITY_VOLUMES} density volumes per scene")
    rec = np.array(medium, structs.MEDIUM).reshape(1).copy()
    rec["present"] = (MEDIUM_HOMOGENEOUS if medium["present"] else 0) | MEDIUM_DENSITY
    rec["g"] = scene.medium.g if scene.medium is not None else 0.0
    void = np.zeros(1, structs.MEDIUM)
    head = np.zeros(1, DENSITY_HEAD)
    head["count"] = len(vols)
    grids = np.zeros(len(vols), DENSITY_GRID)
    offset = 0
    for rec_g, v in zip(grids, vols):
        ss = frame.coefficient(v.sigma_s)
        kappa = frame.coefficient(np.asarray(v.sigma_s) + np.asarray(v.sigma_a))
        peak = float(np.max(v.density)) * float(np.max(kappa))
        if not np.isfinite(peak) or peak > float(np.finfo(np.float32).max):
            raise SceneError(f"{v.key}.sigma_a", "density times the coefficients times the "
                             "scene's size is beyond float32's range, in which the device "
                             "computes")
        rec_g["bmin"] = structs.vec4(frame.point(v.grid_bounds[0]))
        rec_g["bmax"] = structs.vec4(frame.point(v.grid_bounds[1]))
        rec_g["sigma_s"] = structs.vec4(ss)
        rec_g["kappa"] = structs.vec4(kappa)
        rec_g["nx"], rec_g["ny"], rec_g["nz"] = v.density.shape
        rec_g["offset"] = offset
        offset += int(v.density.size)
    values = [np.ascontiguousarray(v.density, np.float32).ravel() for v in vols]
    parts = [rec, void, head, grids, *values]
    return np.concatenate([np.frombuffer(p.tobytes(), np.uint8) for p in parts])


@dataclass
class DensityDevice:
    """A density buffer on the device and the host bytes it was made from (to tell
    whether a re-render can keep it)."""

    host: np.ndarray
    buf: object
    engine: object

    def release(self) -> None:
        if self.buf is not None:
            self.engine.free(self.buf)
            self.buf = None


def upload(ps: PreparedScene, kept: DensityDevice | None = None) -> DensityDevice:
    """``ps``'s density buffer on its device: ``kept`` when it holds the same bytes (a
    re-render that changed no grid, coefficient or medium), else a fresh upload (``kept``
    is released)."""
    host = density_buffer(ps.scene, ps.frame, ps.medium)
    if kept is not None and kept.buf is not None and kept.engine is ps.engine \
            and np.array_equal(kept.host, host):
        return kept
    if kept is not None:
        kept.release()
    return DensityDevice(host, ps.engine.to_device(host), ps.engine)


def density_scene(ps: PreparedScene, dens: DensityDevice) -> PreparedScene:
    """``ps`` with the density buffer bound as its ``medium`` (device) and the first
    record as its host Medium (``present`` set: view segments are wanted)."""
    head = np.frombuffer(dens.host[:structs.MEDIUM.itemsize].tobytes(), structs.MEDIUM)[0]
    return dataclasses.replace(ps, medium=head, dev=dataclasses.replace(ps.dev, medium=dens.buf))


def march_density(ps: PreparedScene, dens: DensityDevice, steps: int, stats: Stats,
                  show_progress: bool = True, per_launch: int = 65536,
                  sample_range: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Single scattering of direct light in a scene with density grids: its own view
    paths (``density_view``), then ``steps`` samples per segment and light
    (``density_march``). Returns (medium, surface) images, (H, W, 3) float32: the light
    scattered in the media, and the directly lit surfaces seen and lit through them (which
    replaces the session's surface term)."""
    dps = density_scene(ps, dens)
    paths = trace_view_paths(dps, stats, show_progress, sample_range=sample_range,
                             program="density_view")
    try:
        segs = paths.device
        cam = ps.scene.camera
        if segs is None or segs.count == 0 or ps.num_lights == 0:
            return np.zeros((cam.height, cam.width, 3), np.float32), paths.surface
        medium = march_segments(dps, segs, steps, stats, show_progress, per_launch,
                                program="density_march")
        stats.set(density_segments=int(segs.count))
        return medium, paths.surface
    finally:
        paths.release()
