"""Scattering inside glass (a dielectric's ``interior_sigma_s``) is rendered only by the
voxel pipeline; every other plan says, in one note, that this light is left out, instead
of rendering the same image as without it in silence."""
from __future__ import annotations

import pytest

from clscatter.pipeline.planner import dropped_light, plan
from clscatter.scene.loader import load_scene


@pytest.mark.parametrize("method", ["auto", "raymarch", "lsg", "epipolar"])
def test_interior_scattering_left_out_is_noted(method):
    scene = load_scene("builtin:caustic_sphere", ["materials.glass.interior_sigma_s=2.0"])
    _, notes = plan(scene, method)
    lines = [n for n in dropped_light(notes) if "interior_sigma_s" in n]
    assert len(lines) == 1 and lines[0].startswith("materials.glass.interior_sigma_s: ")


def test_no_note_when_the_glass_is_clear_or_voxel_renders_it():
    assert not [n for n in plan(load_scene("builtin:caustic_sphere"), "auto")[1]
                if "interior_sigma_s" in n]
    scene = load_scene("builtin:caustic_sphere", ["materials.glass.interior_sigma_s=2.0"])
    assert not [n for n in plan(scene, "voxel")[1] if "interior_sigma_s" in n]
