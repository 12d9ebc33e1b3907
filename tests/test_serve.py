"""``clscatter serve`` without a browser: the real server (uvicorn on 127.0.0.1, a free port)
driven by a WebSocket client and plain HTTP.

Renders are tiny (48 x 36, 1 spp, raymarch) so the file runs in a few seconds. A session
wrapper that makes one chosen setting slow (it polls ``cancel`` like the real session does
between stages) makes cancellation deterministic instead of a race with a fast render.
"""
from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette", reason="clscatter serve needs the 'serve' extra (starlette)")
pytest.importorskip("uvicorn", reason="clscatter serve needs the 'serve' extra (uvicorn)")
httpx = pytest.importorskip("httpx", reason="the serve tests need httpx")
ws_client = pytest.importorskip("websockets.sync.client", reason="the serve tests need websockets")

from clscatter.errors import ClscatterError  # noqa: E402
from clscatter.serve import BackgroundServer  # noqa: E402
from clscatter.serve.app import dumps, open_session  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SPEC = "builtin:occluder"
TINY = ["camera.resolution=[48,36]", "camera.spp=1", 'render.method="raymarch"',
        "render.raymarch.steps=32"]
SLOW_SIGMA = 0.123           # a medium.sigma_s the slow session renders slowly (full only)
BROKEN_SIGMA = 0.321         # a medium.sigma_s whose render raises (a bug, not bad input)


class SlowSession:
    """A real session whose full renders of ``medium.sigma_s = SLOW_SIGMA`` first block
    until their ``cancel`` callback says stop, polling it every 10 ms like the real session
    polls it between stages. Nothing here is timed: the events say what happened
    (``slow_started``: a slow render is waiting; ``stopped_by_cancel``: cancel stopped it;
    ``closed_event``: the session was closed). ``SAFETY_S`` only keeps a broken
    cancellation from hanging the test run (the render then goes on, and the tests fail on
    the missing ``stopped_by_cancel``)."""

    SAFETY_S = 120.0

    def __init__(self, real):
        self.real = real
        self.closed = False
        self.slow_started = threading.Event()
        self.stopped_by_cancel = threading.Event()
        self.closed_event = threading.Event()

    def __getattr__(self, name):
        return getattr(self.real, name)

    def render(self, **kw):
        from clscatter.pipeline.session import Cancelled

        cancel = kw.get("cancel")
        medium = self.real.scene.medium
        if medium is not None and abs(float(medium.sigma_s[0]) - BROKEN_SIGMA) < 1e-9:
            raise RuntimeError("boom")
        if not kw.get("preview") and medium is not None and \
                abs(float(medium.sigma_s[0]) - SLOW_SIGMA) < 1e-9:
            self.slow_started.set()
            gave_up = threading.Event()
            timer = threading.Timer(self.SAFETY_S, gave_up.set)
            timer.daemon = True
            timer.start()
            try:
                while not gave_up.wait(0.01):
                    if cancel is not None and cancel():
                        self.stopped_by_cancel.set()
                        raise Cancelled("render cancelled")
            finally:
                timer.cancel()
        return self.real.render(**kw)

    def close(self):
        self.closed = True
        self.real.close()
        self.closed_event.set()


SESSIONS: list[SlowSession] = []


def slow_factory(spec, overrides, device):
    s = SlowSession(open_session(spec, overrides, device))
    SESSIONS.append(s)
    return s


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(SPEC, TINY, session_factory=slow_factory) as srv:
        yield srv


