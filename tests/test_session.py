"""The warm path: after each kind of change a session re-runs only what the change
invalidates, and its image equals a fresh render of the changed scene."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.errors import SceneError
from clscatter.pipeline.render import render
from clscatter.pipeline.session import Cancelled, RenderSession
from clscatter.scene import load_scene

SMALL = ["camera.resolution=[40,30]", "camera.spp=1"]

# (change, stages that must run, stages that must be reused)
CHANGES = [
    # a light change re-shades the recorded diffuse hits: no camera path is traced
    (["lights[0].position=[0.5,2.5,0.3]"], {"upload_lights", "shade_hits", "raymarch"},
     {"bvh", "view_paths"}),
    (["camera.origin=[0.3,1.2,5.5]"], {"upload_camera", "view_paths", "raymarch"}, {"bvh"}),
    (["medium.sigma_s=0.3"], {"upload_medium", "view_paths", "raymarch"}, {"bvh"}),
    (["materials.floor.albedo=0.9"], {"upload_materials", "view_paths", "raymarch"}, {"bvh"}),
    (["render.raymarch.steps=16"], {"raymarch"}, {"bvh", "view_paths"}),
    (["objects[1].radius=0.7"], {"prepare_scene", "view_paths", "raymarch"}, set()),
]


@pytest.fixture(scope="module")
def session(engine):
    s = RenderSession.from_source("builtin:occluder", SMALL, engine=engine)
    s.render(show_progress=False)
    yield s
    s.close()


@pytest.mark.parametrize("change, runs, kept", CHANGES, ids=[c[0][0] for c in CHANGES])
def test_warm_render_reruns_only_what_changed(session, engine, change, runs, kept):
    session.set(change)
    warm = session.render(show_progress=False)
    ran = set(warm.stats["stages_run"])
    assert runs <= ran, (ran, runs)
    assert not (ran & {"prepare_scene"}) or "prepare_scene" in runs
    assert not (ran & {"view_paths"}) or "view_paths" in runs
    assert kept <= set(warm.stats["reused"]), warm.stats["reused"]
    fresh = render(load_scene("builtin:occluder", SMALL + session.current_overrides()[len(SMALL):]),
                   engine=engine, show_progress=False)
    np.testing.assert_allclose(warm.image, fresh.image, rtol=1e-5, atol=1e-7)


def test_nothing_changed_reuses_everything_but_the_passes(session):
    res = session.render(show_progress=False)
    assert set(res.stats["stages_run"]) == {"raymarch"}
    assert {"bvh", "view_paths"} <= set(res.stats["reused"])


def test_a_bad_change_leaves_the_session_as_it_was(session):
    before = session.render(show_progress=False).image
    with pytest.raises(SceneError) as e:
        session.set(["medium.g=3"])
    assert e.value.key == "medium.g"
    np.testing.assert_array_equal(session.render(show_progress=False).image, before)


def test_preview_and_cancel(session):
    res = session.render(show_progress=False, preview=True)
    assert res.stats["preview"] and res.image.shape == (15, 20, 3)   # halved: kept >= 16 px wide
    with pytest.raises(Cancelled):
        session.render(show_progress=False, cancel=lambda: True)
    full = session.render(show_progress=False)
    assert full.image.shape == (30, 40, 3)


def test_saved_toml_reproduces_the_image(session, engine, tmp_path):
    p = tmp_path / "saved.toml"
    p.write_text(session.to_toml())
    a = session.render(show_progress=False).image
    b = render(load_scene(p), engine=engine, show_progress=False).image
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)


# auto's caustic passes at a tenth of their rays: what these tests compare (a warm render
# against a fresh one) does not depend on how many there are
FEWER_RAYS = ["render.lsg.light_rays=20000", "render.raymap.photons=20000"]


@pytest.mark.parametrize("spec,moves", [
    ("builtin:glass", ["lights[0].position=[0.8,3.0,0.5]", "lights[0].intensity=12"]),
    ("builtin:shafts", ["lights[0].direction=[0.45,-0.85,0.3]",
                        "lights[0].direction=[0.3,-0.9,0.2]"]),
])
def test_light_moves_reshade_hits_like_a_fresh_render(engine, spec, moves):
    """Light changes one after another (behind glass and a mirror too: diffuse hits at the
    end of specular chains) re-shade the recorded hits; each image equals a fresh render
    of the changed scene, and no camera path is traced again. (No time budget: a budget
    sizes auto's caustic passes by the time they take, so two renders would differ.)"""
    sets = ["camera.resolution=[32,24]", "camera.spp=2", "render.time_budget=0", *FEWER_RAYS]
    with RenderSession.from_source(spec, sets, engine=engine) as s:
        s.render(show_progress=False)
        for m in moves:
            s.set([m])
            warm = s.render(show_progress=False)
            assert "shade_hits" in warm.stats["stages_run"]
            assert "view_paths" not in warm.stats["stages_run"]
            fresh = render(load_scene(spec, sets + s.current_overrides()[len(sets):]),
                           engine=engine, show_progress=False)
            assert fresh.surface.max() > 0.0
            np.testing.assert_allclose(warm.surface, fresh.surface, rtol=1e-5, atol=1e-7)
            np.testing.assert_allclose(warm.image, fresh.image, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("method", ["raymap", "photonmap"])
def test_light_move_reuses_the_surface_passes_hits_and_their_tree(engine, method):
    """The surface estimators read the diffuse hits the view paths recorded (not traced
    again) and keep their host copy and the splats' tree with them: after a light move
    the same objects are used, and the image equals a fresh render's."""
    sets = ["camera.resolution=[32,24]", "camera.spp=2", "render.time_budget=0",
            f"render.method=\"{method}\"", f"render.{method}.medium=\"none\"",
            f"render.{method}.passes=2", f"render.{method}.photons=3000"]
    with RenderSession.from_source("builtin:caustic_sphere", sets, engine=engine) as s:
        s.render(show_progress=False)
        hits = s._paths.hits
        kept = {k: hits.derived(k, lambda: pytest.fail(k + " was not kept"))
                for k in ("surface_hits_host", "surface_hit_discs")}
        assert len(kept["surface_hit_discs"]) == hits.count > 0
        s.set(["lights[0].position=[0.6,3.2,0.4]"])
        warm = s.render(show_progress=False)
        assert s._paths.hits is hits and "view_paths" not in warm.stats["stages_run"]
        for k, v in kept.items():
            assert hits.derived(k, lambda: pytest.fail(k + " was built again")) is v
        fresh = render(load_scene("builtin:caustic_sphere", sets + s.current_overrides()[len(sets):]),
                       engine=engine, show_progress=False)
        assert fresh.image.max() > 0.0
        np.testing.assert_allclose(warm.image, fresh.image, rtol=1e-5, atol=1e-7)


def test_segment_derivations_are_built_once_and_freed_with_the_segments(engine):
    """DeviceSegments.derived builds what a method derives from the segments alone once;
    its buffers are freed with the segments."""
    from clscatter.device import structs
    from clscatter.transport.view_paths import ViewPaths
    segs = np.zeros(10, structs.VIEW_SEGMENT)
    segs["pixel"] = np.arange(10) % 4
    live0 = engine.bytes_live
    dev = ViewPaths(None, None, segs).on_device(engine, 2, 2)
    builds = []

    def build():
        builds.append(1)
        return [engine.empty(4096)], "value"

    assert dev.derived("k", build) == "value"
    assert dev.derived("k", build) == "value"
    assert len(builds) == 1
    assert engine.bytes_live >= live0 + 4096
    dev.release()
    assert engine.bytes_live == live0


def test_light_moves_split_the_view_segments_once(engine, monkeypatch):
    """epipolar's split of the view segments into primary and deeper ones depends on the
    segments alone: a warm re-render after a light move reuses it (and the image still
    equals a fresh render's, test_light_moves_reshade_hits_like_a_fresh_render)."""
    sets = ["camera.resolution=[32,24]", "camera.spp=2"]
    launched = []
    orig = type(engine).launch

    def launch(self, kernel, *a, **k):
        launched.append(kernel.function_name)
        return orig(self, kernel, *a, **k)

    monkeypatch.setattr(type(engine), "launch", launch)
    with RenderSession.from_source("builtin:shafts", sets, engine=engine, method="epipolar") as s:
        s.render(show_progress=False)
        assert launched.count("epi_split") == 1
        s.set(["lights[0].direction=[0.45,-0.85,0.3]"])
        s.render(show_progress=False)
        assert launched.count("epi_split") == 1
        assert launched.count("epi_integrate") >= 2


# ---- warm re-renders of the other methods ----------------------------------------------------
# The session's table (clscatter/pipeline/session.py): camera -> the camera buffer, view
# paths, passes; medium -> the medium buffer, view paths, passes; materials -> the material
# buffer, view paths, passes; a method parameter -> passes only. After each change, in one
# session, the warm image equals a fresh one-off render of the changed scene (a one-off
# render is a session used once): rtol 1e-5, atol 1e-6 of the fresh image's maximum (the
# same code on the same inputs; only float summation order on the device may differ).
WARM_SMALL = ["camera.resolution=[32,24]", "camera.spp=1", "render.seed=3"]
WARM_CASES = {
    # method: (scene, quick overrides, [(kind, change), ...])
    "epipolar": ("builtin:shafts", [],
                 [("camera", "camera.origin=[0.4,1.4,7.2]"),
                  ("medium", "medium.sigma_s=0.4"),
                  ("material", "materials.floor.albedo=0.85"),
                  ("param", "render.epipolar.light_rays=64")]),
    "lsg": ("builtin:caustic_sphere", ["render.lsg.light_rays=4000"],
            [("camera", "camera.origin=[0.3,1.7,5.8]"),
             ("medium", "medium.sigma_s=0.2"),
             ("material", "materials.glass.ior=1.35"),
             ("param", "render.lsg.light_rays=3000")]),
    "vpm": ("builtin:caustic_sphere", ["render.vpm.photons=20000"],
            [("camera", "camera.origin=[0.3,1.7,5.8]"),
             ("medium", "medium.sigma_s=0.2"),
             ("material", "materials.glass.ior=1.35"),
             ("param", "render.vpm.knn=16")]),
    "raymap": ("builtin:caustic_sphere", ["render.raymap.photons=4000",
                                          "render.lsg.light_rays=4000"],
               [("camera", "camera.origin=[0.3,1.7,5.8]"),
                ("medium", "medium.sigma_s=0.2"),
                ("material", "materials.floor.albedo=0.8"),
                ("material", "materials.glass.ior=1.35"),
                ("param", "render.raymap.k=16")]),
    "voxel": ("builtin:volume_sphere", ["render.voxel.resolution=16", "render.voxel.photons=1024",
                                        "render.voxel.outer_resolution=16"],
              [("camera", "camera.origin=[0.4,1.7,5.3]"),
               ("medium", "medium.sigma_s=0.25"),
               ("material", "materials.floor.albedo=0.8"),
               ("volume", "volumes[0].sigma_s=0.3"),
               ("param", "render.voxel.photons=2048")]),
}
# the buffer each kind of change re-uploads (None: none) and whether the view paths re-run
WARM_EXPECT = {"camera": ("upload_camera", True), "medium": ("upload_medium", True),
               "material": ("upload_materials", True), "volume": (None, False),
               "param": (None, False)}


@pytest.mark.parametrize("method", sorted(WARM_CASES))
def test_warm_rerenders_of_each_method_equal_fresh_renders(engine, method):
    spec, quick, changes = WARM_CASES[method]
    sets = WARM_SMALL + quick
    with RenderSession.from_source(spec, sets, engine=engine, method=method) as s:
        first = s.render(show_progress=False)
        passes = [p["method"] for p in first.stats["passes"]]
        assert method in passes and "prepare_scene" in first.stats["stages_run"]
        previous = first.image
        for kind, change in changes:
            s.set([change])
            warm = s.render(show_progress=False)
            upload, view = WARM_EXPECT[kind]
            expected = ([upload] if upload else []) + (["view_paths"] if view else []) + passes
            ran = warm.stats["stages_run"]
            assert sorted(ran) == sorted(expected), (change, ran, expected)
            reused = set(warm.stats["reused"])
            assert "bvh" in reused, (change, reused)
            assert view or "view_paths" in reused, (change, reused)
            if method == "voxel":
                # the voxel pipeline's own stages (docs/voxel.md, "Stage reuse in sessions"):
                # volume materials and the medium re-run it from its material stage on, the
                # photon parameters from lighting on, a camera (or a surface's material,
                # which no photon reads) the view only
                vox = warm.stats["voxel_stages_run"]
                want = {"volume": ["material", "lighting", "view"],
                        "medium": ["material", "lighting", "view"],
                        "param": ["lighting", "view"]}.get(kind, ["view"])
                assert vox == want, (change, vox)
            fresh = render(load_scene(spec, s.current_overrides()), method=method,
                           engine=engine, show_progress=False)
            assert fresh.image.max() > 0
            np.testing.assert_allclose(warm.image, fresh.image, rtol=1e-5,
                                       atol=1e-6 * float(fresh.image.max()),
                                       err_msg=f"{method} after {change}")
            assert not np.allclose(warm.image, previous, rtol=1e-3, atol=0), \
                f"{method}: {change} changed nothing in the image"
            previous = warm.image


def test_preview_and_full_frames_keep_both_sets_of_view_paths(engine):
    """Switching from a full frame to a preview and back (the page during and after a drag)
    traces each camera's paths once: the full frame after the previews reuses the paths
    kept for it (re-shaded when the light moved meanwhile) and equals a fresh render."""
    spec = "builtin:glass"
    sets = ["camera.resolution=[32,24]", "camera.spp=2", "render.time_budget=0", *FEWER_RAYS]
    with RenderSession.from_source(spec, sets, engine=engine) as s:
        full = s.render(show_progress=False)
        pre = s.render(show_progress=False, preview=True)
        assert "view_paths" in pre.stats["stages_run"]
        again = s.render(show_progress=False)
        assert "view_paths" not in again.stats["stages_run"]
        assert "view_paths_kept" in again.stats["reused"]
        np.testing.assert_allclose(again.image, full.image, rtol=1e-6, atol=0)
        s.set(["lights[0].position=[0.8,3.0,0.5]"])
        pre2 = s.render(show_progress=False, preview=True)      # the preview's paths, re-shaded
        assert "view_paths" not in pre2.stats["stages_run"]
        assert "shade_hits" in pre2.stats["stages_run"]
        moved = s.render(show_progress=False)                   # the full frame's, re-shaded
        assert "view_paths" not in moved.stats["stages_run"]
        assert "shade_hits" in moved.stats["stages_run"]
        fresh = render(load_scene(spec, sets + ["lights[0].position=[0.8,3.0,0.5]"]),
                       engine=engine, show_progress=False)
        assert not np.allclose(fresh.image, full.image, rtol=1e-3, atol=0)
        np.testing.assert_allclose(moved.image, fresh.image, rtol=1e-5, atol=1e-7)
        s.set(["materials.floor.albedo=0.8"])                   # weights change: both dropped
        after = s.render(show_progress=False)
        assert "view_paths" in after.stats["stages_run"]
        assert s._spare is None
