"""The ``clscatter`` command line (contract: docs/scene_format.md, "Command-line contract").

    clscatter                                   render the built-in demo scene
    clscatter render [SCENE] -o OUT [-o OUT2] [--method M] [--set key=value ...]
                     [--stats FILE.json] [--device SPEC] [--exposure EV]
    clscatter relight [SCENE] -o DIR [--frames N] [--orbit light|camera | --keyframes K.toml]
                      [--format png]
    clscatter check [SCENE] [--method M] [--set key=value ...] [--max-memory SIZE]
    clscatter serve [SCENE] [--port P] [--host H] [--method M] [--set key=value ...]
    clscatter diff A B [--heatmap FILE.png] [--json]
    clscatter devices
    clscatter scenes [--dump NAME]
    clscatter volume convert IN -o OUT [--bounds X0 Y0 Z0 X1 Y1 Z1] [--name density]
    clscatter convert IN -o OUT                 TOML <-> Mitsuba 3 XML (by the suffixes)

SCENE is a TOML file, a Mitsuba 3 XML file (docs/mitsuba.md) or ``builtin:NAME``
(``clscatter scenes`` lists them). Errors the
user can fix print one line naming the key or file and exit with status 2.
"""
from __future__ import annotations

import argparse
import math
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Sequence

from .errors import ClscatterError

DEMO_OUTPUT = "clscatter-demo.png"
IMAGE_SUFFIXES = (".exr", ".npy", ".pfm", ".png")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage too)
        self.exit(2, f"{self.prog}: error: {message}\n")


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="clscatter", description="Single scattering in participating media, on OpenCL.")
    sub = p.add_subparsers(dest="command", parser_class=_Parser)

    r = sub.add_parser("render", help="render a scene to image files")
    r.add_argument("scene", nargs="?", default=None,
                   help="scene TOML file or builtin:NAME (default: the built-in demo)")
    r.add_argument("-o", "--output", action="append", default=None, metavar="OUT",
                   help="output image (.exr .npy .pfm .png); repeatable "
                        f"(default: {DEMO_OUTPUT})")
    r.add_argument("--method", default=None, help="override render.method")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key (dotted path, TOML value); repeatable")
    r.add_argument("--stats", default=None, metavar="FILE.json", help="write run statistics")
    r.add_argument("--device", default=None, help="OpenCL device: P:D or a name substring")
    r.add_argument("--exposure", type=_finite_float, default=0.0,
                   help="PNG exposure in stops (default 0)")
    r.add_argument("--max-memory", default=None, metavar="SIZE",
                   help="refuse renders estimated to need more (e.g. 4G; default: the "
                        "device's and the machine's memory)")
    r.add_argument("--no-progress", action="store_true", help="never show progress bars")
    _quiet_option(r)
    _budget_options(r)
    _cluster_options(r)

    a = sub.add_parser("relight", help="render an animation (light or camera orbit) into a folder, "
                                       "re-running only what each frame changes")
    a.add_argument("scene", nargs="?", default=None, help="scene TOML file or builtin:NAME")
    a.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the frames")
    a.add_argument("--frames", type=int, default=24, help="number of frames (default 24)")
    a.add_argument("--orbit", default="light", choices=("light", "camera"),
                   help="what turns once around the scene (default: light)")
    a.add_argument("--keyframes", default=None, metavar="FILE.toml",
                   help="instead of an orbit: scene keys given at keyframes, interpolated "
                        "between them (objects moving, animated grids; docs/scene_format.md)")
    a.add_argument("--format", default="png", choices=("png", "exr", "npy", "pfm"),
                   help="frame file format (default png)")
    a.add_argument("--method", default=None, help="override render.method")
    a.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    a.add_argument("--device", default=None, help="OpenCL device: P:D or a name substring")
    a.add_argument("--exposure", type=_finite_float, default=0.0, help="PNG exposure in stops")
    a.add_argument("--no-progress", action="store_true", help="never show progress bars")
    _quiet_option(a)
    _budget_options(a)
    _cluster_options(a)

    c = sub.add_parser("check", help="validate a scene and print the plan and cost estimate")
    c.add_argument("scene", nargs="?", default=None, help="scene TOML file or builtin:NAME")
    c.add_argument("--method", default=None, help="override render.method")
    c.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    c.add_argument("--max-memory", default=None, metavar="SIZE")
    c.add_argument("--device", default=None,
                   help="OpenCL device whose memory bounds the budget: P:D or a name substring")
    _budget_options(c)

    d = sub.add_parser("diff", help="compare two images")
    d.add_argument("a")
    d.add_argument("b", help="the reference")
    d.add_argument("--heatmap", default=None, metavar="FILE.png")
    d.add_argument("--json", action="store_true", help="print one JSON object")

    v = sub.add_parser("devices", help="list OpenCL platforms and devices")
    v.add_argument("--device", default=None, help="show which device this spec chooses")

    from .serve import add_serve_command  # imports no web framework until it runs
    add_serve_command(sub)

    s = sub.add_parser("scenes", help="list built-in scenes")
    s.add_argument("--dump", default=None, metavar="NAME", help="print a built-in scene as TOML")

    from .volume_command import add_volume_command  # density grids: .npy <-> .vdb
    add_volume_command(sub)

    cv = sub.add_parser("convert", help="convert a scene between clscatter TOML and "
                                        "Mitsuba 3 XML (by the files' suffixes)")
    cv.add_argument("input", help="scene .toml or .xml file, or builtin:NAME")
    cv.add_argument("-o", "--output", required=True, metavar="OUT",
                    help="the scene to write: .toml, or .xml (its meshes and grids go into "
                         "the folder <OUT's stem>_files beside it)")
    return p


