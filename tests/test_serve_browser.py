"""The relighting page in a real browser: Playwright (Python) driving Debian's headless
``chromium`` (``scripts/setup.sh`` installs it; Playwright's own browser downloads are not
used).

Where ``scripts/setup.sh`` installs the browser -- under CI (``CI`` set), or on a Debian
machine where we are root and ``apt-get`` exists -- a missing Playwright or Chromium makes
this file FAIL: the page's only browser test must not pass by not running. Anywhere else it
is skipped, saying why.

Loads the page, drags the light's handle on the image, checks that the image's pixels
change, types a new ``sigma_s`` and a bad one, checks the stats and the one-line error, and
saves a screenshot into the test's output folder (``tmp_path``).
"""
from __future__ import annotations

import contextlib
import os
import shutil

import numpy as np
import pytest
from setup_installs import setup_installs_here as browser_required

REQUIRED = browser_required()
if REQUIRED:             # installed by scripts/setup.sh: an ImportError fails here
    import playwright.sync_api  # noqa: F401
    import starlette  # noqa: F401
    import uvicorn  # noqa: F401
pytest.importorskip("starlette", reason="clscatter serve needs the 'serve' extra (starlette)")
pytest.importorskip("uvicorn", reason="clscatter serve needs the 'serve' extra (uvicorn)")
sync_api = pytest.importorskip("playwright.sync_api",
                               reason="Playwright is not installed (pip install playwright)")


def _chromium() -> str | None:
    for name in (os.environ.get("CLSCATTER_CHROMIUM"), "/usr/bin/chromium", "chromium",
                 "chromium-browser"):
        if name and (os.path.isfile(name) or shutil.which(name)):
            return name if os.path.isfile(name) else shutil.which(name)
    return None


CHROMIUM = _chromium()
NO_CHROMIUM = ("no Chromium executable (apt-get install chromium; scripts/setup.sh does "
               "this) and Playwright's browser download is not used")


def need_chromium(chromium: str | None, required: str | None) -> str:
    """The browser to drive; without one, a failure where it is required, else a skip."""
    if chromium is not None:
        return chromium
    if required:
        pytest.fail(f"{NO_CHROMIUM}; it is required here ({required}: scripts/setup.sh "
                    "installs it)", pytrace=False)
    pytest.skip(NO_CHROMIUM)


def test_a_missing_browser_fails_where_setup_installs_it():
    """The rule above, on made-up machines (this one's browser is not touched)."""
    apt = {"apt-get": "/usr/bin/apt-get"}.get
    none = {}.get
    assert browser_required({"CI": "1"}, none, 1000) == "CI is set"
    assert browser_required({}, apt, 0) == "we are root on a machine with apt-get"
    assert browser_required({}, apt, 1000) is None            # not root: setup.sh needs sudo
    assert browser_required({}, none, 0) is None              # not Debian
    assert browser_required({"CI": ""}, none, 0) is None
    with pytest.raises(pytest.fail.Exception, match="required here"):
        need_chromium(None, "CI is set")
    with pytest.raises(pytest.skip.Exception, match="no Chromium executable"):
        need_chromium(None, None)
    assert need_chromium("/usr/bin/chromium", "CI is set") == "/usr/bin/chromium"


SPEC = "builtin:occluder"
TINY = ["camera.resolution=[64,48]", "camera.spp=1", 'render.method="raymarch"',
        "render.raymarch.steps=32"]


@contextlib.contextmanager
def open_page(spec: str, sets: list[str], keyframes: list[list[str]] = ()):
    """The relighting page of ``spec`` (with ``sets``, and ``keyframes`` for its frame
    slider) in headless Chromium, loaded; on leaving, no script error may have happened on
    the page."""
    chromium = need_chromium(CHROMIUM, REQUIRED)
    from clscatter.serve import BackgroundServer

    with BackgroundServer(spec, sets, keyframes=keyframes) as srv, \
            sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(srv.url)
            yield page
            assert not errors, errors
        finally:
            browser.close()


def pixels(page) -> np.ndarray:
    """The canvas's RGBA pixels as the page shows them."""
    data = page.evaluate("""() => { const c = document.getElementById('frame');
        return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data); }""")
    return np.asarray(data, dtype=np.int32).reshape(48, 64, 4)


def wait_final(page, after: int) -> None:
    """Until the page shows more than ``after`` full frames and is idle."""
    page.wait_for_function(
        f"Number(document.getElementById('frame').dataset.finals || 0) > {after} && "
        "document.body.dataset.busy === '0'", timeout=60_000)


def finals(page) -> int:
    return int(page.evaluate("document.getElementById('frame').dataset.finals || '0'"))


