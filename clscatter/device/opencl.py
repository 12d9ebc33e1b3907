"""The one place pyopencl is imported: on first use, not when clscatter is imported."""
from __future__ import annotations

from ..errors import DeviceError


def _cl():
    """The ``pyopencl`` module.

    Imported here, lazily, rather than at the top of the device modules: importing it is
    slow, and ``import clscatter`` (scene checks, the CLI's help and argument errors,
    tools that never touch a device) should not pay for it. A missing or broken pyopencl
    becomes a :class:`~clscatter.errors.DeviceError` that names the reason, at the first
    call that needs a device."""
    try:
        import pyopencl as cl
    except ImportError as e:  # pragma: no cover - dependency missing
        raise DeviceError(f"pyopencl is not importable: {e}") from e
    return cl
