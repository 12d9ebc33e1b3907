"""What a pass gets: one object holding the prepared scene, the view paths, the stats and a
launch call that binds the scene's buffers by the kernels' declared names.

A method's ``render(ctx)`` reads everything through its :class:`PassContext`:

* ``ctx.scene``, ``ctx.ps`` (the :class:`~clscatter.transport.prepared.PreparedScene`),
  ``ctx.paths`` (the session's :class:`~clscatter.transport.view_paths.ViewPaths`),
  ``ctx.stats``, ``ctx.show_progress``, ``ctx.engine``;
* ``ctx.call(program, kernel, size, defines, **args)``: the one launch call. Every kernel
  parameter named like a scene buffer (``nodes``, ``tris``, ``lights``, ``medium``,
  ``camera`` or ``cam``, ...) and ``num_lights`` is bound from the prepared scene unless
  given; a misspelled or missing argument is an error;
* ``ctx.scratch(nbytes)``: a device buffer released when the pass ends (whatever happens);
* ``ctx.cache``: this method's slot in the session, kept between renders and released
  when the session closes (values with a ``release()`` have it called): where a method
  keeps structures that survive a change that does not touch them;
* ``ctx.note(line)``: a one-line note for the user (``render`` prints it as
  ``clscatter: note: ...``), e.g. why a budget could not be kept;
* ``ctx.predict(stage, work)`` and ``ctx.learn(stage, work, seconds)``: this machine's
  learnt seconds per unit of a method's own work (the session keeps them per device,
  across runs; None before anything was learnt, and always without a session): how a
  method sizes its first unit of work to a deadline before it has timed one;
* ``ctx.progression(max_passes, planned, own_budget)``: the
  :class:`~clscatter.transport.progressive.Progression` a method with progressive passes
  runs them by: it ends them by the render's deadline (``ctx.deadline``, the share of
  ``render.time_budget`` this pass was given) or the method's own budget, whichever comes
  first, or at the render's error target, and estimates their noise (the session adds it
  to the render's error estimate).
"""
from __future__ import annotations

import time
from typing import Any, Callable, Sequence

import numpy as np

from ..io.stats import Stats
from .prepared import PreparedScene
from .progressive import Progression
from .view_paths import DeviceSegments, ViewPaths


class PassCache(dict):
    """A method's slot in a session: ``{key: value}`` kept between renders. :meth:`release`
    calls ``release()`` on every value that has one and empties the slot."""

    def release(self) -> None:
        for value in self.values():
            free = getattr(value, "release", None)
            if callable(free):
                free()
        self.clear()


