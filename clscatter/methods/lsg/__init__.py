"""Line space gathering (Sun et al. 2010): single scattering gathered from lighting rays."""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ...device import structs
from ...estimators.line_gather import (
    BYTES_PER_SEGMENT,
    BYTES_PER_VIEW,
    LEAF_SIZE,
    QUERIES,
    SPATIAL_SPLIT,
    Gatherer,
    RegionGatherer,
    group_samples,
    region_media,
    sample_groups,
)
from ...estimators.screen_cells import BYTES_PER_SCREEN_VIEW
from ...io.stats import Stats, progress
from ...transport.context import PassContext
from ...transport.emission import targeted_fraction
from ...transport.light_paths import chunk_rays, ray_counts, trace_light_paths
from ...transport.prepared import PreparedScene
from ...transport.view_paths import DeviceSegments, trace_interior_segments
from .. import register
from ..base import AutoRole, Estimate, Method, Param, PassResult, camera_samples

#: pair tests one lighting segment costs the gather, as an order of magnitude (the plane
#: queries of a few hundred to a few thousand view segments): the work estimate's unit
PAIRS_PER_SEGMENT = 1000
#: most rays the automatic radius's pilot traces (in one piece: its segments stay in memory;
#: no more than a chunk of max_bytes holds, at least PILOT_MIN)
PILOT_MAX = 1 << 18
PILOT_MIN = 2000
#: lighting segments a ray in the memory estimate (an upper bound: glass splits rays)
SEGMENTS_PER_RAY = 3
#: least max_bytes that fitting a pass into a memory budget sets: a chunk of the pilot's
#: least rays
MIN_CHUNK_BYTES = 4 << 20
#: view segments the pilot gathers at most (every k-th: it needs medians, not an image)
PILOT_VIEWS = 16384
#: ... and under a time budget (the pilot also measures the cost that sizes passes)
PILOT_BUDGETED = 2048
#: fewest rays a pass under a time budget traces (fewer only if light_rays is smaller)
MIN_PASS_RAYS = 1000
#: a pass's gather visits about rays^(-1/6) of the lighting segments' tree per view segment
#: (a 5-D hyperplane through 6-D Plücker points), so its cost grows like rays^(5/6)
GATHER_EXPONENT = 5.0 / 6.0
#: most a pass's size changes from the pass that sized it (from the pilot: its trial
#: radius differs from the pass's, a looser guide)
RESIZE_MAX = 4.0
PILOT_RESIZE_MAX = 32.0
#: most passes under an error target (the target or a deadline should end them first; a
#: target the estimate cannot reach ends here, with a note)
MAX_PASSES = 1024
#: camera samples take turns pass by pass unless passes over every sample would have an
#: automatic radius below this many pixel footprints: a pixel's jittered samples lie about
#: half a footprint apart, so with a smaller radius they gather mostly different lighting
#: segments, and gathering one of them a pass would cost as much error as it saves gather
#: time (under a time budget passes of one sample trace more rays, so their radius is
#: smaller: it is the radius of passes over every sample that tells whether the samples
#: share their lighting segments)
SAMPLES_SHARE_RADIUS = 0.5

#: the automatic radius is at least the median pixel footprint of the lit view segments
#: over this: no blur is smaller than a sixteenth of a pixel
RADIUS_FLOOR = 16


def _chunk_bytes(params: dict) -> float:
    """The estimated working set of one chunk of a pass's lighting rays: all of them, or
    ``max_bytes`` where that is less."""
    return min(float(params["max_bytes"]),
               float(params["light_rays"]) * SEGMENTS_PER_RAY * BYTES_PER_SEGMENT)


def _group_weights(gathered, groups: int, spp: int) -> dict[int, float]:
    """Weight in the image of each camera-sample group in ``gathered``: its share of their
    samples (each group's image already stands for the whole pixel: its samples'
    estimates times spp over their number)."""
    share = {g: group_samples(g, groups, spp) for g in gathered}
    total = sum(share.values())
    return {g: n / total for g, n in share.items()}


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
    # the radius sits at its floor, footprint / RADIUS_FLOOR: a typical lit view segment
    # then gathers about count_median * radius / trial_radius lighting segments (gathered),
    # more than auto_count (fewer light_rays would cost less for the noise it asks)
    floored: bool = False
    gathered: float = 0.0


