"""The public Python API: ``load`` a scene, ``render`` it, ``write`` the result, and keep a
warm :class:`Session` whose parameters can be edited and re-rendered.

.. code-block:: python

    import clscatter

    scene = clscatter.load("builtin:caustic_sphere")     # TOML path, dict, or "builtin:NAME"
    result = clscatter.render(scene, method="auto")       # RenderResult
    clscatter.write(result, "sphere.exr", "sphere.png")   # all or nothing

    with clscatter.Session(scene) as session:
        params = session.params                           # {"lights[0].position": [...], ...}
        params["lights[0].position"] = [0.5, 3.0, 0.0]
        session.update(params)                            # applies the changed keys only
        result = session.render()                         # re-runs only what the change needs

Design
------
A scene is kept in two forms. The *raw data* is a dict in the scene format
(``docs/scene_format.md``: the TOML file parsed, with the format's own key names, e.g. a
light's ``intensity`` and a spot light's ``target``); the *validated* :class:`Scene` is what
the loader builds from it (where some keys are renamed or derived: ``Light.power``,
``Light.direction``). :func:`load` returns a :class:`SceneSpec` holding both, plus the
folder that relative mesh and grid paths resolve against and a name for messages. The
raw data is the source of truth: :class:`Session` edits it by dotted key, exactly as
``--set`` names keys, and builds a new :class:`Scene` from it, so its parameter names are
always the format's.

:class:`Session` is a thin layer over :class:`~clscatter.pipeline.session.RenderSession`
(which does the warm re-rendering): it turns a mapping of changed keys into a new validated
scene and hands that over.

Errors the user can fix are :class:`~clscatter.errors.ClscatterError`: a bad scene, key or
value is a :class:`~clscatter.errors.SceneError` whose one-line message starts with the
dotted key (``e.key``); an output that cannot be written is named by its path.

This module imports the scene loader (NumPy) but not OpenCL: the device is started by the
first :func:`render` or :meth:`Session.render`.
"""
from __future__ import annotations

import copy
import logging
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union

import numpy as np

from .errors import ClscatterError, SceneError
from .scene.loader import apply_overrides, parse_override, scene_from_dict, scene_source
from .scene.model import Scene

if TYPE_CHECKING:  # the pipeline imports the device (OpenCL): only when rendering
    from .device import Engine
    from .pipeline.render import RenderResult
    from .pipeline.session import RenderSession

__all__ = ["IMAGE_SUFFIXES", "SceneSpec", "Session", "load", "render", "write"]

#: Output formats :func:`write` accepts: linear ``.exr``, ``.npy``, ``.pfm``; tone-mapped
#: ``.png`` (see :mod:`clscatter.io.image`).
IMAGE_SUFFIXES = (".exr", ".npy", ".pfm", ".png")

_log = logging.getLogger("clscatter")

#: What :func:`load` accepts: a SceneSpec, a TOML path, ``"builtin:NAME"`` or a dict in the
#: scene format.
SceneLike = Union["SceneSpec", str, "os.PathLike[str]", Mapping[str, Any]]


def _log_note(line: str) -> None:
    """The default ``on_note``: a one-line note for the user, logged as a warning on the
    ``clscatter`` logger (printed to stderr when logging is not configured)."""
    _log.warning(line)


# ---- scenes ---------------------------------------------------------------------------------

