"""A camera inside closed glass: its view paths start in the glass, and it sees the
radiance there.

Closed form: a camera at the centre of a glass ball (index n) looks out at fog and a wall
beyond the ball, lit by a light whose rays never meet the ball. Every view ray leaves the
ball along its normal, unbent, with the Fresnel transmittance 1 - R0, R0 = ((n - 1) /
(n + 1))^2; radiance / n^2 is what a ray keeps across an interface, so inside the ball the
camera sees n^2 (1 - R0) times what it would see at the same place without the ball
(the part of a view ray reflected back in sees the dark side, then returns with R0^2:
0.16 % at n = 1.5, left out of the bound).
"""
from __future__ import annotations

import copy

import numpy as np
import pytest

from clscatter.pipeline.planner import plan
from clscatter.pipeline.render import render
from clscatter.scene import scene_from_dict

N = 1.5
R0 = ((N - 1) / (N + 1)) ** 2


def _scene(ball: bool) -> dict:
    d = {
        "camera": {"origin": [0.0, 1.0, 0.0], "target": [0.0, 1.0, -3.0], "fov": 40.0,
                   "resolution": [40, 30], "spp": 4},
        "medium": {"sigma_s": 0.3, "sigma_a": 0.02, "g": 0.2,
                   "bounds": {"min": [-2.0, 0.0, -4.0], "max": [2.0, 2.0, -1.0]}},
        "lights": [{"type": "point", "position": [1.2, 1.7, -2.4], "intensity": 4.0}],
        "materials": {"wall": {"type": "diffuse", "albedo": 0.6},
                      "glass": {"type": "dielectric", "ior": N}},
        "objects": [{"shape": "quad", "origin": [-2.0, 0.0, -3.9], "edge_u": [4.0, 0.0, 0.0],
                     "edge_v": [0.0, 2.0, 0.0], "material": "wall"}],
        "render": {"time_budget": 0.0},
    }
    if ball:
        d["objects"].append({"shape": "sphere", "center": [0.0, 1.0, 0.0], "radius": 0.5,
                             "subdivisions": 6, "material": "glass"})
    return d


def _image(d: dict, method: str, engine) -> np.ndarray:
    return render(scene_from_dict(copy.deepcopy(d)), method, engine=engine,
                  show_progress=False).image[..., :3].astype(np.float64)


SPOT = {"type": "spot", "position": [1.2, 1.7, -2.4], "target": [0.0, 0.8, -3.0],
        "intensity": 4.0, "cutoff_angle": 25.0}


@pytest.mark.parametrize("method", ["raymarch", "lsg", "vpm", "epipolar"])
def test_a_camera_inside_a_glass_ball_sees_n_squared_times_the_light(engine, method):
    """The image from the ball's centre over the image without the ball: n^2 (1 - R0) =
    2.16 in the mean (to 1 %) and, for ray marching, in every lit pixel (to 2 %).
    epipolar under a spot light (inside the ball every view segment is behind glass, and
    it ray marches those)."""
    scenes = [_scene(True), _scene(False)]
    if method == "epipolar":
        for d in scenes:
            d["lights"] = [SPOT]
    with_ball, without = (_image(d, method, engine) for d in scenes)
    want = N * N * (1 - R0)
    ratio = with_ball.mean() / without.mean()
    print(f"\n{method}: mean ratio {ratio:.4f} (closed form {want:.4f})")
    assert abs(ratio / want - 1) < 0.01
    if method == "raymarch":
        lit = without > 1e-3 * without.max()
        assert lit.mean() > 0.5
        assert np.allclose(with_ball[lit], want * without[lit], rtol=0.02)


def test_auto_passes_over_voxel_with_the_camera_in_glass():
    """voxel takes the camera to be in air: inside the glass ball (with a graded-index
    volume in the scene, which ``auto`` would give voxel) auto does not pick it and an
    explicit voxel gets a note; outside the ball, auto picks it and no note."""
    d = _scene(True)
    d["volumes"] = [{"shape": "sphere", "center": [0.0, 1.0, -2.5], "radius": 0.4,
                     "ior": 1.2}]
    s = scene_from_dict(copy.deepcopy(d))
    assert s.camera_glass() is s.objects[1]
    passes, notes = plan(s, "auto")
    assert "voxel" not in [p.method for p in passes]
    assert any("not voxel (voxel takes the camera to be in air" in n for n in notes)
    _, notes = plan(s, "voxel")
    assert [n for n in notes if n.startswith("camera.origin is inside objects[1] (glass)")]
    assert not [n for n in plan(s, "raymarch")[1] if "camera.origin" in n]
    d["camera"]["origin"] = [0.0, 1.0, 0.8]
    s = scene_from_dict(d)
    assert s.camera_glass() is None
    assert "voxel" in [p.method for p in plan(s, "auto")[0]]
    assert not [n for n in plan(s, "voxel")[1] if "camera.origin" in n]


@pytest.mark.parametrize("inside", [False, True])
def test_epipolar_with_the_medium_seen_only_through_glass(engine, inside):
    """Every view segment in the medium is behind glass (a glass slab across the view, or
    the camera inside the ball): epipolar sweeps no sample and ray marches them all, so
    its image is ray marching's (to 0.5 %), and auto renders too (both once failed
    looking for the slices of a sweep that never ran)."""
    d = _scene(inside)
    d["lights"] = [SPOT]
    if not inside:
        d["camera"]["origin"] = [0.0, 1.0, 0.3]
        d["objects"].append({"shape": "box", "min": [-3.0, -2.0, -0.6],
                             "max": [3.0, 4.0, -0.4], "material": "glass"})
    res = render(scene_from_dict(copy.deepcopy(d)), "epipolar", engine=engine,
                 show_progress=False)
    epi = res.image[..., :3].astype(np.float64)
    assert "slices" not in res.stats
    assert any("behind mirrors/glass" in f for f in res.stats["epipolar_fallback"])
    rm = _image(d, "raymarch", engine)
    assert abs(epi.mean() / rm.mean() - 1) < 0.005, (epi.mean(), rm.mean())
    assert np.isfinite(_image(d, "auto", engine)).all()
