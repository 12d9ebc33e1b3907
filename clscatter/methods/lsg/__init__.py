"""Line space gathering (Sun et al. 2010): single scattering gathered from lighting rays."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ... import structs
from .linetree import (LINE_NODE, LineTree, PluckerFrame, build_linetree, canonical_signs,
                              plucker)
from ...device import Engine
from ...light_paths import ray_counts, trace_light_paths
from ...prepared import PreparedScene
from ...view_paths import ViewPaths, accumulate_segments
from ...stats import Stats, Timer, progress
from .. import AutoRole, Method, Param, register

F4 = structs.F4

# ``LsgLine`` in cl_kernels/lsg.h
LSG_LINE = np.dtype([("a", *F4), ("u", *F4), ("flux", *F4)], align=True)

# name in cl_kernels/lsg.h -> dtype; used by the layout test
STRUCTS = {"LineNode": LINE_NODE, "LsgLine": LSG_LINE}

# Host + device bytes one lighting segment costs while its chunk is processed, as
# PreparedLines.nbytes and Gatherer.add count them: the traced LightSegment (64), the
# clipped float64 copy (ids, a, u, length, flux: 80), Plücker points (float64 48 +
# float32 24 + canonical copy 24), the tree build's per-level arrays (sorted copy 24,
# key 8, node index 8, permutation 8, order 8), LsgLine (48) and Plücker float8 (32) on
# the host and again on the device, the id (4) and the tree's share (nodes, leaf ranges,
# order: < 24 host + 16 device) -- about 500. Used to plan chunks against max_bytes; the
# measured working set of every chunk is reported as lsg_chunk_bytes_max.
BYTES_PER_SEGMENT = 512


@dataclass
class PreparedLines:
    """One chunk's lighting segments, clipped, in tree order, with their 8-ary tree."""

    lines: np.ndarray          # LSG_LINE in tree order
    points: np.ndarray         # (N, 8) float32 Plücker points (u, m, 0, 0) in tree order
    ids: np.ndarray            # int32: index of each line in the input segment array
    tree: LineTree
    frame: PluckerFrame
    max_m1: float              # largest |m|_1 (for the kernel's rounding allowance)
    nbytes: int                # host working set of the preparation (peak estimate)


def clip_segments(segs: np.ndarray, lo, hi, kappa) -> tuple[np.ndarray, ...]:
    """Cut LIGHT_SEGMENT pieces to the box [lo, hi] (float64, vectorised slab test).

    Returns ``(ids, a, u, length, flux)`` of the non-empty pieces; ``flux`` is attenuated
    by ``exp(-kappa s0)`` to the new start (segments lie inside the medium).
    """
    a = segs["a"][:, :3].astype(np.float64)
    d = segs["b"][:, :3].astype(np.float64) - a
    length = np.linalg.norm(d, axis=1)
    ok = length > 0
    u = np.zeros_like(d)
    u[ok] = d[ok] / length[ok, None]
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / u
        t0, t1 = (lo - a) * inv, (hi - a) * inv
    par = u == 0.0
    inside = (a >= lo) & (a <= hi)
    near = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    far = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    s0 = np.maximum(near.max(axis=1), 0.0)
    s1 = np.minimum(far.min(axis=1), length)
    keep = np.flatnonzero(ok & (s1 > s0))
    s0 = s0[keep]
    flux = segs["flux"][keep, :3].astype(np.float64) * np.exp(-np.outer(s0, np.asarray(kappa)[:3]))
    return (keep.astype(np.int32), a[keep] + s0[:, None] * u[keep], u[keep], s1[keep] - s0, flux)


