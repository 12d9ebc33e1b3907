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

from ...device import AppendBuffer, Engine, launch_appending, structs
from ...io.stats import progress
from ...transport import primitives as prim
from ...transport.view_paths import (
    SAMPLES_PER_LAUNCH,
    DeviceSegments,
    _first_samples,
    _Store,
)
from .grid import VOX_RAY, GridBox
from .photons import Fields, Radiance

MIN_THROUGHPUT = 1e-4     # as view_paths.cl: branches below this (per sample) are dropped


@dataclass
class ViewResult:
    """What :func:`view_pass` returns. ``segments`` (and ``hits``) are on the device,
    sorted by (sample, branch), with pixel offsets; the caller releases them."""

    surface: np.ndarray        # (H, W, 3) directly lit surfaces, seen through the grid too
    inside: np.ndarray         # (H, W, 3) medium radiance from inside the grid (photons)
    segments: DeviceSegments   # structs.VIEW_SEGMENT: the straight medium pieces outside
    counters: dict
    hits: DeviceSegments | None = None   # structs.DIFFUSE_HIT: every diffuse hit (want_hits)

    def release(self) -> None:
        self.segments.release()
        if self.hits is not None:
            self.hits.release()


def tracer_medium(ps, box: GridBox, occlude: bool, density=None):
    """The straight tracers' ``medium`` buffer (``voxel_shadow`` in voxel.cl), on the device
    (the caller frees it): the scene's Medium record and a void record, which with
    ``occlude`` is the grid's occluder (bounded, the grid box: shadow rays crossing it get
    nothing, the photons light those surfaces); without, a scene's density buffer
    (``density``, density.h's layout: its record 1 is the void one) when given, so that
    shadow rays go through the grids."""
    eng = ps.engine
    if density is not None and not occlude:
        return None
    recs = np.zeros(2, structs.MEDIUM)
    recs[0] = ps.medium
    if occlude:
        recs[1]["bounded"] = 1
        recs[1]["bmin"][:3], recs[1]["bmax"][:3] = box.lo, box.hi
    return eng.to_device(recs)