def _cluster_options(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                   help="render on a local Dask cluster of N worker processes")
    g.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="render on a running Dask scheduler, e.g. tcp://host:8786")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1 (got {value})")
    return value


def _open_cluster(args: argparse.Namespace):
    """The Dask cluster the options ask for, or None (Dask is imported only then)."""
    if not (args.workers or args.cluster):
        return None
    try:
        from .cluster import Cluster
    except ImportError as e:
        raise ClscatterError(f"--workers/--cluster need dask.distributed "
                             f"(pip install 'clscatter[cluster]'): {e}") from None
    return Cluster(workers=args.workers, address=args.cluster, device=args.device)


def _budget_options(parser: argparse.ArgumentParser) -> None:
    """``--time-budget`` and ``--target-error``: the scene's ``render.time_budget`` and
    ``render.target_error`` (added to the ``--set`` overrides, so they are checked alike)."""
    parser.add_argument("--time-budget", type=_finite_float, default=None, metavar="SECONDS",
                        help="seconds for the whole render (render.time_budget; auto's "
                             "default is 10): progressive caustic passes are sized to fit")
    parser.add_argument("--target-error", type=_finite_float, default=None, metavar="RELMSE",
                        help="run progressive passes until the render's own relMSE estimate "
                             "is at most this (render.target_error)")


def _budget_overrides(args: argparse.Namespace) -> None:
    """Turn ``--time-budget``/``--target-error`` into overrides after the ``--set`` ones."""
    for flag, key in (("time_budget", "render.time_budget"), ("target_error", "render.target_error")):
        value = getattr(args, flag, None)
        if value is not None:
            args.overrides = [*args.overrides, f"{key}={value!r}"]


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number (got {text!r})")
    return value


def _note(line: str) -> None:
    print(f"clscatter: note: {line}", file=sys.stderr)


def _quiet_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print errors only: no progress bars, notes or closing line "
                        "(render --stats still records the notes)")


def _say(args: argparse.Namespace):
    """(note, line): where a command's notes (stderr) and closing line (stdout) go; both
    silent under --quiet. Every note is also kept in ``args.notes`` (``--stats`` writes
    them)."""
    args.notes = []
    quiet = getattr(args, "quiet", False)

    def note(line: str) -> None:
        args.notes.append(line)
        if not quiet:
            _note(line)
    return note, (lambda line: None) if quiet else print


