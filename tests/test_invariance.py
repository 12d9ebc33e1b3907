"""Translation/scale invariance of every medium method, and of LSG's automatic radius:
the same physical scene moved and scaled (and, for the radius, with far-away objects
added) renders the same image. Every kernel works in the normalised frame
(clscatter/scene/normalised.py), so a method that derives no length from the world units
sees the same numbers up to float rounding."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from clscatter.methods import all_methods
from clscatter.pipeline.render import render
from clscatter.scene import scene_from_dict
from clscatter.scene.builtin import BUILTIN

HERE = Path(__file__).resolve().parent

METHODS = ["raymarch", "epipolar", "lsg", "vpm", "raymap", "photonmap", "voxel"]


def transform_scene(d: dict, scale: float, offset: float) -> dict:
    """The scene dict with every length multiplied by ``scale`` and then every point moved by
    (offset, -offset/2, offset/4): camera origin and target, light positions and targets,
    medium bounds, every object's and volume's shape keys (centre, radius, min/max,
    origin, edges, grid bounds) or, where it has a ``transform``, that transform (scale x
    ``scale``, translation -> scale * translation + offset; its shape keys stay in the
    shape's own frame). Coefficients (medium, volume and dielectric interior sigma_s and
    sigma_a) divide by ``scale``, so every optical depth stays; point and spot intensities
    multiply by scale^2, so the irradiance at the scaled distances stays (directional
    irradiance is unchanged). The radiance of every pixel is then physically the same."""
    d = copy.deepcopy(d)
    off = np.array([offset, -0.5 * offset, 0.25 * offset])

    def pt(v):
        return [float(x) for x in np.asarray(v, float) * scale + off]

    def vec(v):
        return [float(x) for x in np.asarray(v, float) * scale]

    def coef(v):
        return (np.asarray(v, float) / scale).tolist()

    def shape(o):
        if "transform" in o:
            t = o["transform"]
            sc = t.get("scale", 1.0)
            t["scale"] = vec(sc) if isinstance(sc, list) else sc * scale
            t["translate"] = pt(t.get("translate", [0.0, 0.0, 0.0]))
            return
        for k in ("center", "min", "max", "origin"):
            if k in o:
                o[k] = pt(o[k])
        for k in ("edge_u", "edge_v"):
            if k in o:
                o[k] = vec(o[k])
        if "radius" in o:
            o["radius"] = o["radius"] * scale
        if "bounds" in o:
            o["bounds"] = {k: pt(v) for k, v in o["bounds"].items()}

    def interior(mat):
        if isinstance(mat, dict):
            for k in ("interior_sigma_s", "interior_sigma_a"):
                if k in mat:
                    mat[k] = coef(mat[k])

    cam = d["camera"]
    cam["origin"], cam["target"] = pt(cam["origin"]), pt(cam["target"])
    if "medium" in d:
        m = d["medium"]
        for k in ("sigma_s", "sigma_a"):
            if k in m:
                m[k] = coef(m[k])
        if "bounds" in m:
            m["bounds"] = {k: pt(v) for k, v in m["bounds"].items()}
    for light in d.get("lights", []):
        for k in ("position", "target"):
            if k in light:
                light[k] = pt(light[k])
        if "intensity" in light:
            light["intensity"] = (np.asarray(light["intensity"], float) * scale ** 2).tolist()
    for mat in d.get("materials", {}).values():
        interior(mat)
    for o in d.get("objects", []):
        shape(o)
        interior(o.get("material"))
    for v in d.get("volumes", []):
        shape(v)
        for k in ("sigma_s", "sigma_a"):
            if k in v:
                v[k] = coef(v[k])
    return d


def _assert_similar(a, b, scale: float, offset: float) -> None:
    """The loaded scene ``b`` is ``a`` scaled and moved, key by key (so the transform above
    missed nothing: every vertex, light, bound and coefficient)."""
    off = np.array([offset, -0.5 * offset, 0.25 * offset])

    def same_pt(p, q):
        tol = 1e-12 * (abs(offset) + 10.0 * scale)
        assert np.allclose(np.asarray(q), np.asarray(p) * scale + off, rtol=0, atol=tol)

    same_pt(a.camera.origin, b.camera.origin)
    same_pt(a.camera.target, b.camera.target)
    for oa, ob in zip(a.objects, b.objects, strict=True):
        same_pt(oa.vertices, ob.vertices)
        assert np.allclose(ob.material.interior_sigma_a * scale, oa.material.interior_sigma_a)
        assert np.allclose(ob.material.interior_sigma_s * scale, oa.material.interior_sigma_s)
    for va, vb in zip(a.volumes, b.volumes, strict=True):
        if va.mesh is not None:
            same_pt(va.mesh.vertices, vb.mesh.vertices)
        assert np.allclose(vb.sigma_s * scale, va.sigma_s)
        assert np.allclose(vb.sigma_a * scale, va.sigma_a)
    for la, lb in zip(a.lights, b.lights, strict=True):
        if la.position is not None:
            same_pt(la.position, lb.position)
        k = scale ** 2 if la.type != "directional" else 1.0
        assert np.allclose(lb.power, la.power * k)
    if a.medium is not None:
        assert np.allclose(b.medium.sigma_s * scale, a.medium.sigma_s)
        assert np.allclose(b.medium.sigma_a * scale, a.medium.sigma_a)
        if a.medium.bounds is not None:
            same_pt(a.medium.bounds[0], b.medium.bounds[0])
            same_pt(a.medium.bounds[1], b.medium.bounds[1])


def _max_rel(a, b):
    """Largest pixel difference relative to the reference image's largest value."""
    return float(np.abs(a - b).max() / np.abs(b).max())


