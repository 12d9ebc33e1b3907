"""Time budgets and error targets: the progression's stopping rules and noise estimate, a
budgeted LSG pass against a fake clock (work that would take 10x the budget), the
render-level budget and error estimate through the session and the command line."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from clscatter.cli import main
from clscatter.estimators import line_gather
from clscatter.io.stats import Stats
from clscatter.methods.lsg import LineSpaceGathering
from clscatter.pipeline import budget
from clscatter.pipeline.render import render
from clscatter.scene import load_scene
from clscatter.transport.context import PassContext
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.progressive import Progression, relmse_estimate
from clscatter.transport.view_paths import trace_view_paths


class FakeClock:
    """A clock that moves only when told to."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_relmse_estimate_is_relmse_of_the_variance():
    """relmse_estimate(var, I) = mean(var / (I^2 + 0.01 mean|I|^2)), exactly (1e-12)."""
    rng = np.random.default_rng(1)
    image = rng.uniform(0.0, 2.0, (6, 5, 3))
    var = rng.uniform(0.0, 0.1, (6, 5, 3))
    floor = 0.01 * np.mean(np.abs(image)) ** 2
    assert relmse_estimate(var, image) == pytest.approx(np.mean(var / (image ** 2 + floor)), rel=1e-12)
    assert relmse_estimate(np.zeros_like(var), np.zeros_like(image)) == 0.0
    assert math.isinf(relmse_estimate(var, np.zeros_like(image)))


