"""Rendering methods, discovered from this package and registered by name.

Adding a method means adding one module (or package) here with one class decorated by
``@register`` (see :mod:`clscatter.methods.base` for what the class declares) and its
``cl_kernels/methods/<name>.cl``; nothing else names it: the scene loader keeps
``[render.<name>]`` tables raw, :func:`configure` checks them against the class's
``PARAMS`` before any device work, and the ``auto`` planner chooses by the class's declared
capabilities. A method may also live outside the package, in any importable module that
registers it (and adds its kernel folder with :func:`clscatter.device.add_kernel_dir`):
list the module in ``$CLSCATTER_METHODS`` (comma-separated) or import it before rendering.
"""
from __future__ import annotations

import difflib
import importlib
import os
import pkgutil
from typing import Any

from ..errors import SceneError
from .base import TERMS, AutoRole, Fallback, Method, Param, PassResult, param_table
from .base import configure as _configure

__all__ = ["AutoRole", "Fallback", "Method", "Param", "PassResult", "register", "available", "get_method", "configure",
           "all_methods", "param_table", "unavailable"]

#: comma-separated modules outside the package imported with it: methods they register are
#: available like the package's own
ENV_METHODS = "CLSCATTER_METHODS"

_REGISTRY: dict[str, type[Method]] = {}
_BROKEN: dict[str, str] = {}     # module name -> why it could not be imported
_LOADED = False


def register(cls: type[Method]) -> type[Method]:
    """Class decorator: make ``cls`` available under ``cls.NAME`` and append its generated
    parameter table to its docstring (the docstring is the method's user documentation)."""
    if not cls.NAME:
        raise TypeError(f"{cls.__name__} has no NAME")
    bad = (set(cls.TERMS) | set(cls.AUTO)) - set(TERMS)
    if bad or not set(cls.AUTO) <= set(cls.TERMS):
        raise TypeError(f"{cls.__name__}: unknown or undeclared terms {sorted(bad or set(cls.AUTO))}")
    if cls.PARAMS and "Parameters (generated" not in (cls.__doc__ or ""):
        cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n\n    Parameters (generated from PARAMS):\n\n" + \
            "\n".join("    " + line for line in param_table(cls).splitlines()) + "\n"
    _REGISTRY[cls.NAME] = cls
    return cls


def _load_all() -> None:
    """Import every module of this package once, so that their ``@register`` run.

    A module that cannot be imported because an optional dependency is missing is
    remembered with the reason (:func:`unavailable`), not fatal: the other methods work,
    and using this one gives a one-line error that names the dependency.
    """
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for info in pkgutil.iter_modules(__path__):
        if info.name == "base":
            continue
        try:
            importlib.import_module(f"{__name__}.{info.name}")
        except ImportError as e:
            _BROKEN[info.name] = f"needs the Python package '{e.name or e}' ({e})"
    for name in filter(None, (m.strip() for m in os.environ.get(ENV_METHODS, "").split(","))):
        try:
            importlib.import_module(name)
        except ImportError as e:
            raise SceneError(ENV_METHODS, f"cannot import method module {name!r}: {e}") from e


def all_methods() -> dict[str, type[Method]]:
    """``{name: class}`` of every method that imported."""
    _load_all()
    return dict(sorted(_REGISTRY.items()))


def available() -> list[str]:
    """Names of the methods implemented in this build (plus 'auto')."""
    return ["auto", *all_methods()]


def unavailable() -> dict[str, str]:
    """Method modules that could not be imported, with the reason."""
    _load_all()
    return dict(_BROKEN)


def get_method(name: str) -> type[Method]:
    """The method class registered as ``name`` (SceneError naming render.method if none)."""
    _load_all()
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _BROKEN:
        raise SceneError("render.method", f"method '{name}' is unavailable: {_BROKEN[name]}")
    close = difflib.get_close_matches(str(name), available(), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    raise SceneError("render.method", f"unknown method {name!r}{hint}; one of "
                     f"{', '.join(available())}")


def configure(name: str, table: dict | None) -> dict[str, Any]:
    """Checked parameters of method ``name`` from its ``[render.<name>]`` table (defaults
    filled in). An unknown key, a wrong type or a value out of range is a
    :class:`SceneError` naming ``render.<name>.<key>``."""
    _load_all()
    if name not in _REGISTRY:
        if name in _BROKEN:
            if table:
                raise SceneError(f"render.{name}", f"cannot check these parameters: method "
                                 f"'{name}' is unavailable ({_BROKEN[name]})")
            return {}
        if table is not None:
            raise SceneError(f"render.{name}", f"unknown method table [render.{name}] "
                             f"(methods: {', '.join(all_methods())})")
        return {}
    return _configure(_REGISTRY[name], table)


def check_method_param(owner: str, key: str, value: str, term: str) -> None:
    """A parameter of method ``owner`` that names another method, which must be registered
    and compute ``term`` (or be 'none'); else a :class:`SceneError` naming
    ``render.<owner>.<key>``."""
    ok = sorted(n for n, c in all_methods().items() if term in c.TERMS)
    if value != "none" and value not in ok:
        raise SceneError(f"render.{owner}.{key}", f"must be one of {', '.join(ok + ['none'])} "
                         f"(got {value!r})")


def configure_scene(scene, method: str | None = None) -> dict[str, dict[str, Any]]:
    """Check, before any device work, everything a render of ``scene`` will read from the
    methods: the requested method exists (``method`` or ``render.method``) and every
    ``[render.<name>]`` table in the scene is valid, whether or not that method runs.
    Returns ``{name: checked parameters}`` for the tables present and the requested method."""
    requested = method if method is not None else scene.render.method
    if requested != "auto":
        get_method(requested)
    out = {name: configure(name, table) for name, table in scene.render.params.items()}
    if requested != "auto" and requested not in out:
        out[requested] = configure(requested, None)
    return out


def summary(cls: type[Method]) -> str:
    """The first paragraph of ``cls``'s docstring, on one line (never cut mid-sentence)."""
    doc = (cls.__doc__ or "").strip().split("\n\n")[0]
    return " ".join(doc.split())


def methods_markdown() -> str:
    """``docs/methods.md``: every method's summary, terms, auto roles and parameter table,
    generated from the classes (``tools/write_method_docs.py`` writes it; a test checks
    that the committed file is current)."""
    out = ["# Methods", "",
           "Generated from the method classes by `tools/write_method_docs.py`; do not edit.",
           "Set parameters in the scene's `[render.<method>]` table or with",
           "`--set render.<method>.<parameter>=VALUE`. Radii and steps are relative to the",
           "longest side of the scene's bounding box.", ""]
    for name, cls in all_methods().items():
        roles = ", ".join(f"{t} (priority {r.priority})" for t, r in sorted(cls.AUTO.items()))
        out += [f"## `{name}`", "", summary(cls), "",
                f"- computes: {', '.join(sorted(cls.TERMS)) or 'nothing'}",
                f"- lights: {', '.join(sorted(cls.LIGHTS))}",
                f"- used by `auto` for: {roles or 'never (explicit only)'}", "",
                param_table(cls) if cls.PARAMS else "No parameters.", ""]
    return "\n".join(out)
