"""View paths: camera rays through specular chains, surface shading, segment buffers.

:func:`trace_view_paths` runs ``view_paths.cl`` over a :class:`~clscatter.transport.prepared.PreparedScene`: one work-item per camera
sample, dielectric hits split into Fresnel-weighted branches, diffuse hits lit directly
by every light (shadow rays, medium attenuation). It returns the surface image and the
buffer of view segments in the medium, which every medium method consumes.
"""
from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np

from ..device import AppendBuffer, Engine, launch_appending, structs
from ..io.stats import Stats, progress
from . import primitives as prim
from .prepared import PreparedScene

# camera samples per kernel launch (bounds the segment buffer; drives the progress bar)
SAMPLES_PER_LAUNCH = 1 << 17


class DeviceSegments:
    """Records of camera paths on the device (view segments, or diffuse hits), sorted by
    (camera sample, branch), with the offsets of each pixel's run: ``buf`` holds ``count``
    :data:`~clscatter.device.structs.VIEW_SEGMENT` (or :data:`~clscatter.device.structs.DIFFUSE_HIT`)
    records, those of pixel ``p`` are ``[pix_off[p], pix_off[p + 1])``. A method
    that writes one float4 per segment turns it into an image with :meth:`accumulate`
    (summed on the device in segment order: deterministic), so nothing per segment comes
    back to the host. The buffers are freed with :meth:`release` or when this object is
    collected."""

    def __init__(self, engine: Engine, buf, count: int, pix_off, width: int, height: int):
        self.engine, self.buf, self.count, self.pix_off = engine, buf, int(count), pix_off
        self.width, self.height = int(width), int(height)
        self._owned = [buf, pix_off]          # freed together (derived buffers join them)
        self._derived: dict = {}
        self._free = weakref.finalize(self, _free_all, engine, self._owned)

    def derived(self, key: str, build: Callable[[], tuple[list, object]]):
        """What a method derives from these segments alone (no light, no parameter), built
        once: ``build()`` returns ``(device buffers, value)``; the buffers live as long as
        the segments (a warm re-render after a light change reuses them)."""
        if key not in self._derived:
            bufs, value = build()
            self._owned.extend(bufs)
            self._derived[key] = value
        return self._derived[key]

    def accumulate(self, values) -> np.ndarray:
        """Sum a device buffer of ``count`` float4 (one per segment) into an (H, W, 3)
        float32 image, on the device; only the image is read back."""
        return self.pixel_sums(values)[:, :3].reshape(self.height, self.width, 3)

    def pixel_sums(self, values) -> np.ndarray:
        """The per-pixel sums of all four lanes of ``values`` (``count`` float4), (H W, 4)
        float32: :meth:`accumulate` with the fourth lane too (a method's per-segment
        count, e.g. march steps, comes back summed per pixel)."""
        eng = self.engine
        npix = self.width * self.height
        img = prim.segment_sums(eng, values, self.pix_off, npix)
        try:
            return eng.read(img, (npix, 4), np.float32)
        finally:
            eng.free(img)

    def release(self) -> None:
        self._free()
        self._derived.clear()


def _free_all(engine: Engine, bufs: list) -> None:
    engine.free(*bufs)
    bufs.clear()


