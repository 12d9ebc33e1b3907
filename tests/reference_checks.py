"""One check of a rendered image against a reference image, with teeth (a test helper).

This is an importable helper module, not a test file. :func:`assert_matches_reference`
is how the tests compare a method's image with a reference image:

* it asserts ``relmse(img, ref) <= bound`` (``clscatter.io.image.relmse``: the floor is
  ``0.01 * mean(|ref|)**2``, so a bound means the same on dim and bright images) and,
  where given, ``|mean_ratio(img, ref) - 1| <= mean_tol`` and
  ``pixel_error(img, ref) <= per_pixel`` (the typical lit value's relative error: the
  median, over the values where the reference exceeds a tenth of its mean, of
  ``|img - ref| / (|ref| + 0.1 * mean(|ref|))``);
* then it runs the *same* check on two images that are wrong on purpose and asserts that
  it rejects both: ``ref * 1.02`` (a 2 % bias) and ``ref * (1 + 0.05 * n)`` with ``n``
  fixed-seed noise, exactly zero-mean and unit-variance, one value per pixel and channel
  (5 % noise). A check that lets either through has no teeth, and the test fails saying
  so. Where a method's own error is as large as a planted one (a noisy estimator, an
  estimator's known bias), the test passes ``exempt={"noise" or "bias": reason}`` and
  says so; the planted error is still measured and printed.

relMSE alone catches 5 % noise below a bound of about 1e-3 .. 2.5e-3 but a 2 % bias only
below about 2e-4 .. 4e-4 (both times the share of the reference above a tenth of its
mean): a test whose bound is larger passes ``mean_tol`` (below 0.02) so that the mean
catches the bias, and ``per_pixel`` (below ~0.025) where relMSE is dominated by a few
pixels, e.g. light leaking into black pixels at a shadow's edge, that a method resolves
only to a pixel.
"""
from __future__ import annotations

import numpy as np

from clscatter.io.image import mean_ratio, relmse

#: The planted errors the check must reject.
BIAS = 0.02
NOISE = 0.05
NOISE_SEED = 20240517


def _planted_noise(shape) -> np.ndarray:
    n = np.random.default_rng(NOISE_SEED).standard_normal(shape)
    if n.size > 1:                                  # exactly zero-mean, unit-variance
        n = (n - n.mean()) / n.std()
    return n


def pixel_error(img: np.ndarray, ref: np.ndarray) -> float:
    """The typical error of a lit value: the median, over the values where the reference
    exceeds a tenth of its mean, of ``|img - ref| / (|ref| + 0.1 * mean(|ref|))`` (every
    pixel and channel is a value). Robust to the few pixels at a shadow's or a cone's edge
    that dominate relMSE where a method resolves an edge only to a pixel."""
    floor = 0.1 * float(np.mean(np.abs(ref)))
    lit = np.abs(ref) > floor
    return float(np.median(np.abs(img - ref)[lit] / (np.abs(ref[lit]) + floor)))


def _measure(img, ref, bound, mean_tol, per_pixel) -> tuple[dict, list[str]]:
    m = {"relmse": relmse(img, ref), "mean_ratio": mean_ratio(img, ref)}
    failed = []
    if not m["relmse"] <= bound:
        failed.append(f"relMSE {m['relmse']:.3g} > {bound:.3g}")
    if mean_tol is not None and not abs(m["mean_ratio"] - 1.0) <= mean_tol:
        failed.append(f"mean ratio {m['mean_ratio']:.5f} outside 1 +- {mean_tol:g}")
    if per_pixel is not None:
        m["per_pixel"] = pixel_error(img, ref)
        if not m["per_pixel"] <= per_pixel:
            failed.append(f"per-pixel error {m['per_pixel']:.3g} > {per_pixel:g}")
    return m, failed


def assert_matches_reference(img, ref, bound: float, what: str = "", per_pixel=None,
                             mean_tol=None, exempt: dict | None = None) -> dict:
    """Assert that ``img`` matches reference ``ref`` (relMSE <= ``bound``; the mean ratio
    within ``1 +- mean_tol`` and :func:`pixel_error` <= ``per_pixel`` where given) and that
    the same check rejects ``ref`` with a 2 % bias (``"bias"``) and with 5 % per-pixel
    noise (``"noise"``). ``exempt`` maps either name to the reason no bound can catch it
    at the method's own error level (the test then says so; the planted error is still
    measured and printed). Prints and returns the measured values (``relmse``,
    ``mean_ratio``, ``per_pixel`` when checked)."""
    exempt = exempt or {}
    assert set(exempt) <= {"bias", "noise"}, exempt
    img = np.asarray(img, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    label = f"{what}: " if what else ""
    assert img.shape == ref.shape, f"{label}shape {img.shape} vs reference {ref.shape}"
    assert np.isfinite(ref).all() and np.abs(ref).max() > 0, \
        f"{label}the reference is black or not finite"
    m, failed = _measure(img, ref, bound, mean_tol, per_pixel)
    shown = ", ".join(f"{k} {v:.3g}" for k, v in m.items())
    print(f"{label}{shown} (bound {bound:.3g}"
          + (f", mean +-{mean_tol:g}" if mean_tol is not None else "")
          + (f", per pixel {per_pixel:g}" if per_pixel is not None else "") + ")")
    planted = {"bias": (f"a {BIAS:.0%} bias", ref * (1.0 + BIAS)),
               "noise": (f"{NOISE:.0%} per-pixel noise",
                         ref * (1.0 + NOISE * _planted_noise(ref.shape)))}
    for key, (name, wrong) in planted.items():
        wm, caught = _measure(wrong, ref, bound, mean_tol, per_pixel)
        if key in exempt:
            print(f"{label}not checked: {name} {'is' if caught else 'is NOT'} caught "
                  f"({exempt[key]})")
            continue
        assert caught, (f"{label}the bound has no teeth: the check passes the reference "
                        f"with {name} (relMSE {wm['relmse']:.3g} <= {bound:.3g}, mean ratio "
                        f"{wm['mean_ratio']:.4f}); tighten the bound or pass mean_tol/per_pixel")
    assert not failed, f"{label}" + "; ".join(failed)
    return m