def prepare_lines(segs: np.ndarray, view_lo, view_hi, radius: float, kappa, leaf_size: int = 4,
                  frame: PluckerFrame | None = None) -> PreparedLines:
    """Clip lighting segments to the view segments' box grown by ``radius`` (no pair closer
    than r lies outside it), form canonical Plücker points and build the 8-ary tree."""
    margin = radius * 1.001 + 1e-5
    ids, a, u, length, flux = clip_segments(segs, np.asarray(view_lo) - margin,
                                            np.asarray(view_hi) + margin, kappa)
    if frame is None:
        ends = np.concatenate([a, a + length[:, None] * u]) if len(a) else np.zeros((1, 3))
        frame = PluckerFrame.for_box(ends.min(axis=0), ends.max(axis=0))
    u32 = u.astype(np.float32)
    pts = plucker(a, u32.astype(np.float64), frame).astype(np.float32)   # (u32, m32)
    pts[:, :3] = u32
    tree = build_linetree(pts * canonical_signs(u32)[:, None], leaf_size)
    o = tree.order
    lines = np.zeros(len(o), LSG_LINE)
    lines["a"][:, :3] = a[o]
    lines["a"][:, 3] = length[o]
    lines["u"][:, :3] = pts[o, :3]
    lines["flux"][:, :3] = flux[o]
    points = np.zeros((len(o), 8), np.float32)
    points[:, :6] = pts[o]
    max_m1 = float(np.abs(pts[:, 3:]).sum(axis=1).max()) if len(pts) else 0.0
    n = len(segs)
    nbytes = int(segs.nbytes + 80 * n + 96 * len(o) + 56 * len(o) + lines.nbytes + points.nbytes
                 + tree.nbytes)
    return PreparedLines(lines, points, ids[o].astype(np.int32), tree, frame, max_m1, nbytes)


@dataclass
class ChunkResult:
    pair_tests: int
    valid_pairs: int
    kept: int                  # lighting segments left after clipping
    nbytes: int                # host + device working set of this chunk
    tree_seconds: float
    gather_seconds: float
    pairs: np.ndarray | None   # (k, 2) int32 (view index, input light index) if recorded


