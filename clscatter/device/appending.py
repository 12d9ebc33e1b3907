"""Kernels that append records to device buffers through atomic counters, with buffers
that grow and launches that run again until every record fits."""
from __future__ import annotations

import numpy as np

from .engine import Engine


class AppendBuffer:
    """A device buffer that a kernel appends records to through an atomic counter.

    The kernel's record parameter is followed by ``capacity`` and ``counter``; it appends
    with ``idx = atomic_inc(counter)`` and writes only when ``idx < capacity``. After a
    launch the counter tells how many records it wanted to write; when that is more than
    fit, the buffer grows and the same launch runs again (kernels are deterministic), so
    callers never lose records and never need to guess sizes exactly. :meth:`call` is for
    a kernel whose last three parameters are these; a kernel that appends to several
    buffers at once runs through :func:`launch_appending`. The buffers come from the
    engine's pool; :meth:`release` returns them.
    """

    def __init__(self, engine: Engine, dtype: np.dtype, capacity: int):
        self.eng = engine
        self.dtype = np.dtype(dtype)
        self.capacity = max(1, int(capacity))
        self.buf = engine.empty(self.capacity * self.dtype.itemsize)
        self.counter = engine.empty(4)

    def call(self, program: str, kernel: str, global_size: int,
             defines: dict[str, object] | None = None, **args) -> np.ndarray:
        """Keyword launch (see :meth:`Engine.call`) of a kernel whose last three parameters
        are the records, capacity and counter; return the records appended (a host array
        of :attr:`dtype`, in the order the kernel appended them)."""
        got = self.call_on_device(program, kernel, global_size, defines, **args)
        return self.eng.read(self.buf, got, self.dtype) if got else np.zeros(0, self.dtype)

    def call_on_device(self, program: str, kernel: str, global_size: int,
                       defines: dict[str, object] | None = None, **args) -> int:
        """As :meth:`call`, but the records stay in :attr:`buf`: returns their count."""
        rec = self.eng.signature(program, kernel)[-3].name
        return launch_appending(self.eng, program, kernel, global_size, {rec: self},
                                defines, **args)[rec]

    def grow(self, records: int) -> None:
        """Replace :attr:`buf` by one that holds ``records`` with room to spare (the old
        contents are dropped: the launch that overflowed runs again)."""
        self.eng.free(self.buf)
        self.capacity = int(records * 1.25) + 16
        self.buf = self.eng.empty(self.capacity * self.dtype.itemsize)

    def release(self) -> None:
        """Free the record buffer and the counter (see :meth:`Engine.free`)."""
        self.eng.free(self.buf, self.counter)


def launch_appending(eng: Engine, program: str, kernel: str, global_size: int,
                     appends: dict[str, AppendBuffer], defines: dict[str, object] | None = None,
                     **args) -> dict[str, int]:
    """Keyword launch (see :meth:`Engine.call`) of a kernel that appends records to one or
    more :class:`AppendBuffer`: ``appends`` maps each record parameter's name to its
    buffer, and the two parameters declared right after it are its capacity and counter
    (filled in here). The launch runs again, with the overflowed buffers grown, until every
    record fits; returns the record count per name."""
    names = [p.name for p in eng.signature(program, kernel)]
    slots = {}
    for rec, app in appends.items():
        i = names.index(rec)
        slots[rec] = i
        args = {**args, rec: app.buf, names[i + 1]: 0, names[i + 2]: app.counter}
    bound = eng.bind(program, kernel, args)
    kern = eng.kernel(program, kernel, defines)
    while True:
        for rec, app in appends.items():
            eng.cl.enqueue_fill_buffer(eng.queue, app.counter, np.zeros(1, np.int32), 0, 4)
            bound[slots[rec]] = app.buf
            bound[slots[rec] + 1] = np.int32(app.capacity)
        eng.launch(kern, global_size, *bound)
        got = {rec: int(eng.read(app.counter, 1, np.int32)[0]) for rec, app in appends.items()}
        over = [rec for rec, app in appends.items() if got[rec] > app.capacity]
        if not over:
            return got
        for rec in over:
            appends[rec].grow(got[rec])
