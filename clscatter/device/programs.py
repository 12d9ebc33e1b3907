"""Building OpenCL programs from ``cl_kernels/<name>.cl``, once per process and options, with
their binaries kept on disk so that a second run does not compile again."""
from __future__ import annotations

import hashlib
import warnings
from typing import Sequence

from ..errors import KernelBuildError
from .cache import cache_dir, device_identity
from .kernel_sources import _source, find_source, kernel_dirs, program_files


def build_options(defines: dict[str, object] | None) -> list[str]:
    """The compiler options of a program build: ``-I`` to the kernel folder, correctly
    rounded float division and square root (IEEE results rather than each driver's
    approximation), and one ``-DNAME=value`` per define, sorted by name."""
    opts = [o for d in kernel_dirs() for o in ("-I", str(d))]
    opts.append("-cl-fp32-correctly-rounded-divide-sqrt")
    for k, v in sorted((defines or {}).items()):
        opts.append(f"-D{k}={v}")
    return opts


def device_defines(cl, device) -> dict[str, object]:
    """The defines every program is built with on ``device``: ``CLSCATTER_CPU_PREFETCH``
    on a CPU device that claims no other kind, GPU or accelerator (``PREFETCH_HINT`` in
    ``cl_kernels/shared/common.h``: a cache prefetch hint where the kernels run on the
    host's cores; a GPU hides memory latency with other work-items, and a simulator that
    claims every device type, such as Oclgrind, has no prefetch to lower it to)."""
    kind = cl.device_type
    cpu_alone = bool(device.type & kind.CPU) and not device.type & (kind.GPU | kind.ACCELERATOR)
    return {"CLSCATTER_CPU_PREFETCH": 1} if cpu_alone else {}


def binary_key(device, name: str, opts: Sequence[str]) -> str:
    """The on-disk binary cache key of program ``name`` built with ``opts`` for ``device``
    (32 hex digits): every file the program reads (its source and what it includes,
    directly or not, so editing one kernel leaves the other programs' binaries valid),
    the options without the kernel folder's path (a moved checkout keeps its binaries),
    and the :func:`~clscatter.device.cache.device_identity`."""
    h = hashlib.sha256()
    dirs = {str(d) for d in kernel_dirs()}
    for p in program_files(name):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    h.update(name.encode())
    h.update(" ".join(o for o in opts if o not in dirs and o != "-I").encode())
    for part in device_identity(device):
        h.update(part.encode())
    return h.hexdigest()[:32]


class ProgramCache:
    """The programs and kernels of an engine, each built or created once.

    A mixin of :class:`~clscatter.device.engine.Engine`: it uses the engine's ``cl``
    (pyopencl), ``ctx`` and ``device``, and :meth:`_init_programs` sets its own state.
    ``builds`` counts how programs were obtained: compiled from ``"source"`` or loaded
    from the on-disk ``"cache"``."""

    def _init_programs(self) -> None:
        self._programs: dict[tuple, object] = {}     # (name, options) -> cl.Program
        self._kernels: dict[tuple, object] = {}      # (name, defines, kernel) -> cl.Kernel
        self.builds = {"source": 0, "cache": 0}
        self.device_defines = device_defines(self.cl, self.device)

    def program(self, name: str, defines: dict[str, object] | None = None):
        """The built ``cl_kernels/<name>.cl`` with ``-D`` ``defines`` (see
        :func:`build_options`): from this engine's memory, else the binary cache, else
        compiled. Raises :class:`KernelBuildError` (with the compiler's log) when the
        source is missing or does not compile."""
        opts = build_options({**self.device_defines, **(defines or {})})
        key = (name, tuple(opts))
        if key not in self._programs:
            self._programs[key] = self._build(name, opts)
        return self._programs[key]

    def kernel(self, program: str, kernel: str, defines: dict[str, object] | None = None):
        """A kernel object, created once per (program, defines, kernel name)."""
        key = (program, tuple(sorted((defines or {}).items())), kernel)
        if key not in self._kernels:
            self._kernels[key] = self.cl.Kernel(self.program(program, defines), kernel)
        return self._kernels[key]

    def preload(self, programs: Sequence[tuple[str, dict | None]]) -> None:
        """Load each (program, defines) and create every kernel its ``.cl`` file defines,
        now rather than at the first launch: start-up work (a session does it in its
        ``device`` stage) kept out of a render's own time. Programs without a source file
        are skipped."""
        for name, defines in programs:
            path = find_source(f"{name}.cl")
            if not path.is_file():
                continue
            for kernel in _source(path)[1]:
                self.kernel(name, kernel, defines)

    def _build(self, name: str, opts: list[str]):
        """Program ``name`` built with ``opts``: loaded from the binary cache when its
        :func:`binary_key` is there and loads, else compiled and written to the cache (a
        read-only or missing cache folder only costs compiling again)."""
        cl = self.cl
        path = find_source(f"{name}.cl")
        if not path.is_file():
            raise KernelBuildError(f"kernel source {path} does not exist")
        cache = cache_dir()
        binfile = cache / f"{name}-{binary_key(self.device, name, opts)}.bin"
        if binfile.is_file():
            try:
                prog = cl.Program(self.ctx, [self.device], [binfile.read_bytes()]).build(options=opts)
                self.builds["cache"] += 1
                return prog
            except Exception:
                pass  # stale or foreign binary: rebuild from source below
        prog = cl.Program(self.ctx, path.read_text())
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                prog = prog.build(options=opts, cache_dir=False)
        except cl.RuntimeError as e:
            raise KernelBuildError(f"building {path.name} failed:\n{e}") from e
        self.builds["source"] += 1
        try:
            cache.mkdir(parents=True, exist_ok=True)
            tmp = binfile.with_suffix(".tmp")
            tmp.write_bytes(prog.binaries[0])
            tmp.replace(binfile)
        except OSError:
            pass
        return prog
