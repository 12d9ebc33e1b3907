"""Device primitives (clscatter/transport/primitives.py, cl_kernels/primitives.cl) against NumPy.

Integer results (scan, sort permutations and offsets, compaction, gather) must equal the
NumPy reference exactly. Float segment sums must equal a float32 running sum on the host
bit for bit (the kernel sums in index order without fused multiply-add), stay within the
sequential-summation bound (m + 2) * 2**-24 * sum|terms| of the float64 sum, and be
identical between two runs. Sizes that are not powers of two, empty inputs, single
elements, one bucket holding everything, empty buckets and float ties are all covered.
"""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.transport import primitives as P

SIZES = [0, 1, 3, 1023, 1024, 1025, 4097, 100003]
U = 2.0 ** -24          # float32 unit roundoff


@pytest.fixture
def dev(engine):
    """The engine plus a list of buffers to free after the test."""
    bufs: list = []

    class Dev:
        eng = engine

        @staticmethod
        def up(a: np.ndarray):
            b = engine.to_device(a)
            bufs.append(b)
            return b

        @staticmethod
        def keep(*bs):
            bufs.extend(bs)
            return bs[0] if len(bs) == 1 else bs

    yield Dev
    engine.free(*bufs)


def scan_ref(c: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(c, dtype=np.int64)]).astype(np.int32)


# ---- fill ----

def test_fill_int(dev):
    eng = dev.eng
    buf = dev.keep(eng.zeros(4 * 1030))
    P.fill_int(eng, buf, 1025, -7)
    got = eng.read(buf, 1030, np.int32)
    assert (got[:1025] == -7).all() and (got[1025:] == 0).all()


# ---- exclusive scan ----

@pytest.mark.parametrize("n", SIZES)
def test_exclusive_scan_matches_cumsum(dev, n):
    rng = np.random.default_rng(n)
    c = rng.integers(0, 50, n).astype(np.int32)
    c[rng.random(n) < 0.3] = 0
    off, total = dev.keep(*P.exclusive_scan(dev.eng, dev.up(c), n))
    ref = scan_ref(c)
    assert total == int(ref[-1])
    assert np.array_equal(dev.eng.read(off, n + 1, np.int32), ref)


@pytest.mark.parametrize("n,block,single_max", [(1000, 4, 4), (4097, 2, 3), (100003, 16, 8),
                                                (5, 2, 1)])
def test_exclusive_scan_several_levels(dev, n, block, single_max):
    """Small blocks make the block sums themselves need a blocked scan (host recursion)."""
    rng = np.random.default_rng(7)
    c = rng.integers(0, 1000, n).astype(np.int32)
    off, total = dev.keep(*P.exclusive_scan(dev.eng, dev.up(c), n, block=block,
                                            single_max=single_max))
    assert total == int(c.sum())
    assert np.array_equal(dev.eng.read(off, n + 1, np.int32), scan_ref(c))


def test_exclusive_scan_rejects_blocks_that_cannot_shrink(dev):
    with pytest.raises(ValueError):
        P.exclusive_scan(dev.eng, dev.up(np.ones(5, np.int32)), 5, block=1)


def test_exclusive_scan_two_levels_with_default_blocks(dev):
    """More than SCAN_SINGLE_MAX blocks of SCAN_BLOCK: the default path recurses once."""
    n = P.SCAN_BLOCK * P.SCAN_SINGLE_MAX + 1025
    c = np.random.default_rng(3).integers(0, 100, n).astype(np.int32)
    off, total = dev.keep(*P.exclusive_scan(dev.eng, dev.up(c), n))
    assert total == int(c.sum())
    assert np.array_equal(dev.eng.read(off, n + 1, np.int32), scan_ref(c))


# ---- compaction ----