class SceneSpec:
    """A validated scene together with the raw data it was built from.

    ``data``
        the scene as a dict in the scene format (a deep copy on every access: edit it and
        :func:`load` the result, or use a :class:`Session`);
    ``base_dir``
        the folder relative mesh and grid paths are resolved against (made absolute);
    ``source``
        a name for messages (the path, ``builtin:NAME`` or ``<dict>``);
    ``scene``
        the validated :class:`~clscatter.scene.model.Scene` built from ``data``.

    A SceneSpec is *Scene-like*: reading an attribute it does not define reads it from
    ``scene`` (``spec.camera.width``, ``spec.lights``, ``spec.bbox()``). Its attributes are
    read-only: a changed scene is a new SceneSpec (:func:`load` one from this one with
    overrides, or use a :class:`Session`). Building one validates the data (:class:`SceneError` naming the
    dotted key of the first problem); method names and ``[render.<method>]`` tables are
    checked when a render or a session is asked for, before any device work.
    """

    __slots__ = ("_base_dir", "_data", "_scene", "_source")

    def __init__(self, data: Mapping[str, Any], base_dir: str | os.PathLike[str] = ".",
                 source: str = "<dict>") -> None:
        if not isinstance(data, Mapping):
            raise TypeError(f"scene data must be a dict in the scene format, not "
                            f"{type(data).__name__}")
        plain = _plain(dict(data), "")
        base = Path(base_dir).absolute()     # later edits resolve paths as now
        scene = scene_from_dict(plain, base, source)
        self._data = plain
        self._base_dir = base
        self._source = source
        self._scene = scene

    @property
    def data(self) -> dict[str, Any]:
        """The raw scene data (a deep copy: changing it changes nothing here)."""
        return copy.deepcopy(self._data)

    @property
    def base_dir(self) -> Path:
        """The absolute folder relative mesh and grid paths resolve against."""
        return self._base_dir

    @property
    def source(self) -> str:
        """A name for messages: the path, ``builtin:NAME`` or ``<dict>``."""
        return self._source

    @property
    def scene(self) -> Scene:
        """The validated scene built from :attr:`data`."""
        return self._scene

    def __getattr__(self, name: str) -> Any:
        # only reached for names not defined here; never for private names (copy, pickle)
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.scene, name)

    def __repr__(self) -> str:
        cam = self.scene.camera
        return (f"SceneSpec({self.source!r}, {cam.width}x{cam.height}, "
                f"{len(self.scene.objects)} objects, {len(self.scene.lights)} lights)")


def load(spec: SceneLike, overrides: Sequence[str] = (), *,
         base_dir: str | os.PathLike[str] | None = None) -> SceneSpec:
    """Load and validate a scene.

    ``spec`` is a TOML file path, a Mitsuba 3 XML file path, ``"builtin:NAME"``
    (``clscatter scenes`` lists them), a dict in the scene format, a Mitsuba-style scene
    dict (what ``mi.load_dict`` takes: ``"type": "scene"`` at its top), or a
    :class:`SceneSpec` (to derive a new one from). A Mitsuba scene's conversion notes
    (what was approximated or dropped, docs/mitsuba.md) are logged as warnings on the
    ``clscatter`` logger, as render notes are.
    ``overrides`` are ``--set``-style ``"key=value"`` strings (TOML values) applied in order
    before validation, e.g. ``["camera.resolution=[64,48]", "render.lsg.light_rays=100000"]``.
    ``base_dir`` is the folder relative mesh and grid paths resolve against (default: the
    TOML file's folder; the current folder for a built-in or a dict; a SceneSpec's own).
    The input is never modified. Raises :class:`SceneError` naming the dotted key (or the
    file) of the first problem.
    """
    if isinstance(overrides, str):
        raise TypeError("overrides must be a sequence of 'key=value' strings, not one string")
    if isinstance(spec, SceneSpec):
        data, folder, source = spec._data, spec.base_dir, spec.source   # copied below
    elif isinstance(spec, Mapping) and spec.get("type") == "scene":
        from .scene.mitsuba_in import from_mitsuba
        data, notes = from_mitsuba(spec)
        for line in notes:
            _log_note(line)
        folder, source = Path.cwd(), "<mitsuba dict>"
    elif isinstance(spec, Mapping):
        data, folder, source = dict(spec), Path.cwd(), "<dict>"
    elif isinstance(spec, (str, os.PathLike)):
        data, folder = scene_source(os.fspath(spec), on_note=_log_note)
        source = os.fspath(spec)
    elif isinstance(spec, Scene):
        raise TypeError("load needs a path, 'builtin:NAME', a dict or a SceneSpec; a Scene "
                        "object has no raw data to load")
    else:
        raise TypeError(f"cannot load a scene from {type(spec).__name__}")
    data = apply_overrides(_plain(data, ""), list(overrides))
    return SceneSpec(data, folder if base_dir is None else base_dir, source)


# ---- one-off render and outputs ---------------------------------------------------------------