class ViewPaths:
    """What the view-path tracer produced for one image.

    ``surface`` (H, W, 3) float32: radiance of directly lit diffuse surfaces; ``escaped``
    (H, W, 3): throughput of branches that left the scene; the view segments in the medium,
    sorted by (sample, branch), either on the device (:attr:`device`, how the tracer leaves
    them) or as a host array. :attr:`segments` reads a device copy back once, for the
    methods that work on the host; :meth:`on_device` uploads a host array once, for those
    that work on the device. ``hits``: the diffuse hits of the same paths
    (:data:`~clscatter.device.structs.DIFFUSE_HIT`, a :class:`DeviceSegments`) when the tracer was
    asked to keep them, else None.
    """

    def __init__(self, surface: np.ndarray, escaped: np.ndarray,
                 segments: np.ndarray | None = None,
                 sample_range: tuple[int, int] | None = None,
                 device: DeviceSegments | None = None):
        self.surface = surface
        self.escaped = escaped
        self.sample_range = sample_range    # the camera samples traced (None: all)
        self.device = device
        self.hits: DeviceSegments | None = None
        self._host = segments
        if segments is None and device is None:
            self._host = np.zeros(0, structs.VIEW_SEGMENT)

    def __len__(self) -> int:
        return self.device.count if self._host is None else len(self._host)

    @property
    def segments(self) -> np.ndarray:
        """The segments as a host :data:`~clscatter.device.structs.VIEW_SEGMENT` array (read from
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
        """Free the device copy of the segments and the hits (the host copy of the
        segments, if read, stays)."""
        if self.hits is not None:
            self.hits.release()
            self.hits = None
        if self.device is not None:
            self.device.release()
            self.device = None
            if self._host is None:
                self._host = np.zeros(0, structs.VIEW_SEGMENT)


def _sample_span(ps: PreparedScene, sample_range, per_launch: int) -> tuple[int, int, int, int]:
    """The camera samples to trace: (lo, hi) clipped to the image, their count and the
    samples per launch."""
    cam = ps.scene.camera
    n = cam.width * cam.height * cam.spp
    lo, hi = sample_range if sample_range is not None else (0, n)
    lo, hi = max(0, int(lo)), min(n, int(hi))
    total = max(hi - lo, 0)
    return lo, hi, total, int(max(1, min(per_launch, total)))


class _Store:
    """Records appended launch after launch (an :class:`AppendBuffer` per launch), kept
    on the device in one buffer that grows by doubling."""

    def __init__(self, eng: Engine, dtype: np.dtype):
        self.eng, self.dtype = eng, np.dtype(dtype)
        self.rec = self.dtype.itemsize
        self.buf, self.cap, self.count = eng.empty(self.rec), 1, 0

    def take(self, app: AppendBuffer, got: int) -> None:
        eng, rec = self.eng, self.rec
        if self.count + got > self.cap:
            self.cap = max(2 * self.cap, self.count + got, 1)
            bigger = eng.empty(rec * self.cap)
            if self.count:
                eng.cl.enqueue_copy(eng.queue, bigger, self.buf, byte_count=rec * self.count)
            eng.free(self.buf)
            self.buf = bigger
        if got:
            eng.cl.enqueue_copy(eng.queue, self.buf, app.buf, byte_count=rec * got,
                                dst_offset=rec * self.count)
        self.count += got

    def sorted(self, lo: int, total: int, first, w: int, h: int) -> DeviceSegments:
        """The records bucket-sorted by (sample - lo, branch) on the device (appends run
        in no fixed order; the sort makes runs reproducible), with pixel offsets: the
        sample offsets at each pixel's first sample (``first``)."""
        eng, n = self.eng, self.count
        keys, branch = eng.empty(4 * max(n, 1)), eng.empty(4 * max(n, 1))
        perm = samp_off = None
        words = self.rec // 4
        try:
            eng.call("view_paths", "record_keys", n, records=self.buf, stride=words,
                     sample_word=self.dtype.fields["sample"][1] // 4,
                     branch_word=self.dtype.fields["branch"][1] // 4, n=n, base=lo,
                     keys=keys, branch=branch)
            perm, samp_off = prim.bucket_sort(eng, keys, n, max(total, 1), fkey=branch)
            buf = prim.gather(eng, self.buf, perm, n, self.rec)
            pix_off = prim.gather(eng, samp_off, first, w * h + 1, 4)
        finally:
            eng.free(keys, branch, *(b for b in (perm, samp_off) if b is not None))
        return DeviceSegments(eng, buf, n, pix_off, w, h)

    def release(self) -> None:
        self.eng.free(self.buf)


def _first_samples(eng: Engine, lo: int, total: int, w: int, h: int, spp: int):
    """Device int32 (H W + 1): pixel p's samples are [p spp, (p + 1) spp), clipped to the
    range traced and relative to its start."""
    first = np.clip(np.arange(w * h + 1, dtype=np.int64) * spp - lo, 0, total)
    return eng.to_device(first.astype(np.int32))


