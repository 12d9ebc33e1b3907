"""Scene loading: the TOML contract (docs/scene_format.md), overrides, validation, built-ins."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from clscatter.errors import SceneError
from clscatter.scene import (
    BUILTIN,
    DEFAULT_BUILTIN,
    Scene,
    apply_overrides,
    builtin_toml,
    load_scene,
    scene_from_dict,
    shapes,
)

DATA = Path(__file__).parent / "data"
FULL = DATA / "full_scene.toml"

# a stand-in method registry so these tests do not depend on which methods exist
FAKE_PARAMS = {"raymarch": {"steps": 32, "step_scale": 0.5, "jitter": True, "mode": "fast"},
               "lsg": {"light_rays": 1000, "radius": 0.001}}


def _fake_class(name: str, defaults: dict) -> type:
    from clscatter.methods import Method, Param
    return type(name, (Method,), {"NAME": name, "PARAMS": tuple(
        Param(k, v, k, lo=0 if isinstance(v, (int, float)) and not isinstance(v, bool) else None)
        for k, v in defaults.items())})


@pytest.fixture
def fake_methods(monkeypatch):
    import clscatter.methods as methods
    methods._load_all()
    monkeypatch.setattr(methods, "_REGISTRY",
                        {n: _fake_class(n, d) for n, d in FAKE_PARAMS.items()})


def base() -> dict:
    """A small valid scene touching every section; bad cases mutate a copy."""
    return {
        "camera": {"origin": [0.0, 1.0, 6.0], "target": [0.0, 0.5, 0.0]},
        "medium": {"sigma_s": 0.2, "sigma_a": 0.1,
                   "bounds": {"min": [-5.0, 0.0, -5.0], "max": [5.0, 5.0, 5.0]}},
        "lights": [{"type": "point", "position": [0.0, 3.0, 0.0], "intensity": 10.0},
                   {"type": "spot", "position": [1.0, 3.0, 0.0], "target": [0.0, 0.0, 0.0],
                    "intensity": 5.0, "cutoff_angle": 30.0},
                   {"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 1.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                      "glass": {"type": "dielectric", "ior": 1.5}},
        "objects": [
            {"shape": "quad", "origin": [-1.0, 0.0, -1.0], "edge_u": [2.0, 0.0, 0.0],
             "edge_v": [0.0, 0.0, 2.0], "material": "floor"},
            {"shape": "sphere", "center": [0.0, 1.0, 0.0], "radius": 0.5, "material": "glass",
             "transform": {"translate": [0.0, 0.1, 0.0]}},
            {"shape": "box", "min": [1.0, 0.0, 1.0], "max": [1.5, 0.5, 1.5],
             "material": {"type": "black"}},
            {"shape": "mesh", "file": "tetra.obj", "material": "floor"},
        ],
        "volumes": [{"shape": "sphere", "center": [2.0, 1.0, 0.0], "radius": 0.3, "ior": 1.1}],
        "render": {"method": "auto"},
    }


def load(data: dict, *sets: str) -> Scene:
    """Load as ``clscatter render`` does before any device work: the scene, then every
    ``[render.<method>]`` table checked by the methods."""
    from clscatter.methods import configure_scene
    scene = scene_from_dict(apply_overrides(data, sets), DATA, "<test>")
    configure_scene(scene)
    return scene


def params(scene: Scene) -> dict:
    from clscatter.methods import configure_scene
    return configure_scene(scene)


# ---- The full scene file --------------------------------------------------------------

def test_full_scene_camera_medium_render():
    s = load_scene(FULL)
    c = s.camera
    np.testing.assert_array_equal(c.origin, [0.0, 1.0, 6.0])
    np.testing.assert_array_equal(c.target, [0.0, 0.5, 0.0])
    np.testing.assert_array_equal(c.up, [0.0, 1.0, 0.0])
    assert (c.fov, c.fov_axis, c.width, c.height, c.spp) == (40.0, "y", 64, 48, 9)
    m = s.medium
    assert m.sigma_s.dtype == np.float64 and m.sigma_s.shape == (3,)
    np.testing.assert_array_equal(m.sigma_s, [0.2, 0.3, 0.4])
    np.testing.assert_array_equal(m.sigma_a, [0.1, 0.1, 0.1])
    np.testing.assert_allclose(m.kappa, [0.3, 0.4, 0.5])
    assert m.g == 0.25
    np.testing.assert_array_equal(m.bounds[0], [-5.0, 0.0, -5.0])
    np.testing.assert_array_equal(m.bounds[1], [5.0, 5.0, 8.0])
    r = s.render
    assert (r.method, r.max_depth, r.seed) == ("lsg", 8, 7)
    assert r.params["lsg"]["light_rays"] == 1_000_000
    assert r.params["lsg"]["radius"] == 0.001
    assert s.source == str(FULL)


def test_full_scene_lights():
    point, spot, sun = load_scene(FULL).lights
    assert point.type == "point"
    np.testing.assert_array_equal(point.position, [0.0, 3.0, 0.0])
    np.testing.assert_array_equal(point.power, [10.0, 9.0, 8.0])
    assert spot.type == "spot" and spot.cutoff_angle == 20.0
    np.testing.assert_array_equal(spot.power, [20.0, 20.0, 20.0])
    np.testing.assert_allclose(spot.direction, [0.0, -1.0, 0.0])     # normalised target - pos
    assert sun.type == "directional" and sun.position is None
    np.testing.assert_allclose(sun.direction, [0.0, -1.0, 0.0])      # [0,-2,0] normalised
    np.testing.assert_array_equal(sun.power, [1.5, 1.5, 1.5])


def test_full_scene_materials():
    s = load_scene(FULL)
    mats = s.materials
    assert set(mats) == {"glass", "floor", "chrome", "plain"}
    g = mats["glass"]
    assert g.type == "dielectric" and g.ior == 1.33
    np.testing.assert_array_equal(g.interior_sigma_a, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(g.interior_sigma_s, [0.05, 0.05, 0.05])
    np.testing.assert_array_equal(mats["floor"].albedo, [0.5, 0.6, 0.7])
    np.testing.assert_array_equal(mats["chrome"].reflectance, [0.9, 0.9, 0.9])
    np.testing.assert_array_equal(mats["chrome"].color, [0.9, 0.9, 0.9])
    np.testing.assert_array_equal(mats["plain"].albedo, [0.5, 0.5, 0.5])   # default albedo
    # objects share named materials; inline ones are named after their key
    assert s.objects[1].material is mats["floor"] and s.objects[3].material is mats["floor"]
    assert s.objects[2].material.type == "black"
    assert s.objects[2].material.name == "objects[2].material"
    np.testing.assert_array_equal(s.objects[5].material.albedo, [0.25, 0.25, 0.25])


def test_full_scene_shapes_and_transforms():
    s = load_scene(FULL)
    assert [o.shape for o in s.objects] == ["mesh", "sphere", "box", "quad", "sphere", "mesh"]
    assert [o.key for o in s.objects] == [f"objects[{i}]" for i in range(6)]
    for o in s.objects:
        assert o.vertices.dtype == np.float64 and o.vertices.shape[1] == 3
        assert o.faces.dtype == np.int64 and o.faces.shape[1] == 3
    # tetrahedron: scale 2, then rotate 90 deg about z, then translate (1, 2, 3):
    # (1,0,0) -> (2,0,0) -> (0,2,0) -> (1,4,3); a different order would give another point
    tet = s.objects[0]
    verts = {tuple(np.round(v, 9)) for v in tet.vertices}
    assert verts == {(1.0, 2.0, 3.0), (1.0, 4.0, 3.0), (-1.0, 2.0, 3.0), (1.0, 2.0, 5.0)}
    assert tet.normals is None                                   # flat by default
    assert s.objects[5].normals is not None                      # smooth = true
    np.testing.assert_allclose(np.linalg.norm(s.objects[5].normals, axis=1), 1.0)
    # sphere: subdivisions 2 -> 320 triangles; vertices exactly on it; exact normals
    sph = s.objects[1]
    assert len(sph.faces) == 320
    rel = sph.vertices - [0.5, 1.2, 0.0]
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), 0.4, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sph.normals, rel / 0.4, rtol=0, atol=1e-12)
    # box and quad
    assert len(s.objects[2].faces) == 12 and s.objects[2].normals is None
    np.testing.assert_array_equal(s.objects[2].vertices.min(0), [-2.0, 2.45, -2.0])
    np.testing.assert_array_equal(s.objects[2].vertices.max(0), [2.0, 2.55, 2.0])
    q = s.objects[3]
    assert len(q.faces) == 2
    np.testing.assert_array_equal(q.vertices, [[-5, 0, -5], [5, 0, -5], [5, 0, 5], [-5, 0, 5]])
    # ellipsoid (sphere scaled [2,1,1], translated): normals via the inverse transpose
    ell = s.objects[4]
    p = ell.vertices - [0.0, 1.0, -2.0]
    np.testing.assert_allclose((p / [2.0, 1.0, 1.0]) ** 2 @ np.ones(3), 1.0, atol=1e-12)
    expect = p / [4.0, 1.0, 1.0]
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    np.testing.assert_allclose(ell.normals, expect, atol=1e-12)


def test_full_scene_volumes_and_bbox():
    s = load_scene(FULL)
    mesh_vol, grid_vol = s.volumes
    assert mesh_vol.ior == 1.1 and mesh_vol.resolution == 32 and mesh_vol.key == "volumes[0]"
    np.testing.assert_array_equal(mesh_vol.sigma_a, [0.0, 0.2, 0.3])
    np.testing.assert_array_equal(mesh_vol.sigma_s, [0.0, 0.0, 0.0])
    assert len(mesh_vol.mesh.faces) == 4
    assert grid_vol.grid.shape == (4, 4, 4) and grid_vol.mesh is None
    assert grid_vol.ior == pytest.approx(1.2)
    np.testing.assert_array_equal(grid_vol.grid_bounds[0], [-1.0, -1.0, -1.0])
    lo, hi = s.bbox()
    np.testing.assert_array_equal(lo, [-5.0, -1.0, -5.0])     # the grid volume reaches y = -1
    np.testing.assert_array_equal(hi, [5.0, 4.0, 5.0])
    assert s.scene_extent() == 10.0


def test_defaults_of_a_minimal_scene(fake_methods):
    s = scene_from_dict({"camera": {"origin": [0, 0, 5], "target": [0, 0, 0]}}, DATA)
    c = s.camera
    np.testing.assert_array_equal(c.up, [0.0, 1.0, 0.0])
    assert (c.fov, c.fov_axis, c.width, c.height, c.spp) == (45.0, "x", 512, 384, 4)
    assert c.origin.dtype == np.float64                       # ints in the file become floats
    assert s.medium is None and s.lights == [] and s.objects == [] and s.bbox() is None
    assert (s.render.method, s.render.max_depth, s.render.seed) == ("auto", 16, 0)
    assert s.render.params == {}                              # tables stay raw in the scene
    m = scene_from_dict({**base(), "medium": {}, "lights": []}, DATA).medium
    np.testing.assert_array_equal(m.sigma_s, 0.0)
    assert m.g == 0.0 and m.bounds is None


def test_material_defaults():
    d = base()
    d["materials"].update({"m": {"type": "mirror"}, "d": {"type": "dielectric"},
                           "a": {"type": "diffuse"}})
    mats = load(d).materials
    np.testing.assert_array_equal(mats["m"].reflectance, [1.0, 1.0, 1.0])
    assert mats["d"].ior == 1.5
    np.testing.assert_array_equal(mats["d"].interior_sigma_a, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(mats["d"].interior_sigma_s, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(mats["a"].albedo, [0.5, 0.5, 0.5])


# ---- Shapes ------------------------------------------------------------------------------

def test_box_winding_is_outward():
    v, f, n = shapes.box(np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5]))
    assert n is None and f.shape == (12, 3)
    centre = v.mean(axis=0)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, tri.mean(axis=1) - centre) > 0)
    # signed volume (divergence theorem) equals the box volume
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert vol == pytest.approx(2.0 * 3.0 * 0.5)


def test_mirroring_transform_keeps_boxes_outward():
    d = base()
    d["objects"][2]["transform"] = {"scale": [-1.0, 1.0, 1.0], "rotate": [1, 1, 0, 33.0]}
    o = load(d).objects[2]
    tri = o.vertices[o.faces]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert vol == pytest.approx(0.5 ** 3)


def test_quad_and_transformed_quad():
    d = base()
    d["objects"][0]["transform"] = {"rotate": [1.0, 0.0, 0.0, 90.0], "translate": [0, 1, 0],
                                    "scale": 0.5}
    q = load(d).objects[0]
    # (-1,0,-1) -> scale (-0.5,0,-0.5) -> rot 90 about x: (x, -z, y)... -> (-0.5, 0.5, 0) -> +y
    np.testing.assert_allclose(q.vertices[0], [-0.5, 1.5, 0.0], atol=1e-12)


def test_sphere_default_subdivisions():
    s = load(base())
    sph = s.objects[1]
    assert len(sph.faces) == 5120
    np.testing.assert_allclose(np.linalg.norm(sph.vertices - [0, 1.1, 0], axis=1), 0.5,
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(sph.normals, axis=1), 1.0, atol=1e-12)


def test_rotation_matrix_is_right_handed():
    R = shapes.rotation_matrix(np.array([0.0, 0.0, 1.0]), 90.0)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    R = shapes.rotation_matrix(np.array([0.0, 2.0, 0.0]), 90.0)
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-15)


# ---- Overrides -----------------------------------------------------------------------------

def test_overrides_nested_and_indexed():
    s = load_scene(FULL, ["camera.resolution=[32, 24]", "lights[0].intensity=5",
                          "lights.1.cutoff_angle=10.5", "medium.bounds.max=[6, 6, 9]",
                          "objects[1].radius=0.25", "materials.floor.albedo=[0.1,0.2,0.3]"])
    assert (s.camera.width, s.camera.height) == (32, 24)
    np.testing.assert_array_equal(s.lights[0].power, [5.0, 5.0, 5.0])
    assert s.lights[1].cutoff_angle == 10.5
    np.testing.assert_array_equal(s.medium.bounds[1], [6.0, 6.0, 9.0])
    rel = s.objects[1].vertices - [0.5, 1.2, 0.0]
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), 0.25)
    np.testing.assert_array_equal(s.materials["floor"].albedo, [0.1, 0.2, 0.3])


def test_overrides_strings_bare_and_quoted():
    assert load_scene(FULL, ["render.method=raymarch"]).render.method == "raymarch"
    assert load_scene(FULL, ['render.method="epipolar"']).render.method == "epipolar"
    assert load_scene(FULL, ["camera.fov_axis=x"]).camera.fov_axis == "x"


def test_overrides_create_method_tables(fake_methods):
    s = load(base(), "render.raymarch.steps=64", "render.lsg.radius=0.0005")
    assert s.render.params["raymarch"]["steps"] == 64          # raw in the scene
    assert params(s)["raymarch"] == {**FAKE_PARAMS["raymarch"], "steps": 64}   # defaults filled
    assert params(s)["lsg"]["radius"] == 0.0005
    # a table of a reserved method that this build does not implement is an error
    with pytest.raises(SceneError) as e:
        load(base(), "render.voxel.whatever=3")
    assert e.value.key == "render.voxel"
    # render table created from nothing
    d = base()
    del d["render"]
    assert params(load(d, "render.raymarch.jitter=false"))["raymarch"]["jitter"] is False
    # int is fine where the default is a float
    assert params(load(base(), "render.raymarch.step_scale=2"))["raymarch"]["step_scale"] == 2.0


def test_override_appends_a_light():
    s = load(base(), "lights[3].type=point", "lights[3].position=[0, 1, 0]",
             "lights[3].intensity=2")
    assert len(s.lights) == 4 and s.lights[3].type == "point"


def test_overrides_do_not_touch_the_input():
    d = base()
    apply_overrides(d, ["camera.fov=10", "render.raymarch.steps=3"])
    assert d == base()


@pytest.mark.parametrize("override, key", [
    ("camera.fov", "camera.fov"),                            # no '='
    ("lights[7].intensity=1", "lights[7]"),                  # index out of range
    ("camera.fov.x=1", "camera.fov"),                        # not a table
    ("camera.resolution=[64,", "camera.resolution"),         # not TOML, not a bare word
    ("camera.foo=1", "camera.foo"),                          # caught by validation
    ("render.raymarch.bogus=1", "render.raymarch.bogus"),
    ("render.method=sideways", "render.method"),
    ("camera..fov=1", "camera..fov"),
    ("lights.x.intensity=1", "lights"),                      # array indexed by a name
    ("lights[1].type=point", "lights[1].target"),            # spot keys now unknown
])
def test_bad_overrides(override, key, fake_methods):
    with pytest.raises(SceneError) as e:
        load(base(), override)
    assert e.value.key == key
    assert key in str(e.value) and "\n" not in str(e.value)


# ---- Validation: every bad input names its dotted key, in one line ------------------------

def _set(path: str, value):
    def f(d):
        node = d
        parts = path.replace("[", ".").replace("]", "").split(".")
        for p in parts[:-1]:
            node = node[int(p)] if p.isdigit() else node[p]
        last = parts[-1]
        node[int(last) if last.isdigit() else last] = value
    return f


def _del(path: str):
    def f(d):
        node = d
        parts = path.replace("[", ".").replace("]", "").split(".")
        for p in parts[:-1]:
            node = node[int(p)] if p.isdigit() else node[p]
        del node[parts[-1]]
    return f


BAD = [
    # unknown keys and tables, at every level
    (_set("cameras", {}), "cameras"),
    (_set("camera.fvo", 40.0), "camera.fvo"),
    (_set("medium.colour", 1.0), "medium.colour"),
    (_set("medium.bounds.centre", [0, 0, 0]), "medium.bounds.centre"),
    (_set("lights[0].color", 1.0), "lights[0].color"),
    (_set("lights[0].cutoff_angle", 10.0), "lights[0].cutoff_angle"),   # spot key on a point
    (_set("materials.floor.reflectance", 1.0), "materials.floor.reflectance"),
    (_set("objects[2].material", {"type": "black", "albedo": 0.5}), "objects[2].material.albedo"),
    (_set("objects[1].min", [0, 0, 0]), "objects[1].min"),              # box key on a sphere
    (_set("objects[1].transform.shear", 1.0), "objects[1].transform.shear"),
    (_set("volumes[0].material", "floor"), "volumes[0].material"),
    (_set("render.raymarch", {"foo": 1}), "render.raymarch.foo"),
    (_set("render.magic", {"a": 1}), "render.magic"),
    (_set("render.samples", 4), "render.samples"),
    # types
    (_set("render.raymarch", {"steps": "many"}), "render.raymarch.steps"),
    (_set("render.raymarch", {"steps": 1.5}), "render.raymarch.steps"),
    (_set("render.raymarch", {"jitter": 1}), "render.raymarch.jitter"),
    (_set("render.raymarch", {"step_scale": True}), "render.raymarch.step_scale"),
    (_set("render.lsg", 3), "render.lsg"),
    (_set("camera.fov", "wide"), "camera.fov"),
    (_set("camera.fov", float("nan")), "camera.fov"),
    (_set("medium.g", True), "medium.g"),
    (_set("lights[0].position", [1.0, 2.0]), "lights[0].position"),
    (_set("lights[0].position", [1.0, 2.0, "3"]), "lights[0].position"),
    (_set("medium.sigma_s", [0.1, 0.2]), "medium.sigma_s"),
    (_set("medium.sigma_s", "thick"), "medium.sigma_s"),
    (_set("camera.resolution", [64]), "camera.resolution"),
    (_set("camera.resolution", [64.0, 48]), "camera.resolution"),
    (_set("camera.spp", 2.0), "camera.spp"),
    (_set("lights", 5), "lights"),
    (_set("materials.floor", 3), "materials.floor"),
    (_set("objects[0].material", 3), "objects[0].material"),
    (_set("objects[3].file", 7), "objects[3].file"),
    (_set("objects[3].smooth", "yes"), "objects[3].smooth"),
    # impossible values
    (_set("medium.sigma_s", -0.1), "medium.sigma_s"),
    (_set("medium.sigma_a", [0.1, -0.1, 0.1]), "medium.sigma_a"),
    (_set("medium.g", 1.0), "medium.g"),
    (_set("medium.g", -1.5), "medium.g"),
    (_set("materials.floor.albedo", -0.5), "materials.floor.albedo"),
    (_set("materials.glass.ior", 0.0), "materials.glass.ior"),
    (_set("materials.glass.interior_sigma_a", -1.0), "materials.glass.interior_sigma_a"),
    (_set("lights[0].intensity", -1.0), "lights[0].intensity"),
    (_set("lights[2].irradiance", [1, -1, 1]), "lights[2].irradiance"),
    (_set("objects[1].radius", 0.0), "objects[1].radius"),
    (_set("objects[1].subdivisions", 9), "objects[1].subdivisions"),
    (_set("camera.resolution", [0, 48]), "camera.resolution"),
    (_set("camera.resolution", [64, -1]), "camera.resolution"),
    (_set("camera.spp", 0), "camera.spp"),
    (_set("camera.fov", 0.0), "camera.fov"),
    (_set("camera.fov", 180.0), "camera.fov"),
    (_set("camera.fov_axis", "z"), "camera.fov_axis"),
    (_set("render.max_depth", -1), "render.max_depth"),
    (_set("render.seed", -3), "render.seed"),
    (_set("render.method", "magic"), "render.method"),
    (_set("lights[1].cutoff_angle", 0.0), "lights[1].cutoff_angle"),
    (_set("lights[1].cutoff_angle", 90.5), "lights[1].cutoff_angle"),
    (_set("lights[2].direction", [0.0, 0.0, 0.0]), "lights[2].direction"),
    (_set("lights[1].target", [1.0, 3.0, 0.0]), "lights[1].target"),    # == position
    (_set("camera.target", [0.0, 1.0, 6.0]), "camera.target"),           # == origin
    (_set("camera.up", [0.0, 1.0, 12.0]), "camera.up"),                  # parallel to view
    (_set("camera.up", [0.0, 0.0, 0.0]), "camera.up"),
    (_set("medium.bounds.max", [5.0, 0.0, 5.0]), "medium.bounds"),       # min >= max
    (_set("objects[2].max", [1.5, 0.0, 1.5]), "objects[2].max"),
    (_set("objects[0].edge_v", [4.0, 0.0, 0.0]), "objects[0].edge_v"),   # zero-area quad
    (_set("objects[0].edge_u", [0.0, 0.0, 0.0]), "objects[0].edge_v"),
    (_set("objects[1].transform.scale", 0.0), "objects[1].transform.scale"),
    (_set("objects[1].transform.rotate", [0, 0, 0, 30.0]), "objects[1].transform.rotate"),
    (_set("objects[1].transform.rotate", [0, 1, 0]), "objects[1].transform.rotate"),
    (_set("volumes[0].ior", -1.0), "volumes[0].ior"),
    (_set("volumes[0].resolution", 0), "volumes[0].resolution"),
    (_set("volumes[0].shape", "quad"), "volumes[0].shape"),
    (_set("volumes[0]", {"ior": 1.1}), "volumes[0].shape"),
    (_set("volumes[0]", {"grid": "nope.npy", "bounds": {"min": [0, 0, 0], "max": [1, 1, 1]}}),
     "volumes[0].grid"),
    (_set("volumes[0]", {"grid": "ior_grid.npy", "ior": 1.2,
                         "bounds": {"min": [0, 0, 0], "max": [1, 1, 1]}}), "volumes[0].ior"),
    # a directional light in an unbounded medium
    (_del("medium.bounds"), "lights[2].type"),
    # names and kinds
    (_set("objects[0].material", "marble"), "objects[0].material"),
    (_set("objects[0].shape", "cone"), "objects[0].shape"),
    (_set("lights[0].type", "area"), "lights[0].type"),
    (_set("materials.floor.type", "plastic"), "materials.floor.type"),
    # missing required keys
    (_del("lights[0].position"), "lights[0].position"),
    (_del("lights[0].type"), "lights[0].type"),
    (_del("lights[1].cutoff_angle"), "lights[1].cutoff_angle"),
    (_del("objects[0].material"), "objects[0].material"),
    (_del("objects[0].shape"), "objects[0].shape"),
    (_del("objects[1].radius"), "objects[1].radius"),
    (_del("materials.floor.type"), "materials.floor.type"),
    (_del("camera.origin"), "camera.origin"),
    (_del("camera"), "camera"),
    (_del("medium.bounds.min"), "medium.bounds.min"),
    # files
    (_set("objects[3].file", "missing.obj"), "objects[3].file"),
    (_set("objects[3].file", "full_scene.toml"), "objects[3].file"),   # not a mesh format
]


@pytest.mark.parametrize("mutate, key", BAD, ids=[k for _, k in BAD])
def test_bad_scene(mutate, key, fake_methods):
    d = base()
    load(d)                     # the base itself is valid
    mutate(d)
    with pytest.raises(SceneError) as e:
        load(d)
    assert e.value.key == key
    msg = str(e.value)
    assert msg.startswith(key + ": ") and "\n" not in msg


def test_missing_mesh_message_names_the_path():
    d = base()
    d["objects"][3]["file"] = "models/missing.obj"
    with pytest.raises(SceneError, match="missing.obj"):
        load(d)


def test_empty_mesh_is_an_error(tmp_path):
    (tmp_path / "empty.obj").write_text("# nothing\nv 0 0 0\n")
    d = base()
    d["objects"][3]["file"] = "empty.obj"
    with pytest.raises(SceneError) as e:
        scene_from_dict(d, tmp_path)
    assert e.value.key == "objects[3].file" and "\n" not in str(e.value)


@pytest.mark.parametrize("text, where", [
    ('[camera]\norigin = [0, 0, 1]\ntarget = [0, 0\n', "line 3"),        # unclosed at EOF
    ('[camera]\norigin = [0, 0 1]\n', "line 2, column"),
    ('[camera]\nfov = 1\nfov = 2\n', "line 3"),                          # duplicate key
])
def test_bad_toml_names_file_and_line(tmp_path, text, where):
    p = tmp_path / "broken.toml"
    p.write_text(text)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert "broken.toml" in e.value.key and where in msg and "\n" not in msg


def test_missing_scene_file(tmp_path):
    p = tmp_path / "nope.toml"
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert "nope.toml" in str(e.value) and "not found" in str(e.value)


def test_unknown_builtin():
    with pytest.raises(SceneError, match="builtin:nope"):
        load_scene("builtin:nope")


def test_real_method_params_are_checked():
    from clscatter.methods import all_methods, configure
    known = all_methods()
    assert {"raymarch", "lsg", "vpm", "epipolar"} <= set(known)
    for name, cls in known.items():
        assert configure(name, None) == {p.name: p.default for p in cls.PARAMS}
        with pytest.raises(SceneError) as e:
            load(base(), f"render.{name}.no_such_parameter=1")
        assert e.value.key == f"render.{name}.no_such_parameter"


# ---- Built-in scenes ----------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_loads_and_is_sane(name):
    s = load_scene(f"builtin:{name}")
    assert s.source == f"builtin:{name}"
    # the paper-scale scene keeps the LSG paper's image size; the others are quick
    size = (512, 512, 4) if name == "paper_bunny" else (320, 240, 4)
    assert (s.camera.width, s.camera.height, s.camera.spp) == size
    assert s.lights
    if s.density_volumes():                  # a heterogeneous medium instead of [medium]
        assert all(np.any(v.sigma_s > 0) and v.density.max() > 0 for v in s.density_volumes())
    else:
        assert s.medium is not None and np.all(s.medium.sigma_s > 0)
    bb = s.bbox()
    if name == "airlight":
        assert bb is None and s.objects == []
        return
    lo, hi = bb
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)
    assert 1.0 < s.scene_extent() < 100.0
    assert not np.all((s.camera.origin >= lo) & (s.camera.origin <= hi)) or name != "shafts"
    for light in s.lights:
        if light.position is not None:
            assert np.all(np.isfinite(light.position))


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_toml_round_trips(name, tmp_path):
    text = builtin_toml(name)
    assert tomllib.loads(text) == BUILTIN[name]()
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    a, b = load_scene(p), load_scene(f"builtin:{name}")
    assert a.triangle_count() == b.triangle_count()
    for oa, ob in zip(a.objects, b.objects):
        np.testing.assert_array_equal(oa.vertices, ob.vertices)


def test_default_builtin_and_override():
    assert DEFAULT_BUILTIN == "shafts" and DEFAULT_BUILTIN in BUILTIN
    s = load_scene("builtin:shafts", ["camera.resolution=[32,24]", "render.method=raymarch"])
    assert (s.camera.width, s.camera.height, s.render.method) == (32, 24, "raymarch")
    sun = s.lights[0]
    assert sun.type == "directional" and s.medium.bounds is not None
    # every light path into the medium passes the grille: the grille overhangs the medium
    # box by more than the light's horizontal drift over the box's height
    lo, hi = s.medium.bounds
    drift = (hi[1] - lo[1] + 0.1) * np.abs(sun.direction[[0, 2]] / sun.direction[1])
    grille = np.concatenate([o.vertices for o in s.objects if o.material.type == "black"])
    assert np.all(grille.min(0)[[0, 2]] <= lo[[0, 2]] - drift)
    assert np.all(grille.max(0)[[0, 2]] >= hi[[0, 2]] + drift)
