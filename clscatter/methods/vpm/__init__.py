"""Volumetric photon mapping (Jensen & Christensen 1998): the baseline for caustics."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...device.launch import timed_launches
from ...io.stats import Stats, Timer, progress
from ...transport import primitives as prim
from ...transport.context import PassContext
from ...transport.light_paths import chunk_rays, interleaved_parts, trace_light_paths
from ...transport.prepared import PreparedScene
from .. import register
from ..base import Estimate, Method, Param, PassResult, camera_samples
from .photons import (
    BUILD_BYTES_PER_PHOTON,
    PHOTON,
    PhotonMap,
    build_photon_map,
    encode_direction,
    encode_rgb9e5,
)

# photons deposited per NumPy batch (bounds the float64 temporaries of the deposition)
DEPOSIT_BATCH = 1 << 16
#: lighting rays traced and deposited at a time: the deposition's working set (the
#: segments and their per-segment arrays) is one part's, beside the photons kept so far
RAYS_PER_PART = 1 << 17
#: the automatic largest gather radius: this many times the photons' median knn-th
#: nearest distance (from a sample of AUTO_RADIUS_SAMPLE photons, AUTO_RADIUS_QUERIES of
#: them queried), at most AUTO_RADIUS_MAX of the scene's extent
AUTO_RADIUS_FACTOR = 2.0
AUTO_RADIUS_SAMPLE = 1 << 13
AUTO_RADIUS_QUERIES = 1 << 11
AUTO_RADIUS_MAX = 0.05


def auto_max_radius(positions: np.ndarray, knn: int, seed: int = 0) -> float:
    """:data:`AUTO_RADIUS_FACTOR` times the median distance from a photon to its ``knn``-th
    nearest, in the units of ``positions`` (N, 3). From a random sample of at most
    :data:`AUTO_RADIUS_SAMPLE` photons: the sample's own distance grows like (N / m)^(1/3)
    over the whole set's, and is scaled back by it. 0 for fewer than two photons."""
    from scipy.spatial import cKDTree
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    n = len(pos)
    if n < 2:
        return 0.0
    m = min(n, AUTO_RADIUS_SAMPLE)
    rng = np.random.default_rng(seed)
    sub = pos[rng.choice(n, m, replace=False)] if m < n else pos
    k = min(int(knn), m - 1)
    queries = sub[:AUTO_RADIUS_QUERIES]                   # the sample is in random order
    dist = cKDTree(sub).query(queries, k=k + 1)[0][:, -1]
    return float(AUTO_RADIUS_FACTOR * np.median(dist) * (m / n) ** (1.0 / 3.0))


