"""The ``.cl`` kernel sources: where they are, which files a program's build reads, and the
declared parameters of each ``__kernel`` function (what keyword launches check against).

The sources are grouped in folders under ``cl_kernels/``: ``shared/`` (headers of the
concepts every kernel uses), ``transport/`` (camera and light paths, device primitives,
ray casting), ``estimators/`` (the estimators several methods share) and ``methods/`` (one
entry file per method). A program is named by its file name alone and found in the
first folder that holds it; ``#include "x.h"`` searches the same folders. A method that
lives outside the package adds its own folder with :func:`add_kernel_dir`."""
from __future__ import annotations

import importlib.resources
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import DeviceError, KernelArgError, KernelBuildError


def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources and their headers: ``cl_kernels/`` beside the
    package in a checkout, else the installed ``clscatter.cl_kernels`` package. Found once
    per process and remembered: the search stats files, and loading a render's programs
    asks for the folder many times. Raises :class:`DeviceError` when neither exists."""
    global _KERNEL_DIR
    if _KERNEL_DIR is None:
        _KERNEL_DIR = _find_kernel_dir()
    return _KERNEL_DIR


_KERNEL_DIR: Path | None = None


def _find_kernel_dir() -> Path:
    """The search behind :func:`kernel_dir` (a folder counts when it holds
    ``shared/common.h``)."""
    here = Path(__file__).resolve().parents[1]      # the clscatter package
    candidates = [here.parent / "cl_kernels", here / "cl_kernels"]
    try:
        candidates.append(Path(str(importlib.resources.files("clscatter.cl_kernels"))))
    except (ModuleNotFoundError, TypeError):
        pass
    for p in candidates:
        if (p / "shared" / "common.h").is_file():
            return p
    raise DeviceError("cannot find the cl_kernels folder (neither in the checkout nor installed)")


#: the folders of cl_kernels/, in search order
GROUPS = ("shared", "transport", "estimators", "methods")
_EXTRA_DIRS: list[Path] = []


def add_kernel_dir(path: str | Path) -> None:
    """Search ``path`` too, after the engine's own folders, for programs and headers: how
    a method outside the package ships its ``.cl`` beside its module."""
    p = Path(path).resolve()
    if p not in _EXTRA_DIRS:
        _EXTRA_DIRS.append(p)


def kernel_dirs() -> list[Path]:
    """Every folder searched for programs and included files, in order."""
    root = kernel_dir()
    return [root / g for g in GROUPS] + list(_EXTRA_DIRS)


def find_source(name: str, dirs: list[Path] | None = None) -> Path:
    """The file ``name`` (``x.cl`` or ``x.h``) in the first of ``dirs`` (default:
    :func:`kernel_dirs`) that holds it; the first folder's path when none does."""
    dirs = dirs if dirs is not None else kernel_dirs()
    for d in dirs:
        if (d / name).is_file():
            return d / name
    return dirs[0] / name


@dataclass(frozen=True)
class KernelParam:
    """One parameter of a ``__kernel`` function, as declared in its ``.cl`` source."""

    name: str
    ctype: str          # the declared type without qualifiers, e.g. "float", "Light*"
    pointer: bool


_CL_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+\.cl)"', re.M)
_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+)"', re.M)
_KERNEL = re.compile(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)")
# path -> ((mtime_ns, size), text without comments, {kernel name: parameters})
_SOURCES: dict[Path, tuple[tuple[int, int], str, dict[str, tuple[KernelParam, ...]]]] = {}


def _strip_comments(source: str) -> str:
    """``source`` with every ``/* */`` and ``//`` comment replaced by a space."""
    return re.sub(r"/\*.*?\*/|//[^\n]*", " ", source, flags=re.S)


def _source(path: Path) -> tuple[str, dict[str, tuple[KernelParam, ...]]]:
    """A kernel file's text with comments removed and the signatures of every kernel it
    defines. Read and parsed once per process, again only when the file's mtime or size
    changes: a render looks up many signatures across a handful of files."""
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


def kernel_signature(source: str, kernel: str) -> tuple[KernelParam, ...]:
    """The parameters of ``__kernel void <kernel>(...)`` in ``source`` (comments removed).

    Only the ``.cl`` file that defines the kernel is parsed; headers hold no entry points
    (see :func:`program_signature` for a kernel in a ``.cl`` file that another includes).
    Raises :class:`KernelArgError` when ``source`` does not define ``kernel``.
    """
    text = _strip_comments(source)
    m = re.search(r"__kernel\s+void\s+" + re.escape(kernel) + r"\s*\(([^)]*)\)", text)
    if not m:
        raise KernelArgError(f"kernel '{kernel}' is not defined in its program source")
    return _params(m.group(1))


def _dirs(root: Path | None) -> list[Path]:
    return [Path(root)] if root is not None else kernel_dirs()


def program_signature(program: str, kernel: str, root: Path | None = None) -> tuple[KernelParam, ...]:
    """The parameters of ``kernel`` as built from ``<program>.cl`` (found in ``root``, else
    in :func:`kernel_dirs`): defined there, or in a ``.cl`` file it ``#include``s, directly
    or not (``voxel_direct.cl`` builds ``raymarch.cl``'s kernel). Raises
    :class:`KernelBuildError` for a missing program, :class:`KernelArgError` for a kernel
    defined nowhere in it."""
    dirs = _dirs(root)
    path = find_source(f"{program}.cl", dirs)
    if not path.is_file():
        raise KernelBuildError(f"kernel source {path} does not exist")
    queue, seen = [path], {path}
    while queue:
        text, kernels = _source(queue.pop(0))
        if kernel in kernels:
            return kernels[kernel]
        for name in _CL_INCLUDE.findall(text):
            inc = find_source(name, dirs)
            if inc not in seen and inc.is_file():
                seen.add(inc)
                queue.append(inc)
    raise KernelArgError(f"kernel '{kernel}' is not defined in {program}.cl or the .cl files it includes")


def program_files(program: str, root: Path | None = None) -> list[Path]:
    """``<program>.cl`` and every file it ``#include``s, directly or not (``.h`` and
    ``.cl``; sorted by name; missing files left out): what a build of the program reads,
    and so what its cached binary depends on."""
    dirs = _dirs(root)
    first = find_source(f"{program}.cl", dirs)
    queue, seen = [first], {first}
    while queue:
        path = queue.pop()
        if not path.is_file():
            continue
        for name in _INCLUDE.findall(_source(path)[0]):
            inc = find_source(name, dirs)
            if inc not in seen:
                seen.add(inc)
                queue.append(inc)
    return sorted((p for p in seen if p.is_file()), key=lambda p: p.name)
