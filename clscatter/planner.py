"""``auto``: decide which passes a scene needs and skip the rest.

The medium term of an image is the sum of passes over the same view segments:

* **direct** single scattering (light straight from the lights, shadowed): by
  ``epipolar`` when every light is directional or spot (its assumptions; it falls back
  to ray marching for what it cannot do and says so), otherwise by ``raymarch``;
* **caustics** (light that reached the medium through mirrors or glass): by ``lsg``
  restricted to lighting segments with at least one specular bounce, only when the scene
  has mirror or dielectric objects.

No medium, a void medium or no lights: no medium pass at all. An explicit method runs
alone and computes what it can (``lsg`` and ``vpm``: direct light and caustics;
``raymarch`` and ``epipolar``: direct light only, which the notes say). Every decision
is recorded in ``--stats`` under ``plan``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from . import structs
from .methods import available
from .prepared import PreparedScene

DIRECT_ONLY = ("raymarch", "epipolar")


@dataclass
class Pass:
    method: str
    role: str                                     # "direct", "caustics" or "all"
    params: dict = field(default_factory=dict)    # overrides of the scene's [render.<method>]


def _has_specular(ps: PreparedScene) -> bool:
    kinds = {m.type for m in (o.material for o in ps.scene.objects)}
    return bool(kinds & {"mirror", "dielectric"})


def plan(ps: PreparedScene, requested: str) -> tuple[list[Pass], list[str]]:
    """The medium passes to run and notes on what was chosen or skipped."""
    notes: list[str] = []
    if not ps.has_medium:
        notes.append("no participating medium: medium passes skipped")
        return [], notes
    if ps.num_lights == 0:
        notes.append("no lights: medium passes skipped")
        return [], notes
    specular = _has_specular(ps)
    if requested != "auto":
        if requested in DIRECT_ONLY and specular:
            notes.append(f"{requested} computes direct light only: volumetric caustics "
                         "through mirrors/glass are not in this image")
        return [Pass(requested, "direct" if requested in DIRECT_ONLY else "all")], notes
    have = set(available())
    kinds = set(int(t) for t in ps.lights["type"])
    if "epipolar" in have and kinds <= {structs.LIGHT_SPOT, structs.LIGHT_DIRECTIONAL}:
        direct = "epipolar"
        notes.append("direct single scattering by epipolar (directional/spot lights only)")
    else:
        direct = "raymarch"
        notes.append("direct single scattering by raymarch")
    passes = [Pass(direct, "direct")]
    if specular:
        if "lsg" in have:
            passes.append(Pass("lsg", "caustics", {"min_light_depth": 1}))
            notes.append("volumetric caustics by lsg (lighting segments after >= 1 specular bounce)")
        else:
            notes.append("scene has mirrors/glass but no caustic method is available")
    else:
        notes.append("no mirrors or glass: caustic pass skipped")
    return passes, notes
