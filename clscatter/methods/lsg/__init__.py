"""Line space gathering (Sun et al. 2010): single scattering gathered from lighting rays."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ...transport import primitives as prim
from ...device import structs
from .linetree import (LINE_NODE, LineTree, PluckerFrame, build_linetree, canonical_signs,
                              plucker)
from ...device import Engine
from ...geometry import slab_interval
from ...transport.emission import targeted_fraction
from ...transport.light_paths import ray_counts, trace_light_paths
from ...transport.prepared import PreparedScene
from ...transport.view_paths import DeviceSegments, ViewPaths
from ...io.stats import Stats, Timer, progress
from .. import AutoRole, Method, Param, register

F4 = structs.F4

# ``LsgLine`` in cl_kernels/lsg.h
LSG_LINE = np.dtype([("a", *F4), ("u", *F4), ("flux", *F4)], align=True)

# name in cl_kernels/lsg.h -> dtype; used by the layout test
STRUCTS = {"LineNode": structs.register_struct("lsg.h", "LineNode", LINE_NODE),
           "LsgLine": structs.register_struct("lsg.h", "LsgLine", LSG_LINE)}

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
    leaf_points: int = 0       # points in the leaves the hierarchy visited (paper's count)


class Gatherer:
    """View segments on the device plus an accumulator; gathers chunks of lighting segments.

    ``add(segments)`` clips them, builds the tree, runs ``lsg_gather`` (exhaustively, no
    tree, with ``bruteforce=True``) and adds the estimate of every view segment
    into the accumulator; :meth:`values` reads the sum, ``(n_views, 4)`` rgb.
    ``record_pairs > 0`` also returns up to that many valid (view, light) pairs per chunk.
    ``clip = False`` keeps lighting segments whole (otherwise they are cut to the view
    segments' box grown by the radius); ``frame`` fixes the Plücker frame (tests).
    ``views_buf``: the same view segments already on the device (a render's
    :class:`~clscatter.transport.view_paths.DeviceSegments` buffer; not freed here), else uploaded.

    Per view segment, the estimate and the work counters (tests, valid pairs, leaf points)
    accumulate on the device; an :meth:`add` reads back the counters' totals only, and
    :meth:`image` sums the estimate into pixels there. The host needs the view segments
    for the box that clips the lighting segments, and :attr:`valid_per_view` (the
    automatic radius's pilot) reads one count per view.
    """

    def __init__(self, engine: Engine, views: np.ndarray, medium: np.ndarray, radius: float,
                 min_sin: float = 1e-6, leaf_size: int = 4, per_launch: int = 65536,
                 record_pairs: int = 0, show_progress: bool = False, clip: bool = True,
                 frame: PluckerFrame | None = None, views_buf=None):
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
        self._own_views = views_buf is None
        self.views_buf = engine.to_device(views) if views_buf is None else views_buf
        self.medium_buf = engine.to_device(self.medium)
        self.out_buf = engine.zeros(max(self.n, 1) * 16)
        # per view: (tests, valid pairs, leaf points, 0) summed over add() calls
        self.counts_buf = engine.zeros(max(self.n, 1) * 16)
        self._totals = np.zeros(4, np.int64)     # their totals after the last add()
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
            segs = continue_across_faces(segs, self.medium, self.radius)
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
            tests = valid = leaf = 0
            if len(prep.lines) and self.n:
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
                        eng.finish()
                        bar.update(m)
                totals = prim.int_totals(eng, self.counts_buf, self.n, 4)
                tests, valid, leaf = (int(x) for x in (totals - self._totals)[:3])
                self._totals = totals
            pairs = None
            if self.record:
                got = int(eng.read(self.pair_count, 1, np.int32)[0])
                if got > self.record:
                    raise RuntimeError(f"{got} valid pairs exceed record_pairs={self.record}")
                pairs = eng.read(self.pairs_buf, (got, 2), np.int32)
            eng.free(lines_buf, points_buf, ids_buf, nodes_buf, ranges_buf)
        return ChunkResult(tests, valid, len(prep.lines), int(prep.nbytes + dev_bytes),
                           t_build.seconds, t_gather.seconds, pairs, leaf)

    def reset(self) -> None:
        """Zero the accumulator and the per-view counters."""
        q = self.eng.queue
        for buf in (self.out_buf, self.counts_buf):
            self.eng.cl.enqueue_fill_buffer(q, buf, np.zeros(1, np.float32), 0, max(self.n, 1) * 16)
        self._totals[:] = 0

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
                      self.out_buf, self.counts_buf, self.pairs_buf, self.pair_count)


def _chunk_rays(counts: np.ndarray, k: int, n: int) -> int:
    """Rays that chunk (k, n) of trace_light_paths traces (every light's share)."""
    return int(sum(int(c) * (k + 1) // n - int(c) * k // n for c in counts))


def ppb_radii(r1: float, alpha: float, passes: int) -> np.ndarray:
    """Radii of progressive passes 1..passes: ``r_{i+1} = r_i (i + alpha) / (i + 1)``.

    This is the progressive photon beams rule for a 1-D kernel (Jarosz et al. 2011,
    sec. 5): LSG's pair estimate depends on the line distance d only through the disc
    kernel integrated along the chord, ``2 sqrt(r^2 - d^2) / (pi r^2)``, a 1-D kernel in
    d whose variance grows like 1/r, as for photon beams (not 1/r^2 as for surface
    photons). Keeping a fraction alpha of the new variance per pass makes the average
    of the passes consistent: ``r_i ~ i^(alpha - 1) -> 0`` while
    ``sum_i 1/r_i / i^2 -> 0``; its variance falls like ``passes^-alpha`` and the bias
    (a blur, ~ r^2 where the light field is smooth) like ``passes^-2(1 - alpha)``.
    """
    r = np.empty(max(int(passes), 0))
    cur = float(r1)
    for i in range(len(r)):
        r[i] = cur
        cur *= (i + 1 + alpha) / (i + 2)
    return r


@dataclass
class AutoRadius:
    """What the automatic radius was chosen from (``--stats``: ``lsg_auto_radius``)."""

    radius: float              # chosen, normalised units
    trial_radius: float        # radius of the pilot gather
    pilot_rays: int
    count_median: float        # pilot valid pairs per lit view segment, scaled to light_rays
    footprint: float           # median pixel footprint at the lit view segments
    lit_views: int             # view segments with a pilot pair


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
    Where light enters or leaves a bounded medium its lighting segments are continued
    ``radius`` / cos beyond the face (:func:`continue_across_faces`), so that a view point
    near a face gathers over its whole disc (optical depth 10 seen from outside: the
    image's deficit 0.9 % -> 0.01 %; thin media 0.2 % -> 0.1 %).

    *Targeted emission.* With ``min_light_depth >= 1`` (a caustic pass, as ``auto`` runs
    it) and ``targeted`` (default), every light emits only towards the bounding spheres
    of the mirrors and glass (directional lights: their projected footprint), each ray
    weighted by its exact pdf (``clscatter.transport.emission``), so the expected image is the same
    and no ray is spent on light that cannot make a caustic. ``light_rays`` keeps its
    meaning (rays over the whole emission); only the part of them that would have gone
    towards the mirrors and glass is traced (``light_rays`` in ``--stats``), so the noise
    is that of ``light_rays`` untargeted rays at a fraction of the cost (a glass ball
    under a point light: ~3%).

    *Automatic radius* (``radius = 0``, the default). A pilot traces ``light_rays / 8``
    rays (at least 2000) and gathers them at a trial radius r0 (a quarter of the pixel
    footprint at the median view-segment distance, doubled until 64 view segments find a
    pair), counting
    the valid pairs of every view segment. The number of lighting segments a view
    segment's cylinder catches grows linearly with r (lines crossing a segment within
    distance r), so, scaled to the full ``light_rays``, the median count c over the lit
    view segments gives ``r_n = r0 * auto_count / c``: the radius at which a typical lit
    view segment gathers ``auto_count`` lighting segments (relative noise per segment
    ~ 1 / sqrt(auto_count); 16 by default: on caustic_sphere the blur bias of a larger
    count outweighed the noise it saves, e.g. at 24 x 18 and 200k rays the relMSE
    against a converged reference was 0.043 / 0.49 / 9.7 for 16 / 48 / 128, the noise
    part 0.005 / 0.002 / 0.0007). The radius is not allowed below 1/16 of the median pixel
    footprint f at those segments (a blur that small is invisible even with 16 x 16
    samples per pixel, while the noise keeps growing as r shrinks):
    ``r = max(r_n, f / 16)``. At the default 200k rays on caustic_sphere this gives
    r ~ 0.003 of the extent, the best fixed radius measured by hand before (relMSE 6.7e-4,
    9.7e-5, 6.7e-5, 1.7e-4, 5.3e-4 at 0.001, 0.002, 0.003, 0.005, 0.01; 128 x 96 against
    a 1.6M-ray render). Both terms are measured in the data,
    in the normalised frame, so the same physical scene gets the same radius at any
    scale and with objects added far away (tests/test_invariance.py); the bounding box
    plays no part. ``radius > 0`` overrides it (a multiple of the scene extent, as before).
    The pilot's rays are not part of the image.

    *Progressive passes* (``passes`` > 1 or ``time_budget`` > 0): pass i traces
    ``light_rays`` fresh rays (an independent rotation of the stratified set) and gathers
    them with radius ``r_i``, ``r_{i+1} = r_i (i + alpha) / (i + 1)`` (:func:`ppb_radii`,
    the progressive photon beams rule); the image is the mean of the passes, which
    converges to the exact single scattering (no radius bias floor). With
    ``time_budget`` S, passes run while the time of the passes so far plus one more
    (the mean pass time) fits in S; at least one pass runs, and ``passes`` > 1 is then
    an upper bound.

    Lighting rays are processed in chunks whose estimates are summed (with a fixed radius
    the sum equals one pass over all rays), so that one chunk's working set (traced
    segments, tree, device buffers; ~500 bytes per lighting segment) stays within
    ``max_bytes``; a chunk that turns out larger is re-traced in smaller parts. The view
    segments and the accumulator (80 bytes per view segment) are a fixed cost.

    Statistics: ``light_segments`` (traced), ``lsg_light_segments_kept`` (after clipping
    to the view segments' box grown by r), ``view_segments``, ``pair_tests`` (exact
    segment tests after the tree and per-point plane culling), ``pair_tests_bruteforce``
    (light segments x view segments), ``valid_pairs`` (closer than r),
    ``lsg_cull_fraction`` (1 - pair_tests / bruteforce), ``lsg_valid_fraction`` (valid /
    tested); counted the paper's way (sec. 4.3: the share of exhaustive "line
    intersection tests" the hierarchy culls, and the valid share of the rest):
    ``lsg_leaf_points_tested`` (points in the leaves the tree walk reaches, before the
    per-point plane test), ``lsg_cull_fraction_paper`` (1 - that / (lighting segments
    kept after clipping x view segments)), ``lsg_valid_fraction_paper`` (valid /
    leaf points); ``tree_build_seconds`` (clipping, Plücker points, tree), ``gather_seconds``,
    ``chunks``, ``lsg_chunks_retraced``, ``lsg_chunk_bytes_max`` (largest chunk working
    set), ``lsg_radius`` (first pass, normalised units; ``lsg_radius_world`` in scene
    units), ``lsg_radius_last``,
    ``lsg_passes``, ``lsg_pass_seconds``, ``lsg_time_budget``, ``lsg_auto_radius`` (what
    the automatic radius was chosen from), ``lsg_targeted``,
    ``light_rays_specular_fraction`` (emitted rays whose first hit is a mirror or glass);
    ``peak_bytes`` covers the whole render.

    Usage: ``clscatter render scene.toml --method lsg --set render.lsg.light_rays=1000000
    --set render.lsg.time_budget=30``
    """

    NAME = "lsg"
    PARAMS = (
        Param("light_rays", 200_000, "lighting rays per pass, shared among lights by power", lo=1),
        Param("radius", 0.0, "gather radius relative to the scene extent; 0: automatic, "
              "from the lighting-ray density and the pixel footprint", lo=0),
        Param("auto_count", 16.0, "automatic radius: lighting segments a typical lit view "
              "segment should gather", lo=1),
        Param("passes", 1, "progressive passes of fresh rays (an upper bound with time_budget)", lo=1),
        Param("time_budget", 0.0, "seconds for progressive passes (0: run `passes`)", lo=0),
        Param("first_pass", 0, "index of the first progressive pass to run (pass k uses its "
              "own rays and radius, so passes can run apart and be averaged: a cluster runs "
              "each pass as a task)", lo=0),
        Param("alpha", 0.7, "progressive radius reduction r_(i+1) = r_i (i + alpha) / (i + 1)",
              lo=0, hi=1, lo_open=True, hi_open=True),
        Param("targeted", True, "with min_light_depth >= 1, emit only towards mirrors and glass"),
        Param("light_seed", 0, "selects an independent set of lighting rays (view paths unchanged)",
              lo=0),
        Param("max_bytes", 1 << 30, "working-set bound for one chunk of rays", lo=1),
        Param("leaf_size", 4, "least points per tree leaf (at most 8x)", lo=1),
        Param("min_sin", 1e-6, "sin(theta) below this counts as parallel", lo=0, hi=1, hi_open=True),
        Param("segments_per_launch", 65536, "view segments per kernel launch (progress)", lo=1),
        Param("min_light_depth", 0, "gather only lighting segments with at least this many "
              "specular bounces (1: caustics only, as auto uses it beside a direct method)", lo=0),
    )
    TERMS = frozenset({"direct", "caustics"})
    PREVIEW_SCALE = {"light_rays": 0.125, "passes": 0.0, "time_budget": 0.0}
    # a cluster may run each progressive pass as its own task (see clscatter.cluster)
    SPLIT_PASSES = True
    # auto: the caustic pass alone (targeted), progressive under a time budget that the
    # scene's [render.lsg] can change (defaults), caustics only (required)
    AUTO = {"caustics": AutoRole(priority=10, params={"min_light_depth": 1},
                                 defaults={"time_budget": 10.0, "passes": 8})}

    @classmethod
    def estimate(cls, scene, params):
        """Working set: one chunk of lighting segments (bounded by ``max_bytes``; ~3
        segments per ray at BYTES_PER_SEGMENT each) plus 80 bytes per view segment; work:
        the segments traced over all passes (the gather's pair tests scale with them)."""
        from ...pipeline.budget import Estimate, camera_samples
        views = 2.0 * camera_samples(scene)
        rays = float(params["light_rays"])
        chunk = min(float(params["max_bytes"]), rays * 3 * BYTES_PER_SEGMENT)
        return [Estimate("lsg", "render.lsg.light_rays", chunk + views * 80,
                         rays * 3 * params["passes"] + views * 200,
                         "lighting segments (order of magnitude)")]

    #: optional ``f(passes_done, radius, mean values per view segment)`` called after every
    #: pass (tests and benchmarks: the error after each pass from one progressive run)
    pass_callback = None

    def targeted(self) -> bool:
        return bool(self.params["targeted"]) and self.params["min_light_depth"] >= 1

    def traced_rays(self, ps: PreparedScene) -> int:
        """Rays one pass traces: ``light_rays``, or targeted, the part of them that
        untargeted emission would have sent towards the mirrors and glass (the same flux
        per ray, hence the same caustic noise, for a fraction of the work)."""
        n = int(self.params["light_rays"])
        if self.targeted():
            n = max(1, math.ceil(n * targeted_fraction(ps)))
        return n

    def render(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
               show_progress: bool = True) -> np.ndarray:
        """Single-scattered radiance (H, W, 3) gathered from the lighting rays."""
        cam = ps.scene.camera
        views = paths.segments
        p = self.params
        stats.set(view_segments=int(len(views)), lsg_targeted=self.targeted())
        self._rays = self.traced_rays(ps)
        if len(views) == 0 or ps.num_lights == 0 or p["light_rays"] == 0:
            stats.set(pair_tests=0, pair_tests_bruteforce=0, valid_pairs=0, chunks=0,
                      lsg_radius=0.0, lsg_passes=0)
            return np.zeros((cam.height, cam.width, 3), np.float32)
        eng = ps.engine
        r_fixed = p["radius"] * ps.scene.scene_extent() / ps.frame.scale
        dev = paths.on_device(eng, cam.width, cam.height)     # the same segments, in order
        gat = Gatherer(eng, views, ps.medium, r_fixed or 1.0, p["min_sin"], p["leaf_size"],
                       p["segments_per_launch"], show_progress=False, views_buf=dev.buf)
        try:
            if r_fixed > 0:
                r1 = r_fixed
            else:
                with stats.stage("lsg_auto_radius"):
                    auto = self.auto_radius(ps, gat, views)
                r1 = auto.radius
                stats.set(lsg_auto_radius=auto.__dict__)
            totals, passes, pass_seconds = self._progressive(ps, gat, r1, stats, show_progress)
            with stats.stage("lsg_gather"):
                image = gat.image(dev, 1.0 / max(passes, 1))
        finally:
            gat.release()
        radii = ppb_radii(r1, p["alpha"], p["first_pass"] + passes)
        totals["pair_tests_bruteforce"] = totals.pop("light_x_view")
        bf = max(totals["pair_tests_bruteforce"], 1)
        spec, rays = totals.pop("specular_rays"), totals.pop("rays")
        kept_x_view = max(totals.pop("lsg_kept_x_view"), 1)
        stats.set(lsg_cull_fraction_paper=1.0 - totals["lsg_leaf_points_tested"] / kept_x_view,
                  lsg_valid_fraction_paper=totals["valid_pairs"] / max(totals["lsg_leaf_points_tested"], 1))
        stats.set(**totals, lsg_cull_fraction=1.0 - totals["pair_tests"] / bf,
                  lsg_valid_fraction=totals["valid_pairs"] / max(totals["pair_tests"], 1),
                  lsg_radius=float(r1), lsg_radius_last=float(radii[-1]), lsg_passes=passes,
                  lsg_radius_world=float(r1) * ps.frame.scale,
                  lsg_pass_seconds=pass_seconds, lsg_time_budget=p["time_budget"],
                  light_rays_specular_fraction=spec / max(rays, 1))
        return image

    # ---- automatic radius ----
    def auto_radius(self, ps: PreparedScene, gat: Gatherer, views: np.ndarray) -> AutoRadius:
        """The automatic radius (class docstring): a pilot gather at a trial radius."""
        n_rays = self._rays
        pilot = int(min(n_rays, max(2000, n_rays // 8)))
        cam = ps.camera
        mid = 0.5 * (views["a"][:, :3] + views["b"][:, :3]).astype(np.float64)
        dist = np.linalg.norm(mid - cam["origin"][:3].astype(np.float64), axis=1)
        pix = 2.0 * float(np.linalg.norm(cam["right"][:3])) / max(int(cam["width"]), 1)
        foot = dist * pix                       # pixel footprint at each view segment
        lp = trace_light_paths(ps, pilot, None, False, targeted=self.targeted(),
                               seed_offset=-1 - self.params["light_seed"])
        segs = self._select(lp.segments)
        r0 = 0.25 * float(np.median(foot)) if len(foot) else 1e-3
        lit = np.zeros(0, np.int64)
        for _ in range(12):
            gat.reset()
            gat.radius = r0
            gat.add(segs)
            lit = np.flatnonzero(gat.valid_per_view > 0)
            if len(lit) >= min(64, max(1, len(views) // 4)) or len(segs) == 0:
                break
            r0 *= 2.0
        count = float(np.median(gat.valid_per_view[lit])) * n_rays / pilot if len(lit) else 0.0
        gat.reset()
        if len(lit) == 0:                       # no light reaches any view segment
            return AutoRadius(r0, r0, pilot, 0.0, float(np.median(foot)), 0)
        f = float(np.median(foot[lit]))
        r = max(r0 * self.params["auto_count"] / count, f / 16)
        return AutoRadius(float(r), float(r0), pilot, count, f, int(len(lit)))

    # ---- passes ----
    def _select(self, segs: np.ndarray) -> np.ndarray:
        if self.params["min_light_depth"] > 0:
            return segs[segs["depth"] >= self.params["min_light_depth"]]
        return segs

    def _progressive(self, ps: PreparedScene, gat: Gatherer, r1: float, stats: Stats,
                     show_progress: bool) -> tuple[dict, int, list]:
        """Run the passes into ``gat``'s accumulator; (totals, passes run, seconds each)."""
        p = self.params
        budget = float(p["time_budget"])
        most = int(p["passes"]) if budget <= 0 or p["passes"] > 1 else 1 << 30
        first = int(p["first_pass"])
        tot: dict = {}
        seconds: list[float] = []
        r = float(ppb_radii(r1, p["alpha"], first + 1)[-1])    # pass `first`'s radius
        with progress(most if most < 1 << 30 else 0, "lsg passes", show_progress) as bar:
            for i in range(first, first + most):
                done = i - first
                if budget > 0 and done > 0 and sum(seconds) * (1 + 1 / done) > budget:
                    break
                with Timer() as t:
                    gat.radius = r
                    res = self._gather_chunks(ps, gat, stats, show_progress and most == 1,
                                              seed_offset=i + (self.params["light_seed"] << 16))
                seconds.append(t.seconds)
                if self.pass_callback is not None:
                    self.pass_callback(done + 1, r, gat.values() / (done + 1))
                for key, v in res.items():
                    tot[key] = max(tot.get(key, 0), v) if key.endswith("_max") else tot.get(key, 0) + v
                bar.update(1)
                r *= (i + 1 + p["alpha"]) / (i + 2)
        return tot, len(seconds), seconds

    def _gather_chunks(self, ps: PreparedScene, gat: Gatherer, stats: Stats,
                       show_progress: bool, seed_offset: int = 0) -> dict:
        """Trace and gather one pass of lighting rays chunk by chunk within max_bytes."""
        eng = ps.engine
        targeted = self.targeted()
        n_rays = self._rays
        counts = ray_counts(ps, n_rays, targeted)
        budget = self.params["max_bytes"]
        seg_per_ray = 1.0          # lower bound until a chunk has been traced
        n0 = max(1, math.ceil(n_rays * seg_per_ray * BYTES_PER_SEGMENT / budget))
        queue = deque((k, n0) for k in range(n0))
        tot = dict(pair_tests=0, valid_pairs=0, light_x_view=0, chunks=0, lsg_light_segments_kept=0,
                   tree_build_seconds=0.0, gather_seconds=0.0, lsg_chunk_bytes_max=0,
                   lsg_chunks_retraced=0, specular_rays=0, rays=0, lsg_leaf_points_tested=0,
                   lsg_kept_x_view=0)
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
                lp = trace_light_paths(ps, n_rays, None, show_progress,
                                       chunk=(k, n), targeted=targeted, seed_offset=seed_offset)
            segs = self._select(lp.segments)
            seg_per_ray = max(seg_per_ray, len(segs) / rays)
            need = len(segs) * BYTES_PER_SEGMENT
            if need > budget and rays > 1:   # re-trace this chunk in smaller parts
                split = math.ceil(need / budget)
                queue.extendleft((k * split + j, n * split) for j in reversed(range(split)))
                tot["lsg_chunks_retraced"] += 1
                continue
            stats.add("light_rays", rays)
            stats.add("light_segments", int(len(segs)))
            tot["specular_rays"] += int(lp.specular_rays.sum())
            tot["rays"] += rays
            res = gat.add(segs)
            tot["pair_tests"] += res.pair_tests
            tot["valid_pairs"] += res.valid_pairs
            tot["light_x_view"] += len(segs) * gat.n
            tot["chunks"] += 1
            tot["lsg_light_segments_kept"] += res.kept
            tot["lsg_leaf_points_tested"] += res.leaf_points
            tot["lsg_kept_x_view"] += res.kept * gat.n
            tot["tree_build_seconds"] += res.tree_seconds
            tot["gather_seconds"] += res.gather_seconds
            tot["lsg_chunk_bytes_max"] = max(tot["lsg_chunk_bytes_max"], res.nbytes)
            eng.note_host(res.nbytes)
        stats.stages["lsg_tree"] = stats.stages.get("lsg_tree", 0.0) + tot["tree_build_seconds"]
        stats.stages["lsg_gather"] = stats.stages.get("lsg_gather", 0.0) + tot["gather_seconds"]
        return tot