@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("density", [0.0, 0.01, 0.5, 1.0])
def test_compact_matches_flatnonzero(dev, n, density):
    rng = np.random.default_rng(n + int(density * 100))
    flags = np.where(rng.random(n) < density,
                     rng.choice(np.array([1, -3, 7, 2**31 - 1], np.int32), n), 0).astype(np.int32)
    idx, count = dev.keep(*P.compact(dev.eng, dev.up(flags), n))
    ref = np.flatnonzero(flags)
    assert count == len(ref)
    assert np.array_equal(dev.eng.read(idx, count, np.int32), ref)


# ---- bucket sort ----

def _fkeys(kind: str, n: int, rng) -> np.ndarray | None:
    if kind == "none":
        return None
    if kind == "ties":              # few distinct values: most comparisons fall to the index
        return rng.integers(-2, 3, n).astype(np.float32) * np.float32(0.5)
    return rng.standard_normal(n).astype(np.float32)


def _sort_ref(keys: np.ndarray, nkeys: int, fkey: np.ndarray | None):
    n = len(keys)
    perm = (np.argsort(keys, kind="stable") if fkey is None
            else np.lexsort((np.arange(n), fkey, keys)))
    offsets = scan_ref(np.bincount(keys, minlength=nkeys)[:nkeys] if n else np.zeros(nkeys, int))
    return perm.astype(np.int32), offsets


def _run_sort(dev, keys, nkeys, fkey):
    n = len(keys)
    kb = dev.up(keys)
    fb = dev.up(fkey) if fkey is not None else None
    perm, off = dev.keep(*P.bucket_sort(dev.eng, kb, n, nkeys, fb))
    return dev.eng.read(perm, n, np.int32), dev.eng.read(off, nkeys + 1, np.int32)


@pytest.mark.parametrize("n,nkeys", [(0, 1), (0, 5), (1, 1), (1, 7), (3, 2), (1023, 1),
                                     (1025, 3), (4097, 5000), (100003, 37), (100003, 60000),
                                     (100003, 1)])
@pytest.mark.parametrize("fkind", ["none", "ties", "random"])
def test_bucket_sort_matches_lexsort(dev, n, nkeys, fkind):
    """Many and few buckets, empty buckets (nkeys > n), one bucket holding every element
    (the heapsort path on a long run), ties in the float key: the permutation is NumPy's
    exactly, and the same on a second run (atomic order never shows)."""
    rng = np.random.default_rng(n * 31 + nkeys)
    keys = rng.integers(0, nkeys, n).astype(np.int32)
    fkey = _fkeys(fkind, n, rng)
    perm, off = _run_sort(dev, keys, nkeys, fkey)
    ref_perm, ref_off = _sort_ref(keys, nkeys, fkey)
    assert np.array_equal(off, ref_off)
    assert np.array_equal(perm, ref_perm)
    perm2, off2 = _run_sort(dev, keys, nkeys, fkey)
    assert np.array_equal(perm2, perm) and np.array_equal(off2, off)


def test_bucket_sort_special_floats_follow_numpy(dev):
    """-0.0 ties with 0.0; NaNs of either sign and any payload sort after +inf and tie
    with each other; subnormals and infinities in their places."""
    special = np.array([np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, -1e-45, 1.0,
                        -1.0, 3.4e38, -3.4e38], np.float32)
    payload = np.array([0x7fc00123, 0xffc00001, 0x7f800001], np.uint32).view(np.float32)
    pool = np.concatenate([special, payload])
    rng = np.random.default_rng(11)
    for n, nkeys in [(40, 1), (4097, 3), (4097, 700)]:
        keys = rng.integers(0, nkeys, n).astype(np.int32)
        fkey = rng.choice(pool, n)
        perm, off = _run_sort(dev, keys, nkeys, fkey)
        ref_perm, ref_off = _sort_ref(keys, nkeys, fkey)
        assert np.array_equal(off, ref_off)
        assert np.array_equal(perm, ref_perm)


