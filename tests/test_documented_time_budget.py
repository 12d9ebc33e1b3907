"""``render.lsg.time_budget`` (docs/methods.md): a budgeted progressive LSG render adds
passes while one more fits in the budget (at least one runs; ``passes`` > 1 is an upper
bound), and says so in ``lsg_passes``, ``lsg_pass_seconds`` and ``lsg_time_budget``.

No wall clock: LSG times each pass with :class:`clscatter.io.stats.Timer`; the tests replace
that timer (in the LSG module only) with one that reads a fake clock, and each pass (one
call of ``_gather_chunks``) advances the fake clock by a known number of seconds.
"""
from __future__ import annotations

import pytest

import clscatter.methods.lsg as lsg_module
from clscatter.methods.lsg import LineSpaceGathering
from clscatter.pipeline.session import RenderSession

# a fixed radius: no pilot gather, so every lighting-ray trace belongs to a pass
SETS = ["camera.resolution=[16,12]", "camera.spp=1", "render.lsg.light_rays=1500",
        "render.lsg.radius=0.02"]


class FakeClock:
    """Seconds that pass only when a pass of LSG ends: ``durations[k]`` for pass k (the
    last one repeats)."""

    def __init__(self, durations):
        self.now = 0.0
        self.durations = list(durations)
        self.passes = 0

    def pass_done(self) -> None:
        self.now += self.durations[min(self.passes, len(self.durations) - 1)]
        self.passes += 1


@pytest.fixture(scope="module")
def session(engine):
    with RenderSession.from_source("builtin:caustic_sphere", SETS, engine=engine,
                                   method="lsg") as s:
        yield s


@pytest.fixture
def clock(monkeypatch):
    clock = FakeClock([1.0])

    class FakeTimer:
        def __init__(self):
            self.seconds = 0.0

        def __enter__(self):
            self._t = clock.now
            return self

        def __exit__(self, *exc):
            self.seconds = clock.now - self._t

    real = LineSpaceGathering._gather_chunks

    def one_pass(self, *args, **kw):
        out = real(self, *args, **kw)
        clock.pass_done()
        return out

    monkeypatch.setattr(lsg_module, "Timer", FakeTimer)
    monkeypatch.setattr(LineSpaceGathering, "_gather_chunks", one_pass)
    return clock


# (seconds per pass, time_budget, passes, passes that run)
CASES = [
    ([1.0], 3.5, 1, 3),       # after 3 s a 4th pass would end at 4 s > 3.5 s
    ([1.0], 3.0, 1, 3),       # the 3rd pass ends exactly at the budget: it runs
    ([1.0], 2.99, 1, 2),      # ... and not when it would end 0.01 s after it
    ([2.0], 7.0, 1, 3),       # 2 + 2 + 2 = 6; an 8th second is over
    ([5.0], 1.0, 1, 1),       # at least one pass runs, even over the budget
    ([0.5], 10.0, 1, 20),     # passes = 1 with a budget: the budget alone decides
    ([1.0], 100.0, 4, 4),     # passes > 1 is an upper bound under a budget
    ([100.0], 0.0, 3, 3),     # no budget: exactly `passes`, however long they take
]


@pytest.mark.parametrize("durations, budget, passes, expected", CASES,
                         ids=[f"{c[0][0]}s-budget{c[1]}-passes{c[2]}" for c in CASES])
def test_budget_stops_before_the_pass_that_would_exceed_it(session, clock, durations, budget,
                                                           passes, expected):
    clock.durations = durations
    session.set([f"render.lsg.time_budget={budget}", f"render.lsg.passes={passes}"])
    res = session.render(show_progress=False)
    assert clock.passes == expected                       # passes actually traced/gathered
    st = res.stats
    assert st["lsg_passes"] == expected
    assert st["lsg_time_budget"] == budget
    assert st["lsg_pass_seconds"] == pytest.approx([durations[0]] * expected)
    if budget > 0 and expected > 1:
        assert sum(st["lsg_pass_seconds"]) <= budget
    assert st["method"] == "lsg" and res.image.max() > 0


def test_a_budget_gives_the_same_image_as_that_many_passes(session, clock):
    """The passes a budget allows are the passes ``passes = N`` runs: the same rays and
    radii, the same mean (fake clock: 1 s a pass, budget 3.2 s -> 3 passes)."""
    import numpy as np

    session.set(["render.lsg.time_budget=3.2", "render.lsg.passes=1"])
    budgeted = session.render(show_progress=False)
    assert budgeted.stats["lsg_passes"] == 3
    session.set(["render.lsg.time_budget=0", "render.lsg.passes=3"])
    fixed = session.render(show_progress=False)
    assert fixed.stats["lsg_passes"] == 3
    np.testing.assert_allclose(budgeted.image, fixed.image, rtol=1e-5,
                               atol=1e-6 * float(fixed.image.max()))
    session.set(["render.lsg.time_budget=0", "render.lsg.passes=1"])
    one = session.render(show_progress=False)
    assert not np.allclose(one.image, fixed.image, rtol=1e-3, atol=0)   # passes matter

