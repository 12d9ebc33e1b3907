"""Scale-out on Dask: a LocalCluster of 2 worker processes renders the same images as one
process (to float summation tolerance), whatever order tasks finish in, also when a
worker is killed mid-render."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

distributed = pytest.importorskip("distributed", reason="dask.distributed is the 'cluster' extra")

from clscatter.animation import orbit  # noqa: E402
from clscatter.cluster import Cluster  # noqa: E402
from clscatter.pipeline.render import render
from clscatter.pipeline.session import RenderSession
from clscatter.scene import load_scene  # noqa: E402

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
                    "render.lsg.time_budget=0", "render.time_budget=0", "render.raymap.photons=5000"]
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


# ---- the command line: --workers N, --cluster ADDRESS ---------------------------------------
CLI_SMALL = ["--set", "camera.resolution=[40,30]", "--set", "camera.spp=1", "--no-progress"]


def test_cli_workers_renders_the_local_image_on_a_cluster(tmp_path, capsys):
    """``clscatter render SCENE --workers 2``: a local Dask cluster of 2 worker processes
    gives the single-process image (rtol 1e-5, atol 1e-6 of its maximum: only the order of
    the float sums differs) and ``--stats`` says it ran there."""
    from clscatter.cli import main
    from clscatter.io.image import read_image

    local, dist = tmp_path / "local.npy", tmp_path / "cluster.npy"
    assert main(["render", "builtin:occluder", "-o", str(local), *CLI_SMALL]) == 0
    capsys.readouterr()
    code = main(["render", "builtin:occluder", "-o", str(dist), "--workers", "2",
                 "--stats", str(tmp_path / "s.json"), *CLI_SMALL])
    out, err = capsys.readouterr()
    assert code == 0, err
    a, b = read_image(dist), read_image(local)
    assert b.max() > 0 and a.shape == b.shape == (30, 40, 3)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * float(b.max()))
    st = json.loads((tmp_path / "s.json").read_text())
    assert st["cluster_workers"] == 2
    assert st["cluster_tasks"] == 8 == len(st["cluster_task_seconds"])    # 4 per worker
    assert st["cluster_units"]["sample_sets"] == 8 and st["cluster_bytes_out"] > 0
    assert "cluster_start" in st["stages"] and "cluster_render" in st["stages"]
    assert f"40x30 by {st['method']} in " in out


@pytest.mark.parametrize("address", ["foo://host:8786", "no-port-here", "tcp://127.0.0.1:{port}"])
def test_cli_bad_cluster_address_is_one_line_exit_2(tmp_path, capsys, monkeypatch, address):
    """``--cluster ADDRESS`` that is malformed or where no scheduler listens: one line
    naming the address, exit status 2, nothing written. (The unreachable one waits for the
    client's connection timeout, shortened here.)"""
    import socket

    from clscatter import cluster
    from clscatter.cli import main
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", "2s")

    if "{port}" in address:
        with socket.socket() as sock:              # a port that nothing listens on
            sock.bind(("127.0.0.1", 0))
            address = address.format(port=sock.getsockname()[1])
    out = tmp_path / "never.png"
    code = main(["render", "builtin:occluder", "-o", str(out), "--cluster", address, *CLI_SMALL])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"clscatter: error: --cluster {address}: ")
    assert "Traceback" not in err
    assert not list(tmp_path.iterdir())


def test_a_cluster_renders_whatever_the_default_dask_client_is(cluster):
    """A failed ``Cluster(address=...)`` leaves a Dask client that never connected (kept
    alive here by the exception, as a traceback keeps it until garbage collection) and
    Dask makes it the process's default client. ``Cluster.render`` and ``frames`` must
    wait on their own client's futures, not on the default client's event loop (they hung
    for good before). The render runs on a thread: a hang fails instead of blocking."""
    import threading

    from clscatter.errors import ClscatterError

    with pytest.raises(ClscatterError) as failed:
        Cluster(address="foo://nowhere:8786")
    assert distributed.default_client() is not cluster.client     # the trap is set
    out: dict = {}

    def work():
        out["image"] = cluster.render("builtin:occluder", SMALL, units=2,
                                      show_progress=False).image
        out["frames"] = cluster.frames("builtin:occluder", [[], []], SMALL,
                                       show_progress=False)

    t = threading.Thread(target=work, daemon=True)
    t.start()
    t.join(120)
    assert not t.is_alive(), "Cluster.render/frames waited on another client's loop"
    assert out["image"].max() > 0 and len(out["frames"]["frames"]) == 2
    del failed


def _task_keys(dask_scheduler):
    return [str(k) for k in dask_scheduler.tasks]


