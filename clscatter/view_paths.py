"""View paths: camera rays through specular chains, surface shading, segment buffers.

:func:`trace_view_paths` runs ``view_paths.cl`` over a :class:`~clscatter.prepared.PreparedScene`: one work-item per camera
sample, dielectric hits split into Fresnel-weighted branches, diffuse hits lit directly
by every light (shadow rays, medium attenuation). It returns the surface image and the
buffer of view segments in the medium, which every medium method consumes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import structs
from .device import AppendBuffer
from .prepared import PreparedScene
from .stats import Stats, progress

# camera samples per kernel launch (bounds the segment buffer; drives the progress bar)
SAMPLES_PER_LAUNCH = 1 << 17


@dataclass
class ViewPaths:
    """What the view-path tracer produced for one image."""

    surface: np.ndarray    # (H, W, 3) float32 radiance from directly lit diffuse surfaces
    escaped: np.ndarray    # (H, W, 3) float32 throughput of branches that left the scene
    segments: np.ndarray   # structs.VIEW_SEGMENT array, the medium pieces of all paths
    sample_range: tuple[int, int] | None = None   # the camera samples traced (None: all)


def trace_view_paths(ps: PreparedScene, stats: Stats | None = None, show_progress: bool = True,
                     samples_per_launch: int = SAMPLES_PER_LAUNCH,
                     sample_range: tuple[int, int] | None = None) -> ViewPaths:
    """Run ``view_paths.cl`` over every camera sample of ``ps`` (see the module docstring),
    or over the samples ``[lo, hi)`` of ``sample_range`` only: each sample's paths depend on
    its index alone, so disjoint ranges rendered apart sum to the whole image (how a render
    is split across workers, :mod:`clscatter.cluster`)."""
    stats = stats or Stats()
    eng = ps.engine
    cam = ps.scene.camera
    w, h, spp = cam.width, cam.height, cam.spp
    lo, hi = sample_range if sample_range is not None else (0, w * h * spp)
    lo, hi = max(0, int(lo)), min(w * h * spp, int(hi))
    total = max(hi - lo, 0)
    chunk = int(max(1, min(samples_per_launch, total)))
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
            seg_parts.append(segs.call(
                "view_paths", "trace_view", n, **ps.scene_args("view_paths", "trace_view"),
                cam=ps.dev.camera, max_depth=ps.scene.render.max_depth, seed=seed,
                sample_offset=lo + start, num_samples=n, surface=out_surf, escaped=out_esc))
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
    if total == w * h * spp:
        surf_img = surface[:, :3].reshape(h * w, spp, 3).sum(axis=1).reshape(h, w, 3)
        esc_img = escaped[:, :3].reshape(h * w, spp, 3).sum(axis=1).reshape(h, w, 3)
    else:
        pixels = np.arange(lo, hi) // spp
        surf_img = accumulate_segments(surface, pixels, w, h)
        esc_img = accumulate_segments(escaped, pixels, w, h)
    return ViewPaths(surf_img.astype(np.float32), esc_img.astype(np.float32), segments,
                     sample_range if sample_range is None else (lo, hi))


def trace_diffuse_hits(ps: PreparedScene, samples_per_launch: int = SAMPLES_PER_LAUNCH,
                       sample_range: tuple[int, int] | None = None) -> np.ndarray:
    """Where the camera paths of :func:`trace_view_paths` meet diffuse surfaces.

    The same samples and branches (same seeds), one :data:`~clscatter.structs.DIFFUSE_HIT`
    per branch ending on a diffuse surface, with weight = throughput * albedo / pi: a
    method that knows the irradiance E arriving at a hit adds ``weight * E`` to its pixel
    (surface caustics). Sorted by (sample, branch), so runs are reproducible.
    ``sample_range`` (lo, hi) restricts it to those camera samples, as for the view paths.
    """
    eng = ps.engine
    cam = ps.scene.camera
    lo, hi = sample_range if sample_range is not None else (0, cam.width * cam.height * cam.spp)
    total = max(int(hi) - int(lo), 0)
    chunk = int(max(1, min(samples_per_launch, total)))
    hits = AppendBuffer(eng, structs.DIFFUSE_HIT, chunk)
    seed = np.uint32(ps.scene.render.seed & 0xFFFFFFFF)
    parts: list[np.ndarray] = []
    for start in range(0, total, chunk):
        n = min(chunk, total - start)
        parts.append(hits.call(
            "view_paths", "trace_diffuse_hits", n, **ps.scene_args("view_paths", "trace_diffuse_hits"),
            cam=ps.dev.camera, max_depth=ps.scene.render.max_depth, seed=seed,
            sample_offset=int(lo) + start, num_samples=n))
    hits.release()
    out = np.concatenate(parts) if parts else np.zeros(0, structs.DIFFUSE_HIT)
    out = out[np.lexsort((out["branch"], out["sample"]))]
    eng.note_host(out.nbytes)
    return out


def accumulate_segments(values: np.ndarray, pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Sum per-segment rgb ``values`` (N, >=3) into an (H, W, 3) image by pixel index."""
    img = np.zeros((3, width * height), np.float64)
    for c in range(3):
        img[c] = np.bincount(pixels, weights=values[:, c], minlength=width * height)
    return img.T.reshape(height, width, 3).astype(np.float32)