def render(scene: SceneSpec | Scene | SceneLike, method: str | None = None, *,
           engine: Engine | None = None, device: str | None = None,
           max_memory: float | None = None, show_progress: bool = False,
           on_note: Callable[[str], None] | None = _log_note) -> RenderResult:
    """Render ``scene`` once and return the :class:`~clscatter.pipeline.render.RenderResult`.

    ``scene`` is a :class:`SceneSpec`, a validated :class:`~clscatter.scene.model.Scene`, or
    anything :func:`load` accepts. ``method`` is a method name or ``"auto"`` (default: the
    scene's ``render.method``). ``device`` picks the OpenCL device (``"P:D"`` or a name
    substring; default the ``CLSCATTER_DEVICE`` environment variable, then the first
    device), or ``engine`` passes one already made. A render whose estimated peak memory
    exceeds ``max_memory`` bytes (default: the device's and the machine's) is refused before
    anything is allocated. ``on_note`` receives one-line notes (long work, light a plan
    leaves out, dropped triangles, float32 overflow); by default they are logged as warnings
    on the ``clscatter`` logger; ``None`` drops them.

    The result's ``image`` is ``(H, W, 3)`` float32 linear radiance, ``surface`` and
    ``medium`` its two parts, and ``stats`` what ``--stats`` writes (``stats["method"]``
    names the methods that ran). Raises :class:`ClscatterError` (a :class:`SceneError` for a
    bad method or parameter) before any device work.
    """
    from .pipeline.render import render as _render

    if not isinstance(scene, Scene):
        scene = scene.scene if isinstance(scene, SceneSpec) else load(scene).scene
    return _render(scene, method, engine=engine, device=device, show_progress=show_progress,
                   max_memory=max_memory, on_note=on_note)


def write(result: RenderResult | np.ndarray, *paths: str | os.PathLike[str],
          exposure: float = 0.0) -> list[Path]:
    """Write a render's image (a :class:`RenderResult` or an ``(H, W, 3)`` array) to every
    path in ``paths``; returns them as Paths.

    The format follows each suffix: ``.exr``, ``.npy``, ``.pfm`` store linear float32
    values unchanged; ``.png`` is 8-bit sRGB tone-mapped after scaling by
    ``2**exposure``. All or nothing, as the command line writes ``-o``: every path is
    checked first (known suffix, existing writable folder, not a folder, not given twice),
    then each file is written to a hidden staging name beside it and all are renamed into
    place only when every one was written; on any failure no destination is created or
    changed. Raises :class:`ClscatterError` naming the path.
    """
    from .io.image import write_image
    from .io.outputs import check_output, write_all

    if not paths:
        raise TypeError("write needs at least one output path")
    if not math.isfinite(exposure):
        raise ValueError(f"exposure must be a finite number of stops (got {exposure!r})")
    image = getattr(result, "image", result)
    outputs = [check_output(p, IMAGE_SUFFIXES, "clscatter.write") for p in paths]
    seen: set[Path] = set()
    for p in outputs:
        if p.resolve() in seen:
            raise ClscatterError(f"{p}: the same file is given twice as output")
        seen.add(p.resolve())
    write_all([(p, lambda tmp: write_image(tmp, image, exposure=exposure)) for p in outputs])
    return outputs


# ---- warm session -----------------------------------------------------------------------------

