"""``render.lsg.time_budget`` and a render's deadline (docs/methods.md, docs/scene_format.md):
a budgeted progressive LSG pass runs another pass while the mean pass time says it ends in
time (at least one runs; ``passes`` is an upper bound), says so in ``lsg_passes``,
``lsg_pass_seconds``, ``lsg_time_budget`` and ``lsg_stopped_by``; a budget that the
passes fit in changes nothing.

No wall clock: the pass context carries a fake clock, and each pass (one call of
``_gather_chunks``) advances it by a known number of seconds.
"""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.io.stats import Stats
from clscatter.methods.lsg import LineSpaceGathering
from clscatter.scene import load_scene
from clscatter.transport.context import PassContext
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

# a fixed radius: no pilot gather, so every lighting-ray trace belongs to a pass
SETS = ["camera.resolution=[16,12]", "camera.spp=1"]
TABLE = {"light_rays": 1500, "radius": 0.02}


class FakeClock:
    """Seconds that pass only when a pass of LSG ends: ``durations[k]`` for pass k (the
    last one repeats)."""

    def __init__(self, durations):
        self.now = 0.0
        self.durations = list(durations)
        self.passes = 0

    def __call__(self) -> float:
        return self.now

    def pass_done(self) -> None:
        self.now += self.durations[min(self.passes, len(self.durations) - 1)]
        self.passes += 1


@pytest.fixture(scope="module")
def prepared(engine):
    ps = prepare_scene(load_scene("builtin:caustic_sphere", SETS), engine)
    paths = trace_view_paths(ps, Stats(), False)
    yield ps, paths
    paths.release()
    ps.release()


def run(prepared, monkeypatch, durations, table) -> tuple[dict, np.ndarray, FakeClock]:
    ps, paths = prepared
    clock = FakeClock(durations)
    real = LineSpaceGathering._gather_chunks

    def one_pass(self, *args, **kw):
        out = real(self, *args, **kw)
        clock.pass_done()
        return out

    monkeypatch.setattr(LineSpaceGathering, "_gather_chunks", one_pass)
    stats = Stats()
    with PassContext(ps, paths, stats, False, clock=clock) as ctx:
        image = LineSpaceGathering({**TABLE, **table}).render(ctx).medium
    return stats.to_dict(), image, clock


# (seconds per pass, time_budget, passes, passes that run)
CASES = [
    ([1.0], 3.5, 8, 3),       # after 3 s a 4th pass would end at 4 s > 3.5 s
    ([1.0], 3.0, 8, 3),       # the 3rd pass ends exactly at the budget: it runs
    ([1.0], 2.99, 8, 2),      # ... and not when it would end 0.01 s after it
    ([2.0], 7.0, 8, 3),       # 2 + 2 + 2 = 6; an 8th second is over
    ([5.0], 1.0, 8, 1),       # at least one pass runs, even over the budget
    ([0.5], 10.0, 4, 4),      # passes is an upper bound under a budget
    ([100.0], 0.0, 3, 3),     # no budget: exactly `passes`, however long they take
]


@pytest.mark.parametrize("durations, budget, passes, expected", CASES,
                         ids=[f"{c[0][0]}s-budget{c[1]}-passes{c[2]}" for c in CASES])
def test_budget_stops_before_the_pass_that_would_exceed_it(prepared, monkeypatch, durations,
                                                           budget, passes, expected):
    st, image, clock = run(prepared, monkeypatch, durations,
                           {"time_budget": budget, "passes": passes})
    assert clock.passes == expected                       # passes actually traced/gathered
    assert st["lsg_passes"] == expected
    assert st["lsg_time_budget"] == budget
    assert st["lsg_pass_seconds"] == pytest.approx([durations[0]] * expected)
    assert st["lsg_stopped_by"] == ("time_budget" if expected < passes else "passes")
    if budget > 0 and expected > 1:
        assert sum(st["lsg_pass_seconds"]) <= budget
    assert image.max() > 0


def test_a_budget_the_passes_fit_in_changes_nothing(prepared, monkeypatch):
    """Three passes of light_rays that take 0.1 s each under a 100 s budget: the same rays
    and radii as three passes without a budget, the same image; one pass differs."""
    budgeted = run(prepared, monkeypatch, [0.1], {"time_budget": 100.0, "passes": 3})
    fixed = run(prepared, monkeypatch, [0.1], {"time_budget": 0.0, "passes": 3})
    assert budgeted[0]["lsg_pass_rays"] == fixed[0]["lsg_pass_rays"] == [1500] * 3
    np.testing.assert_allclose(budgeted[1], fixed[1], rtol=1e-5,
                               atol=1e-6 * float(fixed[1].max()))
    one = run(prepared, monkeypatch, [0.1], {"time_budget": 0.0, "passes": 1})
    assert not np.allclose(one[1], fixed[1], rtol=1e-3, atol=0)      # passes matter