def test_halves_estimate_tracks_the_true_error():
    """Passes = truth + independent noise of known sigma: the halves' estimate of the mean's
    relMSE is within a factor 1.3 of the true expected relMSE (sigma^2 / n against the
    truth), at 2, 4 and 16 passes, and within 1.5x of the error the mean actually has."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.5, 1.5, (40, 50, 3))
    sigma = 0.1        # the estimate divides by the noisy image itself: noise well below it
    for n in (2, 4, 16):
        prog = Progression(max_passes=n, planned=n)
        passes = truth + rng.normal(0.0, sigma, (n, *truth.shape))
        for p in passes:
            prog.add(p, 1.0)
        expected = relmse_estimate(np.full(truth.shape, sigma ** 2 / n), truth)
        actual = relmse_estimate((passes.mean(0) - truth) ** 2, truth)
        assert prog.error == pytest.approx(expected, rel=0.3), n
        assert 1 / 1.5 < prog.error / actual < 1.5, n
        np.testing.assert_allclose(prog.mean(), passes.mean(0), rtol=1e-12)


def test_progression_stops_at_deadline_target_and_count():
    """The deadline stops passes when the mean pass time would overrun it (one pass always
    runs), the error target once at least 4 passes met it, max_passes otherwise."""
    clock = FakeClock()
    prog = Progression(deadline=clock() + 10.0, max_passes=100, planned=4, clock=clock)
    runs = 0
    while prog.more():
        clock.now += 3.0
        prog.add(None, 3.0)
        runs += 1
    assert runs == 3 and prog.stopped_by == "time_budget"     # 9 s; a 4th would end at 12
    clock = FakeClock()
    late = Progression(deadline=clock() + 1.0, max_passes=100, clock=clock)
    assert late.more()
    clock.now += 5.0
    late.add(None, 5.0)
    assert not late.more()                                     # the first pass alone overran

    prog = Progression(target_error=1e-3, max_passes=1000, planned=8)
    truth = np.ones((8, 8, 3))
    rng = np.random.default_rng(3)
    while prog.more():
        prog.add(truth + rng.normal(0.0, 0.1, truth.shape), 1.0)
    n = len(prog.seconds)
    assert prog.stopped_by == "target_error" and prog.error <= 1e-3
    # sigma^2 / n < 1e-3 first holds at n = 10; the estimate's own noise moves it a little
    assert 6 <= n <= 16
    fixed = Progression(max_passes=3)
    while fixed.more():
        fixed.add(None, 1.0)
    assert len(fixed.seconds) == 3 and fixed.stopped_by == "passes"
    assert fixed.error is None and fixed.variance() is None


CAUSTIC = "builtin:caustic_sphere"
SMALL = ["camera.resolution=[40,30]", "camera.spp=1"]


@pytest.fixture(scope="module")
def caustic(engine):
    scene = load_scene(CAUSTIC, SMALL)
    ps = prepare_scene(scene, engine)
    paths = trace_view_paths(ps, Stats(), False)
    yield ps, paths
    paths.release()
    ps.release()


def test_budgeted_lsg_keeps_its_budget_on_a_fake_clock(caustic, monkeypatch):
    """Every gather advances a fake clock by a cost that grows like rays^(5/6) (the
    gather's model); at the pass's light_rays the 8 passes would take 10x the budget. The
    budgeted pass sizes its passes from what the pilot and each pass cost and ends within
    1.2x the budget, with at least 2 passes and fewer rays per pass than light_rays."""
    ps, paths = caustic
    clock = FakeClock()
    real_add = line_gather.Gatherer.add
    rays_full = 40_000
    per_pass_full = 10.0 * 8.0 / 8      # seconds one full pass costs: 8 of them = 10 x 8 s

    def costly_add(self, segs, *a, **kw):
        clock.now += per_pass_full * (max(len(segs), 1) / (3.0 * rays_full)) ** (5 / 6)
        return real_add(self, segs, *a, **kw)

    monkeypatch.setattr(line_gather.Gatherer, "add", costly_add)
    m = LineSpaceGathering({"light_rays": rays_full, "passes": 8, "radius": 0.0})
    stats = Stats()
    with PassContext(ps, paths, stats, False, deadline=clock() + 8.0, clock=clock) as ctx:
        started = clock()
        m.render(ctx)
    s = stats.to_dict()
    took = clock() - started
    assert took <= 1.2 * 8.0, s["lsg_pass_seconds"]
    assert s["lsg_passes"] >= 2 and max(s["lsg_pass_rays"]) < m.traced_rays(ps)
    assert s["lsg_stopped_by"] in ("time_budget", "passes")
    assert s["lsg_error_estimate"] is not None and s["lsg_error_estimate"] > 0


def test_budgeted_samples_take_turns_where_passes_over_all_would_share(engine, monkeypatch):
    """caustic_sphere at 48x36, 4 spp, 20,000 rays a pass: without a budget the radius is a
    small part of a pixel and every pass gathers every sample (G = 1). Under a budget where
    a pass over every sample fits about 1,300 rays (a fake clock; a gather's cost grows like
    rays^(5/6) times the view segments it gathers), the radius of such passes would span
    the samples, so they take turns (G = 4), each pass then tracing more rays."""
    scene = load_scene(CAUSTIC, ["camera.resolution=[48,36]", "camera.spp=4"])
    ps = prepare_scene(scene, engine)
    paths = trace_view_paths(ps, Stats(), False)
    rays_full = 20_000
    try:
        free = Stats()
        with PassContext(ps, paths, free, False) as ctx:
            LineSpaceGathering({"light_rays": rays_full, "passes": 8}).render(ctx)
        assert free.to_dict()["lsg_sample_groups"] == 1
        clock = FakeClock()
        real_add = line_gather.Gatherer.add

        def costly_add(self, segs, *a, **kw):
            share = self.active / max(self.n, 1)
            clock.now += 10.0 * share * (max(len(segs), 1) / (3.0 * rays_full)) ** (5 / 6)
            return real_add(self, segs, *a, **kw)

        monkeypatch.setattr(line_gather.Gatherer, "add", costly_add)
        tight = Stats()
        with PassContext(ps, paths, tight, False, deadline=clock() + 8.0, clock=clock) as ctx:
            LineSpaceGathering({"light_rays": rays_full, "passes": 8}).render(ctx)
        s = tight.to_dict()
        assert s["lsg_sample_groups"] == 4, s["lsg_auto_radius"]
        auto = s["lsg_auto_radius"]
        assert auto["radius"] < 0.5 * auto["footprint"]   # the passes' own radius: smaller
        assert min(s["lsg_pass_rays"][1:]) > 2000
    finally:
        paths.release()
        ps.release()


def test_budget_first_pass_over_budget_gives_a_note(caustic, monkeypatch):
    """A budget smaller than the smallest pass: one pass runs and one note says so, naming
    what to lower; a first pass within 20% of the budget says nothing."""
    ps, paths = caustic

    def first_pass(cost: float) -> tuple[list[str], int]:
        clock = FakeClock()
        real_add = line_gather.Gatherer.add

        def slow_add(self, segs, *a, **kw):
            clock.now += cost
            return real_add(self, segs, *a, **kw)

        monkeypatch.setattr(line_gather.Gatherer, "add", slow_add)
        notes: list[str] = []
        stats = Stats()
        m = LineSpaceGathering({"light_rays": 1500, "passes": 8, "radius": 0.02})
        with PassContext(ps, paths, stats, False, on_note=notes.append,
                         deadline=clock() + 1.0, clock=clock) as ctx:
            m.render(ctx)
        return notes, stats.values["lsg_passes"]

    notes, passes = first_pass(5.0)
    assert passes == 1 and len(notes) == 1
    assert "the first pass alone took 5 s" in notes[0] and "camera.resolution" in notes[0]
    notes, passes = first_pass(1.1)
    assert passes == 1 and notes == []


def test_a_share_of_the_render_budget_holds_its_overrun_note(caustic, monkeypatch):
    """Inside a session (``hold_overruns``) a first pass that breaks its share of the
    render's budget keeps its note for the session, which tells it only if the whole
    render breaks its budget (the other passes may make up for it); a first pass that
    breaks the method's own ``time_budget`` tells it at once."""
    from clscatter.pipeline.session import _Budget, _report_budget
    ps, paths = caustic
    real_add = line_gather.Gatherer.add

    def run(params: dict, deadline: float | None) -> tuple[list[str], list[str]]:
        clock = FakeClock()

        def slow_add(self, segs, *a, **kw):
            clock.now += 5.0
            return real_add(self, segs, *a, **kw)

        monkeypatch.setattr(line_gather.Gatherer, "add", slow_add)
        told: list[str] = []
        m = LineSpaceGathering({"light_rays": 1500, "passes": 8, "radius": 0.02, **params})
        with PassContext(ps, paths, Stats(), False, on_note=told.append, clock=clock,
                         deadline=None if deadline is None else clock() + deadline,
                         hold_overruns=True) as ctx:
            m.render(ctx)
        return told, ctx.overruns

    told, held = run({}, 1.0)                              # the render's share: held
    assert told == [] and len(held) == 1 and "first pass alone took 5 s" in held[0]
    told, held = run({"time_budget": 1.0}, None)          # its own budget: told at once
    assert len(told) == 1 and "first pass alone took 5 s" in told[0] and held == []
    told, held = run({"time_budget": 1.0}, 0.5)           # the render's share is shorter
    assert told == [] and len(held) == 1

    import time
    now = time.perf_counter()
    for started, expect in ((now, []), (now - 100.0, ["pass note"])):
        out: list[str] = []
        _report_budget(Stats(), _Budget(10.0, "auto's default", started, started + 10.0),
                       out.append, ["pass note"])
        assert out == expect                  # within the budget: nothing; past it: the note
    out = []
    _report_budget(Stats(), _Budget(10.0, "auto's default", now - 100.0, now - 90.0),
                   out.append, [])
    assert len(out) == 1 and "the render took" in out[0]     # no pass's note: the stage
    # the work before the progressive passes used the budget: one line names the longest
    # of it (a stage before the passes, or a pass that had time) and the passes left none
    st = Stats()
    out = []
    _report_budget(st, _Budget(1.0, "render.time_budget", now - 4.0, now - 3.0), out.append,
                   [], {"view_paths": 0.2, "device": 0.4},
                   [("raymarch", 1.25, "fixed"), ("raymap", 1.5, "starved"),
                    ("lsg", 0.62, "starved")])
    assert len(out) == 1 and st.values["notes"] == out
    assert "raymarch alone took 1.25 s" in out[0]
    assert out[0].endswith("after it raymap and lsg had no time left and ran their smallest "
                           "passes (1.5 s, 0.62 s)")
    out = []
    _report_budget(Stats(), _Budget(1.0, "render.time_budget", now - 9.0, now - 8.0),
                   out.append, [], {"view_paths": 6.0}, [("raymarch", 1.25, "fixed"),
                                                          ("lsg", 8.0, "progressive")])
    assert len(out) == 1 and "view_paths alone took 6 s" in out[0] and "after it" not in out[0]
    # (lsg had a share of the budget and kept to it: not work that does not shrink)


def test_render_level_budget_and_error_estimate(engine):
    """auto's default budget is in the stats; an explicit budget and target error are
    recorded; a progressive render reports a finite error estimate; a render without
    progressive passes reports none."""
    scene = load_scene(CAUSTIC, SMALL + ["render.lsg.light_rays=3000", "render.lsg.passes=4"])
    out = render(scene, "lsg", engine=engine, show_progress=False)
    s = out.stats
    assert s["time_budget"] == 0.0 and s["time_budget_source"] == "none"
    assert s["target_error"] == 0.0
    assert s["lsg_passes"] == 4 and math.isfinite(s["error_estimate"]) and s["error_estimate"] > 0

    auto = load_scene(CAUSTIC, SMALL + ["render.lsg.light_rays=3000"])
    assert budget.time_budget(auto, "auto") == (budget.AUTO_TIME_BUDGET, "auto's default")
    assert budget.time_budget(load_scene(CAUSTIC, ["render.time_budget=0"]), "auto")[0] == 0.0
    plain = render(load_scene("builtin:occluder", SMALL), "raymarch", engine=engine,
                   show_progress=False)
    assert plain.stats["error_estimate"] is None


def test_target_error_passes_go_on_until_met(engine):
    """With a reachable target the passes stop once the estimate meets it (more than
    render.lsg.passes); the estimate reported is at most the target."""
    base = SMALL + ["render.lsg.light_rays=2000", "render.lsg.passes=2", "render.lsg.radius=0.02",
                    "render.time_budget=0"]
    one = render(load_scene(CAUSTIC, base), "lsg", engine=engine, show_progress=False).stats
    target = one["error_estimate"] / 3          # two passes' error / 3: about 6 passes
    scene = load_scene(CAUSTIC, base + [f"render.target_error={target!r}"])
    s = render(scene, "lsg", engine=engine, show_progress=False).stats
    assert s["lsg_stopped_by"] == "target_error" and 4 <= s["lsg_passes"] <= 64
    assert s["lsg_error_estimate"] <= target and s["error_estimate"] <= target


def test_cli_time_budget_flags(tmp_path, capsys):
    """--time-budget and --target-error reach the scene (check prints them); a negative
    budget is one line naming the key, exit 2, nothing written."""
    assert main(["check", CAUSTIC, "--time-budget", "3", "--target-error", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "time: 3 s for the whole render (render.time_budget)" in out
    assert "relMSE of 0.01" in out
    assert main(["check", CAUSTIC]) == 0
    assert "time: 10 s for the whole render (auto's default)" in capsys.readouterr().out
    target = tmp_path / "x.png"
    assert main(["render", CAUSTIC, "--time-budget=-1", "-o", str(target)]) == 2
    err = capsys.readouterr().err
    assert "render.time_budget" in err and len(err.strip().splitlines()) == 1
    assert not target.exists()
    stats = tmp_path / "s.json"
    assert main(["render", CAUSTIC, "--method", "raymarch", "--time-budget", "30",
                 "--set", "camera.resolution=[16,12]", "-o", str(tmp_path / "y.npy"),
                 "--stats", str(stats)]) == 0
    s = json.loads(stats.read_text())
    assert s["time_budget"] == 30.0 and s["time_budget_source"] == "render.time_budget"


@pytest.mark.parametrize("name,method,spp", [("caustic_sphere", "auto", 1), ("caustic_mirror", "auto", 1),
                                             ("caustic_sphere", "lsg", 4)])
def test_error_estimate_tracks_the_error_against_a_long_run(engine, name, method, spp):
    """The render's own error estimate (noise from independent halves plus the shrinking
    radii's blur) is within a factor 2 of its relMSE against a long run (48 passes of 4x
    the rays), after 4 and after 16 passes, on built-in caustic scenes: under auto the blur
    dominates the error (caustic_sphere), under lsg the noise does (at 4 spp, where LSG's
    passes gather one sample of each pixel in turn and the estimate compares whole rounds
    of 4 passes: after 8 and 32 passes, two halves of rounds; with 2500 rays a pass, so that
    the automatic radius spans more than half a pixel and the samples do take turns)."""
    from clscatter.io.image import relmse
    base = ["camera.resolution=[48,36]", f"camera.spp={spp}", "render.time_budget=0"]
    rays = 5000 if spp == 1 else 2500
    long = render(load_scene(f"builtin:{name}", base + [f"render.lsg.light_rays={4 * rays}",
                                                         "render.lsg.passes=48"]),
                  method, engine=engine, show_progress=False).image
    for passes in ((4, 16) if spp == 1 else (8, 32)):
        r = render(load_scene(f"builtin:{name}", base + [
            f"render.lsg.light_rays={rays}", f"render.lsg.passes={passes}",
            "render.lsg.light_seed=3"]), method, engine=engine, show_progress=False)
        assert r.stats["lsg_sample_groups"] == (1 if spp == 1 else 4)
        ratio = r.stats["error_estimate"] / relmse(r.image, long)
        assert 0.5 <= ratio <= 2.0, (passes, r.stats["error_estimate"], ratio)


def test_calibration_predicts_from_renders_of_a_like_size(tmp_path, monkeypatch):
    """A prediction uses the rates of the measurements nearest in work and their median: a
    small render's fixed costs and one odd render do not move it; entries of another form
    are ignored."""
    from clscatter.pipeline import calibration
    monkeypatch.setenv("CLSCATTER_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("CLSCATTER_COSTS")                     # the cache folder's costs.json
    (tmp_path / "costs.json").write_text('{"dev": {"lsg": [1e-05, 2e-05], "raymap": 7}}')
    assert calibration.predict("dev", "lsg", 1e9) is None        # bare rates: not measurements
    assert calibration.predict("dev", "raymap", 1e9) is None
    small = [(1e6, 0.3), (2e6, 0.6), (1.5e6, 0.45)]              # 3e-7 s a unit: fixed costs
    large = [(1e9, 1.0), (1.1e9, 1.1), (0.9e9, 40.0), (1.2e9, 1.2)]  # 1e-9, one odd render
    for work, seconds in small + large:
        calibration.record("dev", "lsg", work, seconds)
    # nearest 1e9: 1e9, 1.1e9 and the odd 0.9e9; their median rate is 1e-9
    assert calibration.predict("dev", "lsg", 1e9) == pytest.approx(1.0, rel=1e-9)
    assert calibration.predict("dev", "lsg", 1.5e6) == pytest.approx(0.45, rel=1e-9)
    calibration.record("dev", "lsg", 1.4e6, 7.0)                 # a first compile, say
    assert calibration.predict("dev", "lsg", 1.5e6) == pytest.approx(0.45, rel=1e-9)
    assert calibration.predict("dev", "lsg", 0.0) is None


def test_calibration_prefers_the_asked_scenes_own_rates(tmp_path, monkeypatch):
    """Two scenes whose estimates count the same work at rates 8x apart (one breaks its
    lighting rays into many segments at glass): each scene's prediction comes from its own
    measurements, even when the other's are newer and as near in size; a scene never
    measured, or none named, gets the nearest of all. A file names its scene by its
    absolute path; entries kept without a scene still count."""
    from clscatter.pipeline import calibration
    monkeypatch.setenv("CLSCATTER_COSTS", str(tmp_path / "costs.json"))
    for _ in range(2):
        calibration.record("dev", "lsg", 1e9, 16.0, "builtin:caustic_torus")
    for _ in range(3):
        calibration.record("dev", "lsg", 1e9, 2.0, "builtin:caustic_sphere")
    assert calibration.predict("dev", "lsg", 1e9, "builtin:caustic_torus") == pytest.approx(16.0)
    assert calibration.predict("dev", "lsg", 1e9, "builtin:caustic_sphere") == pytest.approx(2.0)
    assert calibration.predict("dev", "lsg", 1e9, "builtin:glass") == pytest.approx(2.0)
    assert calibration.predict("dev", "lsg", 1e9) == pytest.approx(2.0)
    monkeypatch.chdir(tmp_path)
    calibration.record("dev", "raymarch", 1e9, 5.0, "scene.toml")
    assert calibration.predict("dev", "raymarch", 1e9, str(tmp_path / "scene.toml")) == 5.0
    data = json.loads((tmp_path / "costs.json").read_text())
    data["dev"]["vpm"] = [[1e9, 3.0]]                          # kept before scenes were named
    (tmp_path / "costs.json").write_text(json.dumps(data))
    assert calibration.predict("dev", "vpm", 1e9, "builtin:caustic_torus") == pytest.approx(3.0)


def test_calibration_keeps_what_each_scene_taught(tmp_path, monkeypatch):
    """Many renders of one scene do not push out another scene's measurements: the newest
    KEEP of each scene are kept, for the KEEP_SCENES scenes measured last."""
    from clscatter.pipeline import calibration
    monkeypatch.setenv("CLSCATTER_COSTS", str(tmp_path / "costs.json"))
    monkeypatch.setattr(calibration, "KEEP", 4)
    monkeypatch.setattr(calibration, "KEEP_SCENES", 3)
    calibration.record("dev", "lsg", 1e9, 16.0, "builtin:caustic_torus")
    for k in range(10):                                     # a later run of many renders
        calibration.record("dev", "lsg", 1e9, 2.0 + k, "builtin:glass")
    assert calibration.predict("dev", "lsg", 1e9, "builtin:caustic_torus") == pytest.approx(16.0)
    kept = json.loads((tmp_path / "costs.json").read_text())["dev"]["lsg"]
    assert [e[1] for e in kept] == [16.0, 8.0, 9.0, 10.0, 11.0]     # oldest first
    for name in ("builtin:caustic_sphere", "builtin:caustic_gem"):
        calibration.record("dev", "lsg", 1e9, 1.0, name)
    kept = json.loads((tmp_path / "costs.json").read_text())["dev"]["lsg"]
    assert {e[2] for e in kept} == {"builtin:glass", "builtin:caustic_sphere",
                                    "builtin:caustic_gem"}      # the torus was measured first
    assert calibration.predict("dev", "lsg", 1e9, "builtin:glass") == pytest.approx(10.0)


def test_calibration_file_can_be_named(tmp_path, monkeypatch):
    """$CLSCATTER_COSTS names the calibration file (the suite's own: conftest.py), in place
    of costs.json in the cache folder."""
    from clscatter.pipeline import calibration
    monkeypatch.setenv("CLSCATTER_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CLSCATTER_COSTS", str(tmp_path / "mine.json"))
    calibration.record("dev", "lsg", 1e9, 2.0)
    assert (tmp_path / "mine.json").is_file() and not (tmp_path / "cache").exists()
    assert calibration.predict("dev", "lsg", 1e9) == pytest.approx(2.0, rel=1e-12)


def test_calibration_learns_seconds_per_unit_of_work(tmp_path, monkeypatch, capsys):
    """A rate is recorded per device and stage (negligible work is not), the prediction is
    work times the rates' middle (here two: their geometric mean), the oldest beyond KEEP
    drop out; a render records its full passes and check prints the time on the device."""
    from clscatter.pipeline import calibration
    monkeypatch.setenv("CLSCATTER_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("CLSCATTER_COSTS")                     # the cache folder's costs.json
    assert calibration.predict("dev", "lsg", 1e9) is None
    calibration.record("dev", "lsg", 1e9, 2.0)
    calibration.record("dev", "lsg", 1e9, 8.0)
    calibration.record("dev", "lsg", 10.0, 5.0)                 # below MIN_WORK: ignored
    assert calibration.predict("dev", "lsg", 2e9) == pytest.approx(8.0, rel=1e-12)  # 2e9 * 4e-9
    assert calibration.predict("other", "lsg", 1e9) is None
    for _ in range(calibration.KEEP):
        calibration.record("dev", "lsg", 1e9, 1.0)
    assert calibration.predict("dev", "lsg", 1e9) == pytest.approx(1.0, rel=1e-12)
    (tmp_path / "costs.json").write_text("not json")
    assert calibration.predict("dev", "lsg", 1e9) is None       # unreadable: ignored
    args = [CAUSTIC, "--method", "raymarch", "--set", "camera.resolution=[64,48]"]
    assert main(["check", *args]) == 0
    assert "estimate raymarch" in (out := capsys.readouterr().out) and "not yet calibrated" in out
    assert main(["render", *args, "-o", str(tmp_path / "a.npy")]) == 0
    assert main(["check", *args]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("estimate raymarch"))
    assert "s on this device" in line
    lines = [ln for ln in out.splitlines() if ln.startswith("estimate ")]
    assert [ln.split()[1] for ln in lines] == ["view_paths:", "scene:", "raymarch:"]
    assert all("s on this device" in ln for ln in lines), lines    # the scene's too


def test_an_untracked_pass_is_timed_but_left_out_of_the_estimate():
    """A pass added without an image (another estimator, e.g. the k-nearest opening pass of
    the surface methods) counts in the passes' times, not in the halves."""
    rng = np.random.default_rng(5)
    images = [1.0 + rng.normal(0.0, 0.1, (6, 6, 3)) for _ in range(6)]
    a, b = Progression(max_passes=10), Progression(max_passes=10)
    b.add(None, 1.0)
    for img in images:
        a.add(img, 1.0)
        b.add(img, 1.0)
    assert len(b.seconds) == 7 and len(a.seconds) == 6
    assert b.error == pytest.approx(a.error, rel=1e-12)
    np.testing.assert_allclose(b.mean(), a.mean(), rtol=1e-12)
