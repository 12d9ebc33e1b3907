"""Nothing in the scene format is silently ignored: on the scene that exercises every key
(tests/data/full_scene.toml), changing any documented key changes the image (or, for the
keys that steer the render rather than the picture, what the statistics record), and a
key the format does not know is refused."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from clscatter.errors import SceneError
from clscatter.pipeline.render import render
from clscatter.scene import load_scene

SCENE = Path(__file__).resolve().parent / "data" / "full_scene.toml"
BASE = ["camera.resolution=[24,18]", "camera.spp=1", "render.time_budget=0",
        "render.lsg.light_rays=4000", "render.lsg.radius=0.01",
        "render.voxel.resolution=16", "render.voxel.photons=2048",
        "render.voxel.outer_resolution=16"]

# (override, method that renders what the key controls)
CHANGES = [
    ("camera.origin=[0.3, 1.0, 6.0]", "lsg"), ("camera.target=[0.0, 0.8, 0.0]", "lsg"),
    ("camera.up=[0.3, 1.0, 0.0]", "lsg"), ("camera.fov=35.0", "lsg"),
    ('camera.fov_axis="x"', "lsg"), ("camera.resolution=[26,18]", "lsg"),
    ("camera.spp=2", "lsg"),
    ("medium.sigma_s=0.3", "lsg"), ("medium.sigma_a=0.3", "lsg"), ("medium.g=-0.3", "lsg"),
    ("medium.bounds.max=[5.0, 4.0, 8.0]", "lsg"),
    ("lights[0].position=[0.5, 3.0, 0.0]", "lsg"), ("lights[0].intensity=12.0", "lsg"),
    ("lights[1].position=[2.0, 3.2, 0.5]", "lsg"), ("lights[1].target=[1.5, 0.0, 0.0]", "lsg"),
    ("lights[1].intensity=25.0", "lsg"), ("lights[1].cutoff_angle=30.0", "lsg"),
    ("lights[2].direction=[0.3, -2.0, 0.0]", "lsg"), ("lights[2].irradiance=2.0", "lsg"),
    ("materials.glass.ior=1.6", "lsg"), ("materials.glass.interior_sigma_a=0.5", "lsg"),
    ("materials.glass.interior_sigma_s=0.5", "lsg"), ("materials.glass.interior_g=0.6", "lsg"),
    ("materials.floor.albedo=0.3", "lsg"), ("materials.chrome.reflectance=0.5", "lsg"),
    ('objects[0].file="cow.obj"', "lsg"), ("objects[0].transform.translate=[1.0, 1.5, 3.0]", "lsg"),
    ("objects[0].transform.rotate=[0, 1, 0, 45.0]", "lsg"),
    ("objects[0].transform.scale=1.5", "lsg"),
    ("objects[1].center=[0.7, 1.2, 0.0]", "lsg"), ("objects[1].radius=0.5", "lsg"),
    ("objects[1].subdivisions=0", "lsg"),
    ("objects[2].min=[-2.0, 2.3, -2.0]", "lsg"), ("objects[2].max=[1.0, 2.55, 2.0]", "lsg"),
    ("objects[3].origin=[-5.0, 0.2, -5.0]", "lsg"), ("objects[3].edge_u=[8.0, 0.0, 0.0]", "lsg"),
    ("objects[3].edge_v=[0.0, 0.5, 10.0]", "lsg"), ("objects[0].smooth=true", "lsg"),
    ('objects[0].material={type="diffuse", albedo=0.6}', "lsg"),
    ("render.max_depth=1", "lsg"), ("render.seed=8", "lsg"), ('render.method="raymarch"', None),
    ("render.lsg.radius=0.02", "lsg"),
    ("volumes[0].ior=1.3", "voxel"), ("volumes[0].sigma_s=0.5", "voxel"),
    ("volumes[0].sigma_a=0.6", "voxel"), ("volumes[0].transform.scale=1.3", "voxel"),
    ("volumes[1].bounds.max=[1.2, 1.0, 1.0]", "voxel"), ("volumes[1].sigma_s=0.4", "voxel"),
    ("volumes[1].sigma_a=0.4", "voxel"),
]


_cache: dict = {}


def _image(sets: list[str], method: str | None, engine) -> np.ndarray:
    key = (tuple(sets), method)
    if key not in _cache:
        _cache[key] = render(load_scene(SCENE, BASE + sets), method, engine=engine,
                             show_progress=False).image
    return _cache[key]


@pytest.mark.parametrize("change, method", CHANGES, ids=[c for c, _ in CHANGES])
def test_every_key_changes_the_image(change, method, engine):
    base = _image([], method, engine)
    got = _image([change], method, engine)
    assert got.shape != base.shape or float(np.max(np.abs(got - base))) > 1e-5 * float(base.max()), \
        f"{change} left the image unchanged"


def test_render_controls_reach_the_statistics(engine):
    """time_budget and target_error steer the render: the stats record them."""
    s = render(load_scene(SCENE, BASE + ["render.time_budget=30", "render.target_error=0.5"]),
               "lsg", engine=engine, show_progress=False).stats
    assert s["time_budget"] == 30.0 and s["target_error"] == 0.5


@pytest.mark.parametrize("change, key", [
    ("camera.zoom=2.0", "camera.zoom"), ("medium.density=1.0", "medium.density"),
    ("lights[0].radius=0.1", "lights[0].radius"), ("materials.glass.roughness=0.1",
                                                   "materials.glass.roughness"),
    ("objects[1].height=1.0", "objects[1].height"), ("render.samples=4", "render.samples"),
])
def test_an_unknown_key_is_refused(change, key):
    with pytest.raises(SceneError) as e:
        load_scene(SCENE, BASE + [change])
    assert e.value.key == key
