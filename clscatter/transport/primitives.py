"""Device primitives: scan, bucket sort, compaction, segmented sums, gather, int totals.

Thin host wrappers over ``cl_kernels/primitives.cl`` so that the renderer's hot path can
sort, bucket, compact and accumulate per-sample arrays without reading them back into
NumPy. Every function takes device buffers, returns NEW device buffers (allocated with
``eng.empty``, so they count towards ``eng.bytes_peak``; the caller frees them with
``eng.free``) and reads back at most one int.

Guarantees
    Results are deterministic: the same inputs give the same bits on every run, whatever
    order the atomics of the bucket sort ran in (each bucket is sorted afterwards by a
    key that is unique per element), and float sums are sequential in index order with
    no fused multiply-add (``FP_CONTRACT OFF``), i.e. equal to a float32 running sum on
    the host.

Limits
    Sizes and every total (a scan's sum, an offset) must fit in int32 (< 2**31); int32
    overflow is not detected. Kernels use only OpenCL 1.2 features, plain ``__global``
    buffers (no local memory), no recursion. Per-bucket / per-segment work is one
    work-item each, so a very long bucket or segment is sequential (the bucket sort is
    still O(m log m) for one bucket of m elements: heapsort).
"""
from __future__ import annotations

import numpy as np

from ..device import Engine

PROGRAM = "primitives"
SCAN_BLOCK = 1024           # entries scanned sequentially by one work-item
SCAN_SINGLE_MAX = 4096      # block sums scanned by one work-item up to this many blocks
_GROUP = 64                 # global sizes are rounded up to this (kernels guard the tail)


