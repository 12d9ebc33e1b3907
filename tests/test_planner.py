"""auto: passes chosen from the scene alone by the methods' declared capabilities.

These tests need no OpenCL device: the planner reads the Scene, not device buffers.
"""
from __future__ import annotations

import copy
from pathlib import Path

import pytest

from clscatter.errors import SceneError
from clscatter.methods import AutoRole, Method, get_method
from clscatter.pipeline.planner import plan
from clscatter.scene import scene_from_dict

HERE = Path(__file__).resolve().parent
BASE = {
    "camera": {"origin": [0.0, 1.0, 5.0], "target": [0.0, 0.5, 0.0], "resolution": [8, 6], "spp": 1},
    "medium": {"sigma_s": 0.1, "sigma_a": 0.0, "bounds": {"min": [-3, -1, -3], "max": [3, 3, 3]}},
    "lights": [{"type": "point", "position": [0.0, 2.0, 0.0], "intensity": 5.0}],
    "objects": [{"shape": "sphere", "center": [0.0, 0.5, 0.0], "radius": 0.4,
                 "material": {"type": "diffuse"}}],
}


def _plan(d, requested="auto"):
    return plan(scene_from_dict(copy.deepcopy(d), HERE, "p"), requested)


def _roles(passes):
    return [(p.method, p.role) for p in passes]


