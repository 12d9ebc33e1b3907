"""Line-space gathering of lighting segments along view segments (Sun et al. 2010): the
estimator behind ``lsg`` and behind the voxel pipeline's light beyond its grid.

Lighting segments are clipped to the region the view segments span, turned into Plücker
points in a perfect 8-ary tree (:mod:`.line_tree`), and every view segment's plane query
gathers the pairs within the radius on the device (``cl_kernels/lsg.cl``), as in the
paper; or, the roles swapped, the view segments are the tree (built once and kept over
passes and light moves) and every lighting segment's plane query adds its pairs to the
view segments it meets; or the view segments on the camera's rays are sorted by screen
cell (:mod:`.screen_cells`) and every lighting segment visits the cells it crosses
(:class:`Gatherer`'s ``queries``)."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..device import Engine, structs
from ..device.launch import timed_launches
from ..geometry import slab_interval
from ..io.stats import Timer, progress
from ..transport import primitives as prim
from ..transport.view_paths import DeviceSegments
from .fixed_sum import SCATTER_BYTES, fixed_scale
from .line_tree import (
    POINT_LANES,
    LineTree,
    PluckerFrame,
    build_linetree,
    canonical_signs,
    child_rows,
    linetree_from_rows,
    node_boxes,
    plucker,
    point_block_array,
    point_blocks,
)
from .row_chunks import map_row_chunks
from .screen_cells import ScreenCells, build_screen_cells, on_camera_rays, splat_order

F4 = structs.F4

# ``LsgLine`` in cl_kernels/lsg.h
LSG_LINE = np.dtype([("a", *F4), ("u", *F4), ("flux", *F4)], align=True)

structs.register_struct("lsg.h", "LsgLine", LSG_LINE)

# Host + device bytes one lighting segment costs while its chunk is processed, as
# PreparedLines.nbytes and Gatherer.add count them: the traced LightSegment (64), the
# clipped float64 copy (ids, a, u, length, flux: 80), Plücker points (float64 48 +
# float32 24 + canonical copy 24), the tree build's per-level arrays (sorted copy 24,
# key 8, node index 8, permutation 8, order 8), LsgLine (48) in input order and in tree
# order on the host and again on the device, Plücker blocks (24) on the host and the
# device, the id (4) and the tree's share (nodes, leaf ranges, order: < 24 host + 16
# device) -- about 530. With screen queries the tree for the view segments off the
# camera's rays is built while the splat's own arrays (LsgLine on the host and the device,
# counts: about 120) are alive: about 550 then. Used to plan chunks against max_bytes; the
# measured working set of every chunk is reported as lsg_chunk_bytes_max.
BYTES_PER_SEGMENT = 560

# Bytes one view segment costs in a kept view tree (queries from the lighting side): its
# record (64), Plücker point (24), index (4), sums and count (SCATTER_BYTES, 32) and its
# share of the tree's nodes (under 16) on the device, a host copy of all but the sums, and
# the build's float64 ends and boxes and per-level arrays (rows of 9 floats twice, key,
# permutation: about 100) -- about 345.
BYTES_PER_VIEW = 344

# Weight of where a lighting segment starts (normalised frame, in [-1, 1]) against its
# Plücker coordinates when the line tree chooses its splits (line_tree.build_linetree's
# split_extra). With a few thousand segments a tree has too few levels to split six
# Plücker coordinates often enough for its 6-D boxes to cull; splitting on place first
# groups segments that start together, whose nodes' 3-D boxes then cull
# (tools/bench_lsg_gather.py). 0: Plücker coordinates only, as in the paper.
SPATIAL_SPLIT = 8.0

# Least points per leaf of the line tree (at most 8x). The gather's cost is mostly the
# walk over internal nodes, so leaves of tens of points are faster than leaves of a few
# (tools/bench_lsg_gather.py).
LEAF_SIZE = 16


# Which side of the pairs walks a tree (Gatherer's ``queries``): "views", a tree over each
# chunk's lighting segments and one query per view segment (the paper's way); "lights", a
# tree over the view segments, built once and kept (every pass, chunk and light move
# reuses it), and one query per lighting segment, which adds each pair to its view
# segment's sum atomically; "screen", the view segments on a pinhole camera's rays in
# screen cells (screen_cells.py), kept like the tree, which every lighting segment crosses
# (lsg_splat), and the other view segments (after a mirror or glass) from the side with
# fewer segments, as "views" or as "lights". All three find the same pairs; the cells
# test fewer candidates than either tree walk, which makes them faster on most caustic
# scenes, not all (docs/benchmarks.md, "Camera rays in screen cells"); lsg's default.
QUERIES = ("views", "lights", "screen")


def sample_groups(views: np.ndarray, groups: int, spp: int) -> np.ndarray:
    """The camera-sample group of every view segment: its sample's index within its pixel
    (``spp`` samples a pixel), modulo ``groups``."""
    return views["sample"].astype(np.int64) % max(1, int(spp)) % max(1, int(groups))


def group_samples(group: int, groups: int, spp: int) -> int:
    """How many of a pixel's ``spp`` samples fall in ``group`` of ``groups``."""
    return len(range(int(group), max(1, int(spp)), max(1, int(groups))))


@dataclass
class PreparedLines:
    """One chunk's lighting segments, clipped, in tree order, with their 8-ary tree."""

    lines: np.ndarray          # LSG_LINE in tree order
    points: np.ndarray         # Plücker points (u, m) in tree order: line_tree.point_blocks
    ids: np.ndarray            # int32: index of each line in the input segment array
    tree: LineTree
    boxes: np.ndarray          # (nodes, 2, 4) float32: each node's 3-D box of its segments
    kids: np.ndarray           # (internal, 18, 8) float32: line_tree.child_rows
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
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    ok = length > 0
    u = np.zeros_like(d)
    u[ok] = d[ok] / length[ok, None]
    s0, s1 = slab_interval(a, u, lo, hi, length)
    keep = np.flatnonzero(ok & (s1 > s0))
    s0 = s0[keep]
    flux = segs["flux"][keep, :3].astype(np.float64) * np.exp(-np.outer(s0, np.asarray(kappa)[:3]))
    return (keep.astype(np.int32), a[keep] + s0[:, None] * u[keep], u[keep], s1[keep] - s0, flux)


