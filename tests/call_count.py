"""Counting the Python and C calls a function makes (``sys.setprofile``): how the tests show
that a build is vectorised (its calls grow with the tree's depth, not with its input)
without timing it."""
from __future__ import annotations

import sys
from typing import Any, Callable


def count_calls(fn: Callable[..., Any], *args: Any, **kw: Any) -> tuple[int, Any]:
    """(number of Python and C function calls ``fn(*args, **kw)`` made, its result)."""
    count = [0]

    def profile(frame, event, arg):
        if event in ("call", "c_call"):
            count[0] += 1

    sys.setprofile(profile)
    try:
        result = fn(*args, **kw)
    finally:
        sys.setprofile(None)
    return count[0], result
