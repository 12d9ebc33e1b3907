"""Where results kept across runs live on disk (probe results, program binaries), and the
device identity they are valid for."""
from __future__ import annotations

import os
from pathlib import Path

from .opencl import _cl

ENV_CACHE = "CLSCATTER_CACHE_DIR"


def cache_dir() -> Path:
    """The folder for results kept across runs: ``$CLSCATTER_CACHE_DIR``, else
    ``~/.cache/clscatter/kernels``. Read from the environment at each call (a test or a
    caller may point it elsewhere at any time); the folder may not exist yet, and
    writers create it."""
    return Path(os.environ.get(ENV_CACHE) or Path.home() / ".cache" / "clscatter" / "kernels")


def device_identity(device) -> tuple[str, ...]:
    """What a cached result for ``device`` (an OpenCL device) depends on besides its own
    inputs: platform name and version, device name and version, driver version and the
    pyopencl version, as strings. A cached probe result or program binary is valid only
    while all of these are unchanged. Raises whatever the driver raises for a device that
    cannot describe itself."""
    d = device
    return tuple(str(part) for part in (d.platform.name, d.platform.version, d.name, d.version,
                                        d.driver_version, _cl().VERSION_TEXT))
