"""``auto``: decide which passes a scene needs, from the scene alone, and skip the rest.

An image is the surface term of the view paths plus passes that each compute one *term*
(:mod:`clscatter.methods.base`):

========================  ==================================================================
term                      needed when the scene has
========================  ==================================================================
``direct``                a (non-void) medium, or a density volume, and lights
``caustics``              a medium, lights and mirror or glass objects; or lights and glass
                          that scatters inside (``interior_sigma_s``: all light inside glass
                          came through its surface, so it is caustic light)
``surface_caustics``      lights, mirror or glass objects and diffuse objects
``volumes``               ``[[volumes]]`` with a shape or an index grid (graded index:
                          nothing else bends rays), or glass that scatters inside in a scene
                          with density volumes (the voxel pipeline renders both)
========================  ==================================================================

Scattering inside glass is rendered by the methods that declare ``INTERIOR_SCATTERING``
(``lsg``, which ``auto`` runs for the caustics, and ``voxel``, which ``auto`` runs where
the scene needs it anyway: graded-index volumes); any plan without one gets one note that
the light is left out, and a plan whose method does not model ``interior_g`` (one without
``INTERIOR_PHASE``) one note that it is approximated.

A scene with density volumes (heterogeneous media) is rendered only by methods that
declare ``DENSITY``: ``auto`` passes over the others, and a plan without one gets a note.

For every needed term the planner takes, among the implemented methods that declare an
``AUTO`` role for it, whose assumptions hold for the scene (``Method.suits``) and which
is not expected to miss its accuracy bound there (``Method.unreliable``), the one with
the highest priority; no method name is written here. An explicit method runs alone
and computes its ``TERMS``; the notes say which needed terms that leaves out. A method
that declares ``ALONE`` (the voxel pipeline) replaces every other pass once it is chosen.
Every decision is recorded in ``--stats`` under ``plan``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..methods import all_methods, configure
from ..scene.model import Scene

#: the ending of every plan note that says light the scene needs is left out of the image
#: (``render`` prints those notes; :func:`dropped_light` picks them out)
DROPS_LIGHT = "that light is not in this image"
#: the ending of a plan note that says light is rendered with a simpler model than the
#: scene asks for (``render`` prints those too)
APPROXIMATES = "that light is approximated"


@dataclass
class Pass:
    method: str
    role: str                                     # a term, or "all" for an explicit method
    params: dict = field(default_factory=dict)    # required: override [render.<method>]
    defaults: dict = field(default_factory=dict)  # the role's defaults: [render.<method>] wins

    def table(self, scene: Scene) -> dict:
        """The parameter table this pass runs with: role defaults, then the scene's
        ``[render.<method>]`` values, then what the role requires."""
        return {**self.defaults, **(scene.render.params.get(self.method) or {}), **self.params}


def needed_terms(scene: Scene) -> tuple[list[str], list[str]]:
    """The terms ``scene`` needs, and notes on the ones it does not."""
    notes: list[str] = []
    kinds = {o.material.type for o in scene.objects}
    specular = bool(kinds & {"mirror", "dielectric"})
    lights = bool(scene.lights)
    medium = scene.has_medium() or bool(scene.density_volumes())
    inside = bool(scene.scatters_inside_glass())
    terms: list[str] = []
    if not lights:
        notes.append("no lights: no light-carrying pass")
        return terms, notes
    if medium:
        terms.append("direct")
        if specular:
            terms.append("caustics")
        else:
            notes.append("no mirrors or glass: caustic pass skipped")
    else:
        if inside:
            terms.append("caustics")   # light refracted into glass that scatters inside
        notes.append("no participating medium: medium passes skipped"
                     + (" (but for the light scattered inside glass)" if inside else ""))
    if specular and "diffuse" in kinds:
        terms.append("surface_caustics")
    if any(v.refracts for v in scene.volumes) or (inside and scene.density_volumes()):
        terms.append("volumes")        # light bent by volumes (or glass among density grids)
    return terms, notes


def plan(scene: Scene, requested: str) -> tuple[list[Pass], list[str]]:
    """The passes to run for ``scene`` with ``requested`` ('auto' or a method name), and
    notes on what was chosen or skipped (a note ending in :data:`DROPS_LIGHT` for light
    the scene has and the plan leaves out)."""
    passes, notes = _plan(scene, requested)
    return passes, (notes + interior_scattering_note(scene, passes) + density_note(scene, passes)
                    + camera_glass_note(scene, passes))


def _plan(scene: Scene, requested: str) -> tuple[list[Pass], list[str]]:
    terms, notes = needed_terms(scene)
    methods = all_methods()
    if requested != "auto":
        return _explicit(scene, requested, terms, notes)
    passes: list[Pass] = []
    uncovered: list[str] = []                     # terms no candidate computes
    for term in terms:
        candidates = []
        for name, cls in methods.items():
            role = cls.AUTO.get(term)
            if role is None:
                continue
            why_not = cls.suits(scene) or cls.unreliable(scene) or _no_density(cls, scene)
            if why_not:
                notes.append(f"{term}: not {name} ({why_not})")
                continue
            candidates.append((role.priority, name, role))
        if not candidates:
            uncovered.append(term)
            continue
        _, name, role = max(candidates)
        passes.append(Pass(name, term, dict(role.params or {}), dict(role.defaults or {})))
        extra = ", ".join(f"{k} = {v}" for k, v in {**(role.defaults or {}),
                                                    **(role.params or {})}.items())
        notes.append(f"{term} by {name}" + (f" ({extra})" if extra else ""))
    alone = next((p for p in passes if methods[p.method].ALONE), None)
    if alone is not None:        # it computes the terms its own way (Method.computes), and
        computed = methods[alone.method].computes(scene, configure(alone.method,
                                                                   alone.table(scene)))
        uncovered = [t for t in terms if t not in computed]     # the others' passes go
    why = (f"{alone.method}, which renders the whole image alone, does not compute it"
           if alone is not None else "no available method computes it")
    notes += [f"scene needs {t} but {why}: {DROPS_LIGHT}" for t in uncovered]
    if alone is not None:
        others = [f"{q.role} by {q.method}" for q in passes if q is not alone]
        notes.append(f"{alone.method} renders the whole image alone"
                     + (f" (instead of {', '.join(others)})" if others else ""))
        return [Pass(alone.method, "all", alone.params, alone.defaults)], notes
    return passes, notes


def _explicit(scene: Scene, requested: str, terms: list[str],
              notes: list[str]) -> tuple[list[Pass], list[str]]:
    """The passes of an explicitly requested method: the method, and the methods it asks
    to run beside it for the terms it leaves to them (:meth:`Method.companions`)."""
    methods = all_methods()
    cls = methods[requested]
    if not terms:
        return [], notes
    params = configure(requested, scene.render.params.get(requested))
    companions = [c for c in cls.companions(params)
                  if methods[c].TERMS & set(terms)]      # only for terms the scene needs
    computed = set(cls.computes(scene, params)).union(*(methods[c].TERMS for c in companions))
    names = "+".join([requested, *companions])
    missing = [t for t in terms if t not in computed]
    if len(missing) == len(terms):
        notes.append(f"{names} computes {', '.join(sorted(computed))}, which this scene "
                     f"does not need ({', '.join(terms)}): nothing to run, {DROPS_LIGHT}")
        return [], notes
    if missing:
        notes.append(f"{names} does not compute {', '.join(missing)}: {DROPS_LIGHT}")
    for c in companions:
        notes.append(f"{requested} runs {c} beside it for the medium "
                     f"(render.{requested}.medium)")
    return [Pass(requested, "all")] + [Pass(c, "medium") for c in companions], notes


def interior_scattering_note(scene: Scene, passes: list[Pass]) -> list[str]:
    """A note when a dielectric material scatters light inside (``interior_sigma_s`` above
    0) and no pass of the plan renders that (none declares ``INTERIOR_SCATTERING``): the
    light is not in the image, and the user is told so rather than left to find it
    missing. With one that does not model ``interior_g`` (no ``INTERIOR_PHASE``), a note
    per material whose ``interior_g`` differs from the medium's phase."""
    mats = sorted(scene.scatters_inside_glass(), key=lambda m: m.key or m.name)
    methods = all_methods()
    if not mats:
        return []
    inside = [methods[p.method] for p in passes if methods[p.method].INTERIOR_SCATTERING]
    if inside:
        if all(getattr(c, "INTERIOR_PHASE", False) for c in inside):
            return []                  # interior_g is modelled
        g = scene.medium.g if scene.medium is not None else 0.0
        return [f"{m.key or m.name}.interior_g: light inside the glass scatters with the scene "
                f"medium's phase (g = {g:g}), not {m.interior_g:g}: {APPROXIMATES}" for m in mats
                if m.interior_g is not None and m.interior_g != g]
    who = "+".join(p.method for p in passes) or "this plan"
    name = mats[0].key or mats[0].name
    able = " and ".join(n for n, c in sorted(methods.items()) if c.INTERIOR_SCATTERING)
    return [f"{name}.interior_sigma_s: {who} does not scatter light inside glass "
            f"(only {able} do): {DROPS_LIGHT}"]


