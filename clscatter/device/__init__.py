"""OpenCL platform/device choice, program building with a binary cache, buffer tracking.

Choosing a device
    ``--device`` (CLI) or the ``CLSCATTER_DEVICE`` environment variable name a device as
    ``P:D`` (platform and device index, as ``clscatter devices`` lists them) or as a
    case-insensitive substring of ``"platform name / device name"``. An explicit choice
    is honoured or refused with an error; it never falls back silently. Without one, the
    first device (GPUs before others) that builds and correctly runs ``probe.cl`` is
    used; platforms or devices that fail (the PyPI PoCL wheel on some CPUs, say) are
    skipped and ``clscatter devices`` shows why.

Programs
    Kernels live in ``cl_kernels/`` (found beside the package in a checkout, or as the
    installed ``clscatter.cl_kernels`` package) and are built with ``-I`` to that folder.
    Built binaries are cached in ``$CLSCATTER_CACHE_DIR`` (default
    ``~/.cache/clscatter/kernels``), keyed by every kernel source, the build options and
    the device/driver identity, so a second run does not recompile.
"""
from __future__ import annotations

import difflib
import hashlib
import os
import re
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import DeviceError, KernelArgError, KernelBuildError

ENV_DEVICE = "CLSCATTER_DEVICE"
ENV_CACHE = "CLSCATTER_CACHE_DIR"
# work-items per group of a 1-D launch (Engine.launch; less where a kernel allows fewer)
GROUP_SIZE = 64
# buffer pool (Engine.empty / free): buffers of at least POOL_MIN_BYTES are kept for reuse;
# a request takes the smallest idle one of its size up to POOL_SLACK times it; the idle
# bytes stay under POOL_SHARE of the memory budget
POOL_MIN_BYTES = 1 << 16
POOL_SLACK = 1.25
POOL_SHARE = 0.25


def kernel_dir() -> Path:
    """The folder holding the .cl sources (checkout first, then the installed package),
    found once per process (the search stats files: ~0.16 ms a call, ~70 calls while the
    programs of a render load)."""
    global _KERNEL_DIR
    if _KERNEL_DIR is None:
        _KERNEL_DIR = _find_kernel_dir()
    return _KERNEL_DIR


_KERNEL_DIR: Path | None = None


def _find_kernel_dir() -> Path:
    here = Path(__file__).resolve().parents[1]      # the clscatter package
    checkout = here.parent / "cl_kernels"
    if (checkout / "common.h").is_file():
        return checkout
    installed = here / "cl_kernels"
    if (installed / "common.h").is_file():
        return installed
    try:
        import importlib.resources as res
        p = Path(str(res.files("clscatter.cl_kernels")))
        if (p / "common.h").is_file():
            return p
    except (ModuleNotFoundError, TypeError):
        pass
    raise DeviceError("cannot find the cl_kernels folder (neither in the checkout nor installed)")


def _cl():
    try:
        import pyopencl as cl
    except ImportError as e:  # pragma: no cover - dependency missing
        raise DeviceError(f"pyopencl is not importable: {e}") from e
    return cl


@dataclass
class DeviceInfo:
    """One OpenCL device as listed by ``clscatter devices``."""

    platform_index: int
    device_index: int
    platform: str
    name: str
    kind: str
    ok: bool = False
    reason: str = ""
    handle: object = field(default=None, repr=False)

    @property
    def label(self) -> str:
        return f"{self.platform_index}:{self.device_index} {self.platform} / {self.name}"


