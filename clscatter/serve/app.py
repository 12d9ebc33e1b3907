"""The relighting page's server: a Starlette app, one WebSocket per page, one worker thread
per page that owns a :class:`clscatter.pipeline.session.RenderSession`.

Why this shape:

* Rendering is blocking device work, so it runs on a worker thread, never on the event
  loop; the loop only moves messages, and the server answers (pages, saves, other tabs)
  while a render is running.
* A page never queues work. Every change the page sends lands in a mailbox that keeps only
  the newest value per key and bumps a generation counter; the render in flight polls the
  counter through the session's ``cancel`` callback (between stages) and stops with
  :class:`~clscatter.pipeline.session.Cancelled` as soon as a newer change exists. A stale result
  that finishes anyway is dropped, never sent.
* Progressive frames: a change first renders a preview (the session's reduced resolution,
  1 spp), then, unless the page asked for the preview alone (it does while the user drags),
  the full render at the scene's own settings. That full image is exactly what
  ``clscatter render`` of the saved TOML gives (tested), and what Save downloads; where
  the scene sets no ``render.time_budget`` it renders within :data:`FULL_SECONDS`. Where
  the plan has progressive passes (``lsg``), refinement rounds follow: fresh passes of
  those methods alone, a couple of seconds each, streamed as ``refine`` frames of the
  converging mean, until a newer change arrives (polled between passes, so stale work
  stops within a pass) or :data:`REFINE_ROUNDS` have run.
* Bad input is validated like the command line (``--set`` parsing, the loader, the method
  check) before the session changes; the page shows the same one-line message and the
  session keeps its last good state.
* Device work of all pages is serialised by one lock (the OpenCL engine is process-wide);
  a closed tab cancels its render and frees its device buffers.

Protocol (JSON text messages on ``/ws``):

page -> server
    ``{"type": "set", "id": N, "changes": ["medium.sigma_s=0.3", ...], "mode": M}``: apply
    the changes, then render: M = "preview" (a preview only: the user is dragging), "full"
    (a preview, then the full render) or "refine" (the full render only: a drag ended)
    ``{"type": "refine", "id": N}``: render the current settings at full quality only
    (sent when a drag ends: its previews were already shown)
server -> page
    ``hello`` (page id, scene state, methods, ``keyframes``: each frame's ``key=value``
    changes, empty without ``--keyframes``; the page's frame slider sends a frame's changes
    as a ``set``), ``state`` (after an accepted change),
    ``busy`` (a render started), ``frame`` (level ``preview``, ``full`` or ``refine``; a
    PNG as base64, its stats and ``notes``: the
    plan's notes that leave light out of the image, which the command line prints as
    ``clscatter: note: ...``), ``error`` (one line), ``cancelled`` (the request's render was
    superseded), ``idle`` (nothing left to do).
"""
from __future__ import annotations

import asyncio
import base64
import copy
import io
import json
import logging
import secrets
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from ..errors import ClscatterError
from ..io.stats import json_safe

STATIC = Path(__file__).resolve().parent / "static"
LOG = logging.getLogger("clscatter.serve")

# the OpenCL engine is shared by every session in the process: one render at a time
_DEVICE_LOCK = threading.Lock()


def one_line(err: BaseException) -> str:
    """The message the command line prints for ``err`` (``clscatter: error: <this>``)."""
    return " ".join(str(err).split())


def dumps(msg: dict) -> str:
    """JSON text of a message; raises if anything non-finite slipped through."""
    return json.dumps(json_safe(msg, "null"), allow_nan=False, separators=(",", ":"))


def png_bytes(image: np.ndarray, exposure: float = 0.0) -> bytes:
    """Tone-mapped 8-bit sRGB PNG of linear ``image`` (the CLI's PNG tone curve)."""
    from PIL import Image

    from ..io.image import tonemap

    buf = io.BytesIO()
    Image.fromarray(tonemap(image, exposure)).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def exr_bytes(image: np.ndarray) -> bytes:
    """The float32 linear image as an OpenEXR file (written by :func:`clscatter.io.image.write_image`)."""
    from ..io.image import write_image

    with tempfile.TemporaryDirectory(prefix="clscatter-serve-") as tmp:
        path = Path(tmp) / "image.exr"
        write_image(path, image)
        return path.read_bytes()


def override_key(text: str) -> str:
    """The key part of ``key=value``, normalised (``lights.0.x`` == ``lights[0].x``), used
    to keep only the newest pending value of each key."""
    import re

    key = text.partition("=")[0].strip()
    return re.sub(r"\[\s*(\d+)\s*\]", r".\1", key)