def _cmd_render(args: argparse.Namespace) -> int:
    stats = args.stats_obj
    with stats.stage("startup"):     # imports of the render path, and the output checks
        from .io.image import write_image
        from .io.outputs import check_output, write_all
        from .io.stats import write_json
        from .pipeline.budget import parse_bytes
        from .pipeline.render import render
        from .scene import DEFAULT_BUILTIN, load_scene

        # every output is checked before any work: nothing is rendered for nothing
        outputs = [check_output(o, IMAGE_SUFFIXES, "-o") for o in (args.output or [DEMO_OUTPUT])]
        stats_path = check_output(args.stats, (".json",), "--stats") if args.stats else None
        dests = [p.resolve() for p in outputs] + ([stats_path.resolve()] if stats_path else [])
        if len(set(dests)) != len(dests):
            raise ClscatterError(f"{_first_duplicate(dests)}: the same file is given twice "
                                 "as output")
        max_memory = parse_bytes(args.max_memory) if args.max_memory is not None else None
    note, say = _say(args)
    spec = args.scene or f"builtin:{DEFAULT_BUILTIN}"
    with stats.stage("load_scene"):
        scene = load_scene(spec, args.overrides, on_note=note)
    with stats.stage("cluster_start"):
        cluster = _open_cluster(args)
    if cluster is not None:
        with cluster:
            result = cluster.render(spec, args.overrides, args.method, stats=stats,
                                    show_progress=not args.no_progress)
    else:
        result = render(scene, method=args.method, device=args.device, stats=stats,
                        show_progress=not args.no_progress, max_memory=max_memory,
                        on_note=note)
    writes = [(o, lambda tmp, o=o: write_image(tmp, result.image, exposure=args.exposure))
              for o in outputs]
    t_write = time.perf_counter()
    if stats_path:
        # written last, so the image writes before it are already timed in it
        def write_stats(tmp):
            stats.stages["write_outputs"] = time.perf_counter() - t_write
            write_json(tmp, {**_final(stats, result.stats), "notes": args.notes})
        writes.append((stats_path, write_stats))
    write_all(writes)
    stats.stages["write_outputs"] = time.perf_counter() - t_write
    st = result.stats
    say(f"{scene.source}: {st['width']}x{st['height']} by {st['method']} in "
        f"{st['seconds_total']:.2f} s -> {', '.join(map(str, outputs))}")
    return 0


def diff_command(
    a_path: str | Path,
    b_path: str | Path,
    heatmap_path: str | Path | None = None,
    as_json: bool = False,
) -> int:
    """``clscatter diff A B [--heatmap F] [--json]``: compare image A against reference B.

    Prints one ``name: value`` line per metric (rmse, relmse, psnr (with ``dB``),
    ssim, max_error), or, with ``as_json``, a single JSON object with those five keys
    (non-finite values as strings, see :func:`~clscatter.io.stats.json_safe`). Writes the error heatmap
    to ``heatmap_path`` if given. Returns 0; unreadable files, a linear image (EXR, NPY,
    PFM) against a tone-mapped one (PNG), images with NaN or Inf pixels, or images of
    different sizes raise ImageError naming the files.
    """
    import json
    import math
    import os

    import numpy as np

    from .errors import ImageError
    from .io.image import (
        METRIC_KEYS,
        check_comparable,
        compare,
        read_image,
        write_heatmap,
    )
    from .io.stats import json_safe

    a = read_image(a_path)
    b = read_image(b_path)
    check_comparable(a_path, b_path)       # linear vs tone-mapped: no metric means anything
    for path, img in ((a_path, a), (b_path, b)):
        bad = int((~np.isfinite(img)).any(axis=-1).sum())
        if bad:
            raise ImageError(f"{os.fspath(path)}: {bad} pixels are NaN or Inf (the metrics "
                             "need finite images)")
    if a.shape != b.shape:
        raise ImageError(
            f"{os.fspath(a_path)} is {a.shape[1]} x {a.shape[0]} but "
            f"{os.fspath(b_path)} is {b.shape[1]} x {b.shape[0]} (width x height); "
            f"shapes {a.shape} vs {b.shape}"
        )
    metrics = compare(a, b)
    if heatmap_path is not None:
        write_heatmap(heatmap_path, a, b)
    if as_json:
        print(json.dumps(json_safe(metrics)))
    else:
        for key in METRIC_KEYS:
            unit = " dB" if key == "psnr" and math.isfinite(metrics[key]) else ""
            value = metrics[key]
            print(f"{key}: {value if not math.isfinite(value) else format(value, '.6g')}{unit}")
    return 0


