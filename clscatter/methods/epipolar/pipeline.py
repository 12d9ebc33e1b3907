"""One light through the epipolar pipeline: maps, rectification, integration, lookup.

:func:`render_light` takes the primary view segments (one per camera sample) and returns,
for each, the radiance single-scattered by the medium from one directional or spot light
towards the start of the segment (the caller multiplies by the segment weight), plus the
mask of segments inside the epipole ring, which the caller ray-marches.

Two ways to read the integrated result back (``lookup``):

``segment`` (default)
    Every camera sample is an event of the sweep in the two slices around its direction,
    at its own beta and with its own medium interval ``[t_a, t_b]`` (from the view-path
    tracer, so the depth is exact); the two results are blended linearly in the slice
    angle. The rectified "depth map" is then the samples themselves, and unrectification
    is that blend. Depth discontinuities are never interpolated across.
``grid`` (the paper)
    A camera depth map is ray traced at pixel centres and rectified into ``rays`` view
    rays per slice (uniform in beta); the sweep integrates those; each sample then takes
    the bilinear blend of the four grid rays around its (alpha, beta) (``epi_unrectify``).

Accuracy control. Before the sweep, per light and frame, the error of the
result is estimated on held-out camera samples (svd.py: the SVD with the tree's float32
sums, the sum over light rays, reading samples in neighbouring slices), and the cheapest
setting within ``svd_tolerance`` (RMS relative error, sources in quadrature) is used:
slice spacing halved up to twice, terms 4 / 8 / 16, the plain or referenced
formulation with 1 or 16 groups of slices, 1 / 2 / 4 x the light rays. If none is,
:class:`SVDFallback` hands the light to ``raymarch``; ``--stats`` lists the estimate,
the choice and every setting tried (``epipolar_lights``). The ring around the epipole
(or anti-epipole) is an angle (``ring_degrees``, 2 by default as in the paper), ray
marched, and blended with the sweep over a band beyond it (``ring_band``).
Spot lights: one perspective shadow map up to 60 degrees, five cube faces up to 90
(maps.py).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ...device import structs
from ...io.stats import Stats, progress
from ...transport import primitives as prim
from ...transport.prepared import PreparedScene
from ...transport.view_paths import ViewPaths
from ..base import Fallback
from . import geometry as geo
from .maps import setup_shadow_map, trace_depth_map, trace_shadow_map
from .settings import MIN_LIGHT_RAYS, Settings
from .svd import (
    REF_NODES,
    accepts,
    decompose,
    float32_bound,
    float32_error,
    heldout_error,
    node_extremes,
    references,
    riemann_rel,
    rms,
    slice_error,
    summarize,
    view_entry,
)


class SVDFallback(Fallback):
    """The SVD's estimated error stays above the tolerance at the most terms allowed: the
    light is ray marched instead (``info``: the estimate, for --stats)."""


class LightOutput:
    """One light's result on the device: ``values_buf`` (n float4) the swept radiance of
    each view segment towards its start (times 1 - ring weight; the caller multiplies by
    the segment weight), ``ring_buf`` (n float) the ring weight of each segment (the share
    the caller ray-marches), ``ring_samples`` how many have one > 0. :attr:`values`,
    :attr:`ring` and :attr:`ring_weight` read them back (tests, tools)."""

    def __init__(self, engine, n: int, values_buf, ring_buf, info: dict, ring_samples: int):
        self.engine, self.n, self.info = engine, int(n), info
        self.values_buf, self.ring_buf, self.ring_samples = values_buf, ring_buf, int(ring_samples)

    @property
    def values(self) -> np.ndarray:
        return self.engine.read(self.values_buf, (self.n, 4), np.float32)[:, :3].astype(np.float64)

    @property
    def ring_weight(self) -> np.ndarray:
        return self.engine.read(self.ring_buf, self.n, np.float32).astype(np.float64)

    @property
    def ring(self) -> np.ndarray:
        return self.ring_weight > 0.0

    def release(self) -> None:
        self.engine.free(self.values_buf, self.ring_buf)


def ring_weights(beta: np.ndarray, front: bool, radius: float, band: float) -> np.ndarray:
    """Weight of the ray-marched value of each sample around the epipole: 1 within the
    ring (angle from the epipole direction below ``radius``; the anti-epipole when the
    light is behind the camera), falling smoothly (smoothstep) to 0 across the band
    ``radius .. radius (1 + band)``, 0 beyond. In the band the sweep's value gets the
    complementary weight, so the two meet without a seam: where they differ (the sweep's
    SVD and slice spacing degrade towards the epipole, the ray marcher's steps do not),
    the difference is spread over the band instead of a step along a circle."""
    ang = np.asarray(beta, np.float64) if front else math.pi - np.asarray(beta, np.float64)
    if radius <= 0.0:
        return np.zeros(len(ang))
    outer = radius * (1.0 + max(band, 0.0))
    x = np.clip((outer - ang) / max(outer - radius, 1e-12), 0.0, 1.0)
    w = x * x * (3.0 - 2.0 * x)
    return np.where(ang < radius, 1.0, np.where(ang < outer, w, 0.0))


def segment_dirs(segs: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Unit directions (N, 4) float32 of primary view segments (from the eye)."""
    v = segs["b"][:, :3].astype(np.float64) - eye
    v /= np.maximum(np.linalg.norm(v, axis=1), 1e-30)[:, None]
    out = np.zeros((len(v), 4), np.float32)
    out[:, :3] = v
    return out


def start_defines(svd_terms: int, kappa) -> dict[str, int]:
    """The epipolar program's defines a render starts with: ``EPI_NT`` SVD terms (more
    if the estimate asks) and ``EPI_NCH``, 1 channel for a grey medium (rgb ``kappa`` all
    equal), else 3. Every launch outside render_light uses them too, so one program is
    built per render (and loaded at start-up: :meth:`Epipolar.programs`)."""
    k = np.broadcast_to(np.asarray(kappa, np.float64), 3)
    return {"EPI_NT": int(svd_terms), "EPI_NCH": 1 if np.all(k == k[0]) else 3}


def _auto(st: Settings, cam: geo.CameraGeom) -> Settings:
    """``st`` with its automatic (0) sizes resolved for this image."""
    big = max(cam.width, cam.height)
    return dataclasses.replace(
        st,
        # one light ray per pixel: halving from two changed the built-in scenes' images by
        # relMSE <= 8e-7 at 640 x 480 (the shadow map's texels dominate the error); at
        # least MIN_LIGHT_RAYS, so that the estimate's escalation (up to 4x) reaches
        # enough for thick media in small images
        light_rays=st.light_rays if st.light_rays > 0 else max(big, MIN_LIGHT_RAYS),
        # the map must resolve the occluders whatever the image size: at least 1024
        shadow_map=st.shadow_map if st.shadow_map > 0 else min(4096, max(1024, 2 * big)),
        depth_map=st.depth_map if st.depth_map > 0 else cam.width,
        batch_slices=max(1, st.batch_slices))


def _spacing(st: Settings, axis: geo.Axis, cam: geo.CameraGeom) -> float:
    """Slice spacing in pixels: 1 (the half-pixel bound), or scaled to ``st.slices``."""
    if st.slices <= 0:
        return 1.0
    P, _ = geo.epipole(axis, cam)
    n1 = len(geo.slice_points(P, cam.width, cam.height, 1.0))
    return max(n1 / st.slices, 1e-3)


def render_light(ps: PreparedScene, li: int, segs, st: Settings, stats: Stats,
                 show_progress: bool = True) -> LightOutput:
    """Radiance from light ``li`` scattered towards the start of each primary view segment
    of ``segs`` (:class:`~clscatter.transport.view_paths.DeviceSegments`, or a host segment array,
    uploaded; deeper segments get 0).

    Per-sample work stays on the device: the samples' slice coordinates (``epi_samples``),
    ring weights and the live list (``epi_ring``, compaction), the views' beta ranges and
    t_a envelopes for the SVD's references (``epi_view_ranges``/``epi_view_nodes``), the
    sweep's events (each sample once, bucket-sorted by its first slice then beta; a slice
    sweeps its run merged with the previous slice's), the blend back to the samples
    (``epi_sample_values``) and the error estimate's light-ray sums (``epi_riemann``).
    The host reads back: a few hundred held-out rows for the error estimate and their
    light-ray sums, the slices' event offsets (S + 1 ints: batch sizes), per-group ranges
    and envelope nodes, and counters. The grid lookup (not the
    default) reads the live segments back to trace its direction table on the host.
    Raises :class:`~clscatter.methods.base.Fallback` where the light must be ray marched."""
    cam = geo.CameraGeom.from_struct(ps.camera)
    if isinstance(segs, np.ndarray):
        segs = ViewPaths(None, None, segs).on_device(ps.engine, cam.width, cam.height)
    run = _LightRun(ps, li, segs, _auto(st, cam), cam, stats)
    ok = False
    try:
        run.rectify()
        if run.live.count == 0:
            ok = True
            return run.output()
        run.maps()
        run.events()
        run.svd()
        run.integrate(show_progress)
        run.unrectify()
        ok = True
    finally:
        run.release(keep_output=ok)
    run.finish_info()
    return run.output()


class _LightRun:
    """One light's epipolar pass, stage by stage (:func:`render_light`): the state the
    stages hand on (slices, maps, events, the SVD's tables) and the device buffers they
    allocate, all freed by :meth:`release` except the two results."""

    def __init__(self, ps: PreparedScene, li: int, segs, st: Settings,
                 cam: geo.CameraGeom, stats: Stats):
        self.ps, self.li, self.segs, self.st, self.cam, self.stats = ps, li, segs, st, cam, stats
        self.eng = ps.engine
        self.axis = geo.make_axis(ps.lights[li], cam.origin)
        self.n = segs.count
        self.box = geo.medium_box(ps.medium)
        if self.box is None and not self.axis.spot:
            raise Fallback("a directional light needs a bounded medium")
        self.kappa = np.asarray(ps.medium["kappa"][:3], np.float64)
        self.defines = start_defines(st.svd_terms, self.kappa)
        self.nch = self.defines["EPI_NCH"]
        self.g_hg = float(ps.medium["g"])
        self.d = int(st.light_rays)
        self.bufs: list = []
        self.values_buf = self.eng.zeros(16 * max(self.n, 1))
        self.wr_buf = self.eng.zeros(4 * max(self.n, 1))
        self.R = 0
        self.depth = None
        self.dw = self.dh = 0

    def up(self, arr):
        b = self.eng.to_device(arr)
        self.bufs.append(b)
        return b

    def scratch(self, nbytes: int):
        b = self.eng.empty(nbytes)
        self.bufs.append(b)
        return b

    def release(self, keep_output: bool) -> None:
        self.eng.free(*self.bufs)
        self.bufs = []
        if not keep_output:
            self.eng.free(self.values_buf, self.wr_buf)

    def output(self) -> LightOutput:
        return LightOutput(self.eng, self.n, self.values_buf, self.wr_buf, self.info,
                           self.live.ring)

    # ---- slices, and every sample's coordinates (rectification of the view rays) ----
    def rectify(self) -> None:
        """The slices and each sample's place in them. The slice spacing is halved (twice
        at most) while reading the samples in their neighbouring slices is estimated to be
        off by more than a quarter of the tolerance (thick media lit through grazing box
        faces)."""
        st, cam, n = self.st, self.cam, self.n
        spacing = _spacing(st, self.axis, cam)
        self.ring_rad = math.radians(st.epipole_ring)
        ring_px = self.ring_rad / cam.pixel_angle()          # for the slices' beta ranges
        self.geo_buf, self.idx_buf = self.scratch(16 * max(n, 1)), self.scratch(16 * max(n, 1))
        self.live = None
        for attempt in range(3):
            with self.stats.stage("epipolar_rectify"):
                self._slices(spacing, ring_px)
            if st.lookup != "segment" or self.live.count == 0:
                slice_err = summarize(np.zeros(0))
                break
            with self.stats.stage("epipolar_svd"), np.errstate(all="ignore"):   # as in svd()
                slice_err = _slice_check(self.axis, self.box, self.kappa[:self.nch], self.g_hg,
                                         self.slices, cam.origin,
                                         self.live.rows(self.segs, np.random.default_rng(54321),
                                                        200))
            if slice_err["rms"] <= 0.25 * st.svd_tolerance or attempt == 2:
                break
            spacing *= 0.5
        self.slice_err = slice_err
        slices, live = self.slices, self.live
        self.info: dict = {
            "epipole_px": [float(slices.P[0]), float(slices.P[1])],
            "epipole_in_front": bool(slices.front), "ring_samples": live.ring,
            "ring_degrees": math.degrees(self.ring_rad),
            "ring_band_samples": live.band, "ring_in_view": bool(self.ring_in_view),
            "slice_spacing_px": float(spacing),
            "slice_error": {k: v for k, v in slice_err.items() if k != "errors"}}

    def _slices(self, spacing: float, ring_px: float) -> None:
        """Slices at ``spacing`` pixels, the frame, and the samples' slice coordinates; the
        live samples (outside the ring) the first time."""
        st, cam, eng, n, defines = self.st, self.cam, self.eng, self.n, self.defines
        slices = self.slices = geo.make_slices(self.axis, cam, self.box, spacing, ring_px)
        self.S = len(slices)
        frame = self.frame = geo.frame_struct(self.axis, self.ps.medium, self.d)
        frame["prefilter"] = int(bool(st.prefilter))
        frame["beta_tol"] = st.prefilter_tolerance * cam.pixel_angle()
        frame["nch"] = self.nch
        self.faces = setup_shadow_map(frame, self.axis, self.ps, int(st.shadow_map))
        if st.lookup == "grid":
            self.R = int(st.rays_per_slice) if st.rays_per_slice > 0 else \
                max(2, int(math.ceil(float(slices.length.max()))))
            frame["rays"] = self.R
        self.frame_buf = self.up(frame.reshape(1))
        self.slice_buf = self.up(slices.table)
        self.phi_buf = self.up(slices.phi.astype(np.float32))
        self.lut = slices.lookup_table()
        self.lut_buf = self.up(self.lut)
        # the ring is decided below, in angle (the kernel's pixel disc is off)
        no_ring = np.array([slices.P[0], slices.P[1], -1.0, 0.0], np.float32)
        dirs_buf, ta_buf = view_dirs(eng, self.segs, frame["eye"], defines)
        self.ps.call("epipolar", "epi_samples", n, defines, fr=self.frame_buf, phis=self.phi_buf,
                     nslices=self.S, full=slices.full, lut=self.lut_buf,
                     bins=len(self.lut) - 1, ring=no_ring, dirs=dirs_buf, ta=ta_buf, n=n,
                     geo=self.geo_buf, idx=self.idx_buf)
        if self.live is None:            # beta, hence the ring, does not depend on slices
            self.ring_in_view = _ring_in_view(cam, self.axis, slices.front, self.ring_rad,
                                              st.epipole_band)
            self.live = (_live_samples(eng, self.segs, self.geo_buf, self.idx_buf, self.wr_buf,
                                       slices.front, self.ring_rad, st.epipole_band, defines,
                                       self.bufs)
                         if self.ring_in_view else
                         _primary_samples(eng, self.segs, self.geo_buf, self.idx_buf, defines))
        self.views = DeviceViews(eng, self.geo_buf, self.idx_buf, self.live.buf,
                                 self.live.count, self.S, defines)

    # ---- maps ----
    def maps(self) -> None:
        """The shadow map (and the grid lookup's depth map)."""
        st, cam = self.st, self.cam
        with self.stats.stage("epipolar_maps"):
            if st.lookup == "grid":
                self.dw = int(st.depth_map)
                self.dh = max(1, int(round(self.dw * cam.height / cam.width)))
                self.depth = trace_depth_map(self.ps, self.dw, self.dh, self.defines)
                self.bufs.append(self.depth)
            self.faces_buf = self.up(self.faces)
            self.smap = trace_shadow_map(self.ps, self.frame_buf, int(st.shadow_map),
                                         self.defines, self.faces, self.faces_buf,
                                         frame=self.frame, info=self.info)
            self.bufs.append(self.smap)
            self.eng.finish()

    # ---- the view rays of the sweep (events) ----
    def events(self) -> None:
        """The sweep's events per slice and their offsets."""
        st, S, slices = self.st, self.S, self.slices
        with self.stats.stage("epipolar_rectify"):
            if st.lookup == "segment":
                self.ev_buf, self.off_buf, self.inv_buf, off = _segment_events(
                    self.eng, self.geo_buf, self.idx_buf, self.live, S, self.defines,
                    self.bufs, self.slice_buf)
                self.cnt_off = merged_offsets(off, slices.full)
                self.n_out = 2 * self.live.count                  # two results per sample
                self.b_range = self.views.ranges(1)[0] or (0.0, 0.0)
            else:
                off = self.cnt_off = (np.arange(S + 1) * self.R).astype(np.int32)
                self.n_out = S * self.R
                self.ev_buf = self.scratch(16 * self.n_out)
                self.off_buf = self.up(off)
                self.inv_buf = None
                tab = slices.table
                self.b_range = (float(tab["beta_lo"].min()), float(tab["beta_hi"].max()))
            self.n_ev = int(self.cnt_off[S])
            self.cnt_off_buf = self.up(self.cnt_off)
            self.g_range = (float(slices.table["gamma_lo"].min()),
                            float(slices.table["gamma_hi"].max()))

    # ---- the SVD, with its error control ----
    def svd(self) -> None:
        """The truncated SVD of the visibility-free term, at the cheapest setting whose
        estimated error meets the tolerance; :class:`SVDFallback` when none does."""
        st, info = self.st, self.info
        with self.stats.stage("epipolar_svd"), np.errstate(all="ignore"):
            # overflows of thick media's exponentials are expected here: they make
            # per-sample errors non-finite, which summarize counts as failures
            sv, tried = _svd(self.axis, self.box, self.ps, self.kappa[:self.nch], self.slices,
                             self.views, self.live, self.segs, st, self.R,
                             DeviceRiemann(self.eng, self.frame_buf, self.slice_buf,
                                           self.defines, self.g_hg),
                             extra=self.slice_err["rms"])
            err = {k: v for k, v in sv.error.items() if k != "errors"}
            info.update(svd_error=err, svd_tried=tried, svd_terms=sv.terms,
                        light_ray_factor=sv.ray_mult,
                        svd_groups=int(len(sv.ranges)), svd_singular_values=sv.singular,
                        svd_formulation="referenced" if sv.referenced else "plain")
            if not sv.accepted:
                raise SVDFallback(
                    f"estimated error {err['rms']:.3g} (SVD {err['svd']:.3g}, light rays "
                    f"{err['light_rays']:.3g}, slices {self.slice_err['rms']:.3g} in quadrature, "
                    f"RMS over {err['samples']} held-out samples"
                    + (f", {err['nonfinite']} of them not finite" if err.get("nonfinite") else "")
                    + ") > "
                    f"tolerance {st.svd_tolerance:g} at the best of {len(tried)} settings "
                    f"({sv.terms} terms, {len(sv.ranges)} groups, {sv.ray_mult}x light rays)", info)
            self.defines = {"EPI_NT": int(sv.terms), "EPI_NCH": self.nch}
            self.d = int(st.light_rays) * sv.ray_mult
            self.frame["d"] = self.d
            self.frame["lspan"] = sv.span
            self.frame_buf = self.up(self.frame.reshape(1))
            self.slices.table["group"] = sv.group
            self.slice_buf = self.up(self.slices.table)
            self.sv = sv

    # ---- per batch of slices: rectify the shadow map, integrate ----
    def integrate(self, show_progress: bool) -> None:
        """The sweep: per batch of slices, the rectified shadow map and the Fenwick-tree
        integration of every event."""
        st, S, d, sv, defines = self.st, self.S, self.d, self.sv, self.defines
        gtab_buf, btab_buf = self.up(sv.gtab), self.up(sv.btab)
        gref_buf, bref_buf, grp_buf = self.up(sv.gref), self.up(sv.bref), self.up(sv.ranges)
        nv = int(sv.terms) * self.nch
        cnt_off = self.cnt_off
        # at most ~32 MB of tree per batch (more light rays in thick media)
        batch = max(1, min(int(st.batch_slices), S, (1 << 23) // max(d * nv, 1)))
        max_ev = int(max(cnt_off[min(s + batch, S)] - cnt_off[s] for s in range(0, S, batch)))
        term = self.scratch(8 * batch * d * 4)
        tree = self.scratch(4 * batch * d * nv)
        leaf = self.scratch(4 * batch * d * nv)
        cnt = self.scratch(4 * (max_ev + batch))
        merged = self.scratch(16 * (max_ev + batch) if st.lookup == "segment" else 16)
        dst = self.scratch(4 * (max_ev + batch))
        srt = self.scratch(8 * batch * d * 4)
        self.out = self.scratch(16 * max(self.n_out, 1))
        self.work = self.scratch(8 * S)
        with progress(S, "epipolar slices", show_progress) as bar:
            for s0 in range(0, S, batch):
                nb = min(batch, S - s0)
                with self.stats.stage("epipolar_rectify"):
                    self.ps.call("epipolar", "epi_rectify_shadow", nb * d, defines,
                                 fr=self.frame_buf, slices=self.slice_buf, slice0=s0, nbatch=nb,
                                 faces=self.faces_buf, smap=self.smap, term=term)
                    if st.lookup == "grid":
                        self.ps.call("epipolar", "epi_rectify_depth", nb * self.R, defines,
                                     fr=self.frame_buf, slices=self.slice_buf, slice0=s0,
                                     nbatch=nb, depth=self.depth, dw=self.dw, dh=self.dh,
                                     events=self.ev_buf)
                    self.eng.finish()
                with self.stats.stage("epipolar_integrate"):
                    _launch_slices(self.eng, "epi_integrate", nb, defines, fr=self.frame_buf,
                                   slices=self.slice_buf, slice0=s0, nbatch=nb, term=term,
                                   ev_off=self.off_buf, two_runs=int(st.lookup == "segment"),
                                   wrap=int(self.slices.full), nslices=S,
                                   cnt_off=self.cnt_off_buf, events=self.ev_buf,
                                   gtab_all=gtab_buf, n_g=sv.gtab.shape[1], btab_all=btab_buf,
                                   n_b=sv.btab.shape[1], gref_all=gref_buf, bref_all=bref_buf,
                                   groups=grp_buf, tree=tree, leaf=leaf, cnt_all=cnt,
                                   merged_all=merged, dst_all=dst, sorted_all=srt, out=self.out,
                                   work=self.work)
                    self.eng.finish()
                bar.update(nb)

    # ---- back to the samples ----
    def unrectify(self) -> None:
        """Each live sample's value from its slices' results, times the light's colour,
        into the output buffers."""
        st, eng, live, defines = self.st, self.eng, self.live, self.defines
        with self.stats.stage("epipolar_unrectify"):
            colour = np.zeros(4, np.float32)
            colour[:3] = (np.asarray(self.ps.medium["sigma_s"][:3], np.float64)
                          * np.asarray(self.ps.lights[self.li]["power"][:3], np.float64))
            acc, inv_buf = self.out, self.inv_buf
            if st.lookup == "grid":
                # the grid's lookup needs each live sample's direction: read back (not the
                # default lookup; the host computes the directions as geometry.py does)
                rows = prim.gather(eng, self.segs.buf, live.buf, live.count, SEGMENT_BYTES)
                self.bufs.append(rows)
                live_segs = eng.read(rows, live.count, structs.VIEW_SEGMENT)
                dbuf = self.up(segment_dirs(live_segs, self.cam.origin))
                acc = self.scratch(16 * live.count)
                self.ps.call("epipolar", "epi_unrectify", live.count, defines, fr=self.frame_buf,
                             slices=self.slice_buf, phis=self.phi_buf, nslices=self.S,
                             full=self.slices.full, lut=self.lut_buf, bins=len(self.lut) - 1,
                             R=self.R, grid=self.out, dirs=dbuf, n=live.count, out=acc)
                inv_buf = acc                       # unused with use_acc
            self.ps.call("epipolar", "epi_sample_values", live.count, defines, res=self.out,
                         inv=inv_buf, idx=self.idx_buf, live=live.buf, L=live.count, acc=acc,
                         use_acc=int(st.lookup == "grid"), wr=self.wr_buf, colour=colour,
                         values=self.values_buf)
            self.counts = eng.read(self.work, (self.S, 2), np.int32)

    def finish_info(self) -> None:
        """The light's statistics once the sweep has run."""
        st, S = self.st, self.S
        self.info.update(
            slices=S, light_rays=self.d, shadow_map=int(st.shadow_map), lookup=st.lookup,
            shadow_map_faces=[[int(f["c"][3]), int(f["e1"][3])] for f in self.faces]
            if self.axis.spot else [[int(st.shadow_map)] * 2],
            events=int(self.n_ev), tree_updates=int(self.counts[:, 0].sum()),
            tree_queries=int(self.counts[:, 1].sum()),
            gamma_range=list(self.g_range), beta_range=list(self.b_range), channels=self.nch,
            svd_span=float(self.sv.span))
        if st.lookup == "grid":
            self.info.update(rays_per_slice=self.R, depth_map=[self.dw, self.dh])
        else:
            self.info.update(rays_per_slice=float(self.n_ev) / max(S, 1))


SEGMENT_BYTES = structs.VIEW_SEGMENT.itemsize


@dataclass
class LiveSamples:
    """The samples the sweep integrates (primary, ring weight < 1), on the device:
    ``buf`` their ``count`` indices in increasing order; ``ring`` / ``band`` how many
    primary samples have a ring weight > 0 / strictly between 0 and 1."""

    engine: object
    buf: object
    count: int
    ring: int
    band: int
    geo: object
    idx: object

    def rows(self, segs, rng: np.random.Generator, n_max: int):
        """``min(count, n_max)`` live samples drawn without replacement by ``rng`` (the
        draw NumPy makes from ``range(count)``): their segment, geo and idx rows, read back
        (a few hundred rows: the held-out set of the error estimates)."""
        eng = self.engine
        m = min(self.count, int(n_max))
        pos = rng.choice(self.count, m, replace=False).astype(np.int32)
        if m == 0:
            return (np.zeros(0, structs.VIEW_SEGMENT), np.zeros((0, 4), np.float32),
                    np.zeros((0, 4), np.int32))
        tmp = [eng.to_device(pos)]
        try:
            tmp.append(prim.gather(eng, self.buf, tmp[0], m, 4))
            ids = tmp[1]
            out = []
            for src, size, dt, shape in ((segs.buf, SEGMENT_BYTES, structs.VIEW_SEGMENT, m),
                                         (self.geo, 16, np.float32, (m, 4)),
                                         (self.idx, 16, np.int32, (m, 4))):
                tmp.append(prim.gather(eng, src, ids, m, size))
                out.append(eng.read(tmp[-1], shape, dt))
            return tuple(out)
        finally:
            eng.free(*tmp)


def _live_samples(eng, segs, geo_buf, idx_buf, wr_buf, front: bool, radius: float,
                  band: float, defines: dict, bufs: list) -> LiveSamples:
    """Ring weights into ``wr_buf`` (:func:`ring_weights`, on the device) and the live
    list (a compaction)."""
    n = segs.count
    flags, counts = eng.empty(4 * max(n, 1)), eng.zeros(8)
    try:
        outer = radius * (1.0 + max(band, 0.0))
        eng.call("epipolar", "epi_ring", n, defines, segs=segs.buf, geo=geo_buf, n=n,
                 front=int(bool(front)), radius=radius, outer=outer, wr=wr_buf,
                 live_flag=flags, counts=counts)
        live, count = prim.compact(eng, flags, n)
        bufs.append(live)
        ring, in_band = (int(x) for x in eng.read(counts, 2, np.int32))
    finally:
        eng.free(flags, counts)
    return LiveSamples(eng, live, count, ring, in_band, geo_buf, idx_buf)


def view_dirs(eng, segs, eye, defines: dict):
    """The view segments' unit directions from the eye with their end distances, ``dirs``
    (float4: v, t_b) and ``ta`` (float), from ``epi_view_dirs``: no light changes them, so
    they are derived once per set of view segments (and eye) and a light move reads 20
    bytes a segment instead of its 64-byte record."""
    eye = np.asarray(eye, np.float32).reshape(4)

    def build():
        n = segs.count
        dirs, ta = eng.empty(16 * max(n, 1)), eng.empty(4 * max(n, 1))
        eng.call("epipolar", "epi_view_dirs", n, defines, segs=segs.buf, n=n, eye=eye,
                 dirs=dirs, ta=ta)
        return [dirs, ta], (dirs, ta)

    return segs.derived("epipolar_view_dirs/" + eye.tobytes().hex(), build)


# angle (radians) by which the ring's edge must miss the image for the ring to be skipped:
# well above the float32 error of the kernels' beta (atan2_fast: 4e-7)
RING_MARGIN = 1e-5


def _ring_in_view(cam: geo.CameraGeom, axis: geo.Axis, front: bool, radius: float,
                  band: float) -> bool:
    """Whether a camera ray can come within the ring's outer edge (radius and blended band)
    of the epipole (the anti-epipole when ``front`` is false): else every ring weight is 0
    and the live samples are the primary ones, which :func:`_primary_samples` keeps from
    one light move to the next."""
    if radius <= 0.0:
        return False
    outer = radius * (1.0 + max(band, 0.0))
    a = np.asarray(axis.u, np.float64) * (1.0 if front else -1.0)
    return cam.min_angle_to(a) <= outer + RING_MARGIN


def split_segments(eng, segs, defines: dict):
    """Which view segments are primary (depth 0) and which lie behind mirrors and glass, as
    two per-segment weights (exactly 1.0 or 0.0: the scale of a ray-marched part), and the
    count of deeper ones: ``epi_split``, once per set of view segments
    (:meth:`DeviceSegments.derived`: a warm re-render reuses them)."""
    def build():
        n = segs.count
        primary, deeper, cnt = eng.empty(4 * n), eng.empty(4 * n), eng.zeros(4)
        try:
            eng.call("epipolar", "epi_split", n, defines, segs=segs.buf, n=n, primary=primary,
                     deeper=deeper, counts=cnt)
            n_deep = int(eng.read(cnt, 1, np.int32)[0])
        except BaseException:
            eng.free(primary, deeper, cnt)
            raise
        eng.free(cnt)
        return [primary, deeper], (primary, deeper, n_deep)

    return segs.derived("epipolar_split", build)


def _primary_samples(eng, segs, geo_buf, idx_buf, defines: dict) -> LiveSamples:
    """The live samples when the ring is out of view: every primary segment, in order,
    with ring weight 0 (``wr`` stays the zeros it starts as). What :func:`_live_samples`
    would give, without its kernel, compaction and read-back on every light move: the
    list is compacted once per set of view segments from the split's primary weights
    (:func:`split_segments`; 1.0 and 0.0 are non-zero and zero as int32 flags too)."""
    def build():
        primary = split_segments(eng, segs, defines)[0]
        buf, count = prim.compact(eng, primary, segs.count)
        return [buf], (buf, count)

    buf, count = segs.derived("epipolar_primary_list", build)
    return LiveSamples(eng, buf, count, 0, 0, geo_buf, idx_buf)


class HostViews:
    """The view rays of the SVD's references given on the host (the grid lookup's rays):
    slices ``k0``, ``k1`` (a ray touches the groups of both), ``beta`` and ``t_a``."""

    def __init__(self, k0, k1, beta, ta, S: int):
        self.k0, self.k1, self.beta, self.ta, self.S = k0, k1, beta, ta, S

    def _touch(self, G: int, j: int) -> np.ndarray:
        group = (np.arange(self.S) * G) // self.S
        return (group[self.k0] == j) | (group[self.k1] == j)

    def ranges(self, G: int) -> list:
        out = []
        for j in range(G):
            vs = self._touch(G, j)
            out.append((float(self.beta[vs].min()), float(self.beta[vs].max()))
                       if vs.any() else None)
        return out

    def nodes(self, G: int, brs) -> np.ndarray:
        return np.stack([node_extremes(self.beta[vs], self.ta[vs], lo, hi, REF_NODES, False)
                         for j, (lo, hi) in enumerate(brs)
                         for vs in [self._touch(G, j)]])


RANGE_BLOCK, RANGE_MAX_GROUPS = 256, 16     # EPI_RANGE_BLOCK, EPI_MAX_GROUPS in epipolar.cl


class DeviceViews:
    """The same for the camera samples of the segment lookup, reduced on the device
    (``epi_view_ranges``, ``epi_view_nodes``): only per-group ranges and envelope nodes
    come back."""

    def __init__(self, eng, geo, idx, live, L: int, S: int, defines: dict):
        self.eng, self.geo, self.idx, self.live, self.L, self.S = eng, geo, idx, live, L, S
        self.defines = defines
        self._ranges: dict[int, list] = {}

    def ranges(self, G: int) -> list:
        if G not in self._ranges:
            eng = self.eng
            lo = eng.to_device(np.full(G, np.iinfo(np.int32).max, np.int32), writable=True)
            hi = eng.to_device(np.zeros(G, np.int32), writable=True)
            try:
                if G > RANGE_MAX_GROUPS:
                    raise ValueError(f"at most {RANGE_MAX_GROUPS} groups of slices")
                eng.call("epipolar", "epi_view_ranges", -(-self.L // RANGE_BLOCK), self.defines,
                         geo=self.geo, idx=self.idx, live=self.live, L=self.L, S=self.S, G=G,
                         bmin=lo, bmax=hi)
                a, b = eng.read(lo, G, np.int32), eng.read(hi, G, np.int32)
            finally:
                eng.free(lo, hi)
            self._ranges[G] = [(float(x), float(y)) if i <= k else None
                               for i, k, x, y in zip(a, b, a.view(np.float32), b.view(np.float32))]
        return self._ranges[G]

    def nodes(self, G: int, brs) -> np.ndarray:
        eng = self.eng
        rng = eng.to_device(np.asarray(brs, np.float32).reshape(G, 2))
        inf = np.array(np.inf, np.float32).view(np.int32)
        tmin = eng.to_device(np.full(G * REF_NODES, inf, np.int32), writable=True)
        try:
            eng.call("epipolar", "epi_view_nodes", self.L, self.defines, geo=self.geo,
                     idx=self.idx, live=self.live, L=self.L, S=self.S, G=G, range=rng,
                     nodes=REF_NODES, tmin=tmin)
            out = eng.read(tmin, (G, REF_NODES), np.int32)
        finally:
            eng.free(rng, tmin)
        return out.view(np.float32).astype(np.float64)


# the event sort's buckets: about this many samples each, so that nearly every bucket is
# sorted by insertion sort (bucket_sort_runs: heapsort above 24 elements); at 32 a
# bucket the sorts took 11 ms of a 0.29 s light move on shafts (640x480), at 4 2.7 ms,
# the larger histogram and scan ~1 ms more
EVENTS_PER_BIN = 4


def _segment_events(eng, geo_buf, idx_buf, live: LiveSamples, S: int, defines: dict,
                    bufs: list, slice_buf, bins: int | None = None):
    """The sweep's events: the live samples bucket-sorted on the device by their first
    slice ``k0`` and then by beta (ties by live index), one run per slice. Slice k sweeps
    run k (the k0 side of its samples) merged with run k - 1 (the k1 = k0 + 1 side of
    those), so each sample is sorted once (``epi_integrate``). Returns the events (live
    order permuted), the run offsets (device, and the S + 1 of them on the host for the
    batch sizes) and ``inv`` (place of each live sample in the runs).

    Each run is bucketed further by beta into ``bins`` bins of its slice's beta range
    (``slice_buf``: the EPI_SLICE table; default: about :data:`EVENTS_PER_BIN` samples a
    bin), so that the per-bucket sorts are short; the order is the same."""
    L = live.count
    if bins is None:
        bins = int(min(max(round(L / max(S, 1) / EVENTS_PER_BIN), 1), 1024))
    keys, beta = eng.empty(4 * max(L, 1)), eng.empty(4 * max(L, 1))
    starts = eng.to_device((np.arange(S + 1) * bins).astype(np.int32))
    fine = None
    try:
        eng.call("epipolar", "epi_event_keys", L, defines, geo=geo_buf, idx=idx_buf,
                 live=live.buf, L=L, nslices=S, slices=slice_buf, bins=bins, keys=keys,
                 beta=beta)
        perm, fine = prim.bucket_sort(eng, keys, L, S * bins, fkey=beta)
        bufs.append(perm)
        offs = prim.gather(eng, fine, starts, S + 1, 4)     # each slice's first bin
    finally:
        eng.free(keys, beta, starts, *([fine] if fine is not None else []))
    bufs.append(offs)
    ev = eng.empty(16 * max(L, 1))
    inv = eng.empty(4 * max(L, 1))
    bufs += [ev, inv]
    eng.call("epipolar", "epi_events", L, defines, geo=geo_buf, live=live.buf, L=L,
             perm=perm, events=ev, inv=inv)
    off = eng.read(offs, S + 1, np.int32)
    return ev, offs, inv, off


def merged_offsets(off: np.ndarray, full: bool) -> np.ndarray:
    """Where each slice's sweep starts in the merged order (``epi_integrate``'s
    ``cnt_off``): slice k sweeps run k and run k - 1 (run S - 1 for slice 0 of a full
    fan); ``off`` holds the S + 1 run offsets."""
    runs = np.diff(np.asarray(off, np.int64))
    prev = np.roll(runs, 1)
    if not full and len(prev):
        prev[0] = 0
    return np.concatenate([[0], np.cumsum(runs + prev)]).astype(np.int32)


def _views(axis: geo.Axis, box, ps: PreparedScene, slices: geo.Slices, idx: np.ndarray,
           beta: np.ndarray):
    """View rays (slice ``idx``, ``beta``) as (w, beta, t_a, gamma_a, gamma_b): the medium
    interval from the box (unbounded: [0, t_far]); rays that miss it are dropped."""
    w = slices.table["w"][idx, :3].astype(np.float64)
    v = np.cos(beta)[:, None] * axis.u + np.sin(beta)[:, None] * w
    if box is None:
        ta = np.zeros(len(beta))
        tb = np.full(len(beta), float(ps.medium["t_far"]))
    else:
        ta, tb = view_entry(axis, box, v)
    ok = tb > ta
    return (w[ok], beta[ok], ta[ok], axis.gamma(ta[ok], beta[ok]), axis.gamma(tb[ok], beta[ok]),
            idx[ok])


@dataclass
class SVDSet:
    """The truncated SVDs of one light, one per group of slices (contiguous arcs in phi):
    device arrays ``gtab (G, n_g, NV)``, ``btab (G, n_b, NV)``, ``gref (G, n_g)``,
    ``bref (G, n_b)``, ``ranges (G, 4)`` = (g_lo, g_hi, b_lo, b_hi); ``span`` the largest
    light-side spread; ``group`` (S,) each slice's group; ``error`` the held-out error."""

    gtab: np.ndarray
    btab: np.ndarray
    gref: np.ndarray
    bref: np.ndarray
    ranges: np.ndarray
    span: float
    group: np.ndarray
    terms: int
    singular: list
    error: dict
    referenced: bool = True
    singular_all: list = field(default_factory=list)   # per group: per channel
    accepted: bool = False
    discretisation: dict = field(default_factory=dict)  # light-ray multiplier: error
    ray_mult: int = 1


RAY_MULTS = (1, 2, 4)     # light rays tried: light_rays x these (thick media need more)
HELD_OUT = 400            # camera samples of the error estimate (SVD, float32)
HELD_RIEMANN = 80         # ... of its light-ray part (a sum over light rays each)
HELD_F32 = 40             # ... of its float32 part (the tree's sums emulated)
F32_BOUND_ENOUGH = 0.1    # a float32 bound under this x tolerance is used as it is ...
F32_BOUND_DEPTH = 15.0    # ... up to this optical depth across the medium (tested there)


def _slice_check(axis, box, kappas, g, slices, eye, rows):
    """Held-out estimate of the error of reading samples in their neighbouring slices
    (svd.slice_error) on ``rows`` = (segments, geo, idx) of a few hundred live samples
    (:meth:`LiveSamples.rows`)."""
    segs, sgeo, sidx = rows
    v = segs["b"][:, :3].astype(np.float64) - eye
    perp = v - (v @ axis.u)[:, None] * axis.u
    w = perp / np.maximum(np.linalg.norm(perp, axis=1), 1e-30)[:, None]
    tab = slices.table
    k0, k1 = sidx[:, 0], sidx[:, 1]
    f = sidx[:, 2].view(np.float32).astype(np.float64)
    w0, w1 = tab["w"][k0, :3].astype(np.float64), tab["w"][k1, :3].astype(np.float64)
    cones = None
    if axis.spot:
        # the sample's own cone interval in all three: the cone's silhouette between
        # slices is the known half-pixel limit (geometry); this estimates what the
        # medium's transmittance does across them
        own = geo._cone_interval(axis, w)
        cones = [own, own, own]
    e = slice_error(axis, box, kappas, g, w, w0, w1, f, sgeo[:, 0].astype(np.float64),
                    sgeo[:, 1].astype(np.float64), sgeo[:, 2].astype(np.float64), cones)
    ok = sgeo[:, 2] > sgeo[:, 1]
    return summarize(e[ok])


class DeviceRiemann:
    """The error estimate's light-ray sums (svd.riemann_sums) on the device, ``epi_riemann``:
    per held-out sample and light-ray count, the sweep's sum without occluders with the
    exact ``K``. The host reads back (samples x counts) sums; it spent ~10 ms per light and
    frame on them in NumPy at the defaults, more with 2 or 4 x the light rays."""

    def __init__(self, eng, frame_buf, slice_buf, defines: dict, g: float):
        self.eng, self.frame_buf, self.slice_buf = eng, frame_buf, slice_buf
        self.defines, self.g = defines, float(g)

    def sums(self, refs, k: np.ndarray, beta, g_a, g_b, ds: list[int],
             max_cells: int = 4096) -> list[np.ndarray]:
        """``[(N, channels) for d in ds]`` for the samples (slice ``k``, ``beta``,
        ``[g_a, g_b]``) with the references ``refs`` (svd.Refs)."""
        eng, n = self.eng, len(k)
        held = np.zeros((max(n, 1), 4), np.float32)
        held[:n, 0], held[:n, 1], held[:n, 2] = beta, g_a, g_b
        bufs = [eng.to_device(np.asarray(k, np.int32)), eng.to_device(held),
                eng.to_device(np.asarray(ds, np.int32)),
                eng.to_device(np.asarray(refs.lref, np.float32)),
                eng.to_device(np.asarray(refs.tref, np.float32)),
                eng.empty(16 * max(n * len(ds), 1))]
        try:
            args = dict(fr=self.frame_buf, slices=self.slice_buf, kidx=bufs[0], held=bufs[1],
                        n=n, dlist=bufs[2], nd=len(ds), lref=bufs[3], nl=len(refs.lref),
                        l_lo=refs.g_lo, l_hi=refs.g_hi, tref=bufs[4], nt=len(refs.tref),
                        t_lo=refs.b_lo, t_hi=refs.b_hi, span=refs.span, soft=int(refs.soft),
                        g=self.g, max_cells=max_cells, out=bufs[5])
            # a few hundred long work-items: small groups, so both cores share them evenly
            eng.launch(eng.kernel("epipolar", "epi_riemann", self.defines), n * len(ds),
                       *eng.bind("epipolar", "epi_riemann", args), group=4)
            out = eng.read(bufs[5], (len(ds), n, 4), np.float32)
        finally:
            eng.free(*bufs)
        nch = int(self.defines["EPI_NCH"])
        return [out[i, :, :nch].astype(np.float64) for i in range(len(ds))]


def _truncate(t, nch: int, terms: int):
    """The first ``terms`` terms of each channel of SVD tables made with more."""
    T = t.terms
    cols = np.concatenate([np.arange(c * T, c * T + terms) for c in range(nch)])
    return dataclasses.replace(t, gtab=np.ascontiguousarray(t.gtab[:, cols]),
                               btab=np.ascontiguousarray(t.btab[:, cols]), terms=terms)


def _svd_groups(axis, box, ps, kappas, slices, views, held, st: Settings, G: int,
                terms_list, n_tab: int, riemann: DeviceRiemann, zero: bool = False):
    """References and SVD with the slices cut into ``G`` arcs (decomposed once with the
    most terms; truncations are nested). Returns an SVDSet per entry of ``terms_list``.
    ``riemann``: the light-ray sums on the device (svd.riemann_sums is their reference)."""
    tab = slices.table
    S = len(tab)
    group = (np.arange(S) * G) // S
    cone_all = (tab["cone_lo"].astype(np.float64), tab["cone_hi"].astype(np.float64)) \
        if axis.spot else None
    w_all = tab["w"][:, :3].astype(np.float64)
    g = float(ps.medium["g"])
    hk, hw, hb, hga, hgb = held
    nch = len(kappas)
    tmax = max(terms_list)
    parts, sing_all = [], []
    errs = {T: [] for T in terms_list}
    disc = {m: [] for m in RAY_MULTS}
    singular = None
    # each group's beta range: its view rays' (the slices' own where none touches it)
    brs = [r if r is not None else
           (float(tab["beta_lo"][group == j].min()), float(tab["beta_hi"][group == j].max()))
           for j, r in enumerate(views.ranges(G))]
    nodes = None if zero else views.nodes(G, brs)
    # the float32 bound stands in for the emulation only where it was checked against it
    extent = float(np.linalg.norm(box[1] - box[0])) if box is not None \
        else float(ps.medium["t_far"])
    bound_ok = float(np.max(kappas)) * extent <= F32_BOUND_DEPTH
    for j in range(G):
        sel = group == j
        gr = (float(tab["gamma_lo"][sel].min()), float(tab["gamma_hi"][sel].max()))
        br = brs[j]
        cone = (cone_all[0][sel], cone_all[1][sel]) if cone_all is not None else None
        refs = references(axis, box, w_all[sel], cone, gr, br,
                          None if nodes is None else nodes[j], zero=zero)
        full = decompose(axis, kappas, g, gr, br, tmax, int(st.svd_samples), n_tab, n_tab, refs)
        if singular is None or j == G // 2:
            singular = full.singular
        sing_all.append(full.singular)
        hs = group[hk] == j
        hc = (cone_all[0][hk[hs]], cone_all[1][hk[hs]]) if cone_all is not None else None
        tabs, cache = {}, {}
        rs32 = np.flatnonzero(hs)[:max(1, (HELD_F32 * int(hs.sum())) // max(len(hk), 1))]
        for T in terms_list:
            t = _truncate(full, nch, T)
            e = heldout_error(axis, box, kappas, g, t, refs, hw[hs], hb[hs], hga[hs], hgb[hs], hc,
                              cache=cache)
            # the tree's float32 error, added to each: bounded on a few held-out samples
            # (svd.float32_bound); where that does not settle it (or the medium is thicker
            # than where the bound was checked against the emulation), emulated on them
            f32 = 0.0
            if len(rs32) and e["rms"] <= st.svd_tolerance:   # else it fails anyway
                rc32 = (cone_all[0][hk[rs32]], cone_all[1][hk[rs32]]) if cone_all is not None else None
                g0_32 = tab["gamma_lo"][hk[rs32]].astype(np.float64)
                args32 = (axis, box, kappas, t, refs, hw[rs32], hb[rs32], hga[rs32], hgb[rs32],
                          g0_32)
                f32 = 0.0 if not bound_ok else rms(float32_bound(*args32, int(st.light_rays), rc32))
                if not (bound_ok and f32 <= F32_BOUND_ENOUGH * st.svd_tolerance):
                    f32 = rms(float32_error(*args32, tab["gamma_hi"][hk[rs32]].astype(np.float64),
                                            int(st.light_rays), rc32))
            e = summarize(np.sqrt(e["errors"] ** 2 + f32 ** 2))
            errs[T].append(e["errors"])
            tabs[T] = t
            if e["rms"] <= 0.25 * st.svd_tolerance:    # clearly good: more terms only cost
                for T2 in terms_list[terms_list.index(T) + 1:]:
                    errs[T2].append(e["errors"])
                    tabs[T2] = _truncate(full, nch, T2)
                break
        parts.append((tabs, refs))
        # light-ray discretisation, per light-ray multiplier, on at most 100 samples
        rs = np.flatnonzero(hs)[:max(1, (HELD_RIEMANN * int(hs.sum())) // max(len(hk), 1))]
        if len(rs):
            e, sums = None, {}
            for mult in RAY_MULTS:
                # more light rays only matter where fewer are not clearly good enough
                if e is None or rms(e) > 0.25 * st.svd_tolerance:
                    dd = int(st.light_rays) * mult
                    need = [x for x in (dd, 2 * dd) if x not in sums]
                    if need:
                        sums.update(zip(need, riemann.sums(refs, hk[rs], hb[rs], hga[rs],
                                                           hgb[rs], need)))
                    e = riemann_rel(sums[dd], sums[2 * dd])
                disc[mult].append(e)
    out = {}
    for T in terms_list:
        ts = [p[0][T] for p in parts]
        out[T] = SVDSet(np.stack([t.gtab for t in ts]), np.stack([t.btab for t in ts]),
                        np.stack([t.gref for t in ts]), np.stack([t.bref for t in ts]),
                        np.array([[t.g_lo, t.g_hi, t.b_lo, t.b_hi] for t in ts], np.float32),
                        max(p[1].span for p in parts), group.astype(np.int32), T, singular,
                        summarize(np.concatenate(errs[T])), singular_all=sing_all)
        out[T].discretisation = {m: summarize(np.concatenate(disc[m]) if disc[m] else np.zeros(0))
                                 for m in RAY_MULTS}
    return out


def _svd(axis, box, ps, kappas, slices, views, live: LiveSamples, segs, st: Settings, R,
         riemann: DeviceRiemann, extra: float = 0.0):
    """The SVD set of one light with the fewest terms (device time) whose held-out error's
    RMS is within ``svd_tolerance``: terms ``svd_terms`` doubling up to ``svd_max_terms``,
    tried in the plain formulation, then referenced with the slices in 1 group, then 16
    groups (host time only: the references then follow the view and light entries of
    fewer slices). Returns the chosen set (or, if none passes, the most accurate) and
    the [groups, terms, light-ray factor, formulation, SVD error, light-ray error,
    accepted] evaluated."""
    tab = slices.table
    S = len(tab)
    rng = np.random.default_rng(12345)
    if st.lookup == "segment":
        _, sgeo, sidx = live.rows(segs, rng, HELD_OUT)
        hk = sidx[:, 0]
        held = (hk, tab["w"][hk, :3].astype(np.float64), sgeo[:, 0].astype(np.float64),
                sgeo[:, 1].astype(np.float64), sgeo[:, 2].astype(np.float64))
    else:
        # the grid's view rays: R per slice, uniform in beta over the slice's range
        m = min(R, 64)
        j = (np.arange(m) + 0.5) / m
        kk = np.repeat(np.arange(S), m)
        bb = (tab["beta_lo"][kk] + np.tile(j, S) * (tab["beta_hi"][kk] - tab["beta_lo"][kk]))
        _, vb, vta, _, _, vk = _views(axis, box, ps, slices, kk, bb.astype(np.float64))
        views = HostViews(vk, vk, vb, vta, S)
        kh = rng.integers(0, S, HELD_OUT)
        bh = rng.uniform(tab["beta_lo"][kh], tab["beta_hi"][kh])
        hw, hb, _, hga, hgb, hk = _views(axis, box, ps, slices, kh, bh)
        held = (hk, hw, hb, hga, hgb)
    terms_list = [int(st.svd_terms)]
    while terms_list[-1] < st.svd_max_terms:
        terms_list.append(min(2 * terms_list[-1], int(st.svd_max_terms)))
    tried, best, best_cost = [], None, None
    for G, zero in ((1, True), (1, False), (16, False)):
        if G > 1 and (G > S // 2 or (best is not None and best.accepted)):
            break       # at least two slices per group; 16 groups (~1 s of host time) only
                        # when nothing is within the tolerance yet
        n_tab = 2048 if G == 1 else 512
        sets = _svd_groups(axis, box, ps, kappas, slices, views, held, st, G, terms_list, n_tab,
                           riemann, zero)
        for T in terms_list:
            sv = sets[T]
            sv.referenced = not zero
            for mult in RAY_MULTS:
                # the SVD's (with the tree's float32), the light rays' and the slices'
                # errors: independent sources, combined in quadrature
                total = dict(sv.error, rms=math.sqrt(sv.error["rms"] ** 2 + extra ** 2
                                                     + sv.discretisation[mult]["rms"] ** 2))
                ok = all(accepts(s_, T, total, st.svd_tolerance) for s_ in sv.singular_all)
                tried.append([G, T, mult, "plain" if zero else "referenced",
                              round(sv.error["rms"], 5), round(sv.discretisation[mult]["rms"], 5),
                              ok])
                cost = (0 if ok else 1, T * mult if ok else total["rms"])
                if best_cost is None or cost < best_cost:
                    best = dataclasses.replace(sv, ray_mult=mult, accepted=ok,
                                               error={**total, "svd": sv.error["rms"],
                                                      "light_rays": sv.discretisation[mult]["rms"]})
                    best_cost = cost
        # good enough: the starting terms, or at most twice the device work (trying the
        # referenced formulation and groups costs host time on every frame)
        if best.accepted and best.terms * best.ray_mult <= 2 * terms_list[0]:
            break
        # groups only refine the references: hopeless if one group is far off at most terms
        if not zero and G == 1 and sets[terms_list[-1]].error["rms"] > 30 * st.svd_tolerance:
            break
    return best, tried


def _launch_slices(eng, kernel: str, n: int, defines: dict, **args) -> None:
    """Keyword launch (see ``Engine.call``) of an ``epipolar.cl`` kernel with one work-item
    per slice, each its own work-group: the sweeps are long sequential loops, so a driver
    that groups many work-items per group would serialise them."""
    eng.launch(eng.kernel("epipolar", kernel, defines), int(n),
               *eng.bind("epipolar", kernel, args), group=1)
