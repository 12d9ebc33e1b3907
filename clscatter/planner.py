"""``auto``: decide which passes a scene needs and skip the rest.

Today's decisions (more arrive with each method):
* no medium (or a void one), or no lights: the medium pass is skipped;
* otherwise direct single scattering by ``raymarch`` (the only medium method so far).
Every decision is recorded in ``--stats`` under ``plan``.
"""
from __future__ import annotations

from .paths import PreparedScene


def plan(ps: PreparedScene, requested: str) -> tuple[str | None, list[str]]:
    """The medium method to run (None: none needed) and notes on what was skipped."""
    notes: list[str] = []
    if not ps.has_medium:
        notes.append("no participating medium: medium pass skipped")
        return None, notes
    if ps.num_lights == 0:
        notes.append("no lights: medium pass skipped")
        return None, notes
    if requested != "auto":
        return requested, notes
    notes.append("direct single scattering by raymarch")
    return "raymarch", notes
