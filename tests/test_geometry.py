"""Host geometry helpers against brute force."""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.geometry import box_corners, perpendicular_axes, slab_interval, unit


def test_slab_interval_matches_dense_sampling():
    rng = np.random.default_rng(3)
    n = 400
    a = rng.uniform(-2, 2, (n, 3))
    d = rng.normal(size=(n, 3))
    d[::7, 1] = 0.0                      # exactly parallel to a slab
    d[::11] = 0.0                        # a point
    lo, hi = np.array([-1.0, -0.5, -1.0]), np.array([1.0, 0.5, 1.2])
    enter, leave = slab_interval(a, d, lo, hi, 1.5)
    t = np.linspace(0, 1.5, 30001)
    p = a[:, None, :] + t[None, :, None] * d[:, None, :]
    inside = np.all((p >= lo) & (p <= hi), axis=2)
    for i in range(n):
        if inside[i].any():
            ts = t[inside[i]]
            assert enter[i] <= leave[i]
            assert abs(enter[i] - ts.min()) < 1e-4 and abs(leave[i] - ts.max()) < 1e-4, i
        else:
            assert enter[i] > leave[i] - 1e-4, i


def test_unit_and_corners():
    v = unit([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(v, [[0.6, 0.8, 0.0], [0.0, 0.0, 0.0]])
    c = box_corners([0, 0, 0], [1, 2, 3])
    assert c.shape == (8, 3) and {tuple(x) for x in c} == {(x, y, z) for x in (0, 1)
                                                          for y in (0, 2) for z in (0, 3)}
    np.testing.assert_array_equal(c[5], [1, 0, 3])      # bits 0 and 2 set


def test_perpendicular_axes_complete_a_right_handed_frame():
    rng = np.random.default_rng(4)
    dirs = unit(rng.normal(size=(200, 3)))
    dirs = np.concatenate([dirs, np.eye(3), -np.eye(3), unit([[0.9, 0.1, 0.0], [0.89, 0.4, 0.2]])])
    for d in dirs:
        s1, s2 = perpendicular_axes(d)
        frame = np.stack([s1, s2, d])
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(frame) == pytest.approx(1.0)
