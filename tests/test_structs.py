"""Host dtypes (clscatter/structs.py) agree with the C structs of common.h: sizes and
every field's offset, measured by a kernel compiled on the device in use."""
from __future__ import annotations

from layout import layout_mismatches

from clscatter import structs


def test_struct_layouts_match(engine):
    bad = layout_mismatches(engine, "common.h", structs.ALL)
    assert not bad, f"struct layout mismatches (struct, field, host, device): {bad}"


def test_every_struct_is_16_byte_aligned():
    # device arrays of these structs are indexed with the C size: keep them float4-aligned
    for name, dt in structs.ALL.items():
        if name != "BVHNode":
            assert dt.itemsize % 16 == 0, name
    assert structs.BVH_NODE.itemsize == 32
