"""The voxel pipeline's stages with their inputs, so a relighting session re-runs only what
changed (Sun et al. 2008, fig. 2):

==============  ===========================================  ============================
stage           computes                                     re-runs when
==============  ===========================================  ============================
``geometry``    grid box, coverage of every volume, blurred  a volume's shape moves or
                weights (``voxelise.py``); per volume:       changes; grid parameters
                only the volumes whose own fingerprint
                changed are voxelised again
``material``    n, sigma_s, kappa, grad n, octree, boundary  a volume's ior / sigma, the
                sides (``voxelise.py``, ``octree.py``)       medium; eps parameters
``lighting``    photons, marching, deposition, smoothing;    a light; anything above
                photons on diffuse surfaces
``view``        view paths through the grid; direct light    the camera; anything above
                outside it (``view.py`` + ``raymarch``);
                the surface photon map at the diffuse hits
==============  ===========================================  ============================

The geometry stage keeps each volume's blurred weight (its *contribution*) keyed by
:func:`contribution_key`: the volume's own shape (mesh vertices and faces, or a grid
volume's bounds), the grid box (corner, voxel side, dims) and the normalised frame it is
voxelised into. When the geometry changes the box is recomputed and only the volumes
whose key changed are voxelised again (:attr:`Pipeline.revoxelised`); the rest are
reused as they are. The material stage mixes the contributions in the scene's volume
order, exactly as a whole-scene voxelisation does, so the grids are the same bit for bit.
When the grid box itself changes (a volume moved out of it or past its faces, the union
of the volumes grew or shrank, or ``resolution`` / ``margin`` changed) or the frame
changes, every key changes and every volume is voxelised again.

A session drops its methods' caches, and so the whole :class:`Pipeline`, whenever the
scene's geometry changes (it prepares the scene anew), so the contributions are kept per
engine outside it (:func:`kept_contributions`): host arrays, only those of the last
geometry stage run on that engine (at most one scene's weights, what the pipeline holds
anyway), dropped by :func:`release_contributions` or with the engine.
"""
from __future__ import annotations

import hashlib
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from ...device import Engine
from ...estimators.line_gather import Gatherer
from ...estimators.ray_density import (
    DensitySettings,
    build_map,
    estimate,
    pass_image,
    read_hits,
)
from ...estimators.segment_tree import TreeParams
from ...io.stats import Stats
from ...scene.model import Volume
from ...scene.normalised import Frame
from ...transport.view_paths import DeviceSegments, ViewPaths
from .grid import GridBox, make_box, scene_box
from .photons import Fields, MarchSettings, Radiance, light_pass, upload_fields
from .view import view_pass
from .voxelise import (
    blur,
    boundary_sides,
    gaussian_taps,
    medium_at_centres,
    mix,
    volume_fields,
    volume_weight,
)

STAGES = ("geometry", "material", "lighting", "view")

# per engine: {contribution_key: blurred weight} of the last geometry stage run on it
_CONTRIBUTIONS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def kept_contributions(eng: Engine) -> dict[str, np.ndarray]:
    """The contributions (blurred volume weights by :func:`contribution_key`) the last
    geometry stage on engine ``eng`` voxelised or reused; empty when there are none. The
    arrays are shared, not copies, and read-only."""
    return _CONTRIBUTIONS.get(eng, {})


def release_contributions(eng: Engine | None = None) -> None:
    """Drop the contributions kept for engine ``eng`` (every engine's when None)."""
    if eng is None:
        _CONTRIBUTIONS.clear()
    else:
        _CONTRIBUTIONS.pop(eng, None)


def beyond_mode(beyond: str, medium) -> str:
    """What ``beyond`` means for a scene's medium (a :class:`~clscatter.scene.model.Medium`
    or None): 'auto' is the outer grid where the medium has bounds for it to cover, and
    line-space gathering where it has none (an outer grid over the geometry alone would
    lose the light that leaves it)."""
    if beyond != "auto":
        return beyond
    return "grid" if medium is not None and medium.bounds is not None else "lsg"


