"""Where a benchmark puts its result: ``bench_out/<name>.json`` on every run, and a copy
in ``docs/bench/`` (the committed runs the README quotes) unless the caller says not to
(the tools' ``--no-copy``)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench_out"
DOCS = REPO / "docs" / "bench"


def publish(result: dict, name: str, copy: bool = True) -> Path:
    """Write ``result`` as ``bench_out/<name>.json`` (and copy it to ``docs/bench/``
    when ``copy``); returns the path written."""
    OUT.mkdir(exist_ok=True)
    path = OUT / f"{name}.json"
    path.write_text(json.dumps(result, indent=2))
    if copy:
        shutil.copy(path, DOCS / path.name)
    print(f"wrote {path}")
    return path