# ---------------------------------------------------------------------------- sessions

def open_session(spec: str, overrides: Sequence[str], device: str | None):
    """A :class:`~clscatter.pipeline.session.RenderSession` on ``spec`` with ``--set``
    overrides; what converting a Mitsuba scene approximated goes to the server's log."""
    from ..pipeline.session import RenderSession

    return RenderSession.from_source(spec, list(overrides), device=device,
                                     on_note=lambda line: LOG.warning("note: %s", line))


def applicable_methods(scene) -> list[str]:
    """``auto`` and every implemented method that suits ``scene`` and would compute a term
    it needs (an explicit method with nothing to do is left out)."""
    from ..methods import all_methods
    from ..pipeline.planner import plan

    out = ["auto"]
    for name, cls in all_methods().items():
        try:
            if cls.suits(scene):
                continue
            passes, _ = plan(scene, name)
        except Exception:       # a method whose planner hook fails is not offered
            continue
        if passes:
            out.append(name)
    return out


def scene_state(session, spec: str) -> dict:
    """What the page shows and edits: the scene's raw tables (as the TOML has them), the
    camera as the renderer sees it (defaults filled in), lights with their effective
    values, dielectric materials, the methods that apply."""
    scene = session.scene
    data = session.current_data()
    cam = scene.camera
    lights = []
    for i, (raw, light) in enumerate(zip(data.get("lights", []) or [], scene.lights)):
        item = {"index": i, "type": light.type}
        if light.position is not None:
            item["position"] = light.position
        if light.type == "spot":
            item["target"] = raw.get("target")
            item["intensity"] = raw.get("intensity")
            item["cutoff_angle"] = light.cutoff_angle
        elif light.type == "point":
            item["intensity"] = raw.get("intensity")
        else:
            item["direction"] = light.direction
            item["irradiance"] = raw.get("irradiance")
        lights.append(item)
    medium = data.get("medium") or {}
    materials = {name: {"type": m.type, "ior": m.ior} for name, m in scene.materials.items()}
    return {
        "source": spec,
        "camera": {"origin": cam.origin, "target": cam.target, "up": cam.up, "fov": cam.fov,
                   "fov_axis": cam.fov_axis, "width": cam.width, "height": cam.height,
                   "spp": cam.spp},
        "medium": {"present": scene.medium is not None,
                   "sigma_s": medium.get("sigma_s", 0.0), "sigma_a": medium.get("sigma_a", 0.0),
                   "g": medium.get("g", 0.0)},
        "lights": lights,
        "materials": materials,
        "method": scene.render.method,
        "methods": applicable_methods(scene),
    }


@dataclass
class Frame:
    """The last full-quality frame of a page: what Save downloads (image and the TOML of
    the settings it was rendered with)."""

    image: np.ndarray
    toml: str
    stats: dict
    version: int


@dataclass
class _Mailbox:
    pending: dict[str, str] = field(default_factory=dict)   # key -> newest "key=value"
    mode: str | None = None        # "preview" | "full" | None
    request: int = 0               # id of the newest request
    generation: int = 0            # bumped by every request: renders of older ones stop
    closed: bool = False