@dataclass
class Pipeline:
    """Stage results of one scene on one device, kept between frames."""

    params: dict
    engine: object = None                            # the device its stages live on
    box: GridBox | None = None
    weights: list = field(default_factory=list)
    revoxelised: list = field(default_factory=list)  # volumes voxelised by the last update()
    fields: Fields | None = None
    radiance: Radiance | None = None
    ran: list = field(default_factory=list)          # stages run by the last update()
    timings: dict = field(default_factory=dict)      # seconds of the last update()'s stages
    counters: dict = field(default_factory=dict)

    def _beyond(self, ps) -> str:
        return beyond_mode(self.params["beyond"], ps.scene.medium)

    def invalidate(self, stage: str, eng=None) -> None:
        """Drop ``stage`` and every stage after it."""
        k = STAGES.index(stage)
        if k <= 2 and self.radiance is not None:
            if eng is not None:
                self.radiance.free(eng)
            self.radiance = None
        if k <= 1 and self.fields is not None:
            if eng is not None:
                self.fields.free(eng)
            self.fields = None
        if k == 0:
            self.box = None
            self.weights = []

    def release(self, eng=None) -> None:
        """Free every stage's device buffers (the engine's kept contributions stay:
        :func:`release_contributions` drops them)."""
        self.invalidate("geometry", eng if eng is not None else self.engine)

    def _timed(self, name: str, stats, fn):
        t = time.perf_counter()
        if stats is not None:
            with stats.stage(f"voxel_{name}"):
                out = fn()
        else:
            out = fn()
        self.timings[name] = time.perf_counter() - t
        self.ran.append(name)
        return out

    # ---- stages ----
    def _geometry(self, ps) -> None:
        """The grid box and every volume's blurred weight, reusing the engine's kept
        contributions whose :func:`contribution_key` is unchanged (equal to voxelising
        again, bit for bit); records the volumes voxelised again in :attr:`revoxelised`
        (their ``key``, or ``volumes[<index>]`` without one) and keeps only the current
        volumes' contributions for the engine."""
        p = self.params
        self.box = scene_box(ps.scene, ps.frame, p["resolution"], p["margin"])
        old = kept_contributions(ps.engine)
        kept, weights = {}, []
        for i, v in enumerate(ps.scene.volumes):
            key = contribution_key(self.box, v, ps.frame)
            w = kept.get(key)
            if w is None:
                w = old.get(key)
            if w is None:
                w = voxelise_volume(ps.engine, self.box, v, ps.frame)
                self.revoxelised.append(v.key or f"volumes[{i}]")
            kept[key] = w
            weights.append(w)
        _CONTRIBUTIONS[ps.engine] = kept
        self.weights = weights

    def _material(self, ps) -> None:
        p = self.params
        ss_m, sa_m = medium_at_centres(self.box, ps.medium)
        flds = [volume_fields(self.box, v, ps.frame) for v in ps.scene.volumes]
        n, ss, kappa = mix(self.weights, flds, ss_m, sa_m)
        self.fields = upload_fields(ps.engine, self.box, n, ss, kappa, p["eps"], p["eps2"],
                                    p["step_max"], boundary_sides(self.weights, flds, n))

    def _lighting(self, ps) -> None:
        p = self.params
        ms = MarchSettings(adaptive=p["adaptive"], ds_min=p["step_min"], min_rel=p["min_flux"],
                           steps_per_launch=p["steps_per_launch"], done_fraction=p["done_fraction"],
                           max_turns=ps.scene.render.max_depth)
        outer = (outer_box(ps, self.box, p["outer_resolution"])
                 if self._beyond(ps) == "grid" else None)
        self.radiance = light_pass(ps.engine, self.fields, ps, p["photons"], ms,
                                   test_surfaces=len(ps.bvh.order) > 0, smoothing=p["smoothing"],
                                   outer=outer, surface_photons=p["surface_photons"])

    def update(self, ps, stats=None, show_progress: bool = True, medium=None) -> dict:
        """Run the stages whose results are missing, then the view; returns
        ``{"surface": (H,W,3), "medium": (H,W,3)}`` (full surface term, seen through the grid).
        ``medium``: the density buffer of a scene with density volumes (``view_pass``)."""
        self.ran, self.timings, self.revoxelised = [], {}, []
        if self.box is None:
            self._timed("geometry", stats, lambda: self._geometry(ps))
        if self.fields is None:
            self._timed("material", stats, lambda: self._material(ps))
        if self.radiance is None:
            self._timed("lighting", stats, lambda: self._lighting(ps))
        res = self._timed("view", stats, lambda: self._view(ps, stats, show_progress, medium))
        self.counters = {**self.radiance.counters, **res["counters"],
                         "voxel_grid": self.box.describe(ps.frame)}
        return res

    def _view(self, ps, stats, show_progress, medium=None) -> dict:
        p = self.params
        on_surfaces = self.radiance.surface
        vr = view_pass(ps, self.fields, self.radiance, p["view_rounds"], show_progress,
                       test_surfaces=len(ps.bvh.order) > 0, medium=medium,
                       surface_photons=on_surfaces is not None)
        cam = ps.scene.camera
        direct = np.zeros((cam.height, cam.width, 3), np.float32)
        beyond = np.zeros_like(direct)
        photon_surface = np.zeros_like(direct)
        try:
            if vr.hits is not None and vr.hits.count:
                radius = p["surface_radius"] * ps.scene.scene_extent() / ps.frame.scale
                photon_surface, work = surface_estimate(
                    ps, self.fields.box, vr.hits, on_surfaces, self.radiance.straight,
                    surface_settings(p["surface_k"], radius), show_progress)
                vr.counters.update(work)
            if vr.segments.count and ps.num_lights and ps.has_medium:
                direct = direct_outside(ps, self.fields.box, vr.segments,
                                        self.params["direct_steps"])
                ex = self.radiance.exits
                beyond_how = self._beyond(ps)
                if beyond_how == "grid":
                    beyond = outer_view(ps, self.radiance, vr.segments)
                elif beyond_how == "lsg" and ex is not None and len(ex):
                    r = self.params["exit_radius"] * ps.scene.scene_extent() / ps.frame.scale
                    beyond = gather_exits(ps, vr.segments, ex, r, show_progress)
        finally:
            vr.release()
        return {"surface": vr.surface + photon_surface, "medium": vr.inside + direct + beyond,
                "inside": vr.inside, "direct_outside": direct, "beyond": beyond,
                "surface_direct": vr.surface, "surface_photons": photon_surface,
                "counters": vr.counters}


