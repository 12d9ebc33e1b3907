"""A tiny TOML writer for the subset scene files use (tables, arrays of tables, inline
tables for bounds/transform/material, numbers, strings, booleans)."""
from __future__ import annotations

import json
import math
from typing import Any

# dicts under these keys are written inline ({ ... }) rather than as [table] headers
_INLINE_KEYS = frozenset({"bounds", "transform", "material"})


def toml_value(v: Any) -> str:
    """``v`` as a TOML value (what a scene file or a ``--set`` override holds)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)   # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) else json.dumps(k)


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _emit(table: dict, path: list[str], out: list[str]) -> None:
    """Write ``table``'s plain keys, then its sub-tables and arrays of tables in order."""
    def is_header(k: str, v: Any) -> bool:
        return (isinstance(v, dict) and k not in _INLINE_KEYS) or _is_table_array(v)

    for k, v in table.items():
        if not is_header(k, v):
            out.append(f"{_key(k)} = {toml_value(v)}")
    for k, v in table.items():
        if not is_header(k, v):
            continue
        name = ".".join(_key(p) for p in [*path, k])
        if isinstance(v, dict):
            # a table holding only sub-tables ([materials]) needs no header of its own
            if not v or any(not is_header(ik, iv) for ik, iv in v.items()):
                out.extend(["", f"[{name}]"])
            _emit(v, [*path, k], out)
            continue
        for item in v:
            out.extend(["", f"[[{name}]]"])
            # everything inside an array element is written inline: simple and unambiguous
            for ik, iv in item.items():
                out.append(f"{_key(ik)} = {toml_value(iv)}")


def to_toml(data: dict) -> str:
    """Serialise a scene dict (strings, numbers, booleans, arrays, tables) as TOML text."""
    out: list[str] = []
    _emit(data, [], out)
    return "\n".join(out).lstrip("\n") + "\n"
