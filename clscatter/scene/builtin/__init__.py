"""Built-in scenes, generated in code as dicts in exactly the TOML schema of
docs/scene_format.md, one module per family (no module imports another but ``parts``):

==================  ======================================================================
``basic``           the demo (``shafts``), ``occluder``, ``spotlight``, ``glass``, ``airlight``
``caustics``        glass ball, gem, torus, mirror dish, metaball blob (``caustic_*``)
``epipolar``        scenes of rising shadow complexity and the weak-spot sweeps (``epi_*``)
``volumes``         graded-index volumes for the voxel pipeline (``volume_*``)
``smoke``           heterogeneous media: a density grid (``smoke_plume``)
``paper``           the LSG paper's scale: a 69k-triangle glass bunny (``paper_bunny``)
==================  ======================================================================

``load_scene("builtin:NAME")`` validates them through the same ``scene_from_dict`` as a
file; ``builtin_toml(NAME)`` writes one out as a TOML file to start from.
"""
from __future__ import annotations

from typing import Callable

from .basic import BASIC_SCENES
from .caustics import CAUSTIC_SCENES
from .epipolar import EPIPOLAR_SCENES
from .paper import PAPER_SCENES
from .smoke import SMOKE_SCENES
from .toml_writer import to_toml
from .volumes import VOLUME_SCENES

DEFAULT_BUILTIN = "shafts"

BUILTIN: dict[str, Callable[[], dict]] = {**BASIC_SCENES, **CAUSTIC_SCENES, **EPIPOLAR_SCENES,
                                          **VOLUME_SCENES, **SMOKE_SCENES, **PAPER_SCENES}


def builtin_toml(name: str) -> str:
    """The built-in scene ``name`` as the text of a TOML scene file."""
    from ...errors import SceneError

    if name not in BUILTIN:
        raise SceneError(f"builtin:{name}", f"unknown built-in scene (one of {', '.join(BUILTIN)})")
    return f"# clscatter built-in scene '{name}'\n" + to_toml(BUILTIN[name]())


__all__ = ["BUILTIN", "DEFAULT_BUILTIN", "builtin_toml", "to_toml"]
