"""How much memory a render may use: the smaller of the device's global memory and the
machine's physical memory, unless the user says otherwise."""
from __future__ import annotations

import os


def memory_budget(engine=None, max_memory: float | None = None) -> tuple[float, str]:
    """(bytes, where the number comes from): ``max_memory`` if given, else the smaller of
    the device's global memory and the machine's physical memory. ``engine`` is an
    :class:`~clscatter.device.Engine` or a bare OpenCL device (``clscatter check``, which
    builds no engine), or None for the machine's memory alone."""
    if max_memory is not None:
        return float(max_memory), "--max-memory"
    limits = []
    try:
        limits.append((float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")),
                       "physical memory"))
    except (ValueError, OSError, AttributeError):
        pass
    if engine is not None:
        try:
            device = getattr(engine, "device", engine)
            limits.append((float(device.global_mem_size), "device memory"))
        except Exception:
            pass
    return min(limits) if limits else (float("inf"), "no limit known")