@register
class LineSpaceGathering(Method):
    """``lsg``: line space gathering (Sun, Zhou, Lin, Guo 2010) for single scattering along
    specular light paths: volumetric caustics, light glows, volumetric shadows.

    Lighting rays leave the lights (stratified; flux = power / rays) and are traced through
    mirrors and glass (Fresnel split, TIR, interior absorption, ``render.max_depth``); every
    straight piece inside the medium is kept with the flux at its start. Each *lighting
    segment* becomes a 6-D Plücker point in a perfect 8-ary tree; every view segment is a
    6-D hyperplane whose plane query finds the lighting lines within ``radius``, and each
    pair closer than ``radius`` adds the cylinder-kernel estimate

        sigma_s p(cos) Phi / (pi r^2) * int_chord exp(-kappa (s + t(s))) ds

    (derived in ``cl_kernels/estimators/lsg.h``; the gathering itself is the shared
    :mod:`clscatter.estimators.line_gather`). The image has bias from ``radius`` (a blur of
    caustics, glows and shadow edges) and noise from ``light_rays`` (per view segment, about
    1 / sqrt of the lighting segments its cylinder catches).

    *Targeted emission.* With ``min_light_depth >= 1`` (a caustic pass, as ``auto`` runs
    it) and ``targeted``, lights emit only towards the bounding spheres of the mirrors and
    glass, each ray weighted by its exact pdf (:mod:`clscatter.transport.emission`): the same
    expected image, the noise of ``light_rays`` untargeted rays, the cost of the part of
    them that reaches the mirrors and glass.

    *Automatic radius* (``radius = 0``). A pilot of ``light_rays / 8`` rays (at least 2000,
    at most :data:`PILOT_MAX` and what a chunk of ``max_bytes`` holds) is gathered at a
    trial radius r0; the median number c of
    pairs per lit view segment,
    scaled to ``light_rays``, gives ``r = max(r0 * auto_count / c, f / 16)`` with f the
    median pixel footprint there: a typical lit view segment gathers ``auto_count``
    lighting segments, and no blur is smaller than a sixteenth of a pixel. Both terms are
    measured in the normalised frame, so the radius does not depend on the scene's scale
    or on objects far away. The pilot's rays are not part of the image. ``--stats`` gives
    what the radius was chosen from (``lsg_auto_radius``), with ``floored`` where the
    sixteenth of a pixel decided it and ``gathered``, about how many lighting segments a
    typical lit view segment then gathers (more than ``auto_count`` where floored: fewer
    ``light_rays`` would reach ``auto_count`` sooner).

    *Progressive passes* (``passes`` > 1, or a time budget or error target): pass i traces
    fresh rays and gathers them with ``r_{i+1} = r_i (i + alpha) / (i + 1)``
    (:func:`ppb_radii`); the image is the mean of the passes and converges without a
    radius bias floor. Under a deadline (this pass's share of ``render.time_budget``, or
    ``time_budget``) passes are sized from measured throughput: the automatic radius's
    pilot (at most :data:`PILOT_BUDGETED` rays) times its tracing and gathering, the first
    pass traces what fits in the budget's share of one of ``passes`` planned passes (at
    most ``light_rays``), each later pass is sized from the previous one, and passes run
    while the next one is predicted to end in time, at most ``passes`` (a budget that
    ``passes`` passes of ``light_rays`` fit in changes nothing). The passes' own images give
    the render's noise estimate (:mod:`clscatter.transport.progressive`); with
    ``render.target_error`` passes go on past ``passes`` until the estimate meets it.

    *Camera samples in turn* (``view_samples``, default 1). A pixel's camera samples see
    nearly the same lines through the medium and share every lighting segment, so gathering
    all of them in one pass buys little: the noise is the lighting rays'. Pass i gathers
    only the view segments of samples ``k`` with ``k % G == i % G`` (``G = ceil(spp /
    view_samples)``), weighted to stand for the whole pixel; the passes take turns, so every
    sample is gathered once every G passes. The image is each group's mean over its passes,
    weighted by the group's share of the samples, so every sample weighs the same whatever
    the number of passes. A pass then costs about 1/G of the gather, and a time budget buys
    G times the lighting rays. G is at most the passes the render may run (``passes``, or
    more under an error target): a single pass gathers every sample, as before. Until G
    passes have run, the medium term of a pixel comes from the samples gathered so far
    (edges of objects are antialiased as the passes go on); ``view_samples = 0`` gathers
    every sample in every pass. The error estimate compares whole rounds of G passes (two
    groups differ by their samples as well as by their rays). The samples share their
    lighting segments only where the radius spans them: when passes over every sample
    would have an automatic radius below half the median pixel footprint of the lit view
    segments (:data:`SAMPLES_SHARE_RADIUS`; many rays, fine pixels), each sample gathers
    lighting segments of its own, a pass of one group would lose as much in noise as it
    saves in gather time, and every pass gathers every sample (G = 1).

    *Inside glass* (a dielectric's ``interior_sigma_s``, ``interior_sigma_a``,
    ``interior_g``: a homogeneous medium inside the closed object). Every straight piece of
    a lighting ray inside such an object is kept too, with the flux at its start: the
    light that reached it, refracted through the surface with Fresnel's weight and
    attenuated by the interior extinction (absorption plus scattering) on the way. The
    pass traces the camera paths again for the view segments inside
    (:func:`~clscatter.transport.view_paths.trace_interior_segments`) and gathers each
    object's lighting segments against its own view segments only, with its interior
    sigma_s, extinction and phase (``interior_g``, or the scene medium's g): the same
    estimate as in the medium, region by region (:class:`~clscatter.estimators.line_gather.RegionGatherer`);
    no pair joins light inside the glass to a view segment outside, or the reverse. This
    needs no scene medium. Light inside is always refracted light (at least one specular
    bounce), so the caustic pass ``auto`` runs (``min_light_depth = 1``) includes it.
    Within ``radius`` of the glass surface the gather's disc reaches outside the object,
    where no lighting segment of the region lies: a thin darker rim, as large as the blur
    (the medium's box faces continue their lighting segments beyond the face; glass
    surfaces do not). ``interior = false`` leaves this light out, with a note.

    Rays are processed in chunks whose working set stays within ``max_bytes``; a chunk that
    turns out larger is traced again in smaller parts. Where the render's memory budget
    (``--max-memory``, or the device's) cannot hold a pass as set, ``max_bytes`` is lowered
    to fit it (:meth:`fit_memory`, with a note) rather than the render refused.

    Statistics: ``light_segments``, ``lsg_light_segments_kept``, ``view_segments``,
    ``pair_tests``, ``pair_tests_bruteforce``, ``valid_pairs``, ``lsg_cull_fraction``,
    ``lsg_valid_fraction`` (and the paper's way of counting them, sec. 4.3:
    ``lsg_leaf_points_tested``, ``lsg_cull_fraction_paper``, ``lsg_valid_fraction_paper``;
    with ``queries = "screen"`` the leaf points include the view segments of the screen
    cells visited),
    ``tree_build_seconds``, ``gather_seconds``, ``chunks``, ``lsg_chunks_retraced``,
    ``lsg_chunk_bytes_max``, ``lsg_radius`` (normalised; ``lsg_radius_world`` in scene
    units), ``lsg_radius_last``, ``lsg_passes``, ``lsg_pass_seconds``, ``lsg_time_budget``,
    ``lsg_screen_segments`` (view segments gathered from screen cells, ``queries =
    "screen"``: those on camera rays, over the sample groups gathered),
    ``lsg_auto_radius``, ``lsg_targeted``, ``light_rays_specular_fraction``, ``lsg_pass_rays``,
    ``lsg_stopped_by`` (passes, time_budget or target_error), ``lsg_sample_groups`` (G),
    ``lsg_error_estimate``,
    ``lsg_interior_view_segments``.

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
        Param("passes", 1, "progressive passes of fresh rays (under a time budget: sized to "
              "fit it, fewer if even small ones do not; with an error target: more until it is met)",
              lo=1),
        Param("time_budget", 0.0, "seconds for this pass, pilot included (0: none; "
              "render.time_budget also limits it)", lo=0),
        Param("first_pass", 0, "index of the first progressive pass to run (pass k uses its "
              "own rays and radius, so passes can run apart and be averaged: a cluster runs "
              "each pass as a task)", lo=0),
        Param("alpha", 0.7, "progressive radius reduction r_(i+1) = r_i (i + alpha) / (i + 1)",
              lo=0, hi=1, lo_open=True, hi_open=True),
        Param("targeted", True, "with min_light_depth >= 1, emit only towards mirrors and glass"),
        Param("light_seed", 0, "selects an independent set of lighting rays (view paths unchanged)",
              lo=0),
        Param("max_bytes", 1 << 30, "working-set bound for one chunk of rays", lo=1),
        Param("leaf_size", LEAF_SIZE, "least points per tree leaf (at most 8x)", lo=1),
        Param("spatial_split", SPATIAL_SPLIT, "weight of where lighting segments start against "
              "their Plücker coordinates when the tree splits (0: Plücker coordinates only)", lo=0),
        Param("queries", "screen", "which side walks the line tree: 'views' (a tree over each "
              "chunk's lighting segments, a query per view segment, as in the paper), "
              "'lights' (a tree over the view segments, built once and kept while the view "
              "paths are, a query per lighting segment) or 'screen' (the view segments on "
              "camera rays in screen cells that each lighting segment crosses, kept like "
              "'lights'; the others from the side with fewer segments); the same pairs "
              "every way", choices=QUERIES),
        Param("min_sin", 1e-6, "sin(theta) below this counts as parallel", lo=0, hi=1, hi_open=True),
        Param("segments_per_launch", 65536, "most segments (view or lighting) per kernel "
              "launch; launches are timed to about 0.25 s", lo=1),
        Param("view_samples", 1, "camera samples of each pixel a pass gathers, the pixel's samples "
              "taking turns pass by pass while the automatic radius spans half a pixel "
              "(0: all of them in every pass)", lo=0),
        Param("min_light_depth", 0, "gather only lighting segments with at least this many "
              "specular bounces (1: caustics only, as auto uses it beside a direct method)", lo=0),
        Param("interior", True, "also gather inside glass that scatters (a dielectric's "
              "interior_sigma_s), with its interior coefficients"),
    )
    TERMS = frozenset({"direct", "caustics"})
    # the lighting segments inside glass carry the refracted light: lsg gathers them
    # against the view segments inside, with the material's interior_sigma_s and interior_g
    INTERIOR_SCATTERING = True
    INTERIOR_PHASE = True
    PREVIEW_SCALE = {"light_rays": 0.125, "passes": 0.0, "time_budget": 0.0}
    # a cluster may run each progressive pass as its own task (see clscatter.cluster)
    SPLIT_PASSES = True
    PROGRESSIVE = True
    SIZES_PASSES = True
    # auto: the caustic pass alone (targeted), caustics only (required), progressive under
    # auto's whole-render time budget, planned for 8 passes (a default [render.lsg] can change)
    AUTO = {"caustics": AutoRole(priority=10, params={"min_light_depth": 1},
                                 defaults={"passes": 8})}

    @classmethod
    def estimate(cls, scene, params):
        """Working set: one chunk of lighting segments (bounded by ``max_bytes``;
        :data:`SEGMENTS_PER_RAY` a ray at BYTES_PER_SEGMENT each) plus 80 bytes per view segment, and
        BYTES_PER_VIEW more for the tree over them with ``queries = "lights"``
        (BYTES_PER_SCREEN_VIEW for the screen cells with ``"screen"``); work: the segments
        traced over all passes times :data:`PAIRS_PER_SEGMENT`."""
        views = 2.0 * camera_samples(scene)
        rays = float(params["light_rays"])
        chunk = _chunk_bytes(params)
        per_view = 80 + {"lights": BYTES_PER_VIEW,
                         "screen": BYTES_PER_SCREEN_VIEW}.get(params["queries"], 0)
        # the memory's key: the rays' chunk, or the view segments where they weigh more
        key = "render.lsg.light_rays" if chunk >= views * per_view else "camera.resolution"
        return [Estimate("lsg", key, chunk + views * per_view,
                         rays * 3 * params["passes"] * PAIRS_PER_SEGMENT + views * 200,
                         "pair tests (order of magnitude)", work_key="render.lsg.light_rays")]

    @classmethod
    def fit_memory(cls, scene, params, room):
        """A smaller ``max_bytes``: the lighting rays of a pass are gathered in more chunks
        (the same rays and radius: the same image up to the order of its sums), down to
        :data:`MIN_CHUNK_BYTES` (where even that does not fit, the view segments are what
        is left: the estimate's key then says so)."""
        (est,) = cls.estimate(scene, params)
        chunk = _chunk_bytes(params)
        if chunk <= MIN_CHUNK_BYTES:
            return {}
        return {"max_bytes": max(int(room - (est.bytes - chunk)), MIN_CHUNK_BYTES)}

    #: optional ``f(passes_done, radius, mean values per view segment)`` called after every
    #: pass (:meth:`_mean_values`; tests and benchmarks: the error after each pass from one
    #: progressive run)
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

    def render(self, ctx: PassContext) -> PassResult:
        """Single-scattered radiance gathered from the lighting rays, in the medium term."""
        ps, paths, stats, show_progress = ctx.ps, ctx.paths, ctx.stats, ctx.show_progress
        views = paths.segments
        p = self.params
        stats.set(view_segments=int(len(views)), lsg_targeted=self.targeted())
        self._rays = self._rays_cap = self.traced_rays(ps)
        self._groups_cap = MAX_PASSES            # lowered by the automatic radius's pilot
        self._pass_rays: list[int] = []
        inside = self._interior_views(ctx)
        self._interior = inside is not None
        n_inside = inside.count if inside is not None else 0
        stats.set(lsg_interior_view_segments=int(n_inside))
        if len(views) + n_inside == 0 or ps.num_lights == 0 or p["light_rays"] == 0:
            if inside is not None:
                inside.release()
            stats.set(pair_tests=0, pair_tests_bruteforce=0, valid_pairs=0, chunks=0,
                      lsg_radius=0.0, lsg_passes=0)
            return PassResult(medium=ctx.zeros())
        prog = self._progression(ctx)
        r_fixed = p["radius"] * ps.scene.scene_extent() / ps.frame.scale
        dev = ctx.segments() if len(views) else None          # the same segments, in order
        try:
            gat = self._gatherer(ps, views, dev, inside, r_fixed or 1.0, show_progress)
        except BaseException:
            if inside is not None:
                inside.release()
            raise
        views = gat.views
        try:
            measured = None                      # (rays, seconds) of the pilot (sizes passes)
            if r_fixed > 0:
                r1 = r_fixed
            else:
                with stats.stage("lsg_auto_radius"):
                    auto, measured = self.auto_radius(ps, gat, views, prog)
                r1 = auto.radius
                stats.set(lsg_auto_radius=auto.__dict__)
            image, totals, pass_seconds = self._progressive(ps, gat, dev, r1, measured, prog,
                                                            stats, show_progress)
            self._budget_note(ctx, prog, pass_seconds)
            stats.set(lsg_screen_segments=gat.screen_segments)
        finally:
            gat.release()
            if inside is not None:
                inside.release()
        passes = len(pass_seconds)
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
                  lsg_pass_seconds=pass_seconds, lsg_pass_rays=self._pass_rays,
                  lsg_time_budget=p["time_budget"], lsg_stopped_by=prog.stopped_by or "passes",
                  lsg_sample_groups=self._sample_groups(ps, prog)[0],
                  lsg_error_estimate=prog.error,
                  light_rays_specular_fraction=spec / max(rays, 1))
        return PassResult(medium=image)

    # ---- regions: the scene medium, and the inside of glass that scatters ----
    def _interior_views(self, ctx: PassContext) -> DeviceSegments | None:
        """The view segments inside dielectrics whose interior scatters (traced for this
        pass: :func:`~clscatter.transport.view_paths.trace_interior_segments`), or None when
        the scene has none or ``interior`` is off (noted: that light is then left out)."""
        ps = ctx.ps
        if not region_media(ps):
            return None
        if not self.params["interior"]:
            ctx.note("lsg: render.lsg.interior = false: light scattered inside glass "
                     "(interior_sigma_s) is not in this image")
            return None
        with ctx.stats.stage("view_paths_interior"):
            return trace_interior_segments(ps, ctx.paths.sample_range)

    def _gatherer(self, ps: PreparedScene, views: np.ndarray, dev: DeviceSegments | None,
                  inside: DeviceSegments | None, radius: float, show_progress: bool):
        """The gatherer of this pass: a :class:`Gatherer` over the medium's view segments
        when nothing scatters inside glass (as it always was), else a
        :class:`RegionGatherer` with one part per region that has view segments: the scene
        medium's (``dev``), and one per scattering dielectric over ``inside``, each with
        that region's coefficients."""
        p = self.params
        def make(v, medium, segs, region):
            return Gatherer(ps.engine, v, medium, radius, p["min_sin"], p["leaf_size"],
                            p["segments_per_launch"], show_progress=show_progress,
                            views_buf=segs.buf, region=region, spatial_split=p["spatial_split"],
                            queries=p["queries"], derived=segs.derived, camera=ps.camera)
        if inside is None:
            return make(views, ps.medium, dev, 0)
        parts = []
        try:
            if dev is not None and len(views):
                parts.append((make(views, ps.medium, dev, 0), dev))
            if inside.count:
                host = ps.engine.read(inside.buf, inside.count, structs.VIEW_SEGMENT)
                for region, medium in region_media(ps):
                    if np.any(structs.segment_regions(host) == region):
                        parts.append((make(host, medium, inside, region), inside))
        except BaseException:
            for g, _ in parts:
                g.release()
            raise
        return RegionGatherer(parts)

    def _progression(self, ctx: PassContext):
        """The pass's :class:`~clscatter.transport.progressive.Progression`: ``passes``
        passes (fewer if a deadline, the render's share or ``time_budget``, comes first;
        more, until the render's error target is met, if it is set)."""
        p = self.params
        planned = int(p["passes"])
        prog = ctx.progression(planned, planned, float(p["time_budget"]))
        if prog.target_error > 0:
            prog.max_passes = MAX_PASSES
        return prog

    def _budget_note(self, ctx: PassContext, prog, seconds: list) -> None:
        """Say why the time budget could not be kept, when the first pass alone broke it."""
        if seconds:
            ctx.overrun(prog, prog.overrun_note("lsg", f"a pass of {self._pass_rays[0]} "
                                                "lighting rays", "camera.resolution or camera.spp"))

    # ---- automatic radius ----
    def auto_radius(self, ps: PreparedScene, gat: Gatherer, views: np.ndarray,
                    prog=None) -> tuple[AutoRadius, tuple[int, float]]:
        """The automatic radius (class docstring): a pilot gather at a trial radius, for the
        rays the first pass will trace (under a deadline: as many as fit, by the pilot's
        cost); and (pilot rays, seconds of their tracing and last gather). The pilot needs
        medians only, so it gathers at most about :data:`PILOT_VIEWS` view segments (every
        k-th of them)."""
        n_rays = self._rays
        fits = int(self.params["max_bytes"] // (SEGMENTS_PER_RAY * BYTES_PER_SEGMENT))
        pilot = int(min(n_rays, max(PILOT_MIN, min(n_rays // 8, fits)), PILOT_MAX))
        if prog is not None and prog.budgeted:
            pilot = min(pilot, PILOT_BUDGETED)
        stride = max(1, len(views) // PILOT_VIEWS) if isinstance(gat, Gatherer) else 1
        if stride > 1:                          # statistics: a subset of the view segments
            views = views[::stride]
            p = self.params
            gat = Gatherer(ps.engine, views, ps.medium, gat.radius, p["min_sin"],
                           p["leaf_size"], p["segments_per_launch"],
                           show_progress=gat.show_progress, spatial_split=p["spatial_split"],
                           queries=p["queries"], camera=ps.camera)
        try:
            return self._pilot(ps, gat, views, prog, pilot, stride)
        finally:
            if stride > 1:
                gat.release()

    def _pilot(self, ps: PreparedScene, gat: Gatherer, views: np.ndarray, prog, pilot: int,
               stride: int) -> tuple[AutoRadius, tuple[int, float]]:
        """:meth:`auto_radius` on ``views`` (every ``stride``-th view segment: the pilot's
        gather time is scaled by ``stride`` to stand for all of them)."""
        n_rays = self._rays
        cam = ps.camera
        mid = 0.5 * (views["a"][:, :3] + views["b"][:, :3]).astype(np.float64)
        dist = np.linalg.norm(mid - cam["origin"][:3].astype(np.float64), axis=1)
        pix = 2.0 * float(np.linalg.norm(cam["right"][:3])) / max(int(cam["width"]), 1)
        foot = dist * pix                       # pixel footprint at each view segment
        clock = prog.clock if prog is not None else time.perf_counter
        t0 = clock()
        lp = trace_light_paths(ps, pilot, None, gat.show_progress, targeted=self.targeted(),
                               seed_offset=-1 - self.params["light_seed"],
                               interior=getattr(self, "_interior", False))
        traced = clock() - t0
        segs = self._select(lp.segments)
        r0 = 0.25 * float(np.median(foot)) if len(foot) else 1e-3
        lit = np.zeros(0, np.int64)
        gat.prepare()               # what it keeps is built once, not part of a pass's cost
        for _ in range(12):
            gat.reset()
            gat.radius = r0
            t0 = clock()
            gat.add(segs)
            gathered = clock() - t0
            lit = np.flatnonzero(gat.valid_per_view > 0)
            if len(lit) >= min(64, max(1, len(views) // 4)) or len(segs) == 0:
                break
            r0 *= 2.0
        def sized(groups: int) -> tuple[tuple[int, float], int]:
            """(what the pilot measured for a pass over 1 / groups of the samples, the rays
            such a pass traces: under a deadline, as many as fit)"""
            measured = (pilot, traced + gathered * stride / groups)
            if prog is not None and prog.budgeted:
                return measured, self._sized_rays(pilot, measured[1], prog, limit=PILOT_RESIZE_MAX)
            return measured, n_rays

        groups = self._sample_groups(ps, prog)[0]
        if len(lit) == 0:                       # no light reaches any view segment
            gat.reset()
            measured, self._rays = sized(groups)
            return AutoRadius(r0, r0, pilot, 0.0, float(np.median(foot)), 0), measured
        median = float(np.median(gat.valid_per_view[lit]))
        gat.reset()
        f = float(np.median(foot[lit]))

        def radius(n: int) -> tuple[float, float]:
            """(pairs a lit view segment gathers at r0 with n rays, the radius for n rays)"""
            count = median * n / pilot
            return count, max(r0 * self.params["auto_count"] / count, f / RADIUS_FLOOR)

        # a pass gathers one group of each pixel's camera samples (_sample_groups) unless a
        # pass over every sample would have a radius below half a pixel's footprint: then
        # the samples gather lighting segments of their own and G = 1
        measured, n_rays = sized(1)
        count, r = radius(n_rays)
        if groups > 1 and r >= SAMPLES_SHARE_RADIUS * f:
            measured, n_rays = sized(groups)
            count, r = radius(n_rays)
        else:
            groups = 1
        self._rays = n_rays
        self._groups_cap = groups
        return AutoRadius(float(r), float(r0), pilot, count, f, int(len(lit)),
                          bool(r == f / RADIUS_FLOOR), float(count * r / r0)), measured

    def _sized_rays(self, rays: int, seconds: float, prog, limit: float = 0.0) -> int:
        """Rays for a pass that should take ``prog.pass_seconds()``, given that ``rays``
        rays took ``seconds`` (a pilot or the previous pass): the gather's cost grows like
        rays^:data:`GATHER_EXPONENT`, so ``rays * (wanted / seconds)^(1 / exponent)``,
        within a factor ``limit`` (default :data:`RESIZE_MAX`) of ``rays`` and within
        [MIN_PASS_RAYS, the pass's ray count]."""
        most, limit = self._rays_cap, limit or RESIZE_MAX
        ratio = prog.pass_seconds() / max(seconds, 1e-6)
        want = rays * min(max(ratio, 1e-12) ** (1.0 / GATHER_EXPONENT), limit)
        want = max(want, rays / limit)
        return int(min(most, max(min(MIN_PASS_RAYS, most), want)))

    # ---- passes ----
    def _sample_groups(self, ps: PreparedScene, prog) -> tuple[int, int]:
        """(groups G, spp): pass i gathers the camera samples k of each pixel with
        ``k % G == i % G``: at most ``view_samples`` of them, and G no more than the passes
        the render may run (one pass gathers every sample)."""
        spp = int(ps.scene.camera.spp)
        vs = int(self.params["view_samples"])
        groups = 1 if vs <= 0 else -(-spp // vs)
        groups = min(groups, self._groups_cap)
        return max(1, min(groups, prog.max_passes if prog is not None else 1)), spp

    def _select(self, segs: np.ndarray) -> np.ndarray:
        if self.params["min_light_depth"] > 0:
            return segs[segs["depth"] >= self.params["min_light_depth"]]
        return segs

    def _progressive(self, ps: PreparedScene, gat: Gatherer, dev, r1: float,
                     measured: tuple[int, float] | None, prog, stats: Stats,
                     show_progress: bool) -> tuple[np.ndarray, dict, list]:
        """Run the passes into ``gat``'s accumulator while ``prog`` says so; (the image,
        the mean of the passes; totals; seconds of each pass). Each pass's own image goes
        to ``prog`` (its error estimate); under a deadline each pass after the first is
        sized from the previous one's measured rays per second."""
        p = self.params
        first = int(p["first_pass"])
        tot: dict = {}
        seconds: list[float] = []
        self._pass_rays = []
        r = float(ppb_radii(r1, p["alpha"], first + 1)[-1])    # pass `first`'s radius
        keep_images = prog.max_passes > 1
        previous = None
        groups, spp = self._sample_groups(ps, prog)
        by_group: dict[int, list] = {}          # group -> [sum of its passes' images, passes]
        round_: list = []                       # (group, image, radius) of this round's passes
        total = prog.planned if prog.max_passes > prog.planned else prog.max_passes
        with progress(total, "lsg passes", show_progress) as bar:
            i = first
            while prog.more():
                done = i - first
                if done > 0 and prog.budgeted:   # size from the previous pass's cost
                    self._rays = self._sized_rays(self._pass_rays[-1], seconds[-1], prog)
                elif done == 0 and prog.budgeted and measured is None:
                    self._rays = min(self._rays, PILOT_BUDGETED)
                t0 = prog.clock()
                gat.radius = r
                gat.select(i % groups, groups, spp)
                res = self._gather_chunks(ps, gat, stats, show_progress,
                                          seed_offset=i + (self.params["light_seed"] << 16))
                seconds.append(prog.clock() - t0)
                self._pass_rays.append(int(self._rays))
                with stats.stage("lsg_gather"):     # the pass's image and error estimate
                    cumulative = gat.image(dev) if keep_images else None
                    own = (cumulative if previous is None or cumulative is None
                           else cumulative - previous)
                    previous = cumulative
                    tracked, r_tracked = own, r
                    if groups > 1:
                        acc = by_group.setdefault(i % groups, [0.0, 0])
                        acc[0] = acc[0] + own
                        acc[1] += 1
                        # the error estimate compares whole rounds (one pass of every group):
                        # two passes of different groups differ by their samples, not only noise
                        round_.append((i % groups, own, r))
                        tracked = None
                        if len(round_) == groups:
                            w = _group_weights([g for g, _, _ in round_], groups, spp)
                            tracked = sum(np.float32(w[g]) * img for g, img, _ in round_)
                            r_tracked = float(np.mean([x for _, _, x in round_]))
                            round_.clear()
                    prog.add(tracked, seconds[-1], radius=r_tracked)
                    if self.pass_callback is not None:
                        values = self._mean_values(gat, by_group, groups, spp, done + 1)
                        self.pass_callback(done + 1, r, values)
                for key, v in res.items():
                    tot[key] = max(tot.get(key, 0), v) if key.endswith("_max") else tot.get(key, 0) + v
                if done + 1 > bar.total:
                    bar.total = done + 1
                bar.set_postfix_str("" if prog.error is None else f"relMSE~{prog.error:.2g}")
                bar.update(1)
                r *= (i + 1 + p["alpha"]) / (i + 2)
                i += 1
        with stats.stage("lsg_gather"):
            n = max(len(seconds), 1)
            if by_group:   # each group weighs its samples, however many passes it had
                w = _group_weights(by_group, groups, spp)
                image = sum(np.float32(w[g]) * a / np.float32(k) for g, (a, k) in by_group.items())
            elif previous is not None:
                image = previous * np.float32(1.0 / n)
            else:
                image = gat.image(dev, 1.0 / n)
        return image, tot, seconds

    @staticmethod
    def _mean_values(gat, by_group: dict, groups: int, spp: int, passes: int) -> np.ndarray:
        """The running estimate per view segment, (n_views, 4): what sums into the pixels of
        the image so far (with sample groups, a segment's sum over its group's passes over
        their number, times its group's weight)."""
        values = gat.values()
        if groups <= 1:
            return values / passes
        group = sample_groups(gat.views, groups, spp)
        w = _group_weights(by_group, groups, spp)
        per = np.array([w.get(g, 0.0) / by_group[g][1] if g in by_group else 0.0
                        for g in range(groups)])
        return (values * per[group][:, None]).astype(np.float32)

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
        started, traced = time.perf_counter(), stats.stages.get("light_paths", 0.0)
        tot = dict(pair_tests=0, valid_pairs=0, light_x_view=0, chunks=0, lsg_light_segments_kept=0,
                   tree_build_seconds=0.0, gather_seconds=0.0, lsg_chunk_bytes_max=0,
                   lsg_chunks_retraced=0, specular_rays=0, rays=0, lsg_leaf_points_tested=0,
                   lsg_kept_x_view=0)
        while queue:
            k, n = queue.popleft()
            rays = chunk_rays(counts, k, n)
            if rays == 0:
                continue
            split = math.ceil(rays * seg_per_ray * BYTES_PER_SEGMENT / budget)
            if split > 1 and rays > 1:       # the measured segments per ray say: too big
                queue.extendleft((k * split + j, n * split) for j in reversed(range(split)))
                continue
            with stats.stage("light_paths"):
                lp = trace_light_paths(ps, n_rays, None, show_progress,
                                       chunk=(k, n), targeted=targeted, seed_offset=seed_offset,
                                       interior=getattr(self, "_interior", False))
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
            tot["light_x_view"] += len(segs) * gat.active
            tot["chunks"] += 1
            tot["lsg_light_segments_kept"] += res.kept
            tot["lsg_leaf_points_tested"] += res.leaf_points
            tot["lsg_kept_x_view"] += res.kept * gat.active
            tot["tree_build_seconds"] += res.tree_seconds
            tot["gather_seconds"] += res.gather_seconds
            tot["lsg_chunk_bytes_max"] = max(tot["lsg_chunk_bytes_max"], res.nbytes)
            eng.note_host(res.nbytes)
        # the stages: the tree builds the gatherer timed, and the gather all the rest of
        # the chunks' time outside tracing (their launches, clipping and bookkeeping), so
        # that the stages cover the pass
        traced = stats.stages.get("light_paths", 0.0) - traced
        rest = time.perf_counter() - started - traced - tot["tree_build_seconds"]
        stats.stages["lsg_tree"] = stats.stages.get("lsg_tree", 0.0) + tot["tree_build_seconds"]
        stats.stages["lsg_gather"] = stats.stages.get("lsg_gather", 0.0) + max(rest, 0.0)
        return tot
