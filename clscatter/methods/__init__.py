"""Rendering methods, discovered from this package and registered by name.

Adding a method means adding one module (or package) here with one class decorated by
``@register`` (see :mod:`clscatter.methods.base` for what the class declares) and its
``cl_kernels/<name>.cl``; nothing else names it: the scene loader keeps ``[render.<name>]``
tables raw, :func:`configure` checks them against the class's ``PARAMS`` before any device
work, and the ``auto`` planner chooses by the class's declared capabilities.
"""
from __future__ import annotations

import importlib
import pkgutil
from typing import Any

from ..errors import SceneError
from ..scene.model import METHOD_NAMES
from .base import TERMS, AutoRole, Method, Param, configure as _configure, param_table

__all__ = ["AutoRole", "Method", "Param", "register", "available", "get_method", "configure",
           "all_methods", "param_table", "unavailable"]

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
    if name in METHOD_NAMES:
        raise SceneError("render.method", f"method '{name}' is not implemented in this version "
                         f"(available: {', '.join(available())})")
    raise SceneError("render.method", f"unknown method {name!r} (one of {', '.join(METHOD_NAMES)})")


def configure(name: str, table: dict | None) -> dict[str, Any]:
    """Checked parameters of method ``name`` from its ``[render.<name>]`` table (defaults
    filled in). An unknown key, a wrong type or a value out of range is a
    :class:`SceneError` naming ``render.<name>.<key>``."""
    _load_all()
    if name not in _REGISTRY:
        if table and name in _BROKEN:
            raise SceneError(f"render.{name}", f"cannot check these parameters: method "
                             f"'{name}' is unavailable ({_BROKEN[name]})")
        if table and name in METHOD_NAMES:
            raise SceneError(f"render.{name}", f"method '{name}' is not implemented in this "
                             f"version, so its parameters cannot be used")
        return dict(table or {})
    return _configure(_REGISTRY[name], table)


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
        doc = (cls.__doc__ or "").strip().splitlines()
        roles = ", ".join(f"{t} (priority {r.priority})" for t, r in sorted(cls.AUTO.items()))
        out += [f"## `{name}`", "", doc[0] if doc else "", "",
                f"- computes: {', '.join(sorted(cls.TERMS)) or 'nothing'}",
                f"- lights: {', '.join(sorted(cls.LIGHTS))}",
                f"- used by `auto` for: {roles or 'never (explicit only)'}", "",
                param_table(cls) if cls.PARAMS else "No parameters.", ""]
    return "\n".join(out)
