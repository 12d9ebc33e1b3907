"""View paths: camera rays through specular chains, surface shading, segment buffers.

:func:`trace_view_paths` runs ``view_paths.cl`` over a :class:`~clscatter.prepared.PreparedScene`: one work-item per camera
sample, dielectric hits split into Fresnel-weighted branches, diffuse hits lit directly
by every light (shadow rays, medium attenuation). It returns the surface image and the
buffer of view segments in the medium, which every medium method consumes.
"""
from __future__ import annotations

import weakref

import numpy as np

from . import primitives as prim
from . import structs
from .device import AppendBuffer, Engine
from .prepared import PreparedScene
from .stats import Stats, progress

# camera samples per kernel launch (bounds the segment buffer; drives the progress bar)
SAMPLES_PER_LAUNCH = 1 << 17


class DeviceSegments:
    """View segments on the device, sorted by (camera sample, branch), with the offsets of
    each pixel's run: ``buf`` holds ``count`` :data:`~clscatter.structs.VIEW_SEGMENT`
    records, the segments of pixel ``p`` are ``[pix_off[p], pix_off[p + 1])``. A method
    that writes one float4 per segment turns it into an image with :meth:`accumulate`
    (summed on the device in segment order: deterministic), so nothing per segment comes
    back to the host. The buffers are freed with :meth:`release` or when this object is
    collected."""

    def __init__(self, engine: Engine, buf, count: int, pix_off, width: int, height: int):
        self.engine, self.buf, self.count, self.pix_off = engine, buf, int(count), pix_off
        self.width, self.height = int(width), int(height)
        self._free = weakref.finalize(self, engine.free, buf, pix_off)

    def accumulate(self, values) -> np.ndarray:
        """Sum a device buffer of ``count`` float4 (one per segment) into an (H, W, 3)
        float32 image, on the device; only the image is read back."""
        eng = self.engine
        npix = self.width * self.height
        img = prim.segment_sums(eng, values, self.pix_off, npix)
        try:
            out = eng.read(img, (npix, 4), np.float32)
        finally:
            eng.free(img)
        return out[:, :3].reshape(self.height, self.width, 3)

    def release(self) -> None:
        self._free()


class ViewPaths:
    """What the view-path tracer produced for one image.

    ``surface`` (H, W, 3) float32: radiance of directly lit diffuse surfaces; ``escaped``
    (H, W, 3): throughput of branches that left the scene; the view segments in the medium,
    sorted by (sample, branch), either on the device (:attr:`device`, how the tracer leaves
    them) or as a host array. :attr:`segments` reads a device copy back once, for the
    methods that work on the host; :meth:`on_device` uploads a host array once, for those
    that work on the device.
    """

    def __init__(self, surface: np.ndarray, escaped: np.ndarray,
                 segments: np.ndarray | None = None,
                 sample_range: tuple[int, int] | None = None,
                 device: DeviceSegments | None = None):
        self.surface = surface
        self.escaped = escaped
        self.sample_range = sample_range    # the camera samples traced (None: all)
        self.device = device
        self._host = segments
        if segments is None and device is None:
            self._host = np.zeros(0, structs.VIEW_SEGMENT)

    def __len__(self) -> int:
        return self.device.count if self._host is None else len(self._host)

    @property
    def segments(self) -> np.ndarray:
        """The segments as a host :data:`~clscatter.structs.VIEW_SEGMENT` array (read from
        the device on first use)."""
        if self._host is None:
            d = self.device
            self._host = d.engine.read(d.buf, d.count, structs.VIEW_SEGMENT) if d.count else \
                np.zeros(0, structs.VIEW_SEGMENT)
        return self._host

    def on_device(self, engine: Engine, width: int, height: int) -> DeviceSegments:
        """The segments on ``engine``'s device with their pixel offsets (uploaded once when
        they were given as a host array; a host array in no pixel order is sorted by pixel
        first, stably)."""
        if self.device is None:
            segs = self._host
            pix = segs["pixel"]
            if len(pix) > 1 and np.any(pix[1:] < pix[:-1]):
                segs = segs[np.argsort(pix, kind="stable")]
                pix = segs["pixel"]
                self._host = segs
            off = np.searchsorted(pix, np.arange(width * height + 1)).astype(np.int32)
            self.device = DeviceSegments(engine, engine.to_device(segs), len(segs),
                                         engine.to_device(off), width, height)
        return self.device

    def release(self) -> None:
        """Free the device copy of the segments (the host copy, if read, stays)."""
        if self.device is not None:
            self.device.release()
            self.device = None
            if self._host is None:
                self._host = np.zeros(0, structs.VIEW_SEGMENT)