def continue_across_faces(segs: np.ndarray, medium: np.ndarray, radius: float) -> np.ndarray:
    """``segs`` with every lighting segment that starts where light enters a bounded
    medium (on a face of its box, heading in) continued backwards until it lies
    ``radius`` beyond the face (``radius / cos``), its flux continued exponentially
    (times ``exp(kappa back)`` at the new start, so that it is unchanged from the face
    on); every segment that ends where light leaves it continued forwards likewise.

    The gather averages the light over a disc of radius r around each view point; a view
    point within r of a face would find lighting segments over only the part of its disc
    inside the medium, an underestimate that grows with the optical depth where light
    enters (the lit layer behind the face is 1/kappa deep: 0.9 % of the image at optical
    depth 10 seen from outside with r = 0.004, tests/test_lsg.py; 0.01 % continued).
    Continued, the disc sees the same smooth field as in the interior. Segments that
    start or end elsewhere (at a light, a mirror, glass, an occluder) are unchanged; an
    unbounded medium has no faces."""
    m = medium.reshape(-1)[0]
    if not int(m["bounded"]) or radius <= 0.0 or not len(segs):
        return segs
    lo, hi = m["bmin"][:3].astype(np.float64), m["bmax"][:3].astype(np.float64)
    a = segs["a"][:, :3].astype(np.float64)
    d = segs["b"][:, :3].astype(np.float64) - a
    eps = 1e-5 * float(np.max(hi - lo))
    length = np.linalg.norm(d, axis=1)
    b = a + d
    face = ((np.abs(a - lo) <= eps) & (d > 0)) | ((np.abs(a - hi) <= eps) & (d < 0))
    exit_ = ((np.abs(b - lo) <= eps) & (d < 0)) | ((np.abs(b - hi) <= eps) & (d > 0))
    idx = np.flatnonzero((face.any(1) | exit_.any(1)) & (length > 0))
    if not len(idx):
        return segs
    out = segs.copy()
    u = d[idx] / length[idx, None]
    # far enough to lie r beyond the face: r / cos of the crossing angle (a corner's
    # steepest face; capped at 10 r for grazing crossings); 0 where it does not cross
    def beyond(mask):
        cos = np.max(np.where(mask[idx], np.abs(u), 0.0), axis=1)
        return np.where(mask[idx].any(1), radius / np.maximum(cos, 0.1), 0.0)
    back, ahead = beyond(face), beyond(exit_)
    out["a"][idx, :3] = a[idx] - back[:, None] * u
    out["b"][idx, :3] = b[idx] + ahead[:, None] * u
    out["flux"][idx, :3] *= np.exp(np.outer(back, m["kappa"][:3].astype(np.float64)))
    return out


def clip_lines(segs: np.ndarray, view_lo, view_hi, radius: float, kappa
               ) -> tuple[np.ndarray, ...]:
    """Lighting segments clipped to the view segments' box grown by ``radius`` (no pair
    closer than r lies outside it): :func:`clip_segments`' ``(ids, a, u, length, flux)``."""
    margin = radius * 1.001 + 1e-5
    return clip_segments(segs, np.asarray(view_lo) - margin, np.asarray(view_hi) + margin,
                         kappa)


def continue_and_clip(segs: np.ndarray, medium: np.ndarray, radius: float, view_lo, view_hi,
                      kappa) -> tuple[np.ndarray, ...]:
    """:func:`continue_across_faces` then :func:`clip_lines`, in chunks of rows on threads
    (:func:`~.row_chunks.map_row_chunks`): the same ``(ids, a, u, length, flux)`` as the
    two calls over all of ``segs``."""
    def chunk(start: int, stop: int) -> tuple[np.ndarray, ...]:
        part = continue_across_faces(segs[start:stop], medium, radius)
        ids, *rest = clip_lines(part, view_lo, view_hi, radius, kappa)
        return (ids + np.int32(start), *rest)
    parts = map_row_chunks(chunk, len(segs))
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(cols) for cols in zip(*parts))


def segment_bytes(segs: np.ndarray) -> int:
    """Host bytes of a chunk's traced lighting segments and their clipped float64 copy
    (ids, a, u, length, flux: 80 a segment): what every way of gathering a chunk holds."""
    return int(segs.nbytes + 80 * len(segs))


class BuildStopped(Exception):
    """:func:`prepare_lines` was told to stop: its caller no longer needs the tree."""