def _nmse(a, b):
    return float(((a - b) ** 2).mean() / b.mean() ** 2)


# Per method, a small built-in scene that exercises what the method is for: a glass ball
# under a point light in a medium box (caustics through glass for lsg, vpm, the photon
# and ray maps' floor caustic; glass on the view paths for raymarch); a spot light with a
# rotated box occluder for epipolar (which takes only spot and directional lights); a
# graded-index sphere volume with its own coefficients for voxel.
METHOD_SCENES = {"raymarch": "caustic_sphere", "epipolar": "spotlight", "lsg": "caustic_sphere",
                 "vpm": "caustic_sphere", "raymap": "caustic_sphere",
                 "photonmap": "caustic_sphere", "voxel": "volume_sphere"}
# quick settings, those of tests/golden_cases.py QUICK
QUICK = {"raymarch": {"raymarch": {"steps": 16}}, "epipolar": {},
         "lsg": {"lsg": {"light_rays": 4000}}, "vpm": {"vpm": {"photons": 20000}},
         "raymap": {"raymap": {"photons": 4000}, "lsg": {"light_rays": 4000}},
         "photonmap": {"photonmap": {"photons": 4000}, "lsg": {"light_rays": 4000}},
         "voxel": {"voxel": {"resolution": 16, "photons": 1024, "outer_resolution": 16}}}
# (scale, offset): translated by 1e4 and 1e6, scaled by 1e-3 and 1e3, and two of both
TRANSFORMS = [(1.0, 1e4), (1.0, 1e6), (1e-3, 0.0), (1e3, 0.0), (1e-3, 1e2), (1e3, -1e4)]
# Float tolerance on the largest pixel difference relative to the image's largest value.
# Measured (24 x 18, 1 spp, quick settings, render seeds 0-9, every transform above): 0
# (bit-identical) for every method and transform except translation by 1e6, where
# raymarch 6.4e-9, vpm 1.9e-8, lsg 4.0e-8, photonmap 4.0e-8, raymap 5.9e-8 (float64
# rounding of the world coordinates reaching float32 in a few samples), and voxel, which
# differs by up to 1.2e-7 under every transform and also between two renders of the same
# scene (its photon deposits are float atomics, summed in any order); epipolar 0 at
# every transform. The custom SCENE below: worst 1.2e-7 (lsg, raymap, photonmap at 1e6).
# Bound ~3x the worst. (Not measured here, out of the contract's range: scale 1e-3
# *and* offset 1e6 together leave float64 only ~7 digits of the scene and differ by up to
# 2e-5.) A 5% brighter light differs by 5e-2, 1e5 x the bound.
FLOAT_TOL = 4e-7


