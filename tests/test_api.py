"""The public Python API (clscatter.load / render / write / Session): scenes load from a
built-in name, a TOML file and a dict; renders and writes behave as the command line's;
a Session's params use the scene format's key names and its warm re-renders equal fresh
ones; ``import clscatter`` stays cheap."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import clscatter
from clscatter.errors import ClscatterError, SceneError
from clscatter.io.image import read_image
from clscatter.methods import all_methods
from clscatter.scene import scene_source

DATA = Path(__file__).resolve().parent / "data"
SMALL = ["camera.resolution=[32,24]", "camera.spp=1"]
# warm vs fresh: the same code on the same device; only float32 summation order may differ
RTOL, ATOL = 1e-5, 1e-7


@pytest.fixture(scope="module")
def occluder():
    return clscatter.load("builtin:occluder", SMALL)


def test_load_from_builtin_toml_path_and_dict():
    spec = clscatter.load("builtin:caustic_sphere", SMALL)
    assert spec.source == "builtin:caustic_sphere"
    assert (spec.scene.camera.width, spec.scene.camera.height, spec.scene.camera.spp) == (32, 24, 1)
    assert spec.camera.width == 32 and len(spec.objects) == 2      # Scene-like reads
    assert spec.data["camera"]["resolution"] == [32, 24]            # raw data, overrides in

    toml = clscatter.load(DATA / "full_scene.toml", SMALL)
    assert toml.base_dir == DATA and len(toml.scene.objects) == 6
    assert toml.data["lights"][1]["target"] == [2.0, 0.0, 0.0]     # the format's key, kept

    raw, _ = scene_source("builtin:caustic_sphere")
    before = repr(raw)
    from_dict = clscatter.load(raw, SMALL)
    assert repr(raw) == before                                      # the input is not touched
    assert from_dict.source == "<dict>" and from_dict.data == spec.data
    np.testing.assert_array_equal(from_dict.scene.objects[1].vertices,
                                  spec.scene.objects[1].vertices)

    derived = clscatter.load(spec, ["camera.fov=30"])               # from a SceneSpec
    assert derived.scene.camera.fov == 30.0 and spec.scene.camera.fov == 50.0
    with pytest.raises(AttributeError):
        spec.source = "elsewhere"                                   # read-only


def test_load_refuses_bad_scenes_naming_the_key():
    raw, _ = scene_source("builtin:occluder")
    raw["medium"]["g"] = 2.0
    with pytest.raises(SceneError) as e:
        clscatter.load(raw)
    assert e.value.key == "medium.g" and "\n" not in str(e.value)
    with pytest.raises(SceneError) as e:
        clscatter.load("builtin:occluder", ["camera.fovv=3"])
    assert e.value.key == "camera.fovv"
    with pytest.raises(TypeError):
        clscatter.load(clscatter.load("builtin:occluder").scene)     # a Scene has no raw data


def test_render_gives_a_finite_image_and_stats_naming_the_method(occluder, engine):
    res = clscatter.render(occluder, method="auto", engine=engine)
    assert isinstance(res, clscatter.RenderResult)
    assert res.image.shape == (24, 32, 3) and res.image.dtype == np.float32
    assert np.isfinite(res.image).all() and res.image.max() > 0.0
    assert res.stats["method"] == "raymarch" and res.stats["requested_method"] == "auto"
    with pytest.raises(SceneError) as e:
        clscatter.render(occluder, method="nope", engine=engine)
    assert e.value.key == "render.method"


def test_write_all_formats_or_nothing(occluder, engine, tmp_path):
    res = clscatter.render(occluder, engine=engine)
    outs = [tmp_path / n for n in ("a.exr", "a.npy", "a.pfm", "a.png")]
    assert clscatter.write(res, *outs) == outs
    for p in outs[:3]:                                              # linear formats: exact
        np.testing.assert_array_equal(read_image(p), res.image)
    assert read_image(outs[3]).shape == res.image.shape

    bad = tmp_path / "bad"
    bad.mkdir()
    for paths in ([bad / "b.png", bad / "b.jpg"],                   # unknown suffix
                  [bad / "c.exr", bad / "c.exr"],                   # the same file twice
                  [bad / "d.png", bad / "missing" / "d.exr"]):      # no such folder
        with pytest.raises(ClscatterError):
            clscatter.write(res, *paths)
    with pytest.raises(ClscatterError):                             # fails while writing
        clscatter.write(np.zeros((4, 4, 2), np.float32), bad / "e.npy", bad / "e.exr")
    assert list(bad.iterdir()) == []                                # nothing, not even staging


def test_params_hold_format_keys_and_every_method_default(engine):
    with clscatter.Session(clscatter.load(DATA / "full_scene.toml", SMALL), engine=engine) as s:
        p = s.params
        assert p["camera.resolution"] == [32, 24] and p["camera.fov"] == 40.0
        assert p["lights[0].position"] == [0.0, 3.0, 0.0]
        assert p["lights[1].target"] == [2.0, 0.0, 0.0] and p["lights[1].intensity"] == 20.0
        assert p["materials.glass.ior"] == 1.33
        assert p["objects[0].transform.scale"] == 2.0
        assert p["objects[2].material.type"] == "black"
        assert p["medium.bounds.min"] == [-5.0, 0.0, -5.0]
        assert p["render.lsg.light_rays"] == 1_000_000                # the file's value
        for name, cls in all_methods().items():
            for par in cls.PARAMS:
                key = f"render.{name}.{par.name}"
                assert key in p
                if (name, par.name) not in {("lsg", "light_rays"), ("lsg", "radius")}:
                    assert p[key] == par.default, key
        assert not any(".power" in k for k in p)                    # no Scene field names
        p["camera.fov"] = 10.0
        assert s.params["camera.fov"] == 40.0                       # a copy


def test_a_light_move_renders_warm_and_equals_a_fresh_render(occluder, engine):
    with clscatter.Session(occluder, engine=engine) as s:
        first = s.render()
        assert "prepare_scene" in first.stats["stages_run"]
        params = s.params
        assert s.update(params) == []                               # nothing changed
        params["lights[0].position"] = [0.5, 2.5, 0.3]
        assert s.update(params) == ["lights[0].position"]           # only the changed key
        warm = s.render()
        assert "bvh" in warm.stats["reused"]
        assert "prepare_scene" not in warm.stats["stages_run"]
        assert s.scene.data["lights"][0]["position"] == [0.5, 2.5, 0.3]
    fresh = clscatter.render(clscatter.load("builtin:occluder",
                                            SMALL + ["lights[0].position=[0.5,2.5,0.3]"]),
                             engine=engine)
    assert np.abs(fresh.image - first.image).max() > 1e-3           # the move shows
    np.testing.assert_allclose(warm.image, fresh.image, rtol=RTOL, atol=ATOL)


def test_typed_values_and_method_parameters(occluder, engine):
    with clscatter.Session(occluder, engine=engine) as s:
        s.render()
        applied = s.update({"lights[0].position": np.array([0.2, 2.5, 0.1]),
                            "render.raymarch.steps": 16})
        assert applied == ["lights[0].position", "render.raymarch.steps"]
        assert s.params["lights[0].position"] == [0.2, 2.5, 0.1]   # stored as a list
        assert s.scene.data["render"]["raymarch"] == {"steps": 16}
        s.render()
        assert s.update({"render.raymarch.steps": 8}) == ["render.raymarch.steps"]
        res = s.render()
        assert res.stats["stages_run"] == ["raymarch"]              # only the pass ran
        assert {"bvh", "view_paths"} <= set(res.stats["reused"])


@pytest.mark.parametrize("change, key", [
    ({"medium.g": 3.0}, "medium.g"),                                # out of range
    ({"lights[0].position": [1.0, 2.0]}, "lights[0].position"),     # wrong length
    ({"camera.spp": 1.5}, "camera.spp"),                            # wrong type
    ({"camera.fovv": 30.0}, "camera.fovv"),                         # unknown key
    ({"render.lsg.light_ray": 10}, "render.lsg.light_ray"),         # unknown parameter
    ({"foo.bar": 1}, "foo.bar"),                                    # unknown table
    ({"lights[3].position": [0, 1, 0]}, "lights[3].position"),     # index out of range
    ({"camera.fov.x": 1}, "camera.fov.x"),                          # through a number
    ({"render.method": "nope"}, "render.method"),                   # unknown method
    ({"camera.fov": 30.0, "medium.g": -2.0}, "medium.g"),           # good + bad: neither
])
def test_a_bad_change_names_the_key_and_leaves_the_session(occluder, engine, change, key):
    with clscatter.Session(occluder, engine=engine) as s:
        before = s.render().image
        params = s.params
        with pytest.raises(SceneError) as e:
            s.update(change)
        assert e.value.key == key and "\n" not in str(e.value)
        assert str(e.value).startswith(f"{key}: ")
        assert s.params == params
        np.testing.assert_array_equal(s.render().image, before)


def test_import_is_lazy_and_names_resolve():
    code = ("import sys, clscatter; "
            "print('pyopencl' in sys.modules, 'numpy' in sys.modules, "
            "'clscatter.api' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.split() == ["False", "False", "False"]
    from clscatter import api
    assert clscatter.render is api.render and callable(clscatter.render)
    assert clscatter.load is api.load and clscatter.Session is api.Session
    assert set(clscatter.__all__) == {*clscatter._LAZY, "__version__"}
    for name in clscatter.__all__:
        assert getattr(clscatter, name) is not None and name in dir(clscatter)
    with pytest.raises(AttributeError):
        getattr(clscatter, "no_such_name")  # noqa: B009
    from clscatter import device  # subpackages still import
    assert device.__name__ == "clscatter.device"