class Gatherer:
    """View segments on the device plus an accumulator; gathers chunks of lighting segments.

    ``add(segments)`` clips them, builds the tree, runs ``lsg_gather`` (exhaustively, no
    tree, with ``bruteforce=True``) and adds the estimate of every view segment
    into the accumulator; :meth:`values` reads the sum, ``(n_views, 4)`` rgb.
    ``record_pairs > 0`` also returns up to that many valid (view, light) pairs per chunk.
    ``clip = False`` keeps lighting segments whole (otherwise they are cut to the view
    segments' box grown by the radius); ``frame`` fixes the Plücker frame (tests).
    """

    def __init__(self, engine: Engine, views: np.ndarray, medium: np.ndarray, radius: float,
                 min_sin: float = 1e-6, leaf_size: int = 4, per_launch: int = 65536,
                 record_pairs: int = 0, show_progress: bool = False, clip: bool = True,
                 frame: PluckerFrame | None = None):
        self.eng = engine
        self.views = views
        self.n = len(views)
        self.medium = np.asarray(medium).reshape(1)
        self.radius = float(radius)
        self.min_sin = float(min_sin)
        self.leaf_size = int(leaf_size)
        self.per_launch = max(1, int(per_launch))
        self.record = int(record_pairs)
        self.show_progress = show_progress
        ab = np.concatenate([views["a"][:, :3], views["b"][:, :3]]).astype(np.float64)
        self.lo = ab.min(axis=0) if len(ab) else np.zeros(3)
        self.hi = ab.max(axis=0) if len(ab) else np.zeros(3)
        if not clip:   # (tests) keep the lighting segments whole
            self.lo, self.hi = np.full(3, -np.inf), np.full(3, np.inf)
        self.frame = frame
        self.views_buf = engine.to_device(views)
        self.medium_buf = engine.to_device(self.medium)
        self.out_buf = engine.zeros(max(self.n, 1) * 16)
        self.counts_buf = engine.empty(min(self.per_launch, max(self.n, 1)) * 8)
        self.pairs_buf = engine.empty(max(self.record, 1) * 8)
        self.pair_count = engine.empty(4)

    # ---- one chunk ----
    def add(self, segs: np.ndarray, bruteforce: bool = False) -> ChunkResult:
        eng = self.eng
        t_build, t_gather = Timer(), Timer()
        kappa = self.medium["kappa"][0]
        # bruteforce: a one-leaf tree (the lines in input order, clipped like the tree's)
        leaf = 1 << 62 if bruteforce else self.leaf_size
        with t_build:
            prep = prepare_lines(segs, self.lo, self.hi, self.radius, kappa, leaf, self.frame)
        with t_gather:
            eng.note_host(prep.nbytes)
            lines_buf = eng.to_device(prep.lines)
            points_buf = eng.to_device(prep.points)
            ids_buf = eng.to_device(prep.ids)
            nodes_buf = eng.to_device(prep.tree.nodes)
            ranges_buf = eng.to_device(prep.tree.leaf_ranges)
            dev_bytes = (prep.lines.nbytes + prep.points.nbytes + prep.ids.nbytes
                         + prep.tree.nodes.nbytes + prep.tree.leaf_ranges.nbytes)
            # the host arrays that stay alive beside the new device buffers
            eng.note_host(prep.nbytes - prep.lines.nbytes - prep.points.nbytes)
            eng.cl.enqueue_fill_buffer(eng.queue, self.pair_count, np.zeros(1, np.int32), 0, 4)
            fr = prep.frame
            centre = structs.vec4(fr.centre)
            tests = valid = 0
            if len(prep.lines):
                with progress(self.n, "lsg gather", self.show_progress) as bar:
                    for start in range(0, self.n, self.per_launch):
                        m = min(self.per_launch, self.n - start)
                        eng.call("lsg", "lsg_gather", m, nodes=nodes_buf, leaf_ranges=ranges_buf,
                                 first_leaf=prep.tree.first_leaf, lines=lines_buf,
                                 points=points_buf, line_ids=ids_buf, num_lines=len(prep.lines),
                                 max_m1=prep.max_m1, views=self.views_buf, view_offset=start,
                                 num_views=m, pl_centre=centre, pl_inv_scale=1.0 / fr.scale,
                                 radius=self.radius, min_sin=self.min_sin, medium=self.medium_buf,
                                 exhaustive=int(bruteforce), out=self.out_buf,
                                 counts=self.counts_buf, pairs=self.pairs_buf,
                                 pair_count=self.pair_count, max_pairs=self.record)
                        c = eng.read(self.counts_buf, (m, 2), np.int32)  # (also waits for the launch)
                        tests += int(c[:, 0].sum(dtype=np.int64))
                        valid += int(c[:, 1].sum(dtype=np.int64))
                        bar.update(m)
            pairs = None
            if self.record:
                got = int(eng.read(self.pair_count, 1, np.int32)[0])
                if got > self.record:
                    raise RuntimeError(f"{got} valid pairs exceed record_pairs={self.record}")
                pairs = eng.read(self.pairs_buf, (got, 2), np.int32)
            eng.free(lines_buf, points_buf, ids_buf, nodes_buf, ranges_buf)
        return ChunkResult(tests, valid, len(prep.lines), int(prep.nbytes + dev_bytes),
                           t_build.seconds, t_gather.seconds, pairs)

    def values(self) -> np.ndarray:
        """The accumulated estimate per view segment, ``(n_views, 4)`` float32."""
        return self.eng.read(self.out_buf, (max(self.n, 1), 4), np.float32)[:self.n]

    def release(self) -> None:
        self.eng.free(self.views_buf, self.medium_buf, self.out_buf, self.counts_buf,
                      self.pairs_buf, self.pair_count)


