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
from .base import AutoRole, Method, Param, configure as _configure, param_table

__all__ = ["AutoRole", "Method", "Param", "register", "available", "get_method", "configure",
           "all_methods", "param_table", "unavailable"]

_REGISTRY: dict[str, type[Method]] = {}
_BROKEN: dict[str, str] = {}     # module name -> why it could not be imported
_LOADED = False


def register(cls: type[Method]) -> type[Method]:
    """Class decorator: make ``cls`` available under ``cls.NAME``."""
    if not cls.NAME:
        raise TypeError(f"{cls.__name__} has no NAME")
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
