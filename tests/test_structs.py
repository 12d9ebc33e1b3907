"""Host dtypes agree with the C structs of cl_kernels/: sizes and every field's offset,
measured by a kernel compiled on the device in use, for every registered struct; and every
struct a kernel file declares is either registered or known to live on the device only."""
from __future__ import annotations

import re
from collections import defaultdict

from layout import layout_mismatches

import clscatter.methods  # noqa: F401  (importing the methods registers their structs)
from clscatter.device import kernel_dir, structs


def _registry():
    clscatter.methods.all_methods()
    by_header = defaultdict(dict)
    for cname, (header, dt) in structs.REGISTRY.items():
        by_header[header][cname] = dt
    return by_header


def test_struct_layouts_match(engine):
    for header, dtypes in _registry().items():
        bad = layout_mismatches(engine, header, dtypes)
        assert not bad, f"{header}: struct layout mismatches (struct, field, host, device): {bad}"


def test_every_kernel_struct_has_a_host_twin_or_is_device_only():
    _registry()
    declared = {}
    for path in sorted(kernel_dir().rglob("*.[ch]*")):
        text = re.sub(r"/\*.*?\*/|//[^\n]*", " ", path.read_text(), flags=re.S)
        for m in re.finditer(r"typedef\s+struct\s*\w*\s*\{.*?\}\s*(\w+)\s*;", text, flags=re.S):
            declared[m.group(1)] = path.name
    orphans = {n: f for n, f in declared.items()
               if n not in structs.REGISTRY and n not in structs.DEVICE_ONLY}
    assert not orphans, f"structs with no host dtype (register them, or list as DEVICE_ONLY): {orphans}"
    for name, (header, _) in structs.REGISTRY.items():
        assert declared.get(name) == header, f"{name} is registered for {header}, declared in {declared.get(name)}"


def test_every_struct_is_16_byte_aligned():
    # device arrays of these structs are indexed with the C size: keep them float4-aligned
    for name, dt in structs.ALL.items():
        if name != "BVHNode":
            assert dt.itemsize % 16 == 0, name
    assert structs.BVH_NODE.itemsize == 32
