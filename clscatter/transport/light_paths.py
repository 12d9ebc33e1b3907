"""Light paths: lighting rays from every light through specular chains -> segment buffers.

:func:`trace_light_paths` runs ``light_paths.cl`` (one work-item per lighting ray) and
returns the :data:`~clscatter.device.structs.LIGHT_SEGMENT` pieces inside the medium, each with
the flux it carries at its start. The caustic methods (``lsg``, ``vpm``) consume them.

Emission, in the normalised frame (so fluxes are in normalised units, consistent with
the frame's rescaled intensities; radiance estimates come out unchanged):

* point light, intensity I: power 4 pi I, directions stratified over the sphere;
* spot light: power 2 pi (1 - cos cutoff) I, directions stratified over the cone;
* directional light, irradiance E: rays start on a rectangle facing the light that
  covers the medium bounds and the geometry; power E * area.

Rays are shared among lights in proportion to their power; every ray of a light carries
the same flux, power / rays.

``targeted=True`` (caustic passes, which keep only light that met a mirror or glass):
every light emits only towards the bounding spheres of the specular objects, each ray
weighted by its exact pdf (:mod:`clscatter.transport.emission`); lights are then shared by the
power they send that way. ``LightPaths.specular_rays`` counts, per light, the rays whose
first hit is a mirror or dielectric.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device import AppendBuffer, structs
from ..io.stats import Stats, progress
from .emission import Emission, emission, specular_spheres
from .emission import targets as emission_targets
from .prepared import PreparedScene


def scatters_inside(ps: PreparedScene) -> bool:
    """True when a dielectric material of ``ps`` scatters light inside (interior_sigma_s)."""
    m = ps.materials
    if m is None or not len(m):
        return False
    return bool(np.any((m["type"] == structs.MAT_DIELECTRIC)
                       & (m["interior_sigma_s"][:, :3].max(axis=1) > 0)))


def ray_counts(ps: PreparedScene, num_rays: int, targeted: bool = False) -> np.ndarray:
    """Lighting rays per light, proportional to emitted power (largest remainder); with
    ``targeted``, to the power sent towards the specular objects."""
    if ps.num_lights == 0:
        return np.zeros(0, np.int64)
    if targeted:
        sph = specular_spheres(ps)
        p = np.array([emission_targets(ps, i, sph).power.mean() for i in range(ps.num_lights)])
    else:
        p = np.array([emission(ps, i).power.mean() for i in range(ps.num_lights)])
    if p.sum() <= 0:
        return np.zeros(ps.num_lights, np.int64)
    share = p / p.sum() * num_rays
    counts = np.floor(share).astype(np.int64)
    rest = num_rays - counts.sum()
    counts[np.argsort(-(share - counts))[:rest]] += 1
    counts[(counts == 0) & (p > 0)] = 1
    return counts


@dataclass
class LightPaths:
    segments: np.ndarray        # structs.LIGHT_SEGMENT
    rays: np.ndarray            # rays traced per light
    flux_per_ray: np.ndarray    # (lights, 3) (targeted: the mean, power / rays)
    specular_rays: np.ndarray | None = None   # per light: rays whose first hit is specular


def chunk_rays(counts: np.ndarray, k: int, n: int, interleaved: bool = False) -> int:
    """Rays that chunk ``(k, n)`` of :func:`trace_light_paths` traces, of ``counts`` rays
    per light (every light's share)."""
    if interleaved:
        return int(sum(max(0, (int(c) - k + n - 1) // n) for c in counts))
    return int(sum(int(c) * (k + 1) // n - int(c) * k // n for c in counts))


def interleaved_parts(rays: int, most: int) -> int:
    """How many interleaved chunks :func:`trace_light_paths` splits ``rays`` into so that
    none holds more than about ``most``: an odd number (see there), 1 when all fit."""
    parts = max(1, math.ceil(rays / max(int(most), 1)))
    return parts + (parts % 2 == 0 and parts > 1)


def trace_light_paths(ps: PreparedScene, num_rays: int, stats: Stats | None = None,
                      show_progress: bool = True, rays_per_launch: int = 1 << 16,
                      chunk: tuple[int, int] | None = None, pieces: bool = False,
                      targeted: bool = False, seed_offset: int = 0,
                      interior: bool = False, interleaved: bool = False) -> LightPaths:
    """Trace ``num_rays`` lighting rays (shared among lights by power).

    ``chunk = (k, n)`` traces only the k-th of n equal parts of every light's rays (the
    same rays a full trace would give), so callers can bound memory and sum results: with
    ``interleaved`` rays k, k + n, k + 2n, ... of every light, else a contiguous run of
    them. A ray's Hammersley point is (index / count, radical inverse of the index): a
    contiguous run is a band of the first coordinate, and an interleaved chunk spreads
    over all of a light's directions (or its rectangle) like the whole set only for odd
    ``n`` (an even stride fixes the index's low bits, so the radical inverse stays in a
    band: a wedge of directions), so an even ``n`` is refused (:func:`interleaved_parts`
    gives an odd one).
    ``pieces=True`` returns, instead of the medium segments, the
    :data:`~clscatter.device.structs.RAY_PIECE` on which every branch ends (diffuse or black
    surface, or leaving the scene box) with the flux arriving there, with or without a
    medium (the surface-caustic methods: ``raymap``, ``photonmap``).
    ``targeted=True`` emits only towards the specular objects (:mod:`clscatter.transport.emission`;
    for passes that keep only light with a specular bounce). ``seed_offset`` selects an
    independent set of rays (progressive passes). ``interior=True`` (line space gathering)
    also keeps the pieces inside dielectrics whose interior scatters (a material's
    ``interior_sigma_s``), each tagged with its region (:func:`~clscatter.device.structs.segment_regions`:
    material index + 1; 0 for the pieces in the medium) and carrying the flux at its
    start (the interior extinction up to it included), with or without a medium.
    """
    if interleaved and chunk is not None and chunk[1] > 1 and chunk[1] % 2 == 0:
        raise ValueError(f"interleaved chunks of an even count ({chunk[1]}) are wedges of "
                         "directions: use an odd count (interleaved_parts)")
    stats = stats or Stats()
    eng = ps.engine
    counts = ray_counts(ps, num_rays, targeted)
    spheres = specular_spheres(ps) if targeted else []
    spec = np.zeros(ps.num_lights, np.int64)
    parts: list[np.ndarray] = []
    fluxes = np.zeros((ps.num_lights, 3))
    launch = max(1, int(rays_per_launch))
    record = structs.RAY_PIECE if pieces else structs.LIGHT_SEGMENT
    interior = bool(interior) and not pieces and scatters_inside(ps)
    defines = {"RAY_PIECES": 1} if pieces else {"SEGMENT_REGIONS": 3} if interior else None
    wanted = pieces or ps.has_medium or interior
    segs = AppendBuffer(eng, record, launch * 2) if wanted else None
    seed = np.uint32((ps.scene.render.seed * 2654435761 + 11 + 0x632BE5AB * int(seed_offset))
                     & 0xFFFFFFFF)
    no_targets = eng.to_device(np.zeros((1, 4), np.float32))
    no_offsets = eng.to_device(np.zeros(2, np.int32))
    flags = eng.empty(4 * launch)
    mine = int(counts.sum()) if chunk is None else chunk_rays(counts, *chunk, interleaved)
    with stats.stage("light_paths"), progress(mine, "light paths", show_progress) as bar:
        for li in range(ps.num_lights):
            n_li = int(counts[li])
            em = emission(ps, li)
            flux = em.power / max(n_li, 1)
            tg_buf, off_buf, n_tg = no_targets, no_offsets, 0
            if targeted:
                tg = emission_targets(ps, li, spheres)
                flux = tg.power / max(n_li, 1)
                if tg.rect is not None:
                    em = Emission(tg.power, tg.rect)
                elif len(tg.cones) and n_li > 0 and wanted:
                    offsets = np.concatenate([[0], np.cumsum(tg.counts(n_li))]).astype(np.int32)
                    tg_buf, off_buf = eng.to_device(tg.cones), eng.to_device(offsets)
                    n_tg = len(tg.cones)
            fluxes[li] = flux
            if n_li == 0 or not wanted:
                continue
            # cone mode: the kernel weights each ray itself from the intensity
            flux_arg = ps.lights[li]["power"][:3].astype(np.float64) if n_tg else flux
            lo, hi, stride = 0, n_li, 1
            if chunk is not None:
                k, n = chunk
                lo, hi, stride = (k, n_li, n) if interleaved else (n_li * k // n, n_li * (k + 1) // n, 1)
            start = lo
            while start < hi:
                m = min(launch, (hi - start + stride - 1) // stride)
                parts.append(segs.call(
                    "light_paths", "trace_light", m, defines,
                    **ps.scene_args("light_paths", "trace_light"), light_index=li,
                    max_depth=ps.scene.render.max_depth, seed=seed, ray_offset=start,
                    ray_stride=stride, num_rays=m, rays_total=n_li, flux_per_ray=flux_arg, rect_origin=em.rect[0],
                    rect_u=em.rect[1], rect_v=em.rect[2], targets=tg_buf,
                    target_offsets=off_buf, num_targets=n_tg, ray_flags=flags))
                spec[li] += int(eng.read(flags, m, np.int32).sum())
                start += m * stride
                bar.update(m)
            if n_tg:
                eng.free(tg_buf, off_buf)
    if segs is not None:
        segs.release()
    eng.free(no_targets, no_offsets, flags)
    out = np.concatenate(parts) if parts else np.zeros(0, record)
    out = out[np.lexsort((out["branch"], out["ray"], out["light"]))]
    eng.note_host(out.nbytes)
    stats.add("light_rays", mine)
    stats.add("light_ray_pieces" if pieces else "light_segments", int(len(out)))
    return LightPaths(out, counts, fluxes, spec)


