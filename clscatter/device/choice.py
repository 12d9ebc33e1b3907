"""Which OpenCL device to use: listing platforms and devices, probing that a device builds
and correctly runs ``probe.cl`` (remembered across runs for devices that pass), and
honouring an explicit choice.

``--device`` (CLI) or ``$CLSCATTER_DEVICE`` name a device as ``P:D`` (platform and device
index, as ``clscatter devices`` lists them) or as a case-insensitive substring of
``"platform name / device name"``. An explicit choice is honoured or refused with an
error, never replaced silently. Without one, the first device (GPUs before others) that
passes its probe is used; platforms or devices that fail are skipped, and
``clscatter devices`` shows why."""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DeviceError
from .cache import cache_dir, device_identity
from .kernel_sources import find_source
from .opencl import _cl

ENV_DEVICE = "CLSCATTER_DEVICE"


@dataclass
class DeviceInfo:
    """One OpenCL device as listed by ``clscatter devices``: its indices and names, its
    kind (``cl.device_type`` as a string), whether it passed its probe (``ok``; ``reason``
    says why not) and the pyopencl device (``handle``)."""

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
        """``"P:D platform / device"``, as listed and as a ``--device`` spec matches."""
        return f"{self.platform_index}:{self.device_index} {self.platform} / {self.name}"


def _probe(device) -> str:
    """Build and run probe.cl on ``device``; return '' when it works, else the reason (the
    error's type and first line, or a note that it computed wrong values)."""
    cl = _cl()
    try:
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        probe = find_source("probe.cl")
        src = probe.read_text()
        prog = cl.Program(ctx, src).build(options=["-I", str(probe.parent)], cache_dir=False)
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
    """The JSON file of devices that passed their probe (``{probe key: "ok"}``)."""
    return cache_dir() / "probe.json"


def _probe_key(device) -> str:
    """The key of ``device``'s entry in the probe cache: its :func:`device_identity` and
    the probe source's path (another checkout's probe is another probe)."""
    parts = [*device_identity(device), str(find_source("probe.cl"))]
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:24]


def _cached_probe(device) -> str:
    """:func:`_probe`, remembered across runs for devices that passed (keyed by
    :func:`_probe_key`); ``clscatter devices`` always probes afresh. A device that failed
    is probed again every time (it may have been fixed). An unwritable cache only costs
    probing again."""
    path = _probe_cache_path()
    try:
        ident = _probe_key(device)
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
    """Every platform's devices, in platform then device order (probed afresh when
    ``probe``), and a message for each platform that could not even list its devices.
    Raises :class:`DeviceError` when no OpenCL platform is found."""
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
    """Whether a ``--device`` spec (``P:D`` or a name substring) names ``info``."""
    spec = spec.strip()
    if ":" in spec and all(p.strip().isdigit() for p in spec.split(":", 1)):
        p, d = (int(x) for x in spec.split(":", 1))
        return (info.platform_index, info.device_index) == (p, d)
    return spec.lower() in f"{info.platform} / {info.name}".lower()


def choose_device(spec: str | None = None) -> DeviceInfo:
    """The device to use: ``spec``, else ``$CLSCATTER_DEVICE``, else the first that passes
    its probe (GPUs first). Raises :class:`DeviceError` when the named device does not
    exist or fails its probe, or when no device works (with every device's reason)."""
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
