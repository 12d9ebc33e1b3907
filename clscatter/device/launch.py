"""Launching kernels: keyword arguments checked against the kernel's declaration and
converted to its types, and 1-D launches in work-groups of a fixed size."""
from __future__ import annotations

import difflib
import time
from typing import Callable, Iterator, Sequence

import numpy as np

from ..errors import KernelArgError
from .kernel_sources import KernelParam, program_signature

# work-items per group of a 1-D launch (less where a kernel allows fewer)
GROUP_SIZE = 64

#: what one launch of work whose cost per item varies by orders of magnitude between
#: scenes should take (timed_launches): progress moves and a stop is heard within it
LAUNCH_SECONDS = 0.25
#: items of the first such launch, before any is timed
FIRST_LAUNCH = 1024
#: most a launch may grow over the one before
LAUNCH_GROWTH = 4

# OpenCL scalar parameter types -> the NumPy type a value is converted to
_SCALARS = {"int": np.int32, "uint": np.uint32, "unsigned int": np.uint32, "float": np.float32,
            "long": np.int64, "ulong": np.uint64, "short": np.int16, "ushort": np.uint16,
            "char": np.int8, "uchar": np.uint8}
# OpenCL vector parameter types -> their number of components
_VECTORS = {"float2": 2, "float4": 4, "int2": 2, "int4": 4}


def timed_launches(n: int, most: int, seconds: float = LAUNCH_SECONDS,
                   first: int = FIRST_LAUNCH,
                   clock: Callable[[], float] = time.perf_counter) -> Iterator[tuple[int, int]]:
    """``(start, count)`` of successive launches over ``n`` items, sized so that each takes
    about ``seconds``: the first ``first`` items (at most ``most``), then each the last
    launch's items per second times ``seconds``, at most :data:`LAUNCH_GROWTH` times the
    last launch and at most ``most``, at least 1. The caller launches and waits for the
    launch (``Engine.finish``) before taking the next: the time between two steps of the
    iteration is the launch's."""
    start, size = 0, max(1, min(int(first), int(most)))
    while start < n:
        count = min(size, n - start)
        t = clock()
        yield start, count
        dt = clock() - t
        start += count
        fit = count * seconds / dt if dt > 0 else float("inf")
        size = int(max(1, min(most, LAUNCH_GROWTH * count, fit)))