def prepare_lines(segs: np.ndarray, view_lo, view_hi, radius: float, kappa,
                  leaf_size: int = LEAF_SIZE,
                  frame: PluckerFrame | None = None,
                  spatial_split: float = SPATIAL_SPLIT,
                  clipped: tuple[np.ndarray, ...] | None = None,
                  stop: Callable[[], bool] | None = None) -> PreparedLines:
    """Clip lighting segments (:func:`clip_lines`; ``clipped``: that done already), form
    canonical Plücker points and build the 8-ary tree (its splits steered by where the
    segments start, times ``spatial_split``). ``stop()`` is asked before every chunk of
    rows and every step of the build; once it says so, :class:`BuildStopped` is raised
    (a build on a thread of its own for a render that was cancelled ends soon)."""
    def check() -> None:
        if stop is not None and stop():
            raise BuildStopped()

    ids, a, u, length, flux = (clipped if clipped is not None
                               else clip_lines(segs, view_lo, view_hi, radius, kappa))
    k = len(a)
    # row-wise steps in chunks on threads (map_row_chunks): the same values as whole arrays.
    # First, in input order: the records the kernel reads and each segment's 3-D box
    lines_in = np.zeros(k, LSG_LINE)
    box_in = np.empty((k, 6), np.float32)   # float32 of (min, max) of the ends (rounding
    u32 = np.empty((k, 3), np.float32)      # commutes with min and max: node_boxes' values)

    def records(s: int, e: int) -> tuple[np.ndarray, np.ndarray]:
        check()
        ends = a[s:e] + length[s:e, None] * u[s:e]
        lo, hi = np.minimum(a[s:e], ends), np.maximum(a[s:e], ends)
        box_in[s:e, :3], box_in[s:e, 3:] = lo, hi
        u32[s:e] = u[s:e]
        lines_in["a"][s:e, :3] = a[s:e]
        lines_in["a"][s:e, 3] = length[s:e]
        lines_in["u"][s:e, :3] = u32[s:e]
        lines_in["flux"][s:e, :3] = flux[s:e]
        return lo.min(axis=0), hi.max(axis=0)
    box = map_row_chunks(records, k) if k else [(np.zeros(3), np.zeros(3))]
    if frame is None:
        frame = PluckerFrame.for_segments(np.min([b[0] for b in box], axis=0),
                                          np.max([b[1] for b in box], axis=0))
    signs = canonical_signs(u32)
    pts = np.empty((k, 6), np.float32)                 # (u32, m32), input order
    rows = np.empty((6 + 3 * (spatial_split > 0), k), np.float32)

    def points_and_rows(s: int, e: int) -> None:
        check()
        p = plucker(a[s:e], u32[s:e].astype(np.float64), frame).astype(np.float32)
        p[:, :3] = u32[s:e]
        pts[s:e] = p
        rows[:6, s:e] = (p * signs[s:e, None]).T
        if spatial_split > 0:     # the splits are steered by where the segments start
            rows[6:, s:e] = ((a[s:e] - frame.centre) / frame.scale * spatial_split).T
    map_row_chunks(points_and_rows, k)
    check()
    tree = linetree_from_rows(rows, leaf_size)
    o = tree.order
    # then in tree order: the records, the boxes' rows, point_blocks' layout, the ids
    lines = np.empty(k, LSG_LINE)
    lo, hi = np.empty((3, k), np.float32), np.empty((3, k), np.float32)
    points = point_block_array(k)
    sorted_ids = np.empty(k, np.int32)

    def in_tree_order(s: int, e: int) -> float:
        check()
        oc = o[s:e]
        lines[s:e] = lines_in[oc]
        b = box_in[oc]
        lo[:, s:e], hi[:, s:e] = b[:, :3].T, b[:, 3:].T
        p = pts[oc]
        point_blocks(p, points, s)
        sorted_ids[s:e] = ids[oc]
        return float(np.abs(p[:, 3:]).sum(axis=1).max())
    max_m1 = max(map_row_chunks(in_tree_order, k, align=POINT_LANES)) if k else 0.0
    check()
    boxes = node_boxes(tree, lo, hi)
    check()
    kids = child_rows(tree, boxes)
    nbytes = int(segment_bytes(segs) + 96 * k + 56 * k + 2 * lines.nbytes + points.nbytes
                 + tree.nbytes + boxes.nbytes + kids.nbytes)
    return PreparedLines(lines, points, sorted_ids, tree, boxes, kids, frame, max_m1, nbytes)


@dataclass
class ViewTree:
    """View segments in the order of a line tree over their Plücker points, on the device:
    what a query per lighting segment walks (``lsg_scatter``). ``bufs``: the view records
    in tree order (``views``), their Plücker points, their indices (``ids``), the tree's
    nodes, 3-D boxes and leaf ranges, and the fixed-point sums and valid pairs (``acc``, a
    record of SCATTER_BYTES per view)."""

    tree: LineTree
    frame: PluckerFrame
    max_m1: float
    count: int
    weight_max: float          # the largest weight of a view segment in it (any channel)
    bufs: dict
    nbytes: int

    def release(self, engine) -> None:
        engine.free(*self.bufs.values())
        self.bufs = {}


def build_view_tree(engine: Engine, views: np.ndarray, idx: np.ndarray,
                    leaf_size: int = LEAF_SIZE, spatial_split: float = SPATIAL_SPLIT) -> ViewTree:
    """The :class:`ViewTree` of the view segments ``views[idx]`` (those of length 0 left
    out); its splits are steered by the segments' midpoints, times ``spatial_split``."""
    v = views[np.asarray(idx, np.int64)]
    a = v["a"][:, :3].astype(np.float64)
    b = v["b"][:, :3].astype(np.float64)
    length = np.linalg.norm(b - a, axis=1)
    keep = np.flatnonzero(length > 0)
    v, a, b, length = v[keep], a[keep], b[keep], length[keep]
    ids = np.asarray(idx, np.int64)[keep]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    frame = (PluckerFrame.for_segments(lo.min(axis=0), hi.max(axis=0)) if len(a)
             else PluckerFrame.for_box(np.zeros(3), np.zeros(3)))
    u32 = ((b - a) / np.maximum(length, 1e-300)[:, None]).astype(np.float32)
    pts = plucker(a, u32.astype(np.float64), frame).astype(np.float32)
    pts[:, :3] = u32
    extra = (0.5 * (a + b) - frame.centre) / frame.scale * spatial_split if spatial_split > 0 \
        else None
    tree = build_linetree(pts * canonical_signs(u32)[:, None], leaf_size, extra)
    o = tree.order
    points = point_blocks(pts[o])
    boxes = node_boxes(tree, lo[o].T, hi[o].T)
    n = len(o)
    host = {"views": v[o], "points": points, "ids": ids[o].astype(np.int32),
            "kids": child_rows(tree, boxes), "ranges": tree.leaf_ranges}
    bufs = {k: engine.to_device(x if len(x) else np.zeros(1, x.dtype)) for k, x in host.items()}
    bufs["acc"] = engine.zeros(SCATTER_BYTES * max(n, 1))
    max_m1 = float(np.abs(pts[:, 3:]).sum(axis=1).max()) if n else 0.0
    w_max = float(np.max(v["weight"][:, :3])) if n else 0.0
    return ViewTree(tree, frame, max_m1, n, max(w_max, 0.0), bufs,
                    int(sum(x.nbytes for x in host.values()) + SCATTER_BYTES * n))


