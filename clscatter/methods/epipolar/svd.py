"""The visibility-free part of the integrand, its truncated SVD and the SVD's error (Baran
et al. 2010, Sec. 6).

In slice coordinates (see ``geometry``) the single-scattering integrand of Eq. (3), per
unit gamma, along the view ray ``beta`` of slice ``alpha`` at the light ray ``gamma`` is

    sigma_s E * phase * |dt/dgamma| * exp(-kappa (t - t_a)) * exp(-kappa l)

with ``t`` the distance from the eye, ``t_a`` where the view segment starts (the medium
entry, or the eye), and ``l`` the light's path length inside the medium: ``z_exit - z``
for a directional light (``z`` the axial coordinate, ``z_exit(alpha, gamma)`` where the
light ray enters the box), ``r - r_enter(alpha, gamma)`` for a spot light (``r`` the
distance from the light). Directional: ``t = gamma / sin b``, ``z = gamma cot b``,
``|dt/dgamma| = 1 / sin b``, phase cosine ``cos b``; spot (light at distance ``D``):
``t = D sin g / sin(b + g)``, ``r = D sin b / sin(b + g)``, ``|dt/dgamma| = r^2 / (D sin b)``
cancels the light's ``1/r^2``, phase cosine ``cos(b + g)``.

Only a slice-independent function of ``(gamma, beta)`` can be decomposed once per frame;
``t_a`` depends on the view ray's slice and ``z_exit``/``r_enter`` on the light ray's.

Two formulations (:class:`Refs`; the method picks per light on the error estimate below)

*plain* (:meth:`Refs.zero`, the previous version's): ``K = exp(-kappa (t - z))`` (spot:
    ``phase * exp(-kappa (t + r))``), smooth and <= 1 everywhere (``t >= |z|``), with
    ``F = exp(-kappa z_exit)`` (spot: ``exp(kappa r_enter)``) in the leaves and
    ``exp(kappa t_a)`` on each result. Its singular values fall fast, but where the view
    ray enters the medium far from the eye the values a pixel reads are a tiny fraction of
    the matrix's maximum: the issue's thick fog seen from outside (``kappa t_a`` ~ 6,
    sun behind the camera) reads ``K ~ e^-8`` while the rank-4 truncation error is
    ``~s5/s1 ~ 1e-3`` of the maximum, so a 4-term sweep was 17 x too bright (relMSE 126
    at 48 x 36) although ``s4/s1 ~ 0.001``. It needs 16 terms there (held-out error
    5e-5), and then the float32 prefix sums of the tree, which hold values ``e^8`` above
    what the pixel reads, lose ~1e-3 .. 1e-2 to cancellation.
*referenced*: two slice-independent references taken from the frame, ``t_ref(beta)``, a
    lower envelope of the view segments' start ``t_a`` over the slices at that beta (from
    the camera samples themselves), and ``l_ref(gamma)``, an envelope of the light's entry
    (directional: the upper envelope of ``z_exit``; spot: the lower envelope of
    ``r_enter``); the decomposed function is

        K(gamma, beta) = [phase] * exp(-s(kappa (t - t_ref(beta))) - s(kappa l_ref))

    with ``l_ref = z_ref(gamma) - z`` (directional) or ``r - r_ref(gamma)`` (spot), and
    ``s(y) = y`` for ``y >= 0``, ``expm1(y)`` below (C1). Every point a camera sample
    integrates has both arguments >= 0 (up to the slice spacing), so there ``K`` is the
    transmittance product relative to the references: at most 1, and close to 1 where
    the pixel's integrand is largest (its medium entry); the soft branch fills the unused
    part of the rectangle (nearer than any segment starts, or beyond the light's entry)
    with values <= e^2 instead of an exponentially large continuation, so neither the
    SVD nor the tree's float32 sums spend their precision there. The exact remainders:
    ``F = exp(kappa (z_ref - z_exit))`` (spot: ``cone * exp(kappa (r_enter - r_ref))``) in
    the leaves, ``exp(kappa (t_a - t_ref(beta)))`` on each result, both >= 1 and as large
    as the references' spread over slices, which groups of slices (one SVD per arc of
    slices, ``pipeline._svd_groups``) reduce. The kink of ``s`` costs rank: for the thick
    fog the held-out error is 2.5 (1 group) / 0.58 (16 groups) at 4 terms and 0.013 /
    0.0035 at 16 (SVD with a float32 bound), where plain is 58 at 4 and, with the tree's
    float32 sums emulated (:func:`float32_error`), ~0.007 at 16.

Neither formulation is bounded by a fixed number of terms for every optical depth; what
is bounded is the error the method accepts: the estimate (:func:`heldout_error`: the SVD
on held-out samples, :func:`float32_bound`: a bound on the tree's float32 sums, and where
that is not small or the medium is thick, :func:`float32_error`: the sums emulated,
:func:`riemann_sums` / :func:`riemann_rel`: the light-ray sum (on the device),
:func:`slice_error`: reading samples in neighbouring slices) must be within the
tolerance, with more terms (4, 8, 16), the referenced formulation, 16 groups, 2 or 4 x
the light rays and half or a quarter of the slice spacing tried in turn, else the light
is ray marched (``pipeline.SVDFallback``). Measured over the sweep of
tests/test_epipolar_regimes.py (optical depth 0.1 .. 10 across the medium, camera inside
and outside, light behind / beside / in front / along the view axis, directional and
spot): all 32 configurations with the camera inside are swept; with the camera outside,
four of eight at optical depth 10 and the spot light on the view axis behind the camera
(the paper's claim fails there) fall back (8 of 64 in all). The images' bounds against
raymarch are the test's (docs/testing.md); where the light is in front, one-pixel leaks of
light into shadow pixels along occluder edges dominate them.

The paper decomposes the whole integrand, including ``1/sin b`` (epipole); here the
exactly separable factors (``pure_beta``) are kept out of ``K``, the same approximation
with a better-conditioned matrix. :func:`paper_matrix` builds the paper's matrix.

The SVD: ``K`` is sampled on a ``samples x samples`` grid (64 x 64 in the paper) once per
frame and light and truncated to ``terms`` terms; the singular vectors are extended by
projection (Nyström): ``Gamma_n(g) = K(g, beta_s) V_n / s_n`` and ``B_n(b) = U_n^T
K(gamma_s, b)``, exact at the samples and smooth between them, tabulated for the device.

The error estimate (:func:`heldout_error`): the SVD's relative error of whole pixel
integrals, on a held-out set of camera samples (their own slice, beta and medium
interval, Gauss-Legendre nodes in gamma that are not the SVD's samples), with the exact
``F`` (light entry, cone): ``|int F (K_approx - K)| / int F K``. Cheap (a few hundred
samples x 48 nodes, NumPy); the method raises the terms or falls back on it.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .geometry import Axis

FOUR_PI = 4.0 * math.pi
REF_NODES = 256          # nodes of the reference envelopes t_ref(beta), l_ref(gamma)


def hg(cos: np.ndarray, g: float) -> np.ndarray:
    """Henyey-Greenstein phase function (the convention of common.h)."""
    denom = 1.0 + g * g - 2.0 * g * np.asarray(cos, np.float64)
    return (1.0 - g * g) / (FOUR_PI * denom * np.sqrt(denom))


def soft(y: np.ndarray) -> np.ndarray:
    """``y`` for ``y >= 0``, ``expm1(y)`` below: C1, bounded below by -1."""
    return _soft_in_place(np.array(y, np.float64))


def _soft_in_place(y: np.ndarray) -> np.ndarray:
    """:func:`soft` of a float64 array the caller owns, overwritten (expm1 only where
    negative: most of a grid is not)."""
    neg = y < 0.0
    if neg.any():
        y[neg] = np.expm1(y[neg])
    return y


def _k_values(axis: Axis, kap: float, g: float, gam: np.ndarray, bet: np.ndarray,
              tr: np.ndarray, lr: np.ndarray, use_soft: bool) -> np.ndarray:
    """``K`` at broadcastable ``gam`` and ``bet`` (an outer grid ``(G, 1) x (1, B)``, or
    nodes ``(N, Q)`` with ``(N, 1)``), ``tr`` = t_ref broadcast like ``bet``, ``lr`` =
    l_ref like ``gam``: the one evaluation behind :func:`core` and :func:`k_at`. What
    depends on one coordinate is computed on its own axis; the grid is worked in place."""
    sf = _soft_in_place if use_soft else (lambda y: y)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        if axis.spot:
            s = np.minimum(gam + bet, math.pi - 1e-4)    # beyond pi - beta no view ray reaches
            ss = np.sin(s)
            t = (axis.D * np.sin(gam)) / ss
            r = (axis.D * np.sin(bet)) / ss
            t -= tr
            t *= kap
            r -= lr
            r *= kap
            e = sf(t)
            e += sf(r)
            np.minimum(e, 700.0, out=e)
            np.negative(e, out=e)
            np.exp(e, out=e)
            e *= hg(np.cos(s), g)
            return e
        sb = np.maximum(np.sin(bet), 1e-12)
        t = gam / sb                                    # distance from the eye
        z = gam * (np.cos(bet) / sb)                    # axial coordinate
        t -= tr
        t *= kap
        np.subtract(lr, z, out=z)
        z *= kap
        e = sf(t)
        e += sf(z)
        np.nan_to_num(e, copy=False, nan=700.0)
        np.minimum(e, 700.0, out=e)
        np.negative(e, out=e)
        return np.exp(e, out=e)


# --------------------------------------------------------------------------------------
# references
# --------------------------------------------------------------------------------------
@dataclass
class Refs:
    """Reference envelopes, piecewise linear on uniform nodes: ``tref`` over
    ``[b_lo, b_hi]`` (view), ``lref`` over ``[g_lo, g_hi]`` (light; directional
    ``z_ref``, spot ``r_ref``); ``span`` bounds ``|l_ref - light entry|`` over the light
    rays that meet the medium (the kernel clamps F's exponent to it)."""

    tref: np.ndarray
    lref: np.ndarray
    b_lo: float
    b_hi: float
    g_lo: float
    g_hi: float
    span: float
    soft: bool = True         # False: the plain exponent (the unreferenced formulation)

    def t_at(self, b) -> np.ndarray:
        return np.interp(b, np.linspace(self.b_lo, self.b_hi, len(self.tref)), self.tref)

    def l_at(self, g) -> np.ndarray:
        return np.interp(g, np.linspace(self.g_lo, self.g_hi, len(self.lref)), self.lref)

    @staticmethod
    def zero(g_range, b_range, span: float = 0.0) -> Refs:
        """No references: ``K = exp(-kappa (t - z))`` (spot: ``exp(-kappa (t + r))``),
        smooth and <= 1 everywhere (``t >= |z|``), the formulation of the previous
        version; the best where the camera is inside the medium and thin media."""
        return Refs(np.zeros(2), np.zeros(2), *b_range, *g_range, span, False)


def _ray_box(o, d, box):
    """Slab test, vectorised over the leading axes: ``(t0, t1)`` (no clamping; a miss has
    t0 > t1). Axes with ``d = 0`` constrain nothing when ``o`` is inside their slab (the
    NaN/inf rule of ray_box in common.h)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    return _slabs([o[..., k] for k in range(3)], [d[..., k] for k in range(3)], box)


def _slabs(o, d, box):
    """:func:`_ray_box` on per-axis arrays ``o[k]``, ``d[k]`` (any broadcastable shapes):
    three contiguous passes instead of reductions over a last axis of length 3, which
    is what the host's estimates spend their time on."""
    bmin, bmax = box
    lo = hi = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            ta = (bmin[k] - o[k]) / d[k]
            tb = (bmax[k] - o[k]) / d[k]
            # fmax/fmin skip NaN (0 * inf: the origin on a slab plane of a zero component)
            a, b = np.fmin(ta, tb), np.fmax(ta, tb)
            lo = a if lo is None else np.fmax(lo, a)
            hi = b if hi is None else np.fmin(hi, b)
    return lo, hi


def light_entry(axis: Axis, box, w: np.ndarray, gam: np.ndarray):
    """The light ray ``gamma`` of slice ``w``: where it enters the medium (directional:
    axial coordinate ``z_exit``, the kernel's ``t1`` along ``+u``; spot: distance
    ``r_enter >= 0`` from the light; 0 for an unbounded medium) and whether it meets the
    medium. ``w`` (S, 3), ``gam`` (S, G) -> two (S, G) arrays."""
    w = np.asarray(w, np.float64)[:, None, :]
    g = np.asarray(gam, np.float64)[..., None]
    if axis.spot:
        if box is None:
            return np.zeros(g.shape[:2]), np.ones(g.shape[:2], bool)
        d = -np.cos(g) * axis.u + np.sin(g) * w
        t0, t1 = _ray_box(axis.light, d, box)
        t0 = np.maximum(t0, 0.0)
        return t0, (t0 <= t1) & np.isfinite(t0)
    g = g[..., 0]
    o = [axis.eye[k] + g * w[..., k] for k in range(3)]
    t0, t1 = _slabs(o, [float(axis.u[k]) for k in range(3)], box)
    return t1, (t0 <= t1) & np.isfinite(t1)


def view_entry(axis: Axis, box, dirs: np.ndarray):
    """``(t_a, t_b)`` of unit view directions (N, 3) inside the medium box (t_a >= 0;
    a miss has t_a > t_b)."""
    t0, t1 = _ray_box(axis.eye, np.asarray(dirs, np.float64), box)
    return np.maximum(t0, 0.0), t1


def node_extremes(x, v, lo, hi, n, upper: bool) -> np.ndarray:
    """The extreme (max if ``upper``, else min) of samples ``v`` nearest to each of ``n``
    uniform nodes over [lo, hi] (node ``rint((x - lo) / (hi - lo) (n - 1))``); -inf / inf
    where no sample falls. The reduction the device does for the camera samples
    (``epi_view_nodes``); :func:`envelope_from_nodes` finishes it."""
    out = np.full(n, -np.inf if upper else np.inf)
    if len(x) == 0:
        return out
    j = np.clip(np.rint((np.asarray(x) - lo) / max(hi - lo, 1e-30) * (n - 1)), 0, n - 1).astype(int)
    (np.maximum if upper else np.minimum).at(out, j, v)
    return out


def envelope_from_nodes(out: np.ndarray, upper: bool) -> np.ndarray:
    """The envelope from :func:`node_extremes`: each node takes the extreme of its own
    and its neighbours' samples, so the linear interpolation between two nodes bounds
    every sample between them; nodes with no sample are interpolated (all zero when
    there is none at all)."""
    n = len(out)
    dil = out.copy()
    f = np.maximum if upper else np.minimum
    dil[1:] = f(dil[1:], out[:-1])
    dil[:-1] = f(dil[:-1], out[1:])
    ok = np.isfinite(dil)
    if not ok.any():
        return np.zeros(n)
    idx = np.arange(n)
    return np.interp(idx, idx[ok], dil[ok])


def _envelope(x, v, lo, hi, n, upper: bool) -> np.ndarray:
    """Envelope of samples ``v`` at positions ``x`` on ``n`` uniform nodes over [lo, hi]
    (:func:`node_extremes` then :func:`envelope_from_nodes`)."""
    return envelope_from_nodes(node_extremes(x, v, lo, hi, n, upper), upper)


def references(axis: Axis, box, w: np.ndarray, cone: tuple[np.ndarray, np.ndarray] | None,
               g_range, b_range, view_nodes: np.ndarray,
               n: int = REF_NODES, max_slices: int = 192, zero: bool = False) -> Refs:
    """The envelopes of the module docstring. ``w`` (S, 3): the slices; ``cone``: their
    gamma intervals inside a spot cone; ``view_nodes``: the least segment start of the
    view rays that will be integrated (camera samples, or grid rays) at each of ``n``
    nodes over ``b_range`` (:func:`node_extremes`, ``upper=False``). ``zero``: no
    references (:meth:`Refs.zero`), with the span of the light entries for the kernel."""
    g_lo, g_hi = (float(x) for x in g_range)
    b_lo, b_hi = (float(x) for x in b_range)
    tref = np.zeros(2) if zero else envelope_from_nodes(np.asarray(view_nodes, np.float64),
                                                        upper=False)
    if box is None and axis.spot:
        return Refs(tref, np.zeros(2), b_lo, b_hi, g_lo, g_hi, 0.0, not zero)
    # a subset of the slices (neighbours differ by a pixel: the envelope moves little
    # between them; what it misses is a slightly negative exponent, which the soft branch
    # takes smoothly) and 2 sub-samples per node, so kinks between nodes are seen: the
    # plain formulation needs only the span, so a coarser set does there
    m = max_slices if not zero else max_slices // 2
    sel = np.linspace(0, len(w) - 1, min(len(w), m)).astype(int)   # non-decreasing
    sel = sel[np.r_[True, sel[1:] != sel[:-1]]]     # np.unique without its ~20 ms first call
    gs = np.linspace(g_lo, g_hi, (2 if not zero else 1) * n)
    x, hit = light_entry(axis, box, w[sel], np.broadcast_to(gs, (len(sel), len(gs))))
    if cone is not None:
        hit &= (gs[None, :] >= cone[0][sel, None]) & (gs[None, :] <= cone[1][sel, None])
    G = np.broadcast_to(gs, x.shape)
    if zero:
        span = float(np.abs(x[hit]).max()) if hit.any() else 0.0
        return Refs(np.zeros(2), np.zeros(2), b_lo, b_hi, g_lo, g_hi, 1.25 * span + 1e-3, False)
    lref = _envelope(G[hit], x[hit], g_lo, g_hi, n, upper=not axis.spot)
    span = 0.0
    if hit.any():
        dev = np.abs(np.interp(G[hit], np.linspace(g_lo, g_hi, n), lref) - x[hit])
        span = float(dev.max())
    return Refs(tref, lref, b_lo, b_hi, g_lo, g_hi, 1.25 * span + 1e-3)


# --------------------------------------------------------------------------------------
# the decomposed function
# --------------------------------------------------------------------------------------
def core(axis: Axis, kappa: float, g: float, gam: np.ndarray, bet: np.ndarray,
         refs: Refs | None = None) -> np.ndarray:
    """``K(gamma, beta)`` on the outer grid ``gam (G,) x bet (B,)`` for one channel (see
    the module docstring; ``refs=None``: the plain formulation, :meth:`Refs.zero`)."""
    gam = np.asarray(gam, np.float64)
    bet = np.asarray(bet, np.float64)
    tr = np.zeros_like(bet) if refs is None else refs.t_at(bet)
    lr = np.zeros_like(gam) if refs is None else refs.l_at(gam)
    return _k_values(axis, kappa, g, gam[:, None], bet[None, :], tr[None, :], lr[:, None],
                     refs is not None and refs.soft)


def pure_beta(axis: Axis, g: float, bet: np.ndarray) -> np.ndarray:
    """The factor of the integrand that depends on beta alone."""
    b = np.asarray(bet, np.float64)
    sb = np.maximum(np.sin(b), 1e-9)
    if axis.spot:
        return 1.0 / (axis.D * sb)
    return hg(np.cos(b), g) / sb


def paper_matrix(axis: Axis, kappa: float, g: float, gam, bet, refs: Refs | None = None) -> np.ndarray:
    """The paper's matrix: the whole visibility-free integrand of one slice (no F)."""
    return core(axis, kappa, g, gam, bet, refs) * pure_beta(axis, g, bet)[None, :]


@dataclass
class Tables:
    """Device tables of one light: ``gtab`` (n_g, NV) over ``[g_lo, g_hi]`` and ``btab``
    (n_b, NV) over ``[b_lo, b_hi]``, NV = terms * channels, index ``c * terms + n``;
    ``gref`` (n_g,) and ``bref`` (n_b,) the references on the same grids."""

    gtab: np.ndarray
    btab: np.ndarray
    g_lo: float
    g_hi: float
    b_lo: float
    b_hi: float
    singular: list            # per channel, the leading singular values of K
    terms: int
    gref: np.ndarray | None = None
    bref: np.ndarray | None = None
    span: float = 0.0


def decompose(axis: Axis, kappas: np.ndarray, g: float, g_range, b_range, terms: int = 4,
              samples: int = 64, n_g: int = 2048, n_b: int = 2048,
              refs: Refs | None = None) -> Tables:
    """Truncated SVD of ``K`` for each channel's extinction in ``kappas``."""
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
        K = core(axis, float(kap), g, gs, bs, refs)
        # NumPy's gesdd: ~1 ms for 64 x 64, as fast as gesvd and without importing scipy
        # (0.3-0.5 s of every first render); gesvd only if gesdd does not converge
        try:
            U, S, Vt = np.linalg.svd(K, full_matrices=False)
        except np.linalg.LinAlgError:
            import scipy.linalg
            U, S, Vt = scipy.linalg.svd(K, full_matrices=False, lapack_driver="gesvd")
        singular.append([float(x) for x in S[:max(terms + 2, 6)]])
        n_use = min(terms, len(S))
        Kg = core(axis, float(kap), g, gf, bs, refs)          # (n_g, samples)
        Kb = core(axis, float(kap), g, gs, bf, refs)          # (samples, n_b)
        n_use = int(np.count_nonzero(S[:n_use] > 1e-12 * S[0]))   # S falls: a prefix
        gtab[:, c * terms:c * terms + n_use] = (Kg @ Vt[:n_use].T) / S[:n_use]
        btab[:, c * terms:c * terms + n_use] = (U[:, :n_use].T @ Kb).T * pb[:, None]
    r = refs if refs is not None else Refs.zero((g_lo, g_hi), (b_lo, b_hi))
    return Tables(gtab.astype(np.float32), btab.astype(np.float32), g_lo, g_hi, b_lo, b_hi,
                  singular, terms, r.l_at(gf).astype(np.float32), r.t_at(bf).astype(np.float32),
                  float(r.span))


# --------------------------------------------------------------------------------------
# the error estimate
# --------------------------------------------------------------------------------------
def _table_at(tab: np.ndarray, lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    """Linear interpolation of a device table (n, NV) at ``x`` (as epi_table: clamped to
    the ends), one ``np.interp`` per column (a gather of whole rows costs ~5x more)."""
    n, nv = tab.shape
    xp = np.linspace(lo, hi, n) if hi > lo else np.full(n, lo)
    x = np.asarray(x, np.float64)
    out = np.empty(x.shape + (nv,))
    for c in range(nv):
        out[..., c] = np.interp(x, xp, tab[:, c]) if n > 1 else tab[0, c]
    return out


@functools.lru_cache(maxsize=8)
def gauss_legendre(nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [-1, 1] (cached: numpy computes them anew,
    ~1 ms per call)."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w


F32_SUM = 2.0 ** -24       # float32 unit roundoff (the tree's prefix sums)
F32_TINY = 2.0 ** -126     # the smallest normal float32


def k_at(axis: Axis, kap: float, g: float, gq: np.ndarray, beta: np.ndarray,
         refs: Refs) -> np.ndarray:
    """``K`` elementwise at ``(gq (N, Q), beta (N,))`` (the diagonal of :func:`core`)."""
    beta = np.asarray(beta, np.float64)
    return _k_values(axis, kap, g, np.asarray(gq, np.float64), beta[:, None],
                     refs.t_at(beta)[:, None], refs.l_at(gq), refs.soft)


def _entry_factor(axis: Axis, refs: Refs, le, lr, kap: float) -> np.ndarray:
    """The kernel's ``F`` without the cone (epi_light_factor): the light's entry ``le``
    relative to the reference ``lr = l_ref(gamma)``, its exponent clamped to the span."""
    with np.errstate(over="ignore", invalid="ignore"):    # a miss: le may be +-max float
        ex = kap * (le - lr) if axis.spot else kap * (lr - le)
    return np.exp(np.clip(ex, -refs.span * kap, refs.span * kap))


def _cone_coverage(gc, dg, lo, hi):
    """The fraction of each light-ray cell ``[gc - dg/2, gc + dg/2]`` inside a spot cone's
    gamma interval ``[lo, hi]`` (epi_light_factor's ``cov``)."""
    return np.clip((np.minimum(gc + 0.5 * dg, hi) - np.maximum(gc - 0.5 * dg, lo)) / dg,
                   0.0, 1.0)


def float32_error(axis: Axis, box, kappas, tables: Tables, refs: Refs, w, beta, g_a, g_b,
                  g0, g1, d: int, cone=None) -> np.ndarray:
    """The tree's float32 error per sample (worst channel), emulated: the leaves
    ``F Gamma_n dg`` of the sample's slice rounded to float32, the two prefix sums at its
    interval's ends summed pairwise in float32 (numpy's pairwise reduction: an error
    growing like log d, as the Fenwick tree's), combined with float32 ``B_n``, against the
    same in float64. Large where the tree holds values far above those the sample reads
    (a thick medium seen from outside in the plain formulation)."""
    nt = tables.terms
    B = _table_at(tables.btab, tables.b_lo, tables.b_hi, beta)
    worst = np.zeros(len(beta))
    for j in range(len(beta)):
        dg = max((g1[j] - g0[j]) / d, 1e-30)
        ma = float(np.clip((g_a[j] - g0[j]) / dg, 0.0, d))
        mb = float(np.clip((g_b[j] - g0[j]) / dg, 0.0, d))
        k_b = min(int(math.floor(mb)) + 1, d)
        gc = g0[j] + (np.arange(k_b) + 0.5) * dg
        if box is None and axis.spot:
            le = np.zeros(k_b)
        else:
            le, _ = light_entry(axis, box, w[j:j + 1], gc[None, :])
            le = np.nan_to_num(le[0])
        cov = 1.0 if cone is None else _cone_coverage(gc, dg, cone[0][j], cone[1][j])
        G = _table_at(tables.gtab, tables.g_lo, tables.g_hi, gc)
        lr = refs.l_at(gc)
        for c, kap in enumerate(kappas):
            F = cov * _entry_factor(axis, refs, le, lr, kap)
            leaf = (F[:, None] * G[:, c * nt:(c + 1) * nt] * dg)
            leaf32 = leaf.astype(np.float32)

            def q(m, L, dt):
                k = int(math.floor(m))
                out = L[:k].sum(0, dtype=dt) if k > 0 else np.zeros(nt, dt)
                if k < len(L):
                    out = out + dt(m - k) * L[k]
                return out
            b64 = B[j, c * nt:(c + 1) * nt]
            r64 = float(b64 @ (q(mb, leaf, np.float64) - q(ma, leaf, np.float64)))
            b32 = b64.astype(np.float32)
            r32 = float(np.dot(b32, q(mb, leaf32, np.float32) - q(ma, leaf32, np.float32)))
            if abs(r64) > 0:
                worst[j] = max(worst[j], abs(r32 - r64) / abs(r64))
    return worst


def riemann_sums(axis: Axis, box, kap: float, g: float, refs: Refs, w, beta, g_a, g_b,
                 g0, g1, d: int, cone=None, max_cells: int = 4096) -> np.ndarray:
    """What the sweep computes for samples without occluders, with the exact ``K``: the
    sum over the slice's ``d`` light rays (cells of width ``dg = (g1 - g0) / d``, values at
    the centres, the spot cone as coverage of the cell) of the overlap of each cell with
    ``[g_a, g_b]`` times ``F K`` (the fractional end cells of fw_query). In a thick medium
    seen from outside the end cells are where it goes wrong: a cell centre before the
    medium entry carries the analytic continuation of the view transmittance (plain
    formulation: ``exp(+kappa (t_a - t))``); the interior is a midpoint rule whose error
    grows as ``(kappa dt)^2``. Comparing ``d`` with ``2 d`` light rays estimates it
    (:func:`riemann_rel`). Per sample (N,); samples spanning more than ``max_cells`` cells
    are NaN. The method computes these sums on the device (``epi_riemann``,
    ``pipeline.DeviceRiemann``); this is their reference."""
    dg = np.maximum((g1 - g0) / d, 1e-30)        # an empty slice (g1 = g0) has no cells
    ma = np.clip((g_a - g0) / dg, 0.0, d)
    mb = np.clip((g_b - g0) / dg, 0.0, d)
    i0 = np.floor(ma).astype(int)
    ncell = np.minimum(np.ceil(mb).astype(int), d) - i0
    # the cells of all samples in one flat array (rows of a padded (N, max cells) array
    # would be half padding where the samples' intervals differ in length)
    nc = np.clip(ncell, 0, max_cells)
    row = np.repeat(np.arange(len(nc)), nc)
    start = np.cumsum(nc) - nc
    i = (i0[row] + np.arange(len(row)) - start[row])[:, None]       # (cells, 1)
    ov = np.clip(np.minimum(i + 1, mb[row, None]) - np.maximum(i, ma[row, None]), 0.0, 1.0)
    ov = np.where(i < d, ov, 0.0)
    dgr = dg[row, None]
    gc = g0[row, None] + (i + 0.5) * dgr
    if box is None and axis.spot:
        le, hit = np.zeros_like(gc), np.ones(gc.shape, bool)
    else:
        le, hit = light_entry(axis, box, np.asarray(w)[row], gc)
    cov = 1.0 if cone is None else _cone_coverage(gc, dgr, cone[0][row, None],
                                                  cone[1][row, None])
    # as the kernel: the entry is used for near misses too, clamped to the span
    F = cov * _entry_factor(axis, refs, le, refs.l_at(gc), kap)
    vals = (ov * dgr * F * k_at(axis, kap, g, gc, np.asarray(beta)[row], refs))[:, 0]
    out = np.bincount(row, weights=vals, minlength=len(nc))
    return np.where(ncell <= max_cells, out, np.nan)


def slice_error(axis: Axis, box, kappas, g: float, w: np.ndarray, w0: np.ndarray,
                w1: np.ndarray, f: np.ndarray, beta, g_a, g_b, cones=None,
                nodes: int = 32) -> np.ndarray:
    """Relative error per sample (worst channel) of reading a camera sample in its two
    neighbouring slices ``w0, w1`` (blended with weight ``f`` of ``w1``) instead of its own
    half-plane ``w``: the same (beta, gamma interval) meets other light rays there. Small
    where the light's transmittance varies slowly across slices; in a thick medium lit
    through a grazing box face it is not (the light's entry moves along the face by the
    slice spacing over sin(grazing angle)). ``cones``: the three planes' gamma intervals
    inside a spot cone. Exact integrals (Gauss-Legendre in gamma, no SVD)."""
    x, wq = gauss_legendre(nodes)
    gq = 0.5 * (g_a + g_b)[:, None] + 0.5 * (g_b - g_a)[:, None] * x[None, :]
    wgt = 0.5 * (g_b - g_a)[:, None] * wq[None, :]
    zero = Refs.zero((0.0, 1.0), (0.0, 1.0))
    vals = []
    for i, ww in enumerate((w, w0, w1)):
        if box is None and axis.spot:
            le = np.zeros_like(gq)
        else:
            # every node of the sample's own plane is inside the medium (its light ray
            # meets the box); in the neighbours' planes a light ray that just misses the
            # box keeps its entry's continuation, as in the kernel (epi_light_factor)
            le, _ = light_entry(axis, box, ww, gq)
        hit = np.isfinite(le)
        le = np.nan_to_num(le, nan=0.0, posinf=0.0, neginf=0.0)
        if cones is not None:
            hit &= (gq >= cones[i][0][:, None]) & (gq <= cones[i][1][:, None])
        vals.append((le, hit))
    worst = np.zeros(len(beta))
    for kap in kappas:
        K = k_at(axis, kap, g, gq, beta, zero)
        ints = []
        for le, hit in vals:
            ex = kap * le if axis.spot else -kap * le
            ints.append((wgt * np.where(hit, np.exp(np.clip(ex, -700, 700)), 0.0) * K).sum(1))
        blend = (1.0 - f) * ints[1] + f * ints[2]
        # relative to the sample's value, floored at a tenth of the samples' RMS: samples
        # whose interval just touches a spot cone's silhouette have next to no light of
        # their own and would dominate an unfloored ratio without mattering in the image
        floor = 0.1 * math.sqrt(float(np.mean(ints[0] ** 2))) if len(ints[0]) else 0.0
        den = np.maximum(ints[0], floor)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(den > 0, np.abs(blend - ints[0]) / den, 0.0)
        worst = np.maximum(worst, np.nan_to_num(rel, nan=0.0, posinf=0.0))
    return worst


def riemann_rel(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Relative light-ray discretisation error per sample from the sums with ``d`` and
    ``2 d`` light rays (``(N,)`` or ``(N, channels)``: the worst channel), estimated as
    ``(4/3) |R(d) - R(2d)| / R(2d)`` (midpoint rule: O(dg^2)); 0 where R(2d) is not
    positive or a sum is NaN."""
    r1, r2 = np.asarray(r1, np.float64), np.asarray(r2, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(r2 > 0, 4.0 / 3.0 * np.abs(r1 - r2) / r2, 0.0)
    rel = np.nan_to_num(rel, nan=0.0)
    return rel if rel.ndim == 1 else rel.max(axis=1, initial=0.0)


def _held_light(axis: Axis, box, w, gq, cone):
    """Light entries and hit masks of the held-out samples' slices ``w`` (N, 3) at the
    gamma nodes ``gq`` (N, Q) (the cone ``(lo, hi)`` per sample, or None)."""
    if box is None and axis.spot:
        le, hit = np.zeros_like(gq), np.ones(gq.shape, bool)
    else:
        le, hit = light_entry(axis, box, w, gq)
    if cone is not None:
        hit &= (gq >= cone[0][:, None]) & (gq <= cone[1][:, None])
    return le, hit


def _light_factor(axis: Axis, refs: Refs, le, hit, lr, kap: float) -> np.ndarray:
    """:func:`_entry_factor` where the light ray meets the medium (and its cone), else 0:
    the exact light factor of a held-out integral."""
    return np.where(hit, _entry_factor(axis, refs, le, lr, kap), 0.0)


def _gauss_rule(a: np.ndarray, b: np.ndarray, nodes: int):
    """Gauss-Legendre nodes (N, Q) and weights (N, Q) on the intervals ``[a, b]``."""
    x, wq = gauss_legendre(nodes)
    return (0.5 * (a + b)[:, None] + 0.5 * (b - a)[:, None] * x[None, :],
            0.5 * (b - a)[:, None] * wq[None, :])


def _held_rows(w, beta, g_a, g_b, cone, *extra):
    """The held-out samples with a non-empty finite gamma interval (and ``extra``
    per-sample arrays filtered alike)."""
    ok = (g_b > g_a) & np.isfinite(g_a) & np.isfinite(g_b)
    if cone is not None:
        cone = (cone[0][ok], cone[1][ok])
    return (w[ok], beta[ok], g_a[ok], g_b[ok], cone) + tuple(np.asarray(x)[ok] for x in extra)


def heldout_error(axis: Axis, box, kappas, g: float, tables: Tables, refs: Refs,
                  w: np.ndarray, beta: np.ndarray, g_a: np.ndarray, g_b: np.ndarray,
                  cone: tuple[np.ndarray, np.ndarray] | None = None, nodes: int = 48,
                  cache: dict | None = None) -> dict:
    """Relative error of whole view-ray integrals of held-out camera samples: for each
    (slice ``w`` (N, 3), ``beta``, gamma interval ``[g_a, g_b]``) and channel, the
    truncated SVD's ``|sum_q F (K_svd - K)| / sum_q F K`` over Gauss-Legendre nodes in
    gamma (not the SVD's samples), ``F`` the exact light factor of the sample's slice
    (light entry, spot cone), the tables interpolated as on the device.

    Returns the RMS and the 99th percentile over samples (worst channel), the sample
    count and the per-sample errors. ``cache``: a dict shared by calls that differ only
    in ``tables`` (nested truncations): the light entries are computed once."""
    w, beta, g_a, g_b, cone = _held_rows(w, beta, g_a, g_b, cone)
    if len(beta) == 0:
        return summarize(np.zeros(0))
    gq, wgt = _gauss_rule(g_a, g_b, nodes)
    if cache is not None and "le" in cache:
        le, hit = cache["le"]
    else:
        le, hit = _held_light(axis, box, w, gq, cone)
        if cache is not None:
            cache["le"] = (le, hit)
    lr = refs.l_at(gq)
    nt = tables.terms
    Gt = _table_at(tables.gtab, tables.g_lo, tables.g_hi, gq)          # (N, Q, NV)
    Bt = _table_at(tables.btab, tables.b_lo, tables.b_hi, beta)        # (N, NV)
    pb = pure_beta(axis, g, beta)
    tr = refs.t_at(beta)
    worst = np.zeros(len(beta))
    for c, kap in enumerate(kappas):
        F = _light_factor(axis, refs, le, hit, lr, kap)
        # the exact K at each node (the core on the diagonal of an outer grid)
        K = _k_values(axis, kap, g, gq, beta[:, None], tr[:, None], lr, refs.soft)
        sl = slice(c * nt, (c + 1) * nt)
        Ka = (Gt[..., sl] * Bt[:, None, sl]).sum(-1) / pb[:, None]
        exact = (wgt * F * K).sum(1)
        diff = np.abs((wgt * F * (Ka - K)).sum(1))
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(exact > 0, diff / exact, 0.0)
        worst = np.maximum(worst, rel)
    return summarize(worst)


def float32_bound(axis: Axis, box, kappas, tables: Tables, refs: Refs, w: np.ndarray,
                  beta: np.ndarray, g_a: np.ndarray, g_b: np.ndarray, g0: np.ndarray, d: int,
                  cone: tuple[np.ndarray, np.ndarray] | None = None, nodes: int = 48) -> np.ndarray:
    """A bound on the float32 tree's relative error per held-out sample (worst channel;
    the samples :func:`heldout_error` keeps), a few times cheaper than the emulation
    (:func:`float32_error`), which it exceeds wherever it was checked (the sweep of
    tests/test_epipolar.py, optical depth across the medium up to 14).

    The sweep forms ``sum_n B_n (Q_n(g_b) - Q_n(g_a))`` from prefix sums ``Q_n`` of the
    leaves ``F Gamma_n dg`` from ``g0`` (the slice's first light ray). A float32 sum of
    leaves through ``log2 d`` tree levels errs by at most ``(log2 d + 4) u sum |leaf|``
    (u = 2^-24; the 4 covers rounding the leaves, the subtraction and the dot product
    with ``B``), and each of at most ``d`` leaves may lose the smallest normal float
    (flushed to zero on some devices), so the result's relative error is at most

        ((log2 d + 4) u sum_n |B_n| (A_n(g_a) + A_n(g_b)) + d tiny sum_n |B_n|) / |result|

    with ``A_n(x) = int_g0^x |F Gamma_n|``: on Gauss-Legendre nodes, or the largest
    node's value times the interval where that is larger (a steep exponential the nodes
    do not resolve), doubled for the quadrature of ``|.|``. Large where the tree holds
    values far above those the pixel reads (a thick medium seen from outside in the plain
    formulation)."""
    w, beta, g_a, g_b, cone, g0 = _held_rows(w, beta, g_a, g_b, cone, g0)
    if len(beta) == 0:
        return np.zeros(0)
    g0 = np.minimum(np.asarray(g0, np.float64), g_a)
    gq, wgt = _gauss_rule(g_a, g_b, nodes)
    g0q, w0 = _gauss_rule(g0, g_a, nodes)
    le, hit = _held_light(axis, box, w, gq, cone)
    le0, hit0 = _held_light(axis, box, w, g0q, cone)
    lr, lr0 = refs.l_at(gq), refs.l_at(g0q)
    nt = tables.terms
    Gt = _table_at(tables.gtab, tables.g_lo, tables.g_hi, gq)
    G0 = np.abs(_table_at(tables.gtab, tables.g_lo, tables.g_hi, g0q))
    Bt = _table_at(tables.btab, tables.b_lo, tables.b_hi, beta)
    levels = math.log2(max(d, 2)) + 4.0
    bound = np.zeros(len(beta))
    for c, kap in enumerate(kappas):
        sl = slice(c * nt, (c + 1) * nt)
        F = _light_factor(axis, refs, le, hit, lr, kap)
        f0 = _light_factor(axis, refs, le0, hit0, lr0, kap)[..., None] * G0[..., sl]
        fab = F[..., None] * Gt[..., sl]
        res = np.abs((Bt[:, sl] * (wgt[..., None] * fab).sum(1)).sum(1))
        fab = np.abs(fab)
        a_ab = np.maximum((wgt[..., None] * fab).sum(1), (g_b - g_a)[:, None] * fab.max(1))
        a_a = np.maximum((w0[..., None] * f0).sum(1), (g_a - g0)[:, None] * f0.max(1))
        Bc = np.abs(Bt[:, sl])
        amp = 2.0 * levels * F32_SUM * (Bc * (2.0 * a_a + a_ab)).sum(1) \
            + 2.0 * d * F32_TINY * Bc.sum(1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            b = np.where(res > 0, amp / res, 0.0)
        bound = np.maximum(bound, np.nan_to_num(b, nan=0.0))
    return bound


SINGULAR_LIMIT = 1.0 / 40.0   # the paper's bound on s_N / s_1 (Sec. 6)


def accepts(singular: list, terms: int, error: dict, tolerance: float) -> bool:
    """Whether ``terms`` terms are good enough: the held-out error's RMS within the
    tolerance *and* the paper's claim for the last term kept, ``s_N <= s_1 / 40`` in every
    channel (the second guards the estimate's sampling: where the claim fails, e.g. a spot
    light behind the camera, the terms are raised even if 600 samples look fine)."""
    ok = error["rms"] <= tolerance
    for sv in singular:
        if len(sv) >= terms and sv[0] > 0 and sv[terms - 1] > SINGULAR_LIMIT * sv[0]:
            ok = False
    return bool(ok)


def rms(x: np.ndarray) -> float:
    """Root mean square of ``x`` (0 for an empty array)."""
    x = np.asarray(x, np.float64)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else 0.0


# a per-sample relative error that is not a number (an overflow in a thick medium's
# exponentials) counts as this: far above any tolerance, finite in --stats
NONFINITE_ERROR = 1e6


def summarize(rel: np.ndarray) -> dict:
    """RMS, 99th percentile and count of per-sample relative errors (``errors``: the
    array itself, dropped before --stats). Non-finite errors count as
    ``NONFINITE_ERROR`` (dropping them would let an estimate whose samples overflowed
    pass), and how many there were is ``nonfinite``."""
    rel = np.asarray(rel, np.float64)
    bad = ~(rel < NONFINITE_ERROR)          # NaN, inf, and errors summarized once already
    rel = np.where(bad, NONFINITE_ERROR, rel)
    return {"rms": rms(rel), "p99": _percentile(rel, 99.0), "samples": int(len(rel)),
            "nonfinite": int(bad.sum()), "errors": rel}


def _percentile(x: np.ndarray, q: float) -> float:
    """``np.percentile(x, q)`` (linear interpolation) for the few hundred errors of an
    estimate, by a sort: np.percentile's first call in a process costs ~20 ms of imports."""
    if not len(x):
        return 0.0
    xs = np.sort(x)
    pos = q / 100.0 * (len(xs) - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, len(xs) - 1)
    return float(xs[lo] + (pos - lo) * (xs[hi] - xs[lo]))