class PageWorker:
    """One page: its session, its mailbox and the worker thread that renders for it.

    ``send`` is called from the worker thread with each message for the page (it must be
    thread-safe; the app passes one that hands the message to the event loop).
    """

    def __init__(self, spec: str, overrides: Sequence[str], device: str | None,
                 send: Callable[[dict], None],
                 session_factory: Callable[..., Any] | None = None):
        self.page = secrets.token_hex(8)
        self.spec = spec
        self.send = send
        factory = session_factory or open_session
        self.session = factory(spec, overrides, device)
        self.box = _Mailbox()
        self.cond = threading.Condition()
        self.version = 0              # bumped by every accepted change
        self.last_full: Frame | None = None
        self.renders = 0              # renders completed (for tests and the bench)
        self.cancels = 0              # renders stopped by a newer change or a closed page
        self.thread = threading.Thread(target=self._run, name=f"clscatter-page-{self.page}",
                                       daemon=True)

    def start(self, first_mode: str = "full") -> None:
        """Start the worker; it renders the initial scene (preview, then full)."""
        with self.cond:
            self.box.mode = first_mode
        self.thread.start()

    # ---- called from the event loop ------------------------------------------------------
    def submit(self, request: int, changes: Sequence[str], mode: str) -> None:
        """Queue ``changes`` (``key=value`` strings) and a render at ``mode``; whatever is
        rendering now is cancelled at its next stage boundary."""
        with self.cond:
            for text in changes:
                key = override_key(text)
                self.box.pending.pop(key, None)     # keep the order of the newest changes
                self.box.pending[key] = text
            self.box.mode = mode            # the newest request says what to render
            self.box.request = request
            self.box.generation += 1
            self.cond.notify()

    def close(self) -> None:
        """The page went away: cancel the render in flight, end the thread, free the device."""
        with self.cond:
            self.box.closed = True
            self.box.generation += 1
            self.cond.notify()

    # ---- the worker thread ---------------------------------------------------------------
    def _run(self) -> None:
        try:
            while True:
                with self.cond:
                    while not self.box.closed and self.box.mode is None and not self.box.pending:
                        self.cond.wait()
                    if self.box.closed:
                        return
                    changes = list(self.box.pending.values())
                    self.box.pending.clear()
                    mode = self.box.mode or "full"
                    self.box.mode = None
                    request, generation = self.box.request, self.box.generation
                if changes and not self._apply(request, changes):
                    self._send_idle(generation)
                    continue
                self._render(request, generation, mode)
        except Exception:               # never silently: the page hears about it
            LOG.error("page worker failed:\n%s", traceback.format_exc())
            self.send({"type": "error", "id": None,
                       "message": "internal error in the page worker (see the server log)"})
        finally:
            try:
                self.session.close()
            except Exception:
                LOG.error("closing the session failed:\n%s", traceback.format_exc())

    def _validate(self, changes: Sequence[str]) -> None:
        """Raise the command line's error for ``changes`` on top of the current settings."""
        self.session.validate(list(changes))

    def _apply(self, request: int, changes: list[str]) -> bool:
        """Apply the changes the loader and the method check accept; one ``error`` message
        per rejected one. True if anything changed."""
        try:
            self._validate(changes)
            accepted = changes
        except ClscatterError:
            accepted = []
            for text in changes:             # find the culprit(s); keep the good ones
                try:
                    self._validate([*accepted, text])
                    accepted.append(text)
                except ClscatterError as e:
                    self.send({"type": "error", "id": request, "change": text,
                               "message": one_line(e)})
        if not accepted:
            return False
        self.session.set(accepted)
        self.version += 1
        self.send({"type": "state", "id": request, "version": self.version,
                   "state": scene_state(self.session, self.spec)})
        return True

    def _stale(self, generation: int) -> bool:
        return self.box.closed or self.box.generation != generation

    def _send_idle(self, generation: int) -> None:
        """Nothing left to render; ``saveable``: the last full frame is of the current
        settings (what Save downloads)."""
        if not self._stale(generation):
            frame = self.last_full
            self.send({"type": "idle",
                       "saveable": frame is not None and frame.version == self.version})

    def _render(self, request: int, generation: int, mode: str) -> None:
        from ..pipeline.session import Cancelled

        levels = {"preview": ["preview"], "refine": ["full"]}.get(mode, ["preview", "full"])
        version = self.version
        for level in levels:
            if self._stale(generation):
                return
            self.send({"type": "busy", "id": request, "level": level})
            t0 = time.perf_counter()
            try:
                with _DEVICE_LOCK:
                    if self._stale(generation):
                        raise Cancelled("superseded before it started")
                    result = self.session.render(show_progress=False, preview=level == "preview",
                                                 cancel=lambda: self._stale(generation),
                                                 default_budget=FULL_SECONDS)
            except Cancelled:
                self.cancels += 1
                if not self.box.closed:
                    self.send({"type": "cancelled", "id": request, "level": level})
                return
            except ClscatterError as e:
                self.send({"type": "error", "id": request, "message": one_line(e)})
                self._send_idle(generation)
                return
            except Exception as e:      # a bug, not bad input: tell the page, keep serving
                LOG.error("render failed:\n%s", traceback.format_exc())
                self.send({"type": "error", "id": request, "message":
                           f"internal error: {type(e).__name__}: {one_line(e)} (see the "
                           "server's log)"})
                self._send_idle(generation)
                return
            seconds = time.perf_counter() - t0
            self.renders += 1
            if self._stale(generation):     # finished, but a newer change exists: drop it
                self.cancels += 1
                return
            final = level == "full"
            if final:
                self.last_full = Frame(result.image, self.session.to_toml(), result.stats,
                                       version)
            self._send_frame(request, level, final, version, seconds, result.image,
                             result.stats)
            if final and not self._refine(request, generation, version, result):
                return
        self._send_idle(generation)

    def _send_frame(self, request: int, level: str, final: bool, version: int,
                    seconds: float, image: np.ndarray, stats: dict) -> None:
        self.send({"type": "frame", "id": request, "level": level, "final": final,
                   "version": version, "seconds": seconds,
                   "width": int(image.shape[1]), "height": int(image.shape[0]),
                   "png": base64.b64encode(png_bytes(image)).decode("ascii"),
                   "stats": frame_stats(stats), "notes": light_notes(stats)})

    def _refine(self, request: int, generation: int, version: int, full) -> bool:
        """After a full frame, up to :data:`REFINE_ROUNDS` rounds of fresh progressive
        passes (the plan's ``SPLIT_PASSES`` passes only, the next pass indices, at most
        :data:`REFINE_SECONDS` each), each streamed as a ``refine`` frame: the image is the
        full frame's fixed passes plus the mean of every progressive pass so far, so it
        converges while nothing newer arrives. False when a newer change stopped it."""
        from ..pipeline.session import Cancelled

        split = [(k, m) for k, m in self.session.progressive_passes() if k in full.parts]
        if not split or REFINE_ROUNDS == 0:
            return True
        done = {k: full.part_passes[k] for k, _ in split}
        sums = {k: full.parts[k].astype(np.float64) * done[k] for k, _ in split}
        fixed = full.image.astype(np.float64) - sum(full.parts[k] for k, _ in split)
        for _ in range(REFINE_ROUNDS):
            if self._stale(generation):
                return False
            params = {k: {"first_pass": done[k], "passes": 1 << 10,
                          "time_budget": REFINE_SECONDS} for k, _ in split}
            t0 = time.perf_counter()
            try:
                with _DEVICE_LOCK:
                    r = self.session.render(show_progress=False, only=[k for k, _ in split],
                                            pass_params=params,
                                            cancel=lambda: self._stale(generation))
            except Cancelled:
                self.cancels += 1
                return False
            for k, _ in split:
                n = r.part_passes[k]
                sums[k] += r.parts[k].astype(np.float64) * n
                done[k] += n
            if self._stale(generation):
                return False
            image = (fixed + sum(sums[k] / done[k] for k, _ in split)).astype(np.float32)
            stats = {**full.stats, "refine_passes": {m: done[k] for k, m in split}}
            self.renders += 1
            self._send_frame(request, "refine", False, version, time.perf_counter() - t0,
                             image, stats)
        return True