class Session:
    """A scene kept prepared on a device and re-rendered after changes (warm).

    ``scene`` is a :class:`SceneSpec` or anything :func:`load` accepts (a bare validated
    ``Scene`` is refused: the session edits the raw data). ``method``, ``engine``,
    ``device``, ``max_memory`` and ``on_note`` are as for :func:`render`; ``show_progress``
    shows progress bars. The method name and every ``[render.<method>]`` table are checked
    here, before any device work (:class:`SceneError`).

    :attr:`params` is the scene as a flat dict of dotted keys; :meth:`update` applies the
    keys that changed; :meth:`render` re-runs only what they invalidate (a light move
    re-uploads the light and re-shades recorded hits, the BVH is kept: ``stats["reused"]``
    and ``stats["stages_run"]`` say what). A warm render equals a fresh :func:`render` of
    the same scene. :meth:`close` (or leaving a ``with`` block) frees the device buffers;
    the session can still render afterwards, preparing anew.

    The work is done by a :class:`~clscatter.pipeline.session.RenderSession`; this class
    only keeps the raw data and turns key changes into a new validated scene for it.
    """

    def __init__(self, scene: SceneSpec | SceneLike, method: str | None = None, *,
                 engine: Engine | None = None, device: str | None = None,
                 max_memory: float | None = None, show_progress: bool = False,
                 on_note: Callable[[str], None] | None = _log_note) -> None:
        from .pipeline.render import check
        from .pipeline.session import RenderSession

        if isinstance(scene, Scene):
            raise TypeError("Session needs a scene from clscatter.load (or a path, "
                            "'builtin:NAME' or dict): a bare Scene has no raw data to edit")
        spec = scene if isinstance(scene, SceneSpec) else load(scene)
        check(spec.scene, method)
        self._spec = spec
        self._method = method
        self._show_progress = show_progress
        self._on_note = on_note
        self._session: RenderSession = RenderSession(spec.scene, method, engine=engine,
                                                     device=device, max_memory=max_memory)

    @property
    def scene(self) -> SceneSpec:
        """The current scene (raw data and validated scene), every update applied."""
        return self._spec

    @property
    def method(self) -> str | None:
        """The method the session renders with (``None``: the scene's ``render.method``)."""
        return self._method

    @property
    def params(self) -> dict[str, Any]:
        """The scene's parameters as a new dict ``{dotted key: value}`` (a copy: edit it and
        pass it to :meth:`update`).

        Keys are named exactly as ``--set`` names them: ``camera.fov``,
        ``lights[0].position``, ``materials.glass.ior``, ``objects[1].transform.scale``,
        ``render.lsg.light_rays``. They are every value in the raw data (vectors and colours
        are one value each), then what the data leaves to defaults: the camera's ``up``,
        ``fov``, ``fov_axis``, ``resolution`` and ``spp``, ``render.method``, ``max_depth``
        and ``seed``, and every parameter of every available method under
        ``render.<method>.<name>`` with its declared default (``clscatter.methods``
        ``PARAMS``; an ``auto`` plan may use its own default where the scene sets none).
        Values are plain Python (numbers, strings, booleans, lists).
        """
        return _params(self._spec)

    def update(self, changes: Mapping[str, Any]) -> list[str]:
        """Apply the keys of ``changes`` whose values differ from :attr:`params`; return
        those keys, in order (an empty list: nothing changed, nothing is re-rendered).

        Values are typed (``[0.5, 3.0, 0.0]``, ``1.33``, ``"lsg"``, ``True``); NumPy arrays
        and scalars, tuples and paths are accepted and stored as lists, numbers and
        strings. A key that is not in :attr:`params` is set where ``--set`` would set it
        (``camera.fov`` on a scene that leaves it to the default; an index equal to an
        array's length appends a table) and must be one the format knows. The changed
        scene is validated exactly as the command line validates it (loader, method name
        and parameters); on any error — an unknown key, a wrong type or value — a one-line
        :class:`SceneError` naming the key is raised and the session is left as it was.
        """
        if not isinstance(changes, Mapping):
            raise TypeError(f"update needs a mapping of dotted keys to values, not "
                            f"{type(changes).__name__}")
        from .pipeline.render import check

        current = self.params
        data = self._spec._data
        applied: list[str] = []
        try:
            for key, value in changes.items():
                if not isinstance(key, str):
                    raise TypeError(f"parameter keys are dotted strings, not "
                                    f"{type(key).__name__}")
                value = _plain(value, key)
                if key in current and _same(current[key], value):
                    continue
                applied.append(key)
                data = _assign(data, key, value)
            if not applied:
                return []
            spec = SceneSpec(data, self._spec.base_dir, self._spec.source)
            check(spec.scene, self._method)
        except SceneError as e:
            renamed = _named_by(e, applied)
            if renamed is e:
                raise
            raise renamed from None
        self._spec = spec
        self._session.update(spec.scene)
        return applied

    def render(self, *, preview: bool = False,
               cancel: Callable[[], bool] | None = None) -> RenderResult:
        """Render the current scene, re-running only what changed since the last render
        (the first render prepares everything). ``preview`` renders at a quarter of the
        resolution with one sample per pixel; ``cancel()`` is polled between stages and
        stops the render with :class:`~clscatter.pipeline.session.Cancelled`. Returns a
        :class:`RenderResult` as :func:`render` does."""
        return self._session.render(show_progress=self._show_progress, cancel=cancel,
                                    on_note=self._on_note, preview=preview)

    def close(self) -> None:
        """Free the device buffers the session holds (it can still render: anew)."""
        self._session.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Session({self._spec!r}, method={self._method!r})"


