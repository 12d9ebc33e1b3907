"""Device buffers of an engine: allocation, transfers, the live and peak byte counts renders
report, and a pool that keeps large released buffers for the next request of their size.

Pool parameters (read at each call, so a caller may change them here:
``clscatter.device.buffers.POOL_MIN_BYTES = ...``): buffers of at least :data:`POOL_MIN_BYTES`
are kept for reuse; a request takes the smallest idle one from its size up to
:data:`POOL_SLACK` times it; the idle bytes stay under :data:`POOL_SHARE` of the memory
budget."""
from __future__ import annotations

import threading
import time

import numpy as np

from .memory import memory_budget

POOL_MIN_BYTES = 1 << 16
POOL_SLACK = 1.25
POOL_SHARE = 0.25


class BufferPool:
    """Buffer allocation, transfers and accounting of an engine.

    A mixin of :class:`~clscatter.device.engine.Engine`: it uses the engine's ``cl``
    (pyopencl), ``ctx``, ``queue`` and ``wait_seconds``, and :meth:`_init_buffers` sets
    its own state. ``bytes_live`` counts the bytes of the device buffers made here and not
    yet freed; ``bytes_peak`` is the most that ever were (plus host arrays registered with
    :meth:`note_host`). Pooled buffers count in neither while idle."""

    def _init_buffers(self) -> None:
        self._sizes: dict[int, int] = {}        # id(buffer) -> bytes counted as live
        self.bytes_live = 0
        self.bytes_peak = 0
        # idle buffers for reuse, oldest first: [size, generation, buffer]
        self._pool: list[list] = []
        self._pool_bytes = 0
        self._pool_cap: float | None = None     # set by fit_pool, else at the first free
        self._generation = 0
        self._pool_lock = threading.Lock()      # a page's session may close from another thread

    def _track(self, buf, nbytes: int):
        """Count ``buf`` (``nbytes``) as live; return it."""
        self._sizes[id(buf)] = nbytes
        self.bytes_live += nbytes
        self.bytes_peak = max(self.bytes_peak, self.bytes_live)
        return buf

    def to_device(self, array: np.ndarray, writable: bool = False):
        """A new device buffer holding a copy of a host array (at least 1 byte; an empty
        array gives a buffer of one zero element), read-only unless ``writable``. Never
        pooled."""
        mf = self.cl.mem_flags
        arr = np.ascontiguousarray(array)
        if arr.nbytes == 0:
            arr = np.zeros(1, np.int32) if arr.dtype.itemsize < 4 else np.zeros(1, arr.dtype)
        flags = (mf.READ_WRITE if writable else mf.READ_ONLY) | mf.COPY_HOST_PTR
        t = time.perf_counter()
        buf = self.cl.Buffer(self.ctx, flags, hostbuf=arr)
        self.wait_seconds += time.perf_counter() - t
        return self._track(buf, arr.nbytes)

    def empty(self, nbytes: int):
        """An uninitialised read-write device buffer of at least ``nbytes`` (at least 4).

        Large ones come from the pool of buffers released by :meth:`free` when one fits
        (at most :data:`POOL_SLACK` times the size): a re-render allocates the same
        scratch as the render before it, and fresh memory costs the CPU device page faults
        on first touch. The queue is in order, so a reused buffer is never written before
        the commands that used it before have run. When the driver is out of memory, the
        pool is released and the allocation tried once more."""
        nbytes = max(int(nbytes), 4)
        if nbytes >= POOL_MIN_BYTES:
            with self._pool_lock:
                best = None
                for entry in self._pool:
                    if nbytes <= entry[0] <= POOL_SLACK * nbytes and (best is None
                                                                      or entry[0] < best[0]):
                        best = entry
                if best is not None:
                    self._pool.remove(best)
                    self._pool_bytes -= best[0]
            if best is not None:
                return self._track(best[2], best[0])
        try:
            buf = self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, nbytes)
        except self.cl.MemoryError:
            if not self._pool:
                raise
            self.drain_pool()
            buf = self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, nbytes)
        return self._track(buf, nbytes)

    def zeros(self, nbytes: int):
        """A device buffer of at least ``nbytes`` (as :meth:`empty`) filled with zero
        bytes (the fill is enqueued)."""
        buf = self.empty(nbytes)
        self.cl.enqueue_fill_buffer(self.queue, buf, np.zeros(1, np.uint32), 0, max(int(nbytes), 4))
        return buf

    def read(self, buf, shape, dtype, offset: int = 0) -> np.ndarray:
        """Copy a device buffer (from byte ``offset``) back into a new host array of
        ``shape`` and ``dtype``, waiting for it (counted in ``wait_seconds``)."""
        out = np.empty(shape, dtype)
        if out.nbytes:
            t = time.perf_counter()
            self.cl.enqueue_copy(self.queue, out, buf, src_offset=int(offset))
            self.queue.finish()
            self.wait_seconds += time.perf_counter() - t
        return out

    def free(self, *bufs) -> None:
        """Stop counting device buffers as live: large ones made by :meth:`empty` or
        :meth:`zeros` go to the pool for reuse (while its idle bytes stay under
        :data:`POOL_SHARE` of the memory budget), the rest are released now. The caller
        must not use a buffer after freeing it; freeing one again does nothing."""
        if self._pool_cap is None:
            self._pool_cap = POOL_SHARE * memory_budget(self)[0]
        for b in bufs:
            with self._pool_lock:
                if id(b) not in self._sizes and any(e[2] is b for e in self._pool):
                    continue                # freed twice: it is in the pool already
                n = self._sizes.pop(id(b), 0)
                self.bytes_live -= n
                pooled = getattr(b, "flags", 0) == self.cl.mem_flags.READ_WRITE
                if n >= POOL_MIN_BYTES and pooled and self._pool_bytes + n <= self._pool_cap:
                    self._pool.append([n, self._generation, b])
                    self._pool_bytes += n
                    continue
            try:
                b.release()
            except Exception:
                pass

    def trim_pool(self) -> None:
        """Release the pooled buffers that no request took since the last call, and start
        a new generation (a render calls this at its end: the pool then holds what one
        render freed, which the next render of the same size takes again)."""
        with self._pool_lock:
            keep = [e for e in self._pool if e[1] == self._generation]
            for e in self._pool:
                if e[1] != self._generation:
                    e[2].release()
            self._pool = keep
            self._pool_bytes = sum(e[0] for e in keep)
            self._generation += 1

    def fit_pool(self, limit: float, need: float) -> None:
        """Before a render of estimated peak ``need`` bytes within a ``limit`` budget in
        bytes (the session's, ``--max-memory`` included): the pool's idle bytes are capped
        at :data:`POOL_SHARE` of the limit and at what the render leaves free, the oldest
        released first, so pooled memory never pushes a render past its budget."""
        with self._pool_lock:
            self._pool_cap = POOL_SHARE * float(limit)
            room = min(self._pool_cap, max(float(limit) - float(need) - self.bytes_live, 0.0))
            while self._pool and self._pool_bytes > room:
                e = self._pool.pop(0)
                e[2].release()
                self._pool_bytes -= e[0]

    def drain_pool(self) -> None:
        """Release every pooled buffer now (a session does when it closes)."""
        with self._pool_lock:
            for e in self._pool:
                e[2].release()
            self._pool, self._pool_bytes = [], 0

    def note_host(self, nbytes: int) -> None:
        """Count a transient host working set of ``nbytes`` towards the peak."""
        self.bytes_peak = max(self.bytes_peak, self.bytes_live + int(nbytes))

    def reset_peak(self) -> None:
        """Start measuring the peak afresh from the bytes live now."""
        self.bytes_peak = self.bytes_live