def deposit_photons(segments: np.ndarray, kappa: np.ndarray, num_photons: int, seed: int,
                    batch: int = DEPOSIT_BATCH, independent: bool = False,
                    unit: float | None = None) -> tuple[np.ndarray, float]:
    """Photons along lighting segments: ``(packed PHOTON array, power_scale W)``.

    Each segment carries flux ``Phi(s) = Phi_a exp(-kappa s)`` (rgb) along its length.
    Photons are placed with a density proportional to the *scalar* flux
    ``phi(s) = mean(Phi_a) exp(-kbar s)`` (``kbar`` = mean of kappa), stratified: with
    ``C(s) = phi_a (1 - exp(-kbar s)) / (kbar W)`` the expected photon count up to s, the
    j-th photon of a segment sits at ``C(s_j) = j + u`` (one uniform ``u`` per segment).
    ``W`` is chosen so that ``num_photons`` are stored in total, and each photon gets the
    power ``Phi(s_j) / rho(s_j)`` with ``rho = dC/ds``: ``W`` for grey flux and media, so
    the photons carry equal power (dim branches, like Fresnel reflections, get
    proportionally fewer photons: Russian roulette by stratification). For any function
    g, ``E[sum_j power_j g(x_j)] = int Phi(s) g(x(s)) ds``: the photons are an unbiased
    track-length discretisation of the lighting rays, in W * length.

    ``independent=True``: no stratification, a Poisson process instead. A segment gets
    ``Poisson(expected)`` photons, each at an independent position ``C(s_j) = U_j
    expected`` (U uniform), the same density and power: photons are independent of one
    another (a photon mapper's classic photons; with ~1 photon per ray also independent
    of each other's rays), which is what the kNN estimate's ``(k - 1) / V`` assumes.
    The total is ``num_photons`` in expectation.

    ``unit``: the power the stored RGB9E5 values are relative to (default ``W``), so that
    photons deposited part by part share one scale; ``W`` is returned either way.
    """
    kappa = np.asarray(kappa, np.float64)[:3]
    kbar = float(kappa.mean())
    a = segments["a"][:, :3].astype(np.float64)
    d = segments["b"][:, :3].astype(np.float64) - a
    length = np.linalg.norm(d, axis=1)
    flux = segments["flux"][:, :3].astype(np.float64)
    phi = flux.mean(axis=1)
    ok = (length > 0) & (phi > 0)
    length = np.where(ok, length, 0.0)
    phi = np.where(ok, phi, 0.0)
    d = d / np.where(length > 0, length, 1.0)[:, None]
    if kbar > 0:
        mass = phi * -np.expm1(-kbar * length) / kbar
    else:
        mass = phi * length
    total = float(mass.sum())
    if total <= 0 or num_photons <= 0:
        return np.zeros(0, PHOTON), 1.0
    W = total / num_photons
    rng = np.random.default_rng(seed)
    u = rng.random(len(segments))
    expected = mass / W
    if independent:
        counts = rng.poisson(expected).astype(np.int64)
    else:
        counts = np.maximum(np.ceil(expected - u), 0).astype(np.int64)
    dir_code = encode_direction(d)      # one code per segment, shared by its photons
    photons = np.zeros(int(counts.sum()), PHOTON)
    ends = np.cumsum(counts)
    first = 0
    while first < len(segments):
        # a run of whole segments holding about `batch` photons
        done = int(ends[first - 1]) if first else 0
        last = max(int(np.searchsorted(ends, done + batch, side="right")), first + 1)
        n = counts[first:last]
        idx = np.repeat(np.arange(first, last), n)
        if len(idx):
            j = np.arange(len(idx)) - np.repeat(np.cumsum(n) - n, n)
            if independent:                          # C(s) = U * expected, U iid uniform
                c = rng.random(len(idx)) * expected[idx] * W / phi[idx]
            else:
                c = (j + u[idx]) * W / phi[idx]      # (1 - exp(-kbar s)) / kbar at the photon
            s = np.minimum(-np.log1p(-kbar * c) / kbar if kbar > 0 else c, length[idx])
            pos = a[idx] + s[:, None] * d[idx]
            # power = Phi(s) / rho(s), rho(s) = phi_a exp(-kbar s) / W
            power = flux[idx] * np.exp(-(kappa - kbar) * s[:, None]) * (W / phi[idx])[:, None]
            out = photons[done:done + len(idx)]
            out["x"], out["y"], out["z"] = pos.T
            out["dir"] = dir_code[idx]
            out["power"] = encode_rgb9e5(power / (unit or W))
        first = last
    return photons, W


@dataclass
class DevicePhotonMap:
    """A photon map uploaded to the device (what the gather kernel reads)."""

    photons: object          # device buffer of PHOTON
    nodes: object            # device buffer of POINT_NODE
    count: int
    levels: int
    leaf_size: int
    power_scale: float

    @staticmethod
    def upload(engine, tree: PhotonMap) -> "DevicePhotonMap":
        return DevicePhotonMap(engine.to_device(tree.photons), engine.to_device(tree.nodes),
                               tree.count, tree.levels, tree.leaf_size, tree.power_scale)

    def free(self, engine) -> None:
        engine.free(self.photons, self.nodes)


