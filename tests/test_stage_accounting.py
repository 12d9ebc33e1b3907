"""Every second of a render is accounted for: the stages in ``--stats`` sum to at least
95% of ``seconds_total`` for every method, through the real command line (or leave at
most 10 ms out: these renders take a tenth of a second, where a busy machine's scheduling
alone can leave 5%)."""
from __future__ import annotations

import json

import pytest
from method_scenes import overrides_for, scene_for

from clscatter.cli import main
from clscatter.methods import all_methods


@pytest.mark.parametrize("method", sorted(all_methods()))
def test_stages_cover_the_render(method, tmp_path, capsys):
    stats = tmp_path / "s.json"
    sets = [x for o in overrides_for(method) for x in ("--set", o)]
    code = main(["render", scene_for(method), "--method", method, "-o",
                 str(tmp_path / "o.npy"), "--stats", str(stats), "--no-progress", *sets])
    assert code == 0, capsys.readouterr().err
    st = json.loads(stats.read_text())
    covered = sum(st["stages"].values())
    left_out = st["seconds_total"] - covered
    assert left_out <= max(0.05 * st["seconds_total"], 0.01), (covered, st["seconds_total"],
                                                                st["stages"])
    # nested stages count once (epipolar's fallback runs raymarch's stage inside its own)
    assert covered <= 1.001 * st["seconds_total"], (covered, st["seconds_total"], st["stages"])
    assert {"startup", "load_scene", "configure", "device", "view_paths",
            "write_outputs"} <= set(st["stages"])


def test_start_up_loads_the_programs_the_render_uses(engine, monkeypatch):
    """The programs an epipolar render builds (view paths, primitives, epipolar with its
    starting defines) are loaded at start-up: the passes use no other (program, defines)."""
    from clscatter.device import Engine
    from clscatter.pipeline.render import render
    from clscatter.scene.loader import load_scene

    loaded, phase = [], ["start"]
    real_kernel, real_preload = Engine.kernel, Engine.preload

    def kernel(self, name, kernel, defines=None):
        loaded.append((phase[0], name, tuple(sorted((defines or {}).items()))))
        return real_kernel(self, name, kernel, defines)

    def preload(self, programs):
        phase[0] = "preload"
        real_preload(self, programs)
        phase[0] = "render"

    monkeypatch.setattr(Engine, "kernel", kernel)
    monkeypatch.setattr(Engine, "preload", preload)
    scene = load_scene("builtin:shafts", ["camera.resolution=[40,30]", "camera.spp=1"])
    render(scene, method="epipolar", engine=engine, show_progress=False)
    pre = {(n, d) for p, n, d in loaded if p == "preload"}
    used = {(n, d) for p, n, d in loaded if p == "render"}
    assert {"view_paths", "primitives", "epipolar"} <= {n for n, _ in pre}
    assert used <= pre, used - pre


def test_a_stage_inside_another_counts_once(monkeypatch):
    """On a fake clock (the stats module's ``time``), advanced by hand: exact seconds."""
    import types

    from clscatter.io import stats as stats_module
    from clscatter.io.stats import Stats
    now = [100.0]
    monkeypatch.setattr(stats_module, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))

    def sleep(seconds):
        now[0] += seconds

    st = Stats()
    with st.stage("outer") as outer:
        sleep(0.02)
        with st.stage("inner"):
            sleep(0.05)
        with st.stage("outer"):                 # the same name nested: still counted once
            sleep(0.01)
    assert outer.seconds == pytest.approx(0.08, abs=1e-9)
    assert st.stages["inner"] == pytest.approx(0.05, abs=1e-9)
    assert st.stages["outer"] == pytest.approx(0.03, abs=1e-9)     # 0.02 + 0.01, not 0.08
    assert sum(st.stages.values()) == pytest.approx(outer.seconds, abs=1e-9)
    sleep(1.0)
    assert st.to_dict()["seconds_total"] == pytest.approx(1.08, abs=1e-9)
