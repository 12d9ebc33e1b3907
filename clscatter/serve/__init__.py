"""``clscatter serve SCENE``: a local web page to relight a scene interactively.

Drag the light on the image, orbit the camera, change the medium, the light's intensity,
a glass material's ior and the method; previews come while dragging and the full render
when the user stops (``docs/serve.md``). The web framework (Starlette + uvicorn) is an
optional extra, imported only here: ``pip install 'clscatter[serve]'``.

The command line wires :func:`add_serve_command` and :func:`cmd_serve` in; errors the user
can fix (a bad scene, a port in use, the extra missing) are :class:`ClscatterError` s, so
they print as one line with exit status 2 like every other command.
"""
from __future__ import annotations

import argparse
import socket
import sys
from typing import Any, Sequence

from ..errors import ClscatterError

LOOPBACK = ("127.0.0.1", "localhost", "::1")

__all__ = ["add_serve_command", "cmd_serve", "serve", "LOOPBACK"]


def add_serve_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``serve`` to the ``clscatter`` sub-command parsers; returns its parser."""
    s = subparsers.add_parser("serve", help="serve a local web page to relight a scene")
    s.add_argument("scene", nargs="?", default=None,
                   help="scene TOML file or builtin:NAME (default: the built-in demo)")
    s.add_argument("--port", type=_port, default=8000,
                   help="TCP port (default 8000; 0 picks a free one)")
    s.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    s.add_argument("--method", default=None, help="initial render.method")
    s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key (dotted path, TOML value); repeatable")
    s.add_argument("--device", default=None, help="OpenCL device: P:D or a name substring")
    s.add_argument("--keyframes", default=None, metavar="FILE.toml",
                   help="keyframed scene keys (as for relight): the page gets a frame slider")
    return s


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be in [0, 65535] (got {value})")
    return value


def _need_extra() -> None:
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as e:
        raise ClscatterError(f"clscatter serve needs the Python package '{e.name}': "
                             "pip install 'clscatter[serve]'") from None


def _listen(host: str, port: int) -> socket.socket:
    """A bound, listening socket (so port 0 can be resolved and printed before serving)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise ClscatterError(f"--host {host}: cannot resolve ({e.strerror})") from None
    family, kind, proto, _, addr = infos[0]
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(addr)
        sock.listen(64)
    except OSError as e:
        sock.close()
        raise ClscatterError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    return sock


def url_of(sock: socket.socket) -> str:
    """The page's address for a listening socket."""
    host, port = sock.getsockname()[:2]
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/"


def serve(spec: str, overrides: Sequence[str] = (), host: str = "127.0.0.1", port: int = 8000,
          device: str | None = None, ready=None,
          keyframes: Sequence[Sequence[str]] = ()) -> None:
    """Check the scene, listen on ``host:port``, print the URL and serve until interrupted.

    ``ready(url)`` is called instead of printing when given. The scene is loaded and checked
    first, so a bad scene fails here with the command line's one-line error; so is every
    frame of ``keyframes`` (:func:`clscatter.keyframes.load`: each frame's ``--set``
    overrides), which the page offers on a frame slider."""
    _need_extra()
    from ..pipeline.render import check
    from ..scene import load_scene

    check(load_scene(spec, overrides))           # one-line SceneError before listening
    for frame in keyframes:
        check(load_scene(spec, [*overrides, *frame]))
    if host not in LOOPBACK:
        print(f"clscatter: warning: serving on {host}: anyone who can reach this address can "
              "use the page and the device (default: 127.0.0.1)", file=sys.stderr)
    import uvicorn

    from .app import create_app

    sock = _listen(host, port)
    url = url_of(sock)
    if ready is not None:
        ready(url)
    else:
        print(f"clscatter serve: {spec} at {url}  (Ctrl-C stops)", flush=True)
    app = create_app(spec, overrides, device, keyframes=keyframes)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", ws_max_size=1 << 20))
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()


class BackgroundServer:
    """The page's server on a thread of this process, on 127.0.0.1 and a free port (tests,
    the benchmark): ``with BackgroundServer(spec, overrides) as srv: srv.url``; ``srv.app``
    is the Starlette app (``srv.app.state.pages`` holds the open pages)."""

    def __init__(self, spec: str, overrides: Sequence[str] = (), device: str | None = None,
                 session_factory=None, keyframes: Sequence[Sequence[str]] = ()):
        _need_extra()
        import threading

        import uvicorn

        from .app import create_app

        self.app = create_app(spec, overrides, device, session_factory, keyframes)
        self._sock = _listen("127.0.0.1", 0)
        self.url = url_of(self._sock)
        self._server = uvicorn.Server(uvicorn.Config(self.app, log_level="warning"))
        self._thread = threading.Thread(target=self._server.run,
                                        kwargs={"sockets": [self._sock]}, daemon=True)

    def __enter__(self) -> "BackgroundServer":
        import time

        self._thread.start()
        deadline = time.monotonic() + 30
        while not self._server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError("the page server did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.should_exit = True
        self._thread.join(60)
        self._sock.close()


def cmd_serve(args: argparse.Namespace) -> int:
    """``clscatter serve [SCENE] [--port P] [--host H] [--method M] [--set k=v] [--device D]``."""
    from ..scene import DEFAULT_BUILTIN

    overrides = list(args.overrides)
    if args.method is not None:
        overrides.append(f'render.method="{args.method}"')
    frames: list[list[str]] = []
    if args.keyframes is not None:
        from ..keyframes import load as load_keyframes
        frames = load_keyframes(args.keyframes)
    serve(args.scene or f"builtin:{DEFAULT_BUILTIN}", overrides, host=args.host, port=args.port,
          device=args.device, keyframes=frames)
    return 0