def voxelise_volume(eng: Engine, box: GridBox, v: Volume, frame: Frame) -> np.ndarray:
    """One volume's contribution: its coverage on ``box`` (``volume_weight``) blurred by
    the 9-tap Gaussian, float32 (nx, ny, nz), read-only (it is shared between renders);
    what a whole-scene voxelisation computes for it."""
    w = blur(eng, volume_weight(eng, box, v, frame), gaussian_taps())
    w.flags.writeable = False
    return w


def contribution_key(box: GridBox, v: Volume, frame: Frame) -> str:
    """Fingerprint of what one volume's blurred weight reads: its shape (a mesh's vertices
    and faces, or a grid volume's bounds; not its index or coefficients, not a grid's
    values, which only the material stage samples), the grid box (corner, voxel side,
    dims) and the normalised frame (centre, scale). Equal keys give equal weights."""
    h = hashlib.sha256()
    parts = [box.lo, box.h, tuple(box.dims), frame.centre, frame.scale]
    if v.mesh is not None:
        parts += ["mesh", v.mesh.vertices, v.mesh.faces]
    else:
        parts += ["bounds", *v.grid_bounds]
    for part in parts:
        if isinstance(part, np.ndarray):
            a = np.ascontiguousarray(part)
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())
        else:
            h.update(repr(part).encode())
    return h.hexdigest()