def trace_view_paths(ps: PreparedScene, stats: Stats | None = None, show_progress: bool = True,
                     samples_per_launch: int = SAMPLES_PER_LAUNCH,
                     sample_range: tuple[int, int] | None = None,
                     keep_hits: bool = False, program: str = "view_paths") -> ViewPaths:
    """Run ``view_paths.cl`` over every camera sample of ``ps`` (see the module docstring),
    or over the samples ``[lo, hi)`` of ``sample_range`` only: each sample's paths depend on
    its index alone, so disjoint ranges rendered apart sum to the whole image (how a render
    is split across workers, :mod:`clscatter.cluster`). With ``keep_hits`` the same launch
    also records the diffuse hits (:attr:`ViewPaths.hits`, on the device; what
    :func:`shade_hits` relights after a light change). ``program`` names a build of
    ``view_paths.cl`` with its medium functions replaced and the same ``trace_view``
    signature (``density_view``: the view paths of a scene with density grids).

    Everything per sample stays on the device: the segments are appended per launch into
    one buffer, bucket-sorted by (sample, branch), and the per-sample surface and escaped
    radiance are summed into pixels there. Read back: the two images and the counts.
    """
    stats = stats or Stats()
    with stats.stage("view_paths"), progress(_sample_span(ps, sample_range, 1)[2], "view paths",
                                             show_progress) as bar:
        images, segs, hits = _trace(ps, sample_range, samples_per_launch, shade=True,
                                    want_segs=True, want_hits=keep_hits, bar=bar,
                                    program=program)
    lo, hi, total, _ = _sample_span(ps, sample_range, samples_per_launch)
    stats.set(view_segments=int(segs.count), camera_samples=int(total))
    paths = ViewPaths(images[0], images[1], None, sample_range if sample_range is None else (lo, hi),
                      segs)
    paths.hits = hits
    return paths


def _trace(ps: PreparedScene, sample_range, per_launch: int, shade: bool, want_segs: bool,
           want_hits: bool, bar=None, program: str = "view_paths", interior: bool = False):
    """The ``trace_view`` launches over the samples of ``sample_range``: the (surface,
    escaped) images when ``shade`` (else None), and the segments and diffuse hits, each
    sorted by (sample, branch) as a :class:`DeviceSegments` when wanted (else None).
    ``interior``: the segments are the pieces inside glass that scatters instead of those
    in the medium (``view_paths.cl`` built with ``SEGMENT_REGIONS = 2``)."""
    eng = ps.engine
    cam = ps.scene.camera
    w, h, spp = cam.width, cam.height, cam.spp
    lo, hi, total, chunk = _sample_span(ps, sample_range, per_launch)
    per_sample = 16 * max(total, 1) if shade else 16
    out_surf, out_esc = eng.empty(per_sample), eng.empty(per_sample)
    want_segs = want_segs and (interior or ps.has_medium)
    defines = {"SEGMENT_REGIONS": 2} if interior else None
    wanted = {"segs": (want_segs, structs.VIEW_SEGMENT, 2 * chunk),
              "hits": (want_hits, structs.DIFFUSE_HIT, chunk)}
    apps = {k: AppendBuffer(eng, dt, cap if on else 1) for k, (on, dt, cap) in wanted.items()}
    stores = {k: _Store(eng, wanted[k][1]) for k in apps}
    seed = np.uint32(ps.scene.render.seed & 0xFFFFFFFF)
    first = None
    try:
        for start in range(0, total, chunk):
            n = min(chunk, total - start)
            got = launch_appending(
                eng, program, "trace_view", n, apps, defines,
                **ps.scene_args(program, "trace_view"), max_depth=ps.scene.render.max_depth,
                    seed=seed, sample_offset=lo + start,
                num_samples=n, shade=int(shade), want_segs=int(want_segs),
                want_hits=int(want_hits), out_offset=start if shade else 0, surface=out_surf,
                escaped=out_esc)
            for k in apps:
                stores[k].take(apps[k], got[k])
            if bar is not None:
                bar.update(n)
        first = _first_samples(eng, lo, total, w, h, spp)
        images = (_pixel_image(eng, out_surf, first, w, h),
                  _pixel_image(eng, out_esc, first, w, h)) if shade else None
        segs = stores["segs"].sorted(lo, total, first, w, h) if want_segs or shade else None
        hits = stores["hits"].sorted(lo, total, first, w, h) if want_hits else None
        return images, segs, hits
    finally:
        for k in apps:
            apps[k].release()
            stores[k].release()
        eng.free(out_surf, out_esc, *([first] if first is not None else []))


def _pixel_image(eng: Engine, per_sample, first, w: int, h: int) -> np.ndarray:
    """Sum per-sample float4 values into an (H, W, 3) image on the device."""
    img = prim.segment_sums(eng, per_sample, first, w * h)
    try:
        return eng.read(img, (w * h, 4), np.float32)[:, :3].reshape(h, w, 3)
    finally:
        eng.free(img)