@dataclass
class ScreenSide:
    """What ``queries = "screen"`` keeps for a set of view segments: those on the camera's
    rays in screen ``cells``, the indices of the others (``rest``) and a device copy of
    them (``rest_buf``)."""

    cells: ScreenCells
    rest: np.ndarray
    rest_buf: object

    def release(self, engine) -> None:
        self.cells.release(engine)
        engine.free(self.rest_buf)


def phase_max(g: float) -> float:
    """The largest value of the Henyey-Greenstein phase function with parameter ``g``:
    ``(1 + |g|) / (4 pi (1 - |g|)^2)`` (forward for g > 0, backward for g < 0)."""
    ag = min(abs(float(g)), 1.0 - 1e-4)
    return (1.0 + ag) / (4.0 * np.pi * (1.0 - ag) ** 2)


@dataclass
class ChunkResult:
    pair_tests: int
    valid_pairs: int
    kept: int                  # lighting segments left after clipping
    nbytes: int                # host + device working set of this chunk
    tree_seconds: float
    gather_seconds: float
    pairs: np.ndarray | None   # (k, 2) int32 (view index, input light index) if recorded
    leaf_points: int = 0       # points in the leaves the hierarchy visited (paper's count)

    def plus(self, other: ChunkResult, same_segments: bool = False) -> ChunkResult:
        """This chunk's counts, times and pairs with ``other``'s added (the larger working
        set); ``same_segments``: both gathered the same lighting segments (for different
        view segments), which are then kept once, not twice."""
        pairs = [p for p in (self.pairs, other.pairs) if p is not None]
        return ChunkResult(self.pair_tests + other.pair_tests,
                           self.valid_pairs + other.valid_pairs,
                           self.kept if same_segments else self.kept + other.kept,
                           max(self.nbytes, other.nbytes),
                           self.tree_seconds + other.tree_seconds,
                           self.gather_seconds + other.gather_seconds,
                           np.concatenate(pairs) if pairs else None,
                           self.leaf_points + other.leaf_points)