def _no_density(cls, scene: Scene) -> str:
    """Why ``auto`` passes over ``cls`` on ``scene``: it has density volumes and ``cls``
    does not render them ('' otherwise)."""
    if cls.DENSITY or not scene.density_volumes():
        return ""
    return f"{cls.NAME} does not render heterogeneous media (density volumes)"


def density_note(scene: Scene, passes: list[Pass]) -> list[str]:
    """One note when the scene has density volumes and no pass of the plan renders them:
    the light they scatter, and their shadows, are not in the image."""
    vols = scene.density_volumes()
    methods = all_methods()
    if not vols or not passes or any(methods[p.method].DENSITY for p in passes):
        return []
    who = "+".join(p.method for p in passes)
    able = " and ".join(n for n, c in sorted(methods.items()) if c.DENSITY)
    return [f"{vols[0].key}.density: {who} does not render heterogeneous media (only "
            f"{able} do): the density is ignored, {DROPS_LIGHT}"]


def camera_glass_note(scene: Scene, passes: list[Pass]) -> list[str]:
    """One note when the camera is inside closed glass and a pass of the plan takes it to
    be in air (no ``CAMERA_IN_GLASS``): what that pass renders is not what the camera
    sees there (the glass's n^2 radiance gain, its inside taken for the scene medium)."""
    methods = all_methods()
    air = [p.method for p in passes if not methods[p.method].CAMERA_IN_GLASS]
    glass = scene.camera_glass() if air else None
    if glass is None:
        return []
    return [f"camera.origin is inside {glass.key} (glass), which {'+'.join(air)} does not "
            f"model (it takes the camera to be in air: no n^2 radiance gain, the glass's "
            f"inside taken for the scene medium): {APPROXIMATES}"]


def dropped_light(notes: list[str]) -> list[str]:
    """The plan notes that say light the scene needs is left out of the image."""
    return [n for n in notes if n.endswith(DROPS_LIGHT)]


def user_notes(notes: list[str]) -> list[str]:
    """The plan notes a render prints: light left out, or rendered approximately."""
    return [n for n in notes if n.endswith((DROPS_LIGHT, APPROXIMATES))]
