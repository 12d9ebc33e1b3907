"""Rendering methods, registered by name.

A method computes the medium's single scattering (and, for the caustic methods, light
carried by specular chains) for the view segments the path tracer produced. Each
method is one module with one class; the class docstring is its user documentation,
``PARAMS`` maps every ``[render.<name>]`` key to its documented default.

Register a method with ``@register``; ``get_method(name)`` finds it. The scene loader
checks ``[render.<name>]`` keys against :func:`method_params`.
"""
from __future__ import annotations

import importlib
from typing import Any

from ..errors import SceneError

# every method name the scene format reserves (SCENE_FORMAT.md, render.method)
CONTRACT_METHODS = ("auto", "lsg", "epipolar", "voxel", "raymarch", "vpm", "raymap", "photonmap")

# modules imported to populate the registry; a method whose module does not exist yet
# is simply absent (its name is still reserved)
_MODULES = ("raymarch", "lsg", "vpm", "epipolar")

_REGISTRY: dict[str, type] = {}


def register(cls: type) -> type:
    """Class decorator: make ``cls`` available under ``cls.NAME``."""
    _REGISTRY[cls.NAME] = cls
    return cls


def _load_all() -> None:
    for m in _MODULES:
        name = f"{__name__}.{m}"
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:  # a real missing dependency inside the module: report it
                raise


def available() -> list[str]:
    """Names of the methods implemented in this build (plus 'auto')."""
    _load_all()
    return ["auto", *sorted(_REGISTRY)]


def method_params() -> dict[str, dict[str, Any]]:
    """``{method name: {parameter: default}}`` for every implemented method."""
    _load_all()
    return {name: dict(cls.PARAMS) for name, cls in _REGISTRY.items()}


def get_method(name: str) -> type:
    """The method class registered as ``name`` (SceneError naming render.method if none)."""
    _load_all()
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in CONTRACT_METHODS:
        raise SceneError("render.method", f"method '{name}' is not implemented in this version "
                         f"(available: {', '.join(available())})")
    raise SceneError("render.method", f"unknown method '{name}' (one of {', '.join(CONTRACT_METHODS)})")


def settings(cls: type, params: dict | None) -> dict[str, Any]:
    """``cls.PARAMS`` overlaid with the scene's ``[render.<name>]`` values (the loader has
    already checked keys and types; :func:`check` validates ranges)."""
    p = dict(cls.PARAMS)
    p.update(params or {})
    return p


def check(cls: type, p: dict, checks) -> None:
    """Raise ``SceneError("render.<NAME>.<key>", "<rule> (got <value>)")`` for the first
    ``(key, ok, rule)`` in ``checks`` whose ``ok`` is false."""
    for key, ok, rule in checks:
        if not ok:
            raise SceneError(f"render.{cls.NAME}.{key}", f"{rule} (got {p.get(key)!r})")