def _final(stats, rendered: dict) -> dict:
    """The render's statistics with the CLI's own stages (scene loading, output writing)
    and the total up to now."""
    final = dict(rendered)
    now = stats.to_dict()
    final["stages"] = now["stages"]
    final["seconds_total"] = now["seconds_total"]
    return final


from .keyframes import MAX_FRAMES  # noqa: E402  relight refuses more (frames built up front)


def _cmd_relight(args: argparse.Namespace) -> int:
    """Frames of a light or camera orbit, written to a folder with ``frames.json``: into
    a hidden staging folder beside it first, moved there only when every frame is done
    (an interrupted or failed animation leaves the folder as it was)."""
    from .animation import orbit, orbit_path
    from .io.image import write_image
    from .io.outputs import staged_folder
    from .io.stats import progress, write_json
    from .scene import DEFAULT_BUILTIN, load_scene

    note, say = _say(args)
    spec = args.scene or f"builtin:{DEFAULT_BUILTIN}"
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise ClscatterError(f"{args.output}: -o must be a folder for the frames")
    if not out.resolve().parent.is_dir():
        raise ClscatterError(f"{args.output}: parent folder {out.resolve().parent} does not exist")
    if args.frames > MAX_FRAMES:
        raise ClscatterError(f"--frames: at most {MAX_FRAMES:,} (got {args.frames:,})")
    scene = load_scene(spec, args.overrides, on_note=note)
    if args.keyframes is not None:
        from .keyframes import load as load_keyframes
        frames = load_keyframes(args.keyframes)
        for sets in (frames[0], frames[-1]):          # every key checked before any frame
            load_scene(spec, [*args.overrides, *sets])
        path = None
        movement = f"keyframes {Path(args.keyframes).name}"
    else:
        frames = orbit(scene, args.frames, args.orbit)
        path = orbit_path(scene, args.orbit)          # the axis and radii, for frames.json
        movement = f"{args.orbit} orbit" + (f", radius {path.radius:.3g}"
                                            if path.radius is not None else "")
    _check_frames_fit(out, len(frames), scene.camera.width * scene.camera.height, args.format)
    for m in (path.movers if path is not None else []):
        if m.widened:
            note(f"{m.key} is close to the orbit's axis: it orbits at "
                  + (f"radius {m.radius:.3g} (its height kept)" if m.radius is not None
                     else f"{m.tilt_deg:g} degrees from the axis")
                  + " so that the frames differ")
    from .pipeline.render import check
    check(scene, args.method)                        # bad parameters fail before any frame
    digits = max(4, len(str(len(frames) - 1)))
    names = [f"frame_{i:0{digits}d}.{args.format}" for i in range(len(frames))]
    with staged_folder(out) as stage:
        def save(i: int, image, _stats) -> None:
            write_image(stage / names[i], image, exposure=args.exposure)

        cluster = _open_cluster(args)
        if cluster is not None:
            with cluster:
                record = cluster.frames(spec, frames, args.overrides, args.method,
                                        show_progress=not args.no_progress, on_frame=save)
        else:
            from .pipeline.session import RenderSession
            record = {"frames": []}
            with RenderSession.from_source(spec, args.overrides, method=args.method,
                                           device=args.device) as session, \
                    progress(len(frames), "frames", not args.no_progress) as bar:
                for i, sets in enumerate(frames):
                    session.set(sets, replace=True)
                    res = session.render(show_progress=False)
                    save(i, res.image, res.stats)
                    record["frames"].append({
                        "frame": i, "seconds": res.stats["seconds_total"],
                        "stages": res.stats["stages"], "stages_run": res.stats["stages_run"],
                        "reused": res.stats["reused"],
                        **{k: res.stats[k] for k in ("voxel_stages_run", "voxel_stage_seconds")
                           if k in res.stats}})
                    bar.update(1)
        if path is not None:
            record.update(orbit=args.orbit, **path.record())
        else:
            record.update(keyframes=str(args.keyframes), overrides=frames)
        record.update(scene=spec, count=len(frames), files=names)
        write_json(stage / "frames.json", record)
    total = sum(f["seconds"] for f in record["frames"])
    say(f"{spec}: {len(frames)} frames ({movement}) in {total:.2f} s -> {out}/")
    return 0


# bytes per pixel a frame file takes at most (PNG: 8-bit RGB, uncompressed)
_FRAME_BYTES = {"png": 3, "exr": 12, "npy": 12, "pfm": 12}


