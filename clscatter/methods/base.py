"""What every rendering method is: declared parameters, declared capabilities, one render call.

A method is one class in one module (or package) of :mod:`clscatter.methods`:

* ``NAME`` — the name the scene's ``render.method`` and ``--method`` use;
* ``PARAMS`` — a tuple of :class:`Param`, each declared once (default, one-line doc, range);
  the ``[render.<NAME>]`` table is checked against it before any device work, defaults
  come from it, and the parameter table of the class docstring and of ``docs/methods.md``
  is generated from it (:func:`param_table`);
* capabilities the ``auto`` planner reads instead of method names: ``TERMS`` (what the
  method computes when it runs alone), ``LIGHTS`` (light types it handles; others it leaves
  to a fallback it documents), ``AUTO`` (the roles it can take in an ``auto`` plan, with a
  priority and parameter overrides for that role), ``ALONE`` (once chosen it renders the
  whole image by itself: the voxel pipeline, which owns everything its grid touches);
* ``render(ctx)`` — given its :class:`~clscatter.transport.context.PassContext`, the
  radiance it adds to the image as a :class:`PassResult`.

Terms (the pieces an image is made of):

``direct``            single scattering of light that came straight from a light (shadowed)
``caustics``          single scattering of light that came through mirrors or glass,
                      including light scattered inside glass (a dielectric's
                      ``interior_sigma_s``: that light always came through the surface)
``surface_caustics``  diffuse surfaces lit through mirrors or glass
``volumes``           light bent by graded-index ``[[volumes]]`` (and scattering glass in a
                      scene with density grids)
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ..errors import SceneError
from ..io.stats import Stats
from ..transport.context import PassContext

TERMS = ("direct", "caustics", "surface_caustics", "volumes")
LIGHT_KINDS = frozenset({"point", "spot", "directional"})


def _tname(v: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
            list: "an array", dict: "a table"}.get(type(v), type(v).__name__)


@dataclass(frozen=True)
class Param:
    """One ``[render.<method>]`` parameter: its default (which fixes its type), a one-line
    doc, and its range: ``lo``/``hi`` bounds (``lo_open``/``hi_open`` make them strict) or
    ``choices`` for strings."""

    name: str
    default: Any
    doc: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] | None = None

    @property
    def type(self) -> type:
        return type(self.default)

    def rule(self) -> str:
        """The range as a phrase, e.g. ``"must be in (0, 1]"`` ('' when unbounded)."""
        if self.choices:
            return "must be one of " + ", ".join(repr(c) for c in self.choices)
        if self.lo is not None and self.hi is not None:
            return (f"must be in {'(' if self.lo_open else '['}{self.lo:g}, "
                    f"{self.hi:g}{')' if self.hi_open else ']'}")
        if self.lo is not None:
            return f"must be {'>' if self.lo_open else '>='} {self.lo:g}"
        if self.hi is not None:
            return f"must be {'<' if self.hi_open else '<='} {self.hi:g}"
        return ""

    def check(self, value: Any, key: str) -> Any:
        """``value`` converted to this parameter's type, or :class:`SceneError` naming ``key``."""
        t = self.type
        if t is bool:
            if not isinstance(value, bool):
                raise SceneError(key, f"expected true or false, got {_tname(value)}")
            return value
        if t is int:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise SceneError(key, f"expected an integer, got {_tname(value)}")
            value = int(value)
        elif t is float:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise SceneError(key, f"expected a number, got {_tname(value)}")
            value = float(value)
            if not math.isfinite(value):
                raise SceneError(key, f"must be a finite number (got {value!r})")
        elif t is str:
            if not isinstance(value, str):
                raise SceneError(key, f"expected a string, got {_tname(value)}")
        if self.choices is not None and value not in self.choices:
            raise SceneError(key, f"{self.rule()} (got {value!r})")
        if t in (int, float):
            bad = ((self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo))
                   or (self.hi is not None and (value >= self.hi if self.hi_open else value > self.hi)))
            if bad:
                raise SceneError(key, f"{self.rule()} (got {value!r})")
        return value


@dataclass(frozen=True)
class Estimate:
    """One stage's cost: ``bytes`` of working set and ``work`` operations of ``unit``;
    ``key`` is the scene key that scales the bytes most, ``work_key`` the one that scales
    the work most (the same key unless given)."""

    stage: str
    key: str
    bytes: float
    work: float = 0.0
    unit: str = ""
    work_key: str = ""

    @property
    def work_by(self) -> str:
        """The key that scales the work."""
        return self.work_key or self.key


def costs(stage: str, memory: dict[str, float], work: dict[str, float],
          unit: str) -> list[Estimate]:
    """A pass's estimate from its cost terms: ``memory`` and ``work`` map the key that
    scales each term (a ``[render.<method>]`` key, ``camera.resolution``, ...) to its bytes
    or operations; the estimate names the key of the largest term of each, so a refusal
    names what to lower."""
    return [Estimate(stage, max(memory, key=memory.get), float(sum(memory.values())),
                     float(sum(work.values())), unit, max(work, key=work.get))]


