"""The warm path: a prepared scene kept on the device, re-rendered after changes.

A :class:`RenderSession` holds everything a render builds (the device and its programs, the
normalised frame, the BVH and the scene's device buffers, the view paths) and, when the
scene changes, re-runs only what the change invalidates:

============================  ==============================================================
what changed                  what runs again
============================  ==============================================================
objects' or volumes' shapes   everything (a new BVH; the normalised frame may move)
a volume's coefficients       passes (the voxel pipeline from its material stage on)
materials                     the material buffer, view paths, passes
lights                        the light buffer, the surface shading (re-shading the recorded
                              diffuse hits, no camera path traced), passes
camera                        the camera buffer, view paths, passes (switching back to the
                              camera before, as from a preview to a full frame, reuses the
                              view paths kept for it: re-shaded if the lights moved)
medium                        the medium buffer, view paths (segment weights), passes
render.max_depth / seed       view paths, passes
method or its parameters      passes only
============================  ==============================================================

A one-off :func:`clscatter.pipeline.render.render` is a session used once, so a warm re-render and
a fresh render run the same code and give the same image. ``stats["stages_run"]`` lists
what ran and ``stats["reused"]`` what was kept; ``stats["stages"]`` times them.

Sources: :meth:`RenderSession.from_source` keeps the scene's raw TOML data, so changes can
be given as ``--set``-style overrides (:meth:`set`, validated exactly like the command
line; a bad value raises the same one-line :class:`SceneError` and leaves the session as it
was) and the current scene can be saved as TOML (:meth:`to_toml`).
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..device import Engine, get_engine
from ..io.stats import Stats
from ..methods import configure, get_method
from ..scene.builtin import to_toml
from ..scene.loader import apply_overrides, scene_from_dict, scene_source
from ..scene.model import Scene
from ..transport.context import PassCache, PassContext
from ..transport.prepared import (
    PreparedScene,
    geometry_key,
    prepare_scene,
    refresh,
    same_frame,
)
from ..transport.progressive import Cancelled, relmse_estimate
from ..transport.view_paths import ViewPaths, shade_hits, trace_view_paths
from . import budget, calibration
from .check import check, scene_notes
from .planner import user_notes


def _view_key(scene: Scene) -> tuple:
    """What the view paths depend on besides the device buffers: depth and seed."""
    return scene.render.max_depth, scene.render.seed


class RenderSession:
    """A scene prepared on one device, rendered again and again (see the module docstring)."""

    def __init__(self, scene: Scene, method: str | None = None, engine: Engine | None = None,
                 device: str | None = None, max_memory: float | None = None,
                 keep_hits: bool = True):
        self.scene = scene
        # record the view paths' diffuse hits on the device with them, so that a light
        # change re-shades those instead of tracing the camera paths again (80 bytes per
        # hit; a one-off render does not keep them)
        self.keep_hits = keep_hits
        self.method = method
        self.max_memory = max_memory
        self._engine = engine
        self._device = device
        self._ps: PreparedScene | None = None
        self._geometry: tuple | None = None
        self._paths: ViewPaths | None = None
        self._paths_key: tuple | None = None
        self._paths_camera: bytes = b""      # the camera and lights they were traced and
        self._paths_lights: bytes = b""      # shaded for
        self._spare: tuple | None = None     # (key, camera, lights, ViewPaths): see _keep_as_spare
        self._pending: list[str] = []       # buffers re-uploaded since the last render
        self._caches: dict[str, PassCache] = {}   # each method's slot (PassContext.cache)
        self._data: dict | None = None
        self._base_dir = Path.cwd()
        self._source = scene.source
        self._overrides: list[str] = []
        self._base_overrides: list[str] = []

    # ---- sources and changes ---------------------------------------------------------------
    @classmethod
    def from_source(cls, spec: str | Path, overrides: Sequence[str] = (),
                    on_note: Callable[[str], None] | None = None, **kw) -> "RenderSession":
        """A session on ``spec`` (TOML or Mitsuba XML path, or ``builtin:NAME``) with
        ``--set`` overrides; ``on_note`` hears what converting the scene approximated."""
        data, base_dir = scene_source(spec, on_note)
        return cls.from_data(data, base_dir, str(spec), overrides, **kw)

    @classmethod
    def from_data(cls, data: dict, base_dir: str | Path, source: str,
                  overrides: Sequence[str] = (), **kw) -> "RenderSession":
        """A session on raw scene ``data`` (relative paths resolved against ``base_dir``)."""
        scene = scene_from_dict(apply_overrides(data, overrides), Path(base_dir), source)
        s = cls(scene, **kw)
        s._data, s._base_dir, s._source = data, Path(base_dir), source
        s._overrides = list(overrides)
        s._base_overrides = list(overrides)
        return s

    def validate(self, overrides: Sequence[str], replace: bool = False) -> tuple[Scene, list[str]]:
        """The scene ``overrides`` would give, checked exactly as the command line checks
        it (loader, method names and parameters), without changing the session; and the
        override list it would hold. ``replace``: the overrides replace every earlier
        change (they apply to the source with the session's original overrides only: an
        animation frame), else they add to the current ones. Raises the CLI's one-line
        :class:`~clscatter.errors.ClscatterError`."""
        if self._data is None:
            raise TypeError("needs a session made by RenderSession.from_source")
        merged = (self._base_overrides if replace else self._overrides) + list(overrides)
        scene = scene_from_dict(apply_overrides(self._data, merged), self._base_dir, self._source)
        check(scene, self.method)
        return scene, merged

    def set(self, overrides: Sequence[str], replace: bool = False) -> None:
        """Apply ``--set key=value`` overrides (see :meth:`validate`); on error nothing
        changes."""
        scene, self._overrides = self.validate(overrides, replace)
        self.update(scene)

    def update(self, scene: Scene) -> None:
        """Move the session to ``scene``; the next :meth:`render` re-runs what changed."""
        self.scene = scene

    def current_overrides(self) -> list[str]:
        """Every ``--set`` override applied to the source so far, in order."""
        return list(self._overrides)

    def current_data(self) -> dict:
        """The scene's raw data with every override applied (what :meth:`to_toml` writes)."""
        if self._data is None:
            raise TypeError("needs a session made by RenderSession.from_source")
        data = apply_overrides(self._data, self._overrides)
        return _absolute_paths(copy.deepcopy(data), self._base_dir)

    def to_toml(self) -> str:
        """The current scene as a TOML file that ``clscatter render`` reproduces exactly
        (relative mesh and grid paths made absolute)."""
        return to_toml(self.current_data())

    @property
    def engine(self) -> Engine:
        if self._engine is None:
            self._engine = get_engine(self._device)
        return self._engine

    # ---- rendering -------------------------------------------------------------------------
    def render(self, show_progress: bool = True, cancel: Callable[[], bool] | None = None,
               on_note: Callable[[str], None] | None = None, preview: bool = False,
               stats: Stats | None = None, samples: tuple[int, int] | None = None,
               only: Sequence[int] | None = None, pass_params: dict | None = None,
               default_budget: float | None = None):
        """Render the current scene, re-running only what changed since the last render.

        ``preview`` renders at a quarter of the resolution with one sample per pixel (the
        stats say so); ``cancel()`` is polled between stages and between progressive
        passes and raises :class:`Cancelled`.
        ``stats`` may be one the caller started earlier (the CLI times scene loading and
        output writing in it too). ``samples = (lo, hi)`` renders only those camera samples
        (see :func:`~clscatter.transport.view_paths.trace_view_paths`). ``only`` runs just those passes
        of the plan (by index) and ``pass_params`` (``{index: {param: value}}``) overrides their
        parameters: how a cluster splits a render into tasks (:mod:`clscatter.cluster`).
        ``default_budget`` replaces the default time budget where the scene sets none
        (the relighting page's full frames, which refinement follows).
        """
        started = time.perf_counter()
        scene = _preview_scene(self.scene) if preview else self.scene
        stats = stats or Stats()
        ran: list[str] = []
        reused: list[str] = []

        def stop_if_asked() -> None:
            if cancel is not None and cancel():
                raise Cancelled("render cancelled")

        with stats.stage("configure"):
            req = check(scene, self.method)
            time_limit = _time_budget(scene, req, started, stats, preview or only is not None,
                                      default_budget)
        with stats.stage("device"):
            engine = self.engine
            engine.quiet_host_threads()
            engine.preload(_programs(scene, req))
        clock = (time.perf_counter(), engine.wait_seconds)
        with stats.stage("configure"):
            limit, source = budget.memory_budget(engine, self.max_memory)
            fitted_memory = budget.fit_memory(scene, req, limit, source)
            budget.check_budget(req.estimates, limit, source)
            engine.fit_pool(limit, budget.peak_bytes(req.estimates))
            fitted = [p.method for p in req.passes if time_limit.deadline is not None
                      and get_method(p.method).SIZES_PASSES]
            for line in (user_notes(req.notes) + fitted_memory
                         + budget.long_work_notes(req.estimates, fitted) + scene_notes(scene)):
                if on_note is not None:
                    on_note(line)
            if scene.dropped_triangles():
                stats.set(degenerate_triangles_dropped=scene.dropped_triangles())
            stats.set(estimated_peak_bytes=int(budget.peak_bytes(req.estimates)))
            engine.reset_peak()
        stop_if_asked()

        # ---- prepared scene: BVH and device buffers ----
        with stats.stage("scene_structs"):
            geometry = geometry_key(scene)
            warm = (self._ps is not None and geometry == self._geometry
                    and same_frame(self._ps, scene))
        if warm:
            changed = refresh(self._ps, scene, stats)
            reused.append("bvh")
            ran += [f"upload_{c}" for c in changed]
            self._pending += changed
            if set(changed) - {"camera", "lights"}:
                self._release_spare()          # its segments' weights changed too
        else:
            self.release()
            t0 = time.perf_counter()
            self._ps = prepare_scene(scene, engine, stats)
            _calibrate(engine, req, scene, "scene", time.perf_counter() - t0, stats)
            self._geometry = geometry
            ran.append("prepare_scene")
            self._pending = ["all"]
        ps = self._ps
        stop_if_asked()

        # ---- view paths ----
        key = (_view_key(scene), samples)
        if self._paths is not None and set(self._pending) == {"camera"} | (set(self._pending) & {"lights"}):
            self._swap_spare(ps, key, stats, ran, reused)
        relight = (self._paths is not None and key == self._paths_key
                   and self._paths.hits is not None
                   and set(self._pending) == {"lights"})
        if relight:
            # only lights changed: the segments (their weights hold no light) stay; the
            # surface is re-shaded at the recorded diffuse hits
            with stats.stage("shade_hits"):
                self._paths.surface = shade_hits(ps, self._paths.hits)
            self._paths_lights = ps.lights.tobytes()
            self._pending = []
            ran.append("shade_hits")
            reused.append("view_paths")
            stats.set(view_segments=int(len(self._paths)))
        elif self._paths is None or self._pending or key != self._paths_key:
            if ("camera" in self._pending and set(self._pending) <= {"camera", "lights"}
                    and self._paths is not None):
                self._keep_as_spare()          # another camera (a preview): keep these
            else:
                self._release_paths()
            self._paths = trace_view_paths(ps, stats, show_progress, sample_range=samples,
                                           keep_hits=self.keep_hits)
            self._paths_key = key
            self._paths_camera, self._paths_lights = ps.camera.tobytes(), ps.lights.tobytes()
            self._pending = []
            ran.append("view_paths")
            _calibrate(engine, req, scene, "view_paths", stats.stages.get("view_paths", 0.0),
                       stats)
        else:
            reused.append("view_paths")
            stats.set(view_segments=int(len(self._paths)))
        paths = self._paths

        # ---- passes ----
        try:
            return self._run_passes(_Run(scene, req, ps, paths, stats, show_progress,
                                         stop_if_asked, ran, reused, preview, only,
                                         pass_params or {}, clock, on_note, time_limit,
                                         cancel))
        finally:
            engine.trim_pool()      # keep what this render freed for the next one

    def _run_passes(self, run: "_Run") -> RenderResult:
        """Run the plan's passes, each with its own :class:`PassContext`, and compose the
        image: the view paths' surface term (or the one a pass traced itself) plus every
        pass's surface and medium radiance.

        Passes whose method refines progressively (``Method.PROGRESSIVE``) run after the
        others and share what those leave of the render's time budget, each the same part
        of the rest, those that size their passes to fit (``Method.SIZES_PASSES``) last;
        their error estimates add up to the render's ``error_estimate``."""
        scene, stats = run.scene, run.stats
        cam = scene.camera
        views = [None] * len(run.req.passes)          # view_surface by plan index
        added = np.zeros((cam.height, cam.width, 3), np.float32)
        medium = np.zeros((cam.height, cam.width, 3), np.float32)
        errors = None                                  # (variance, squared bias) images
        parts: dict[int, np.ndarray] = {}              # each pass's own surface + medium
        counts: dict[int, int] = {}                    # progressive passes each ran (or 1)
        order = [k for k, p in enumerate(run.req.passes) if run.only is None or k in run.only]
        order.sort(key=lambda k: _budget_order(get_method(run.req.passes[k].method)))
        progressive_left = sum(1 for k in order if get_method(run.req.passes[k].method).PROGRESSIVE)

        def base() -> np.ndarray:          # the last pass in plan order that traced one wins
            return next((v for v in reversed(views) if v is not None), run.paths.surface)

        def image_so_far() -> np.ndarray:
            return base() + added + medium

        overruns: list[str] = []                       # passes' first passes past their share
        shared = dict(stats.stages)                    # the work before the passes
        ran: list[tuple[str, float, str]] = []         # (method, seconds, PASS_* kind)
        for k in order:
            p = run.req.passes[k]
            run.stop_if_asked()
            cls = get_method(p.method)
            table = {**p.table(scene), **run.pass_params.get(k, {})}
            method = cls(cls.preview(table) if run.preview else table)
            deadline = None
            kind = PASS_PROGRESSIVE if cls.PROGRESSIVE else PASS_FIXED
            if cls.PROGRESSIVE and run.budget.deadline is not None:
                now = time.perf_counter()
                left = max(run.budget.deadline - now, 0.0)
                kind = PASS_STARVED if left <= 0.0 else kind
                deadline = now + left / progressive_left
                progressive_left -= 1
            t0 = time.perf_counter()
            with PassContext(run.ps, run.paths, stats, run.show_progress,
                             self._caches.setdefault(p.method, PassCache()), run.on_note,
                             deadline, scene.render.target_error, image_so_far,
                             cancel=run.cancel, costs=_costs(run),
                             hold_overruns=True) as ctx:
                out = method.render(ctx)
                err = ctx.errors()
            if kind != PASS_STARVED:    # a pass with no time left says so in the budget's note
                overruns += ctx.overruns or []
            ran.append((p.method, time.perf_counter() - t0, kind))
            if deadline is None and not run.preview and run.only is None:
                _calibrate(run.ps.engine, run.req, scene, p.method, time.perf_counter() - t0,
                           stats)
            run.ran.append(p.method)
            if err is not None:
                errors = err if errors is None else (errors[0] + err[0], errors[1] + err[1])
            views[k] = out.view_surface
            if out.surface is not None:
                added = added + out.surface
            if out.medium is not None:
                medium = medium + out.medium
            parts[k] = sum(x for x in (out.surface, out.medium) if x is not None)
            counts[k] = max(sum(len(p.seconds) for p in ctx.progressions), 1)
        surface = base() + added
        with stats.stage("compose"):
            image = _finite(surface + medium, stats, run.on_note)
        _report_error(stats, errors, image, scene.render.target_error, run.on_note)
        _report_budget(stats, run.budget, run.on_note, overruns, shared, ran)
        result = self._result(run, image, surface, medium)
        result.parts = {k: np.asarray(v, np.float32) for k, v in parts.items()
                        if isinstance(v, np.ndarray)}
        result.part_passes = {k: counts[k] for k in result.parts}
        return result

    def _result(self, run: "_Run", image: np.ndarray, surface: np.ndarray,
                medium: np.ndarray) -> RenderResult:
        """The :class:`RenderResult` with the render's statistics."""
        engine, cam, req, stats = run.ps.engine, run.scene.camera, run.req, run.stats
        chosen = "+".join(p.method for p in req.passes) or "none"
        # host time: the render (after device choice) minus the waits on the device
        render_s = time.perf_counter() - run.clock[0]
        wait_s = engine.wait_seconds - run.clock[1]
        stats.set(render_seconds=render_s, device_wait_seconds=wait_s,
                  host_seconds=max(render_s - wait_s, 0.0))
        stats.set(method=chosen, requested_method=req.requested, plan=req.notes,
                  passes=[{"method": p.method, "role": p.role} for p in req.passes],
                  device=engine.name, width=cam.width, height=cam.height, spp=cam.spp,
                  peak_bytes=int(engine.bytes_peak), stages_run=run.ran, reused=run.reused,
                  preview=bool(run.preview))
        return RenderResult(image.astype(np.float32, copy=False), stats.to_dict(),
                            np.array(surface, np.float32), medium.astype(np.float32, copy=False))

    def progressive_passes(self) -> list[tuple[int, str]]:
        """(plan index, method) of the current plan's passes that can run further
        progressive passes apart (``Method.SPLIT_PASSES``: pass k depends on k alone), so a
        later ``render(only=..., pass_params={k: {"first_pass": n, ...}})`` adds fresh passes
        to an image: how the relighting page refines after a full frame."""
        req = check(self.scene, self.method)
        return [(k, p.method) for k, p in enumerate(req.passes) if get_method(p.method).SPLIT_PASSES]

    def view_surface(self) -> np.ndarray:
        """The surface image of the last render's view paths (direct light on diffuse
        surfaces, before any pass added to it)."""
        return self._paths.surface

    def release(self) -> None:
        """Free the device buffers and the methods' cached structures (the session can
        render again; it prepares anew)."""
        for cache in self._caches.values():
            cache.release()
        self._caches.clear()
        self._release_paths()
        if self._ps is not None:
            self._ps.release()
        self._ps = None
        self._geometry = None

    def close(self) -> None:
        """Free the device buffers and empty the engine's buffer pool (what the session's
        renders left there for the next one)."""
        self.release()
        if self._engine is not None:
            self._engine.drain_pool()

    def _release_paths(self) -> None:
        if self._paths is not None:
            self._paths.release()
        self._paths = None
        self._release_spare()

    # ---- a second set of view paths: switching between preview and full frames ----
    # The view paths of the camera before the last camera change are kept aside (with the
    # camera and lights they were traced and shaded for), so that switching back to that
    # camera (the page's full frame after a drag's previews) reuses them: re-shaded if the
    # lights changed meanwhile, dropped by any change that alters segment weights.
    def _keep_as_spare(self) -> None:
        self._release_spare()
        if self._paths is not None and self._paths.hits is not None:
            self._spare = (self._paths_key, self._paths_camera, self._paths_lights, self._paths)
        elif self._paths is not None:
            self._paths.release()
        self._paths = None

    def _release_spare(self) -> None:
        if self._spare is not None:
            self._spare[3].release()
        self._spare = None

    def _swap_spare(self, ps: PreparedScene, key: tuple, stats: Stats, ran: list,
                    reused: list) -> None:
        """Make the kept view paths current when they were traced for this camera, and
        keep the current ones aside in their place."""
        if self._spare is None:
            return
        s_key, s_camera, s_lights, s_paths = self._spare
        if s_key != key or s_camera != ps.camera.tobytes():
            return
        self._spare = (self._paths_key, self._paths_camera, self._paths_lights, self._paths)
        self._paths, self._paths_key, self._paths_camera = s_paths, s_key, s_camera
        self._paths_lights = s_lights
        self._pending = ["lights"] if s_lights != ps.lights.tobytes() else []
        reused.append("view_paths_kept")

    def __enter__(self) -> "RenderSession":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class RenderResult:
    image: np.ndarray            # (H, W, 3) float32 linear radiance
    stats: dict[str, Any]
    surface: np.ndarray          # the surface part alone (direct light + surface caustics)
    medium: np.ndarray           # the medium part alone
    parts: dict = field(default_factory=dict)  # plan index -> that pass's own radiance
    part_passes: dict = field(default_factory=dict)  # plan index -> its progressive passes


