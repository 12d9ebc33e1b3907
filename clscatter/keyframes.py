"""Keyframed animations: scene keys given at some frames, every frame in between made from
them, as ``--set`` overrides (one list per frame, like :func:`clscatter.animation.orbit`).

A keyframe file is TOML with one ``[[key]]`` table per keyframe: its ``frame`` (an integer
>= 0) and any scene keys as dotted paths in quotes, with the value they take at that frame::

    [[key]]
    frame = 0
    "objects[1].transform.translate" = [0.0, 1.0, 0.0]
    "volumes[0].density" = "smoke_000.npy"

    [[key]]
    frame = 23
    "objects[1].transform.translate" = [1.5, 1.0, 0.0]
    "volumes[0].density" = "smoke_023.npy"

The animation has ``last frame + 1`` frames. At each frame every key named in any keyframe
takes a value: between two keyframes that both give it a number (or a list of numbers of
the same length) it is interpolated linearly; any other value (a file name, a string, a
boolean) holds from its keyframe until the next one gives another (a sequence of grid
files: animated smoke); before a key's first keyframe it takes that keyframe's value, after
its last one the last value. Paths in values are relative to the scene file, as in the
scene. Every frame is an absolute set of overrides of the original scene, so any frame
renders on its own and reproduces exactly; the session re-runs what each frame changes.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from .errors import ClscatterError

#: most frames a keyframe file may describe (the frames' overrides are built up front)
MAX_FRAMES = 100_000


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _numbers(v: Any) -> bool:
    return _number(v) or (isinstance(v, list) and bool(v) and all(_number(x) for x in v))


def _lerp(a: Any, b: Any, t: float) -> Any:
    if isinstance(a, list):
        return [float(x) + (float(y) - float(x)) * t for x, y in zip(a, b)]
    return float(a) + (float(b) - float(a)) * t


def parse(data: dict, source: str = "keyframes") -> list[tuple[int, dict[str, Any]]]:
    """The keyframes of ``data`` (a keyframe file's TOML), sorted by frame, checked: one
    ``[[key]]`` array, each with a distinct integer ``frame`` in [0, MAX_FRAMES) and at
    least one scene key. Errors are one line naming the file and the keyframe."""
    keys = data.get("key")
    extra = sorted(set(data) - {"key"})
    if extra:
        raise ClscatterError(f"{source}: unknown table or key '{extra[0]}' (keyframes are "
                             "[[key]] tables)")
    if not isinstance(keys, list) or not keys or not all(isinstance(k, dict) for k in keys):
        raise ClscatterError(f"{source}: needs at least one [[key]] table")
    out: dict[int, dict[str, Any]] = {}
    for i, k in enumerate(keys):
        frame = k.get("frame")
        if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame < MAX_FRAMES:
            raise ClscatterError(f"{source}: key[{i}].frame must be an integer in "
                                 f"[0, {MAX_FRAMES}) (got {frame!r})")
        if frame in out:
            raise ClscatterError(f"{source}: key[{i}]: frame {frame} is given twice")
        values = {name: v for name, v in k.items() if name != "frame"}
        if not values:
            raise ClscatterError(f"{source}: key[{i}] (frame {frame}) sets no scene key")
        out[frame] = values
    return sorted(out.items())


def frames(keyframes: list[tuple[int, dict[str, Any]]]) -> list[list[str]]:
    """Every frame's overrides (``key=value`` strings) from sorted ``keyframes``."""
    from .scene.builtin.toml_writer import (
        toml_value,  # the command line starts without it
    )
    count = keyframes[-1][0] + 1
    names = sorted({name for _, values in keyframes for name in values})
    tracks = {name: [(f, v[name]) for f, v in keyframes if name in v] for name in names}
    return [[f"{name}={toml_value(_at(tracks[name], f))}" for name in names]
            for f in range(count)]


def _at(track: list[tuple[int, Any]], frame: int) -> Any:
    """The value of one key's track at ``frame`` (see the module docstring)."""
    if frame <= track[0][0]:
        return track[0][1]
    for (f0, v0), (f1, v1) in zip(track, track[1:]):
        if f0 <= frame < f1:
            same = (_numbers(v0) and _numbers(v1)
                    and (not isinstance(v0, list) or (isinstance(v1, list) and len(v0) == len(v1)))
                    and isinstance(v0, list) == isinstance(v1, list))
            return _lerp(v0, v1, (frame - f0) / (f1 - f0)) if same else v0
    return track[-1][1]


def load(path: str | Path) -> list[list[str]]:
    """The frames of keyframe file ``path`` (:func:`parse`, then :func:`frames`)."""
    from .scene.loader import read_toml  # the command line starts without the loader
    if not Path(path).is_file():
        raise ClscatterError(f"{path}: keyframe file not found")
    return frames(parse(read_toml(path), str(path)))
