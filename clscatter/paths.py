"""View paths: camera rays through specular chains, surface shading, segment buffers.

:func:`prepare_scene` turns a scene into device buffers once (normalised frame, triangle
soup, BVH, structs); :func:`trace_view_paths` runs ``paths.cl``: one work-item per camera
sample, dielectric hits split into Fresnel-weighted branches, diffuse hits lit directly
by every light (shadow rays, medium attenuation). It returns the surface image and the
buffer of view segments in the medium, which every medium method consumes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import structs
from .accel.bvh import BVH, build_bvh
from .device import AppendBuffer, Engine
from .scene.frame import Frame, camera_struct, light_structs, medium_struct, triangle_soup
from .scene.model import Scene
from .stats import Stats, progress

# camera samples per kernel launch (bounds the segment buffer; drives the progress bar)
SAMPLES_PER_LAUNCH = 1 << 17


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


@dataclass
class ViewPaths:
    """What the view-path tracer produced for one image."""

    surface: np.ndarray    # (H, W, 3) float32 radiance from directly lit diffuse surfaces
    escaped: np.ndarray    # (H, W, 3) float32 throughput of branches that left the scene
    segments: np.ndarray   # structs.VIEW_SEGMENT array, the medium pieces of all paths


def trace_view_paths(ps: PreparedScene, stats: Stats | None = None, show_progress: bool = True,
                     samples_per_launch: int = SAMPLES_PER_LAUNCH) -> ViewPaths:
    """Run ``paths.cl`` over every camera sample of ``ps`` (see the module docstring)."""
    stats = stats or Stats()
    eng = ps.engine
    cam = ps.scene.camera
    w, h, spp = cam.width, cam.height, cam.spp
    total = w * h * spp
    kern = eng.kernel("paths", "trace_view")
    chunk = int(min(samples_per_launch, total))
    surface = np.zeros((total, 4), np.float32)
    escaped = np.zeros((total, 4), np.float32)
    seg_parts: list[np.ndarray] = []
    out_surf = eng.empty(chunk * 16)
    out_esc = eng.empty(chunk * 16)
    segs = AppendBuffer(eng, structs.VIEW_SEGMENT, chunk * 2 if ps.has_medium else 1)
    seed = np.uint32(ps.scene.render.seed & 0xFFFFFFFF)
    with stats.stage("view_paths"), progress(total, "view paths", show_progress) as bar:
        start = 0
        while start < total:
            n = min(chunk, total - start)
            seg_parts.append(segs.launch(
                kern, n, ps.buf["nodes"], ps.buf["tris"], ps.buf["normals"], ps.buf["tri_mat"],
                ps.buf["materials"], ps.buf["lights"], np.int32(ps.num_lights), ps.buf["medium"],
                ps.buf["camera"], np.int32(ps.scene.render.max_depth), seed, np.int32(start),
                np.int32(n), out_surf, out_esc))
            surface[start:start + n] = eng.read(out_surf, (chunk, 4), np.float32)[:n]
            escaped[start:start + n] = eng.read(out_esc, (chunk, 4), np.float32)[:n]
            start += n
            bar.update(n)
    eng.free(out_surf, out_esc)
    segs.release()
    segments = np.concatenate(seg_parts) if seg_parts else np.zeros(0, structs.VIEW_SEGMENT)
    # the kernel appends in no fixed order: sort so that runs are reproducible
    segments = segments[np.lexsort((segments["branch"], segments["sample"]))]
    eng.note_host(surface.nbytes + escaped.nbytes + segments.nbytes)
    stats.set(view_segments=int(len(segments)), camera_samples=int(total))
    surf_img = surface[:, :3].reshape(h * w, spp, 3).sum(axis=1).reshape(h, w, 3)
    esc_img = escaped[:, :3].reshape(h * w, spp, 3).sum(axis=1).reshape(h, w, 3)
    return ViewPaths(surf_img.astype(np.float32), esc_img.astype(np.float32), segments)


def accumulate_segments(values: np.ndarray, pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Sum per-segment rgb ``values`` (N, >=3) into an (H, W, 3) image by pixel index."""
    img = np.zeros((3, width * height), np.float64)
    for c in range(3):
        img[c] = np.bincount(pixels, weights=values[:, c], minlength=width * height)
    return img.T.reshape(height, width, 3).astype(np.float32)
