"""The viewing pass and its join with the engine's straight view paths.

Every camera sample is traced as the engine traces it (``view_paths.cl``: same rays, same
seeds, same surface shading and specular splitting), with one difference: a branch whose
straight ray enters the grid box before its next surface stops at the box
(``voxel_trace_camera``). Its straight medium piece up to the box goes to the usual view
segment buffer; the branch itself (throughput and attenuation so far) goes to the viewing
pass (``voxel_view_march``), which bends it through the grid at one-voxel steps and adds
the in-scattered light stored by the photons. Where the curved ray leaves the grid, or meets
a surface inside it, the straight tracer takes over again (``voxel_trace_rays``), and so on
for a few rounds (a mirror may send a ray back into the grid).

So every piece of every view path lies either outside the grid (straight; its medium
segments get direct single scattering from ``raymarch``, the engine's direct pass) or
inside it (curved; all its light from the photons, which carry direct light and light bent
by the volumes alike). Nothing is counted twice and nothing is left out, up to what the
two sides each neglect (see the method's documentation).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import structs
from ...device import AppendBuffer, Engine
from ...stats import progress
from ...view_paths import SAMPLES_PER_LAUNCH
from .grid import VOX_RAY, GridBox
from .photons import Fields, Radiance

MIN_THROUGHPUT = 1e-4     # as view_paths.cl: branches below this (per sample) are dropped


@dataclass
class ViewResult:
    surface: np.ndarray        # (H, W, 3) directly lit surfaces, seen through the grid too
    inside: np.ndarray         # (H, W, 3) medium radiance from inside the grid (photons)
    segments: np.ndarray       # structs.VIEW_SEGMENT: the straight medium pieces outside
    counters: dict


def _run_tracer(eng: Engine, program_kernel: tuple[str, str], n: int, args: dict,
                segs: AppendBuffer, stop_cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Launch a tracer kernel with its two appended outputs (stopped rays, segments);
    grows the stopped-ray buffer and relaunches when it overflowed (kernels are
    deterministic). Returns (surface per work-item, stopped rays, segments)."""
    prog, kern = program_kernel
    surface = eng.empty(16 * n)
    count = eng.empty(4)
    try:
        while True:
            stopped = eng.empty(stop_cap * VOX_RAY.itemsize)
            eng.cl.enqueue_fill_buffer(eng.queue, count, np.zeros(1, np.int32), 0, 4)
            got_segs = segs.call(prog, kern, n, **args, surface=surface, stopped=stopped,
                                 max_stopped=stop_cap, stop_count=count)
            got = int(eng.read(count, 1, np.int32)[0])
            if got <= stop_cap:
                rays = eng.read(stopped, got, VOX_RAY) if got else np.zeros(0, VOX_RAY)
                eng.free(stopped)
                return eng.read(surface, (n, 4), np.float32), rays, got_segs
            eng.free(stopped)
            stop_cap = int(got * 1.25) + 16
    finally:
        eng.free(surface, count)


def view_pass(ps, fields: Fields, radiance: Radiance, max_rounds: int = 4,
              show_progress: bool = True, test_surfaces: bool = True) -> ViewResult:
    """Trace the whole image through the grid (see the module docstring)."""
    eng = ps.engine
    box: GridBox = fields.box
    cam = ps.scene.camera
    W, H, spp = cam.width, cam.height, cam.spp
    total = W * H * spp
    chunk = int(min(SAMPLES_PER_LAUNCH, total))
    segs = AppendBuffer(eng, structs.VIEW_SEGMENT, chunk * 2 if ps.has_medium else 1)
    seed = np.uint32(ps.scene.render.seed & 0xFFFFFFFF)
    gmin, gmax = box.lo4(), box.hi4()
    surface = np.zeros((3, W * H), np.float64)
    inside = np.zeros((3, W * H), np.float64)
    seg_parts: list[np.ndarray] = []
    ray_parts: list[np.ndarray] = []
    counters = {"voxel_view_rays": 0, "voxel_view_rounds": 0}
    base = ps.scene_args("voxel", "voxel_trace_camera")
    with progress(total, "voxel view", show_progress) as bar:
        for start in range(0, total, chunk):
            n = min(chunk, total - start)
            surf, rays, sg = _run_tracer(eng, ("voxel", "voxel_trace_camera"), n, {
                **base, "cam": ps.dev.camera, "max_depth": ps.scene.render.max_depth, "seed": seed,
                "sample_offset": start, "num_samples": n, "gmin": gmin, "gmax": gmax}, segs, n + 64)
            pix = np.arange(start, start + n) // spp
            for c in range(3):
                surface[c] += np.bincount(pix, weights=surf[:, c], minlength=W * H)
            seg_parts.append(sg)
            ray_parts.append(rays)
            bar.update(n)
    rays = np.concatenate(ray_parts) if ray_parts else np.zeros(0, VOX_RAY)
    march_args = dict(glo=gmin, ghi=gmax, dims=box.dims4(), h=box.h, n_grid=fields.n,
                      grad=fields.grad, sigma_s=fields.sigma_s, kappa=fields.kappa,
                      rad=radiance.rad, dirs=radiance.dirs, g_phase=float(ps.medium["g"]),
                      max_steps=4 * sum(box.dims), nodes=ps.dev.nodes, tris=ps.dev.tris,
                      test_surfaces=int(test_surfaces))
    trace_base = ps.scene_args("voxel", "voxel_trace_rays")
    for rnd in range(max_rounds):
        if len(rays) == 0:
            break
        counters["voxel_view_rays"] += len(rays)
        counters["voxel_view_rounds"] = rnd + 1
        n = len(rays)
        rin, rout, L = eng.to_device(rays), eng.empty(n * VOX_RAY.itemsize), eng.empty(16 * n)
        try:
            eng.call("voxel", "voxel_view_march", n, rays=rin, count=n, radiance=L, rays_out=rout,
                     **march_args)
            Lh = eng.read(L, (n, 4), np.float32)
            out = eng.read(rout, n, VOX_RAY)
        finally:
            eng.free(rin, rout, L)
        for c in range(3):
            inside[c] += np.bincount(rays["pixel"], weights=Lh[:, c], minlength=W * H)
        out = out[out["thr"][:, :3].max(axis=1) > MIN_THROUGHPUT / spp]
        if len(out) == 0 or rnd == max_rounds - 1:
            break
        rbuf = eng.to_device(out)
        try:
            surf, rays, sg = _run_tracer(eng, ("voxel", "voxel_trace_rays"), len(out), {
                **trace_base, "max_depth": ps.scene.render.max_depth,
                "min_weight": MIN_THROUGHPUT / spp, "rays": rbuf, "count": len(out),
                "gmin": gmin, "gmax": gmax}, segs, len(out) + 64)
        finally:
            eng.free(rbuf)
        for c in range(3):
            surface[c] += np.bincount(out["pixel"], weights=surf[:, c], minlength=W * H)
        seg_parts.append(sg)
    segs.release()
    segments = np.concatenate(seg_parts) if seg_parts else np.zeros(0, structs.VIEW_SEGMENT)
    segments = segments[np.lexsort((segments["branch"], segments["sample"]))]
    counters["voxel_segments_outside"] = int(len(segments))
    img = lambda a: a.T.reshape(H, W, 3).astype(np.float32)
    return ViewResult(img(surface), img(inside), segments, counters)

