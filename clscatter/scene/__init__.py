"""Scenes: the model (dataclasses), the TOML loader with validation, shapes, built-ins.

``load_scene("scene.toml", ["render.lsg.radius=0.0005"])`` or
``load_scene("builtin:shafts")`` gives a validated :class:`Scene`; every problem is a
:class:`~clscatter.errors.SceneError` naming the dotted key (see ``loader.py``).
"""
from .builtin import BUILTIN, DEFAULT_BUILTIN, builtin_toml
from .loader import (
    apply_overrides,
    load_scene,
    read_toml,
    scene_from_dict,
    scene_source,
)
from .model import (
    Camera,
    Light,
    Material,
    Medium,
    Object,
    RenderSettings,
    Scene,
    Volume,
)

__all__ = [
    "BUILTIN", "DEFAULT_BUILTIN", "builtin_toml",
    "apply_overrides", "load_scene", "read_toml", "scene_from_dict", "scene_source",
    "Camera", "Light", "Material", "Medium", "Object", "RenderSettings", "Scene", "Volume",
]