def trace_view_paths(ps: PreparedScene, stats: Stats | None = None, show_progress: bool = True,
                     samples_per_launch: int = SAMPLES_PER_LAUNCH,
                     sample_range: tuple[int, int] | None = None) -> ViewPaths:
    """Run ``view_paths.cl`` over every camera sample of ``ps`` (see the module docstring),
    or over the samples ``[lo, hi)`` of ``sample_range`` only: each sample's paths depend on
    its index alone, so disjoint ranges rendered apart sum to the whole image (how a render
    is split across workers, :mod:`clscatter.cluster`).

    Everything per sample stays on the device: the segments are appended per launch into
    one buffer, bucket-sorted by (sample, branch) (the appends run in no fixed order; the
    sort makes runs reproducible), and the per-sample surface and escaped radiance are
    summed into pixels there. Read back: the two images and the segment count.
    """
    stats = stats or Stats()
    eng = ps.engine
    cam = ps.scene.camera
    w, h, spp = cam.width, cam.height, cam.spp
    lo, hi = sample_range if sample_range is not None else (0, w * h * spp)
    lo, hi = max(0, int(lo)), min(w * h * spp, int(hi))
    total = max(hi - lo, 0)
    chunk = int(max(1, min(samples_per_launch, total)))
    rec = structs.VIEW_SEGMENT.itemsize
    out_surf = eng.empty(16 * max(total, 1))
    out_esc = eng.empty(16 * max(total, 1))
    segs = AppendBuffer(eng, structs.VIEW_SEGMENT, chunk * 2 if ps.has_medium else 1)
    store, cap, count = eng.empty(rec), 1, 0
    seed = np.uint32(ps.scene.render.seed & 0xFFFFFFFF)
    scratch = []
    try:
        with stats.stage("view_paths"), progress(total, "view paths", show_progress) as bar:
            for start in range(0, total, chunk):
                n = min(chunk, total - start)
                got = segs.call_on_device(
                    "view_paths", "trace_view", n,
                    **ps.scene_args("view_paths", "trace_view"), cam=ps.dev.camera,
                    max_depth=ps.scene.render.max_depth, seed=seed, sample_offset=lo + start,
                    num_samples=n, out_offset=start, surface=out_surf, escaped=out_esc)
                if count + got > cap:               # grow the store (amortised doubling)
                    cap = max(2 * cap, count + got, 1)
                    bigger = eng.empty(rec * cap)
                    if count:
                        eng.cl.enqueue_copy(eng.queue, bigger, store, byte_count=rec * count)
                    eng.free(store)
                    store = bigger
                if got:
                    eng.cl.enqueue_copy(eng.queue, store, segs.buf, byte_count=rec * got,
                                        dst_offset=rec * count)
                count += got
                bar.update(n)
            # pixel p's samples are [p * spp, (p + 1) * spp) clipped to the range traced
            first = np.clip(np.arange(w * h + 1, dtype=np.int64) * spp - lo, 0, total)
            first_buf = eng.to_device(first.astype(np.int32))
            scratch.append(first_buf)
            surf_img = _pixel_image(eng, out_surf, first_buf, w, h)
            esc_img = _pixel_image(eng, out_esc, first_buf, w, h)
            device = _sort_segments(eng, store, count, lo, total, first_buf, w, h)
    finally:
        segs.release()
        eng.free(out_surf, out_esc, store, *scratch)
    stats.set(view_segments=int(count), camera_samples=int(total))
    return ViewPaths(surf_img, esc_img, None, sample_range if sample_range is None else (lo, hi),
                     device)


def _pixel_image(eng: Engine, per_sample, first, w: int, h: int) -> np.ndarray:
    """Sum per-sample float4 values into an (H, W, 3) image on the device."""
    img = prim.segment_sums(eng, per_sample, first, w * h)
    try:
        return eng.read(img, (w * h, 4), np.float32)[:, :3].reshape(h, w, 3)
    finally:
        eng.free(img)


def _sort_segments(eng: Engine, store, count: int, lo: int, total: int, first, w: int,
                   h: int) -> DeviceSegments:
    """Bucket-sort ``count`` view segments in ``store`` by (sample - lo, branch) on the
    device; the pixel offsets are the sample offsets at each pixel's first sample."""
    rec = structs.VIEW_SEGMENT.itemsize
    keys, branch = eng.empty(4 * max(count, 1)), eng.empty(4 * max(count, 1))
    perm = samp_off = None
    try:
        eng.call("view_paths", "view_segment_keys", count, segs=store, n=count, base=lo,
                 keys=keys, branch=branch)
        perm, samp_off = prim.bucket_sort(eng, keys, count, max(total, 1), fkey=branch)
        buf = prim.gather(eng, store, perm, count, rec)
        pix_off = prim.gather(eng, samp_off, first, w * h + 1, 4)
    finally:
        eng.free(keys, branch, *(b for b in (perm, samp_off) if b is not None))
    return DeviceSegments(eng, buf, count, pix_off, w, h)


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
    # host sort: the hits feed host-built structures (ray map, photon map) on the host
    out = out[np.lexsort((out["branch"], out["sample"]))]
    eng.note_host(out.nbytes)
    return out


def accumulate_segments(values: np.ndarray, pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Sum per-segment rgb ``values`` (N, >=3) into an (H, W, 3) image by pixel index, on
    the host: for methods whose per-segment values are host arrays already (LSG, VPM,
    voxel); device methods use :meth:`DeviceSegments.accumulate`."""
    img = np.zeros((3, width * height), np.float64)
    for c in range(3):
        img[c] = np.bincount(pixels, weights=values[:, c], minlength=width * height)
    return img.T.reshape(height, width, 3).astype(np.float32)