def gather_on_device(engine, medium: np.ndarray, pmap: DevicePhotonMap, seg_buf, n: int,
                     knn: int, dx: float, max_radius: float, seed: int,
                     per_launch: int = 16384, show_progress: bool = False):
    """Run ``vpm_gather`` over the ``n`` VIEW_SEGMENT records of the device buffer
    ``seg_buf``. Returns two new device buffers (the caller frees them): ``n`` float4,
    the rgb radiance of each segment with its number of march samples in the last lane,
    and ``n`` int2, the boxes and photons its kNN queries tested. ``dx`` and
    ``max_radius`` in the photons' (normalised) units."""
    med = engine.to_device(np.asarray(medium).reshape(1))
    out_buf, work_buf = engine.empty(16 * max(n, 1)), engine.empty(8 * max(n, 1))
    try:
        with progress(n, "vpm gather", show_progress) as bar:
            for start, m in timed_launches(n, per_launch):
                engine.call("vpm", "vpm_gather", m, {"KNN": int(knn)}, segs=seg_buf,
                            seg_offset=start, num_segs=m, photons=pmap.photons,
                            num_photons=pmap.count, nodes=pmap.nodes, levels=pmap.levels,
                            power_scale=pmap.power_scale, medium=med, dx=dx,
                            max_r2=max_radius * max_radius, seed=seed & 0xFFFFFFFF,
                            out=out_buf, work_out=work_buf)
                engine.finish()             # a launch at a time: progress, and a stop heard
                bar.update(m)
    finally:
        engine.free(med)
    return out_buf, work_buf