class Gatherer:
    """View segments on the device plus an accumulator; gathers chunks of lighting segments.

    ``add(segments)`` clips them, builds the tree, runs ``lsg_gather`` (exhaustively, no
    tree, with ``bruteforce=True``) and adds the estimate of every view segment
    into the accumulator; :meth:`values` reads the sum, ``(n_views, 4)`` rgb.
    ``record_pairs > 0`` also returns up to that many valid (view, light) pairs per chunk.
    ``clip = False`` keeps lighting segments whole (otherwise they are cut to the view
    segments' box grown by the radius); ``frame`` fixes the Plücker frame (tests);
    ``spatial_split`` weighs where segments start in the tree's splits (:data:`SPATIAL_SPLIT`).
    ``views_buf``: the same view segments already on the device (a render's
    :class:`~clscatter.transport.view_paths.DeviceSegments` buffer; not freed here), else uploaded.
    ``region``: the region the lighting segments and ``medium`` belong to
    (:func:`~clscatter.device.structs.segment_regions`: 0 the scene medium, m + 1 the inside
    of dielectric material m, ``medium`` then holding its interior coefficients,
    :func:`region_media`); view segments of other regions gather nothing.

    :meth:`select` restricts the following :meth:`add` calls to a group of each pixel's
    camera samples (their estimate scaled to stand for the whole pixel).

    ``queries`` (:data:`QUERIES`) picks the side that walks a tree in each :meth:`add`:
    ``views`` builds the tree over the chunk's lighting segments and walks it once per
    view segment (``lsg_gather``); ``lights`` walks a tree over the view segments
    (:class:`ViewTree`, built at the first use and kept; with ``derived``, a
    :meth:`~clscatter.transport.view_paths.DeviceSegments.derived` of the same view
    segments, kept as long as they are) once per lighting segment (``lsg_scatter``);
    ``screen`` (with ``camera``, a CAMERA record; else as ``views``) puts the view
    segments on the camera's rays in :class:`~.screen_cells.ScreenCells`, kept likewise,
    which every lighting segment crosses (``lsg_splat``), and gathers the others from
    the side with fewer segments. All find the same pairs and the same estimate (to
    float rounding: the lighting side's sums are exact fixed-point ones).
    :attr:`last_queries` says which the last :meth:`add` took.

    Per view segment, the estimate and the work counters (tests, valid pairs, leaf points)
    accumulate on the device; an :meth:`add` reads back the counters' totals only, and
    :meth:`image` sums the estimate into pixels there. The host needs the view segments
    for the box that clips the lighting segments, and :attr:`valid_per_view` (the
    automatic radius's pilot) reads one count per view.
    """

    def __init__(self, engine: Engine, views: np.ndarray, medium: np.ndarray, radius: float,
                 min_sin: float = 1e-6, leaf_size: int = LEAF_SIZE, per_launch: int = 65536,
                 record_pairs: int = 0, show_progress: bool = False, clip: bool = True,
                 frame: PluckerFrame | None = None, views_buf=None, region: int = 0,
                 spatial_split: float = SPATIAL_SPLIT, queries: str = "views",
                 derived=None, camera: np.ndarray | None = None):
        if queries not in QUERIES:
            raise ValueError(f"queries must be one of {QUERIES}, not {queries!r}")
        self.queries = queries
        self.eng = engine
        self.region = int(region)
        self.views = views
        self.n = len(views)
        self.medium = np.asarray(medium).reshape(1)
        self.radius = float(radius)
        self.min_sin = float(min_sin)
        self.leaf_size = int(leaf_size)
        self.spatial_split = float(spatial_split)
        self.per_launch = max(1, int(per_launch))
        self.record = int(record_pairs)
        self.show_progress = show_progress
        ab = np.concatenate([views["a"][:, :3], views["b"][:, :3]]).astype(np.float64)
        self.lo = ab.min(axis=0) if len(ab) else np.zeros(3)
        self.hi = ab.max(axis=0) if len(ab) else np.zeros(3)
        if not clip:   # (tests) keep the lighting segments whole
            self.lo, self.hi = np.full(3, -np.inf), np.full(3, np.inf)
        self.frame = frame
        self._own_views = views_buf is None
        self.views_buf = engine.to_device(views) if views_buf is None else views_buf
        self.medium_buf = engine.to_device(self.medium)
        self.out_buf = engine.zeros(max(self.n, 1) * 16)
        # per view: (tests, valid pairs, leaf points, 0) summed over add() calls
        self.counts_buf = engine.zeros(max(self.n, 1) * 16)
        self._totals = np.zeros(4, np.int64)     # their totals after the last add()
        self.pairs_buf = engine.empty(max(self.record, 1) * 8)
        self.pair_count = engine.empty(4)
        self._groups: dict[tuple[int, int, int], tuple[object, int, float]] = {}
        self._group: tuple[object, int, float] | None = None    # None: every view segment
        self._group_key: tuple[int, int, int] | None = None
        self._group_idx: dict[tuple[int, int, int], np.ndarray] = {}
        self._view_trees: dict = {}          # (part, group key) -> what _kept built
        self._derived = derived              # keeps view trees beyond this gatherer
        self.camera = camera                 # a pinhole's rays: screen cells, not a tree
        self.last_queries = ""               # the side the last add() queried from

    @property
    def active(self) -> int:
        """View segments the next :meth:`add` gathers (the selected group's, or all)."""
        return self._group[1] if self._group is not None else self.n

    # ---- camera-sample groups ----
    def select(self, group: int | None, groups: int = 1, spp: int = 1) -> None:
        """Gather only the view segments of the camera samples ``k`` with ``k % groups ==
        group`` (``k`` the sample's index within its pixel, ``spp`` per pixel), each
        estimate times ``spp`` over the group's samples, so one group estimates the whole
        pixel as all of them do (exactly so on average over the groups); ``None`` (or one
        group): every view segment, as before. The index lists are built once per group."""
        groups, spp = max(1, int(groups)), max(1, int(spp))
        if group is None or groups <= 1:
            self._group = self._group_key = None
            return
        key = (int(group) % groups, groups, spp)
        if key not in self._groups:
            idx = np.flatnonzero(sample_groups(self.views, groups, spp) == key[0]).astype(np.int32)
            buf = self.eng.to_device(idx if len(idx) else np.zeros(1, np.int32))
            self._groups[key] = (buf, len(idx), spp / max(group_samples(key[0], groups, spp), 1))
            self._group_idx[key] = idx
        self._group, self._group_key = self._groups[key], key

    def prepare(self) -> None:
        """Build what this gatherer keeps for the active view segments (the view tree with
        ``queries = "lights"``, the screen cells with ``"screen"``) now rather than in the
        next :meth:`add`, whose time then holds its own work only (the automatic radius's
        pilot sizes passes by it)."""
        if not self.active:
            return
        if self.queries == "lights":
            self._view_tree(None)
        elif self.queries == "screen" and self.camera is not None:
            self._screen()

    # ---- one chunk ----
    def add(self, segs: np.ndarray, bruteforce: bool = False) -> ChunkResult:
        """Gather the lighting segments ``segs`` into every active view segment's estimate,
        from the side ``queries`` says (``bruteforce``: every pair, a query per view segment
        over a one-leaf tree)."""
        t_build, t_gather = Timer(), Timer()
        kappa = self.medium["kappa"][0]
        with t_build:
            clipped = continue_and_clip(segs, self.medium, self.radius, self.lo, self.hi, kappa)
        queries = "views" if bruteforce else self.queries
        if queries == "screen" and self.camera is None:
            queries = "views"
        self.last_queries = queries
        if queries == "lights" and self.active:
            with t_build:
                vt = self._view_tree(None)
            return self._add_from_lights(segs, clipped, vt, None, t_build, t_gather)
        if queries == "screen" and self.active:
            return self._add_from_screen(segs, clipped, t_build, t_gather)
        return self._add_from_views(segs, clipped, bruteforce, t_build, t_gather)

    def _add_from_screen(self, segs, clipped, t_build: Timer, t_gather: Timer) -> ChunkResult:
        """The camera's rays in screen cells from the lighting side; the other view
        segments from the side with fewer segments (a tree over them, or one over the
        lighting segments queried by them alone). A tree over the lighting segments is
        built on a host thread while the device splats them over the cells."""
        with t_build:
            side = self._screen()
            sc, rest, rest_buf = side.cells, side.rest, side.rest_buf
            rest_from_views = 0 < len(rest) <= len(clipped[0])
            vt = None if len(rest) == 0 or rest_from_views else self._view_tree(rest)
        if not rest_from_views:
            return self._add_from_lights(segs, clipped, vt, sc, t_build, t_gather)
        t_wait = Timer()        # the tree's time beyond the splat's (the rest is hidden)
        halt = threading.Event()
        pool = ThreadPoolExecutor(1)
        try:
            building = pool.submit(prepare_lines, segs, self.lo, self.hi, self.radius,
                                   self.medium["kappa"][0], self.leaf_size, self.frame,
                                   self.spatial_split, clipped, halt.is_set)
            res = self._add_from_lights(segs, clipped, None, sc, t_build, t_gather)
            with t_wait:
                prep = building.result()
        finally:                # a cancelled render stops the tree and does not wait for it
            halt.set()
            pool.shutdown(wait=False)
        # both working sets at once while the tree was built beside the splat (the traced
        # and clipped segments, which both count, once)
        both = res.nbytes + prep.nbytes - segment_bytes(segs)
        self.eng.note_host(both)
        scale = self._group[2] if self._group is not None else 1.0
        more = self._add_from_views(segs, clipped, False, t_wait, Timer(),
                                    group=(rest_buf, len(rest), scale), prep=prep)
        out = res.plus(more, same_segments=True)
        out.nbytes = max(out.nbytes, both)
        return out

    def _add_from_views(self, segs, clipped, bruteforce: bool, t_build: Timer,
                        t_gather: Timer, group: tuple | None = None,
                        prep: PreparedLines | None = None) -> ChunkResult:
        """A tree over the lighting segments (``prep``: built already), a query per view
        segment (``lsg_gather``); ``group``: (index buffer, count, scale) of the view
        segments that query, instead of the selected group's (or all)."""
        eng = self.eng
        kappa = self.medium["kappa"][0]
        # bruteforce: a one-leaf tree (the lines in input order, clipped like the tree's)
        leaf = 1 << 62 if bruteforce else self.leaf_size
        if prep is None:
            with t_build:
                prep = prepare_lines(segs, self.lo, self.hi, self.radius, kappa, leaf,
                                     self.frame, self.spatial_split, clipped)
        with t_gather:
            eng.note_host(prep.nbytes)
            lines_buf = eng.to_device(prep.lines)
            points_buf = eng.to_device(prep.points)
            ids_buf = eng.to_device(prep.ids)
            kids_buf = eng.to_device(prep.kids)
            ranges_buf = eng.to_device(prep.tree.leaf_ranges)
            dev_bytes = (prep.lines.nbytes + prep.points.nbytes + prep.ids.nbytes
                         + prep.kids.nbytes
                         + prep.tree.leaf_ranges.nbytes)
            # the host arrays that stay alive beside the new device buffers
            eng.note_host(prep.nbytes - prep.lines.nbytes - prep.points.nbytes)
            self._clear_pair_count()
            fr = prep.frame
            centre = structs.vec4(fr.centre)
            tests = valid = leaf = 0
            # (index list, its length, scale); all views: any buffer, unread with indexed = 0
            index_buf, count, scale = group or self._group or (self.pair_count, self.n, 1.0)
            if len(prep.lines) and count:
                with progress(count, "lsg gather", self.show_progress) as bar:
                    for start, m in timed_launches(count, self.per_launch):
                        eng.call("lsg", "lsg_gather", m, kids=kids_buf,
                                 leaf_ranges=ranges_buf,
                                 first_leaf=prep.tree.first_leaf, lines=lines_buf,
                                 points=points_buf, line_ids=ids_buf, num_lines=len(prep.lines),
                                 max_m1=prep.max_m1, views=self.views_buf, view_offset=start,
                                 num_views=m, view_index=index_buf,
                                 indexed=int((group or self._group) is not None), scale=scale,
                                 pl_centre=centre, pl_inv_scale=1.0 / fr.scale,
                                 radius=self.radius, min_sin=self.min_sin, medium=self.medium_buf,
                                 region=self.region, exhaustive=int(bruteforce), out=self.out_buf,
                                 counts=self.counts_buf, pairs=self.pairs_buf,
                                 pair_count=self.pair_count, max_pairs=self.record)
                        eng.finish()
                        bar.update(m)
                totals = prim.int_totals(eng, self.counts_buf, self.n, 4)
                tests, valid, leaf = (int(x) for x in (totals - self._totals)[:3])
                self._totals = totals
            pairs = self._recorded_pairs()
            eng.free(lines_buf, points_buf, ids_buf, kids_buf, ranges_buf)
        return ChunkResult(tests, valid, len(prep.lines), int(prep.nbytes + dev_bytes),
                           t_build.seconds, t_gather.seconds, pairs, leaf)

    def _add_from_lights(self, segs, clipped, vt: ViewTree | None, sc: ScreenCells | None,
                         t_build: Timer, t_gather: Timer) -> ChunkResult:
        """A query per lighting segment: over the tree ``vt`` of view segments
        (``lsg_scatter``) and over the camera's rays in the screen cells ``sc``
        (``lsg_splat``), either of which may be None."""
        eng = self.eng
        ids, a, u, length, flux = clipped
        n = len(ids)
        if sc is not None and sc.count and n:
            with t_build:
                o = splat_order(sc, a, u, length)
                ids, a, u, length, flux = ids[o], a[o], u[o], length[o], flux[o]
        lines = np.zeros(n, LSG_LINE)
        lines["a"][:, :3] = a
        lines["a"][:, 3] = length
        lines["u"][:, :3] = u.astype(np.float32)
        lines["flux"][:, :3] = flux
        nbytes = int(segment_bytes(segs) + 2 * lines.nbytes + 24 * n)
        tests = valid = leaf = 0
        sides = [x for x in (vt, sc) if x is not None and x.count]
        with t_gather:
            eng.note_host(nbytes)
            _, _, scale = self._group or (None, self.n, 1.0)
            if n and sides:
                sigma_s = float(np.max(self.medium["sigma_s"][0][:3]))
                g = float(self.medium["g"][0])
                bound = (float(np.sum(flux.max(axis=1) * length)) * phase_max(g)
                         / (np.pi * self.radius ** 2) * sigma_s
                         * max(x.weight_max for x in sides) * scale)
                fixed = fixed_scale(bound)
                bufs = [eng.to_device(lines), eng.to_device(ids.astype(np.int32)),
                        eng.zeros(16 * n)]
                lines_buf, ids_buf, counts_buf = bufs
                self._clear_pair_count()
                for x in sides:
                    eng.cl.enqueue_fill_buffer(eng.queue, x.bufs["acc"], np.zeros(1, np.uint32),
                                               0, SCATTER_BYTES * x.count)
                common = dict(lights=lines_buf, light_ids=ids_buf, scale=scale,
                              radius=self.radius, min_sin=self.min_sin, medium=self.medium_buf,
                              fixed_scale=fixed, light_counts=counts_buf, pairs=self.pairs_buf,
                              pair_count=self.pair_count, max_pairs=self.record)
                try:
                    with progress(n, "lsg gather", self.show_progress) as bar:
                        for start, m in timed_launches(n, self.per_launch):
                            if vt is not None and vt.count:
                                self._scatter(vt, start, m, common)
                            if sc is not None and sc.count:
                                self._splat(sc, start, m, common)
                            eng.finish()
                            bar.update(m)
                    for x in sides:
                        eng.call("lsg", "lsg_scatter_finish", x.count, acc=x.bufs["acc"],
                                 view_ids=x.bufs["ids"], num_views=x.count,
                                 inv_scale=1.0 / fixed, out=self.out_buf,
                                 counts=self.counts_buf)
                    tests, valid, leaf = (int(x) for x in prim.int_totals(eng, counts_buf, n, 4)[:3])
                    self._totals[1] += valid        # the views' valid counts rose by as many
                finally:
                    eng.free(*bufs)
            pairs = self._recorded_pairs()
        return ChunkResult(tests, valid, n, nbytes, t_build.seconds, t_gather.seconds, pairs,
                           leaf)

    def _scatter(self, vt: ViewTree, start: int, m: int, common: dict) -> None:
        """``lsg_scatter`` of lighting segments start .. start + m - 1 over the tree."""
        fr, tb = vt.frame, vt.bufs
        self.eng.call("lsg", "lsg_scatter", m, kids=tb["kids"], leaf_ranges=tb["ranges"],
                      first_leaf=vt.tree.first_leaf, views=tb["views"], points=tb["points"],
                      view_ids=tb["ids"], max_m1=vt.max_m1, light_offset=start, num_lights=m,
                      pl_centre=structs.vec4(fr.centre), pl_inv_scale=1.0 / fr.scale,
                      acc=tb["acc"], **common)

    def _splat(self, sc: ScreenCells, start: int, m: int, common: dict) -> None:
        """``lsg_splat`` of lighting segments start .. start + m - 1 over the screen cells."""
        eye, ex, ey, ez = sc.frame
        b = sc.bufs
        self.eng.call("lsg", "lsg_splat", m, views=b["views"], dirs=b["dirs"], view_ids=b["ids"],
                      cell_start=b["start"], nx=sc.nx, ny=sc.ny, eye=eye, ex=ex, ey=ey, ez=ez,
                      grid=sc.grid, reach=sc.reach, light_offset=start, num_lights=m,
                      acc=b["acc"], **common)

    def _active_region(self) -> np.ndarray:
        """Indices of the active view segments (the selected group's, or all) in this
        gatherer's region."""
        key = self._group_key
        idx = self._group_idx[key] if key is not None else np.arange(self.n)
        return idx[np.rint(self.views["a"][idx, 3]).astype(np.int64) == self.region]

    def _kept(self, part: str, build):
        """``build()``'s result for ``part`` of the active view segments, made once: kept by
        ``derived`` when given (it outlives the gatherer: a later render over the same view
        segments, e.g. after a light move, reuses it), else until :meth:`release`."""
        key = (part, self._group_key)
        if key not in self._view_trees:
            if self._derived is None:
                self._view_trees[key] = build()[1]
            else:
                name = (f"lsg_view_{part} views={self.n} region={self.region} "
                        f"group={self._group_key} leaf={self.leaf_size} "
                        f"split={self.spatial_split:g}")
                self._view_trees[key] = self._derived(name, build)
        return self._view_trees[key]

    def _view_tree(self, rest: np.ndarray | None) -> ViewTree:
        """The :class:`ViewTree` of the active view segments of this gatherer's region
        (``rest``: of those off the camera's rays, :meth:`_screen`)."""
        def build() -> tuple[list, ViewTree]:
            idx = self._active_region() if rest is None else rest
            vt = build_view_tree(self.eng, self.views, idx, self.leaf_size, self.spatial_split)
            self.eng.note_host(vt.nbytes)
            return list(vt.bufs.values()), vt
        return self._kept("tree" if rest is None else "rest_tree", build)

    def _screen(self) -> ScreenSide:
        """The active view segments of this gatherer's region on the camera's rays in
        :class:`ScreenCells`, the indices of the others and a device copy of them."""
        def build() -> tuple[list, ScreenSide]:
            idx = self._active_region()
            ray, reach = on_camera_rays(self.views[idx], self.camera)
            sc = build_screen_cells(self.eng, self.views, idx[ray], self.camera, reach,
                                    self.views_buf)
            rest = idx[~ray].astype(np.int32)
            rest_buf = self.eng.to_device(rest if len(rest) else np.zeros(1, np.int32))
            self.eng.note_host(sc.nbytes + rest.nbytes)
            return [*sc.bufs.values(), rest_buf], ScreenSide(sc, rest, rest_buf)
        return self._kept("screen", build)

    def _clear_pair_count(self) -> None:
        self.eng.cl.enqueue_fill_buffer(self.eng.queue, self.pair_count, np.zeros(1, np.int32),
                                        0, 4)

    def _recorded_pairs(self) -> np.ndarray | None:
        """The valid pairs the last launch recorded (``record_pairs > 0``), else None."""
        if not self.record:
            return None
        got = int(self.eng.read(self.pair_count, 1, np.int32)[0])
        if got > self.record:
            raise RuntimeError(f"{got} valid pairs exceed record_pairs={self.record}")
        return self.eng.read(self.pairs_buf, (got, 2), np.int32)

    def reset(self) -> None:
        """Zero the accumulator and the per-view counters."""
        q = self.eng.queue
        for buf in (self.out_buf, self.counts_buf):
            self.eng.cl.enqueue_fill_buffer(q, buf, np.zeros(1, np.float32), 0, max(self.n, 1) * 16)
        self._totals[:] = 0

    @property
    def screen_segments(self) -> int:
        """View segments this gatherer keeps in screen cells (``queries = "screen"``: those
        on the camera's rays, over the sample groups gathered so far)."""
        return sum(kept.cells.count for (part, _), kept in self._view_trees.items()
                   if part == "screen")

    @property
    def valid_per_view(self) -> np.ndarray:
        """Valid pairs per view segment, summed over the add() calls since the last
        reset(), (n_views,) int64 (read from the device)."""
        c = self.eng.read(self.counts_buf, (max(self.n, 1), 4), np.int32)[:self.n]
        return c[:, 1].astype(np.int64)

    def values(self) -> np.ndarray:
        """The accumulated estimate per view segment, ``(n_views, 4)`` float32."""
        return self.eng.read(self.out_buf, (max(self.n, 1), 4), np.float32)[:self.n]

    def image(self, segs: DeviceSegments, scale: float = 1.0) -> np.ndarray:
        """The accumulated estimate summed into an (H, W, 3) image on the device, times
        ``scale``; ``segs`` holds the same view segments in the same order (its pixel
        offsets)."""
        return segs.accumulate(self.out_buf) * np.float32(scale)

    def release(self) -> None:
        self.eng.free(*([self.views_buf] if self._own_views else []), self.medium_buf,
                      self.out_buf, self.counts_buf, self.pairs_buf, self.pair_count,
                      *(g[0] for g in self._groups.values()))
        self._groups.clear()
        if self._derived is None:
            for kept in self._view_trees.values():
                kept.release(self.eng)
        self._view_trees.clear()