def _probe(device) -> str:
    """Build and run probe.cl on ``device``; return '' when it works, else the reason."""
    cl = _cl()
    try:
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        src = (kernel_dir() / "probe.cl").read_text()
        prog = cl.Program(ctx, src).build(options=["-I", str(kernel_dir())], cache_dir=False)
        a = np.arange(16, dtype=np.float32)
        mf = cl.mem_flags
        a_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
        o_buf = cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes)
        prog.probe(queue, a.shape, None, a_buf, np.int32(len(a)), o_buf)
        out = np.empty_like(a)
        cl.enqueue_copy(queue, out, o_buf)
        queue.finish()
    except Exception as e:  # any failure makes the device unusable; report why
        msg = str(e).strip().splitlines()
        return f"{type(e).__name__}: {msg[0] if msg else ''}"[:300]
    expect = a * a + 6.0
    if not np.allclose(out, expect, rtol=1e-5, atol=1e-5):
        return "probe kernel ran but returned wrong values"
    return ""


def _probe_cache_path() -> Path:
    return Path(os.environ.get(ENV_CACHE) or Path.home() / ".cache" / "clscatter" / "kernels") \
        / "probe.json"


def _device_identity(device) -> str:
    """Platform, device and driver versions: a cached probe result is valid only while
    all of these are unchanged."""
    cl = _cl()
    parts = [device.platform.name, device.platform.version, device.name, device.version,
             device.driver_version, cl.VERSION_TEXT, str(kernel_dir() / "probe.cl")]
    return hashlib.sha256("|".join(map(str, parts)).encode()).hexdigest()[:24]


def _cached_probe(device) -> str:
    """:func:`_probe`, remembered across runs for devices that passed (keyed by
    :func:`_device_identity`); ``clscatter devices`` always probes afresh. A device that
    failed is probed again every time (it may have been fixed)."""
    import json
    path = _probe_cache_path()
    try:
        ident = _device_identity(device)
    except Exception:        # a device that cannot even describe itself: probe it, no cache
        return _probe(device)
    try:
        cache = json.loads(path.read_text())
    except (OSError, ValueError):
        cache = {}
    if cache.get(ident) == "ok":
        return ""
    reason = _probe(device)
    if not reason:
        cache[ident] = "ok"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(cache))
            tmp.replace(path)
        except OSError:
            pass
    return reason


def list_devices(probe: bool = True) -> tuple[list[DeviceInfo], list[str]]:
    """All platforms' devices, probed; plus messages for platforms that failed outright."""
    cl = _cl()
    infos: list[DeviceInfo] = []
    problems: list[str] = []
    try:
        platforms = cl.get_platforms()
    except Exception as e:
        raise DeviceError(f"no OpenCL platform found ({e}); install pocl-opencl-icd") from e
    for pi, plat in enumerate(platforms):
        try:
            pname = plat.name.strip()
            devices = plat.get_devices()
        except Exception as e:
            problems.append(f"platform {pi}: skipped ({type(e).__name__}: {e})")
            continue
        for di, dev in enumerate(devices):
            try:
                kind = cl.device_type.to_string(dev.type)
            except Exception:
                kind = "?"
            info = DeviceInfo(pi, di, pname, dev.name.strip(), kind, handle=dev)
            if probe:
                info.reason = _probe(dev)
                info.ok = not info.reason
            infos.append(info)
    return infos, problems


def _matches(info: DeviceInfo, spec: str) -> bool:
    spec = spec.strip()
    if ":" in spec and all(p.strip().isdigit() for p in spec.split(":", 1)):
        p, d = (int(x) for x in spec.split(":", 1))
        return (info.platform_index, info.device_index) == (p, d)
    return spec.lower() in f"{info.platform} / {info.name}".lower()


