"""Row-wise host work in chunks on threads.

NumPy releases the GIL inside its loops over large arrays, so a step that treats every
row alone (clipping segments, forming Plücker points, gathering rows into a new order) runs
on all of the host's cores when its rows are cut into chunks, each chunk on a thread; a
chunk that fits in the caches also spares the memory traffic of whole-array temporaries.
Results are the same as one call over all rows: the chunks are rows of the same arrays,
in order.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

R = TypeVar("R")

#: rows a thread treats at once
ROW_CHUNK = 1 << 14


def host_threads() -> int:
    """The cores this process may run on (its CPU affinity where the platform says, else
    the machine's count): how many threads the host's parallel work uses."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def map_row_chunks(fn: Callable[[int, int], R], n: int, chunk: int | None = None,
                   align: int = 1) -> list[R]:
    """``[fn(start, stop), ...]`` over consecutive row ranges that cover ``[0, n)``, each at
    most ``chunk`` rows (default :data:`ROW_CHUNK`, rounded up to a multiple of ``align``,
    so that every ``start`` is one), on up to one thread per core; in order of ``start``.
    One call ``fn(0, n)`` when ``n <= chunk``."""
    align = max(1, int(align))
    chunk = -(-max(1, int(chunk or ROW_CHUNK)) // align) * align
    starts = list(range(0, n, chunk)) or [0]
    if len(starts) == 1:
        return [fn(0, n)]
    threads = min(len(starts), host_threads())
    if threads == 1:
        return [fn(s, min(s + chunk, n)) for s in starts]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(lambda s: fn(s, min(s + chunk, n)), starts))