def scene_materials(scene) -> list:
    """The scene's materials in the order of the device material table (the first use of
    each by the objects, in scene order: :func:`clscatter.scene.normalised.triangle_soup`)."""
    seen: dict[int, object] = {}
    for o in scene.objects:
        seen.setdefault(id(o.material), o.material)
    return list(seen.values())


def interior_medium(material_row: np.ndarray, g: float) -> np.ndarray:
    """A Medium record (``structs.MEDIUM``) of the homogeneous medium inside a dielectric
    (one row of the device material table, normalised units): sigma_s and sigma_a its
    interior ones, kappa their sum, phase ``g``, unbounded (the object's surface bounds it:
    the segments inside end there)."""
    m = np.zeros(1, structs.MEDIUM)
    ss = material_row["interior_sigma_s"][:3].astype(np.float64)
    sa = material_row["interior_sigma_a"][:3].astype(np.float64)
    m["sigma_s"] = structs.vec4(ss)
    m["sigma_a"] = structs.vec4(sa)
    m["kappa"] = structs.vec4(ss + sa)
    m["bmin"], m["bmax"] = structs.vec4([-1e30] * 3), structs.vec4([1e30] * 3)
    m["g"], m["present"], m["bounded"], m["t_far"] = g, 1, 0, 1e30
    return m