def test_bucket_sort_clamps_out_of_range_keys(dev):
    """Documented behaviour for a caller's bug: keys < 0 join bucket 0, keys >= nkeys join
    the last bucket, and perm stays a permutation."""
    rng = np.random.default_rng(5)
    n, nkeys = 1025, 9
    keys = rng.integers(-4, nkeys + 4, n).astype(np.int32)
    keys[:2] = [np.iinfo(np.int32).min, np.iinfo(np.int32).max]
    perm, off = _run_sort(dev, keys, nkeys, None)
    ref_perm, ref_off = _sort_ref(np.clip(keys, 0, nkeys - 1), nkeys, None)
    assert np.array_equal(off, ref_off) and np.array_equal(perm, ref_perm)


def test_bucket_sort_needs_a_bucket(dev):
    with pytest.raises(ValueError):
        P.bucket_sort(dev.eng, dev.up(np.zeros(3, np.int32)), 3, 0)


# ---- segment sums ----

def _segments(nout: int, m: int, rng) -> np.ndarray:
    """nout + 1 sorted offsets over m entries, with empty runs and a long one."""
    cuts = np.sort(rng.integers(0, m + 1, max(nout - 1, 0)))
    return np.concatenate([[0], cuts, [m]]).astype(np.int32) if nout else np.zeros(1, np.int32)


def _sum_refs(values, offsets, weights):
    terms = values if weights is None else values * weights[:, None]      # float32 products
    nout = len(offsets) - 1
    ref32 = np.zeros((nout, 4), np.float32)
    ref64 = np.zeros((nout, 4))
    bound = np.zeros((nout, 4))
    for s in range(nout):
        lo, hi = offsets[s], offsets[s + 1]
        if hi > lo:
            ref32[s] = np.cumsum(terms[lo:hi], axis=0, dtype=np.float32)[-1]   # sequential
            t64 = values[lo:hi].astype(np.float64)
            if weights is not None:
                t64 = t64 * weights[lo:hi, None]
            ref64[s] = t64.sum(axis=0)
            bound[s] = (hi - lo + 2) * U * np.abs(t64).sum(axis=0)
    return ref32, ref64, bound


@pytest.mark.parametrize("nout,m", [(0, 0), (1, 0), (1, 1), (1, 100003), (7, 3), (1000, 4097),
                                    (3000, 1025), (1025, 100003)])
@pytest.mark.parametrize("weighted", [False, True])
def test_segment_sums(dev, nout, m, weighted):
    rng = np.random.default_rng(nout * 7 + m)
    values = rng.standard_normal((m, 4)).astype(np.float32)
    weights = rng.random(m).astype(np.float32) if weighted else None
    offsets = _segments(nout, m, rng)
    eng = dev.eng
    vb, ob = dev.up(values), dev.up(offsets)
    wb = dev.up(weights) if weighted else None
    out1 = eng.read(dev.keep(P.segment_sums(eng, vb, ob, nout, wb)), (nout, 4), np.float32)
    out2 = eng.read(dev.keep(P.segment_sums(eng, vb, ob, nout, wb)), (nout, 4), np.float32)
    ref32, ref64, bound = _sum_refs(values, offsets, weights)
    assert np.array_equal(out1.view(np.uint32), out2.view(np.uint32))     # deterministic
    assert np.array_equal(out1, ref32)                                      # running sum
    assert (np.abs(out1 - ref64) <= bound).all()


# ---- gather ----

@pytest.mark.parametrize("itemsize", [4, 12, 16, 64, 80])
@pytest.mark.parametrize("n", [0, 1, 1025])
def test_gather_records(dev, itemsize, n):
    """Random indices with repeats plus out-of-range ones (-1, nsrc): those give zeros."""
    rng = np.random.default_rng(itemsize + n)
    words = itemsize // 4
    nsrc = 777
    src = rng.integers(0, 2**32, (nsrc, words), dtype=np.uint64).astype(np.uint32)
    index = rng.integers(0, nsrc, n).astype(np.int32)
    if n > 2:
        index[:2] = [-1, nsrc]
    dst = dev.keep(P.gather(dev.eng, dev.up(src), dev.up(index), n, itemsize))
    got = dev.eng.read(dst, (n, words), np.uint32)
    ok = (index >= 0) & (index < nsrc)
    ref = np.zeros((n, words), np.uint32)
    ref[ok] = src[index[ok]]
    assert np.array_equal(got, ref)