@dataclass
class _Run:
    """One render's state, handed from the staging of :meth:`RenderSession.render` to its
    passes."""

    scene: Scene
    req: Any
    ps: PreparedScene
    paths: ViewPaths
    stats: Stats
    show_progress: bool
    stop_if_asked: Callable[[], None]
    ran: list
    reused: list
    preview: bool
    only: Sequence[int] | None
    pass_params: dict
    clock: tuple[float, float]
    on_note: Callable[[str], None] | None
    budget: "_Budget"
    cancel: Callable[[], bool] | None = None


@dataclass
class _Budget:
    """The render's time budget: seconds (0: none), where it comes from, when the render
    started and the deadline its progressive passes end by (None: no deadline)."""

    seconds: float
    source: str
    started: float
    deadline: float | None


def _time_budget(scene: Scene, req, started: float, stats: Stats, exempt: bool,
                 default: float | None = None) -> _Budget:
    """The render's :class:`_Budget` (:func:`budget.time_budget`; ``default`` where the
    scene sets none), recorded in the stats. ``exempt`` (a preview, or a cluster's task:
    fixed work) sets no deadline."""
    if default is not None and scene.render.time_budget is None:
        seconds, source = float(default), "the caller's default"
    else:
        seconds, source = budget.time_budget(scene, req.requested)
    stats.set(time_budget=seconds, time_budget_source=source,
              target_error=scene.render.target_error)
    deadline = started + seconds if seconds > 0 and not exempt else None
    return _Budget(seconds, source, started, deadline)


