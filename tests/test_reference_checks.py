"""The guard of every image-against-reference test (tests/reference_checks.py) has teeth
itself: it passes a close image, fails a far one, and fails a test whose bound would let
a 2 % bias or 5 % per-pixel noise through."""
from __future__ import annotations

import numpy as np
import pytest
from reference_checks import _planted_noise, assert_matches_reference, pixel_error


def _ref(h=24, w=32):
    y, x = np.mgrid[0:h, 0:w] / 8.0
    base = 0.004 * (1.2 + np.sin(x) * np.cos(y))          # dim: mean ~0.005
    return np.stack([base, 0.8 * base, 1.1 * base], axis=-1)


def test_planted_noise_is_exactly_zero_mean_unit_variance():
    n = _planted_noise((24, 32, 3))
    assert abs(n.mean()) < 1e-12 and abs(n.std() - 1.0) < 1e-12
    assert np.array_equal(n, _planted_noise((24, 32, 3)))      # fixed seed


def test_a_close_image_passes_and_a_far_one_fails():
    ref = _ref()
    close = ref * (1.0 + 0.003 * _planted_noise(ref.shape)[::-1])
    m = assert_matches_reference(close, ref, 2e-5, "close", per_pixel=0.01, mean_tol=0.01)
    assert m["relmse"] < 2e-5 and m["per_pixel"] < 0.01
    with pytest.raises(AssertionError, match="relMSE"):
        assert_matches_reference(ref * 1.01, ref, 2e-5, "1 % bias")
    with pytest.raises(AssertionError, match="mean ratio"):
        assert_matches_reference(ref * 1.015, ref, 1e-3, "1.5 % bias", per_pixel=0.01,
                                 mean_tol=0.01)


def test_a_bound_without_teeth_fails_the_test():
    ref = _ref()
    # relMSE 1e-3 lets a 2 % bias (4e-4) through
    with pytest.raises(AssertionError, match="no teeth.*2% bias"):
        assert_matches_reference(ref, ref, 1e-3, "loose")
    # the mean catches the bias, but 5 % noise (relMSE 2.5e-3) still passes 3e-3
    with pytest.raises(AssertionError, match="no teeth.*5% per-pixel noise"):
        assert_matches_reference(ref, ref, 3e-3, "loose", mean_tol=0.01)
    # the typical pixel's error catches the noise
    assert_matches_reference(ref, ref, 3e-3, "teeth", mean_tol=0.01, per_pixel=0.02)
    # a stated exemption lets the test pass without that planted error being caught
    assert_matches_reference(ref, ref, 3e-3, "exempt", mean_tol=0.01,
                             exempt={"noise": "the method is noisier than that"})


def test_pixel_error_ignores_a_few_edge_pixels():
    from clscatter.io.image import relmse
    ref = _ref()
    ref2 = ref.copy()
    ref2[:, 10] = 0.0                              # a black column: a shadow
    leaky = ref2.copy()
    leaky[:, 10] = ref[:, 10] * 0.3                # light leaking into it
    assert pixel_error(leaky, ref2) == 0.0         # the lit values are exact
    assert relmse(leaky, ref2) > 0.1               # relMSE sees only the leak