class KernelLauncher:
    """Keyword and positional kernel launches of an engine.

    A mixin of :class:`~clscatter.device.engine.Engine`: it uses the engine's ``cl``
    (pyopencl), ``device``, ``queue``, ``kernel()`` (the program cache),
    ``shares_host_cores`` and ``wait_seconds``, and :meth:`_init_launches` sets its own
    state."""

    def _init_launches(self) -> None:
        self._signatures: dict[tuple, tuple[KernelParam, ...]] = {}   # (program, kernel)
        self._groups: dict[int, int] = {}                             # kernel.int_ptr -> size

    def signature(self, program: str, kernel: str) -> tuple[KernelParam, ...]:
        """The declared parameters of ``kernel`` in ``cl_kernels/<program>.cl`` or a ``.cl``
        file it includes (cached; see :func:`~clscatter.device.program_signature`)."""
        key = (program, kernel)
        if key not in self._signatures:
            self._signatures[key] = program_signature(program, kernel)
        return self._signatures[key]

    def bind(self, program: str, kernel: str, args: dict[str, object]) -> list:
        """Positional kernel arguments from keyword ``args``, checked against the signature.

        Every parameter must be given exactly once (an unknown or missing name is a
        :class:`KernelArgError`, with a "did you mean"); scalars are converted to the
        declared type, so ``n=len(x)`` is passed as a 32-bit int where the kernel says
        ``int``; vectors are zero-padded or cut to their width; pointer parameters must
        be device buffers; a struct passed by value must be a matching NumPy record.
        """
        params = self.signature(program, kernel)
        names = [p.name for p in params]
        unknown = [k for k in args if k not in names]
        if unknown:
            near = difflib.get_close_matches(unknown[0], names, n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise KernelArgError(f"{program}.cl:{kernel} has no parameter '{unknown[0]}'{hint}")
        missing = [n for n in names if n not in args]
        if missing:
            raise KernelArgError(f"{program}.cl:{kernel}: missing argument(s) {', '.join(missing)}")
        out = []
        for p in params:
            v = args[p.name]
            if p.pointer:
                if not isinstance(v, self.cl.MemoryObjectHolder):
                    raise KernelArgError(f"{program}.cl:{kernel}: '{p.name}' ({p.ctype}) needs a "
                                         f"device buffer, got {type(v).__name__}")
                out.append(v)
            elif p.ctype in _SCALARS:
                out.append(_SCALARS[p.ctype](v))
            elif p.ctype in _VECTORS:
                vec = np.zeros(_VECTORS[p.ctype], np.float32 if p.ctype.startswith("float") else np.int32)
                flat = np.asarray(v).ravel()
                vec[:len(flat)] = flat[:len(vec)]
                out.append(vec)
            else:  # a struct passed by value: the caller gives a matching NumPy record
                out.append(v)
        return out

    def call(self, program: str, kernel: str, global_size: int | Sequence[int],
             defines: dict[str, object] | None = None, **args) -> None:
        """Launch ``kernel`` of ``cl_kernels/<program>.cl`` with keyword arguments.

        ``engine.call("raymarch", "raymarch", n, segs=buf, num_segs=n, ...)``: names are
        checked against the kernel's declaration (see :meth:`bind`), so a swapped or
        misspelled argument is an error instead of a wrong image.
        """
        self.launch(self.kernel(program, kernel, defines), global_size,
                    *self.bind(program, kernel, args))

    def _group_size(self, kernel) -> int:
        """:data:`GROUP_SIZE`, or the most ``kernel`` allows on this device if less."""
        key = kernel.int_ptr
        if key not in self._groups:
            most = kernel.get_work_group_info(self.cl.kernel_work_group_info.WORK_GROUP_SIZE,
                                              self.device)
            self._groups[key] = max(1, min(GROUP_SIZE, int(most)))
        return self._groups[key]

    def launch(self, kernel, global_size: int | Sequence[int], *args,
               group: int | None = None) -> None:
        """Enqueue ``kernel`` over ``global_size`` work-items with positional ``args``
        (nothing when any dimension is zero or less).

        A 1-D launch runs in work-groups of :data:`GROUP_SIZE` (or ``group``), its size
        rounded up to a multiple (every kernel returns early past its own count): a
        driver that chooses the group size itself picks it from the global size's
        divisors, and PoCL compiles the kernel anew for each group size it meets, so sizes
        that change with the scene (slices per batch, live samples) would compile kernels
        again frame after frame. Arguments are set one by one (``set_arg``) rather than
        through pyopencl's generated per-kernel invokers, whose cache costs host time in
        every process (numpy scalars, arrays and records pass as their bytes). On a CPU
        device the enqueue call's own time counts in ``wait_seconds``: it lasts until the
        runtime's worker threads, which take the host's cores, have the kernel (on a GPU
        it is the driver's host work, and counts as host time)."""
        gs = (int(global_size),) if np.isscalar(global_size) else tuple(int(g) for g in global_size)
        if min(gs) <= 0:
            return
        for i, a in enumerate(args):
            kernel.set_arg(i, a)
        if len(gs) == 1:
            g = int(group) if group else self._group_size(kernel)
            size, local = (-(-gs[0] // g) * g,), (g,)
        else:
            size, local = gs, None
        t = time.perf_counter()
        self.cl.enqueue_nd_range_kernel(self.queue, kernel, size, local)
        if self.shares_host_cores:
            self.wait_seconds += time.perf_counter() - t