def test_each_render_sends_its_scene_under_a_key_of_its_own(cluster):
    """The scene payload is scattered as one object with a fresh key. (Scattered as a dict
    it went out value by value under the dict's own key names -- ``data``, ``source`` ...
    -- shared by every render and frame set: one render's release of them could delete the
    next one's scene, which then failed with "lost dependencies".)"""
    from clscatter.cluster import scene_payload

    fields = set(scene_payload("builtin:occluder", SMALL))
    seen: list[list[str]] = []

    def look(done, total):
        if done == 1:
            seen.append(cluster.client.run_on_scheduler(_task_keys))

    for _ in range(2):
        cluster.render("builtin:occluder", SMALL, units=2, show_progress=False, on_unit=look)
    assert len(seen) == 2
    for keys in seen:
        assert not fields & set(keys), sorted(fields & set(keys))
    rec = cluster.frames("builtin:occluder", [[], []], SMALL, show_progress=False)
    assert [f["frame"] for f in rec["frames"]] == [0, 1]


def test_cli_workers_and_cluster_together_is_a_usage_error(capsys):
    from clscatter.cli import main

    code = main(["render", "builtin:occluder", "--workers", "2", "--cluster", "tcp://x:1"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--cluster" in err, err


class _Attempts:
    """A scheduler plugin counting where each render task was sent: ``attempts[key]`` lists
    the worker of every time the task went to ``processing`` (a second entry: it was lost
    and run again), ``removed`` the workers the scheduler lost."""

    name = "clscatter-test-attempts"

    def __init__(self, scheduler):
        self.scheduler = scheduler
        self.attempts: dict[str, list[str | None]] = {}
        self.removed: list[str] = []

    def transition(self, key, start, finish, *args, **kwargs):
        if finish == "processing" and str(key).startswith("_render_unit"):
            ts = self.scheduler.tasks.get(key)
            ws = ts.processing_on if ts is not None else None
            self.attempts.setdefault(str(key), []).append(ws.address if ws is not None else None)

    def remove_worker(self, scheduler=None, worker=None, **kwargs):
        self.removed.append(worker)


def _install_attempts(dask_scheduler):
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Attempts(_Attempts, SchedulerPlugin):
        pass

    dask_scheduler.add_plugin(Attempts(dask_scheduler), name=_Attempts.name)


def _read_attempts(dask_scheduler):
    p = dask_scheduler.plugins[_Attempts.name]
    return {"attempts": {k: list(v) for k, v in p.attempts.items()}, "removed": list(p.removed)}


def _remove_attempts(dask_scheduler):
    dask_scheduler.remove_plugin(name=_Attempts.name)


def test_a_worker_killed_mid_render_loses_nothing(cluster, engine):
    """Kill one worker process as soon as the first unit has arrived (the others are still
    queued or running); Dask re-runs its tasks elsewhere and the deterministic units give
    the same image. A scheduler plugin proves that a task really was lost with the worker
    and run again on another one (not just that the image came out right)."""
    sets = SMALL + ["camera.resolution=[64,48]", "render.raymarch.steps=64"]
    pids = cluster.client.run(os.getpid)              # {worker address: pid}
    victim_addr, victim = min(pids.items(), key=lambda kv: kv[1])
    seen = []

    def kill_on_first(done, total):
        seen.append(done)
        if done == 1:
            os.kill(victim, 9)

    cluster.client.run_on_scheduler(_install_attempts)
    try:
        res = cluster.render("builtin:occluder", sets, units=16, show_progress=False,
                             on_unit=kill_on_first)
        log = cluster.client.run_on_scheduler(_read_attempts)
    finally:
        cluster.client.run_on_scheduler(_remove_attempts)
    assert seen[0] == 1 and seen[-1] == 16          # the kill came with 15 units outstanding
    ref = _single("builtin:occluder", sets, engine)
    np.testing.assert_allclose(res.image, ref, rtol=1e-5, atol=1e-6 * ref.max())
    with pytest.raises(ProcessLookupError):
        os.kill(victim, 0)                                # the victim is really gone
    attempts = log["attempts"]
    assert len(attempts) == 16 == res.stats["cluster_tasks"], attempts   # one key per unit
    assert victim_addr in log["removed"], log["removed"]
    rerun = {k: w for k, w in attempts.items() if len(w) > 1}
    assert rerun, f"no task was run twice: {attempts}"
    # a task the victim had was sent again, to a worker that was not the victim
    assert any(w[0] == victim_addr and any(x != victim_addr for x in w[1:])
               for w in rerun.values()), rerun