def region_media(ps) -> list[tuple[int, np.ndarray]]:
    """(region, Medium record) of every dielectric material of the prepared scene ``ps``
    whose interior scatters (``interior_sigma_s`` above 0 in a channel): region m + 1 for
    material m (:func:`~clscatter.device.structs.segment_regions`), phase ``interior_g``, or
    the scene medium's g where the material gives none (0 without a medium), as the
    scene format says."""
    mats = scene_materials(ps.scene)
    g_medium = float(ps.scene.medium.g) if ps.scene.medium is not None else 0.0
    out = []
    for i, row in enumerate(ps.materials if ps.materials is not None else []):
        if int(row["type"]) != structs.MAT_DIELECTRIC or float(row["interior_sigma_s"][:3].max()) <= 0:
            continue
        g = mats[i].interior_g if i < len(mats) and mats[i].interior_g is not None else g_medium
        out.append((i + 1, interior_medium(row, float(g))))
    return out


@dataclass
class _Part:
    gatherer: Gatherer
    segs: DeviceSegments       # the view segments it gathers into, on the device


class RegionGatherer:
    """Several :class:`Gatherer`, one per region, behind the interface of one: the scene
    medium's over the shared view segments, and one per dielectric whose interior scatters
    over the view segments inside glass (:func:`~clscatter.transport.view_paths.trace_interior_segments`).
    :meth:`add` hands each lighting segment to the gatherer of its region (its tag), so a
    pair is only ever formed inside one region, with that region's sigma_s, g and kappa.
    ``views``, :meth:`values` and :attr:`valid_per_view` run over the parts' view segments
    in order; :meth:`image` sums every part's image."""

    def __init__(self, parts: list[tuple[Gatherer, DeviceSegments]]):
        self.parts = [_Part(g, d) for g, d in parts]
        views = [p.gatherer.views for p in self.parts]
        self.views = np.concatenate(views) if views else np.zeros(0, structs.VIEW_SEGMENT)
        self.n = len(self.views)
        self.show_progress = any(p.gatherer.show_progress for p in self.parts)

    @property
    def radius(self) -> float:
        return self.parts[0].gatherer.radius if self.parts else 0.0

    @radius.setter
    def radius(self, r: float) -> None:
        for p in self.parts:
            p.gatherer.radius = float(r)

    def add(self, segs: np.ndarray, bruteforce: bool = False) -> ChunkResult:
        """Gather the lighting segments ``segs`` (any regions) into their region's part."""
        regions = structs.segment_regions(segs) if len(segs) else np.zeros(0, np.int32)
        res = ChunkResult(0, 0, 0, 0, 0.0, 0.0, None, 0)
        for p in self.parts:
            sub = segs[regions == p.gatherer.region]
            if len(sub) and p.gatherer.n:
                res = res.plus(p.gatherer.add(sub, bruteforce))
        return res

    def reset(self) -> None:
        for p in self.parts:
            p.gatherer.reset()

    def select(self, group: int | None, groups: int = 1, spp: int = 1) -> None:
        for p in self.parts:
            p.gatherer.select(group, groups, spp)

    @property
    def active(self) -> int:
        return sum(p.gatherer.active for p in self.parts)

    @property
    def screen_segments(self) -> int:
        return sum(p.gatherer.screen_segments for p in self.parts)

    def prepare(self) -> None:
        for p in self.parts:
            p.gatherer.prepare()

    @property
    def valid_per_view(self) -> np.ndarray:
        got = [p.gatherer.valid_per_view for p in self.parts]
        return np.concatenate(got) if got else np.zeros(0, np.int64)

    def values(self) -> np.ndarray:
        got = [p.gatherer.values() for p in self.parts]
        return np.concatenate(got) if got else np.zeros((0, 4), np.float32)

    def image(self, segs: DeviceSegments | None = None, scale: float = 1.0) -> np.ndarray:
        """Every part's estimate summed into one (H, W, 3) image on the device, times
        ``scale`` (``segs`` is not used: each part has its own view segments; it is there
        so that this stands in for :meth:`Gatherer.image`)."""
        img = None
        for p in self.parts:
            part = p.gatherer.image(p.segs, scale)
            img = part if img is None else img + part
        return img

    def release(self) -> None:
        for p in self.parts:
            p.gatherer.release()