class _Pass:
    """The device state of one view pass: the append buffers the tracers write to, the
    view segments of every launch (a :class:`~clscatter.transport.view_paths._Store`), the camera
    samples' pixel offsets and the two images so far. Images are the only per-pixel data
    read back: each launch's per-work-item values are summed into pixels on the device and
    the image (or a camera launch's band of pixels) is added here (float64)."""

    def __init__(self, ps, box: GridBox, samples_per_launch: int, medium=None,
                 want_hits: bool = False):
        eng = self.eng = ps.engine
        self.ps = ps
        # the straight tracers' medium buffer (tracer_medium: the grid's occluder, or the
        # density grids their shadow rays go through); the caller owns it
        self.medium = {"medium": medium}
        cam = ps.scene.camera
        self.w, self.h, self.spp = cam.width, cam.height, cam.spp
        self.total = self.w * self.h * self.spp
        self.chunk = int(max(1, min(samples_per_launch, self.total)))
        self.bounds = {"gmin": box.lo4(), "gmax": box.hi4(), "want_hits": int(want_hits)}
        self.apps = {"stopped": AppendBuffer(eng, VOX_RAY, self.chunk + 64),
                     "segs": AppendBuffer(eng, structs.VIEW_SEGMENT,
                                          self.chunk * 2 if ps.has_medium else 1),
                     "hits": AppendBuffer(eng, structs.DIFFUSE_HIT,
                                          self.chunk + 64 if want_hits else 1)}
        self.segs = _Store(eng, structs.VIEW_SEGMENT)
        self.hits = _Store(eng, structs.DIFFUSE_HIT)
        self.first = _first_samples(eng, 0, self.total, self.w, self.h, self.spp)
        self.surface = np.zeros((self.h, self.w, 3), np.float64)
        self.inside = np.zeros((self.h, self.w, 3), np.float64)

    def trace(self, kernel: str, n: int, stopped: _Store, surface, **args) -> None:
        """One straight-tracer launch (``voxel_trace_camera`` / ``voxel_trace_rays``) over
        ``n`` work-items: ``surface[i]`` written, the rays it stopped at the grid moved
        into ``stopped``, its segments into :attr:`segs` and its diffuse hits into
        :attr:`hits` (an overflowing launch runs again with its buffers grown: the kernels
        are deterministic)."""
        got = launch_appending(self.eng, "voxel", kernel, n, self.apps, **self.bounds,
                               **args, surface=surface)
        stopped.take(self.apps["stopped"], got["stopped"])
        self.segs.take(self.apps["segs"], got["segs"])
        self.hits.take(self.apps["hits"], got["hits"])

    def by_sample(self, store: _Store) -> DeviceSegments:
        """``store``'s records bucket-sorted by (sample, branch), with pixel offsets."""
        return store.sorted(0, self.total, self.first, self.w, self.h)

    def camera(self, bar) -> DeviceSegments:
        """Every camera sample traced straight up to the grid, launch by launch: adds their
        surface light; returns the rays stopped at the grid, sorted by (sample, branch)."""
        eng, ps = self.eng, self.ps
        store = _Store(eng, VOX_RAY)
        surface = eng.empty(16 * self.chunk)
        args = {**ps.scene_args("voxel", "voxel_trace_camera"), **self.medium,
                "max_depth": ps.scene.render.max_depth,
                "seed": np.uint32(ps.scene.render.seed & 0xFFFFFFFF)}
        pixels = self.surface.reshape(-1, 3)
        try:
            for start in range(0, self.total, self.chunk):
                n = min(self.chunk, self.total - start)
                self.trace("voxel_trace_camera", n, store, surface, **args, sample_offset=start,
                           num_samples=n)
                p0, sums = sample_sums(eng, surface, start, n, self.spp)
                pixels[p0:p0 + len(sums)] += sums
                bar.update(n)
            return self.by_sample(store)
        finally:
            store.release()
            eng.free(surface)

    def round(self, rays: DeviceSegments, march_args: dict, last: bool) -> DeviceSegments | None:
        """One grid round: ``rays`` bent through the grid (their light added to the inside
        image); unless ``last``, the rays it hands back that still carry light go on
        straight (their surface light added, their segments kept). Returns the rays
        stopped at the grid again, sorted (None when none went on)."""
        eng, n = self.eng, rays.count
        light, out = eng.empty(16 * n), eng.empty(n * VOX_RAY.itemsize)
        kept = None
        try:
            self.ps.call("voxel", "voxel_view_march", n, rays=rays.buf, count=n, radiance=light,
                     rays_out=out, **march_args)
            self.inside += rays.accumulate(light)
            if last:
                return None
            kept = keep_rays(eng, out, rays, MIN_THROUGHPUT / self.spp)
            return self.straight(kept) if kept.count else None
        finally:
            eng.free(light, out)
            if kept is not None:
                kept.release()

    def straight(self, rays: DeviceSegments) -> DeviceSegments:
        """``rays`` (handed back by the viewing pass) traced on straight: adds their
        surface light; returns the rays stopped at the grid, sorted."""
        eng, ps = self.eng, self.ps
        store = _Store(eng, VOX_RAY)
        surface = eng.empty(16 * rays.count)
        try:
            self.trace("voxel_trace_rays", rays.count, store, surface,
                       **{**ps.scene_args("voxel", "voxel_trace_rays"), **self.medium},
                       max_depth=ps.scene.render.max_depth, min_weight=MIN_THROUGHPUT / self.spp,
                       rays=rays.buf, count=rays.count)
            self.surface += rays.accumulate(surface)
            return self.by_sample(store)
        finally:
            store.release()
            eng.free(surface)

    def release(self) -> None:
        for app in self.apps.values():
            app.release()
        self.segs.release()
        self.hits.release()
        self.eng.free(self.first)


def sample_sums(eng: Engine, values, start: int, n: int, spp: int) -> tuple[int, np.ndarray]:
    """Per-pixel sums of the float4 ``values`` of camera samples ``[start, start + n)``
    (pixel = sample // spp), on the device: (first pixel, (pixels, 3) float32). Only the
    launch's pixels are read back, so a pass reads one image's worth in all."""
    p0, p1 = start // spp, (start + n - 1) // spp + 1
    offsets = eng.to_device(np.clip(np.arange(p0, p1 + 1) * spp - start, 0, n).astype(np.int32))
    sums = None
    try:
        sums = prim.segment_sums(eng, values, offsets, p1 - p0)
        return p0, eng.read(sums, (p1 - p0, 4), np.float32)[:, :3]
    finally:
        eng.free(offsets, *([sums] if sums is not None else []))


