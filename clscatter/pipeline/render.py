"""One render: scene -> checked method parameters -> plan -> prepared device scene -> view
paths -> passes -> image. A one-off render is a :class:`~clscatter.pipeline.session.RenderSession`
used once (the stages live there)."""
from __future__ import annotations

from ..device import Engine
from ..scene.model import Scene
from .check import Prepared, check, scene_notes
from .session import RenderResult, RenderSession

__all__ = ["Prepared", "RenderResult", "check", "render", "scene_notes"]


def render(scene: Scene, method: str | None = None, engine: Engine | None = None,
           device: str | None = None, show_progress: bool = True,
           max_memory: float | None = None, on_note=None, stats=None) -> RenderResult:
    """Render ``scene`` with ``method`` (default: the scene's render.method).

    :func:`check` runs first; a render whose estimated peak memory exceeds ``max_memory``
    (default: the device's and the machine's memory) is refused before anything is
    allocated. ``on_note`` receives one-line notes for the user (long work, dropped
    triangles). This is a :class:`~clscatter.pipeline.session.RenderSession` used once.
    """
    with RenderSession(scene, method, engine=engine, device=device,
                       max_memory=max_memory, keep_hits=False) as session:
        return session.render(show_progress=show_progress, on_note=on_note, stats=stats)
