"""atan2_fast (common.h), the epipolar kernels' atan2, against NumPy's float64 arctan2:
every quadrant, the axes, equal magnitudes, the reduction's branch point tan(pi/8),
tiny and huge arguments, signed zeros and NaN."""
from __future__ import annotations

import numpy as np


def _run(engine, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    y, x = np.asarray(y, np.float32), np.asarray(x, np.float32)
    yb, xb, out = engine.to_device(y), engine.to_device(x), engine.empty(4 * len(y))
    try:
        engine.call("epipolar", "atan2_test", len(y), {"EPI_NT": 4, "EPI_NCH": 1}, y=yb, x=xb,
                    n=len(y), out=out)
        return engine.read(out, len(y), np.float32)
    finally:
        engine.free(yb, xb, out)


def test_atan2_fast_matches_float64_everywhere(engine):
    rng = np.random.default_rng(3)
    n = 200_000
    ang = rng.uniform(-np.pi, np.pi, n)
    r = 10.0 ** rng.uniform(-20, 20, n)
    y, x = (r * np.sin(ang)).astype(np.float32), (r * np.cos(ang)).astype(np.float32)
    t = np.tan(np.pi / 8)
    edge = np.array([[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [-1, -1], [1, -1], [-1, 1],
                     [t, 1], [np.nextafter(t, 1), 1], [1, t], [1e-38, 1], [1, 1e-38],
                     [3e38, 1], [1, 3e38], [-2.5, 1e-30], [5, -7], [0, 0]], np.float64)
    y = np.concatenate([y, edge[:, 0].astype(np.float32)])
    x = np.concatenate([x, edge[:, 1].astype(np.float32)])
    got = _run(engine, y, x).astype(np.float64)
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    err = np.abs(got - want)
    assert err.max() <= 4e-7, (err.max(), y[err.argmax()], x[err.argmax()])
    assert np.sqrt(np.mean(err ** 2)) < 1.5e-7       # mostly within an ulp or two
    assert got[-1] == 0.0                              # atan2(0, 0)


def test_atan2_fast_signs_and_nan(engine):
    y = np.array([0.0, -0.0, 0.0, -0.0, np.nan, 1.0, np.nan], np.float32)
    x = np.array([1.0, 1.0, -1.0, -1.0, 1.0, np.nan, np.nan], np.float32)
    got = _run(engine, y, x)
    assert got[0] == 0.0 and not np.signbit(got[0])
    assert got[1] == 0.0 and np.signbit(got[1])
    np.testing.assert_allclose(got[2:4], [np.pi, -np.pi], rtol=1e-7)
    assert np.isnan(got[4:]).all()


def _sincos(engine, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, np.float32)
    xb, out = engine.to_device(x), engine.empty(8 * len(x))
    try:
        engine.call("epipolar", "sincos_test", len(x), {"EPI_NT": 4, "EPI_NCH": 1}, x=xb,
                    n=len(x), out=out)
        got = engine.read(out, (len(x), 2), np.float32).astype(np.float64)
        return got[:, 0], got[:, 1]
    finally:
        engine.free(xb, out)


def test_sincos_fast_matches_float64(engine):
    """The spot light's angles (within +-pi) and well beyond, quadrant boundaries and
    their neighbours, tiny arguments, zero; NaN and inf give NaN."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.uniform(-np.pi, np.pi, 200_000), rng.uniform(-1e3, 1e3, 50_000),
                        10.0 ** rng.uniform(-30, 0, 1000)]).astype(np.float32)
    q = (np.arange(-40, 41) * np.pi / 4).astype(np.float32)
    x = np.concatenate([x, q, np.nextafter(q, np.float32(np.inf)),
                        np.nextafter(q, np.float32(-np.inf))])
    s, c = _sincos(engine, x)
    xd = x.astype(np.float64)
    err = np.maximum(np.abs(s - np.sin(xd)), np.abs(c - np.cos(xd)))
    small = np.abs(xd) <= np.pi
    assert err[small].max() <= 2e-7, (err[small].max(), x[small][err[small].argmax()])
    assert err.max() <= 3e-7, (err.max(), x[err.argmax()])
    tiny = np.abs(xd) < 1e-20
    assert np.array_equal(s[tiny], xd[tiny]) and np.all(c[tiny] == 1.0)
    s0, c0 = _sincos(engine, np.array([-0.0, np.nan, np.inf, -np.inf]))
    assert s0[0] == 0.0 and c0[0] == 1.0
    assert np.isnan(s0[1:]).all() and np.isnan(c0[1:]).all()