def keep_rays(eng: Engine, rays, sorted_rays: DeviceSegments, min_thr: float) -> DeviceSegments:
    """The throughput filter, on the device: of the ``sorted_rays.count`` VoxRay records in
    ``rays`` (in the order of ``sorted_rays``: by sample, so by pixel), those whose largest
    rgb throughput exceeds ``min_thr``, compacted in order, with their pixel offsets
    (``kept_off[p]`` = rays kept before pixel p's first = the exclusive scan of the keep
    flags at ``sorted_rays.pix_off[p]``)."""
    n = sorted_rays.count
    keep = eng.empty(4 * max(n, 1))
    index = scan = None
    try:
        eng.call("voxel", "vox_keep_flags", n, rays=rays, count=n, min_thr=np.float32(min_thr),
                 keep=keep)
        index, m = prim.compact(eng, keep, n)
        scan, _ = prim.exclusive_scan(eng, keep, n)
        buf = prim.gather(eng, rays, index, m, VOX_RAY.itemsize)
        npix = sorted_rays.width * sorted_rays.height
        off = prim.gather(eng, scan, sorted_rays.pix_off, npix + 1, 4)
    finally:
        eng.free(keep, *(b for b in (index, scan) if b is not None))
    return DeviceSegments(eng, buf, m, off, sorted_rays.width, sorted_rays.height)


def march_args(ps, fields: Fields, radiance: Radiance, test_surfaces: bool) -> dict:
    """``voxel_view_march``'s arguments but the rays and its outputs: the grid, its fields,
    the photons' radiance and the scene's BVH."""
    box = fields.box
    return dict(glo=box.lo4(), ghi=box.hi4(), dims=box.dims4(), h=box.h, n_grid=fields.n,
                grad=fields.grad, sigma_s=fields.sigma_s, kappa=fields.kappa, rad=radiance.rad,
                dirs=radiance.dirs, g_phase=float(ps.medium["g"]), max_steps=4 * sum(box.dims),
                test_surfaces=int(test_surfaces), boundary=fields.boundary,
                max_depth=ps.scene.render.max_depth)


def view_pass(ps, fields: Fields, radiance: Radiance, max_rounds: int = 4,
              show_progress: bool = True, test_surfaces: bool = True,
              samples_per_launch: int = SAMPLES_PER_LAUNCH, medium=None,
              surface_photons: bool = False) -> ViewResult:
    """Trace the whole image through the grid (see the module docstring). ``medium``: a
    device buffer in ``density.h``'s layout for the straight tracers (a scene with density
    volumes: surfaces are then lit through the grids), else the scene's own.
    ``surface_photons``: the photons light the surfaces where the light crosses the grid
    (:func:`tracer_medium`'s occluder for the shadow rays, and every diffuse hit kept in
    :attr:`ViewResult.hits` for the photon estimate); ``medium`` is then not used.

    Everything per camera sample and per ray stays on the device between the passes: the
    rays stopped at the grid are collected launch by launch and bucket-sorted by (sample,
    branch) (appends run in no fixed order; the sort makes every sum below reproducible),
    marched, filtered by throughput (a compaction) and traced on; per-sample and per-ray
    light is summed into pixels there. The view segments of every launch are kept in one
    buffer and returned sorted by (sample, branch) (a
    :class:`~clscatter.transport.view_paths.DeviceSegments`, for the direct and beyond passes).
    Read back: per-pixel sums only (each camera launch's band of pixels, two images per
    round; added here in float64) and the counts.

    Order: (sample, branch) is unique while each branch tree that one launch follows from
    one ray has fewer than 64 branches (``voxel_trace_rays`` numbers a ray's tree from 64 x
    its id), and branch ids are exact float32 sort keys below 2^24, which they stay up to
    ``max_rounds`` = 4 (64^4 = 2^24). Beyond either limit records with equal keys keep
    the order of their launches but, within one launch, their append order (not
    reproducible).
    """
    box: GridBox = fields.box
    args = march_args(ps, fields, radiance, test_surfaces)
    counters = {"voxel_view_rays": 0, "voxel_view_rounds": 0}
    own = tracer_medium(ps, box, surface_photons, medium)
    vp = _Pass(ps, box, samples_per_launch, own if own is not None else medium, surface_photons)
    rays = None
    hits = None
    try:
        with progress(vp.total, "voxel view", show_progress) as bar:
            rays = vp.camera(bar)
        for rnd in range(max_rounds):
            if rays is None or rays.count == 0:
                break
            counters["voxel_view_rays"] += rays.count
            counters["voxel_view_rounds"] = rnd + 1
            nxt = vp.round(rays, args, rnd == max_rounds - 1)
            rays.release()
            rays = nxt
        segments = vp.by_sample(vp.segs)
        if surface_photons:
            hits = vp.by_sample(vp.hits)
    finally:
        if rays is not None:
            rays.release()
        vp.release()
        if own is not None:
            ps.engine.free(own)
    counters["voxel_segments_outside"] = int(segments.count)
    if hits is not None:
        counters["voxel_diffuse_hits"] = int(hits.count)
    return ViewResult(vp.surface.astype(np.float32), vp.inside.astype(np.float32), segments,
                      counters, hits)
