"""Long work is announced (clscatter/pipeline/budget.py): a render whose estimated work
exceeds ``LONG_WORK`` says so, one note per stage over it, before any rendering; the
command line prints it as ``clscatter: note: ...``. ``LONG_WORK`` is lowered in-process
instead of rendering something huge."""
from __future__ import annotations

import pytest

import clscatter.pipeline.session as session_module
from clscatter.cli import main
from clscatter.pipeline import budget
from clscatter.pipeline.render import check
from clscatter.pipeline.session import RenderSession
from clscatter.scene import load_scene

SPEC = "builtin:occluder"
SETS = ["camera.resolution=[16,12]", "camera.spp=1", 'render.method="raymarch"']
LONG = "this will take a while"


def _estimates():
    return check(load_scene(SPEC, SETS)).estimates


@pytest.fixture
def events(monkeypatch):
    """The order of notes and of the first rendering stage (tracing the camera paths)."""
    seen: list[str] = []
    real = session_module.trace_view_paths

    def trace(*a, **k):
        seen.append("trace_view_paths")
        return real(*a, **k)

    monkeypatch.setattr(session_module, "trace_view_paths", trace)
    return seen


def test_work_over_long_work_is_announced_before_rendering(engine, monkeypatch, events):
    est = _estimates()
    work = sorted(e.work for e in est)
    # between the smallest and the largest stage: exactly the stages above it are announced
    threshold = (work[0] + work[-1]) / 2
    over = [e for e in est if e.work > threshold]
    assert 0 < len(over) < len(est)
    monkeypatch.setattr(budget, "LONG_WORK", threshold)
    with RenderSession.from_source(SPEC, SETS, engine=engine) as s:
        res = s.render(show_progress=False, on_note=lambda line: events.append(line))
    notes = [e for e in events if LONG in e]
    assert len(notes) == len(over), events
    for e, line in zip(over, notes):
        assert line.startswith(f"{e.stage}: about ") and f"({e.work_by})" in line
    assert events.index("trace_view_paths") > max(events.index(n) for n in notes), events
    assert res.image.max() > 0                    # announced, not refused


def test_work_under_long_work_is_not_announced(engine, events):
    assert max(e.work for e in _estimates()) < budget.LONG_WORK
    with RenderSession.from_source(SPEC, SETS, engine=engine) as s:
        s.render(show_progress=False, on_note=lambda line: events.append(line))
    assert not [e for e in events if LONG in e], events
    assert events == ["trace_view_paths"]


def test_the_command_line_prints_the_note_before_the_render(tmp_path, monkeypatch, capsys,
                                                            events):
    monkeypatch.setattr(budget, "LONG_WORK", 1.0)      # every stage is "long"
    from clscatter import cli

    real_note = cli._note

    def note(line):                                   # the CLI's notes, in order with the trace
        events.append(line)
        real_note(line)

    monkeypatch.setattr(cli, "_note", note)
    out = tmp_path / "o.npy"
    code = main(["render", SPEC, "-o", str(out), "--no-progress",
                 *[x for o in SETS for x in ("--set", o)]])
    err = capsys.readouterr().err
    assert code == 0, err
    notes = [ln for ln in err.splitlines() if ln.startswith("clscatter: note: ") and LONG in ln]
    assert len(notes) == len(_estimates()), err       # one per stage: view paths, raymarch
    assert any(ln.startswith("clscatter: note: view_paths: about ") for ln in notes)
    first_note = next(i for i, e in enumerate(events) if LONG in e)
    assert first_note < events.index("trace_view_paths"), events
    assert out.is_file()


@pytest.mark.parametrize("time_budget, announced", [(0.0, True), (5.0, False)])
def test_passes_a_deadline_sizes_are_not_announced(engine, monkeypatch, time_budget, announced):
    """lsg sizes its passes to a deadline: under a time budget its estimate (of the unshrunk
    passes) says nothing about how long it will take, and it is not announced; the other
    stages still are, and without a budget lsg is too."""
    sets = ["camera.resolution=[16,12]", "camera.spp=1", 'render.method="lsg"',
            "render.lsg.light_rays=2000", f"render.time_budget={time_budget}"]
    monkeypatch.setattr(budget, "LONG_WORK", 1.0)      # every stage is "long"
    notes: list[str] = []
    with RenderSession.from_source("builtin:caustic_sphere", sets, engine=engine) as s:
        s.render(show_progress=False, on_note=notes.append)
    stages = [n.split(":", 1)[0] for n in notes if LONG in n]
    assert "view_paths" in stages
    assert ("lsg" in stages) == announced, notes