#: kinds of pass in a budgeted render (_report_budget): fixed work, progressive passes
#: with a share of the budget, and progressive passes that found none left
PASS_FIXED, PASS_PROGRESSIVE, PASS_STARVED = "fixed", "progressive", "starved"


def _budget_order(cls) -> int:
    """When a pass runs within a budgeted render: fixed work first, then progressive passes
    of a fixed size, then those that size their passes to the time left."""
    return 0 if not cls.PROGRESSIVE else 2 if cls.SIZES_PASSES else 1


def _costs(run: "_Run"):
    """The (predict, learn) pair a pass context offers its method: this device's
    calibration (:mod:`clscatter.pipeline.calibration`) under the method's own stage names."""
    device, source = run.ps.engine.device.name.strip(), run.scene.source
    return (lambda stage, work: calibration.predict(device, stage, work, source),
            lambda stage, work, seconds: _record(run.stats, run.ps.engine, stage, work,
                                                 seconds, run.scene))


def _calibrate(engine: Engine, req, scene: Scene, stage: str, seconds: float,
               stats: Stats) -> None:
    """Record that ``stage`` (the scene's preparation, its view paths, or a pass that ran
    in full) took ``seconds`` for its estimated work in ``req`` (:func:`_record`)."""
    _record(stats, engine, stage, sum(e.work for e in req.estimates if e.stage == stage),
            seconds, scene)