def choose_device(spec: str | None = None) -> DeviceInfo:
    """The device to use: ``spec``, else ``$CLSCATTER_DEVICE``, else the first that works."""
    spec = spec or os.environ.get(ENV_DEVICE) or None
    infos, problems = list_devices(probe=False)
    if spec:
        chosen = [i for i in infos if _matches(i, spec)]
        if not chosen:
            listing = "; ".join(i.label for i in infos) or "none"
            raise DeviceError(f"device '{spec}' not found (available: {listing})")
        info = chosen[0]
        info.reason = _cached_probe(info.handle)
        info.ok = not info.reason
        if not info.ok:
            raise DeviceError(f"device '{info.label}' fails its probe: {info.reason}")
        return info
    cl = _cl()
    ordered = sorted(infos, key=lambda i: 0 if i.handle.type & cl.device_type.GPU else 1)
    reasons = list(problems)
    for info in ordered:
        info.reason = _cached_probe(info.handle)
        info.ok = not info.reason
        if info.ok:
            return info
        reasons.append(f"{info.label}: {info.reason}")
    raise DeviceError("no working OpenCL device" + (": " + "; ".join(reasons) if reasons else
                      " (install pocl-opencl-icd)"))


# OpenCL scalar parameter types -> the NumPy type a value is converted to
_SCALARS = {"int": np.int32, "uint": np.uint32, "unsigned int": np.uint32, "float": np.float32,
            "long": np.int64, "ulong": np.uint64, "short": np.int16, "ushort": np.uint16,
            "char": np.int8, "uchar": np.uint8}
_VECTORS = {"float2": 2, "float4": 4, "int2": 2, "int4": 4}


@dataclass(frozen=True)
class KernelParam:
    """One parameter of a ``__kernel`` function, as declared in its ``.cl`` source."""

    name: str
    ctype: str          # the declared type without qualifiers, e.g. "float", "Light*"
    pointer: bool


_CL_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+\.cl)"', re.M)
_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+)"', re.M)


def _strip_comments(source: str) -> str:
    return re.sub(r"/\*.*?\*/|//[^\n]*", " ", source, flags=re.S)


_KERNEL = re.compile(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)")
_SOURCES: dict[Path, tuple[tuple[int, int], str, dict[str, tuple[KernelParam, ...]]]] = {}


def _source(path: Path) -> tuple[str, dict[str, tuple[KernelParam, ...]]]:
    """A kernel file's text with comments removed and the signatures of every kernel it
    defines, read and parsed once per process (again only when the file's mtime or size
    changes): a render looks up ~80 signatures across a handful of files."""
    st = path.stat()
    stamp = (st.st_mtime_ns, st.st_size)
    got = _SOURCES.get(path)
    if got is None or got[0] != stamp:
        text = _strip_comments(path.read_text())
        kernels: dict[str, tuple[KernelParam, ...]] = {}
        for m in _KERNEL.finditer(text):            # the first definition wins, as in C
            kernels.setdefault(m.group(1), _params(m.group(2)))
        got = _SOURCES[path] = (stamp, text, kernels)
    return got[1], got[2]


def kernel_signature(source: str, kernel: str) -> tuple[KernelParam, ...]:
    """The parameters of ``__kernel void <kernel>(...)`` in ``source`` (comments removed).

    Only the ``.cl`` file that defines the kernel is parsed; headers hold no entry points
    (see :func:`program_signature` for a kernel in a ``.cl`` file that another includes).
    """
    text = _strip_comments(source)
    m = re.search(r"__kernel\s+void\s+" + re.escape(kernel) + r"\s*\(([^)]*)\)", text)
    if not m:
        raise KernelArgError(f"kernel '{kernel}' is not defined in its program source")
    return _params(m.group(1))


def _params(declaration: str) -> tuple[KernelParam, ...]:
    """KernelParams of a kernel's comma-separated parameter declarations."""
    params = []
    for raw in declaration.split(","):
        words = raw.replace("*", " * ").split()
        if not words:
            continue
        pointer = "*" in words
        name = words[-1]
        ctype = " ".join(w for w in words[:-1] if w not in
                         ("__global", "global", "__local", "local", "__constant", "constant",
                          "const", "restrict", "__restrict", "*"))
        params.append(KernelParam(name, ctype + ("*" if pointer else ""), pointer))
    return tuple(params)