def test_drag_light_type_sigma_and_screenshot(tmp_path):
    with open_page(SPEC, TINY) as page:
        wait_final(page, 0)
        before = pixels(page)
        assert before[..., :3].max() > 50                      # a lit image, not black
        assert not page.is_visible("#notes")                   # raymarch drops nothing here

        # drag the point light's handle 120 px right and 40 px up on the image
        handle = page.locator(".handle.position")
        box = handle.bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        n = finals(page)
        page.mouse.move(x, y)
        page.mouse.down()
        for k in range(1, 9):
            page.mouse.move(x + 15 * k, y - 5 * k)
            page.wait_for_timeout(40)
        page.mouse.up()
        wait_final(page, n)
        after = pixels(page)
        changed = (np.abs(after[..., :3] - before[..., :3]).max(axis=-1) > 3).mean()
        assert changed > 0.10, f"only {changed:.1%} of the pixels changed after the drag"
        pos = page.input_value("#light-position")
        assert pos != "[0, 2.6, 0]" and pos.startswith("[")
        assert "bvh" in page.inner_text("#stats-reused")

        # type sigma_s: a new frame, new stats
        head = page.inner_text("#stats-head")
        n = finals(page)
        page.fill("#sigma_s", "0.35")
        page.press("#sigma_s", "Enter")
        wait_final(page, n)
        assert page.inner_text("#stats-head") != head
        assert "raymarch" in page.inner_text("#stats-run")
        thicker = pixels(page)
        assert np.abs(thicker[..., :3] - after[..., :3]).max() > 10

        # a bad value: the command line's one-line message on the page
        page.fill("#sigma_s", "-1")
        page.press("#sigma_s", "Enter")
        page.wait_for_function("document.getElementById('error').textContent.length > 0",
                               timeout=30_000)
        assert page.inner_text("#error") == \
            "medium.sigma_s: must be non-negative (got [-1, -1, -1])"
        assert "bad" in (page.get_attribute("#sigma_s", "class") or "")
        page.wait_for_function("document.body.dataset.busy === '0'", timeout=30_000)

        # Save still gives the last good settings (the bad value changed nothing)
        assert "disabled" not in (page.get_attribute("#save-toml", "class") or "")
        with page.expect_download() as dl:
            page.click("#save-toml")
        saved = tmp_path / "saved.toml"
        dl.value.save_as(saved)
        assert "sigma_s = 0.35" in saved.read_text()

        # orbit: drag the image itself; the camera moves and a new full frame comes
        n = finals(page)
        cbox = page.locator("#frame").bounding_box()
        cx, cy = cbox["x"] + cbox["width"] * 0.2, cbox["y"] + cbox["height"] * 0.8
        page.mouse.move(cx, cy)
        page.mouse.down()
        for k in range(1, 6):
            page.mouse.move(cx + 12 * k, cy)
            page.wait_for_timeout(40)
        page.mouse.up()
        wait_final(page, n)
        assert np.abs(pixels(page)[..., :3] - thicker[..., :3]).max() > 10

        shot = tmp_path / "serve_page.png"
        page.screenshot(path=str(shot))
        assert shot.stat().st_size > 10_000
        print(f"screenshot: {shot}")


def test_notes_that_leave_light_out_are_shown(monkeypatch):
    """raymarch on the glass scene leaves its caustics out: the page shows the command
    line's note above the image, and hides it again once ``auto`` (which adds them) ran
    (one refine round after its full frame, not the page's usual rounds)."""
    from clscatter.pipeline.planner import DROPS_LIGHT
    from clscatter.serve import app as app_mod
    monkeypatch.setattr(app_mod, "REFINE_ROUNDS", 1)

    tiny = ["camera.resolution=[32,24]", "camera.spp=1", 'render.method="raymarch"',
            "render.raymarch.steps=16"]
    with open_page("builtin:glass", tiny) as page:
        wait_final(page, 0)
        assert page.is_visible("#notes")
        lines = page.inner_text("#notes").strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("note: raymarch does not compute")
        assert lines[0].endswith(DROPS_LIGHT) and "caustics" in lines[0]
        n = finals(page)
        page.select_option("#method", "auto")
        wait_final(page, n)
        assert not page.is_visible("#notes") and page.inner_text("#notes") == ""


def test_hint_stage_dots_and_a_refused_value():
    """Under a directional sun (no handle) the hint points at the direction disc; the stage
    table marks a method's own stages ("raymarch" ran, so its row is marked); a refused
    value, after another control re-renders, shows the value in use again."""
    tiny = ["camera.resolution=[32,24]", "camera.spp=1", 'render.method="raymarch"',
            "render.raymarch.steps=8"]
    with open_page("builtin:shafts", tiny) as page:
        wait_final(page, 0)
        assert "direction disc" in page.inner_text("#hint-light")
        assert page.locator(".handle").count() == 0
        marked = page.eval_on_selector_all(
            "#stages tbody tr.ran td:first-child", "els => els.map(e => e.textContent)")
        assert "raymarch" in marked

        g = page.input_value("#g")
        page.fill("#g", "0.3.3")
        page.press("#g", "Enter")
        page.wait_for_function("document.getElementById('error').textContent.length > 0",
                               timeout=30_000)
        page.wait_for_function("document.body.dataset.busy === '0'", timeout=30_000)
        n = finals(page)
        # another control re-renders while the refused field still has the focus
        page.evaluate("""() => { const s = document.getElementById('sigma_s');
            s.value = '0.2'; s.dispatchEvent(new Event('change')); }""")
        wait_final(page, n)
        assert page.input_value("#g") == g
        assert "bad" not in (page.get_attribute("#g", "class") or "")


def test_keyframe_slider_renders_the_frame():
    """With keyframes the page shows a frame slider (hidden without); moving it to the last
    frame renders that frame: the light's intensity field shows the frame's value and the
    image changes (the page's exposure follows the image, so not by the factor)."""
    tiny = ["camera.resolution=[64,48]", "camera.spp=1", 'render.method="raymarch"',
            "render.raymarch.steps=8"]
    frames = [["lights[0].intensity=1.0"], ["lights[0].intensity=8.0"]]
    with open_page("builtin:occluder", tiny, frames) as page:
        wait_final(page, 0)
        assert page.is_visible("#frame-box")
        before = pixels(page)
        n = finals(page)
        page.evaluate("""() => { const s = document.getElementById('frame-slider');
            s.value = '1'; s.dispatchEvent(new Event('input'));
            s.dispatchEvent(new Event('change')); }""")
        wait_final(page, n)
        assert page.inner_text("#frame-label").strip() == "1 / 1"
        assert float(page.input_value("#light-power")) == 8.0
        assert not np.array_equal(pixels(page), before)
    with open_page("builtin:occluder", tiny) as page:
        wait_final(page, 0)
        assert not page.is_visible("#frame-box")
