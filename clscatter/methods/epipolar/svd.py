"""The visibility-free part of the integrand and its truncated SVD (Baran et al. 2010, Sec. 6).

In slice coordinates (see ``geometry``) the single-scattering integrand of Eq. (3), per
unit gamma, splits into factors that depend on the light ray alone (``F(alpha, gamma)``,
computed per slice on the device: light transmittance from where the light ray enters
the medium box, spot cone), on the view ray alone (``pure_beta``) and a slice-independent
*core* ``K(gamma, beta)`` that couples them:

directional (``gamma = t sin(beta)``, ``|dt/dgamma| = 1 / sin(beta)``,
``z = gamma cot(beta)``, phase cosine ``cos(beta)``)::

    sigma_s E p(cos b) / sin b * exp(kappa t_a) * exp(-kappa z_exit(alpha, g))
                                                * exp(-kappa g tan(b / 2))

    since  -kappa (t - t_a) - kappa (z_exit - z) = kappa t_a - kappa z_exit
                                                  - kappa g (1/sin b - cot b)

spot (light at distance ``D``; ``t = D sin g / sin(b + g)``, ``r = D sin b / sin(b + g)``,
``|dt/dgamma| = r^2 / (D sin b)`` cancels the ``1/r^2`` of the light, phase cosine
``cos(b + g)``)::

    sigma_s I / (D sin b) * exp(kappa t_a) * exp(kappa r_enter(alpha, g)) * cone(alpha, g)
                          * p(cos(b + g)) exp(-kappa D (sin b + sin g) / sin(b + g))

The paper decomposes the whole visibility-free integrand; taking the exactly separable
factors out first and decomposing only the core is the same approximation with a
better-conditioned matrix (the ``1/sin b`` of the epipole no longer dominates it).
:func:`paper_matrix` builds the paper's full matrix for the singular-value check.

The core is sampled on an ``samples x samples`` grid (64 x 64 in the paper) once per
frame and light, and truncated to ``terms`` terms (4). The paper upsamples the singular
vectors linearly; here they are extended by projection (Nyström): ``Gamma_n(g) =
K(g, beta_s) V_n / s_n`` and ``B_n(b) = U_n^T K(gamma_s, b)``, exact at the samples and
smooth between them, tabulated finely for the device.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import Axis

FOUR_PI = 4.0 * math.pi


def hg(cos: np.ndarray, g: float) -> np.ndarray:
    """Henyey-Greenstein phase function (the convention of common.h)."""
    denom = 1.0 + g * g - 2.0 * g * np.asarray(cos, np.float64)
    return (1.0 - g * g) / (FOUR_PI * denom * np.sqrt(denom))


def core(axis: Axis, kappa: float, g: float, gam: np.ndarray, bet: np.ndarray) -> np.ndarray:
    """``K(gamma, beta)`` on the outer grid ``gam (G,) x bet (B,)`` for one channel."""
    G, Bt = np.meshgrid(np.asarray(gam, np.float64), np.asarray(bet, np.float64), indexing="ij")
    if axis.spot:
        s = np.minimum(G + Bt, math.pi - 1e-4)         # beyond pi - beta no view ray reaches
        with np.errstate(over="ignore"):
            expo = kappa * axis.D * (np.sin(Bt) + np.sin(G)) / np.sin(s)
        return hg(np.cos(s), g) * np.exp(-np.minimum(expo, 700.0))
    return np.exp(-kappa * G * np.tan(0.5 * Bt))


def pure_beta(axis: Axis, g: float, bet: np.ndarray) -> np.ndarray:
    """The factor of the integrand that depends on beta alone."""
    b = np.asarray(bet, np.float64)
    sb = np.maximum(np.sin(b), 1e-9)
    if axis.spot:
        return 1.0 / (axis.D * sb)
    return hg(np.cos(b), g) / sb


def paper_matrix(axis: Axis, kappa: float, g: float, gam, bet) -> np.ndarray:
    """The paper's matrix: the whole visibility-free integrand of one slice (no F)."""
    return core(axis, kappa, g, gam, bet) * pure_beta(axis, g, bet)[None, :]


@dataclass
class Tables:
    """Device tables of one light: ``gtab`` (n_g, NV) over ``[g_lo, g_hi]`` and ``btab``
    (n_b, NV) over ``[b_lo, b_hi]``, NV = terms * channels, index ``c * terms + n``."""

    gtab: np.ndarray
    btab: np.ndarray
    g_lo: float
    g_hi: float
    b_lo: float
    b_hi: float
    singular: list            # per channel, the leading singular values of the core
    terms: int


def decompose(axis: Axis, kappas: np.ndarray, g: float, g_range, b_range, terms: int = 4,
              samples: int = 64, n_g: int = 2048, n_b: int = 2048) -> Tables:
    """Truncated SVD of the core for each channel's extinction in ``kappas``."""
    g_lo, g_hi = (float(x) for x in g_range)
    b_lo, b_hi = (float(x) for x in b_range)
    if not g_hi > g_lo:
        g_hi = g_lo + 1e-6
    if not b_hi > b_lo:
        b_hi = b_lo + 1e-6
    gs = np.linspace(g_lo, g_hi, samples)
    bs = np.linspace(b_lo, b_hi, samples)
    gf = np.linspace(g_lo, g_hi, n_g)
    bf = np.linspace(b_lo, b_hi, n_b)
    pb = pure_beta(axis, g, bf)
    nch = len(kappas)
    gtab = np.zeros((n_g, nch * terms))
    btab = np.zeros((n_b, nch * terms))
    singular = []
    for c, kap in enumerate(kappas):
        K = core(axis, float(kap), g, gs, bs)
        U, S, Vt = np.linalg.svd(K, full_matrices=False)
        singular.append([float(x) for x in S[:max(terms + 2, 6)]])
        n_use = min(terms, len(S))
        Kg = core(axis, float(kap), g, gf, bs)          # (n_g, samples)
        Kb = core(axis, float(kap), g, gs, bf)          # (samples, n_b)
        for n in range(n_use):
            if S[n] <= 1e-12 * S[0]:
                break
            gtab[:, c * terms + n] = Kg @ Vt[n] / S[n]
            btab[:, c * terms + n] = (U[:, n] @ Kb) * pb
    return Tables(gtab.astype(np.float32), btab.astype(np.float32), g_lo, g_hi, b_lo, b_hi,
                  singular, terms)