class PassContext:
    """One pass's view of the render (see the module docstring). A context is used once,
    inside ``with``: leaving it frees the scratch buffers the pass took."""

    def __init__(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
                 show_progress: bool = True, cache: PassCache | None = None,
                 on_note: Callable[[str], None] | None = None,
                 deadline: float | None = None, target_error: float = 0.0,
                 image_so_far: Callable[[], np.ndarray | None] | None = None,
                 clock: Callable[[], float] = time.perf_counter,
                 cancel: Callable[[], bool] | None = None,
                 costs: tuple[Callable[[str, float], float | None],
                              Callable[[str, float, float], None]] | None = None,
                 hold_overruns: bool = False):
        self.ps = ps
        #: with ``hold_overruns``, :meth:`overrun` keeps here what it would tell (the
        #: session tells it only when the whole render breaks its budget); else None
        self.overruns: list[str] | None = [] if hold_overruns else None
        self._costs = costs            # (predict, learn) of the session's calibration
        self.cancel = cancel           # polled between progressive passes
        self.clock = clock             # what deadlines are measured on (tests give a fake one)
        self.deadline = deadline
        self.target_error = float(target_error)
        self._image_so_far = image_so_far
        self.progressions: list[Progression] = []
        self._on_note = on_note
        self.paths = paths
        self.stats = stats
        self.show_progress = show_progress
        self.cache = cache if cache is not None else PassCache()
        self._scratch: list = []

    @property
    def scene(self):
        return self.ps.scene

    @property
    def engine(self):
        return self.ps.engine

    @property
    def shape(self) -> tuple[int, int, int]:
        """The image's shape, (H, W, 3)."""
        cam = self.ps.scene.camera
        return cam.height, cam.width, 3

    def zeros(self) -> np.ndarray:
        """A black (H, W, 3) float32 image."""
        return np.zeros(self.shape, np.float32)

    def segments(self) -> DeviceSegments:
        """The view segments on the device, sorted, with each pixel's run."""
        cam = self.ps.scene.camera
        return self.paths.on_device(self.ps.engine, cam.width, cam.height)

    def note(self, line: str) -> None:
        """Tell the user ``line`` (one line); also kept in the stats under ``notes``."""
        self.stats.note(line)
        if self._on_note is not None:
            self._on_note(line)

    def overrun(self, prog: Progression, line: str | None) -> None:
        """A progression's note that its first pass alone broke its deadline (None: it did
        not). Told at once when that deadline is the method's own ``time_budget``, or when
        no session watches the render's budget; otherwise the deadline is only this pass's
        share of the render's budget, and the line waits in :attr:`overruns`."""
        if line is None:
            return
        if self.overruns is None or prog.own_deadline:
            self.note(line)
        else:
            self.overruns.append(line)

    def predict(self, stage: str, work: float) -> float | None:
        """Seconds ``work`` units of ``stage`` should take on this device, as learnt from
        earlier :meth:`learn` calls (None before any, or without a session)."""
        return None if self._costs is None else self._costs[0](stage, work)

    def learn(self, stage: str, work: float, seconds: float) -> None:
        """Keep that ``work`` units of ``stage`` took ``seconds`` here (for :meth:`predict`)."""
        if self._costs is not None:
            self._costs[1](stage, work, seconds)

    def progression(self, max_passes: int, planned: int, own_budget: float = 0.0) -> Progression:
        """A :class:`Progression` for this pass's progressive passes: at most ``max_passes``,
        the time shared among ``planned``, ending by the render's deadline or ``own_budget``
        seconds from now (0: none), whichever is first."""
        prog = Progression(None, self.target_error, max_passes, planned, self._image_so_far,
                           self.clock, self.cancel)
        own = prog.started + own_budget if own_budget > 0 else None
        ends = [t for t in (self.deadline, own) if t is not None]
        prog.deadline = min(ends) if ends else None
        prog.own_deadline = own is not None and (self.deadline is None or own < self.deadline)
        self.progressions.append(prog)
        return prog

    def errors(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The per-pixel variance and squared blur bias of this pass's progressions, summed
        (None without one that has two halves; see
        :meth:`~clscatter.transport.progressive.Progression.bias_squared`)."""
        out = None
        for p in self.progressions:
            var = p.variance()
            if var is None:
                continue
            bias = p.bias_squared(var)
            bias = np.zeros_like(var) if bias is None else bias
            out = (var, bias) if out is None else (out[0] + var, out[1] + bias)
        return out

    def call(self, program: str, kernel: str, global_size: int | Sequence[int],
             defines: dict[str, object] | None = None, **args: Any) -> None:
        """Launch ``program``/``kernel`` over ``global_size`` with keyword arguments, the
        scene's buffers bound by name (:meth:`PreparedScene.call`)."""
        self.ps.call(program, kernel, global_size, defines, **args)

    def scratch(self, nbytes: int):
        """A device buffer of ``nbytes`` (contents undefined) freed when the pass ends."""
        buf = self.ps.engine.empty(nbytes)
        self._scratch.append(buf)
        return buf

    def close(self) -> None:
        """Free the scratch buffers (the session calls it when the pass ends)."""
        if self._scratch:
            self.ps.engine.free(*self._scratch)
        self._scratch = []

    def __enter__(self) -> "PassContext":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