def surface_settings(k: int, radius: float) -> DensitySettings:
    """The surface photon map's settings: ``k`` nearest photons within ``radius``
    (normalised), Epanechnikov weights, a static kd-tree over the photons' hit points (the
    photon map's: ``photonmap``'s defaults, 16 photons a leaf)."""
    return DensitySettings(k=int(k), kernel="epanechnikov", max_radius=float(radius), lazy=False,
                           tree=TreeParams(c_min=16, r_min=0.0, d_max=40, alpha_deg=0.0))


def surface_estimate(ps, box: GridBox, hits: DeviceSegments, photons: np.ndarray,
                     straight: np.ndarray, settings: DensitySettings,
                     show_progress: bool = False) -> tuple[np.ndarray, dict]:
    """The light the photons bring to the view paths' diffuse ``hits`` (DIFFUSE_HIT records
    on the device, sorted, with pixel offsets), summed into pixels: (H, W, 3) and counters.

    Per light, the photon-map estimate E = sum w_i Phi_i / (pi R^2) over the ``settings.k``
    nearest of its ``photons`` arriving from the front (R: the k-th distance, at most
    ``settings.max_radius``; ``clscatter/estimators/ray_density.py``, the estimator of
    ``photonmap``) at every hit, times the hit's weight (throughput x albedo / pi), on
    the device. Then the seam: the hits' straight direct light lacks, per light, what
    crosses the grid's box, and a density estimate blurs the edge of the photons' region
    by its radius (light spilled outside, missing inside). Where the hit's shadow ray
    passes within ``max_radius`` of the box's surface (:func:`seam_correction`) the light
    the occluder took is added back and the same estimate of the ``straight`` photons
    (the same photons gone on straight through the grid) taken off: where the grid
    changes nothing there the two estimates are equal and the hit gets exactly the
    straight direct light, and elsewhere the difference is the grid's effect, estimated.
    The hits' positions and normals are read once for the host-built trees' queries."""
    cam = ps.scene.camera
    img = np.zeros((cam.height, cam.width, 3), np.float64)
    host = read_hits(ps, hits)
    st = Stats()
    near_hits = 0
    for li in range(ps.num_lights):
        mine = photons[photons["light"] == li]
        if len(mine):
            img += pass_image(ps, hits, host, mine, "photonmap", settings, st, show_progress)
        corr, near = seam_correction(ps, box, hits, host, li, straight[straight["light"] == li],
                                     settings)
        img += corr
        near_hits += near
    work = {f"voxel_surface_{k[len('photonmap_'):]}": int(v) for k, v in st.values.items()
            if k in ("photonmap_nodes_visited", "photonmap_refs_tested")}
    work["voxel_surface_seam_hits"] = near_hits
    return img.astype(np.float32), work


def seam_correction(ps, box: GridBox, hits: DeviceSegments, host: np.ndarray, light: int,
                    straight: np.ndarray, settings: DensitySettings) -> tuple[np.ndarray, int]:
    """Light ``light``'s seam correction of the surface estimate at the hits whose shadow
    ray passes within ``settings.max_radius`` of the grid box's surface (``voxel_seam``:
    those hits and the straight direct light the grid's occluder took from them): weight x
    (that light - the photon-map estimate of the ``straight`` photons), summed into pixels
    (H, W, 3); and how many hits it corrected."""
    eng = ps.engine
    cam = ps.scene.camera
    img = np.zeros((cam.height, cam.width, 3), np.float64)
    out = eng.empty(16 * max(hits.count, 1))
    try:
        ps.call("voxel", "voxel_seam", hits.count, hits=hits.buf, n=hits.count, light_index=light,
                glo=box.lo4(), ghi=box.hi4(), delta=np.float32(settings.max_radius), out=out)
        took = eng.read(out, (hits.count, 4), np.float32)
    finally:
        eng.free(out)
    near = np.flatnonzero(took[:, 3] > 0)
    if len(near) == 0:
        return img, 0
    e = np.zeros((len(near), 3), np.float64)
    if len(straight):
        rmap = build_map(eng, straight, "photonmap", settings)
        try:
            e = estimate(rmap, host["p"][near, :3], host["n"][near, :3], "photonmap", settings)[0]
        finally:
            rmap.release()
    value = host["weight"][near, :3] * (took[near, :3].astype(np.float64) - e)
    flat = img.reshape(-1, 3)
    np.add.at(flat, host["pixel"][near], value)
    return img, int(len(near))


