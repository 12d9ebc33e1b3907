"""Photons: generation where light enters the grid, adaptive marching with deposition.

Generation (``photon_emit``, Sun et al. 2008 sec. 4.3). The paper renders the grid's
faces into a shadow map from the light and makes one photon per covered pixel. Here the
"shadow map" is a stratified S x S set of jittered samples over what the light sends
towards the grid, and the photon starts where its ray enters the grid box:

* point light: directions uniform in solid angle over the smallest cone around the
  direction to the grid's centre that holds all its corners (the whole sphere when the
  light is in the grid or too close), flux I * Omega / S^2 each;
* spot light: the same cone or the spot's own cone, whichever is narrower; directions
  outside the spot's cone carry nothing;
* directional light: start points on the rectangle facing the light that covers the
  grid's shadow, flux E * area / S^2 each.

A photon's flux is attenuated by the scene medium between the light and the grid and it
is dropped when a surface blocks the way (shadow ray). Inside the grid the radiance per
unit length it deposits, integrated over a voxel and divided by the voxel's volume, is the
fluence rate there (a point light at distance d gives I / d^2), so nothing else needs
normalising.

Marching (``photon_march``, sec. 4.4 / 5.3): see the kernel's comment. The host launches
it repeatedly, ``steps_per_launch`` steps each time, until no more than
``1 - done_fraction`` of the photons are still live (the paper stops at 1/1000), then
smooths the deposited grids with the 3x3x3 binomial kernel (the paper's final smoothing).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...device import AppendBuffer, Engine, structs
from ...geometry import box_corners, perpendicular_axes
from ...transport import primitives as prim
from .grid import GridBox
from .octree import Octree, build_octree
from .voxelise import (
    SMOOTH_TAPS,
    blur_buffers,
    gradient,
    interior_gradient,
    medium_at_centres,
)


@dataclass
class Fields:
    """Device grids of one material state: index, its gradient, scattering, extinction,
    octree, boundary sides. Built by :func:`upload_fields`."""

    box: GridBox
    n: object
    grad: object
    sigma_s: object       # float4 per voxel (rgb)
    kappa: object         # float4 per voxel (rgb)
    octree: Octree
    n_host: np.ndarray
    boundary: object = None   # float4 per voxel: w, n_lo, n_hi (voxelise.boundary_sides)

    def free(self, eng: Engine) -> None:
        eng.free(self.n, self.grad, self.sigma_s, self.kappa)
        if self.boundary is not None:
            eng.free(self.boundary)
        self.octree.free(eng)


def upload_fields(eng: Engine, box: GridBox, n: np.ndarray, sigma_s4: np.ndarray, kappa4: np.ndarray,
                  eps: float, eps2: float, limit: float, boundary: np.ndarray | None = None) -> Fields:
    """Upload n, sigma_s, kappa (host grids) and build grad n and the octree on the device.
    ``boundary`` ((nx, ny, nz, 4), :func:`~.voxelise.boundary_sides`) says where the
    volumes' sharp boundaries lie and between which indices: paths cross them by Snell's
    law with the Fresnel transmittance, and ``grad`` is then the interior gradient
    (:func:`~.voxelise.interior_gradient`: the boundaries' jumps taken out); None: no
    boundaries (paths bend through every index change by the ray equation alone)."""
    n = np.ascontiguousarray(n, np.float32)
    nb = eng.to_device(n)
    b = (np.zeros((*box.dims, 4), np.float32) if boundary is None
         else np.ascontiguousarray(boundary, np.float32))
    grad, bb = gradient(eng, box, nb), eng.to_device(b)
    if boundary is not None:
        interior_gradient(eng, box, grad, bb)
    return Fields(box, nb, grad, eng.to_device(np.ascontiguousarray(sigma_s4, np.float32)),
                  eng.to_device(np.ascontiguousarray(kappa4, np.float32)),
                  build_octree(eng, box, nb, eps, eps2, limit), n, bb)


@dataclass
class Radiance:
    """The lighting pass's product: per voxel, flux-weighted length (rgb) and the same
    summed over rgb times the travel direction (device float4 grids), smoothed."""

    rad: object
    dirs: object
    counters: dict = field(default_factory=dict)
    exits: np.ndarray | None = None     # structs.LIGHT_SEGMENT: the light beyond the grid
    surface: np.ndarray | None = None   # structs.RAY_PIECE: photons on diffuse surfaces
    straight: np.ndarray | None = None  # structs.RAY_PIECE: the same photons gone on straight
    outer: GridBox | None = None        # the coarse grid that holds the light beyond the grid
    outer_rad: object = None
    outer_dirs: object = None

    def free(self, eng: Engine) -> None:
        eng.free(self.rad, self.dirs)
        if self.outer_rad is not None:
            eng.free(self.outer_rad, self.outer_dirs)

    def host(self, eng: Engine, box: GridBox) -> tuple[np.ndarray, np.ndarray]:
        return (eng.read(self.rad, (*box.dims, 4), np.float32),
                eng.read(self.dirs, (*box.dims, 4), np.float32))


@dataclass
class Emitter:
    """Kernel arguments of ``photon_emit`` for one light."""

    S: int
    axis: np.ndarray
    cos_max: float
    rect: np.ndarray          # (3, 4) origin, u, v
    flux: np.ndarray          # (4,) per photon
    solid_angle: float = 0.0


def emitter(light: np.ndarray, box: GridBox, photons: int) -> Emitter:
    """Where and how photons of ``light`` (a structs.LIGHT record) are generated."""
    S = max(1, int(math.ceil(math.sqrt(photons))))
    N = S * S
    P = light["power"][:3].astype(np.float64)
    rect = np.zeros((3, 4), np.float32)
    axis = np.array([0.0, 0.0, 1.0, 0.0], np.float32)
    lo, hi = box.lo, box.hi
    corners = box_corners(lo, hi)
    if light["type"] == structs.LIGHT_DIRECTIONAL:
        d = light["direction"][:3].astype(np.float64)
        d /= np.linalg.norm(d)
        e1, e2 = perpendicular_axes(d)
        c1, c2, cd = corners @ e1, corners @ e2, corners @ d
        pad = 1e-4 * box.h
        rect[0, :3] = (c1.min() - pad) * e1 + (c2.min() - pad) * e2 + (cd.min() - box.h) * d
        rect[1, :3] = (c1.max() - c1.min() + 2 * pad) * e1
        rect[2, :3] = (c2.max() - c2.min() + 2 * pad) * e2
        area = float(np.linalg.norm(rect[1, :3]) * np.linalg.norm(rect[2, :3]))
        flux = P * area / N
        return Emitter(S, axis, -1.0, rect, np.array([*flux, 0.0], np.float32))
    pos = light["position"][:3].astype(np.float64)
    centre = (lo + hi) / 2
    to_c = centre - pos
    dist = np.linalg.norm(to_c)
    cos_box = -1.0
    if dist > 0 and not np.all((pos >= lo) & (pos <= hi)):
        a = to_c / dist
        dirs = corners - pos
        cos_box = float(np.min(dirs @ a / np.linalg.norm(dirs, axis=1)))
        if cos_box <= 0.0:        # very close: the cone would not be convex, use the sphere
            cos_box = -1.0
        axis[:3] = a
    cos_max = cos_box
    if light["type"] == structs.LIGHT_SPOT and float(light["cos_cutoff"]) > cos_box:
        cos_max = float(light["cos_cutoff"])
        axis[:3] = light["direction"][:3]
    omega = 2 * math.pi * (1 - cos_max)
    flux = P * omega / N
    return Emitter(S, axis, cos_max, rect, np.array([*flux, 0.0], np.float32), omega)


@dataclass
class MarchState:
    """Photon states on the device (pos.w = 1 while live; ``crossing``: a float per
    photon, its side of the volumes' boundaries (0 outside, 1 inside, -1 not known yet:
    the start))."""

    pos: object
    vel: object
    flux: object
    count: int
    crossing: object = None

    def free(self, eng: Engine) -> None:
        eng.free(self.pos, self.vel, self.flux)
        if self.crossing is not None:
            eng.free(self.crossing)

    def host(self, eng: Engine) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(eng.read(b, (self.count, 4), np.float32) for b in (self.pos, self.vel, self.flux))


@dataclass
class MarchSettings:
    adaptive: bool = True
    ds_min: float = 1.0            # voxels
    min_rel: float = 1e-3          # a photon dies below this fraction of its start flux
    steps_per_launch: int = 16
    done_fraction: float = 0.999   # stop launching when this fraction has finished
    max_launches: int = 4096
    max_turns: int = 16            # total internal reflections that end a photon (render.max_depth)


def march(eng: Engine, fields: Fields, state: MarchState, rad, dirs, ms: MarchSettings,
          bvh=None, test_surfaces: bool = False) -> dict:
    """Launch ``photon_march`` until almost all photons are done; deposits add into
    ``rad``/``dirs``. Returns counters: launches, steps, photons still live."""
    box = fields.box
    if state.crossing is None:
        state.crossing = no_crossings(eng, state.count)
    bnd = (fields.boundary if fields.boundary is not None
           else eng.to_device(np.zeros((box.size, 4), np.float32)))
    counters = eng.empty(8)
    nodes, tris = (bvh if bvh is not None else (fields.n, fields.n))
    launches = steps = 0
    live = state.count
    try:
        while launches < ms.max_launches and live > (1.0 - ms.done_fraction) * state.count:
            eng.cl.enqueue_fill_buffer(eng.queue, counters, np.zeros(1, np.int32), 0, 8)
            eng.call("voxel", "photon_march", state.count, pos=state.pos, vel=state.vel,
                     flux=state.flux, count=state.count, steps=ms.steps_per_launch,
                     glo=box.lo4(), ghi=box.hi4(), dims=box.dims4(), h=box.h, n_grid=fields.n,
                     grad=fields.grad, kappa=fields.kappa, level=fields.octree.level,
                     smax=fields.octree.smax, adaptive=ms.adaptive,
                     ds_min=ms.ds_min * box.h, min_rel=ms.min_rel, nodes=nodes,
                     tris=tris, test_surfaces=test_surfaces, boundary=bnd,
                     crossing=state.crossing, max_turns=ms.max_turns, rad=rad, dirs=dirs,
                     counters=counters)
            c = eng.read(counters, 2, np.int32)
            live, steps, launches = int(c[0]), steps + int(c[1]), launches + 1
    finally:
        eng.free(counters)
        if fields.boundary is None:
            eng.free(bnd)
    return {"launches": launches, "steps": steps, "live_at_end": live}


def no_crossings(eng: Engine, count: int):
    """A device float per photon, -1: its side of the boundaries not known yet."""
    return eng.to_device(np.full(max(count, 1), -1.0, np.float32), True)


def start_state(eng: Engine, pos: np.ndarray, vel: np.ndarray, flux: np.ndarray) -> MarchState:
    """Photon states from host arrays (N, 4) (tests and custom emitters)."""
    f = np.array(flux, np.float32)
    f[:, 3] = f[:, :3].max(axis=1)
    return MarchState(eng.to_device(np.asarray(pos, np.float32), True),
                      eng.to_device(np.asarray(vel, np.float32), True), eng.to_device(f, True), len(pos))


def smooth(eng: Engine, box: GridBox, buf) -> None:
    """3x3x3 binomial smoothing of a float4 grid in place (sec. 4.4, last step)."""
    tmp = eng.empty(16 * box.size)
    taps = eng.to_device(SMOOTH_TAPS)
    try:
        blur_buffers(eng, buf, tmp, box.dims, 4, taps, 1)
        eng.cl.enqueue_copy(eng.queue, buf, tmp, byte_count=16 * box.size)
    finally:
        eng.free(tmp, taps)


def exits_by_photon(eng: Engine, app: AppendBuffer, n: int, photons: int,
                    rec: np.dtype = structs.LIGHT_SEGMENT) -> np.ndarray:
    """The ``n`` records (``rec``, with a ``ray`` field: the photon) that one launch of
    ``photon_exits`` (lighting segments) or ``photon_surface`` (photons on surfaces)
    appended to ``app`` (at most one per photon, in no fixed order), bucket-sorted by
    photon index on the device (``record_keys`` of view_paths.cl takes any record's int
    words), then read back: lsg's line tree (``gather_exits``) and the surface photon map
    are built from them on the host, so this read is what those host structures need; the
    order makes it reproducible."""
    if n == 0:
        return np.zeros(0, rec)
    keys, unused = eng.empty(4 * n), eng.empty(4 * n)
    perm = offsets = out = None
    try:
        word = rec.fields["ray"][1] // 4
        eng.call("view_paths", "record_keys", n, records=app.buf, stride=rec.itemsize // 4,
                 sample_word=word, branch_word=word, n=n, base=0, keys=keys, branch=unused)
        perm, offsets = prim.bucket_sort(eng, keys, n, photons)
        out = prim.gather(eng, app.buf, perm, n, rec.itemsize)
        return eng.read(out, n, rec)
    finally:
        eng.free(keys, unused, *(b for b in (perm, offsets, out) if b is not None))


def light_pass(eng: Engine, fields: Fields, ps, photons: int, ms: MarchSettings,
               test_surfaces: bool, smoothing: bool = True, outer: GridBox | None = None,
               surface_photons: bool = False) -> Radiance:
    """Emit ``photons`` per light of the prepared scene ``ps``, march them, deposit,
    smooth. ``ps.dev`` supplies the scene BVH, lights and medium. Photons that leave the
    grid become lighting segments (``exits``, sorted by (light, photon)) and, with an
    ``outer`` grid, are also deposited there as straight lines (``photon_outer``). With
    ``surface_photons`` (and surfaces in the scene), those that reach a diffuse surface in
    or beyond the grid are kept as photon-map records (``surface``, ``photon_surface``,
    sorted by (light, photon)), and so are the same photons gone on straight from where
    they entered the grid, as if it held nothing (``straight``: the surface estimate's
    seam correction)."""
    box = fields.box
    rad, dirs = eng.zeros(16 * box.size), eng.zeros(16 * box.size)
    orad = odirs = okappa = None
    if outer is not None:
        orad, odirs = eng.zeros(16 * outer.size), eng.zeros(16 * outer.size)
        ss, sa = medium_at_centres(outer, ps.medium)
        k4 = np.zeros((*outer.dims, 4), np.float32)
        k4[..., :3] = ss + sa
        okappa = eng.to_device(k4)
    total = {"voxel_photons": 0, "voxel_photons_entering": 0, "voxel_launches": 0,
             "voxel_photon_steps": 0, "voxel_photons_unfinished": 0}
    seed = np.uint32((ps.scene.render.seed * 40503 + 7) & 0xFFFFFFFF)
    exits: list[np.ndarray] = []
    on_surfaces: list[np.ndarray] = []
    straights: list[np.ndarray] = []
    surface_photons = surface_photons and test_surfaces
    app = AppendBuffer(eng, structs.LIGHT_SEGMENT, 1024)
    app_s = AppendBuffer(eng, structs.RAY_PIECE, 1024) if surface_photons else None
    entering = eng.empty(4)
    for li in range(ps.num_lights):
        em = emitter(ps.lights[li], box, photons)
        N = em.S * em.S
        st = MarchState(eng.empty(16 * N), eng.empty(16 * N), eng.empty(16 * N), N, no_crossings(eng, N))
        try:
            prim.fill_int(eng, entering, 1, 0)
            ps.call("voxel", "photon_emit", N, light_index=li, S=em.S,
                     seed=seed, axis=em.axis, cos_max=em.cos_max, rect_o=em.rect[0],
                     rect_u=em.rect[1], rect_v=em.rect[2], flux_per_photon=em.flux,
                     glo=box.lo4(), ghi=box.hi4(), dims=box.dims4(), h=box.h, n_grid=fields.n,
                     pos=st.pos, vel=st.vel, flux=st.flux, entering=entering)
            alive = int(eng.read(entering, 1, np.int32)[0])
            if surface_photons:
                straights.append(surface_records(eng, ps, st, li, app_s, straight=True))
            c = march(eng, fields, st, rad, dirs, ms, (ps.dev.nodes, ps.dev.tris), test_surfaces)
            got = app.call_on_device("voxel", "photon_exits", N, pos=st.pos, vel=st.vel,
                                     flux=st.flux, count=N, light_index=li,
                                     **ps.scene_args("voxel", "photon_exits"))
            exits.append(exits_by_photon(eng, app, got, N))
            if surface_photons:
                on_surfaces.append(surface_records(eng, ps, st, li, app_s, straight=False))
            if outer is not None:
                ps.call("voxel", "photon_outer", N, pos=st.pos, vel=st.vel, flux=st.flux, count=N,
                         olo=outer.lo4(), ohi=outer.hi4(), od=outer.dims4(), oh=outer.h,
                         okappa=okappa, rad=orad, dirs=odirs)
        finally:
            st.free(eng)
        total["voxel_photons"] += N
        total["voxel_photons_entering"] += alive
        total["voxel_launches"] += c["launches"]
        total["voxel_photon_steps"] += c["steps"]
        total["voxel_photons_unfinished"] += c["live_at_end"]
    app.release()
    if app_s is not None:
        app_s.release()
    eng.free(entering)
    ex = np.concatenate(exits) if exits else np.zeros(0, structs.LIGHT_SEGMENT)
    total["voxel_photons_leaving"] = int(len(ex))
    on_surface = straight = None
    if surface_photons:
        none = np.zeros(0, structs.RAY_PIECE)
        on_surface = np.concatenate(on_surfaces) if on_surfaces else none
        straight = np.concatenate(straights) if straights else none
        total["voxel_surface_photons"] = int(len(on_surface))
    if smoothing:
        smooth(eng, box, rad)
        smooth(eng, box, dirs)
    if outer is not None:
        eng.free(okappa)
        if smoothing:
            smooth(eng, outer, orad)
            smooth(eng, outer, odirs)
    return Radiance(rad, dirs, total, ex, on_surface, straight, outer, orad, odirs)


def surface_records(eng: Engine, ps, st: MarchState, light: int, app: AppendBuffer,
                    straight: bool) -> np.ndarray:
    """``photon_surface`` over the photon states ``st`` of light ``light``: the photons
    that reached a diffuse surface (after marching), or with ``straight`` (the states
    ``photon_emit`` left) those that would have gone on straight through the grid, as
    RAY_PIECE records sorted by photon."""
    got = app.call_on_device("voxel", "photon_surface", st.count, pos=st.pos, vel=st.vel,
                             flux=st.flux, count=st.count, light_index=light,
                             straight=int(straight), **ps.scene_args("voxel", "photon_surface"))
    return exits_by_photon(eng, app, got, st.count, structs.RAY_PIECE)
