"""The host side of the device's exact fixed-point sums (``cl_kernels/shared/fixed_sum.h``):
64-bit integer sums in units of ``1 / scale``, which do not depend on the order the
work-items add in. Used where many work-items add into one place: the ray map's splat
(:mod:`.disc_splat`) and line space gathering from the lighting side (:mod:`.line_gather`)."""
from __future__ import annotations

#: no sum reaches 2^FIXED_BITS units (the words hold 64 bits: room for every term's rounding)
FIXED_BITS = 62
#: the least bound a scale is made for, so that the scale stays within float32's range
MIN_BOUND = 1e-18
#: bytes of a view segment's record in lsg's lighting-side sums (lsg.cl, SCATTER_WORDS):
#: its three channels' sums and its valid pairs, within one cache line
SCATTER_BYTES = 32


def fixed_scale(bound: float) -> float:
    """Units per value for sums that are at most ``bound``: 2^FIXED_BITS / bound (the
    bound at least :data:`MIN_BOUND`; a looser bound costs precision, not correctness:
    one unit is ``bound`` / 2^62, about 2e-19 of it)."""
    return 2.0 ** FIXED_BITS / max(float(bound), MIN_BOUND)
