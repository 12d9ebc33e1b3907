"""Seconds per unit of estimated work, learnt from this machine's own renders.

Every render's plan carries cost estimates (``Method.estimate``: work in a method's own
unit, e.g. pair tests or ray casts). After a render, each stage that ran in full (not cut
short by a time budget) records its measured seconds against its estimated work, per
device; ``clscatter check`` then turns each estimate into a time on that device. The
first render of a method on a device calibrates it, as the probe result and the program
binaries are kept after their first use.

The rate kept is the geometric mean of the last :data:`KEEP` measurements (estimates are
orders of magnitude; a rate moves with the scene, so the prediction is a guide, within a
factor of a few, not a promise). Rates live in ``costs.json`` beside the other cached
results (:func:`clscatter.device.cache.cache_dir`); a file that cannot be read or written
is ignored.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..device.cache import cache_dir

#: measurements kept per device and stage
KEEP = 8
#: stages whose work estimate is below this are not recorded (their time is noise)
MIN_WORK = 1e5


def _path() -> Path:
    return cache_dir() / "costs.json"


def _load() -> dict:
    try:
        data = json.loads(_path().read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def record(device: str, stage: str, work: float, seconds: float) -> None:
    """Keep ``seconds / work`` for ``stage`` on ``device`` (nothing for negligible work)."""
    if not (work >= MIN_WORK and seconds > 0 and math.isfinite(seconds)):
        return
    data = _load()
    rates = data.setdefault(device, {}).setdefault(stage, [])
    rates.append(seconds / work)
    del rates[:-KEEP]
    try:
        _path().parent.mkdir(parents=True, exist_ok=True)
        tmp = _path().with_suffix(".tmp")
        tmp.write_text(json.dumps(data))
        tmp.replace(_path())
    except OSError:
        pass


def predict(device: str, stage: str, work: float) -> float | None:
    """Seconds ``work`` of ``stage`` should take on ``device``; None before any record."""
    rates = _load().get(device, {}).get(stage)
    if not rates:
        return None
    return work * math.exp(sum(math.log(r) for r in rates) / len(rates))