def program_signature(program: str, kernel: str, root: Path | None = None) -> tuple[KernelParam, ...]:
    """The parameters of ``kernel`` as built from ``<root>/<program>.cl`` (root: the kernel
    directory): defined there, or in a ``.cl`` file it ``#include``s, directly or not
    (``voxel_direct.cl`` builds ``raymarch.cl``'s kernel)."""
    root = Path(root) if root is not None else kernel_dir()
    path = root / f"{program}.cl"
    if not path.is_file():
        raise KernelBuildError(f"kernel source {path} does not exist")
    queue, seen = [path], {path}
    while queue:
        text, kernels = _source(queue.pop(0))
        if kernel in kernels:
            return kernels[kernel]
        for name in _CL_INCLUDE.findall(text):
            inc = root / name
            if inc not in seen and inc.is_file():
                seen.add(inc)
                queue.append(inc)
    raise KernelArgError(f"kernel '{kernel}' is not defined in {program}.cl or the .cl files it includes")


def program_files(program: str, root: Path | None = None) -> list[Path]:
    """``<root>/<program>.cl`` and every file it ``#include``s, directly or not (``.h`` and
    ``.cl``; sorted by name): what a build of the program reads."""
    root = Path(root) if root is not None else kernel_dir()
    first = root / f"{program}.cl"
    queue, seen = [first], {first}
    while queue:
        path = queue.pop()
        if not path.is_file():
            continue
        for name in _INCLUDE.findall(_source(path)[0]):
            inc = root / name
            if inc not in seen:
                seen.add(inc)
                queue.append(inc)
    return sorted((p for p in seen if p.is_file()), key=lambda p: p.name)


def one_blas_thread() -> None:
    """Limit every BLAS loaded in the process (OpenBLAS, MKL, ...) to one thread.

    The engine calls this when its device is the CPU, at creation and before each render;
    it acts again only after new modules were imported (a library imported later, SciPy
    say, brings its own BLAS; setting the limit costs ~1 ms). The host's linear algebra is
    small (the epipolar SVD of a 64 x 64 table), but a multi-threaded OpenBLAS keeps its
    worker threads spinning for a while after each call, on the cores the kernels that
    follow need: on a 2-core machine that took ~40 ms (12% of the samples a profiler
    saw) from a 0.34 s epipolar re-render after a light move. The limit stays for the
    whole process (NumPy's own linear algebra runs one thread from then on). Without
    threadpoolctl (or with a BLAS it does not know) nothing changes."""
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


