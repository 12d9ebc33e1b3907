"""Line space gathering (Sun et al. 2010): single scattering gathered from lighting rays."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ...estimators.line_gather import BYTES_PER_SEGMENT, Gatherer
from ...io.stats import Stats, Timer, progress
from ...transport.context import PassContext
from ...transport.emission import targeted_fraction
from ...transport.light_paths import ray_counts, trace_light_paths
from ...transport.prepared import PreparedScene
from .. import register
from ..base import AutoRole, Estimate, Method, Param, PassResult, camera_samples

#: pair tests one lighting segment costs the gather, as an order of magnitude (the plane
#: queries of a few hundred to a few thousand view segments): the work estimate's unit
PAIRS_PER_SEGMENT = 1000
#: a budget counts as kept while the time stays within this factor of it
BUDGET_SLACK = 1.2
#: most rays the automatic radius's pilot traces (in one piece: its segments stay in memory)
PILOT_MAX = 1 << 18


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
    at most :data:`PILOT_MAX`) is gathered at a trial radius r0; the median number c of
    pairs per lit view segment,
    scaled to ``light_rays``, gives ``r = max(r0 * auto_count / c, f / 16)`` with f the
    median pixel footprint there: a typical lit view segment gathers ``auto_count``
    lighting segments, and no blur is smaller than a sixteenth of a pixel. Both terms are
    measured in the normalised frame, so the radius does not depend on the scene's scale
    or on objects far away. The pilot's rays are not part of the image.

    *Progressive passes* (``passes`` > 1 or ``time_budget`` > 0): pass i traces fresh rays
    and gathers them with ``r_{i+1} = r_i (i + alpha) / (i + 1)`` (:func:`ppb_radii`); the
    image is the mean of the passes and converges without a radius bias floor. With a
    ``time_budget``, passes run while one more fits in it (at least one runs).

    Rays are processed in chunks whose working set stays within ``max_bytes``; a chunk that
    turns out larger is traced again in smaller parts.

    Statistics: ``light_segments``, ``lsg_light_segments_kept``, ``view_segments``,
    ``pair_tests``, ``pair_tests_bruteforce``, ``valid_pairs``, ``lsg_cull_fraction``,
    ``lsg_valid_fraction`` (and the paper's way of counting them, sec. 4.3:
    ``lsg_leaf_points_tested``, ``lsg_cull_fraction_paper``, ``lsg_valid_fraction_paper``),
    ``tree_build_seconds``, ``gather_seconds``, ``chunks``, ``lsg_chunks_retraced``,
    ``lsg_chunk_bytes_max``, ``lsg_radius`` (normalised; ``lsg_radius_world`` in scene
    units), ``lsg_radius_last``, ``lsg_passes``, ``lsg_pass_seconds``, ``lsg_time_budget``,
    ``lsg_auto_radius``, ``lsg_targeted``, ``light_rays_specular_fraction``.

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
        the segments traced over all passes times :data:`PAIRS_PER_SEGMENT`."""
        views = 2.0 * camera_samples(scene)
        rays = float(params["light_rays"])
        chunk = min(float(params["max_bytes"]), rays * 3 * BYTES_PER_SEGMENT)
        return [Estimate("lsg", "render.lsg.light_rays", chunk + views * 80,
                         rays * 3 * params["passes"] * PAIRS_PER_SEGMENT + views * 200,
                         "pair tests (order of magnitude)")]

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

    def render(self, ctx: PassContext) -> PassResult:
        """Single-scattered radiance gathered from the lighting rays, in the medium term."""
        ps, paths, stats, show_progress = ctx.ps, ctx.paths, ctx.stats, ctx.show_progress
        views = paths.segments
        p = self.params
        stats.set(view_segments=int(len(views)), lsg_targeted=self.targeted())
        self._rays = self.traced_rays(ps)
        if len(views) == 0 or ps.num_lights == 0 or p["light_rays"] == 0:
            stats.set(pair_tests=0, pair_tests_bruteforce=0, valid_pairs=0, chunks=0,
                      lsg_radius=0.0, lsg_passes=0)
            return PassResult(medium=ctx.zeros())
        eng = ps.engine
        r_fixed = p["radius"] * ps.scene.scene_extent() / ps.frame.scale
        dev = ctx.segments()                                  # the same segments, in order
        gat = Gatherer(eng, views, ps.medium, r_fixed or 1.0, p["min_sin"], p["leaf_size"],
                       p["segments_per_launch"], show_progress=show_progress, views_buf=dev.buf)
        try:
            if r_fixed > 0:
                r1 = r_fixed
            else:
                with stats.stage("lsg_auto_radius"):
                    auto = self.auto_radius(ps, gat, views)
                r1 = auto.radius
                stats.set(lsg_auto_radius=auto.__dict__)
            totals, passes, pass_seconds = self._progressive(ps, gat, r1, stats, show_progress)
            budget = float(p["time_budget"])
            if budget > 0 and pass_seconds and pass_seconds[0] > BUDGET_SLACK * budget:
                ctx.note(f"render.lsg.time_budget: the first pass alone took "
                         f"{pass_seconds[0]:.3g} s, more than the {budget:g} s budget (a pass "
                         f"is the smallest unit of work); lower render.lsg.light_rays to keep it")
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
        return PassResult(medium=image)

    # ---- automatic radius ----
    def auto_radius(self, ps: PreparedScene, gat: Gatherer, views: np.ndarray) -> AutoRadius:
        """The automatic radius (class docstring): a pilot gather at a trial radius."""
        n_rays = self._rays
        pilot = int(min(n_rays, max(2000, n_rays // 8), PILOT_MAX))
        cam = ps.camera
        mid = 0.5 * (views["a"][:, :3] + views["b"][:, :3]).astype(np.float64)
        dist = np.linalg.norm(mid - cam["origin"][:3].astype(np.float64), axis=1)
        pix = 2.0 * float(np.linalg.norm(cam["right"][:3])) / max(int(cam["width"]), 1)
        foot = dist * pix                       # pixel footprint at each view segment
        lp = trace_light_paths(ps, pilot, None, gat.show_progress, targeted=self.targeted(),
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
                    res = self._gather_chunks(ps, gat, stats, show_progress,
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
