"""Helper for struct-layout tests: compare NumPy dtypes with C structs on the device."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from clscatter.device import kernel_dirs


def layout_mismatches(engine, header: str, dtypes: dict[str, np.dtype]) -> list[tuple]:
    """Build a kernel that includes ``header`` and reports sizeof/offsetof of every struct
    in ``dtypes`` (C name -> dtype); return (struct, field, host, device) mismatches."""
    lines = [f'#include "{header}"', "__kernel void layout(__global int *out) {"]
    expected = []
    for cname, dt in dtypes.items():
        var = f"v_{cname}"
        lines.append(f"  {cname} {var};")
        lines.append(f"  out[{len(expected)}] = (int)sizeof({cname});")
        expected.append((cname, "sizeof", dt.itemsize))
        for field in dt.names:
            lines.append(f"  out[{len(expected)}] = (int)((__private char *)&{var}.{field} - "
                         f"(__private char *)&{var});")
            expected.append((cname, field, dt.fields[field][1]))
    lines.append("}")
    prog = cl.Program(engine.ctx, "\n".join(lines)).build(options=[o for d in kernel_dirs() for o in ("-I", str(d))])
    out = cl.Buffer(engine.ctx, cl.mem_flags.WRITE_ONLY, 4 * len(expected))
    prog.layout(engine.queue, (1,), None, out)
    got = np.empty(len(expected), np.int32)
    cl.enqueue_copy(engine.queue, got, out)
    return [(c, f, e, int(g)) for (c, f, e), g in zip(expected, got) if e != g]