# ---- helpers ----------------------------------------------------------------------------------

def _plain(value: Any, key: str) -> Any:
    """``value`` as the plain data the scene format holds: NumPy arrays and scalars to
    lists and Python numbers, tuples to lists, paths to strings, mappings to dicts (copies
    throughout). ``None`` is refused (the format has no null)."""
    if value is None:
        raise SceneError(key, "expected a value, got None (the scene format has no null)")
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v, key) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def _same(a: Any, b: Any) -> bool:
    """Equal values of the same kinds (``1`` and ``1.0`` are the same number; ``True`` is
    not ``1``)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, dict)) or isinstance(b, (list, dict)):
        return False
    return a == b


def _assign(data: dict, key: str, value: Any) -> dict:
    """A copy of ``data`` with ``value`` at the dotted ``key``. The path is walked (and
    missing tables created) by the loader's own ``--set`` code, so keys mean and fail
    exactly as on the command line."""
    if "=" in key:
        raise SceneError(key, "bad key (expected a dotted path like lights[0].position)")
    tokens, _ = parse_override(f"{key}=0")
    data = apply_overrides(data, [f"{key}=0"])    # creates the path; errors name the key
    node: Any = data
    for tok in tokens[:-1]:
        node = node[int(tok)] if isinstance(node, list) else node[tok]
    last = tokens[-1]
    node[int(last) if isinstance(node, list) else last] = value
    return data


def _path(key: str) -> list[str]:
    """The tokens of a dotted key (``lights[0].position`` -> ``lights, 0, position``)."""
    return [t.strip() for t in re.sub(r"\[\s*(\d+)\s*\]", r".\1", key).split(".")]


def _named_by(error: SceneError, keys: Sequence[str]) -> SceneError:
    """``error`` renamed after the first of ``keys`` (the keys an update set) that lies
    under the key it names: the loader names the first part of a path it rejects (``foo``
    for ``foo.bar``, ``lights[4]`` for ``lights[4].position``, ``camera.fov`` for
    ``camera.fov.x``); the user is told the key they gave, then the loader's message.
    ``error`` itself when it names a key given or no key lies under its key."""
    where = _path(error.key)
    paths = [(key, _path(key)) for key in keys]
    if any(path == where for _, path in paths):
        return error
    for key, path in paths:
        if len(path) > len(where) and path[:len(where)] == where:
            return SceneError(key, str(error))
    return error


def _flatten(node: Any, prefix: str, out: dict[str, Any]) -> None:
    """Every value of the raw data ``node`` under its ``--set`` key: tables are walked
    (``a.b``), arrays of tables indexed (``a[0].b``); anything else (numbers, strings,
    vectors, colours, empty arrays) is one value. Empty tables hold nothing."""
    for name, value in node.items():
        key = f"{prefix}.{name}" if prefix else str(name)
        if isinstance(value, dict):
            _flatten(value, key, out)
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, item in enumerate(value):
                _flatten(item, f"{key}[{i}]", out)
        else:
            out[key] = copy.deepcopy(value)


def _params(spec: SceneSpec) -> dict[str, Any]:
    """:attr:`Session.params` of ``spec`` (see there)."""
    from .methods import all_methods

    out: dict[str, Any] = {}
    _flatten(spec._data, "", out)
    cam, settings = spec.scene.camera, spec.scene.render
    defaults = {
        "camera.up": [float(x) for x in cam.up],
        "camera.fov": float(cam.fov),
        "camera.fov_axis": cam.fov_axis,
        "camera.resolution": [int(cam.width), int(cam.height)],
        "camera.spp": int(cam.spp),
        "render.method": settings.method,
        "render.max_depth": int(settings.max_depth),
        "render.seed": int(settings.seed),
    }
    for name, cls in all_methods().items():
        for p in cls.PARAMS:
            defaults[f"render.{name}.{p.name}"] = copy.deepcopy(p.default)
    for key, value in defaults.items():
        out.setdefault(key, value)
    return out