def gather(engine, medium: np.ndarray, pmap: DevicePhotonMap, segments: np.ndarray, knn: int,
           dx: float, max_radius: float, seed: int, per_launch: int = 16384,
           show_progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gather_on_device` over a host array of ``segments``, its results read back:
    (N, 4) float32 and (N, 2) int32 (tests and inspection; renders keep them on the
    device)."""
    n = len(segments)
    if n == 0:
        return np.zeros((0, 4), np.float32), np.zeros((0, 2), np.int32)
    seg_buf = engine.to_device(segments)
    bufs = (seg_buf,)
    try:
        bufs += gather_on_device(engine, medium, pmap, seg_buf, n, knn, dx, max_radius, seed,
                                 per_launch, show_progress)
        return engine.read(bufs[1], (n, 4), np.float32), engine.read(bufs[2], (n, 2), np.int32)
    finally:
        engine.free(*bufs)


def knn_points(engine, pmap: DevicePhotonMap, points: np.ndarray, wo: np.ndarray, knn: int,
               max_radius: float, g: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' kNN query and estimate at (N, 3) ``points`` with unit directions
    towards the camera ``wo``: (count (N,), heap indices (N, knn), -1 past count; the
    estimate without sigma_s (N, 3)). For tests and inspection."""
    n = len(points)
    p4 = np.zeros((max(n, 1), 4), np.float32)
    w4 = np.zeros((max(n, 1), 4), np.float32)
    p4[:n, :3], w4[:n, :3] = points, wo
    bufs = [engine.to_device(p4), engine.to_device(w4), engine.empty(4 * n),
            engine.empty(4 * n * knn), engine.empty(16 * n)]
    engine.call("vpm", "vpm_knn", n, {"KNN": int(knn)}, points=bufs[0], wo=bufs[1],
                num_points=n, photons=pmap.photons, num_photons=pmap.count, nodes=pmap.nodes,
                levels=pmap.levels, power_scale=pmap.power_scale, g=g,
                max_r2=max_radius * max_radius, count_out=bufs[2], idx_out=bufs[3],
                est_out=bufs[4])
    count = engine.read(bufs[2], n, np.int32)
    idx = engine.read(bufs[3], (n, knn), np.int32)
    est = engine.read(bufs[4], (n, 4), np.float32)[:, :3]
    engine.free(*bufs)
    return count, idx, est


# lighting segments a photon ray leaves, as the memory estimate assumes (1.16 measured on
# the glass bunny of builtin:paper_bunny; more where light bounces inside glass often)
SEGMENTS_PER_RAY = 1.25


@register
class VolumetricPhotonMapping(Method):
    """``vpm``: volumetric photon mapping (Jensen & Christensen 1998), k-nearest-neighbour
    gathers while marching the view segments. The baseline for volumetric caustics.

    *Photons.* ``photons / photons_per_ray`` lighting rays are traced by
    ``clscatter.transport.light_paths`` (the rays LSG uses: stratified emission, mirrors,
    Fresnel-split dielectrics, TIR, interior absorption, ``render.max_depth``). Along every
    lighting segment in the medium, photons are placed with a density proportional to
    the flux the segment still carries (``deposit``: ``independent`` by default, a Poisson
    process, each photon's position drawn on its own; ``stratified``: evenly spaced
    with one random offset per segment), so that ``photons``
    photons of (for grey media) equal power are stored in all (:func:`deposit_photons`:
    an unbiased track-length discretisation of the lighting rays; dim branches such as
    Fresnel reflections get proportionally fewer photons). The photon map stores 20 bytes
    per photon (position, octahedral direction, RGB9E5 power), sorted by leaf of the
    estimators' balanced point tree, laid out as an implicit perfect binary tree of boxes
    (``clscatter/methods/vpm/photons.py``, ``SegmentTree.balanced``).

    *Gather.* Every view segment from the view-path tracer is marched with step ``dx``
    from a random offset (jittered regular samples, each standing for ``dx``). At each
    sample the ``knn`` nearest photons within ``max_radius`` (a bounded max-heap per
    work-item, nearest-child-first tree walk, the search ball seeded from the previous
    sample's radius) give the in-scattered radiance
    ``sigma_s sum_p f(w_p . wo) Phi_p / V(r)``: r is the distance to the ``knn``-th
    photon and the sum runs over the ``knn - 1`` photons inside it (unbiased for a
    Poisson process, where ``knn / V`` is biased by ``knn / (knn - 1)``); with fewer than
    ``knn`` photons within ``max_radius``, all of them over the ball of radius
    ``max_radius``. By default ``max_radius`` is automatic: :data:`AUTO_RADIUS_FACTOR`
    times the photons' median ``knn``-th nearest distance (at most
    :data:`AUTO_RADIUS_MAX` of the extent, the former fixed cap), so that it shrinks like the
    photon spacing and the estimate converges; a fixed cap does not, since in a shadow
    next to lit fog every lit photon within it leaks in (on ``builtin:epi_sun`` VPM stayed
    11-16 % above ray marching from 250k to 4M photons with the former fixed 0.05; 7-10 %
    with the automatic cap, the k-nearest blur into the trunks' shadows; an explicit small
    cap, 0.003, gave 0.5 %). In a bounded medium V is the part of the ball inside the medium box
    (no photon can lie outside it), which removes the estimate's deficit along the box
    walls and a floor on the box's bottom. Each sample is weighted by the transmittance
    back to the segment start; the segment's weight carries the rest of the way to the eye.

    *Bias.* Apart from the kernel's blur (width ~r; a point light's glow peak and sharp
    caustics come out wider and lower) the estimate is unbiased for Poisson-like photon
    sets. Photons stratified along fewer, denser rays are less noisy but more regular
    than Poisson, which biases the kNN estimate a little low, and makes its error look
    smaller than it is. Those correlated photons would make VPM look
    better than the method is (32 photons on one line are worth far fewer than 32
    independent ones, and the benchmark then weighs LSG against a cheaper tracer), so
    the defaults are the classic photon map: independent photons, one per lighting ray
    on average (``photons_per_ray = 1``, ``deposit = "independent"``).

    *Caustic pass.* ``min_light_depth >= 1`` keeps only lighting segments after a
    specular bounce (as LSG's caustic pass); with ``targeted`` the lights then emit only
    towards the mirrors and glass (``clscatter.transport.emission``), so no photon ray is wasted.

    *Cost.* Gather time is proportional to the number of march samples (view segments x
    length in the medium / ``dx``) times the kNN cost (~log photons + a few x ``knn``);
    samples farther than ``max_radius`` from every photon are skipped. Memory: the photon
    map (~26 bytes per photon with the tree). The lighting rays are traced and deposited in
    parts of at most :data:`RAYS_PER_PART` rays, so that the peak is while depositing a part
    (its lighting segments, 64 bytes each, :data:`SEGMENTS_PER_RAY` a ray in the estimate,
    with ~180 bytes of per-segment arrays, beside the photons kept so far) or while
    building the tree (~72 bytes per photon), the larger: it grows with the photons, not
    with the segments that carry them.

    Statistics: ``photons`` (stored), ``light_rays``, ``light_segments``, ``vpm_parts``,
    ``gather_steps`` (kNN queries), ``knn_boxes_tested``, ``knn_photons_tested``,
    ``photon_trace_seconds``, ``photon_build_seconds`` (deposition and tree, NumPy: the
    benchmarks report it apart from the device gather), ``vpm_targeted``,
    ``light_rays_specular_fraction``,
    ``gather_seconds``, ``photon_map_bytes``, ``vpm_max_radius`` (the cap used, relative to
    the extent; ``vpm_max_radius_world`` in scene units); ``peak_bytes`` covers the whole
    render.

    The LSG paper's comparisons use ``p`` photons, ``knn`` and ``dx`` (scene extent 1);
    e.g. p = 89M, knn = 128, dx = 0.002 at 512 x 512 x 4 samples.

    Usage: ``clscatter render builtin:caustic_sphere --method vpm --set render.vpm.knn=64``
    """

    NAME = "vpm"
    PARAMS = (
        Param("photons", 1_000_000, "photons stored in the photon map", lo=1),
        Param("photons_per_ray", 1.0, "photons per traced lighting ray, on average (sets the "
              "ray count: photons / photons_per_ray)", lo=0, lo_open=True),
        Param("deposit", "independent", "photon placement along the lighting segments: "
              "independent (Poisson) or stratified", choices=("independent", "stratified")),
        Param("knn", 32, "photons per density estimate", lo=2, hi=1024),
        Param("dx", 0.004, "march step, relative to the scene's extent", lo=0, lo_open=True),
        Param("max_radius", 0.0, "largest gather radius, relative to the extent; 0: automatic, "
              "twice the photons' median knn-th nearest distance, at most 0.05 (it shrinks as "
              "photons are added, so shadows converge)", lo=0),
        Param("leaf_size", 8, "least photons per kd-tree leaf (at most 2x)", lo=1, hi=4096),
        Param("segments_per_launch", 16384, "most view segments per kernel launch; launches "
              "are timed to about 0.25 s", lo=1),
        Param("min_light_depth", 0, "deposit photons only on lighting segments with at least "
              "this many specular bounces (1: caustics only)", lo=0),
        Param("targeted", True, "with min_light_depth >= 1, emit only towards mirrors and glass"),
        Param("light_seed", 0, "selects an independent set of lighting rays and photons", lo=0),
    )
    TERMS = frozenset({"direct", "caustics"})
    PREVIEW_SCALE = {"photons": 0.125}

    @classmethod
    def estimate(cls, scene, params):
        photons = float(params["photons"])
        segs = 2.0 * camera_samples(scene)
        steps = segs / params["dx"]                # an upper bound: every segment spans the scene
        # the peak is a part's deposition (its lighting segments, 64 bytes, with ~180 bytes
        # of per-segment arrays, beside the photons) or the tree build's, the larger
        rays = photons / params["photons_per_ray"]
        light_segs = SEGMENTS_PER_RAY * min(rays, RAYS_PER_PART)
        peak = max(light_segs * (64 + 180) + photons * PHOTON.itemsize,
                   photons * (PHOTON.itemsize + BUILD_BYTES_PER_PHOTON))
        return [Estimate("vpm", "render.vpm.photons", peak,
                         steps * params["knn"] * 4, "photon distance tests (upper bound)")]

    def targeted(self) -> bool:
        return bool(self.params["targeted"]) and self.params["min_light_depth"] >= 1

    def rays(self) -> int:
        """Lighting rays to trace."""
        return max(1, round(self.params["photons"] / self.params["photons_per_ray"]))

    def build_photon_map(self, ps: PreparedScene, stats: Stats,
                         show_progress: bool = True) -> PhotonMap:
        """Trace the lighting rays and deposit their photons part by part (at most
        :data:`RAYS_PER_PART` rays a part, an odd number of interleaved parts, so that every
        part spreads over the lights' directions like the whole set and carries about the
        same power: each takes its share of the photons, all in one power unit), then
        build the photon map (host arrays)."""
        eng = ps.engine
        rays = self.rays()
        parts = interleaved_parts(rays, RAYS_PER_PART)
        total = self.params["photons"]
        base_seed = (ps.scene.render.seed * 1000003 + 7 + 7919 * self.params["light_seed"])
        kept: list[np.ndarray] = []
        kept_bytes = specular = traced = 0
        unit = None
        t_trace, t_build = Timer(), Timer()
        for k in range(parts):
            with stats.stage("photon_trace"), t_trace:
                lp = trace_light_paths(ps, rays, stats, show_progress, chunk=(k, parts),
                                       targeted=self.targeted(),
                                       seed_offset=self.params["light_seed"], interleaved=True)
            specular += int(lp.specular_rays.sum())
            traced += chunk_rays(lp.rays, k, parts, interleaved=True)
            with stats.stage("photon_build"), t_build:
                segs = lp.segments
                if self.params["min_light_depth"] > 0:
                    segs = segs[segs["depth"] >= self.params["min_light_depth"]]
                del lp
                share = total * (k + 1) // parts - total * k // parts
                seed = (base_seed + 0x9E3779B1 * k) & 0xFFFFFFFF
                photons, w = deposit_photons(segs, ps.medium["kappa"], share, seed,
                                             independent=self.params["deposit"] == "independent",
                                             unit=unit)
                if len(photons) and unit is None:
                    unit = w
                # working sets (measured with tracemalloc): the deposition holds the part's
                # segments, ~180 bytes of per-segment arrays, its photons and one batch's
                # temporaries beside the photons kept so far
                eng.note_host(segs.nbytes + 180 * len(segs) + photons.nbytes + kept_bytes
                              + 160 * min(DEPOSIT_BATCH, len(photons)))
                del segs
                kept.append(photons)
                kept_bytes += photons.nbytes
                del photons
        with stats.stage("photon_build"), t_build:
            photons = np.concatenate(kept) if kept else np.zeros(0, PHOTON)
            del kept
            # the parts and their concatenation, then the tree build ~BUILD_BYTES_PER_PHOTON
            # per photon beyond the photons
            n = len(photons)
            eng.note_host(max(2 * photons.nbytes, photons.nbytes + BUILD_BYTES_PER_PHOTON * n))
            tree = build_photon_map(photons, self.params["leaf_size"], unit or 1.0)
            del photons
        stats.set(photon_trace_seconds=t_trace.seconds, vpm_targeted=self.targeted(),
                  light_rays_specular_fraction=specular / max(traced, 1),
                  photon_build_seconds=t_build.seconds, photons=tree.count,
                  photon_map_bytes=tree.nbytes, photon_tree_levels=tree.levels, vpm_parts=parts)
        return tree

    def render(self, ctx: PassContext) -> PassResult:
        """Single-scattered radiance of every view segment, in the medium term."""
        ps, paths, stats, show_progress = ctx.ps, ctx.paths, ctx.stats, ctx.show_progress
        cam = ps.scene.camera
        if len(paths) == 0 or ps.num_lights == 0:
            return PassResult(medium=ctx.zeros())
        eng = ps.engine
        tree = self.build_photon_map(ps, stats, show_progress)
        rel = ps.scene.scene_extent() / ps.frame.scale
        max_r = self.params["max_radius"] * rel
        if max_r <= 0:
            with stats.stage("vpm_radius"):
                pos = tree.photons.view(np.float32).reshape(-1, PHOTON.itemsize // 4)[:, :3]
                max_r = min(auto_max_radius(pos, self.params["knn"]) or math.inf,
                            AUTO_RADIUS_MAX * rel)
        stats.set(vpm_max_radius=max_r / rel, vpm_max_radius_world=max_r * ps.frame.scale)
        pmap = DevicePhotonMap.upload(eng, tree)
        eng.note_host(tree.nbytes)   # the host copy while uploading
        del tree                     # the gather reads the device copy
        seed = (ps.scene.render.seed * 7919 + 29) & 0xFFFFFFFF
        # per segment everything stays on the device: the gather's values are summed into
        # pixels there and its work counters totalled there
        segs = ctx.segments()
        with stats.stage("vpm_gather") as t_gather:
            p = self.params
            values, work = gather_on_device(eng, ps.medium, pmap, segs.buf, segs.count, p["knn"],
                                            p["dx"] * rel, max_r, seed,
                                            p["segments_per_launch"], show_progress)
            try:
                pmap.free(eng)
                sums = segs.pixel_sums(values)
                boxes, tested = prim.int_totals(eng, work, segs.count, 2)
            finally:
                eng.free(values, work)
        stats.set(gather_seconds=t_gather.seconds,
                  gather_steps=int(sums[:, 3].astype(np.float64).sum()),
                  knn_boxes_tested=int(boxes), knn_photons_tested=int(tested))
        return PassResult(medium=sums[:, :3].reshape(cam.height, cam.width, 3))
