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

Every name in ``__all__`` is importable from ``clscatter.device``. A setting or private
name is changed where it is defined (``clscatter.device.buffers.POOL_MIN_BYTES``,
``clscatter.device.choice._probe``): these names here are copies.
"""
from __future__ import annotations

from ..errors import DeviceError, KernelArgError, KernelBuildError
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
    "POOL_SHARE", "POOL_SLACK", "add_kernel_dir", "choose_device", "find_source",
    "get_engine", "kernel_dir", "kernel_dirs", "kernel_signature", "launch_appending", "list_devices", "one_blas_thread",
    "program_files", "program_signature",
]
