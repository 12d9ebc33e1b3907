"""Scale-out on Dask: a LocalCluster of 2 worker processes renders the same images as one
process (to float summation tolerance), whatever order tasks finish in, also when a
worker is killed mid-render."""
from __future__ import annotations

import os

import numpy as np
import pytest

distributed = pytest.importorskip("distributed", reason="dask.distributed is the 'cluster' extra")

from clscatter.animation import orbit                     # noqa: E402
from clscatter.cluster import Cluster                     # noqa: E402
from clscatter.pipeline.render import render
from clscatter.scene import load_scene                    # noqa: E402
from clscatter.pipeline.session import RenderSession

SMALL = ["camera.resolution=[48,36]", "camera.spp=1"]


@pytest.fixture(scope="module")
def cluster():
    with Cluster(workers=2) as c:
        yield c


def _single(spec, overrides, engine):
    return render(load_scene(spec, overrides), engine=engine, show_progress=False).image


def test_direct_scene_equals_single_process(cluster, engine):
    res = cluster.render("builtin:occluder", SMALL, units=7, show_progress=False)
    ref = _single("builtin:occluder", SMALL, engine)
    assert res.image.max() > 0
    np.testing.assert_allclose(res.image, ref, rtol=1e-5, atol=1e-6 * ref.max())
    st = res.stats
    assert st["cluster_workers"] == 2 and st["cluster_tasks"] == 7
    assert len(st["cluster_task_seconds"]) == 7 and st["cluster_bytes_out"] > 0


def test_caustic_scene_equals_single_process(cluster, engine):
    """auto on a glass ball: direct, surface caustics on sample sets, the progressive LSG
    caustic pass split into one task per pass (its lighting rays spread over the workers)."""
    sets = SMALL + ["render.lsg.light_rays=20000", "render.lsg.passes=3",
                    "render.lsg.time_budget=0", "render.raymap.photons=5000"]
    res = cluster.render("builtin:caustic_sphere", sets, units=3, show_progress=False)
    ref = render(load_scene("builtin:caustic_sphere", sets), engine=engine, show_progress=False)
    assert res.stats["cluster_units"] == {"sample_sets": 3, "progressive_passes": 3}
    assert ref.medium.max() > 0 and ref.surface.max() > 0
    np.testing.assert_allclose(res.image, ref.image, rtol=1e-4, atol=1e-5 * ref.image.max())
    np.testing.assert_allclose(res.medium, ref.medium, rtol=1e-4, atol=1e-5 * ref.medium.max())


def test_animation_frames_equal_single_process(cluster, engine):
    scene = load_scene("builtin:occluder", SMALL)
    frames = orbit(scene, 4, "light")
    got = {}
    rec = cluster.frames("builtin:occluder", frames, SMALL, show_progress=False,
                         on_frame=lambda i, img, st: got.__setitem__(i, img))
    assert sorted(got) == [0, 1, 2, 3] and [f["frame"] for f in rec["frames"]] == [0, 1, 2, 3]
    with RenderSession.from_source("builtin:occluder", SMALL, engine=engine) as s:
        for i, sets in enumerate(frames):
            s.set(sets, replace=True)
            ref = s.render(show_progress=False).image
            np.testing.assert_allclose(got[i], ref, rtol=1e-5, atol=1e-7)
    assert not np.allclose(got[0], got[2])               # the light really moved


def test_a_worker_killed_mid_render_loses_nothing(cluster, engine):
    """Kill one worker process as soon as the first unit has arrived (the others are still
    queued or running); Dask re-runs its tasks elsewhere and the deterministic units give
    the same image."""
    sets = SMALL + ["camera.resolution=[64,48]", "render.raymarch.steps=64"]
    pids = cluster.client.run(os.getpid)
    victim = sorted(pids.values())[0]
    seen = []

    def kill_on_first(done, total):
        seen.append(done)
        if done == 1:
            os.kill(victim, 9)

    res = cluster.render("builtin:occluder", sets, units=16, show_progress=False,
                         on_unit=kill_on_first)
    assert seen[0] == 1 and seen[-1] == 16          # the kill came with 15 units outstanding
    ref = _single("builtin:occluder", sets, engine)
    np.testing.assert_allclose(res.image, ref, rtol=1e-5, atol=1e-6 * ref.max())
    with pytest.raises(ProcessLookupError):
        os.kill(victim, 0)                                # the victim is really gone