def _quick_builtin(method: str) -> dict:
    d = BUILTIN[METHOD_SCENES[method]]()
    d["camera"].update(resolution=[24, 18], spp=1)
    d["render"].update(seed=7, **copy.deepcopy(QUICK[method]))
    return d


def test_every_packaged_method_is_covered():
    """Every method the package registers (not those test modules add, like toyfog)."""
    packaged = {name for name, cls in all_methods().items()
                if cls.__module__.startswith("clscatter.")}
    assert packaged == set(METHODS) == set(METHOD_SCENES)


@pytest.mark.parametrize("method", METHODS)
def test_every_method_is_translation_and_scale_invariant(engine, method):
    """Each method on its small built-in scene: translated by 1e4 and by 1e6, scaled by
    1e-3 and by 1e3 (and scaled and moved together), the image is finite and equals the
    untransformed one within FLOAT_TOL of its largest value (float rounding; the
    measurements are with FLOAT_TOL). The bound can fail: the same scene with every light
    5% brighter exceeds it by orders of magnitude."""
    d = _quick_builtin(method)
    s0 = scene_from_dict(copy.deepcopy(d), HERE, "inv")
    base = render(s0, method, engine=engine, show_progress=False)
    assert np.isfinite(base.image).all() and base.medium.max() > 0
    assert base.stats["method"].split("+")[0] == method, base.stats["method"]
    rows = []
    for scale, offset in TRANSFORMS:
        s1 = scene_from_dict(transform_scene(d, scale, offset), HERE, "inv")
        _assert_similar(s0, s1, scale, offset)
        res = render(s1, method, engine=engine, show_progress=False)
        assert np.isfinite(res.image).all(), (method, scale, offset)
        err = _max_rel(res.image, base.image)
        rows.append((scale, offset, err, _nmse(res.image, base.image)))
    print(f"\n{method} on {METHOD_SCENES[method]}: " + "; ".join(
        f"x{s:g} +{o:g}: max {e:.2e} (nmse {n:.1e})" for s, o, e, n in rows))
    for scale, offset, err, _ in rows:
        assert err < FLOAT_TOL, (method, scale, offset, err)
    brighter = copy.deepcopy(d)
    for light in brighter["lights"]:
        k = "intensity" if "intensity" in light else "irradiance"
        light[k] = (np.asarray(light[k], float) * 1.05).tolist()
    res = render(scene_from_dict(brighter, HERE, "inv"), method, engine=engine,
                 show_progress=False)
    err = _max_rel(res.image, base.image)
    print(f"{method}: 5% brighter light: max {err:.2e}")
    assert err > 1000 * FLOAT_TOL, (method, err)


SCENE = {
    "camera": {"origin": [0.0, 1.2, 4.5], "target": [0.0, 0.8, 0.0], "up": [0.0, 1.0, 0.0],
               "fov": 50.0, "resolution": [32, 24], "spp": 1},
    "medium": {"sigma_s": [0.3, 0.25, 0.2], "sigma_a": 0.03, "g": 0.2,
               "bounds": {"min": [-2.0, 0.0, -2.0], "max": [2.0, 2.8, 2.0]}},
    "lights": [{"type": "spot", "position": [0.2, 2.6, 0.1], "target": [0.0, 0.0, 0.0],
                "intensity": [12.0, 10.0, 8.0], "cutoff_angle": 30.0}],
    "objects": [
        {"shape": "sphere", "center": [0.0, 1.1, 0.0], "radius": 0.45,
         "material": {"type": "dielectric", "ior": 1.5}},
        {"shape": "box", "min": [0.7, 0.0, -0.6], "max": [1.1, 0.9, -0.2],
         "material": {"type": "diffuse", "albedo": 0.5}},
        {"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
         "edge_v": [0.0, 0.0, 4.0], "material": {"type": "diffuse", "albedo": 0.6}},
    ],
    "render": {"lsg": {"light_rays": 20000}, "vpm": {"photons": 100000},
               "epipolar": {}, "raymarch": {"steps": 16},
               "raymap": {"photons": 4000}, "photonmap": {"photons": 4000},
               "voxel": {"resolution": 16, "photons": 1024, "outer_resolution": 16}},
}

MOVES = [(1e-3, 1e2), (1e3, -1e4), (1.0, 1e6)]


