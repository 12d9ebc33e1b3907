"""Latency of the relighting page (``clscatter serve``): from a light drag to the first
preview frame, and from the end of the drag to the full (converged) frame.

Runs the real server on 127.0.0.1 in this process and talks to it over its WebSocket like
the page does: a drag step is a ``set`` with ``mode: preview``; the end of the drag is a
``refine``. Each scene's light is moved ``--drags`` times (point lights along a small
circle, directional lights around the vertical). Also records the first (cold) frame.
Writes ``bench_out/serve.json`` and prints a Markdown table; with ``--screenshot FILE`` a
headless-Chromium screenshot of the page on the first scene (needs Playwright and Debian's
``chromium``).

    .venv/bin/python tools/bench_serve.py [--scenes builtin:shafts builtin:caustic_sphere]
        [--drags 5] [--screenshot docs/serve.png]
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def light_move(state: dict, k: int, n: int) -> str:
    """The k-th of n drag positions of light 0 as an override."""
    light = state["lights"][0]
    a = 2 * math.pi * (k + 1) / (n + 1)
    if light["type"] == "directional":
        d = light["direction"]
        tilt = math.atan2(math.hypot(d[0], d[2]), -d[1])
        az = math.atan2(d[2], d[0]) + 0.4 * math.sin(a)
        v = [math.sin(tilt) * math.cos(az), -math.cos(tilt), math.sin(tilt) * math.sin(az)]
        return f"lights[0].direction=[{v[0]:.5f}, {v[1]:.5f}, {v[2]:.5f}]"
    p = light["position"]
    q = [p[0] + 0.3 * math.cos(a), p[1], p[2] + 0.3 * math.sin(a)]
    return f"lights[0].position=[{q[0]:.5f}, {q[1]:.5f}, {q[2]:.5f}]"


def bench_scene(spec: str, drags: int, overrides: list[str]) -> dict:
    from websockets.sync.client import connect

    from clscatter.serve import BackgroundServer

    with BackgroundServer(spec, overrides) as srv, \
            connect(srv.url.replace("http://", "ws://") + "ws", max_size=1 << 26,
                    open_timeout=60) as ws:
        def until(pred, timeout=600.0):
            deadline = time.monotonic() + timeout
            while True:
                m = json.loads(ws.recv(timeout=max(0.01, deadline - time.monotonic())))
                if m["type"] == "error":
                    raise RuntimeError(m["message"])
                if pred(m):
                    return m

        t0 = time.perf_counter()
        hello = until(lambda m: m["type"] == "hello")
        state = hello["state"]
        first_preview = until(lambda m: m["type"] == "frame" and not m["final"])
        t_first_preview = time.perf_counter() - t0
        first = until(lambda m: m["type"] == "frame" and m["final"])
        t_first = time.perf_counter() - t0
        until(lambda m: m["type"] == "idle")
        print(f"{spec}: first preview {t_first_preview:.2f} s, first full {t_first:.2f} s",
              file=sys.stderr, flush=True)
        rows = []
        rid = 0
        for k in range(drags):
            change = light_move(state, k, drags)
            rid += 1
            t = time.perf_counter()
            ws.send(json.dumps({"type": "set", "id": rid, "changes": [change], "mode": "preview"}))
            prev = until(lambda m: m["type"] == "frame" and m["id"] == rid)
            t_prev = time.perf_counter() - t
            until(lambda m: m["type"] == "idle")
            rid += 1
            t = time.perf_counter()
            ws.send(json.dumps({"type": "refine", "id": rid}))
            full = until(lambda m: m["type"] == "frame" and m["id"] == rid and m["final"])
            t_full = time.perf_counter() - t
            until(lambda m: m["type"] == "idle")
            print(f"{spec}: drag {k + 1}/{drags}: preview {t_prev:.2f} s, full {t_full:.2f} s",
                  file=sys.stderr, flush=True)
            rows.append({"change": change, "to_preview_s": t_prev, "to_full_s": t_full,
                         "preview_stages_run": prev["stats"]["stages_run"],
                         "preview_reused": prev["stats"]["reused"],
                         "full_stages_run": full["stats"]["stages_run"],
                         "full_reused": full["stats"]["reused"],
                         "preview_size": [prev["width"], prev["height"]],
                         "full_size": [full["width"], full["height"]],
                         "preview_stages": prev["stats"]["stages"],
                         "full_stages": full["stats"]["stages"]})
        return {
            "scene": spec, "overrides": overrides, "method": first["stats"]["method"],
            "full_size": [first["width"], first["height"]], "spp": first["stats"]["spp"],
            "preview_size": [first_preview["width"], first_preview["height"]],
            "cold_first_preview_s": t_first_preview, "cold_first_full_s": t_first,
            "drag_to_preview_median_s": statistics.median(r["to_preview_s"] for r in rows),
            "release_to_full_median_s": statistics.median(r["to_full_s"] for r in rows),
            "drags": rows,
        }


def screenshot(spec: str, overrides: list[str], path: Path) -> None:
    from playwright.sync_api import sync_playwright

    from clscatter.serve import BackgroundServer

    with BackgroundServer(spec, overrides) as srv, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True)
        page = browser.new_page(viewport={"width": 1200, "height": 900})
        page.goto(srv.url)
        page.wait_for_function("Number(document.getElementById('frame').dataset.finals||0) > 0"
                               " && document.body.dataset.busy === '0'", timeout=600_000)
        path.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(path))
        browser.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["builtin:shafts", "builtin:caustic_sphere"])
    ap.add_argument("--drags", type=int, default=5)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--out", default=str(REPO / "bench_out" / "serve.json"))
    ap.add_argument("--screenshot", default=None, metavar="FILE.png")
    args = ap.parse_args()
    results = [bench_scene(s, args.drags, args.overrides) for s in args.scenes]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print("| scene | method | full / preview size | drag -> preview frame | release -> full frame "
          "| cold first full frame |")
    print("|---|---|---|---|---|---|")
    for r in results:
        fw, fh = r["full_size"]
        pw_, ph = r["preview_size"]
        print(f"| `{r['scene']}` | {r['method']} | {fw}x{fh} {r['spp']} spp / {pw_}x{ph} 1 spp | "
              f"{r['drag_to_preview_median_s']:.2f} s | {r['release_to_full_median_s']:.2f} s | "
              f"{r['cold_first_full_s']:.1f} s |")
    print(f"(medians of {args.drags} drags; JSON: {out})")
    if args.screenshot:
        screenshot(args.scenes[0], args.overrides, Path(args.screenshot))
        print(f"screenshot: {args.screenshot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
