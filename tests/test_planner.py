"""auto: passes chosen by what the scene contains."""
from __future__ import annotations

import copy
from pathlib import Path

from clscatter.prepared import prepare_scene
from clscatter.planner import plan
from clscatter.scene import scene_from_dict

HERE = Path(__file__).resolve().parent
BASE = {
    "camera": {"origin": [0.0, 1.0, 5.0], "target": [0.0, 0.5, 0.0], "resolution": [8, 6], "spp": 1},
    "medium": {"sigma_s": 0.1, "sigma_a": 0.0, "bounds": {"min": [-3, -1, -3], "max": [3, 3, 3]}},
    "lights": [{"type": "point", "position": [0.0, 2.0, 0.0], "intensity": 5.0}],
    "objects": [{"shape": "sphere", "center": [0.0, 0.5, 0.0], "radius": 0.4,
                 "material": {"type": "diffuse"}}],
}


def _plan(engine, d, requested="auto"):
    ps = prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "p"), engine)
    try:
        return plan(ps, requested)
    finally:
        ps.release()


def test_no_medium_or_lights_skips_everything(engine):
    d = copy.deepcopy(BASE)
    del d["medium"]
    assert _plan(engine, d)[0] == []
    d = copy.deepcopy(BASE)
    d["lights"] = []
    assert _plan(engine, d)[0] == []
    d = copy.deepcopy(BASE)
    d["medium"]["sigma_s"] = 0.0                  # a void medium is no medium
    assert _plan(engine, d)[0] == []


def test_point_light_diffuse_scene_is_raymarched_without_caustics(engine):
    passes, notes = _plan(engine, BASE)
    assert [(p.method, p.role) for p in passes] == [("raymarch", "direct")]
    assert any("caustic pass skipped" in n for n in notes)


def test_specular_objects_add_an_lsg_caustic_pass(engine):
    d = copy.deepcopy(BASE)
    d["objects"][0]["material"] = {"type": "dielectric", "ior": 1.5}
    passes, _ = _plan(engine, d)
    assert [(p.method, p.role) for p in passes] == [("raymarch", "direct"), ("lsg", "caustics")]
    assert passes[1].params == {"min_light_depth": 1}
    passes, notes = _plan(engine, d, "raymarch")      # explicit: alone, with a warning
    assert [p.method for p in passes] == ["raymarch"] and any("caustics" in n for n in notes)


def test_bad_method_parameters_name_their_key():
    import pytest
    from clscatter.errors import SceneError
    from clscatter.methods import get_method
    for method, key, value in (("raymarch", "steps", 0), ("lsg", "radius", -1.0),
                               ("vpm", "knn", 1), ("epipolar", "svd_terms", 0)):
        with pytest.raises(SceneError, match=f"render.{method}.{key}: .*got"):
            get_method(method)({key: value})
