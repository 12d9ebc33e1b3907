"""Far objects do no harm: objects 1e7 away, out of view, leave every method's image as it
is, and a far object in view still shows and occludes.

The device works in float32 in a frame fitted to the scene's bounding box, which leaves
far objects out (``Scene.bbox``, ``FAR_FACTOR`` in clscatter/scene/model.py): they stay
in the BVH at large normalised coordinates. Renders with and without two unit spheres
1e7 away (one behind the camera, one off to the side) use the same seeds, so the random
streams are the same and only the frame could differ.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from clscatter.pipeline.render import render
from clscatter.scene import scene_from_dict
from clscatter.scene.model import FAR_FACTOR
from clscatter.scene.normalised import Frame

HERE = Path(__file__).resolve().parent

# Largest pixel difference relative to the image's peak, with and without the far
# spheres. Measured (24 x 18, 1 spp, the settings below): 0 (bit-identical) for every
# case but raymap and auto on the glass scene, 3.5e-8 (float rounding in the ray map,
# whose escaping ray pieces end on the BVH's box, which the far spheres widen).
FLOAT_TOL = 1e-6

SHADOW = {
    "camera": {"origin": [0.0, 1.5, 4.0], "target": [0.0, 0.5, 0.0], "up": [0.0, 1.0, 0.0],
               "fov": 50.0, "resolution": [24, 18], "spp": 1},
    "medium": {"sigma_s": 0.3, "sigma_a": 0.03, "g": 0.2,
               "bounds": {"min": [-2.0, 0.0, -2.0], "max": [2.0, 2.5, 2.0]}},
    "lights": [{"type": "point", "position": [0.3, 2.2, 0.2], "intensity": 6.0}],
    "objects": [
        {"shape": "sphere", "center": [0.0, 0.8, 0.0], "radius": 0.4,
         "material": {"type": "diffuse", "albedo": 0.5}},
        {"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
         "edge_v": [0.0, 0.0, 4.0], "material": {"type": "diffuse", "albedo": 0.6}},
    ],
    "render": {"seed": 3, "time_budget": 0.0, "raymarch": {"steps": 16},
               "lsg": {"light_rays": 4000}, "vpm": {"photons": 20000},
               "raymap": {"photons": 4000}, "photonmap": {"photons": 4000},
               "voxel": {"resolution": 16, "photons": 1024, "outer_resolution": 16}},
}

# one unit sphere 1e7 behind the camera, one 1e7 off to the side
FAR = [{"shape": "sphere", "center": [0.0, 1.5, 1e7], "radius": 1.0,
        "material": {"type": "diffuse", "albedo": 0.5}},
       {"shape": "sphere", "center": [1e7, 0.0, 0.0], "radius": 1.0,
        "material": {"type": "diffuse", "albedo": 0.5}}]


def _variant(kind: str) -> dict:
    """The shadow scene, or with a spot or a directional light, a small glass sphere (the
    caustic methods' scene) or a graded-index volume (voxel)."""
    d = copy.deepcopy(SHADOW)
    if kind == "spot":
        d["lights"] = [{"type": "spot", "position": [0.3, 2.2, 0.2], "target": [0.0, 0.0, 0.0],
                        "intensity": 6.0, "cutoff_angle": 35.0}]
    elif kind == "sun":
        d["lights"] = [{"type": "directional", "direction": [0.2, -1.0, -0.3], "irradiance": 2.0}]
    elif kind == "glass":
        d["objects"][0]["material"] = {"type": "dielectric", "ior": 1.5}
    elif kind == "volume":
        d["volumes"] = [{"shape": "sphere", "center": [0.8, 0.6, 0.5], "radius": 0.4,
                         "ior": 1.2, "sigma_s": 0.5, "sigma_a": 0.05}]
    return d


def _render(d: dict, method: str, engine):
    return render(scene_from_dict(copy.deepcopy(d), HERE, "far"), method, engine=engine,
                  show_progress=False)


def _max_rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def _with_far(d: dict) -> dict:
    d = copy.deepcopy(d)
    d["objects"] = d["objects"] + copy.deepcopy(FAR)
    return d


def test_far_objects_leave_the_frame_and_the_extent_alone():
    """The far spheres are named far; the scene's bounding box, extent and device frame
    are exactly those of the scene without them. The near region (camera, light, medium
    box, objects) is 6 long, so a unit sphere whose box lies 4000 from it is near (it
    widens the box) and one 10000 off is far (FAR_FACTOR x 6 = 6000); the same scene
    scaled by 1e-3 and moved by 1e3 classifies the same."""
    near = scene_from_dict(copy.deepcopy(SHADOW), HERE, "far")
    far = scene_from_dict(_with_far(SHADOW), HERE, "far")
    assert [k for k, _, _ in far.far_items()] == ["objects[2]", "objects[3]"]
    assert near.far_items() == []
    for a, b in zip(near.bbox(), far.bbox()):
        assert np.array_equal(a, b)
    assert far.scene_extent() == near.scene_extent() == 4.0
    f0, f1 = Frame.for_scene(near), Frame.for_scene(far)
    assert f1.scale == f0.scale and np.array_equal(f1.centre, f0.centre)
    assert FAR_FACTOR * 6.0 == 6000.0
    for x, is_far in ((4003.0, False), (10003.0, True)):
        d = copy.deepcopy(SHADOW)
        d["objects"].append({"shape": "sphere", "center": [x, 0.0, 0.0], "radius": 1.0,
                             "material": {"type": "diffuse"}})
        s = scene_from_dict(d, HERE, "far")
        assert (s.far_items() != []) == is_far, x
        assert s.scene_extent() == pytest.approx(4.0 if is_far else x + 3.0, rel=1e-3)
    from test_invariance import transform_scene
    moved = scene_from_dict(transform_scene(_with_far(SHADOW), 1e-3, 1e3), HERE, "far")
    assert [k for k, _, _ in moved.far_items()] == ["objects[2]", "objects[3]"]
    assert moved.scene_extent() == pytest.approx(4e-3, rel=1e-9)


def test_a_lone_object_far_from_the_camera_is_near():
    """The first object to join the near region always joins: a scene whose only object is
    1e7 from the camera keeps its frame on that object."""
    d = copy.deepcopy(SHADOW)
    del d["medium"]
    d["objects"] = [copy.deepcopy(FAR[1])]
    s = scene_from_dict(d, HERE, "far")
    assert s.far_items() == [] and s.scene_extent() == pytest.approx(2.0)
    assert np.allclose(Frame.for_scene(s).centre, [1e7, 0.0, 0.0], atol=1e-6)


# (method, scene variant): each method on a scene it computes something for
CASES = [("raymarch", "shadow"), ("raymarch", "sun"), ("epipolar", "spot"),
         ("epipolar", "sun"), ("auto", "shadow"), ("auto", "glass"), ("lsg", "glass"),
         ("vpm", "glass"), ("vpm", "sun"), ("photonmap", "glass"), ("raymap", "glass"),
         ("voxel", "volume")]


@pytest.mark.parametrize("method, kind", CASES, ids=[f"{m}-{k}" for m, k in CASES])
def test_far_spheres_out_of_view_change_nothing(engine, method, kind):
    """Two unit spheres 1e7 away, out of view: the image equals the one without them within
    FLOAT_TOL of its peak. (Before the frame left far objects out, raymarch differed by
    0.54 of the peak, relMSE 0.21.)"""
    d = _variant(kind)
    base = _render(d, method, engine)
    assert np.isfinite(base.image).all() and base.image.max() > 0
    res = _render(_with_far(d), method, engine)
    assert res.stats["method"] == base.stats["method"]
    err = _max_rel(res.image, base.image)
    assert err < FLOAT_TOL, (method, kind, err)


def _in_view(distance: float) -> dict:
    """The shadow scene under a directional light from straight above (irradiance does not
    fall off, so a far surface is as bright as a near one), with a diffuse sphere of radius
    0.3 ``distance`` centred ``distance`` from the camera along a fixed direction above
    its view axis: the same angular disc, normals and lighting at every distance."""
    d = copy.deepcopy(SHADOW)
    d["camera"].update(target=[0.0, 1.2, 0.0], fov=60.0, resolution=[32, 24])
    d["lights"] = [{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}]
    u = np.array([0.0, 0.35, -4.0]) / np.linalg.norm([0.0, 0.35, -4.0])
    c = np.asarray(d["camera"]["origin"]) + distance * u
    d["objects"].append({"shape": "sphere", "center": c.tolist(), "radius": 0.3 * distance,
                         "material": {"type": "diffuse", "albedo": 0.7}})
    return d


# relative to the peak, on the pixels the sphere covers: measured 3.4e-7 (raymarch),
# 3.0e-5 (epipolar and auto: its shadow map and depth grid follow the frame, which
# holds the sphere in the reference)
IN_VIEW_TOL = 1e-4


@pytest.mark.parametrize("method", ["raymarch", "epipolar", "auto"])
def test_a_far_sphere_in_view_shows_and_occludes(engine, method):
    """A sphere of radius 3e6 at 1e7, in view behind the fog box, against the same sphere
    scaled down (radius 30 at 100, then part of the near region): on the pixels it covers
    (where it changes the image by over 1e-3 of the peak) the images agree within
    IN_VIEW_TOL of the peak (lit diffuse surface, without self-shadowing; before surface
    offsets grew with the coordinates about half of them were black). Everywhere else the
    image is the one without the sphere within FLOAT_TOL (the reference is not: its frame
    is 30x wider)."""
    far, scaled = _render(_in_view(1e7), method, engine), _render(_in_view(100.0), method, engine)
    none = _render(_in_view(100.0) | {"objects": copy.deepcopy(SHADOW["objects"])}, method,
                   engine)
    peak = float(scaled.image.max())
    covered = np.abs(scaled.image - none.image).max(axis=2) > 1e-3 * peak
    assert covered.sum() > 50          # the sphere shows, on about a seventh of the image
    assert float(np.abs(scaled.image - none.image).max()) > 0.3 * peak
    on = float(np.abs(far.image - scaled.image).max(axis=2)[covered].max()) / peak
    off = float(np.abs(far.image - none.image).max(axis=2)[~covered].max()) / peak
    assert on < IN_VIEW_TOL and off < FLOAT_TOL, (method, on, off)


# epipolar leaves light in a medium whose every light ray is blocked, far roof or near
# (its truncated SVD of the slices' transmittance): measured 8.6e-3 of the lit image's
# peak, the same with a roof just above the medium box
EPIPOLAR_LEAK = 0.02


@pytest.mark.parametrize("method", ["raymarch", "epipolar", "vpm"])
def test_a_far_roof_over_a_directional_light_still_shadows(engine, method):
    """A 1e8-wide slab 1e7 above the scene, in the way of a directional light from above:
    far, yet every method that traces from the light (epipolar's shadow map, vpm's
    photons) starts beyond it, as raymarch's shadow rays reach it: no direct light (the
    image is 0; epipolar: below EPIPOLAR_LEAK of the lit image's peak), where without
    the slab the scene is lit."""
    d = _variant("sun")
    d["lights"][0]["direction"] = [0.0, -1.0, 0.0]
    lit = _render(d, method, engine)
    peak = float(lit.image.max())
    assert peak > 0.05
    d["objects"].append({"shape": "box", "min": [-5e7, 1e7, -5e7], "max": [5e7, 1.1e7, 5e7],
                         "material": {"type": "diffuse", "albedo": 0.5}})
    s = scene_from_dict(copy.deepcopy(d), HERE, "far")
    assert [k for k, _, _ in s.far_in_beam(d["lights"][0]["direction"])] == ["objects[2]"]
    dark = float(_render(d, method, engine).image.max())
    assert dark <= (EPIPOLAR_LEAK * peak if method == "epipolar" else 0.0), (method, dark, peak)