def _record(stats: Stats, engine: Engine, stage: str, work: float, seconds: float,
            scene: Scene) -> None:
    """Keep that ``work`` of ``stage`` took ``seconds`` on ``engine``'s device, on ``scene``
    (:mod:`clscatter.pipeline.calibration`); the record's own time (a file read and
    written) is the stage ``calibrate``."""
    with stats.stage("calibrate"):
        calibration.record(engine.device.name.strip(), stage, work, seconds, scene.source)


def _report_error(stats: Stats, errors: tuple | None, image: np.ndarray,
                  target: float, on_note) -> None:
    """``error_estimate`` in the stats: the image's relMSE estimated from its progressive
    passes (:mod:`clscatter.transport.progressive`: noise from independent halves, plus the
    gather radii's blur; each also alone), None without any; and a note when the error
    target was not reached."""
    if errors is None:
        stats.set(error_estimate=None)
        return
    noise = relmse_estimate(errors[0], image)
    bias = max(relmse_estimate(errors[1], image), 0.0)
    err = noise + bias
    stats.set(error_estimate=err, error_estimate_noise=noise, error_estimate_bias=bias)
    if target > 0 and err > target and on_note is not None:
        on_note(f"render.target_error: the estimated relMSE is {err:.3g}, above the target "
                f"{target:g}, when the passes stopped (raise render.time_budget to go on)")