def _check_frames_fit(out: Path, frames: int, pixels: int, fmt: str) -> None:
    """Refuse an animation whose frames could not fit on the output's file system (each
    frame counted at its uncompressed size, plus 4 KiB)."""
    need = frames * (pixels * _FRAME_BYTES[fmt] + 4096)
    free = shutil.disk_usage(out.resolve().parent).free
    if need > free:
        raise ClscatterError(f"--frames: {frames:,} frames of {fmt} may need up to "
                             f"{need / 2**30:.1f} GiB, more than the {free / 2**30:.1f} GiB "
                             f"free under {out.resolve().parent}")


def _first_duplicate(paths: list[Path]) -> Path:
    seen = set()
    for p in paths:
        if p in seen:
            return p
        seen.add(p)
    return paths[0]


def _cmd_check(args: argparse.Namespace) -> int:
    """Validate the scene and the method parameters, print the plan and the estimates."""
    from .pipeline.budget import (
        check_budget,
        fit_memory,
        human_bytes,
        memory_budget,
        parse_bytes,
        peak_bytes,
        time_budget,
    )
    from .pipeline.render import check
    from .scene import DEFAULT_BUILTIN, load_scene

    scene = load_scene(args.scene or f"builtin:{DEFAULT_BUILTIN}", args.overrides, on_note=_note)
    req = check(scene, args.method)
    device = _device_for_budget(args.device)        # before printing: a bad --device is one line
    max_memory = parse_bytes(args.max_memory) if args.max_memory is not None else None
    limit, source = memory_budget(device, max_memory)
    fitted = fit_memory(scene, req, limit, source)
    c = scene.camera
    print(f"{scene.source}: valid; {c.width}x{c.height}, {c.spp} spp, "
          f"{scene.triangle_count()} triangles")
    print("plan: " + (", ".join(f"{p.method} ({p.role})" for p in req.passes) or "no passes"))
    for n in req.notes + fitted:
        print(f"  {n}")
    for e in req.estimates:
        keys = e.key if e.work_by == e.key else f"{e.key}; work: {e.work_by}"
        print(f"estimate {e.stage}: {human_bytes(e.bytes)}, about {e.work:.2g} {e.unit} ({keys})"
              + _predicted_time(device, e, scene.source))
    print(f"peak: about {human_bytes(peak_bytes(req.estimates))} of {human_bytes(limit)} ({source})")
    seconds, origin = time_budget(scene, req.requested)
    line = (f"{seconds:g} s for the whole render ({origin}); progressive passes share what "
            "the others leave" if seconds > 0 else "no time budget (render.time_budget)")
    if scene.render.target_error > 0:
        line += f"; passes stop at an estimated relMSE of {scene.render.target_error:g}"
    print(f"time: {line}")
    check_budget(req.estimates, limit, source)
    return 0


def _predicted_time(device, e, source: str = "") -> str:
    """``; about N s on this device`` from earlier renders' measured rates
    (:mod:`clscatter.pipeline.calibration`; those of the scene ``source`` where there are
    any), or a word on why there is none."""
    from .pipeline.calibration import MIN_WORK, predict
    name = getattr(device, "name", None)
    if not isinstance(name, str) or e.work < MIN_WORK:
        return ""
    seconds = predict(name.strip(), e.stage, e.work, source)
    if seconds is None:
        return "; time not yet calibrated on this device (a render calibrates it)"
    return f"; about {seconds:.2g} s on this device (before any time budget)"


def _device_for_budget(spec: str | None):
    """The OpenCL device a render would choose (its memory bounds the budget, as in
    ``render``), or None with a note when none works (the machine's memory alone)."""
    from .device import DeviceError, choose_device
    try:
        return choose_device(spec).handle
    except DeviceError as e:
        if spec:
            raise
        _note(f"no working device ({e}); the budget is the machine's memory alone")
        return None


def _cmd_diff(args: argparse.Namespace) -> int:
    return diff_command(args.a, args.b, heatmap_path=args.heatmap, as_json=args.json)


def _cmd_serve(args: argparse.Namespace) -> int:
    from .serve import cmd_serve
    return cmd_serve(args)


