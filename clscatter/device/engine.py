"""The engine: one OpenCL context and in-order queue on the chosen device, with its program
cache, buffers and launches (each a mixin from its own module), and one engine per
device spec per process."""
from __future__ import annotations

import os
import sys
import time

from .buffers import BufferPool
from .choice import ENV_DEVICE, DeviceInfo, choose_device
from .launch import KernelLauncher
from .opencl import _cl
from .programs import ProgramCache


def one_blas_thread() -> None:
    """Limit every BLAS loaded in the process (OpenBLAS, MKL, ...) to one thread.

    The engine calls this when its device is the CPU, at creation and before each render.
    It acts again only after new modules were imported, since setting the limit is not
    free and a library imported later (SciPy, say) brings its own BLAS. The host's linear
    algebra is small (the epipolar SVD of a 64 x 64 table), but a multi-threaded OpenBLAS
    keeps its worker threads spinning for a while after each call, on the cores the
    kernels that follow need, which slows the kernels down. The limit stays for the whole
    process (NumPy's own linear algebra runs one thread from then on). Without
    threadpoolctl (an optional dependency, imported here) or with a BLAS it does not know,
    nothing changes."""
    global _BLAS_MODULES
    if len(sys.modules) == _BLAS_MODULES:
        return
    try:
        from threadpoolctl import threadpool_limits
        threadpool_limits(1, user_api="blas")
    except Exception:       # not installed, or an unknown BLAS: only a speed matter
        pass
    _BLAS_MODULES = len(sys.modules)       # after importing threadpoolctl itself


_BLAS_MODULES = -1          # len(sys.modules) when the limit was last set


class Engine(ProgramCache, BufferPool, KernelLauncher):
    """An OpenCL context + queue on one device, with cached programs
    (:class:`~clscatter.device.programs.ProgramCache`), tracked and pooled buffers
    (:class:`~clscatter.device.buffers.BufferPool`) and checked launches
    (:class:`~clscatter.device.launch.KernelLauncher`).

    ``bytes_peak`` is the largest total of live device buffers allocated through this
    engine (plus host arrays registered with :meth:`note_host`); renders report it as
    ``peak_bytes``. ``wait_seconds`` is the time the host spent blocked on the device:
    kernel completion, transfers and, on a CPU device, the enqueue calls themselves (an
    enqueue returns only once the runtime has handed the kernel to worker threads that
    take the host's cores). A render's time minus this is its host time (``--stats``:
    ``host_seconds``).
    """

    def __init__(self, info: DeviceInfo):
        cl = _cl()
        self.cl = cl
        self.info = info
        self.device = info.handle
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx)
        self._init_programs()
        self._init_buffers()
        self._init_launches()
        self.wait_seconds = 0.0
        self.shares_host_cores = bool(self.device.type & cl.device_type.CPU)
        self.quiet_host_threads()

    @property
    def name(self) -> str:
        """``"platform / device"``."""
        return f"{self.info.platform} / {self.info.name}"

    def quiet_host_threads(self) -> None:
        """One BLAS thread (:func:`one_blas_thread`) when the kernels run on the host's
        own cores; nothing for a GPU."""
        if self.shares_host_cores:
            one_blas_thread()

    def finish(self) -> None:
        """Wait for every enqueued command (counted in :attr:`wait_seconds`)."""
        t = time.perf_counter()
        self.queue.finish()
        self.wait_seconds += time.perf_counter() - t


_ENGINES: dict[str | None, Engine] = {}


def finish_all() -> None:
    """Wait for every engine's queue to drain (errors ignored): the first step of a stop
    requested by a signal, so that no kernel still in flight uses a buffer the unwinding
    then frees."""
    for engine in list(_ENGINES.values()):
        try:
            engine.queue.finish()
        except Exception:           # a queue already broken: nothing is in flight on it
            pass


def get_engine(spec: str | None = None) -> Engine:
    """The process-wide engine for a device spec: ``spec``, else ``$CLSCATTER_DEVICE``,
    else the first working device (see :func:`~clscatter.device.choose_device`), made at
    the first call and the same object after."""
    spec = spec or os.environ.get(ENV_DEVICE) or None
    if spec not in _ENGINES:
        _ENGINES[spec] = Engine(choose_device(spec))
    return _ENGINES[spec]