#: a full frame's time budget where the scene sets none (refinement rounds follow it)
FULL_SECONDS = 4.0
#: refinement rounds after a full frame, and the seconds of progressive passes in each
REFINE_ROUNDS = 8
REFINE_SECONDS = 2.0


def frame_stats(stats: dict) -> dict:
    """The stats the page shows: seconds per stage, what ran, what was re-used, the plan."""
    keep = ("method", "requested_method", "plan", "passes", "width", "height", "spp",
            "seconds_total", "stages", "stages_run", "reused", "preview", "device",
            "peak_bytes", "nonfinite_pixels_zeroed", "refine_passes")
    return {k: copy.deepcopy(stats[k]) for k in keep if k in stats}


def light_notes(stats: dict) -> list[str]:
    """The plan's notes that say light the scene needs is left out of the image (the lines
    ``clscatter render`` prints as ``clscatter: note: ...``); the page shows them."""
    from ..pipeline.planner import dropped_light

    return list(dropped_light(list(stats.get("plan") or [])))


# --------------------------------------------------------------------------------- app

@dataclass
class ServeConfig:
    """What ``clscatter serve`` was started with."""

    spec: str
    overrides: list[str] = field(default_factory=list)
    device: str | None = None
    session_factory: Callable[..., Any] | None = None
    keyframes: list[list[str]] = field(default_factory=list)