class Engine:
    """An OpenCL context + queue on one device, with cached programs and tracked buffers.

    ``bytes_peak`` is the largest total of live device buffers allocated through this
    engine (plus host arrays registered with :meth:`note_host`); renders report it as
    ``peak_bytes``.
    """

    def __init__(self, info: DeviceInfo):
        cl = _cl()
        self.cl = cl
        self.info = info
        self.device = info.handle
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx)
        self._programs: dict[tuple, object] = {}
        self._kernels: dict[tuple, object] = {}
        self._signatures: dict[tuple, tuple[KernelParam, ...]] = {}
        self._groups: dict[int, int] = {}
        self._sizes: dict[int, int] = {}
        self.bytes_live = 0
        self.bytes_peak = 0
        # idle buffers for reuse: [size, generation, buffer] (see empty, free, trim_pool)
        self._pool: list[list] = []
        self._pool_bytes = 0
        self._pool_cap: float | None = None
        self._generation = 0
        self._pool_lock = threading.Lock()      # a page's session may close from another thread
        self.builds = {"source": 0, "cache": 0}   # how programs were obtained
        # seconds the host spent blocked on the device (kernel completion, transfers, and
        # on a CPU device the enqueue calls themselves: an enqueue returns only once the
        # runtime has handed the kernel to worker threads that take the host's cores,
        # 0.05-2 ms a launch, ~10 ms of a 0.26 s epipolar light move): a render's time
        # minus this is its host time (``--stats``: host_seconds)
        self.wait_seconds = 0.0
        self.shares_host_cores = bool(self.device.type & cl.device_type.CPU)
        self.quiet_host_threads()

    @property
    def name(self) -> str:
        return f"{self.info.platform} / {self.info.name}"

    def quiet_host_threads(self) -> None:
        """One BLAS thread (:func:`one_blas_thread`) when the kernels run on the host's
        own cores; nothing for a GPU."""
        if self.shares_host_cores:
            one_blas_thread()

    # ---- programs ----
    def program(self, name: str, defines: dict[str, object] | None = None):
        """Build (or fetch from cache) ``cl_kernels/<name>.cl`` with ``-D`` defines."""
        opts = ["-I", str(kernel_dir()), "-cl-fp32-correctly-rounded-divide-sqrt"]
        for k, v in sorted((defines or {}).items()):
            opts.append(f"-D{k}={v}")
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
        ``device`` stage) kept out of a render's own time."""
        for name, defines in programs:
            path = kernel_dir() / f"{name}.cl"
            if not path.is_file():
                continue
            for kernel in _source(path)[1]:
                self.kernel(name, kernel, defines)

    def signature(self, program: str, kernel: str) -> tuple[KernelParam, ...]:
        """The declared parameters of ``kernel`` in ``cl_kernels/<program>.cl`` or a ``.cl``
        file it includes (cached; see :func:`program_signature`)."""
        key = (program, kernel)
        if key not in self._signatures:
            self._signatures[key] = program_signature(program, kernel)
        return self._signatures[key]

    def bind(self, program: str, kernel: str, args: dict[str, object]) -> list:
        """Positional kernel arguments from keyword ``args``, checked against the signature.

        Every parameter must be given exactly once (an unknown or missing name is a
        :class:`KernelArgError`, with a "did you mean"); scalars are converted to the
        declared type, so ``n=len(x)`` is passed as a 32-bit int where the kernel says
        ``int``; pointer parameters must be device buffers.
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

    def _cache_key(self, name: str, opts: Sequence[str]) -> str:
        """The binary cache key: the program's source and every file it includes, directly
        or not (so editing one kernel leaves the other programs' binaries valid), the
        options, the device and driver."""
        h = hashlib.sha256()
        kd = kernel_dir()
        for p in program_files(name, kd):
            h.update(p.name.encode())
            h.update(p.read_bytes())
        h.update(name.encode())
        h.update(" ".join(o for o in opts if o != str(kd)).encode())
        d = self.device
        for part in (d.platform.name, d.platform.version, d.name, d.version, d.driver_version,
                     self.cl.VERSION_TEXT):
            h.update(str(part).encode())
        return h.hexdigest()[:32]

    def _build(self, name: str, opts: list[str]):
        cl = self.cl
        path = kernel_dir() / f"{name}.cl"
        if not path.is_file():
            raise KernelBuildError(f"kernel source {path} does not exist")
        cache = Path(os.environ.get(ENV_CACHE) or Path.home() / ".cache" / "clscatter" / "kernels")
        key = self._cache_key(name, opts)
        binfile = cache / f"{name}-{key}.bin"
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
            pass  # a read-only cache only costs rebuilds
        return prog

    # ---- buffers ----
    def _track(self, buf, nbytes: int):
        self._sizes[id(buf)] = nbytes
        self.bytes_live += nbytes
        self.bytes_peak = max(self.bytes_peak, self.bytes_live)
        return buf

    def to_device(self, array: np.ndarray, writable: bool = False):
        """Copy a host array into a new device buffer (at least 1 byte)."""
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
        """An uninitialised read-write device buffer of at least ``nbytes``.

        Large ones come from the pool of buffers released by :meth:`free` when one fits
        (at most :data:`POOL_SLACK` times the size): a re-render allocates the same ~220 MB
        of scratch as the render before it, and fresh memory costs the CPU device page
        faults on first touch (~8,400, ~10 ms, of a 0.3 s epipolar light move here). The
        queue is in order, so a reused buffer is never written before the commands that
        used it before have run."""
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
        """A new device buffer filled with zero bytes."""
        buf = self.empty(nbytes)
        self.cl.enqueue_fill_buffer(self.queue, buf, np.zeros(1, np.uint32), 0, max(int(nbytes), 4))
        return buf

    def read(self, buf, shape, dtype, offset: int = 0) -> np.ndarray:
        """Copy a device buffer (from byte ``offset``) back into a new host array of
        ``shape`` and ``dtype``."""
        out = np.empty(shape, dtype)
        if out.nbytes:
            t = time.perf_counter()
            self.cl.enqueue_copy(self.queue, out, buf, src_offset=int(offset))
            self.queue.finish()
            self.wait_seconds += time.perf_counter() - t
        return out

    def finish(self) -> None:
        """Wait for every enqueued command (counted in :attr:`wait_seconds`)."""
        t = time.perf_counter()
        self.queue.finish()
        self.wait_seconds += time.perf_counter() - t

    def free(self, *bufs) -> None:
        """Stop counting device buffers as live: large ones made by :meth:`empty` or
        :meth:`zeros` go to the pool for reuse (while its idle bytes stay under
        :data:`POOL_SHARE` of the memory budget), the rest are released now. The caller
        must not use a buffer after freeing it, nor free it twice."""
        if self._pool_cap is None:
            from .budget import memory_budget
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
        """Before a render of estimated peak ``need`` bytes within a ``limit`` budget (the
        session's, ``--max-memory`` included): the pool's idle bytes are capped at
        :data:`POOL_SHARE` of the limit and at what the render leaves free, the oldest
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
        """Count a transient host working set towards the peak."""
        self.bytes_peak = max(self.bytes_peak, self.bytes_live + int(nbytes))

    def reset_peak(self) -> None:
        self.bytes_peak = self.bytes_live

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
        """Enqueue ``kernel`` over ``global_size`` work-items.

        A 1-D launch runs in work-groups of :data:`GROUP_SIZE` (or ``group``), its size
        rounded up to a multiple (every kernel returns early past its own count). A driver
        that chooses the group size itself picks it from the global size's divisors, and
        PoCL compiles the kernel anew for each group size it meets: a render whose sizes
        change with the scene (slices per batch, live samples) paid that, ~0.3 s a time,
        on every frame. Arguments are set one by one (``set_arg``) rather than through
        pyopencl's generated per-kernel invokers, whose cache costs ~0.07 s of host time
        per process (numpy scalars, arrays and records pass as their bytes). On a CPU
        device the enqueue call's own time counts in :attr:`wait_seconds`: it lasts until
        the runtime's worker threads, which take the host's cores, have the kernel (on a
        GPU it is the driver's host work, and counts as host time)."""
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


_ENGINES: dict[str | None, Engine] = {}


def get_engine(spec: str | None = None) -> Engine:
    """The process-wide engine for a device spec (see :func:`choose_device`)."""
    spec = spec or os.environ.get(ENV_DEVICE) or None
    if spec not in _ENGINES:
        _ENGINES[spec] = Engine(choose_device(spec))
    return _ENGINES[spec]


class AppendBuffer:
    """A device buffer that a kernel appends records to through an atomic counter.

    The kernel's last three arguments must be ``(records, capacity, counter)``; it appends
    with ``idx = atomic_inc(counter)`` and writes only when ``idx < capacity``. After a
    launch the counter tells how many records it wanted to write; when that is more than
    fit, the buffer grows and the same launch runs again (kernels are deterministic), so
    callers never lose records and never need to guess sizes exactly. A kernel that
    appends to several buffers at once runs through :func:`launch_appending`.
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
        are the records, capacity and counter; return the records appended."""
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
