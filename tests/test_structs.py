"""Host dtypes (clscatter/structs.py) agree with the C structs of common.h: sizes and
every field's offset, measured by a kernel compiled on the device in use."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from clscatter import structs
from clscatter.device import kernel_dir


def _layout_source() -> tuple[str, list[tuple[str, str, int]]]:
    lines = ['#include "common.h"', "__kernel void layout(__global int *out) {"]
    expected = []
    for cname, dt in structs.ALL.items():
        var = f"v_{cname}"
        lines.append(f"  {cname} {var};")
        lines.append(f"  out[{len(expected)}] = (int)sizeof({cname});")
        expected.append((cname, "sizeof", dt.itemsize))
        for field in dt.names:
            lines.append(f"  out[{len(expected)}] = (int)((__private char *)&{var}.{field} - "
                         f"(__private char *)&{var});")
            expected.append((cname, field, dt.fields[field][1]))
    lines.append("}")
    return "\n".join(lines), expected


def test_struct_layouts_match(engine):
    src, expected = _layout_source()
    prog = cl.Program(engine.ctx, src).build(options=["-I", str(kernel_dir())])
    out = cl.Buffer(engine.ctx, cl.mem_flags.WRITE_ONLY, 4 * len(expected))
    prog.layout(engine.queue, (1,), None, out)
    got = np.empty(len(expected), np.int32)
    cl.enqueue_copy(engine.queue, got, out)
    mismatches = [(c, f, e, int(g)) for (c, f, e), g in zip(expected, got) if e != g]
    assert not mismatches, f"struct layout mismatches (struct, field, host, device): {mismatches}"


def test_every_struct_is_16_byte_aligned():
    # device arrays of these structs are indexed with the C size: keep them float4-aligned
    for name, dt in structs.ALL.items():
        if name != "BVHNode":
            assert dt.itemsize % 16 == 0, name
    assert structs.BVH_NODE.itemsize == 32