def trace_interior_segments(ps: PreparedScene, sample_range: tuple[int, int] | None = None,
                            samples_per_launch: int = SAMPLES_PER_LAUNCH) -> DeviceSegments:
    """The view segments inside dielectrics whose interior scatters (a material's
    ``interior_sigma_s``), on the device, sorted by (sample, branch), with pixel offsets.

    The same camera paths as :func:`trace_view_paths` (same seeds and branching; the
    samples of ``sample_range``), traced again with ``view_paths.cl`` built with
    ``SEGMENT_REGIONS = 2``: every straight piece of a branch inside such an object, from
    where it enters (or reflects inside) to where it meets the surface again, with
    weight = the throughput at its start times 1 / ior^2 (radiance scattered inside
    reaches a camera in air divided by n^2; a camera inside glass has its own n^2 in the
    throughput; the interior extinction beyond the start is the estimator's) and its
    region in ``a.w``
    (:func:`~clscatter.device.structs.segment_regions`: the material index + 1). A
    separate trace, so the shared segments every medium method reads stay the pieces in
    the medium alone."""
    return _trace(ps, sample_range, samples_per_launch, shade=False, want_segs=True,
                  want_hits=False, interior=True)[1]


def trace_diffuse_hits_on_device(ps: PreparedScene, samples_per_launch: int = SAMPLES_PER_LAUNCH,
                                 sample_range: tuple[int, int] | None = None) -> DeviceSegments:
    """The diffuse hits of :func:`trace_diffuse_hits`, left on the device, sorted by
    (sample, branch), with pixel offsets (a :class:`DeviceSegments` of
    :data:`~clscatter.device.structs.DIFFUSE_HIT` records): what :func:`shade_hits` relights.
    (A render that traces the view paths anyway records them in the same launch:
    ``trace_view_paths(..., keep_hits=True)``.)"""
    return _trace(ps, sample_range, samples_per_launch, shade=False, want_segs=False,
                  want_hits=True)[2]


def shade_hits(ps: PreparedScene, hits: DeviceSegments) -> np.ndarray:
    """Direct light of every light at the diffuse hits ``hits`` (shadow rays, medium
    attenuation: the shading ``trace_view`` does inline), summed into an (H, W, 3) image
    on the device: the view paths' ``surface`` after a light change, without tracing the
    camera paths again."""
    eng = ps.engine
    out = eng.empty(16 * max(hits.count, 1))
    try:
        ps.call("view_paths", "shade_hits", hits.count, hits=hits.buf, n=hits.count, out=out)
        return hits.accumulate(out)
    finally:
        eng.free(out)


def trace_diffuse_hits(ps: PreparedScene, samples_per_launch: int = SAMPLES_PER_LAUNCH,
                       sample_range: tuple[int, int] | None = None) -> np.ndarray:
    """Where the camera paths of :func:`trace_view_paths` meet diffuse surfaces, as a host
    array (the ray map and photon map build host structures from them).

    The same samples and branches (same seeds), one :data:`~clscatter.device.structs.DIFFUSE_HIT`
    per branch ending on a diffuse surface, with weight = throughput * albedo / pi: a
    method that knows the irradiance E arriving at a hit adds ``weight * E`` to its pixel
    (surface caustics). Sorted by (sample, branch) on the device, so runs are
    reproducible. ``sample_range`` (lo, hi) restricts it to those camera samples, as for
    the view paths.
    """
    hits = trace_diffuse_hits_on_device(ps, samples_per_launch, sample_range)
    try:
        out = hits.engine.read(hits.buf, hits.count, structs.DIFFUSE_HIT) if hits.count else \
            np.zeros(0, structs.DIFFUSE_HIT)
    finally:
        hits.release()
    ps.engine.note_host(out.nbytes)
    return out


def accumulate_segments(values: np.ndarray, pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Sum per-segment rgb ``values`` (N, >=3) into an (H, W, 3) image by pixel index, on
    the host: the NumPy reference that tests and tools compare device sums with (renders
    sum on the device: :meth:`DeviceSegments.accumulate`)."""
    img = np.zeros((3, width * height), np.float64)
    for c in range(3):
        img[c] = np.bincount(pixels, weights=values[:, c], minlength=width * height)
    return img.T.reshape(height, width, 3).astype(np.float32)