def test_planner_needs_no_opencl():
    """Plan in a fresh process where importing pyopencl fails."""
    import subprocess
    import sys
    code = ("import sys; sys.modules['pyopencl'] = None\n"
            "from clscatter.pipeline.planner import plan\n"
            "from clscatter.scene import load_scene\n"
            "passes, notes = plan(load_scene('builtin:shafts'), 'auto')\n"
            "print([p.method for p in passes])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=HERE.parent)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "['epipolar']"


def test_no_medium_or_lights_skips_everything():
    d = copy.deepcopy(BASE)
    del d["medium"]
    assert _plan(d)[0] == []
    d = copy.deepcopy(BASE)
    d["lights"] = []
    assert _plan(d)[0] == []
    d = copy.deepcopy(BASE)
    d["medium"]["sigma_s"] = 0.0                  # a void medium is no medium
    assert _plan(d)[0] == []


def test_point_light_diffuse_scene_is_raymarched_without_caustics():
    passes, notes = _plan(BASE)
    assert _roles(passes) == [("raymarch", "direct")]
    assert any("caustic pass skipped" in n for n in notes)


def test_spot_and_directional_lights_choose_epipolar():
    d = copy.deepcopy(BASE)
    d["lights"] = [{"type": "spot", "position": [0, 2, 0], "target": [0, 0, 0], "intensity": 5.0,
                    "cutoff_angle": 20.0}]
    assert _roles(_plan(d)[0]) == [("epipolar", "direct")]
    d["lights"].append({"type": "point", "position": [1, 2, 0], "intensity": 1.0})
    passes, notes = _plan(d)                       # a point light breaks epipolar's assumptions
    assert _roles(passes) == [("raymarch", "direct")]
    assert any("not epipolar" in n for n in notes)


def _directional(direction, sigma, origin=(0.0, 1.0, 5.0)):
    d = copy.deepcopy(BASE)
    d["camera"]["origin"] = list(origin)
    d["medium"]["sigma_s"] = sigma
    d["lights"] = [{"type": "directional", "direction": direction, "irradiance": 1.0}]
    return d


@pytest.mark.parametrize("direction,sigma,origin,method,why", [
    # the box is 6 wide: optical depth 6 sigma across; camera at z = 5 outside, 2 inside
    ([0.0, -0.3, -1.0], 0.5, (0.0, 1.0, 5.0), "epipolar", ""),           # 3: thin enough
    ([0.0, -0.3, -1.0], 0.8, (0.0, 1.0, 5.0), "raymarch", "along the view"),   # 4.8
    ([1.0, -0.3, 0.0], 0.8, (0.0, 1.0, 5.0), "epipolar", ""),            # across the view
    ([1.0, -0.3, 0.0], 1.4, (0.0, 1.0, 5.0), "raymarch", "optical depth 8.4"),  # thick
    ([0.0, -0.3, -1.0], 0.8, (0.0, 1.0, 2.0), "epipolar", ""),           # camera inside
    ([1.0, -0.3, 0.0], 1.4, (0.0, 1.0, 2.0), "epipolar", ""),            # 8.4 from inside
    ([0.0, -0.3, -1.0], 2.1, (0.0, 1.0, 2.0), "raymarch", "along the view"),   # 12.6
    ([1.0, -0.3, 0.0], 3.0, (0.0, 1.0, 2.0), "epipolar", ""),            # 18, across
    ([1.0, -0.3, 0.0], 4.1, (0.0, 1.0, 2.0), "raymarch", "optical depth 24.6"),
])
def test_auto_passes_epipolar_over_where_its_estimate_fails(direction, sigma, origin, method,
                                                            why):
    """``Epipolar.unreliable``: thick media (optical depth >= 8 across seen from outside,
    >= 24 from inside), and lights along the view through >= 4 from outside, >= 12 from
    inside, go to raymarch with a note that says why; an explicit ``epipolar`` still runs
    there."""
    d = _directional(direction, sigma, origin)
    scene = scene_from_dict(copy.deepcopy(d), HERE, "p")
    inside = origin[2] < 3.0
    assert scene.camera_in_medium() == inside
    assert scene.optical_depth_across() == pytest.approx(6.0 * sigma)
    passes, notes = _plan(d)
    assert _roles(passes) == [(method, "direct")]
    if why:
        assert any(n.startswith("direct: not epipolar") and why in n for n in notes), notes
    assert _roles(_plan(d, "epipolar")[0]) == [("epipolar", "all")]


def test_a_spot_behind_the_camera_seen_from_outside_is_not_swept_by_auto():
    """A spot light just behind the camera shining along the view, camera outside the
    medium: the estimate fails at any optical depth (test_epipolar_regimes.py), so auto
    ray marches it; the same spot in front of the camera is swept."""
    d = copy.deepcopy(BASE)
    d["lights"] = [{"type": "spot", "position": [0.0, 1.1, 6.5], "target": [0.0, 0.5, 0.0],
                    "intensity": 5.0, "cutoff_angle": 30.0}]
    passes, notes = _plan(d)
    assert _roles(passes) == [("raymarch", "direct")]
    assert any("spot light behind the camera" in n for n in notes), notes
    d["lights"][0]["position"] = [0.0, 2.5, 2.0]
    assert _roles(_plan(d)[0]) == [("epipolar", "direct")]


def test_specular_objects_add_an_lsg_caustic_pass():
    d = copy.deepcopy(BASE)
    d["objects"][0]["material"] = {"type": "dielectric", "ior": 1.5}
    passes, _ = _plan(d)
    assert _roles(passes)[:2] == [("raymarch", "direct"), ("lsg", "caustics")]
    assert passes[1].params == {"min_light_depth": 1}
    assert passes[1].defaults == {"passes": 8}
    scene = scene_from_dict(copy.deepcopy({**d, "render": {"lsg": {"time_budget": 2.0,
                                                                   "min_light_depth": 0}}}), HERE)
    # the scene's values win over the role's defaults, never over what it requires
    assert passes[1].table(scene) == {"time_budget": 2.0, "passes": 8, "min_light_depth": 1}
    passes, notes = _plan(d, "raymarch")      # explicit: alone, with a warning
    assert [p.method for p in passes] == ["raymarch"] and any("caustics" in n for n in notes)


def test_the_planner_follows_declared_capabilities(monkeypatch):
    """A new method with a higher priority for a term takes it over; nothing in the planner
    names it."""
    import clscatter.methods as methods

    class Fancy(Method):
        NAME = "fancy"
        TERMS = frozenset({"direct"})
        AUTO = {"direct": AutoRole(priority=99)}

    methods._load_all()
    monkeypatch.setitem(methods._REGISTRY, "fancy", Fancy)
    assert _roles(_plan(BASE)[0]) == [("fancy", "direct")]

    class Picky(Fancy):
        NAME = "picky"
        AUTO = {"direct": AutoRole(priority=100)}
        LIGHTS = frozenset({"directional"})

    monkeypatch.setitem(methods._REGISTRY, "picky", Picky)
    passes, notes = _plan(BASE)                    # a point light: picky does not suit
    assert _roles(passes) == [("fancy", "direct")] and any("not picky" in n for n in notes)


def test_bad_method_parameters_name_their_key():
    for method, key, value in (("raymarch", "steps", 0), ("lsg", "radius", -1.0),
                               ("vpm", "knn", 1), ("epipolar", "svd_terms", 0),
                               ("lsg", "light_rays", 0), ("epipolar", "lookup", "nope")):
        with pytest.raises(SceneError, match=f"render.{method}.{key}: .*got"):
            get_method(method)({key: value})


def test_volumes_make_the_voxel_pipeline_render_alone():
    """A graded-index volume: nothing but the voxel pipeline bends rays, and it owns the
    whole image (a separate direct pass would count the light twice)."""
    d = copy.deepcopy(BASE)
    d["volumes"] = [{"shape": "sphere", "center": [0.0, 1.5, 0.0], "radius": 0.5, "ior": 1.3}]
    passes, notes = _plan(d)
    assert _roles(passes) == [("voxel", "all")]
    assert any("renders the whole image alone" in n and "direct by raymarch" in n for n in notes)


@pytest.mark.parametrize("spec,sets,missing", [
    ("builtin:caustic_sphere", [], []),                     # voxelised glass, photons on the floor
    ("builtin:caustic_sphere", ["render.voxel.surface_photons=false"], ["surface_caustics"]),
    ("builtin:caustic_sphere", ["render.voxel.voxelise_dielectrics=false"],
     ["caustics", "surface_caustics"]),
    ("builtin:glass", [], ["caustics", "surface_caustics"]),          # a mirror besides the glass
    ("builtin:caustic_mirror", [], ["caustics", "surface_caustics"]),   # photons end at mirrors
])
def test_voxel_says_which_caustics_it_leaves_out(spec, sets, missing):
    """An explicit voxel pass notes the caustics it leaves out (Method.computes): none where
    it voxelises the glass and puts photons on surfaces; the surface ones without surface
    photons; all of them without voxelised glass or with a mirror."""
    from clscatter.scene import load_scene
    _, notes = plan(load_scene(spec, sets), "voxel")
    said = [n for n in notes if "does not compute" in n]
    if missing:
        assert len(said) == 1 and f"does not compute {', '.join(missing)}:" in said[0], notes
    else:
        assert not said, notes


VOLUME = 'volumes=[{shape="sphere", center=[1.6, 1.0, 0.0], radius=0.3, ior=1.3}]'


@pytest.mark.parametrize("spec,sets,missing", [
    ("builtin:caustic_sphere", [], []),                     # voxelised glass, photons on the floor
    ("builtin:caustic_sphere", ["render.voxel.surface_photons=false"], ["surface_caustics"]),
    ("builtin:glass", [], ["caustics", "surface_caustics"]),          # a mirror besides the glass
])
def test_auto_notes_only_the_light_the_alone_method_leaves_out(spec, sets, missing):
    """Under auto a volume makes voxel render the whole image alone, in place of the other
    passes: the terms it does not compute itself (Method.computes) are noted as left out,
    whether another method could have taken them or not, as for an explicit voxel pass."""
    from clscatter.scene import load_scene
    passes, notes = plan(load_scene(spec, [VOLUME, *sets]), "auto")
    assert _roles(passes) == [("voxel", "all")]
    left = sorted(n.split()[2] for n in notes
                  if "voxel, which renders the whole image alone, does not compute it" in n)
    assert left == sorted(missing), notes
    assert not [n for n in notes if "no available method" in n], notes