def _chunk_rays(counts: np.ndarray, k: int, n: int) -> int:
    """Rays that chunk (k, n) of trace_light_paths traces (every light's share)."""
    return int(sum(int(c) * (k + 1) // n - int(c) * k // n for c in counts))


@register
class LineSpaceGathering(Method):
    """``lsg``: line space gathering (Sun, Zhou, Lin, Guo 2010) for single scattering along
    specular light paths: volumetric caustics, light glows, volumetric shadows.

    Lighting rays leave the lights (stratified; flux = power / rays) and are traced through
    mirrors and glass (Fresnel split, TIR, interior absorption, ``render.max_depth``); every
    straight piece inside the medium is kept with the flux at its start. Each such
    *lighting segment* becomes a 6-D Plücker point; the points go into a balanced
    median-split kd-tree collapsed into a perfect 8-ary tree (``clscatter.methods.lsg.linetree``).
    Every view segment (seen directly or through mirrors and glass) is a 6-D hyperplane;
    a stackless walk of the tree finds the lighting lines that may pass within ``radius``
    (``|P . w| = d sin theta <= d``), an exact segment-to-segment distance keeps the pairs
    closer than ``radius``, and each adds the cylinder-kernel estimate

        sigma_s p(cos) Phi / (pi r^2) * int_chord exp(-kappa (s + t(s))) ds

    (``cl_kernels/lsg.h`` derives it: a track-length estimate over the cylinder of radius
    r around the view segment; exact for a uniform beam). LSG is a density estimator:
    the image has bias from ``radius`` (blur of sharp caustics, of the 1/d^2 glow near a
    point light, and of shadow edges) and noise from ``light_rays`` (relative noise per
    view segment ~ 1/sqrt(expected lighting rays through its cylinder), which grows like
    ``light_rays * radius``). Halving ``radius`` needs twice the rays for the same noise.

    Lighting rays are processed in chunks whose estimates are summed (with a fixed radius
    the sum equals one pass over all rays), so that one chunk's working set (traced
    segments, tree, device buffers; ~500 bytes per lighting segment) stays within
    ``max_bytes``; a chunk that turns out larger is re-traced in smaller parts. The view
    segments and the accumulator (80 bytes per view segment) are a fixed cost.

    ``radius``: the scene format's example ``0.001`` suits ~1M rays or more. At the
    default 200k rays, 0.003 balances noise and blur: on a glass-sphere caustic scene
    (128 x 96) the relMSE against a 1.6M-ray render was 6.7e-4, 9.7e-5, 6.7e-5, 1.7e-4
    and 5.3e-4 for r = 0.001, 0.002, 0.003, 0.005 and 0.01 (at 50k rays r = 0.005 was
    best). Use smaller radii with more rays for sharper caustics.

    Statistics: ``light_segments`` (traced), ``lsg_light_segments_kept`` (after clipping
    to the view segments' box grown by r), ``view_segments``, ``pair_tests`` (exact
    segment tests after the tree and per-point plane culling), ``pair_tests_bruteforce``
    (light segments x view segments), ``valid_pairs`` (closer than r),
    ``lsg_cull_fraction`` (1 - pair_tests / bruteforce), ``lsg_valid_fraction`` (valid /
    tested), ``tree_build_seconds`` (clipping, Plücker points, tree), ``gather_seconds``,
    ``chunks``, ``lsg_chunks_retraced``, ``lsg_chunk_bytes_max`` (largest chunk working
    set), ``lsg_radius`` (normalised units); ``peak_bytes`` covers the whole render.

    Usage: ``clscatter render scene.toml --method lsg --set render.lsg.light_rays=1000000
    --set render.lsg.radius=0.001``
    """

    NAME = "lsg"
    PARAMS = (
        Param("light_rays", 200_000, "lighting rays, shared among lights by power", lo=1),
        Param("radius", 0.003, "gather radius, relative to the scene extent", lo=0, lo_open=True),
        Param("max_bytes", 1 << 30, "working-set bound for one chunk of rays", lo=1),
        Param("leaf_size", 4, "least points per tree leaf (at most 8x)", lo=1),
        Param("min_sin", 1e-6, "sin(theta) below this counts as parallel", lo=0, hi=1, hi_open=True),
        Param("segments_per_launch", 65536, "view segments per kernel launch (progress)", lo=1),
        Param("min_light_depth", 0, "gather only lighting segments with at least this many "
              "specular bounces (1: caustics only, as auto uses it beside a direct method)", lo=0),
    )
    TERMS = frozenset({"direct", "caustics"})
    AUTO = {"caustics": AutoRole(priority=10, params={"min_light_depth": 1})}

    def render(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
               show_progress: bool = True) -> np.ndarray:
        """Single-scattered radiance (H, W, 3) gathered from the lighting rays."""
        cam = ps.scene.camera
        views = paths.segments
        r = self.params["radius"] * ps.scene.scene_extent() / ps.frame.scale
        stats.set(lsg_radius=r, view_segments=int(len(views)))
        if len(views) == 0 or ps.num_lights == 0 or self.params["light_rays"] == 0:
            stats.set(pair_tests=0, pair_tests_bruteforce=0, valid_pairs=0, chunks=0)
            return np.zeros((cam.height, cam.width, 3), np.float32)
        eng = ps.engine
        p = self.params
        gat = Gatherer(eng, views, ps.medium, r, p["min_sin"], p["leaf_size"],
                       p["segments_per_launch"], show_progress=show_progress)
        try:
            totals = self._gather_chunks(ps, gat, stats, show_progress)
            values = gat.values()
        finally:
            gat.release()
        totals["pair_tests_bruteforce"] = totals.pop("light_x_view")
        bf = max(totals["pair_tests_bruteforce"], 1)
        stats.set(**totals, lsg_cull_fraction=1.0 - totals["pair_tests"] / bf,
                  lsg_valid_fraction=totals["valid_pairs"] / max(totals["pair_tests"], 1))
        return accumulate_segments(values, views["pixel"], cam.width, cam.height)

    def _gather_chunks(self, ps: PreparedScene, gat: Gatherer, stats: Stats,
                       show_progress: bool) -> dict:
        """Trace and gather the lighting rays chunk by chunk within max_bytes."""
        eng = ps.engine
        counts = ray_counts(ps, self.params["light_rays"])
        budget = self.params["max_bytes"]
        seg_per_ray = 1.0          # lower bound until a chunk has been traced
        n0 = max(1, math.ceil(self.params["light_rays"] * seg_per_ray * BYTES_PER_SEGMENT / budget))
        queue = deque((k, n0) for k in range(n0))
        tot = dict(pair_tests=0, valid_pairs=0, light_x_view=0, chunks=0, lsg_light_segments_kept=0,
                   tree_build_seconds=0.0, gather_seconds=0.0, lsg_chunk_bytes_max=0,
                   lsg_chunks_retraced=0)
        while queue:
            k, n = queue.popleft()
            rays = _chunk_rays(counts, k, n)
            if rays == 0:
                continue
            split = math.ceil(rays * seg_per_ray * BYTES_PER_SEGMENT / budget)
            if split > 1 and rays > 1:       # the measured segments per ray say: too big
                queue.extendleft((k * split + j, n * split) for j in reversed(range(split)))
                continue
            with stats.stage("light_paths"):
                lp = trace_light_paths(ps, self.params["light_rays"], None, show_progress, chunk=(k, n))
            segs = lp.segments
            if self.params["min_light_depth"] > 0:
                segs = segs[segs["depth"] >= self.params["min_light_depth"]]
            seg_per_ray = max(seg_per_ray, len(segs) / rays)
            need = len(segs) * BYTES_PER_SEGMENT
            if need > budget and rays > 1:   # re-trace this chunk in smaller parts
                split = math.ceil(need / budget)
                queue.extendleft((k * split + j, n * split) for j in reversed(range(split)))
                tot["lsg_chunks_retraced"] += 1
                continue
            stats.add("light_rays", rays)
            stats.add("light_segments", int(len(segs)))
            res = gat.add(segs)
            tot["pair_tests"] += res.pair_tests
            tot["valid_pairs"] += res.valid_pairs
            tot["light_x_view"] += len(segs) * gat.n
            tot["chunks"] += 1
            tot["lsg_light_segments_kept"] += res.kept
            tot["tree_build_seconds"] += res.tree_seconds
            tot["gather_seconds"] += res.gather_seconds
            tot["lsg_chunk_bytes_max"] = max(tot["lsg_chunk_bytes_max"], res.nbytes)
            eng.note_host(res.nbytes)
        stats.stages["lsg_tree"] = stats.stages.get("lsg_tree", 0.0) + tot["tree_build_seconds"]
        stats.stages["lsg_gather"] = stats.stages.get("lsg_gather", 0.0) + tot["gather_seconds"]
        return tot