def create_app(spec: str, overrides: Sequence[str] = (), device: str | None = None,
               session_factory: Callable[..., Any] | None = None,
               keyframes: Sequence[Sequence[str]] = ()) -> Starlette:
    """The Starlette app serving the page for scene ``spec`` (``--set`` ``overrides``);
    ``keyframes`` (each frame's overrides, :func:`clscatter.keyframes.load`) go to the page
    in ``hello``, which shows a frame slider that sets a frame's keys as any change does;
    the page opens at frame 0.

    Each WebSocket connection gets its own :class:`PageWorker` (its own session, so tabs do
    not disturb each other); ``app.state.pages`` maps page ids to workers while they are
    open. ``session_factory(spec, overrides, device)`` replaces :func:`open_session` (tests).
    """
    frames = [list(f) for f in keyframes]
    # the page opens at frame 0
    config = ServeConfig(spec, list(overrides) + (frames[0] if frames else []), device,
                         session_factory, frames)
    pages: dict[str, PageWorker] = {}

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    async def favicon(request: Request) -> Response:
        return Response(status_code=204)

    async def health(request: Request) -> Response:
        return JSONResponse({"scene": config.spec, "pages": len(pages)})

    async def save(request: Request) -> Response:
        page = pages.get(request.path_params["page"])
        what = request.path_params["what"]
        if page is None:
            return PlainTextResponse("no such page (reload it)", status_code=404)
        frame = page.last_full
        if frame is None or frame.version != page.version:
            return PlainTextResponse("the image is still being rendered: save when the busy "
                                     "indicator stops", status_code=409)
        stem = _stem(config.spec)
        if what == "image.png":
            body, media, name = png_bytes(frame.image), "image/png", f"{stem}.png"
        elif what == "image.exr":
            body, media, name = await asyncio.to_thread(exr_bytes, frame.image), \
                "image/x-exr", f"{stem}.exr"
        elif what == "scene.toml":
            body, media, name = frame.toml.encode(), "application/toml", f"{stem}.toml"
        else:
            return PlainTextResponse("unknown download", status_code=404)
        return Response(body, media_type=media,
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})

    async def socket(ws: WebSocket) -> None:
        await ws.accept()
        loop = asyncio.get_running_loop()
        outbox: asyncio.Queue[dict | None] = asyncio.Queue()

        def send(msg: dict) -> None:        # from the worker thread
            loop.call_soon_threadsafe(outbox.put_nowait, msg)

        try:
            worker = await asyncio.to_thread(PageWorker, config.spec, config.overrides,
                                             config.device, send, config.session_factory)
        except ClscatterError as e:
            await ws.send_text(dumps({"type": "error", "id": None, "message": one_line(e)}))
            await ws.close()
            return
        pages[worker.page] = worker
        state = await asyncio.to_thread(scene_state, worker.session, config.spec)
        await ws.send_text(dumps({"type": "hello", "page": worker.page, "state": state,
                                  "keyframes": config.keyframes}))
        worker.start()

        async def pump() -> None:
            while True:
                msg = await outbox.get()
                if msg is None:
                    return
                await ws.send_text(dumps(msg))

        sender = asyncio.create_task(pump())
        try:
            while True:
                text = await ws.receive_text()
                reply = handle_message(worker, text)
                if reply is not None:
                    await outbox.put(reply)
        except WebSocketDisconnect:
            pass
        finally:
            worker.close()
            pages.pop(worker.page, None)
            sender.cancel()
            await asyncio.to_thread(worker.thread.join, 30.0)

    app = Starlette(routes=[
        Route("/", index),
        Route("/health", health),
        Route("/favicon.ico", favicon),
        Route("/save/{page}/{what}", save),
        WebSocketRoute("/ws", socket),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ])
    app.state.pages = pages
    app.state.config = config
    return app


def handle_message(worker: PageWorker, text: str) -> dict | None:
    """Act on one message from the page; a reply for malformed ones (never an exception)."""
    try:
        msg = json.loads(text)
    except ValueError:
        return {"type": "error", "id": None, "message": "malformed message (not JSON)"}
    if not isinstance(msg, dict):
        return {"type": "error", "id": None, "message": "malformed message (not an object)"}
    request = msg.get("id")
    if not isinstance(request, int) or isinstance(request, bool):
        return {"type": "error", "id": None, "message": "malformed message (no integer id)"}
    kind = msg.get("type")
    if kind == "set":
        changes = msg.get("changes")
        mode = msg.get("mode", "full")
        if not isinstance(changes, list) or not all(isinstance(c, str) for c in changes) \
                or mode not in ("preview", "full", "refine"):
            return {"type": "error", "id": request, "message": "malformed set (changes: list "
                    "of key=value, mode: preview|full|refine)"}
        worker.submit(request, changes, mode)
        return None
    if kind == "refine":
        worker.submit(request, [], "refine")
        return None
    return {"type": "error", "id": request, "message": f"unknown message type {kind!r}"}


def _stem(spec: str) -> str:
    name = spec.split(":", 1)[1] if spec.startswith("builtin:") else Path(spec).stem
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "scene"
