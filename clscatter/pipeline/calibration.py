"""Seconds per unit of estimated work, learnt from this machine's own renders.

Every render's plan carries cost estimates (``Method.estimate``: work in a method's own
unit, e.g. pair tests or ray casts). After a render, each stage that ran in full (not cut
short by a time budget) records its estimated work and measured seconds, per device;
``clscatter check`` then turns each estimate into a time on that device. The first render
of a method on a device calibrates it, as the probe result and the program binaries are
kept after their first use.

A prediction takes the :data:`NEAR` kept measurements whose work is nearest the asked
work (by ratio; the newer first among equals) and multiplies the work by the median of
their rates (seconds per unit; with an even count, the geometric mean of the middle two).
A rate moves with the size of a render (fixed costs weigh more in a small one) and with
the scene (the estimates count a scene's work without tracing it: how many segments a
lighting ray breaks into at glass, how many of them pass near the view rays), and a single
odd render (another program on the machine, a first compile) should not move the
prediction: the nearest in size, and their median, keep it to the renders like the one
asked about. Each measurement also names its scene (``Scene.source``: the file or
``builtin:NAME``); where measurements of the asked scene are kept, the prediction is made
from those alone. Estimates are orders of magnitude, so the prediction is
a guide, within a factor of a few, not a promise. The last :data:`KEEP` measurements of
each of the :data:`KEEP_SCENES` scenes measured last are kept (so renders of one scene do
not push out what was learnt on others), in ``costs.json`` beside the other cached results
(:func:`clscatter.device.cache.cache_dir`), or in the file ``$CLSCATTER_COSTS`` names (the
test suite points it at a file of its own, so that its small renders do not replace a
user's measurements); a file that cannot be read or written is ignored, and so are entries
in another form.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

from ..device.cache import cache_dir

#: measurements kept per device, stage and scene
KEEP = 16
#: scenes whose measurements are kept per device and stage (those measured last)
KEEP_SCENES = 16
#: measurements a prediction is made from (those nearest the asked work)
NEAR = 3
#: stages whose work estimate is below this are not recorded (their time is noise)
MIN_WORK = 1e5


#: the variable that names the calibration file (default: costs.json in the cache folder)
ENV_COSTS = "CLSCATTER_COSTS"


def _path() -> Path:
    return Path(os.environ.get(ENV_COSTS) or cache_dir() / "costs.json")


def _load() -> dict:
    try:
        data = json.loads(_path().read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def scene_key(source: str) -> str:
    """What names a scene among the measurements: ``builtin:NAME`` as it is, a file by its
    absolute path (the same file from any folder); "" for none."""
    source = str(source)
    if not source or source.startswith(("builtin:", "<")):
        return source
    try:
        return str(Path(source).resolve())
    except (OSError, RuntimeError):
        return source


def _measurements(entries) -> list[tuple[float, float, str]]:
    """The ``(work, seconds, scene)`` of a stage's stored entries, oldest first (scene ""
    for an entry kept without one)."""
    out = []
    for e in entries if isinstance(entries, list) else []:
        if not (isinstance(e, list) and len(e) in (2, 3)):
            continue
        scene = e[2] if len(e) == 3 else ""
        if (all(isinstance(v, (int, float)) for v in e[:2]) and isinstance(scene, str)
                and e[0] > 0 and e[1] > 0 and math.isfinite(e[0]) and math.isfinite(e[1])):
            out.append((float(e[0]), float(e[1]), scene))
    return out


def record(device: str, stage: str, work: float, seconds: float, scene: str = "") -> None:
    """Keep ``(work, seconds)`` for ``stage`` on ``device``, measured on ``scene`` (its
    source; nothing for negligible work)."""
    if not (work >= MIN_WORK and math.isfinite(work) and seconds > 0 and math.isfinite(seconds)):
        return
    data = _load()
    stages = data.setdefault(device, {})
    if not isinstance(stages, dict):
        stages = data[device] = {}
    kept = [list(m) for m in _measurements(stages.get(stage))]
    kept.append([float(work), float(seconds), scene_key(scene)])
    stages[stage] = _retained(kept)
    try:
        _path().parent.mkdir(parents=True, exist_ok=True)
        tmp = _path().with_suffix(".tmp")
        tmp.write_text(json.dumps(data))
        tmp.replace(_path())
    except OSError:
        pass


def _retained(entries: list[list]) -> list[list]:
    """Of ``entries`` (oldest first, the scene last in each), the newest :data:`KEEP` of
    each of the :data:`KEEP_SCENES` scenes whose newest entry is newest, oldest first."""
    per: dict[str, int] = {}
    out = []
    for e in reversed(entries):
        scene = e[2]
        if scene not in per:
            if len(per) == KEEP_SCENES:
                continue
            per[scene] = 0
        if per[scene] < KEEP:
            per[scene] += 1
            out.append(e)
    return out[::-1]


def predict(device: str, stage: str, work: float, scene: str = "") -> float | None:
    """Seconds ``work`` of ``stage`` should take on ``device`` for ``scene`` (its source;
    see the module docstring); None before any measurement."""
    stages = _load().get(device, {})
    kept = _measurements(stages.get(stage) if isinstance(stages, dict) else None)
    if not kept or not work > 0:
        return None
    key = scene_key(scene)
    same = [m for m in kept if key and m[2] == key]
    kept = same or kept
    newest_first = list(reversed(kept))
    near = sorted(range(len(newest_first)),
                  key=lambda i: (abs(math.log(newest_first[i][0] / work)), i))[:NEAR]
    rates = sorted(newest_first[i][1] / newest_first[i][0] for i in near)
    mid = len(rates) // 2
    rate = rates[mid] if len(rates) % 2 else math.sqrt(rates[mid - 1] * rates[mid])
    return work * rate
