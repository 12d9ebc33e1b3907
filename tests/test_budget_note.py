"""A budget that cannot be kept is said: when LSG's first pass alone exceeds its
``time_budget`` (a pass is its smallest unit of work), the render prints one note naming
the key and what to lower. No wall clock: the pass's seconds come from a fake timer."""
from __future__ import annotations

from clscatter.pipeline.session import RenderSession

SETS = ["camera.resolution=[16,12]", "camera.spp=1", "render.lsg.light_rays=1500",
        "render.lsg.radius=0.02"]


def test_a_first_pass_over_the_budget_is_said_in_one_note(engine, monkeypatch):
    """When the first pass alone exceeds the budget (with some slack), the render says so
    in one note naming the budget's key and what to lower; within the slack it says
    nothing. The pass's seconds come from a fake clock."""
    import clscatter.methods.lsg as lsg_mod

    def render_with(first_pass_seconds: float) -> list[str]:
        now = [0.0]

        class FakeTimer:
            def __enter__(self):
                self._t = now[0]
                return self

            def __exit__(self, *exc):
                now[0] += first_pass_seconds
                self.seconds = now[0] - self._t

        monkeypatch.setattr(lsg_mod, "Timer", FakeTimer)
        notes: list[str] = []
        with RenderSession.from_source("builtin:caustic_sphere",
                                       SETS + ["render.lsg.time_budget=10", "render.lsg.passes=8"],
                                       engine=engine, method="lsg") as s:
            res = s.render(show_progress=False, on_note=notes.append)
        assert res.stats["lsg_passes"] == 1
        return [n for n in notes if n.startswith("render.lsg.time_budget: ")]

    over = render_with(30.0)
    assert len(over) == 1 and "30 s" in over[0] and "lower render.lsg.light_rays" in over[0]
    assert render_with(11.0) == []          # within 20% of the budget: kept