def camera_samples(scene) -> int:
    """Camera samples of a render of ``scene`` (pixels times samples per pixel)."""
    c = scene.camera
    return int(c.width) * int(c.height) * int(c.spp)


@dataclass
class PassResult:
    """What a pass adds to the image, (H, W, 3) float32 radiance each (None: nothing).

    ``surface``: light on surfaces (surface caustics); ``medium``: light scattered in the
    medium. ``view_surface``: set only by a pass that traced view paths of its own on a
    prepared variant of the scene (the voxel pipeline with voxelised glass): their direct
    light on surfaces, which then replaces the session's view paths' surface term."""

    surface: np.ndarray | None = None
    medium: np.ndarray | None = None
    view_surface: np.ndarray | None = None

    def radiance(self) -> np.ndarray:
        """What the pass adds, surface and medium together (a pass that set
        ``view_surface`` replaces the surface term instead: that is not included)."""
        parts = [x for x in (self.surface, self.medium) if x is not None]
        if not parts:
            raise ValueError("the pass added nothing")
        return parts[0] if len(parts) == 1 else parts[0] + parts[1]


class Fallback(Exception):
    """A fast method cannot meet its bound on part of the work (a light, a set of
    segments) and hands that part to the estimator it falls back to. ``info``: what it
    measured, for ``--stats``. Raised and caught only as this type, so that a defect
    raising another exception is never mistaken for a fallback."""

    def __init__(self, message: str, info: dict | None = None):
        super().__init__(message)
        self.info = dict(info or {})


@dataclass(frozen=True)
class AutoRole:
    """A role a method can take in an ``auto`` plan: the highest ``priority`` among the
    methods that suit the scene wins. ``params`` are what the role requires (they override
    the scene's ``[render.<method>]`` values); ``defaults`` are the role's own defaults,
    which the scene's values override."""

    priority: int
    params: dict[str, Any] | None = None
    defaults: dict[str, Any] | None = None