def test_gather_rejects_odd_itemsize(dev):
    with pytest.raises(ValueError):
        P.gather(dev.eng, dev.up(np.zeros(8, np.int32)), dev.up(np.zeros(2, np.int32)), 2, 6)


# ---- the pipeline they exist for ----

def test_sort_gather_accumulate_equals_per_pixel_sums(dev):
    """Segments with a pixel key and a depth: bucket_sort by (pixel, depth), gather the
    64-byte records into that order, sum their radiance per pixel. Equals the NumPy
    per-pixel sums in depth order, bit for bit as float32 running sums."""
    rng = np.random.default_rng(2024)
    n, npix = 50021, 3001
    rec = np.dtype([("radiance", np.float32, 4), ("depth", np.float32), ("pixel", np.int32),
                    ("pad", np.int32, 10)])
    assert rec.itemsize == 64
    segs = np.zeros(n, rec)
    segs["radiance"] = rng.random((n, 4)).astype(np.float32)
    segs["depth"] = rng.integers(0, 50, n).astype(np.float32)
    segs["pixel"] = rng.integers(0, npix, n)
    eng = dev.eng
    perm, off = dev.keep(*P.bucket_sort(eng, dev.up(segs["pixel"].copy()), n, npix,
                                        dev.up(segs["depth"].copy())))
    sorted_buf = dev.keep(P.gather(eng, dev.up(segs), perm, n, 64))
    got_recs = eng.read(sorted_buf, n, rec)
    order = np.lexsort((np.arange(n), segs["depth"], segs["pixel"]))
    assert np.array_equal(got_recs, segs[order])
    rad = dev.up(np.ascontiguousarray(got_recs["radiance"]))
    pix = eng.read(dev.keep(P.segment_sums(eng, rad, off, npix)), (npix, 4), np.float32)
    ref32, ref64, bound = _sum_refs(segs["radiance"][order], eng.read(off, npix + 1, np.int32),
                                    None)
    assert np.array_equal(pix, ref32)
    assert (np.abs(pix - ref64) <= bound).all()


def test_no_scratch_left_behind(dev):
    """Every temporary is freed: after freeing the results, live bytes are as before."""
    eng = dev.eng
    keys, flags = dev.up(np.arange(5000, dtype=np.int32) % 13), dev.up(np.ones(5000, np.int32))
    before = eng.bytes_live
    perm, off = P.bucket_sort(eng, keys, 5000, 13)
    scan, _ = P.exclusive_scan(eng, keys, 5000, block=8, single_max=8)
    kept, _ = P.compact(eng, flags, 5000)
    eng.free(perm, off, scan, kept)
    assert eng.bytes_live == before


@pytest.mark.parametrize("n,lanes", [(0, 1), (1, 1), (3, 2), (255, 2), (256, 1), (257, 3),
                                     (100003, 2)])
def test_int_totals_match_int64_sums(dev, n, lanes):
    """Totals of interleaved int32 counters equal NumPy's int64 sums, including totals
    past 2**31 (large values) and negative entries; empty input gives zeros."""
    rng = np.random.default_rng(n + lanes)
    vals = rng.integers(-1000, 2**30, size=(max(n, 1), lanes), dtype=np.int64).astype(np.int32)
    buf = dev.up(vals)
    got = P.int_totals(dev.eng, buf, n, lanes)
    want = vals[:n].astype(np.int64).sum(axis=0) if n else np.zeros(lanes, np.int64)
    assert got.dtype == np.int64 and got.shape == (lanes,)
    np.testing.assert_array_equal(got, want)
    if n >= 255:
        assert want.max() > 2**31          # the test reaches past int32
