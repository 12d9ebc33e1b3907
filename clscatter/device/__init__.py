"""The OpenCL device: choosing it, building programs with a binary cache, buffers, launches.

Choosing a device (:mod:`.choice`)
    ``--device`` (CLI) or the ``CLSCATTER_DEVICE`` environment variable name a device as
    ``P:D`` (platform and device index, as ``clscatter devices`` lists them) or as a
    case-insensitive substring of ``"platform name / device name"``. An explicit choice
    is honoured or refused with an error; it never falls back silently. Without one, the
    first device (GPUs before others) that builds and correctly runs ``probe.cl`` is
    used; platforms or devices that fail (the PyPI PoCL wheel on some CPUs, say) are
    skipped and ``clscatter devices`` shows why.

Programs (:mod:`.kernel_sources`, :mod:`.programs`, :mod:`.cache`)
    Kernels live in ``cl_kernels/`` (found beside the package in a checkout, or as the
    installed ``clscatter.cl_kernels`` package) and are built with ``-I`` to that folder.
    Built binaries are cached in ``$CLSCATTER_CACHE_DIR`` (default
    ``~/.cache/clscatter/kernels``), keyed by every kernel source, the build options and
    the device/driver identity, so a second run does not recompile.

The engine (:mod:`.engine`, with :mod:`.buffers`, :mod:`.launch`, :mod:`.appending`)
    One context and queue per device, tracked and pooled buffers, keyword launches
    checked against the kernels' declarations, and kernels that append records.

Every name below is importable from ``clscatter.device``; so are the modules' private
names (read from the module that defines them). Assigning a name on this package
(``clscatter.device.POOL_MIN_BYTES = ...``, or ``monkeypatch.setattr(clscatter.device,
"_probe", ...)`` in a test) rebinds it in every module of the package that defines or
imports it, so the new value takes effect wherever it is used.
"""
from __future__ import annotations

import sys
import types

from ..errors import DeviceError, KernelArgError, KernelBuildError
from . import (
    appending,
    buffers,
    cache,
    choice,
    engine,
    kernel_sources,
    launch,
    opencl,
    programs,
)
from .appending import AppendBuffer, launch_appending
from .buffers import POOL_MIN_BYTES, POOL_SHARE, POOL_SLACK
from .cache import ENV_CACHE
from .choice import ENV_DEVICE, DeviceInfo, choose_device, list_devices
from .engine import Engine, get_engine, one_blas_thread
from .kernel_sources import (
    KernelParam,
    add_kernel_dir,
    find_source,
    kernel_dir,
    kernel_dirs,
    kernel_signature,
    program_files,
    program_signature,
)
from .launch import GROUP_SIZE

__all__ = [
    "AppendBuffer", "DeviceError", "DeviceInfo", "ENV_CACHE", "ENV_DEVICE", "Engine",
    "GROUP_SIZE", "KernelArgError", "KernelBuildError", "KernelParam", "POOL_MIN_BYTES",
    "POOL_SHARE", "POOL_SLACK", "choose_device", "get_engine", "kernel_dir", "kernel_dirs", "add_kernel_dir", "find_source",
    "kernel_signature", "launch_appending", "list_devices", "one_blas_thread",
    "program_files", "program_signature",
]

# the package's modules, in dependency order (a private name is read from the first
# that has it; an assignment rebinds the name in all of them)
_MODULES = (opencl, cache, kernel_sources, choice, programs, buffers, launch, engine, appending)


def __getattr__(name: str):
    """A name not re-exported above (a private one, such as ``_probe`` or
    ``_BLAS_MODULES``), read now from the module that holds it."""
    if not name.startswith("__"):
        for module in _MODULES:
            if name in vars(module):
                return vars(module)[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _Package(types.ModuleType):
    """The package module's type: an assignment to one of its names rebinds that name in
    every module of the package that holds it (the re-exports above are copies, and would
    otherwise change nothing where the name is used). A private name stays out of the
    package's own namespace, so that reading it (:func:`__getattr__`) always gives the
    defining module's current value."""

    def __setattr__(self, name: str, value) -> None:
        held = [] if name.startswith("__") else [m for m in _MODULES if name in vars(m)]
        for module in held:
            setattr(module, name, value)
        if not held or name in vars(self):
            super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