class Method:
    """Base class of the rendering methods (see the module docstring)."""

    NAME: ClassVar[str] = ""
    PARAMS: ClassVar[tuple[Param, ...]] = ()
    TERMS: ClassVar[frozenset[str]] = frozenset()
    LIGHTS: ClassVar[frozenset[str]] = LIGHT_KINDS
    AUTO: ClassVar[dict[str, AutoRole]] = {}
    # True for a method that, once auto picks it, renders the whole image alone (it computes
    # the other terms its own way, so another pass would count light twice)
    ALONE: ClassVar[bool] = False
    # True for a method that scatters light inside dielectric objects (a material's
    # interior_sigma_s): the planner notes any other plan leaving that light out
    INTERIOR_SCATTERING: ClassVar[bool] = False
    # True for a method that renders heterogeneous media (volumes with a density grid):
    # ``auto`` passes over the others on such a scene, and the planner notes an explicit one
    DENSITY: ClassVar[bool] = False
    # True for a method that renders what a camera inside closed glass sees (its view paths
    # start in the glass, with the glass's n^2 in their throughput); ``auto`` passes over
    # the others there, and the planner notes an explicit one
    CAMERA_IN_GLASS: ClassVar[bool] = True

    def __init__(self, params: dict | None = None):
        self.params: dict[str, Any] = configure(type(self), params)

    @classmethod
    def check_params(cls, params: dict[str, Any]) -> None:
        """Rules that involve several parameters (each one's own range is in its
        :class:`Param`); raise :class:`SceneError` naming ``render.<NAME>.<key>``."""

    @classmethod
    def suits(cls, scene) -> str:
        """'' when this method's assumptions hold for ``scene`` (a :class:`Scene`), else why
        not. The default: every light's kind is in ``LIGHTS``, and the camera is in air
        unless the method handles a camera inside glass (``CAMERA_IN_GLASS``)."""
        kinds = {light.type for light in scene.lights}
        if kinds - cls.LIGHTS:
            return f"{cls.NAME} handles {', '.join(sorted(cls.LIGHTS))} lights only"
        glass = None if cls.CAMERA_IN_GLASS else scene.camera_glass()
        if glass is not None:
            return f"{cls.NAME} takes the camera to be in air; it is inside {glass.key} (glass)"
        return ""

    @classmethod
    def unreliable(cls, scene) -> str:
        """'' unless this method is expected to miss its accuracy bound on ``scene`` (a
        method that does detects it and falls back, after paying for the check): ``auto``
        then passes it over, while an explicit choice still runs it. Default: ''."""
        return ""

    @classmethod
    def estimate(cls, scene, params: dict[str, Any]) -> list:
        """Cost estimates (:class:`Estimate`) of this pass on ``scene`` with
        checked ``params``, made before anything is allocated; [] when negligible."""
        return []

    @classmethod
    def fit_memory(cls, scene, params: dict[str, Any], room: float) -> dict[str, Any]:
        """Parameter values with which this pass's estimated working set fits in ``room``
        bytes at the same result (a method that splits its work into parts it sums: a
        smaller part), or {} when none do. Default: {} (what the pass needs, it needs)."""
        return {}

    #: True when the method's progressive passes can run apart (``first_pass``/``passes``
    #: parameters; pass k's rays and radius depend on k alone) and be averaged: a cluster
    #: then splits the pass's lighting rays across workers, one task per pass
    SPLIT_PASSES: ClassVar[bool] = False

    #: True when the method refines by progressive passes run through
    #: ``ctx.progression(...)``: the session runs it after the fixed passes and gives it its
    #: share of the render's time budget (``ctx.deadline``)
    PROGRESSIVE: ClassVar[bool] = False

    #: True when a progressive method sizes each pass to the time it has (``lsg``): the
    #: session runs it after the progressive passes of a fixed size, so it gets the rest
    SIZES_PASSES: ClassVar[bool] = False

    #: for previews (a relighting page while the user drags): parameters scaled by this
    #: factor (integers rounded, at least 1) so a pass costs a fraction of its full time
    PREVIEW_SCALE: ClassVar[dict[str, float]] = {}

    @classmethod
    def preview(cls, table: dict[str, Any]) -> dict[str, Any]:
        """``table`` (a ``[render.<NAME>]`` table) for a fast preview: every parameter in
        ``PREVIEW_SCALE`` scaled (from its given or default value), the rest unchanged."""
        out = dict(table)
        defaults = {p.name: p.default for p in cls.PARAMS}
        for key, factor in cls.PREVIEW_SCALE.items():
            value = out.get(key, defaults[key]) * factor
            out[key] = max(1, int(round(value))) if isinstance(defaults[key], int) else value
        return out

    @classmethod
    def programs(cls, scene, params: dict[str, Any]) -> list[tuple[str, dict | None]]:
        """The kernel programs (name, ``-D`` defines) a render of ``scene`` with checked
        ``params`` will use: the session loads them, and creates their kernels, at start-up
        (stage ``device``) instead of at the pass's first launch. A program not listed is
        loaded when first used; one listed but not used costs its load (~10 ms). Default:
        none."""
        return []

    @classmethod
    def companions(cls, params: dict[str, Any]) -> list[str]:
        """Methods the planner runs beside this one when it is chosen explicitly, for the
        terms it leaves to them (the ray map's medium term). Default: none."""
        return []

    @classmethod
    def computes(cls, scene, params: dict) -> frozenset[str]:
        """The terms this method computes for ``scene`` with its checked ``params``: its
        ``TERMS`` (a method whose terms depend on the scene or on its parameters says so
        here; the planner's notes on light left out read this)."""
        return cls.TERMS

    def render(self, ctx: PassContext) -> PassResult:
        """What this method adds to the image (its ``TERMS``), given its
        :class:`~clscatter.transport.context.PassContext`."""
        raise NotImplementedError

    def run(self, ps, paths, stats=None, show_progress: bool = False) -> PassResult:
        """:meth:`render` on a prepared scene and its view paths outside a session (tests,
        benchmarks): a fresh context and cache, released afterwards."""
        with PassContext(ps, paths, stats if stats is not None else Stats(),
                         show_progress) as ctx:
            try:
                return self.render(ctx)
            finally:
                ctx.cache.release()


def configure(cls: type[Method], table: dict | None) -> dict[str, Any]:
    """``cls``'s parameters: defaults overlaid with ``table`` (a ``[render.<NAME>]`` table),
    each key known, typed and in range, else :class:`SceneError` naming
    ``render.<NAME>.<key>`` (with "did you mean")."""
    params = {p.name: p for p in cls.PARAMS}
    out = {name: p.default for name, p in params.items()}
    for key, value in (table or {}).items():
        where = f"render.{cls.NAME}.{key}"
        if key not in params:
            close = difflib.get_close_matches(key, list(params), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise SceneError(where, f"unknown parameter of method '{cls.NAME}'{hint}; "
                             f"allowed: {', '.join(params) or 'none'}")
        out[key] = params[key].check(value, where)
    cls.check_params(out)
    return out


def param_table(cls: type[Method]) -> str:
    """The parameter reference of ``cls`` as a Markdown table (name, type, default, range,
    meaning), generated from ``PARAMS``: the docs show exactly what the code checks."""
    rows = ["| parameter | type | default | range | meaning |", "|---|---|---|---|---|"]
    for p in cls.PARAMS:
        default = f"{p.default:_}" if p.type is int else repr(p.default) if p.type is str \
            else str(p.default).lower() if p.type is bool else f"{p.default:g}"
        rng = p.rule().replace("must be ", "") or "any"
        rows.append(f"| `{p.name}` | {p.type.__name__} | {default} | {rng} | {p.doc} |")
    return "\n".join(rows)