def _report_budget(stats: Stats, b: _Budget, on_note, overruns: list[str],
                   shared: dict[str, float] | None = None,
                   ran: list[tuple[str, float, str]] = ()) -> None:
    """A note when the render ran past its time budget by more than BUDGET_SLACK: the
    passes' own notes where a first pass alone broke its share of the budget
    (``overruns``: what could not be made smaller); or else one line naming the longest
    work that does not shrink with the budget, among the stages before the passes
    (``shared``: their seconds) and the fixed passes (``ran``: method, seconds and kind,
    :data:`PASS_FIXED` and the others), and the progressive passes that then had no time
    left (:data:`PASS_STARVED`: each still runs its smallest pass). Within the budget a
    pass that overran its share says nothing: the others made up for it."""
    if b.deadline is None:
        return
    took = time.perf_counter() - b.started
    if took <= budget.BUDGET_SLACK * b.seconds or on_note is None:
        return
    if overruns:
        for line in overruns:
            stats.note(line)
            on_note(line)
        return
    fixed = dict(shared if shared is not None else stats.stages)
    fixed.update((m, s) for m, s, kind in ran if kind == PASS_FIXED)
    name = max(fixed, key=fixed.get) if fixed else "the render"
    line = (f"{b.source}: the render took {took:.3g} s of its {b.seconds:g} s budget; "
            f"{name} alone took {fixed.get(name, took):.3g} s (work that does not shrink "
            f"with the budget: lower the resolution, spp or that stage's parameters)")
    late = [(m, s) for m, s, kind in ran if kind == PASS_STARVED]
    if late:
        line += (f"; after it {' and '.join(m for m, _ in late)} had no time left and ran "
                 f"their smallest passes ({', '.join(f'{s:.3g} s' for _, s in late)})")
    stats.note(line)
    on_note(line)


