"""The epipolar segment lookup's per-sample kernels (epipolar.cl: epi_ring, epi_split,
epi_view_ranges, epi_view_nodes, epi_event_keys + bucket sort + epi_events,
epi_sample_values, epi_weighted) against NumPy versions of the same maths: the host code
they replaced (pipeline.ring_weights, svd.node_extremes, the argsort of the events)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from clscatter.device import structs
from clscatter.methods.epipolar import geometry as geo_mod
from clscatter.methods.epipolar.pipeline import (
    DeviceViews,
    HostViews,
    LiveSamples,
    _segment_events,
    merged_offsets,
    ring_weights,
)
from clscatter.methods.epipolar.svd import REF_NODES

DEFS = {"EPI_NT": 4, "EPI_NCH": 3}


def _segments(rng, n, deep_fraction=0.3):
    s = np.zeros(n, structs.VIEW_SEGMENT)
    s["depth"] = (rng.random(n) < deep_fraction).astype(np.int32)
    s["weight"][:, :3] = rng.uniform(0.1, 1.0, (n, 3))
    s["sample"] = np.arange(n)
    return s


def _samples(rng, n, S, equal_beta=False):
    """geo = (beta, gamma_a, gamma_b, t_a), idx = (k0, k1, f bits, 0)."""
    geo = rng.uniform(0.0, 1.0, (n, 4)).astype(np.float32)
    geo[:, 0] = 0.7 if equal_beta else rng.uniform(0.0, math.pi, n)
    geo[:, 3] = rng.uniform(0.0, 5.0, n)
    idx = np.zeros((n, 4), np.int32)
    idx[:, 0] = rng.integers(0, S, n)
    idx[:, 1] = np.minimum(idx[:, 0] + rng.integers(0, 2, n), S - 1)
    f = rng.uniform(0.0, 1.0, n).astype(np.float32)
    f[rng.random(n) < 0.1] = 0.0          # weight-0 second events
    f[rng.random(n) < 0.05] = 1.0         # weight-0 first events
    idx[:, 2] = f.view(np.int32)
    return geo, idx


def _live(engine, geo_buf, idx_buf, live_idx):
    buf = engine.to_device(np.asarray(live_idx, np.int32))
    return LiveSamples(engine, buf, len(live_idx), 0, 0, geo_buf, idx_buf)


@pytest.mark.parametrize("front", [True, False])
@pytest.mark.parametrize("radius,band", [(0.05, 1.0), (0.3, 0.5), (0.0, 1.0), (0.1, 0.0)])
def test_ring_kernel_matches_ring_weights(engine, front, radius, band):
    """epi_ring's weights equal pipeline.ring_weights for primary segments (within 2e-5:
    the float32 angle pi - beta rounds by 2.4e-7, times the smoothstep's slope 1.5 / band
    width = 30 at the narrowest band here) and are 0 for deeper ones; live = primary and
    w < 1; the counts match."""
    rng = np.random.default_rng(3)
    n = 5003
    segs = _segments(rng, n)
    geo, _ = _samples(rng, n, 7)
    geo[:5, 0] = [0.0, radius, radius * (1 + band), math.pi - radius, math.pi]   # edges
    sb, gb = engine.to_device(segs), engine.to_device(geo)
    wr, flags, counts = engine.empty(4 * n), engine.empty(4 * n), engine.zeros(8)
    try:
        engine.call("epipolar", "epi_ring", n, DEFS, segs=sb, geo=gb, n=n, front=int(front),
                    radius=radius, outer=radius * (1 + band), wr=wr, live_flag=flags,
                    counts=counts)
        got = engine.read(wr, n, np.float32)
        live = engine.read(flags, n, np.int32)
        ring, in_band = engine.read(counts, 2, np.int32)
    finally:
        engine.free(sb, gb, wr, flags, counts)
    primary = segs["depth"] == 0
    ref = np.where(primary, ring_weights(geo[:, 0], front, radius, band), 0.0)
    np.testing.assert_allclose(got, ref, atol=2e-5)
    # where float32 and float64 agree on the side of 0 and 1 (not on a boundary)
    clear = (np.abs(ref - 1.0) > 1e-5) & ((ref > 1e-5) | (ref == 0.0))
    assert np.array_equal(live[clear].astype(bool), (primary & (ref < 1.0))[clear])
    assert abs(ring - int((primary & (ref > 0)).sum())) <= 2
    assert abs(in_band - int((primary & (ref > 0) & (ref < 1)).sum())) <= 2
    if radius == 0.0:
        assert ring == 0 and np.all(got == 0.0)


def test_split_and_weighted(engine):
    """epi_split's scales and count; epi_weighted multiplies by each segment's rgb weight."""
    rng = np.random.default_rng(5)
    n = 1001
    segs = _segments(rng, n)
    vals = rng.uniform(0.0, 2.0, (n, 4)).astype(np.float32)
    sb, vb = engine.to_device(segs), engine.to_device(vals)
    p, d, c, w = engine.empty(4 * n), engine.empty(4 * n), engine.zeros(4), engine.empty(16 * n)
    try:
        engine.call("epipolar", "epi_split", n, segs=sb, n=n, primary=p, deeper=d, counts=c)
        engine.call("epipolar", "epi_weighted", n, values=vb, segs=sb, n=n, weighted=w)
        prim_, deep, cnt = (engine.read(p, n, np.float32), engine.read(d, n, np.float32),
                            int(engine.read(c, 1, np.int32)[0]))
        weighted = engine.read(w, (n, 4), np.float32)
    finally:
        engine.free(sb, vb, p, d, c, w)
    assert np.array_equal(deep, (segs["depth"] > 0).astype(np.float32))
    assert np.array_equal(prim_, 1.0 - deep)
    assert cnt == int((segs["depth"] > 0).sum())
    np.testing.assert_allclose(weighted[:, :3], vals[:, :3] * segs["weight"][:, :3], rtol=1e-6)
    assert np.all(weighted[:, 3] == 0.0)


def test_primary_samples_are_the_ring_free_live_list(engine):
    """Out of view, the ring leaves the live list at every primary segment: the derived
    list (the split's primary weights compacted, built once) equals what epi_ring and its
    compaction give with a ring no sample reaches, and NumPy's."""
    from clscatter.methods.epipolar.pipeline import _live_samples, _primary_samples
    from clscatter.transport.view_paths import ViewPaths
    rng = np.random.default_rng(8)
    n = 1000
    segs = _segments(rng, n)
    dev = ViewPaths(None, None, segs).on_device(engine, 10, 10)
    geo, idx = _samples(rng, n, 7)
    geo[:, 0] = rng.uniform(0.5, 3.0, n)          # all beyond a ring of 0.1 rad
    gb, ib, wr = engine.to_device(geo), engine.to_device(idx), engine.zeros(4 * n)
    bufs = []
    try:
        ring = _live_samples(engine, dev, gb, ib, wr, True, 0.1, 1.0, DEFS, bufs)
        prim_ = _primary_samples(engine, dev, gb, ib, DEFS)
        again = _primary_samples(engine, dev, gb, ib, DEFS)
        want = np.flatnonzero(segs["depth"] == 0)
        assert prim_.count == ring.count == len(want) and (ring.ring, ring.band) == (0, 0)
        assert np.array_equal(engine.read(prim_.buf, prim_.count, np.int32), want)
        assert np.array_equal(engine.read(ring.buf, ring.count, np.int32), want)
        assert again.buf is prim_.buf                # derived once per set of segments
        assert np.all(engine.read(wr, n, np.float32) == 0.0)
    finally:
        engine.free(gb, ib, wr, *bufs)
        dev.release()


def _host_events(geo, idx, live, S):
    """The runs as NumPy builds them: the live samples ordered by first slice k0, then
    beta (NaN last), then live index; each slice's run offsets."""
    L = len(live)
    k0 = idx[live, 0]
    order = np.lexsort((np.arange(L), geo[live, 0], k0))
    off = np.zeros(S + 1, np.int64)
    off[1:] = np.cumsum(np.bincount(k0, minlength=S))
    return geo[live[order]], off, order


@pytest.mark.parametrize("n,S,L,equal,bins", [(2000, 37, 1500, False, None), (1, 3, 1, False, None),
                                              (500, 5, 0, False, None), (3001, 11, 3001, True, 7),
                                              (1025, 1, 700, False, 1), (4000, 9, 3900, False, 97),
                                              (2000, 37, 1500, False, 1024)])
def test_events_match_host_sort(engine, n, S, L, equal, bins):
    """epi_event_keys + bucket_sort + epi_events give the host's runs in the host's
    order, the run offsets, and inv (the place of each live sample in the runs): empty,
    one sample, one slice, all betas equal, sizes not powers of 2, one bin per slice up to
    1024 (betas beyond a slice's range, a zero range, +-inf and NaN betas land in its
    first or last bin)."""
    rng = np.random.default_rng(n + S)
    geo, idx = _samples(rng, n, S, equal)
    if n > 100 and not equal:
        geo[rng.choice(n, 5, replace=False), 0] = [np.nan, np.inf, -np.inf, -1.0, 9.0]
    live = np.sort(rng.choice(n, L, replace=False)).astype(np.int32)
    table = np.zeros(S, geo_mod.EPI_SLICE)
    table["beta_lo"] = rng.uniform(0.0, 1.0, S)
    table["beta_hi"] = table["beta_lo"] + rng.uniform(0.5, 2.5, S)
    table["beta_hi"][0] = table["beta_lo"][0]              # a zero range
    gb, ib, sb = engine.to_device(geo), engine.to_device(idx), engine.to_device(table)
    lv = _live(engine, gb, ib, live)
    bufs: list = []
    try:
        ev, offs, inv, off = _segment_events(engine, gb, ib, lv, S, DEFS, bufs, sb, bins)
        got = engine.read(ev, (L, 4), np.float32)
        inv_h = engine.read(inv, L, np.int32)
        off_dev = engine.read(offs, S + 1, np.int32)
    finally:
        engine.free(gb, ib, sb, lv.buf, *bufs)
    ref, ref_off, order = _host_events(geo, idx, live, S)
    assert np.array_equal(off, ref_off) and np.array_equal(off_dev, ref_off)
    assert np.array_equal(got, ref, equal_nan=True)
    want = np.zeros(L, np.int64)
    want[order] = np.arange(L)
    assert np.array_equal(inv_h, want)


@pytest.mark.parametrize("full", [False, True])
def test_merged_offsets(full):
    """Where each slice's sweep starts: slice k sweeps run k and run k - 1 (the last run
    for slice 0 of a full fan, none for an open one)."""
    off = np.array([0, 3, 3, 10, 12])
    runs = np.diff(off)
    per = [runs[k] + (runs[k - 1] if k > 0 else (runs[-1] if full else 0)) for k in range(4)]
    assert np.array_equal(merged_offsets(off, full), np.concatenate([[0], np.cumsum(per)]))
    assert np.array_equal(merged_offsets(np.zeros(1, np.int32), full), [0])


@pytest.mark.parametrize("G", [1, 16])
def test_view_reductions_match_host(engine, G):
    """epi_view_ranges / epi_view_nodes (atomics on float bits) equal HostViews (NumPy):
    each group's beta range over the live samples touching it, and the least t_a per
    envelope node; a group no sample touches has no range."""
    rng = np.random.default_rng(G)
    n, S = 4000, 40
    geo, idx = _samples(rng, n, S)
    idx[:, 0] = np.where(idx[:, 0] < 10, 20, idx[:, 0])     # slices 0..9: no sample
    idx[:, 1] = np.maximum(idx[:, 1], idx[:, 0])
    live = np.sort(rng.choice(n, 3000, replace=False)).astype(np.int32)
    gb, ib, lb = engine.to_device(geo), engine.to_device(idx), engine.to_device(live)
    try:
        dv = DeviceViews(engine, gb, ib, lb, len(live), S, DEFS)
        hv = HostViews(idx[live, 0], idx[live, 1], geo[live, 0].astype(np.float64),
                       geo[live, 3].astype(np.float64), S)
        r_dev, r_host = dv.ranges(G), hv.ranges(G)
        assert r_dev == r_host
        if G == 16:
            assert r_host[0] is None             # slices 0..2: untouched
        brs = [r if r is not None else (0.0, 1.0) for r in r_host]
        nd, nh = dv.nodes(G, brs), hv.nodes(G, brs)
    finally:
        engine.free(gb, ib, lb)
    assert nd.shape == (G, REF_NODES)
    assert np.array_equal(np.isinf(nd), np.isinf(nh))
    assert np.array_equal(nd, nh)


@pytest.mark.parametrize("nch", [1, 3])
def test_sample_values_blend(engine, nch):
    """epi_sample_values: (1 - f) res[2 p] + f res[2 p + 1] with p = inv[j] (a weight-0
    side is not read: NaN there stays out), one channel spread to three when nch = 1,
    times colour and 1 - ring weight; samples not live stay 0; with use_acc the given
    per-sample value replaces the blend."""
    rng = np.random.default_rng(nch)
    n, S = 3001, 9
    geo, idx = _samples(rng, n, S)
    live = np.sort(rng.choice(n, 2000, replace=False)).astype(np.int32)
    L = len(live)
    wr = rng.uniform(0.0, 1.0, n).astype(np.float32)
    res = rng.uniform(0.0, 3.0, (2 * L, 4)).astype(np.float32)
    inv = rng.permutation(L).astype(np.int32)
    f = idx[live, 2].view(np.float32).astype(np.float64)
    res[2 * inv[f == 1.0]] = np.nan                # unread sides
    res[2 * inv[f == 0.0] + 1] = np.nan
    acc = rng.uniform(0.0, 1.0, (L, 4)).astype(np.float32)
    colour = np.array([0.5, 1.5, 2.0, 0.0], np.float32)
    defs = {"EPI_NT": 4, "EPI_NCH": nch}
    bufs = [engine.to_device(x) for x in (res, inv, idx, live, acc, wr)]
    out = engine.zeros(16 * n)
    try:
        got = {}
        for use_acc in (0, 1):
            engine.call("epipolar", "epi_sample_values", L, defs, res=bufs[0], inv=bufs[1],
                        idx=bufs[2], live=bufs[3], L=L, acc=bufs[4], use_acc=use_acc,
                        wr=bufs[5], colour=colour, values=out)
            got[use_acc] = engine.read(out, (n, 4), np.float32)
    finally:
        engine.free(out, *bufs)
    assert (f == 0.0).any() and (f == 1.0).any()
    r = np.nan_to_num(res.astype(np.float64))
    f = f[:, None]
    s = (1 - f) * r[2 * inv] + f * r[2 * inv + 1]
    for use_acc, base in ((0, s), (1, acc.astype(np.float64))):
        if nch == 1:
            base = np.repeat(base[:, :1], 3, axis=1)
        want = np.zeros((n, 3))
        want[live] = base[:, :3] * colour[:3] * (1.0 - wr[live, None])
        np.testing.assert_allclose(got[use_acc][:, :3], want, rtol=2e-6, atol=1e-7)
        others = np.setdiff1d(np.arange(n), live)
        assert np.all(got[use_acc][others] == 0.0)
