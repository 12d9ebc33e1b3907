"""Run statistics (``--stats FILE.json``) and progress bars."""
from __future__ import annotations

import json
import math
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


class Timer:
    """Wall-clock seconds of ``with`` blocks (``.seconds``: the total of the blocks that
    ended): the one way a stage is timed (:meth:`Stats.stage` uses it too)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._t = 0.0

    def __enter__(self) -> "Timer":
        self._t = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds += time.perf_counter() - self._t


class Stats:
    """Seconds per stage plus named counters, serialised as the ``--stats`` JSON object.

    Required keys (docs/scene_format.md): method, device, seconds_total, stages, peak_bytes,
    width, height. Methods add their own counters with :meth:`set`.
    """

    def __init__(self) -> None:
        self._t0 = time.perf_counter()
        self.stages: dict[str, float] = {}
        self.values: dict[str, Any] = {}
        self._nested: list[float] = []     # seconds of stages inside each open stage

    @contextmanager
    def stage(self, name: str) -> Iterator[Timer]:
        """Time a block as stage ``name`` (repeated stages of one name add up). A stage
        opened inside another counts for itself only: the outer one records its block's
        seconds less the inner ones (epipolar's fallback runs raymarch's stage), so the
        stages sum to at most ``seconds_total``. The :class:`Timer` it yields holds the
        whole block's seconds afterwards."""
        timer = Timer()
        self._nested.append(0.0)
        try:
            with timer:
                yield timer
        finally:
            inner = self._nested.pop()
            self.stages[name] = self.stages.get(name, 0.0) + timer.seconds - inner
            if self._nested:
                self._nested[-1] += timer.seconds

    def set(self, **values: Any) -> None:
        self.values.update(values)

    def add(self, key: str, amount: float) -> None:
        self.values[key] = self.values.get(key, 0) + amount

    def note(self, line: str) -> None:
        """Keep a note told to the user under ``notes``."""
        self.values["notes"] = [*self.values.get("notes", []), line]

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.values)
        d.setdefault("method", "")
        d.setdefault("device", "")
        d.setdefault("peak_bytes", 0)
        d["seconds_total"] = time.perf_counter() - self._t0
        d["stages"] = dict(self.stages)
        return json_safe(d)

    def write(self, path: str | Path) -> None:
        write_json(path, self.to_dict())


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically (temp file + rename); inf/nan as strings."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=2, sort_keys=True) + "\n")
    tmp.replace(p)


def json_safe(value: Any, nonfinite: str = "string") -> Any:
    """``value`` ready for ``json.dumps(..., allow_nan=False)``: dict keys as strings, tuples
    as lists, NumPy arrays and scalars as plain Python values, and non-finite floats as
    the strings "inf", "-inf", "nan" (``nonfinite="string"``: statistics files, image
    metrics) or as None (``nonfinite="null"``: the relighting page's messages)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v, nonfinite) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, nonfinite) for v in value]
    if hasattr(value, "tolist") and callable(value.tolist):     # NumPy arrays and scalars
        value = value.tolist()
        if isinstance(value, list):
            return json_safe(value, nonfinite)
    if isinstance(value, float) and not math.isfinite(value):
        return None if nonfinite == "null" else str(value)
    return value


def progress(total: int, desc: str, enabled: bool = True):
    """A tqdm progress bar that appears only after a second of work and only on a terminal.

    tqdm is imported here, not at module level, so that scene and parameter checks (which
    import this module) work and report errors even where tqdm is missing."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, disable=None if enabled else True, delay=1.0,
                leave=False, unit="it", dynamic_ncols=True)
