"""Scattering inside glass (a dielectric's ``interior_sigma_s``) is rendered only by the
voxel pipeline: ``auto`` picks it there (the term ``volumes``), and every other plan says,
in one note, that this light is left out, instead of rendering the same image as without
it in silence. ``interior_g``, which the voxel pipeline does not model (it scatters with
the scene medium's phase), is accepted and noted as approximated when it differs."""
from __future__ import annotations

import pytest

from clscatter.pipeline.planner import dropped_light, needed_terms, plan, user_notes
from clscatter.scene.loader import load_scene

SCATTERING = ["materials.glass.interior_sigma_s=2.0"]


@pytest.mark.parametrize("method", ["raymarch", "lsg", "epipolar", "vpm"])
def test_interior_scattering_left_out_is_noted(method):
    _, notes = plan(load_scene("builtin:caustic_sphere", SCATTERING), method)
    lines = [n for n in dropped_light(notes) if "interior_sigma_s" in n]
    assert len(lines) == 1 and lines[0].startswith("materials.glass.interior_sigma_s: ")


def test_auto_picks_the_method_that_scatters_inside_glass():
    scene = load_scene("builtin:caustic_sphere", SCATTERING)
    assert "volumes" in needed_terms(scene)[0]
    passes, notes = plan(scene, "auto")
    assert [p.method for p in passes] == ["voxel"]
    assert not [n for n in notes if "interior_sigma_s" in n]
    assert "volumes" not in needed_terms(load_scene("builtin:caustic_sphere"))[0]


def test_no_note_when_the_glass_is_clear():
    assert not [n for n in plan(load_scene("builtin:caustic_sphere"), "auto")[1]
                if "interior" in n]


def test_interior_g_is_accepted_and_its_approximation_noted():
    scene = load_scene("builtin:caustic_sphere", SCATTERING + ["materials.glass.interior_g=0.4"])
    assert scene.materials["glass"].interior_g == 0.4
    lines = [n for n in user_notes(plan(scene, "auto")[1]) if "interior_g" in n]
    assert len(lines) == 1 and lines[0].startswith("materials.glass.interior_g: ")
    same = load_scene("builtin:caustic_sphere",
                      SCATTERING + [f"materials.glass.interior_g={scene.medium.g}"])
    assert not [n for n in plan(same, "auto")[1] if "interior_g" in n]