def _cmd_devices(args: argparse.Namespace) -> int:
    from .device import choose_device, list_devices
    infos, problems = list_devices(probe=True)
    for msg in problems:
        print(msg)
    for i in infos:
        state = "ok" if i.ok else f"unusable: {i.reason}"
        print(f"{i.label} [{i.kind}] {state}")
    chosen = choose_device(args.device)
    print(f"chosen: {chosen.label}")
    return 0


def _cmd_scenes(args: argparse.Namespace) -> int:
    from .scene import BUILTIN, DEFAULT_BUILTIN, builtin_toml
    if args.dump:
        if args.dump not in BUILTIN:
            raise ClscatterError(f"scenes --dump: no built-in scene '{args.dump}' "
                                 f"(one of {', '.join(sorted(BUILTIN))})")
        sys.stdout.write(builtin_toml(args.dump))
        return 0
    labels = {name: f"builtin:{name}" + (" (default)" if name == DEFAULT_BUILTIN else "")
              for name in BUILTIN}
    width = max(map(len, labels.values()), default=0)
    for name in sorted(BUILTIN):
        print(f"{labels[name]:<{width}}  {scene_summary(BUILTIN[name].__doc__)}".rstrip())
    return 0


def scene_summary(doc: str | None) -> str:
    """The first paragraph of a built-in scene's description, on one line and whole (never
    cut mid-sentence), without the double backquotes that mark code in the docstring."""
    paragraph = []
    for line in (doc or "").strip().splitlines():
        if not line.strip():
            break
        paragraph.append(line.strip())
    return " ".join(" ".join(paragraph).replace("``", "").split())


def _cmd_volume(args: argparse.Namespace) -> int:
    from .volume_command import run_volume
    return run_volume(args)


def _cmd_convert(args: argparse.Namespace) -> int:
    from .scene.mitsuba_out import write_scene
    for line in write_scene(args.input, args.output):
        _note(line)
    print(f"{args.input} -> {args.output}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        argv = ["render"]
    from .io.stats import Stats
    stats = Stats()          # seconds_total counts from here: argument parsing onwards
    try:
        with stats.stage("startup"):
            parser = _build_parser()
            args = parser.parse_args(argv)
        args.stats_obj = stats
        if getattr(args, "quiet", False):
            args.no_progress = True
        _budget_overrides(args)
    except SystemExit as e:          # argparse: usage errors (one line, status 2) and --help
        return int(e.code or 0)
    if args.command is None:
        parser.print_help()
        return 2
    handlers = {"render": _cmd_render, "relight": _cmd_relight, "check": _cmd_check,
                "diff": _cmd_diff, "serve": _cmd_serve,
                "devices": _cmd_devices, "scenes": _cmd_scenes, "volume": _cmd_volume,
                "convert": _cmd_convert}
    previous = {sig: signal.signal(sig, _terminate) for sig in (signal.SIGTERM, signal.SIGINT)}
    _STOPPED.clear()
    try:
        return handlers[args.command](args)
    except ClscatterError as e:
        if _STOPPED:
            return _interrupted()
        text = str(e)
        if e.exit_status == 2:
            text = " ".join(text.split())  # user errors: exactly one line
        print(f"clscatter: error: {text}", file=sys.stderr)
        return e.exit_status
    except KeyboardInterrupt:
        return _interrupted()
    except Exception:
        if not _STOPPED:
            raise
        # the interrupt was raised inside library code that turned it into an error of
        # its own (NumPy does, in some compares): still an interruption
        return _interrupted()
    except BrokenPipeError:          # e.g. `clscatter scenes | head`
        sys.stderr.close()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


#: set once SIGINT or SIGTERM arrived during a command
_STOPPED: set[int] = set()


def _interrupted() -> int:
    print("clscatter: interrupted; nothing was written", file=sys.stderr)
    return 130


def _terminate(signum, frame) -> None:
    """SIGTERM stops like Ctrl-C (SIGINT): between kernel launches, with no output
    written. Remembered, so that an interrupt some library turned into another error
    still ends as an interruption. The devices' queues are drained first, so the
    unwinding frees no buffer a kernel in flight still uses."""
    _STOPPED.add(signum)
    engines = sys.modules.get("clscatter.device.engine")   # none made yet: nothing in flight
    if engines is not None:
        engines.finish_all()
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
