"""Progressive surface density estimation (``raymap``, ``photonmap``): the gather radius of
every hit, its shrinking from pass to pass, and the passes themselves.

*First pass, automatic radius.* Every diffuse hit x gathers its ``k`` nearest rays
(photons) within ``max_radius`` (:func:`~.ray_density.estimate_on_device`): its radius
``R_1(x)`` is the distance of the k-th, the radius whose disc holds ``k`` of this pass's
rays at x (``max_radius`` where fewer lie within). With an explicit radius r the domain is
r instead (the k nearest where more than k lie within). The estimates and the radii are in
the normalised frame, so they do not depend on the scene's scale.

*No disc smaller than the camera sample's cell.* A pixel is the mean of its radiance over
its footprint, and its ``spp`` camera samples are fixed for the whole render: each stands
for a cell of ``1 / spp`` of the footprint. Where the rays crowd (a caustic's focus, where
the irradiance is singular) the k nearest lie within a disc far smaller than that cell,
and the estimate at the sample's point follows the singular irradiance there, growing or
falling without limit as rays are added while the pixel's true mean stays put. So every hit's radius is at least the radius of a disc of
its cell's area, ``c(x) = f(x) / sqrt(pi spp)`` (:func:`cell_radii`; ``f(x)`` the pixel
footprint at x, :func:`footprints`): where ``R_1(x)`` is smaller the hit gathers every ray
within ``c(x)`` instead (a fixed-radius splat over those hits, :mod:`.disc_splat`), so the
estimate is the irradiance averaged over a disc the size of its cell and converges to a
finite image, blurred by at most a camera sample's share of a pixel.

*Later passes.* Pass i (from 1) traces fresh rays (``seed_offset`` i) and gathers at every
hit all rays within the fixed radius ``R_i(x) = max(s_i B(x), c(x))``, the base
``B(x) = max(R_1(x), c(x))`` and ``s_i^2 = prod_{j<i} (j + alpha) / (j + 1)``
(:func:`ppm_scales`): progressive photon mapping's rule for a 2-D kernel (Hachisuka et
al. 2008; Knaus and Zwicker 2011, ``r_{i+1}^2 = r_i^2 (i + alpha) / (i + 1)``), down to
the sample's cell. A pass's expected count within its disc falls like ``i^(alpha - 1)``
while the mean of ``n`` passes has variance falling like ``n^-alpha`` and a blur (bias ~
r^2) falling like ``n^(alpha - 1)`` until the radii reach the cells: the mean converges
(to the cell-averaged image).
These fixed-radius passes need no nearest-neighbour search: every segment adds itself to
the hits whose disc it qualifies for (:mod:`.disc_splat`, over a tree of the hits built
once), so a hit gathers every ray within its radius.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from ..io.stats import Stats
from ..transport.view_paths import DeviceSegments, trace_diffuse_hits_on_device
from .disc_splat import HitDiscs
from .ray_density import (
    DensitySettings,
    caustic_pieces,
    hit_irradiance,
    pass_image,
    read_hits,
    weighed_image,
)

#: under a deadline a pass has at least this many rays (or all of them, if fewer) and at
#: most RESIZE times (or 1 / RESIZE of) the rays of the pass its cost was measured on
MIN_PASS_RAYS = 2000
RESIZE = 8.0
#: under a deadline the passes are sized as if it were shared among at most this many
#: (however many ``passes`` allows; more run if time is left): the first pass's rays set
#: the base radius, which falls with them faster than the later passes' shrinking makes
#: up for, so a few large passes blur less than many small ones; four are the k-nearest
#: opening pass and three for the error estimate's independent halves
MAX_SPLIT = 4


def sized_rays(rays: int, measured: tuple[int, float] | None, want: float) -> int:
    """Rays for a pass that should take ``want`` seconds, given that ``measured = (rays,
    seconds)`` of a pass like it (None: nothing measured: ``rays``), as if its cost grew in
    proportion to its rays; at most ``rays`` (the parameter's count) and at least
    :data:`MIN_PASS_RAYS`."""
    if measured is None or not np.isfinite(want):
        return int(rays)
    n, secs = measured
    ratio = min(max(want / max(secs, 1e-6), 1.0 / RESIZE), RESIZE)
    return int(min(rays, max(min(MIN_PASS_RAYS, rays), n * ratio)))


def ppm_scales(alpha: float, passes: int) -> np.ndarray:
    """Radius factors ``s_1 .. s_passes`` of progressive passes: ``s_1 = 1``,
    ``s_{i+1}^2 = s_i^2 (i + alpha) / (i + 1)`` (a 2-D kernel's rule, module docstring)."""
    s = np.empty(max(int(passes), 0))
    cur = 1.0
    for i in range(len(s)):
        s[i] = np.sqrt(cur)
        cur *= (i + 1 + alpha) / (i + 2)
    return s


def footprints(ps, points: np.ndarray) -> np.ndarray:
    """The pixel footprint at ``points`` (normalised frame): their distance from the camera
    times one pixel's width at unit distance (seen through mirrors or glass, the straight
    distance: a guide, not a measure)."""
    cam = ps.camera
    pix = 2.0 * float(np.linalg.norm(cam["right"][:3])) / max(int(cam["width"]), 1)
    dist = np.linalg.norm(np.asarray(points, np.float64)[:, :3]
                          - cam["origin"][:3].astype(np.float64), axis=1)
    return dist * pix


@dataclass
class SurfacePasses:
    """What the passes gave: the image (their mean), each pass's seconds, the median base
    radius over the lit hits (normalised; 0 without any), the radius factors used and why
    they stopped."""

    image: np.ndarray
    seconds: list[float] = field(default_factory=list)
    rays: list[int] = field(default_factory=list)          # traced by each pass
    radius: float = 0.0
    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stopped_by: str = "passes"
    error: float | None = None
    hits: int = 0                         # diffuse hits estimated
    sized_from: str = "none"              # what the passes' rays were sized from


def cell_radii(foot: np.ndarray, spp: int) -> np.ndarray:
    """``c(x)`` of the module docstring: the radius of a disc whose area is one camera
    sample's share of the pixel footprints ``foot``, ``foot / sqrt(pi spp)``."""
    return np.asarray(foot, np.float64) / np.sqrt(np.pi * max(int(spp), 1))


def base_radii(first: np.ndarray, cell: np.ndarray, explicit: float) -> np.ndarray:
    """``B(x)`` of the module docstring: ``explicit`` if it is positive, else the first
    pass's radius ``first``; at least the sample's cell radius ``cell``."""
    b = np.full(len(first), explicit) if explicit > 0 else np.asarray(first, np.float64)
    return np.maximum(b, np.asarray(cell, np.float64))


def progressive_surface_caustics(ps, estimator: str, rays: int, settings: DensitySettings,
                                 stats: Stats, prog, alpha: float, radius: float = 0.0,
                                 seed: int = 0, show_progress: bool = False,
                                 sample_range: tuple[int, int] | None = None,
                                 first_cost: tuple[int, float] | None = None,
                                 predict_first: Callable[[int, int], float | None] | None = None,
                                 kept_hits: DeviceSegments | None = None) -> SurfacePasses:
    """The surface caustics (as :func:`~.ray_density.surface_caustics`) refined by passes
    while ``prog`` (a :class:`~clscatter.transport.progressive.Progression`) says so;
    each later pass's own image goes to ``prog.add`` with its radius (the median base
    radius times ``s_i``; the first, k-nearest, pass is another estimator and stays out of
    the error estimate). ``radius``: explicit first radius (normalised; 0: automatic);
    ``seed``: selects independent sets of rays (pass i uses ``seed_offset = i + (seed <<
    16)``). The first pass with ``seed`` 0 is exactly ``surface_caustics``.

    Under a deadline (``prog.budgeted``) the passes' rays are sized to the first pass's
    share of the time (:func:`sized_rays`; the time left over the planned passes, at
    least over :data:`MAX_SPLIT`) from ``first_cost`` (rays and seconds of an
    earlier first pass over the same hits, e.g. a session's previous render) or else from
    ``predict_first(rays, hits)`` (the seconds a first pass of ``rays`` over ``hits``
    diffuse hits should take on this device, e.g. learnt from earlier renders; None: not
    known); with neither, all ``rays``. Every later pass traces as many (the radius rule
    assumes passes alike); the passes stop when the next would end past the deadline.
    ``sized_from`` in the result says which of the three it was (``session``,
    ``calibration``, ``none``).

    ``kept_hits``: the diffuse hits of these camera samples already on the device (a
    :class:`~clscatter.transport.view_paths.DeviceSegments` the view paths recorded; None:
    traced here and freed after). Their host copy and the splats' tree over them are
    derived once and kept with them, so a warm re-render after a light change reuses
    all three."""
    cam = ps.scene.camera
    out = SurfacePasses(np.zeros((cam.height, cam.width, 3), np.float32))
    if ps.num_lights == 0:
        return out
    dev = kept_hits
    if dev is None:
        with stats.stage(f"{estimator}_trace"):
            dev = trace_diffuse_hits_on_device(ps, sample_range=sample_range)
    try:
        with stats.stage(f"{estimator}_trace"):
            hits = dev.derived("surface_hits_host", lambda: ([], read_hits(ps, dev)))
        stats.set(diffuse_hits=int(dev.count))
        out.hits = int(dev.count)
        if first_cost is not None:
            out.sized_from = "session"
        elif predict_first is not None and prog.budgeted and dev.count > 0:
            seconds = predict_first(int(rays), int(dev.count))
            if seconds is not None and seconds > 0:
                first_cost, out.sized_from = (int(rays), float(seconds)), "calibration"
        if dev.count > 0:
            _run_passes(ps, dev, hits, estimator, rays, settings, stats, prog, alpha, radius,
                        seed, show_progress, out, first_cost)
    finally:
        if dev is not kept_hits:
            dev.release()
    return out


def _run_passes(ps, dev, hits, estimator: str, rays: int, settings: DensitySettings,
                stats: Stats, prog, alpha: float, radius: float, seed: int,
                show_progress: bool, out: SurfacePasses,
                first_cost: tuple[int, float] | None = None) -> None:
    """The pass loop of :func:`progressive_surface_caustics`, filling ``out``: until a
    pass has rays, each is a first pass (it sets the radii); then fixed radii ``s_i B``."""
    total = None
    base = None
    discs = None               # the hits' tree for the later passes' splats (kept with the hits)
    scales: list[float] = []
    first = settings if radius <= 0 else replace(settings, max_radius=radius)
    cell = cell_radii(footprints(ps, hits["p"]), ps.scene.camera.spp)
    i = 0
    # every pass traces the same rays (progressive photon mapping's radius rule assumes
    # passes alike): under a deadline, as many as the first pass's share of it allows
    share = max(prog.pass_seconds(), prog.remaining() / MAX_SPLIT)
    n = sized_rays(rays, first_cost, share) if prog.budgeted else rays
    while True:
        expected = None
        if prog.budgeted and out.seconds:
            expected = out.seconds[-1]
        elif prog.budgeted and first_cost is not None:
            expected = first_cost[1] * n / max(first_cost[0], 1)
        if not prog.more(expected):
            break
        t0 = prog.clock()
        s = float(ppm_scales(alpha, i + 1)[-1])
        with stats.stage(f"{estimator}_trace"):
            pieces = caustic_pieces(ps, n, stats, show_progress,
                                    seed_offset=i + (seed << 16))
        stats.add(f"{estimator}_rays_stored", int(len(pieces)))
        opening = base is None      # the k-nearest pass: another estimator than the rest
        if len(pieces) == 0:
            own = np.zeros_like(out.image)
        elif base is None:
            own, base, out.radius = _first_pass(ps, dev, hits, pieces, estimator, first,
                                                stats, show_progress, cell, radius)
        else:
            if discs is None:
                with stats.stage(f"{estimator}_splat"):
                    discs = dev.derived("surface_hit_discs", lambda: _discs(ps, hits))
            own = pass_image(ps, dev, hits, pieces, estimator, settings, stats,
                             show_progress,
                             radii=np.maximum(base * s, cell).astype(np.float32),
                             discs=discs)
        out.seconds.append(prog.clock() - t0)
        out.rays.append(int(n))
        scales.append(s)
        # the error estimate compares passes of one estimator: the k-nearest opening pass
        # (a different kernel and radius rule) is left out of it
        prog.add(None if opening else own, out.seconds[-1],
                 radius=None if base is None else s * max(out.radius, 1e-30))
        total = own.astype(np.float64) if total is None else total + own
        i += 1
    n = max(len(out.seconds), 1)
    if total is not None:
        out.image = (total / n).astype(np.float32) if n > 1 else total.astype(np.float32)
    out.scales = np.asarray(scales)
    out.stopped_by = prog.stopped_by or "passes"
    out.error = prog.error


def _discs(ps, hits: np.ndarray) -> tuple[list, HitDiscs]:
    """The splats' tree over the diffuse hits, with its buffers (for ``derived``)."""
    d = HitDiscs.build(ps.engine, hits["p"][:, :3], hits["n"][:, :3])
    return list(d.buf.values()), d


def _first_pass(ps, dev, hits, pieces, estimator: str, settings: DensitySettings, stats: Stats,
                show_progress: bool, cell: np.ndarray, radius: float):
    """The first pass's image, the base radii ``B`` it gives (:func:`base_radii`) and their
    median over the hits it found k rays for (0 without any; with an explicit radius, over
    every hit). Hits whose k nearest lie within their cell radius ``cell`` are estimated
    again over every ray within it (module docstring); ``<estimator>_cell_floored`` in the
    statistics is their share of the hits."""
    eng = ps.engine
    r_buf = eng.empty(4 * dev.count)
    e_buf = None
    try:
        e_buf = hit_irradiance(ps, dev, hits, pieces, estimator, settings, stats,
                               show_progress, out_r=r_buf)
        r1 = eng.read(r_buf, dev.count, np.float32).astype(np.float64)
        small = np.flatnonzero(r1 < cell)
        stats.set(**{f"{estimator}_cell_floored": float(len(small) / max(dev.count, 1))})
        if len(small):
            fixed = _estimate_within_cells(ps, dev, hits, pieces, estimator, settings, stats,
                                           e_buf, small, cell[small])
            eng.free(e_buf)
            e_buf = fixed
        own = weighed_image(ps, dev, e_buf, estimator, stats)
    finally:
        eng.free(*(b for b in (r_buf, e_buf) if b is not None))
    base = base_radii(r1, cell, radius)
    lit = np.flatnonzero(r1 < settings.max_radius) if radius <= 0 else np.arange(len(r1))
    return own, base, float(np.median(base[lit])) if len(lit) else 0.0


def _estimate_within_cells(ps, dev, hits, pieces, estimator: str, settings: DensitySettings,
                           stats: Stats, e_buf, small: np.ndarray, radii: np.ndarray):
    """A new buffer: ``e_buf`` (every hit's irradiance) with the hits ``small`` estimated
    again over every ray within ``radii`` (a splat over a tree of those hits alone)."""
    eng = ps.engine
    with stats.stage(f"{estimator}_splat"):
        discs = HitDiscs.build(eng, hits["p"][small, :3], hits["n"][small, :3])
    try:
        sub = hit_irradiance(ps, dev, hits, pieces, estimator, settings, stats,
                             radii=radii.astype(np.float32), discs=discs)
        try:
            e_sub = eng.read(sub, (len(small), 4), np.float32)
        finally:
            eng.free(sub)
    finally:
        discs.release()
    with stats.stage(f"{estimator}_splat"):
        e = eng.read(e_buf, (dev.count, 4), np.float32)
        e[small] = e_sub
        return eng.to_device(e)