def _padded(n: int) -> int:
    """``n`` rounded up to a multiple of 64: a prime global size would make drivers
    choose work-groups of one item."""
    return -(-int(n) // _GROUP) * _GROUP


def _read_int(eng: Engine, buf, index: int) -> int:
    """Element ``index`` of an int32 device buffer (one 4-byte read)."""
    return int(eng.read(buf, 1, np.int32, offset=4 * int(index))[0])


def fill_int(eng: Engine, buf, n: int, value: int) -> None:
    """Set the first ``n`` int32 entries of ``buf`` to ``value``."""
    eng.call(PROGRAM, "fill_int", _padded(n), buf=buf, n=n, value=value)


def _scan(eng: Engine, src, n: int, nonzero: bool, block: int, single_max: int):
    """Exclusive scan of ``src`` (or of ``src != 0`` when ``nonzero``) into a new buffer
    of ``n + 1`` int32; returns (buffer, total)."""
    n = int(n)
    out = eng.empty(4 * (n + 1))
    if n == 0:
        fill_int(eng, out, 1, 0)
        return out, 0
    nblocks = -(-n // block)
    sums = eng.empty(4 * nblocks)
    eng.call(PROGRAM, "scan_blocks", _padded(nblocks), src=src, n=n, block=block,
             nonzero=int(bool(nonzero)), out=out, block_sums=sums)
    if nblocks <= single_max:
        block_offsets = eng.empty(4 * (nblocks + 1))
        eng.call(PROGRAM, "scan_single", 1, src=sums, n=nblocks, dst=block_offsets)
    else:                   # too many blocks for one work-item: scan the sums in blocks
        block_offsets, _ = _scan(eng, sums, nblocks, False, block, single_max)
    eng.call(PROGRAM, "scan_add", _padded(n + 1), out=out, n=n, block=block,
             block_offsets=block_offsets)
    eng.free(sums, block_offsets)
    return out, _read_int(eng, out, n)


def exclusive_scan(eng: Engine, counts, n: int, *, block: int = SCAN_BLOCK,
                   single_max: int = SCAN_SINGLE_MAX):
    """Exclusive prefix sum of ``n`` int32 ``counts`` on the device.

    Returns ``(offsets, total)``: a new buffer of ``n + 1`` int32 with ``offsets[0] = 0``
    and ``offsets[i + 1] = offsets[i] + counts[i]``, and ``total = offsets[n]`` read back.
    Three passes: one work-item per ``block`` entries scans them sequentially, the block
    sums are scanned by one work-item (or, beyond ``single_max`` blocks, by this same
    function on the host side: a Python recursion, log_block(n) levels deep), and every
    entry adds its block's offset. ``block``/``single_max`` are tuning knobs (tests use
    small ones to exercise several levels); ``block >= 2`` and ``single_max >= 1``.
    """
    if block < 2 or single_max < 1:
        raise ValueError(f"exclusive_scan: need block >= 2 and single_max >= 1, got "
                         f"block={block}, single_max={single_max}")
    return _scan(eng, counts, n, False, int(block), int(single_max))


def compact(eng: Engine, flags, n: int):
    """The indices ``i`` with ``flags[i] != 0`` (``n`` int32 flags), in increasing order.

    Returns ``(indices, count)``: a new int32 buffer (room for at least one entry, so it
    is valid even when ``count == 0``) and the number kept. Built from a scan of
    ``flags != 0``, so the order is the index order without sorting.
    """
    n = int(n)
    offsets, count = _scan(eng, flags, n, True, SCAN_BLOCK, SCAN_SINGLE_MAX)
    out = eng.empty(4 * max(count, 1))
    eng.call(PROGRAM, "compact_write", _padded(n), flags=flags, offsets=offsets, n=n, out=out)
    eng.free(offsets)
    return out, count


def bucket_sort(eng: Engine, keys, n: int, nkeys: int, fkey=None):
    """Group ``n`` elements by their int32 ``keys`` in ``[0, nkeys)``; returns
    ``(perm, offsets)``.

    ``perm`` (``n`` int32) lists the original indices by increasing key; ``offsets``
    (``nkeys + 1`` int32) is where each key's run starts in ``perm``, ``offsets[nkeys] =
    n``. Within a key the order is by ``(fkey[i], i)`` when ``fkey`` (``n`` float32) is
    given, else by ``i``, so ``perm`` equals ``np.lexsort((np.arange(n), fkey, keys))``
    (``np.argsort(keys, kind="stable")`` without ``fkey``) exactly, every run.

    Float keys follow NumPy's sort order: ``-0.0`` ties with ``0.0``; NaN (any sign or
    payload) sorts after every number, ``+inf`` included, and NaNs tie with each other.
    Keys outside ``[0, nkeys)`` are a caller's bug; they are clamped (negative keys join
    bucket 0, keys ``>= nkeys`` join bucket ``nkeys - 1``), so ``perm`` is still a
    permutation. ``nkeys`` must be >= 1 unless ``n == 0``.

    Device memory: 8 bytes per element of scratch besides the results. Cost: a histogram
    and a scatter with 32-bit atomics, a scan, and one work-item per bucket sorting its
    run (insertion sort up to 24 elements, heapsort above).
    """
    n, nkeys = int(n), int(nkeys)
    if nkeys < 1 and n > 0:
        raise ValueError(f"bucket_sort: nkeys must be >= 1 for n = {n} elements")
    nkeys = max(nkeys, 0)
    perm = eng.empty(4 * max(n, 1))
    if n == 0:
        offsets = eng.zeros(4 * (nkeys + 1))
        return perm, offsets
    counts = eng.zeros(4 * nkeys)
    eng.call(PROGRAM, "bucket_histogram", _padded(n), keys=keys, n=n, nkeys=nkeys,
             counts=counts)
    offsets, _ = exclusive_scan(eng, counts, nkeys)
    cursor = counts                                   # reused: cursor[k] = offsets[k]
    eng.cl.enqueue_copy(eng.queue, cursor, offsets, byte_count=4 * nkeys)
    slots = eng.empty(8 * n)
    eng.call(PROGRAM, "bucket_scatter", _padded(n), keys=keys,
             fkey=fkey if fkey is not None else keys, use_fkey=int(fkey is not None),
             n=n, nkeys=nkeys, cursor=cursor, slots=slots)
    eng.call(PROGRAM, "bucket_sort_runs", _padded(nkeys), slots=slots, offsets=offsets,
             nkeys=nkeys, perm=perm)
    eng.free(counts, slots)
    return perm, offsets


def segment_sums(eng: Engine, values, offsets, nout: int, weights=None):
    """Per-run sums of float4 ``values``: ``out[i] = sum(values[j] (* weights[j]))`` over
    ``j`` in ``[offsets[i], offsets[i + 1])``.

    ``offsets`` holds ``nout + 1`` non-decreasing int32 (e.g. from :func:`bucket_sort`);
    ``weights`` an optional float32 buffer indexed like ``values``. Returns a new buffer
    of ``nout`` float4 (zero for an empty run). Each run is summed by one work-item in
    index order, product then sum rounded separately, so the result is bit-for-bit a
    float32 running sum (deterministic; error at most about ``m * 2**-24 * sum|terms|``
    for a run of ``m``).
    """
    nout = int(nout)
    out = eng.empty(16 * max(nout, 1))
    eng.call(PROGRAM, "segment_sums", _padded(nout), values=values,
             weights=weights if weights is not None else values,
             use_weights=int(weights is not None), offsets=offsets, nout=nout, out=out)
    return out


def gather(eng: Engine, src, index, n: int, itemsize: int):
    """``dst[i] = src[index[i]]`` for ``n`` records of ``itemsize`` bytes (a multiple of 4).

    Records are copied as 32-bit words, so any struct layout works (e.g. 64-byte
    segments permuted by a :func:`bucket_sort` ``perm``); records of whole 16-byte quads
    go one record per work-item (``gather_quads``, ~3x faster on the CPU device). An index
    outside the records that ``src`` holds (its byte size // ``itemsize``) gives an all-zero record. Returns a
    new buffer of ``n * itemsize`` bytes.
    """
    n, itemsize = int(n), int(itemsize)
    if itemsize <= 0 or itemsize % 4:
        raise ValueError(f"gather: itemsize must be a positive multiple of 4, got {itemsize}")
    words = itemsize // 4
    nsrc = min(int(src.size) // itemsize, 2**31 - 1)
    dst = eng.empty(max(n * itemsize, 4))
    if itemsize % 16 == 0:
        eng.call(PROGRAM, "gather_quads", _padded(n), src=src, nsrc=nsrc,
                 index=index, n=n, quads=itemsize // 16, dst=dst)
    else:
        eng.call(PROGRAM, "gather_words", _padded(n * words), src=src, nsrc=nsrc, index=index,
                 n=n, words=words, dst=dst)
    return dst


INT_TOTAL_GROUPS = 256      # partial sums read back by int_totals


def int_totals(eng: Engine, values, n: int, lanes: int = 1) -> np.ndarray:
    """Totals of int32 counters on the device: ``values`` holds ``n`` records of
    ``lanes`` interleaved int32 (e.g. per-segment (boxes, photons) statistics); returns the
    ``lanes`` totals as int64, exact (64-bit partial sums, so no int32 overflow). Reads back
    at most 256 partials per lane instead of the ``n`` records."""
    n, lanes = int(n), max(1, int(lanes))
    if n <= 0:
        return np.zeros(lanes, np.int64)
    groups = min(INT_TOTAL_GROUPS, n)
    per = -(-n // groups)
    groups = -(-n // per)
    partial = eng.empty(8 * groups * lanes)
    try:
        eng.call(PROGRAM, "int_totals", _padded(groups), values=values, n=n, lanes=lanes,
                 per=per, groups=groups, partial=partial)
        return eng.read(partial, (groups, lanes), np.int64).sum(axis=0)
    finally:
        eng.free(partial)
