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
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ...prepared import PreparedScene
from ...stats import Stats, progress
from . import geometry as geo
from .maps import setup_shadow_map, trace_depth_map, trace_shadow_map
from .svd import decompose

LOOKUPS = ("segment", "grid")


@dataclass
class Settings:
    """The method's parameters (``0``: automatic, resolved per image by :func:`_auto`)."""

    slices: int = 0
    rays_per_slice: int = 0
    light_rays: int = 0
    shadow_map: int = 0
    depth_map: int = 0
    svd_terms: int = 4
    svd_samples: int = 64
    prefilter: bool = True
    prefilter_tolerance: float = 1.0
    epipole_ring: float = 8.0
    lookup: str = "segment"
    batch_slices: int = 256


@dataclass
class LightOutput:
    values: np.ndarray                 # (n, 3) float64, 0 inside the ring
    ring: np.ndarray                   # (n,) bool
    info: dict = field(default_factory=dict)


def segment_dirs(segs: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Unit directions (N, 4) float32 of primary view segments (from the eye)."""
    v = segs["b"][:, :3].astype(np.float64) - eye
    v /= np.maximum(np.linalg.norm(v, axis=1), 1e-30)[:, None]
    out = np.zeros((len(v), 4), np.float32)
    out[:, :3] = v
    return out


def _auto(st: Settings, cam: geo.CameraGeom) -> Settings:
    """``st`` with its automatic (0) sizes resolved for this image."""
    big = max(cam.width, cam.height)
    return dataclasses.replace(
        st,
        light_rays=st.light_rays if st.light_rays > 0 else 2 * big,
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


def _segment_events(geo: np.ndarray, idx: np.ndarray, nslices: int):
    """Events of the segment lookup, two per sample (its two neighbouring slices, weights
    1 - f and f), sorted by (slice, beta); ``geo``/``idx`` from ``epi_samples``.
    Returns the events, the slice offsets, each event's weight and its sample."""
    n = len(geo)
    f = idx[:, 2].view(np.float32)
    k = np.concatenate([idx[:, 0], idx[:, 1]])
    wgt = np.concatenate([1.0 - f, f])
    order = np.argsort(k + np.tile(geo[:, 0], 2).astype(np.float64) * 0.25)   # beta / 4 < 1
    order = order[wgt[order] > 0.0]
    src = order % n
    off = np.zeros(nslices + 1, np.int32)
    off[1:] = np.cumsum(np.bincount(k[order], minlength=nslices))
    return geo[src], off, wgt[order].astype(np.float64), src


def render_light(ps: PreparedScene, li: int, segs: np.ndarray, st: Settings, stats: Stats,
                 show_progress: bool = True) -> LightOutput:
    """Radiance from light ``li`` scattered towards the start of each primary segment."""
    eng = ps.engine
    cam = geo.CameraGeom.from_struct(ps.camera)
    axis = geo.make_axis(ps.lights[li], cam.origin)
    st = _auto(st, cam)
    n = len(segs)
    box = geo.medium_box(ps.medium)
    if box is None and not axis.spot:
        raise ValueError("a directional light needs a bounded medium")
    kappa = np.asarray(ps.medium["kappa"][:3], np.float64)
    nch = 1 if np.all(kappa == kappa[0]) else 3
    defines = {"EPI_NT": int(st.svd_terms), "EPI_NCH": nch}
    kern = lambda name: eng.kernel("epipolar", name, defines)
    values = np.zeros((n, 3), np.float64)
    d = int(st.light_rays)
    bufs = []

    def up(arr):
        b = eng.to_device(arr)
        bufs.append(b)
        return b

    def scratch(nbytes):
        b = eng.empty(nbytes)
        bufs.append(b)
        return b

    try:
        # ---- slices, and every sample's coordinates (rectification of the view rays) ----
        with stats.stage("epipolar_rectify"):
            slices = geo.make_slices(axis, cam, box, _spacing(st, axis, cam), st.epipole_ring)
            S = len(slices)
            frame = geo.frame_struct(axis, ps.medium, d)
            frame["prefilter"] = int(bool(st.prefilter))
            frame["beta_tol"] = st.prefilter_tolerance * cam.pixel_angle()
            frame["nch"] = nch
            setup_shadow_map(frame, axis, ps, int(st.shadow_map))
            R = 0
            if st.lookup == "grid":
                R = int(st.rays_per_slice) if st.rays_per_slice > 0 else \
                    max(2, int(math.ceil(float(slices.length.max()))))
                frame["rays"] = R
            frame_buf = up(frame.reshape(1))
            slice_buf = up(slices.table)
            phi_buf = up(slices.phi.astype(np.float32))
            geo_buf, idx_buf = scratch(16 * max(n, 1)), scratch(16 * max(n, 1))
            ring_px = np.array([slices.P[0], slices.P[1], st.epipole_ring, 0.0], np.float32)
            eng.launch(kern("epi_samples"), n, frame_buf, phi_buf, np.int32(S),
                       np.int32(slices.full), ps.buf["camera"], ring_px, up(segs), np.int32(n),
                       geo_buf, idx_buf)
            sgeo = eng.read(geo_buf, (n, 4), np.float32)
            sidx = eng.read(idx_buf, (n, 4), np.int32)
            ring = sidx[:, 3] != 0
            live = np.flatnonzero(~ring)
        info: dict = {"epipole_px": [float(slices.P[0]), float(slices.P[1])],
                      "epipole_in_front": bool(slices.front), "ring_samples": int(ring.sum())}
        if len(live) == 0:
            return LightOutput(values, ring, info)

        # ---- maps ----
        with stats.stage("epipolar_maps"):
            if st.lookup == "grid":
                dw = int(st.depth_map)
                dh = max(1, int(round(dw * cam.height / cam.width)))
                depth = trace_depth_map(ps, dw, dh, defines)
                bufs.append(depth)
            smap = trace_shadow_map(ps, frame_buf, int(st.shadow_map), defines)
            bufs.append(smap)
            eng.queue.finish()

        # ---- the view rays of the sweep (events) and the SVD ----
        with stats.stage("epipolar_rectify"):
            if st.lookup == "segment":
                ev, off, ev_w, ev_src = _segment_events(sgeo[live], sidx[live], S)
                ev_buf = up(ev)
                n_ev = len(ev)
                b_range = (float(sgeo[live, 0].min()), float(sgeo[live, 0].max()))
            else:
                off = (np.arange(S + 1) * R).astype(np.int32)
                n_ev = S * R
                ev_buf = scratch(16 * n_ev)
                tab = slices.table
                b_range = (float(tab["beta_lo"].min()), float(tab["beta_hi"].max()))
            off_buf = up(off)
            g_range = (float(slices.table["gamma_lo"].min()), float(slices.table["gamma_hi"].max()))
        with stats.stage("epipolar_svd"):
            tables = decompose(axis, kappa[:nch], float(ps.medium["g"]), g_range, b_range,
                               int(st.svd_terms), int(st.svd_samples))
            gtab_buf, btab_buf = up(tables.gtab), up(tables.btab)

        # ---- per batch of slices: rectify the shadow map, integrate ----
        nv = int(st.svd_terms) * nch
        batch = min(int(st.batch_slices), S)
        max_ev = int(max(off[min(s + batch, S)] - off[s] for s in range(0, S, batch)))
        term = scratch(8 * batch * d * 4)
        tree = scratch(4 * batch * d * nv)
        leaf = scratch(4 * batch * d * nv)
        cnt = scratch(4 * (max_ev + batch))
        srt = scratch(8 * batch * d * 4)
        out = scratch(16 * max(n_ev, 1))
        work = scratch(8 * S)
        k_rs, k_rd, k_int = kern("epi_rectify_shadow"), kern("epi_rectify_depth"), kern("epi_integrate")
        with progress(S, "epipolar slices", show_progress) as bar:
            for s0 in range(0, S, batch):
                nb = min(batch, S - s0)
                with stats.stage("epipolar_rectify"):
                    eng.launch(k_rs, nb * d, frame_buf, slice_buf, np.int32(s0), np.int32(nb),
                               smap, term)
                    if st.lookup == "grid":
                        eng.launch(k_rd, nb * R, frame_buf, slice_buf, np.int32(s0), np.int32(nb),
                                   ps.buf["medium"], ps.buf["camera"], depth, np.int32(dw),
                                   np.int32(dh), ev_buf)
                    eng.queue.finish()
                with stats.stage("epipolar_integrate"):
                    _launch_slices(eng, k_int, nb, frame_buf, slice_buf, np.int32(s0),
                                   np.int32(nb), term, off_buf, ev_buf, gtab_buf,
                                   np.int32(len(tables.gtab)), np.float32(tables.g_lo),
                                   np.float32(tables.g_hi), btab_buf, np.int32(len(tables.btab)),
                                   np.float32(tables.b_lo), np.float32(tables.b_hi), tree, leaf,
                                   cnt, srt, out, work)
                    eng.queue.finish()
                bar.update(nb)

        # ---- back to the samples ----
        with stats.stage("epipolar_unrectify"):
            if st.lookup == "segment":
                res = eng.read(out, (n_ev, 4), np.float32)[:, :nch].astype(np.float64)
                acc = np.zeros((len(live), nch))
                for c in range(nch):
                    acc[:, c] = np.bincount(ev_src, weights=res[:, c] * ev_w, minlength=len(live))
            else:
                dbuf = up(segment_dirs(segs[live], cam.origin))
                ubuf = scratch(16 * len(live))
                eng.launch(kern("epi_unrectify"), len(live), frame_buf, slice_buf, phi_buf,
                           np.int32(S), np.int32(slices.full), np.int32(R), out, dbuf,
                           np.int32(len(live)), ubuf)
                acc = eng.read(ubuf, (len(live), 4), np.float32)[:, :nch].astype(np.float64)
            colour = (np.asarray(ps.medium["sigma_s"][:3], np.float64)
                      * np.asarray(ps.lights[li]["power"][:3], np.float64))
            values[live] = acc * colour
        counts = eng.read(work, (S, 2), np.int32)
        eng.note_host(int(values.nbytes) * 4)
    finally:
        eng.free(*bufs)
    info.update(slices=S, light_rays=d, shadow_map=int(st.shadow_map), lookup=st.lookup,
                events=int(n_ev), tree_updates=int(counts[:, 0].sum()),
                tree_queries=int(counts[:, 1].sum()), svd_singular_values=tables.singular,
                gamma_range=list(g_range), beta_range=list(b_range), channels=nch)
    if st.lookup == "grid":
        info.update(rays_per_slice=R, depth_map=[dw, dh])
    else:
        info.update(rays_per_slice=float(n_ev) / max(S, 1))
    return LightOutput(values, ring, info)


def _launch_slices(eng, kernel, n, *args) -> None:
    """One work-item per slice, each its own work-group: the sweeps are long sequential
    loops, so a driver that groups many work-items per group would serialise them."""
    kernel(eng.queue, (int(n),), (1,), *args)
