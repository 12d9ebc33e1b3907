"""Scattering inside glass (a dielectric's ``interior_sigma_s``) is rendered by ``lsg``
(the lighting segments inside the glass gathered against the view segments inside, with
the interior coefficients) and by the voxel pipeline. ``auto`` gets it from its caustic
pass (``lsg``: all light inside glass came through its surface), or from the voxel
pipeline where the scene needs that anyway; every other plan says, in one note, that this
light is left out, instead of rendering the same image as without it in silence.
``interior_g``, which the voxel pipeline does not model (it scatters with the scene
medium's phase), is accepted and noted as approximated there; ``lsg`` models it."""
from __future__ import annotations

import pytest

from clscatter.pipeline.planner import dropped_light, needed_terms, plan, user_notes
from clscatter.scene.loader import load_scene

SCATTERING = ["materials.glass.interior_sigma_s=2.0"]


@pytest.mark.parametrize("method", ["raymarch", "epipolar", "vpm"])
def test_interior_scattering_left_out_is_noted(method):
    _, notes = plan(load_scene("builtin:caustic_sphere", SCATTERING), method)
    lines = [n for n in dropped_light(notes) if "interior_sigma_s" in n]
    assert len(lines) == 1 and lines[0].startswith("materials.glass.interior_sigma_s: ")
    assert "only lsg and voxel do" in lines[0]


@pytest.mark.parametrize("method", ["lsg", "voxel"])
def test_methods_that_scatter_inside_glass_drop_nothing(method):
    _, notes = plan(load_scene("builtin:caustic_sphere", SCATTERING), method)
    assert not [n for n in dropped_light(notes) if "interior_sigma_s" in n]


def test_auto_gets_interior_scattering_from_its_caustic_pass():
    scene = load_scene("builtin:caustic_sphere", SCATTERING)
    terms = needed_terms(scene)[0]
    assert "caustics" in terms and "volumes" not in terms
    passes, notes = plan(scene, "auto")
    assert "lsg" in [p.method for p in passes] and "voxel" not in [p.method for p in passes]
    assert not [n for n in notes if "interior_sigma_s" in n]
    assert "volumes" not in needed_terms(load_scene("builtin:caustic_sphere"))[0]


def test_interior_scattering_without_a_medium_still_needs_the_caustic_pass():
    scene = load_scene("builtin:caustic_sphere", SCATTERING + ["medium.sigma_s=0.0",
                                                               "medium.sigma_a=0.0"])
    assert not scene.has_medium()
    assert needed_terms(scene)[0][:1] == ["caustics"]
    passes, notes = plan(scene, "auto")
    assert [p.method for p in passes if p.role == "caustics"] == ["lsg"]
    assert not dropped_light(notes)


def test_no_note_when_the_glass_is_clear():
    assert not [n for n in plan(load_scene("builtin:caustic_sphere"), "auto")[1]
                if "interior" in n]


def test_interior_g_is_accepted_and_its_approximation_noted_where_it_is_one():
    scene = load_scene("builtin:caustic_sphere", SCATTERING + ["materials.glass.interior_g=0.4"])
    assert scene.materials["glass"].interior_g == 0.4
    lines = [n for n in user_notes(plan(scene, "voxel")[1]) if "interior_g" in n]
    assert len(lines) == 1 and lines[0].startswith("materials.glass.interior_g: ")
    assert not [n for n in plan(scene, "auto")[1] if "interior_g" in n]      # lsg models it
    assert not [n for n in plan(scene, "lsg")[1] if "interior_g" in n]
    same = load_scene("builtin:caustic_sphere",
                      SCATTERING + [f"materials.glass.interior_g={scene.medium.g}"])
    assert not [n for n in plan(same, "voxel")[1] if "interior_g" in n]