def direct_outside(ps, box: GridBox, segs: DeviceSegments, steps: int,
                   per_launch: int = 65536) -> np.ndarray:
    """raymarch's direct single scattering over ``segs`` with the grid box occluding
    (``cl_kernels/voxel_direct.cl``): the light that crosses the grid is the photons'.
    Launched over the device segments and summed into pixels there (only the image is
    read back)."""
    eng = ps.engine
    med2 = np.zeros(2, ps.medium.dtype)
    med2[0] = ps.medium
    med2[1]["bmin"][:3], med2[1]["bmax"][:3] = box.lo, box.hi
    n = segs.count
    chunk = max(1, min(per_launch, n))
    med_buf, out = eng.to_device(med2), eng.empty(16 * max(n, 1))
    seed = np.uint32((ps.scene.render.seed * 7919 + 17) & 0xFFFFFFFF)   # as raymarch
    try:
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            # the grid's box rides in a second medium record
            ps.call("voxel_direct", "raymarch", m, medium=med_buf, segs=segs.buf,
                     seg_offset=start, num_segs=m, scale=out, use_scale=0, steps=steps,
                     seed=seed, out=out)
        return segs.accumulate(out)
    finally:
        eng.free(med_buf, out)


def gather_exits(ps, segs: DeviceSegments, exits: np.ndarray, radius: float,
                 show_progress: bool = True) -> np.ndarray:
    """Single scattering outside the grid of the light that left it (the photons' straight
    continuations), by lsg's line-space gathering with ``radius`` (normalised units).

    The :class:`~clscatter.estimators.line_gather.Gatherer` needs the view segments on the host
    (their bounding box clips the lighting segments before its host line tree is built),
    so they are read back once for it; it gathers over the device copy itself, and its
    per-segment estimates stay on the device, summed into pixels there."""
    views = ViewPaths(None, None, device=segs).segments
    gat = Gatherer(ps.engine, views, ps.medium, radius, show_progress=show_progress,
                   views_buf=segs.buf)
    try:
        gat.add(exits)
        return gat.image(segs)
    finally:
        gat.release()


def outer_box(ps, box: GridBox, resolution: int) -> GridBox:
    """The coarse grid for the light beyond the voxel grid: the medium's bounds when it
    has them, else the box of the scene's near geometry (far objects left out:
    :meth:`~clscatter.transport.prepared.PreparedScene.near_box`) and the voxel grid."""
    if ps.medium["bounded"]:
        lo, hi = ps.medium["bmin"][:3].astype(np.float64), ps.medium["bmax"][:3].astype(np.float64)
    else:
        lo, hi = box.lo.copy(), box.hi.copy()
        near = ps.near_box()
        if near is not None:
            lo, hi = np.minimum(lo, near[0]), np.maximum(hi, near[1])
    return make_box(lo, hi, resolution)


def outer_view(ps, radiance: Radiance, segs: DeviceSegments) -> np.ndarray:
    """Single scattering along ``segs`` of the light held by the outer grid, launched over
    the device segments and summed into pixels there (only the image is read back)."""
    eng = ps.engine
    ob = radiance.outer
    out = eng.empty(16 * max(segs.count, 1))
    try:
        ps.call("voxel", "outer_view", segs.count, segs=segs.buf, count=segs.count,
                 olo=ob.lo4(), od=ob.dims4(), oh=ob.h,
                 rad=radiance.outer_rad, dirs=radiance.outer_dirs, out=out)
        return segs.accumulate(out)
    finally:
        eng.free(out)
