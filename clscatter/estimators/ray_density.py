"""Surface density estimation from lighting rays: the ray map (hemisphere-disc, Havran et
al. 2005 Sec. 4.2) and the photon map (Jensen 1996), sharing everything but the query.

Both start from the same lighting rays (:func:`caustic_pieces`: the light tracer's
:data:`~clscatter.device.structs.RAY_PIECE` records after at least one specular bounce) and
estimate irradiance with eq. (1) of the paper, ``E(x) = sum_i w_i Phi_i / (pi R^2)``
(``rm_density`` in ``cl_kernels/raymap.cl``):

* **photon map**: the pieces that end on diffuse surfaces, as points (their end points),
  the K nearest incoming ones by Euclidean distance; R = distance of the K-th;
* **ray map**: every piece as a segment (also those that end on black surfaces or leave the
  scene: they pass by boundaries), the K nearest incoming ones under max(II.a, distance to
  the part above the tangent plane), i.e. the rays that meet a hemisphere of radius R and
  whose prolongation meets its disc; kernel weights from the tangent-plane distance II.a.

Near a boundary (an edge, a corner, the rim of a caustic on a small object) the photon
map's disc covers area that received no photons, so it underestimates; the ray map counts
the rays that pass the boundary as if the surface went on (no boundary bias).
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from ..device import structs
from ..io.stats import Stats, progress
from ..transport import primitives as prim
from ..transport.light_paths import trace_light_paths
from ..transport.view_paths import trace_diffuse_hits_on_device
from .disc_splat import HitDiscs, splat_on_device
from .knn_queries import RayMap, _f4, heap_define, heap_scratch, kth_end_distance
from .segment_tree import TreeParams

ESTIMATORS = ("raymap", "photonmap")
KERNELS = ("box", "epanechnikov")


@dataclass
class DensitySettings:
    """What a surface estimate needs (radii in the normalised frame)."""

    k: int = 64
    kernel: str = "epanechnikov"
    max_radius: float = 0.05
    batch: int = 32768
    lazy: bool = True
    run: int = 1                 # queries per work-item (consecutive, coherent)
    reuse_eps: float = 0.0       # candidate-list reuse distance (Sec. 6.3); 0 = off
    tree: TreeParams = field(default_factory=TreeParams)


def caustic_pieces(ps, rays: int, stats: Stats | None = None, show_progress: bool = True,
                   min_depth: int = 1, targeted: bool = True, seed_offset: int = 0) -> np.ndarray:
    """Lighting-ray pieces that carry light through mirrors or glass (``depth >=
    min_depth``), ending on a surface or leaving the scene (normalised frame).
    ``targeted``: emit only towards the specular objects (``clscatter.transport.emission``, exact
    pdf weights), since light that never meets one is not kept anyway. ``seed_offset``
    selects an independent set of rays (progressive passes; 0: the first)."""
    lp = trace_light_paths(ps, rays, stats, show_progress, pieces=True,
                           targeted=targeted and min_depth >= 1, seed_offset=seed_offset)
    p = lp.segments
    return p[p["depth"] >= min_depth]


def map_segments(pieces: np.ndarray, estimator: str) -> tuple[np.ndarray, ...]:
    """What the ray map (segments) or the photon map (the pieces ending on diffuse
    surfaces) of ``pieces`` holds: ``(a, b, d, flux)`` (float64, unit directions d; the
    photon map's are read as the points b)."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}")
    if estimator == "photonmap":
        pieces = pieces[pieces["end"] == structs.PIECE_DIFFUSE]
    a = pieces["a"][:, :3].astype(np.float64)
    b = pieces["b"][:, :3].astype(np.float64)
    d = b - a
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(length > 0, d / np.where(length > 0, length, 1.0), 0.0)
    return a, b, d, pieces["flux"][:, :3].astype(np.float64)


def build_map(engine, pieces: np.ndarray, estimator: str, settings: DensitySettings) -> RayMap:
    """The ray map (segments) or photon map (diffuse end points) of ``pieces``."""
    a, b, d, flux = map_segments(pieces, estimator)
    return RayMap(engine, a, b, d, flux, settings.tree, points=estimator == "photonmap",
                  lazy=settings.lazy)


def lazy_radius(rmap: RayMap, x: np.ndarray, k: int, max_radius: float) -> np.ndarray:
    """Per query, the region the lazy tree refines: 1.01 times the distance to the K-th
    nearest ray end point, at most ``max_radius`` (the K-th of all of them when there are
    fewer than K). The ray map's K nearest rays mostly end near the query; the refinement
    only steers the work, the query itself is exact whatever the tree. The end points'
    balanced tree is searched only within ``max_radius / 1.01`` (a little more, for float
    rounding): a K-th point farther away gives ``max_radius`` anyway."""
    x = np.asarray(x, np.float64).reshape(-1, 3)
    if len(rmap.b) == 0:
        return np.full(len(x), max_radius)
    kk = min(k, len(rmap.b))
    dist = kth_end_distance(rmap, x, kk, max_radius / 1.01 * (1 + 1e-5))
    return np.minimum(dist * 1.01, max_radius)


def estimate_on_device(rmap: RayMap, x: np.ndarray, n: np.ndarray, estimator: str,
                       settings: DensitySettings, show_progress: bool = False,
                       stats: Stats | None = None, radii: np.ndarray | None = None,
                       out_r=None):
    """Irradiance at points ``x`` with unit normals ``n`` (normalised frame), left on the
    device: two new buffers (the caller frees them), Q float4 (rgb irradiance) and Q int2
    (nodes visited, references tested). Queries run in batches of ``settings.batch`` in
    the given order (keep them coherent, e.g. in pixel order): each batch refines the lazy
    tree on the host (its query positions: what that host structure needs), then one
    kernel launch answers it into its part of the buffers. With ``stats``, the lazy radii
    and the refinement (with the tree's upload) are timed as the stages
    ``<estimator>_radius`` and ``<estimator>_refine``.

    ``radii`` (Q, normalised): every query's own domain radius instead of
    ``settings.max_radius`` (a fixed-radius estimate wherever fewer than K rays lie within;
    the lazy tree then refines exactly that far). ``out_r``: a device buffer of Q floats
    that gets each estimate's R (the K-th distance, or the domain radius)."""
    eng = rmap.engine
    x = np.asarray(x, np.float64).reshape(-1, 3)
    n = np.asarray(n, np.float64).reshape(-1, 3)
    nq = len(x)
    out_e, out_work = eng.zeros(16 * max(nq, 1)), eng.zeros(8 * max(nq, 1))
    if nq == 0 or len(rmap.b) == 0:
        return out_e, out_work
    metric = 3 if estimator == "raymap" else 1     # RM_HEMIDISC / RM_SEGMENT (points)
    k = int(settings.k)
    batch = settings.batch
    if heap_define(k)["RM_K"] > 256:        # global heaps: bound their scratch (~64 MB)
        batch = max(1, min(batch, 8192 * max(1, int(settings.run))))
    with progress(nq, f"{estimator} density", show_progress) as bar:
        for start in range(0, nq, batch):
            sl = slice(start, min(nq, start + batch))
            xb, nb = x[sl], n[sl]
            m = len(xb)
            with _stage(stats, f"{estimator}_radius"):
                if radii is not None:
                    radius = np.asarray(radii, np.float64)[sl] if rmap.lazy else 0.0
                else:
                    radius = lazy_radius(rmap, xb, k, settings.max_radius) if rmap.lazy else 0.0
            with _stage(stats, f"{estimator}_refine"):
                rmap.prepare(xb, nb, radius)
            run = max(1, int(settings.run))
            qr = np.asarray(radii, np.float32)[sl] if radii is not None else np.zeros(1, np.float32)
            bufs = [eng.to_device(_f4(xb)), eng.to_device(_f4(nb)),
                    *heap_scratch(eng, k, (m + run - 1) // run), eng.to_device(qr)]
            try:
                eng.call("raymap", "rm_density", (m + run - 1) // run, heap_define(k),
                         **rmap.tree_args(), seg_flux=rmap.buf["seg_flux"], qx=bufs[0],
                         qn=bufs[1], num_q=m, k=k, metric=metric, radius=settings.max_radius,
                         plane_weights=int(estimator == "raymap"),
                         epanechnikov=int(settings.kernel == "epanechnikov"),
                         cos_alpha=rmap.cos_alpha, run=run, reuse_eps=settings.reuse_eps,
                         qr=bufs[4], per_query_radius=int(radii is not None),
                         scratch_d=bufs[2], scratch_x=bufs[3], out_offset=start, out_e=out_e,
                         out_work=out_work, out_r=out_r if out_r is not None else bufs[4],
                         want_r=int(out_r is not None))
                eng.finish()                  # the next batch refines the tree in place
            finally:
                eng.free(*bufs)
            bar.update(m)
    return out_e, out_work


def _stage(stats: Stats | None, name: str):
    """``stats.stage(name)``, or nothing to time without statistics."""
    return stats.stage(name) if stats is not None else nullcontext()


def estimate(rmap: RayMap, x: np.ndarray, n: np.ndarray, estimator: str,
             settings: DensitySettings, show_progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`estimate_on_device` read back: irradiance (Q, 3) and the work per query
    (Q, 2) (tests and tools; renders keep them on the device)."""
    nq = len(np.asarray(x).reshape(-1, 3))
    eng = rmap.engine
    e_buf, w_buf = estimate_on_device(rmap, x, n, estimator, settings, show_progress)
    try:
        return (eng.read(e_buf, (max(nq, 1), 4), np.float32)[:nq, :3],
                eng.read(w_buf, (max(nq, 1), 2), np.int32)[:nq].astype(np.int64))
    finally:
        eng.free(e_buf, w_buf)


def surface_caustics(ps, estimator: str, rays: int, settings: DensitySettings, stats: Stats,
                     show_progress: bool = True,
                     sample_range: tuple[int, int] | None = None) -> np.ndarray:
    """Radiance (H, W, 3) of diffuse surfaces lit through mirrors and glass, seen along the
    camera paths (directly or through specular chains): sum over diffuse hits of
    weight * E(hit). Settings' radii are in the normalised frame.

    The hits stay on the device (sorted by camera sample, so by pixel); their positions and
    normals are read once for the host-built tree, which the queries refine lazily batch by
    batch. Each hit's irradiance, its weighted value and the per-pixel sums stay on the
    device; the work counters are totalled there."""
    cam = ps.scene.camera
    img = np.zeros((cam.height, cam.width, 3), np.float32)
    if ps.num_lights == 0:
        return img
    with stats.stage(f"{estimator}_trace"):
        pieces = caustic_pieces(ps, rays, stats, show_progress)
        dev = trace_diffuse_hits_on_device(ps, sample_range=sample_range)
    try:
        hits = read_hits(ps, dev)
        stats.set(**{f"{estimator}_rays_stored": int(len(pieces)), "diffuse_hits": int(dev.count)})
        if len(pieces) == 0 or dev.count == 0:
            return img
        img = pass_image(ps, dev, hits, pieces, estimator, settings, stats, show_progress)
    finally:
        dev.release()
    return img


def read_hits(ps, dev) -> np.ndarray:
    """The diffuse hits of ``dev`` on the host (what the host-built tree needs)."""
    if dev.count == 0:
        return np.zeros(0, structs.DIFFUSE_HIT)
    return ps.engine.read(dev.buf, dev.count, structs.DIFFUSE_HIT)


def pass_image(ps, dev, hits: np.ndarray, pieces: np.ndarray, estimator: str,
               settings: DensitySettings, stats: Stats, show_progress: bool = False,
               radii: np.ndarray | None = None, out_r=None,
               discs: HitDiscs | None = None) -> np.ndarray:
    """One estimate's image (H, W, 3, finite): :func:`hit_irradiance` at every hit of
    ``dev``, weighed and summed per pixel (:func:`weighed_image`)."""
    e_buf = hit_irradiance(ps, dev, hits, pieces, estimator, settings, stats, show_progress,
                           radii=radii, out_r=out_r, discs=discs)
    try:
        return weighed_image(ps, dev, e_buf, estimator, stats)
    finally:
        ps.engine.free(e_buf)


def hit_irradiance(ps, dev, hits: np.ndarray, pieces: np.ndarray, estimator: str,
                   settings: DensitySettings, stats: Stats, show_progress: bool = False,
                   radii: np.ndarray | None = None, out_r=None, discs: HitDiscs | None = None):
    """The irradiance at every hit of ``dev`` (``hits`` on the host), a device buffer of
    ``dev.count`` float4 the caller frees: the map of ``pieces`` queried (``radii``,
    ``out_r``: :func:`estimate_on_device`), its statistics set under ``estimator``. With
    ``radii`` and ``discs`` (the hits' tree, :class:`~.disc_splat.HitDiscs`, over these
    hits or a subset of them, then ``radii`` and the result are the subset's) the
    fixed-radius estimate is splatted from the segments (:func:`~.disc_splat.splat_on_device`,
    the stage ``<estimator>_splat``) and no map is built."""
    eng = ps.engine
    nh = dev.count
    if discs is not None and radii is not None:
        with stats.stage(f"{estimator}_splat"):
            e_buf, (visited, tested) = splat_on_device(
                discs, *map_segments(pieces, estimator), radii, estimator, settings.kernel,
                settings.k)
            eng.finish()
        # summed over the splatted passes (the search's own counts stay those of the
        # K-nearest pass)
        stats.add(f"{estimator}_splat_nodes_visited", int(visited))
        stats.add(f"{estimator}_splat_hits_tested", int(tested))
        return e_buf
    rmap = w_buf = e_buf = None
    try:
        with stats.stage(f"{estimator}_build"):
            rmap = build_map(eng, pieces, estimator, settings)
        with stats.stage(f"{estimator}_estimate"):
            e_buf, w_buf = estimate_on_device(rmap, hits["p"][:, :3], hits["n"][:, :3],
                                              estimator, settings, show_progress, stats,
                                              radii=radii, out_r=out_r)
            visited, tested = prim.int_totals(eng, w_buf, nh, 2)
        t = rmap.tree
        stats.set(**{f"{estimator}_tree_nodes": int(t.n),
                     f"{estimator}_tree_refs": int(t.num_refs),
                     f"{estimator}_index_peak_bytes": int(t.peak_bytes),
                     f"{estimator}_collapses": int(t.collapses),
                     f"{estimator}_nodes_visited": int(visited),
                     f"{estimator}_refs_tested": int(tested)})
        eng.note_host(t.nbytes + pieces.nbytes + hits.nbytes)
        return e_buf
    except BaseException:
        if e_buf is not None:
            eng.free(e_buf)
        raise
    finally:
        if rmap is not None:
            rmap.release()
        if w_buf is not None:
            eng.free(w_buf)


def weighed_image(ps, dev, e_buf, estimator: str, stats: Stats) -> np.ndarray:
    """The image (H, W, 3, finite) of irradiance ``e_buf`` at the hits of ``dev``: each
    hit's weight (throughput x albedo / pi) times its irradiance, summed per pixel."""
    eng = ps.engine
    nh = dev.count
    with stats.stage(f"{estimator}_estimate"):
        v_buf = eng.empty(16 * nh)
        try:
            ps.call("raymap", "rm_weigh_hits", nh, hits=dev.buf, e=e_buf, n=nh, out=v_buf)
            img = dev.accumulate(v_buf)
        finally:
            eng.free(v_buf)
    return np.where(np.isfinite(img), img, 0.0).astype(np.float32)