def _render(d, method, **lsg):
    d = copy.deepcopy(d)
    d["render"]["lsg"] = {**d["render"]["lsg"], **lsg}
    return render(scene_from_dict(d, HERE, "inv"), method, show_progress=False)


@pytest.mark.parametrize("method", METHODS)
def test_custom_scene_is_translation_and_scale_invariant(engine, method):
    """A spot light, a glass ball and a box in a medium box: scaled by 1e-3 and moved by
    1e2, scaled by 1e3 and moved by -1e4, moved by 1e6: the same image within FLOAT_TOL.
    LSG's automatic radius comes out the same in the normalised frame (1e-4)."""
    base = render(scene_from_dict(copy.deepcopy(SCENE), HERE, "inv"), method, engine=engine,
                  show_progress=False)
    assert np.isfinite(base.image).all() and base.medium.max() > 0
    for scale, offset in MOVES:
        res = render(scene_from_dict(transform_scene(SCENE, scale, offset), HERE, "inv"),
                     method, engine=engine, show_progress=False)
        assert np.isfinite(res.image).all()
        err = _max_rel(res.image, base.image)
        assert err < FLOAT_TOL, (method, scale, offset, err)
        if method == "lsg":
            assert res.stats["lsg_radius"] == pytest.approx(base.stats["lsg_radius"], rel=1e-4)


FAR = [{"shape": "box", "min": [40.0, 0.0, -60.0], "max": [44.0, 30.0, -56.0],
        "material": {"type": "diffuse", "albedo": 0.5}},
       {"shape": "sphere", "center": [-50.0, 5.0, -80.0], "radius": 3.0,
        "material": {"type": "diffuse", "albedo": 0.5}}]


def test_automatic_radius_ignores_scale_and_far_objects(engine):
    """LSG caustic pass (targeted, automatic radius) of the same physical scene at scale
    1e-3, 1 and 1e3: the radius in world units scales with the scene (relative 1e-3) and
    the images agree within the noise (normalised MSE below half that between two
    independent ray sets; measured < 1e-3 of it).

    With two diffuse objects added ~60 units away (outside the medium, out of direct
    view; the bounding box grows ~25x) the automatic radius stays the same in world
    units (measured 0.15% apart, as the pilot's medians see a few diverging view paths;
    bound 2%), and the image is close to the one rendered with exactly the first scene's
    world radius (measured 2.6x the noise, from that 0.15%; bound 10x). (The images
    with and without the far objects differ by ~180x the noise for reasons that are not
    the radius: the normalised frame is 25x coarser, so some deep glass chains of the
    light and view tracers end differently, as they do for raymarch: a property of
    the tracers.) The old rule, a fixed fraction of the bounding box (radius = 0.003),
    grows the radius 25x with the far objects: that changes the image by 1.5e6x the
    noise (bound 1000x)."""
    d = copy.deepcopy(SCENE)
    lsg = {"min_light_depth": 1}
    ref = _render(d, "lsg", **lsg)
    other = _render(d, "lsg", light_seed=1, **lsg)
    noise = _nmse(other.medium, ref.medium)
    assert noise > 0 and ref.medium.max() > 0
    r_world = ref.stats["lsg_radius_world"]
    for s in (1e-3, 1e3):
        res = _render(transform_scene(d, s, 0.0), "lsg", **lsg)
        err = _nmse(res.medium, ref.medium)
        assert err < 0.5 * noise, (s, err, noise)
        assert res.stats["lsg_radius_world"] == pytest.approx(s * r_world, rel=1e-3)
    far = copy.deepcopy(d)
    far["objects"] = far["objects"] + copy.deepcopy(FAR)
    auto = _render(far, "lsg", **lsg)
    assert auto.stats["lsg_radius_world"] == pytest.approx(r_world, rel=0.02)
    extent = scene_from_dict(copy.deepcopy(far), HERE, "inv").scene_extent()
    same_r = _render(far, "lsg", min_light_depth=1, radius=r_world / extent)
    bbox_rule = _render(far, "lsg", min_light_depth=1, radius=0.003)
    e_auto, e_bbox = _nmse(auto.medium, same_r.medium), _nmse(bbox_rule.medium, same_r.medium)
    assert e_auto < 10 * noise and e_bbox > 1000 * noise, (e_auto, e_bbox, noise)