class Page:
    """A WebSocket client playing the page: send changes, read messages with timeouts."""

    def __init__(self, srv: BackgroundServer):
        self._cm = ws_client.connect(srv.url.replace("http://", "ws://") + "ws",
                                     max_size=1 << 24, open_timeout=30)
        self.ws = self._cm.__enter__()
        self.seen: list[dict] = []
        self.hello = self.next(lambda m: m["type"] == "hello", 60)
        self.page = self.hello["page"]
        self.id = 0

    def next(self, pred, timeout: float = 30.0) -> dict:
        """The first message (after those already read) for which ``pred`` holds."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no expected message within {timeout} s; got "
                                     f"{[m['type'] for m in self.seen[-12:]]}")
            m = json.loads(self.ws.recv(timeout=left))
            self.seen.append(m)
            if pred(m):
                return m

    def set(self, changes, mode: str = "full") -> int:
        self.id += 1
        self.ws.send(json.dumps({"type": "set", "id": self.id, "changes": changes, "mode": mode}))
        return self.id

    def final(self, request: int, timeout: float = 60.0) -> dict:
        return self.next(lambda m: m["type"] == "frame" and m["id"] == request and m["final"],
                         timeout)

    def close(self):
        self._cm.__exit__(None, None, None)


def decode(frame: dict) -> np.ndarray:
    import base64

    from PIL import Image
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(frame["png"]))).convert("RGB"))


@pytest.fixture
def page(server):
    p = Page(server)
    p.first = p.final(0)
    p.next(lambda m: m["type"] == "idle")
    yield p
    p.close()


def test_initial_frames_are_preview_then_full(page):
    """The first render comes as a quarter-resolution preview, then the full image."""
    frames = [m for m in page.seen if m["type"] == "frame"]
    assert [f["level"] for f in frames] == ["preview", "full"]
    assert (frames[0]["width"], frames[0]["height"]) == (16, 12)      # 48/3 x 36/3, 1 spp
    assert (frames[1]["width"], frames[1]["height"]) == (48, 36)
    assert frames[0]["stats"]["stages_run"][0] == "prepare_scene"
    assert frames[0]["notes"] == [] and frames[1]["notes"] == []   # raymarch drops nothing
    assert "bvh" in frames[1]["stats"]["reused"]           # the full render re-uses the BVH
    assert decode(frames[1]).shape == (36, 48, 3)


def test_frames_carry_the_notes_that_leave_light_out(tmp_path, capsys):
    """The page gets the plan's notes that leave light out of the image with every frame,
    in the words ``clscatter render`` prints (``clscatter: note: ...``): raymarch on the
    glass scene drops its caustics; switching to ``auto`` (which adds them) empties the
    list. (The occluder page of the other tests never has any.)"""
    from clscatter.cli import main
    from clscatter.pipeline.planner import DROPS_LIGHT

    tiny = ["camera.resolution=[32,24]", "camera.spp=1", 'render.method="raymarch"',
            "render.raymarch.steps=16"]
    with BackgroundServer("builtin:glass", tiny) as srv:
        p = Page(srv)
        try:
            full = p.final(0)
            frames = [m for m in p.seen if m["type"] == "frame"]
            assert [f["level"] for f in frames] == ["preview", "full"]
            notes = full["notes"]
            assert len(notes) == 1 and notes[0].endswith(DROPS_LIGHT) and "caustics" in notes[0]
            assert frames[0]["notes"] == notes              # the preview says it too
            assert notes[0] in full["stats"]["plan"]
            rid = p.set(['render.method="auto"'], mode="refine")
            after = p.final(rid, timeout=120)
            assert after["notes"] == [], after["notes"]
            assert "lsg" in after["stats"]["method"]
        finally:
            p.close()
    # the command line prints the same note
    assert main(["render", "builtin:glass", "--no-progress", "-o", str(tmp_path / "x.png"),
                 *[a for o in tiny for a in ("--set", o)]]) == 0
    err = capsys.readouterr().err
    assert [ln for ln in err.splitlines() if ln.startswith("clscatter: note: ")] == \
        [f"clscatter: note: {notes[0]}"]


def test_light_change_gives_new_frame_and_reuses_bvh(page):
    """Moving the light re-renders (pixels change) without rebuilding the BVH."""
    before = decode(page.first).astype(int)
    rid = page.set(["lights[0].position=[1.5, 2.6, 1.0]"])
    state = page.next(lambda m: m["type"] == "state" and m["id"] == rid)
    assert state["state"]["lights"][0]["position"] == [1.5, 2.6, 1.0]
    frame = page.final(rid)
    after = decode(frame).astype(int)
    changed = (np.abs(after - before).max(axis=-1) > 2).mean()
    assert changed > 0.10, f"only {changed:.1%} of the pixels changed"
    both = [m["stats"] for m in page.seen if m["type"] == "frame" and m["id"] == rid]
    assert [st["preview"] for st in both] == [True, False]
    for st in both:
        assert "bvh" in st["reused"] and "prepare_scene" not in st["stages_run"]
        assert "raymarch" in st["stages_run"] and "bvh_build" not in st["stages"]
    assert "upload_lights" in both[0]["stages_run"]     # the preview saw the change first


def test_preview_mode_renders_only_the_preview_and_refine_the_full(page):
    """While dragging the page asks for previews only; the end of the drag for the full one."""
    rid = page.set(["lights[0].position=[0.5, 2.4, 0.5]"], mode="preview")
    frame = page.next(lambda m: m["type"] == "frame" and m["id"] == rid)
    assert frame["level"] == "preview" and frame["stats"]["preview"] is True
    page.next(lambda m: m["type"] == "idle")
    page.id += 1
    page.ws.send(json.dumps({"type": "refine", "id": page.id}))
    full = page.final(page.id)
    assert full["stats"]["preview"] is False and full["width"] == 48
    levels = [m["level"] for m in page.seen if m["type"] == "frame" and m["id"] == page.id]
    assert levels == ["full"]                   # no redundant preview after a drag


def test_newer_change_cancels_the_render_in_flight(server, page):
    """A newer change stops the render in flight (between stages: the slow render below
    would otherwise block for good); the stale request never produces a frame; the page's
    worker never queues it. Event-based: no latency is measured."""
    worker = server.app.state.pages[page.page]
    session = worker.session
    slow = page.set([f"medium.sigma_s={SLOW_SIGMA}"], mode="refine")
    page.next(lambda m: m["type"] == "busy" and m["id"] == slow and m["level"] == "full")
    # "busy" goes out before the worker takes the device and calls the session: wait for
    # the slow render itself to start (an event, not a duration).
    assert session.slow_started.wait(60) and not session.stopped_by_cancel.is_set()
    fresh = page.set(["medium.sigma_s=0.2"], mode="refine")
    page.next(lambda m: m["type"] == "cancelled" and m["id"] == slow)
    assert session.stopped_by_cancel.is_set()       # stopped by cancel, not by running out
    frame = page.final(fresh)
    assert not [m for m in page.seen if m["type"] == "frame" and m["id"] == slow]
    state = [m for m in page.seen if m["type"] == "state" and m["id"] == fresh][-1]
    assert state["state"]["medium"]["sigma_s"] == 0.2
    assert frame["stats"]["reused"] == ["bvh"]
    assert worker.cancels == 1


def test_choosing_a_method_on_the_page_reaches_the_render(page, monkeypatch):
    """The page's *Method* menu sends ``render.method="NAME"`` (mode full, as app.js does):
    the state, the preview and the full frame all say the chosen method ran; choosing the
    first one again goes back. (One refine round after lsg's full frame: the rounds are
    test_progressive_passes_refine_after_the_full_frame's.)"""
    from clscatter.serve import app as app_mod
    monkeypatch.setattr(app_mod, "REFINE_ROUNDS", 1)
    js = (REPO / "clscatter" / "serve" / "static" / "app.js").read_text()
    assert '`render.method="${$("method").value}"`' in js     # what the menu sends
    methods = page.hello["state"]["methods"]
    assert page.hello["state"]["method"] == "raymarch" and "lsg" in methods
    assert page.first["stats"]["method"] == "raymarch"
    for name in ("lsg", "raymarch"):
        rid = page.set([f'render.method="{name}"'], mode="full")
        state = page.next(lambda m, rid=rid: m["type"] == "state" and m["id"] == rid)
        assert state["state"]["method"] == name
        full = page.final(rid, timeout=120)
        frames = [m for m in page.seen if m["type"] == "frame" and m["id"] == rid]
        assert [f["level"] for f in frames] == ["preview", "full"]
        for f in frames:
            assert f["stats"]["method"] == name, f["stats"]
            assert f["stats"]["requested_method"] == name
            assert name in f["stats"]["stages_run"]
            assert [p["method"] for p in f["stats"]["passes"]] == [name]
        assert "bvh" in full["stats"]["reused"]          # a method change keeps the scene
        page.next(lambda m: m["type"] == "idle")


def _cli_message(override: str) -> str:
    """The one-line message ``clscatter check SPEC --set ... --set override`` prints."""
    from clscatter.pipeline.render import check
    from clscatter.scene import load_scene
    try:
        check(load_scene(SPEC, [*TINY, override]))
    except ClscatterError as e:
        return " ".join(str(e).split())
    raise AssertionError(f"{override} was accepted")


BAD = ["medium.sigma_s=-1", "lights[0].intensity=abc", "medium.g=1.5", "camera.fov=",
       'render.method="nope"', "lights[3].position=[0, 1, 2]", "camera.spp=0",
       "medium.colour=1", "render.raymarch.steps=-4"]


def test_bad_input_gives_the_command_lines_one_line_message(page):
    """Each bad value typed into the page gives exactly the CLI's message; the session keeps
    its last good state and the next good change renders."""
    for bad in BAD:
        rid = page.set([bad])
        err = page.next(lambda m: m["type"] == "error" and m["id"] == rid)
        assert err["message"] == _cli_message(bad), bad
        assert "\n" not in err["message"] and err["change"] == bad
    # a bad and a good change together: the good one is applied
    rid = page.set(["medium.g=7", "medium.g=0.5"])       # same key: only the newest is kept
    page.final(rid)
    rid = page.set(["medium.sigma_a=-3", "medium.sigma_s=0.15"])
    page.next(lambda m: m["type"] == "error" and m["id"] == rid)
    state = page.next(lambda m: m["type"] == "state" and m["id"] == rid)
    assert state["state"]["medium"]["sigma_s"] == 0.15 and state["state"]["medium"]["g"] == 0.5
    page.final(rid)
    # malformed messages: an error, and the server goes on
    for text in ["not json", "[1, 2]", '{"type": "set"}', '{"type": "zap", "id": 9}',
                 '{"type": "set", "id": 10, "changes": "medium.g=0"}']:
        page.ws.send(text)
        assert page.next(lambda m: m["type"] == "error")["message"].startswith(("malformed", "unknown"))
    page.final(page.set(["medium.g=0.1"]))


def test_a_failing_render_is_reported_and_the_server_goes_on(page):
    """A render that raises (a bug) gives the page one line; the next change renders."""
    rid = page.set([f"medium.sigma_s={BROKEN_SIGMA}"])
    err = page.next(lambda m: m["type"] == "error" and m["id"] == rid)
    assert err["message"].startswith("internal error: RuntimeError: boom")
    page.final(page.set(["medium.sigma_s=0.1"]))


def test_cli_prints_the_same_line():
    """The message above is what the command line prints after ``clscatter: error:``."""
    bad = "medium.sigma_s=-1"
    out = subprocess.run([sys.executable, "-m", "clscatter", "check", SPEC, "--set", bad],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines()[-1] == f"clscatter: error: {_cli_message(bad)}"


def test_saved_toml_rerenders_to_the_same_image(server, page, tmp_path):
    """Save: the TOML of the current settings renders (fresh process state, no session) to
    exactly the EXR the page saved; the PNG is its tone-mapped image."""
    from clscatter.io.image import read_image, tonemap
    from clscatter.pipeline.render import render
    from clscatter.scene import load_scene

    rid = page.set(["lights[0].position=[-0.8, 2.2, 0.7]", "medium.sigma_s=0.18",
                    "medium.g=0.3", "camera.origin=[1.0, 1.8, 5.5]"])
    page.final(rid)
    page.next(lambda m: m["type"] == "idle")
    base = f"{server.url}save/{page.page}/"
    toml = httpx.get(base + "scene.toml", timeout=30)
    exr = httpx.get(base + "image.exr", timeout=30)
    png = httpx.get(base + "image.png", timeout=30)
    assert toml.status_code == exr.status_code == png.status_code == 200
    assert "attachment" in exr.headers["content-disposition"]
    (tmp_path / "saved.toml").write_text(toml.text)
    (tmp_path / "saved.exr").write_bytes(exr.content)
    (tmp_path / "saved.png").write_bytes(png.content)
    saved = read_image(tmp_path / "saved.exr")
    again = render(load_scene(tmp_path / "saved.toml"), show_progress=False).image
    assert saved.shape == (36, 48, 3) and np.isfinite(saved).all() and saved.max() > 0
    assert np.array_equal(again, saved), f"max |diff| {np.abs(again - saved).max():g}"
    from PIL import Image
    assert np.array_equal(np.asarray(Image.open(tmp_path / "saved.png").convert("RGB")),
                          tonemap(saved))
    # while a change is being rendered, Save refuses instead of mixing old image/new TOML
    slow = page.set([f"medium.sigma_s={SLOW_SIGMA}"], mode="refine")
    page.next(lambda m: m["type"] == "busy" and m["id"] == slow and m["level"] == "full")
    assert httpx.get(base + "scene.toml", timeout=30).status_code == 409
    page.final(page.set(["medium.sigma_s=0.18"], mode="refine"))
    assert httpx.get(f"{server.url}save/nosuchpage/scene.toml", timeout=30).status_code == 404


def test_closed_tab_stops_its_work(server):
    """Closing the page cancels its render (the slow render below would otherwise block
    for good) and frees its session; the worker thread ends. Event-based: the waits are
    generous bounds for a loaded machine, not timings."""
    p = Page(server)
    p.final(0)
    worker = server.app.state.pages[p.page]
    session = worker.session
    slow = p.set([f"medium.sigma_s={SLOW_SIGMA}"], mode="refine")
    p.next(lambda m: m["type"] == "busy" and m["id"] == slow and m["level"] == "full")
    assert session.slow_started.wait(60)       # "busy" precedes the call
    p.close()
    assert session.closed_event.wait(60), "the session was never closed"
    assert session.stopped_by_cancel.is_set()       # the render was cancelled, not finished
    worker.thread.join(60)
    assert not worker.thread.is_alive() and worker.cancels == 1
    assert session.closed
    # the page leaves the app's table when its socket handler ends (after the join)
    for _ in range(600):
        if p.page not in server.app.state.pages:
            break
        time.sleep(0.05)
    assert p.page not in server.app.state.pages


def test_page_and_assets_are_local(server):
    """One page, plain JS/CSS served from the package, nothing from outside (works offline)."""
    html = httpx.get(server.url, timeout=30).text
    for asset in ("/static/app.js", "/static/style.css"):
        assert asset in html
        assert httpx.get(server.url.rstrip("/") + asset, timeout=30).status_code == 200
    static = (REPO / "clscatter" / "serve" / "static")
    for f in static.iterdir():
        text = f.read_text()
        assert "http://" not in text and "https://" not in text and "//cdn" not in text, f.name


def test_messages_never_carry_nan_or_inf():
    """Stats with NaN/Inf go out as null; JSON without NaN/Inf literals."""
    text = dumps({"a": float("nan"), "b": [float("inf"), np.float32(-np.inf)], "c": np.ones(2)})
    assert json.loads(text) == {"a": None, "b": [None, None], "c": [1.0, 1.0]}
    assert "NaN" not in text and "Infinity" not in text


def test_serve_command_prints_the_url_and_warns_off_loopback():
    """``python -m clscatter.serve`` (the serve command) prints its URL, serves the page and
    warns when bound to an address other than 127.0.0.1."""
    proc = subprocess.Popen([sys.executable, "-m", "clscatter.serve", SPEC, "--port", "0",
                             "--host", "127.0.0.2", *[a for o in TINY for a in ("--set", o)]],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "http://127.0.0.2:" in line, line
        url = line.split(" at ")[1].split()[0]
        r = httpx.get(url, timeout=30)
        assert r.status_code == 200 and "clscatter" in r.text
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "warning: serving on 127.0.0.2" in err


def test_serve_command_bad_scene_is_one_line():
    """A bad scene or option fails before listening: one line, exit status 2."""
    for args in (["builtin:nope"], [SPEC, "--set", "medium.g=2"]):
        out = subprocess.run([sys.executable, "-m", "clscatter.serve", *args, "--port", "0"],
                             capture_output=True, text=True, cwd=REPO, timeout=120)
        assert out.returncode == 2, out.stderr
        lines = [ln for ln in out.stderr.splitlines() if ln.startswith("clscatter:")]
        assert len(lines) == 1 and lines[0].startswith("clscatter: error: "), out.stderr


def test_scene_state_offers_the_controls_the_scene_has():
    """The page's controls come from the scene: glass materials with their ior, the light's
    kind and values, and ``auto`` plus only the methods that apply."""
    from clscatter.methods import all_methods
    from clscatter.serve.app import scene_state

    s = open_session("builtin:caustic_sphere", [], None)
    try:
        st = scene_state(s, "builtin:caustic_sphere")
    finally:
        s.close()
    assert st["materials"]["glass"] == {"type": "dielectric", "ior": 1.5}
    assert st["lights"][0]["type"] == "point" and st["lights"][0]["intensity"] == 20.0
    assert st["methods"][0] == "auto" and "lsg" in st["methods"]
    assert set(st["methods"]) <= {"auto", *all_methods()}
    s = open_session("builtin:shafts", ["lights[0].direction=[0, -2, 0]"], None)
    try:
        st = scene_state(s, "builtin:shafts")
    finally:
        s.close()
    light = st["lights"][0]
    assert light["type"] == "directional" and light["irradiance"] == 3.0
    assert np.allclose(light["direction"], [0, -1, 0])        # normalised, as rendered
    assert not st["materials"] or all(m["type"] != "dielectric" for m in st["materials"].values())


def test_clscatter_serve_command():
    """``clscatter serve`` itself: a bad scene is one line, exit 2."""
    help_ = subprocess.run([sys.executable, "-m", "clscatter", "serve", "--help"],
                           capture_output=True, text=True, cwd=REPO, timeout=120)
    assert help_.returncode == 0, help_.stderr
    assert "--port" in help_.stdout and "--host" in help_.stdout
    out = subprocess.run([sys.executable, "-m", "clscatter", "serve", "builtin:nope", "--port", "0"],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "clscatter: error: builtin:nope: unknown built-in scene 'nope' (one of "
        + ", ".join(__import__("clscatter.scene", fromlist=["BUILTIN"]).BUILTIN) + ")"]


def test_progressive_passes_refine_after_the_full_frame():
    """On a caustic scene the full frame is followed by refine frames: fresh LSG passes
    (the next pass indices) averaged in, their count growing frame by frame, the image
    moving towards convergence; Save stays the full frame. A newer change stops the
    refinement: no refine frame of the old request follows the new request's frames."""
    from clscatter.serve import app as app_mod

    tiny = ["camera.resolution=[32,24]", "camera.spp=1", "render.lsg.light_rays=2000",
            "render.lsg.passes=2", "render.raymap.photons=2000"]
    rounds, app_mod.REFINE_ROUNDS = app_mod.REFINE_ROUNDS, 3
    try:
        with BackgroundServer("builtin:caustic_sphere", tiny) as srv:
            p = Page(srv)
            try:
                full = p.final(0, timeout=120)
                refs = [p.next(lambda m: m["type"] == "frame" and m["level"] == "refine", 120)
                        for _ in range(3)]
                p.next(lambda m: m["type"] == "idle", 60)
                counts = [r["stats"]["refine_passes"]["lsg"] for r in refs]
                assert counts[0] > 2 and counts == sorted(set(counts))      # 2: the full frame's
                assert all(not r["final"] for r in refs)
                assert not np.array_equal(decode(refs[-1]), decode(full))
                rid = p.set(["lights[0].intensity=30.0"], mode="refine")
                p.final(rid, timeout=120)
                newer = p.set(["lights[0].intensity=20.0"], mode="refine")
                p.final(newer, timeout=120)
                p.next(lambda m: m["type"] == "idle", 180)
                first_newer = next(i for i, m in enumerate(p.seen) if m.get("id") == newer)
                assert not [m for m in p.seen[first_newer:]
                            if m["type"] == "frame" and m["id"] == rid]
            finally:
                p.close()
    finally:
        app_mod.REFINE_ROUNDS = rounds


def test_a_converted_mitsuba_scene_logs_its_notes(tmp_path, caplog):
    """The page's session on a Mitsuba scene: what the conversion dropped is in the
    server's log, one warning a note (as the command line prints it)."""
    import logging

    from clscatter.scene.builtin import BUILTIN
    from clscatter.scene.mitsuba_out import write_xml
    from clscatter.serve.app import open_session

    xml = tmp_path / "scene.xml"
    write_xml(BUILTIN["occluder"](), xml)
    text = xml.read_text().replace("</scene>", '<shape type="cylinder" id="pillar"/>\n</scene>')
    xml.write_text(text)
    with caplog.at_level(logging.WARNING, logger="clscatter.serve"):
        session = open_session(str(xml), [], None)
        session.close()
    notes = [r.getMessage() for r in caplog.records if r.name == "clscatter.serve"]
    assert notes == ['note: shape "cylinder" (pillar): not a shape clscatter reads; dropped']


def test_keyframes_reach_the_page_and_a_frame_sets_its_keys(tmp_path):
    """``clscatter serve --keyframes``: the frames (each one's ``key=value`` changes, as
    :func:`clscatter.keyframes.load` makes them) come in ``hello``; sending a frame's changes
    (what the page's frame slider does) renders that frame, whose image differs from
    frame 0's and equals a fresh render of the scene with those keys. A missing keyframe
    file is the command line's one line, exit 2."""
    from clscatter.keyframes import load as load_keyframes
    from clscatter.pipeline.session import RenderSession

    kf = tmp_path / "keys.toml"
    kf.write_text('[[key]]\nframe = 0\n"lights[0].intensity" = 2.0\n'
                  '[[key]]\nframe = 2\n"lights[0].intensity" = 6.0\n')
    frames = load_keyframes(kf)
    assert frames == [["lights[0].intensity=2.0"], ["lights[0].intensity=4.0"],
                      ["lights[0].intensity=6.0"]]
    with BackgroundServer(SPEC, TINY, keyframes=frames) as srv:
        p = Page(srv)
        try:
            assert p.hello["keyframes"] == frames
            p.final(0)
            first = decode(p.final(p.set(frames[0])))
            last = decode(p.final(p.set(frames[2])))
        finally:
            p.close()
    assert not np.array_equal(first, last)
    with RenderSession.from_source(SPEC, TINY + frames[2]) as s:
        fresh = s.render(show_progress=False)
    from PIL import Image

    from clscatter.serve.app import png_bytes
    want = np.asarray(Image.open(io.BytesIO(png_bytes(fresh.image))).convert("RGB"))
    assert np.abs(last.astype(int) - want.astype(int)).max() <= 1
    out = subprocess.run([sys.executable, "-m", "clscatter", "serve", SPEC, "--port", "0",
                          "--keyframes", str(tmp_path / "missing.toml")],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1 and "missing.toml" in out.stderr