def _finite(image: np.ndarray, stats: Stats, on_note) -> np.ndarray:
    """``image`` with non-finite pixels (float32 overflow) set to 0, counted in the stats
    and said in a note, never silently."""
    bad = ~np.isfinite(image)
    if not bad.any():
        return image
    count = int(bad.any(axis=-1).sum())
    stats.set(nonfinite_pixels_zeroed=count)
    if on_note is not None:
        on_note(f"{count} pixels overflowed float32 and were set to 0 (are the scene's "
                "intensities or coefficients extreme?)")
    return np.where(bad, 0.0, image)


def _programs(scene: Scene, req) -> list[tuple[str, dict | None]]:
    """The kernel programs a render of ``scene`` by plan ``req`` uses: the camera paths'
    (every render traces them) and each pass's (:meth:`Method.programs`)."""
    progs: list[tuple[str, dict | None]] = [("view_paths", None), ("primitives", None)]
    for p in req.passes:
        cls = get_method(p.method)
        progs += cls.programs(scene, configure(p.method, p.table(scene)))
    return progs


def _preview_scene(scene: Scene) -> Scene:
    """``scene`` at a quarter of the resolution (at least 16 pixels wide) and 1 spp."""
    cam = copy.copy(scene.camera)
    f = max(1, min(4, cam.width // 16))
    cam.width, cam.height = max(1, cam.width // f), max(1, cam.height // f)
    cam.spp = 1
    out = copy.copy(scene)
    out.camera = cam
    return out


def _absolute_paths(data: dict, base_dir: Path) -> dict:
    """Make the ``file`` of mesh objects/volumes and ``grid``/``density`` of volumes absolute."""
    for section in ("objects", "volumes"):
        for item in data.get(section, []) or []:
            for key in ("file", "grid", "density"):
                if isinstance(item, dict) and isinstance(item.get(key), str):
                    p = Path(item[key])
                    item[key] = str(p if p.is_absolute() else (base_dir / p).resolve())
    return data
