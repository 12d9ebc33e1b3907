"""The paper's bias study (Havran et al. 2005, Sec. 4.3, Fig. 4): density estimation on a
convex and a concave corner lit by parallel rays and on a wave surface lit by cosine and
parallel rays, photon map against the ray map's hemisphere-disc. 100,000 rays, K = 200,
Epanechnikov kernel as in the paper; the reference is the flux of 50x more rays landing in
small patches of the surface, over the patches' true area. Estimates are averaged over 24
positions along the extruded (z) direction, which averages noise out and leaves the bias.

Measured (this file's seeds; mean |E / E_ref - 1| over the path points within 0.02 of the
edge for the corners (inside the typical estimation radius R ~ 0.025), over one period
for the wave, there for the estimate averaged over 8 ray sets (one set's ~2 % noise
hides the bias); the reference itself has ~1.5 % noise, none for parallel rays on the
wave, where it is exact):

=========================  ==========  ===================
scene                      photon map  ray map (hemi-disc)
=========================  ==========  ===================
convex corner (edge)       36.4 %      1.5 %
concave corner             33.8 %      7.9 %
wave, cosine rays          1.2 %       2.3 %
wave, parallel rays        1.6 %       0.64 %
=========================  ==========  ===================

On the wave the ray map is better with parallel rays and worse with cosine-distributed
ones (low around the trough); see test_wave_topological_bias.

At the convex edge the photon map falls to 0.51 of the true irradiance (half its disc
is off the surface); the ray map stays within 1.2 %. In the concave corner the photon
map also reads 0.51 at the corner line, the ray map 0.84: rays that the wall stops more
than R above the floor do not meet the hemisphere although their prolongation meets
the disc, so part of the disc behind the wall stays uncounted.
"""
from __future__ import annotations

import numpy as np
import pytest
from bias_scenes import Z, concave_corner, convex_corner, wave, wave_dy, wave_y

from clscatter.estimators.knn_queries import RayMap
from clscatter.estimators.ray_density import DensitySettings, estimate
from clscatter.estimators.segment_tree import TreeParams

N_RAYS, K, REF_FACTOR = 100_000, 200, 50
Z_EVAL = 0.35        # estimates (and the wave's reference) over |z| <= Z_EVAL: the source is finite in z
SETTINGS = DensitySettings(k=K, kernel="epanechnikov", max_radius=0.2, batch=4096,
                           tree=TreeParams())


def _reference(scene, rng, bins, area):
    """Flux of REF_FACTOR x N_RAYS rays landing in x-bins of the surface / true areas."""
    acc = np.zeros(len(bins) - 1)
    for _ in range(REF_FACTOR // 10):
        o, b, d, f, on = scene(10 * N_RAYS, rng)
        acc += np.histogram(b[on, 0], bins)[0] * f / (REF_FACTOR // 10)
    return acc / area


def _estimates(engine, o, b, d, f, on, xs, ys, normals):
    zs = np.linspace(-Z_EVAL, Z_EVAL, 24)
    q = np.array([[x, y, z] for x, y in zip(xs, ys) for z in zs])
    nq = np.repeat(normals, len(zs), axis=0)
    out = {}
    flux = np.full((len(o), 3), f)
    for est in ("photonmap", "raymap"):
        if est == "photonmap":
            rm = RayMap(engine, b[on], b[on], d[on], flux[on], SETTINGS.tree, points=True, lazy=True)
        else:
            rm = RayMap(engine, o, b, d, flux, SETTINGS.tree, lazy=True)
        e, _ = estimate(rm, q, nq, est, SETTINGS)
        rm.release()
        out[est] = e[:, 0].reshape(len(xs), len(zs)).mean(1)
    return out


_REPORT: dict = {}


def _errors(name, est, ref, near):
    res = {k: float(np.mean(np.abs(v[near] / ref[near] - 1))) for k, v in est.items()}
    res_all = {k + "_all": float(np.mean(np.abs(v / ref - 1))) for k, v in est.items()}
    _REPORT[name] = {**res, **res_all}
    print(name, _REPORT[name])
    print("  ref", np.round(ref, 3), {k: np.round(v, 3) for k, v in est.items()})
    return res


@pytest.mark.parametrize("kind", ["convex", "concave"])
def test_corner_boundary_bias(engine, kind):
    rng = np.random.default_rng(21 if kind == "convex" else 22)
    scene = convex_corner if kind == "convex" else concave_corner
    o, b, d, f, on = scene(N_RAYS, rng)
    s = np.array([0.001, 0.003, 0.006, 0.01, 0.015, 0.02, 0.03, 0.05, 0.08, 0.12])
    xs = -s if kind == "convex" else s                 # along the lit face, towards the edge
    e = _estimates(engine, o, b, d, f, on, xs, np.zeros_like(xs), np.tile([0.0, 1.0, 0.0], (len(xs), 1)))
    h = 0.001
    bins = np.sort(np.r_[xs - h, xs + h])
    ref = _reference(scene, np.random.default_rng(99), bins, 2 * h * 2 * Z)[::2]
    ref = ref if kind == "concave" else ref            # bins are sorted by x
    order = np.argsort(xs)
    ref_at = np.empty_like(ref)
    ref_at[order] = ref
    assert np.allclose(ref_at, 1.0, rtol=0.05)         # the reference: uniform irradiance 1
    err = _errors(kind + "_corner", e, ref_at, s <= 0.02)
    # the hemisphere-disc removes the convex edge's boundary bias and most of the concave
    # corner's (there, rays stopped by the wall higher than R above the floor miss the
    # hemisphere although their prolongation meets the disc: ~0.84 at the corner line)
    assert err["raymap"] < (0.03 if kind == "convex" else 0.12)
    assert err["photonmap"] > 3 * err["raymap"]


WAVE_SEEDS = 8       # ray sets per wave: the claims are about the estimators, not one set


@pytest.mark.parametrize("cosine", [True, False])
def test_wave_topological_bias(engine, cosine):
    """The wave, estimates from WAVE_SEEDS independent ray sets of N_RAYS each. What one
    ray set shows is mostly its noise (~2 % per point): with one set the ray map beat the
    photon map for some seeds and lost for others. Averaged over the sets the noise falls
    (~0.7 % per point for 8 sets) and the bias shows. Seed study, 12 ray sets per wave
    (seeds 31/32 and 1001 .. 1011), error = mean |E / E_ref - 1| over the period:

    * parallel rays (exact reference: E = cos of the slope): the seed-averaged estimate's
      error is 0.34 % for the ray map, 1.5 % for the photon map, whose disc straddles
      crests and troughs; per set the ray map's error is lower in 11 of 12 sets (1.77 %
      against 2.20 % on average). Here (8 sets): 0.64 % against 1.60 %, per set 1.74 %
      against 2.16 %. Asserted: the ray map's seed-averaged error under 0.7 x the photon
      map's and under 1.2 %, and lower on average per set.
    * cosine-distributed rays (reference: 50 x more rays): the ray map is *not* better:
      seed-averaged error 1.7 % against 1.0 % for the photon map (per set 2.6 % against
      2.0 %); it reads 4-6 % low around the trough, where grazing rays are stopped by the
      crests before they meet the hemisphere (the concave corner's effect, smaller). Here
      (8 sets): 2.29 % against 1.16 %, per set 2.88 % against 2.04 %. Asserted: both
      seed-averaged errors within 2x of that (photon map < 2 %, ray map < 3.5 %), nothing
      about which is lower.
    """
    xs = np.linspace(-0.25, 0.0, 11)                   # one period: crest, trough
    ys = wave_y(xs)
    nrm = np.c_[-wave_dy(xs), np.ones_like(xs), np.zeros_like(xs)]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    h = 0.002
    fine = np.linspace(-h, h, 201)
    arc = np.array([np.trapezoid(np.sqrt(1 + wave_dy(x + fine) ** 2), x + fine) for x in xs])
    acc = np.zeros(len(xs))
    rr = np.random.default_rng(98)
    for _ in range(REF_FACTOR // 10):
        o2, b2, _, f2, _ = wave(10 * N_RAYS, rr, cosine, (xs[0] - h, xs[-1] + h))
        idx = np.searchsorted(xs - h, b2[:, 0]) - 1
        ok = (idx >= 0) & (idx < len(xs)) & (b2[:, 0] <= xs[np.clip(idx, 0, len(xs) - 1)] + h)
        ok &= np.abs(b2[:, 2]) <= Z_EVAL              # where the estimates are taken
        acc += np.bincount(idx[ok], minlength=len(xs)) * f2 / (REF_FACTOR // 10)
    ref = acc / (arc * 2 * Z_EVAL)
    if not cosine:                                     # parallel: E = cos of the slope, exactly
        assert np.allclose(ref, nrm[:, 1], rtol=0.02)  # (the reference's method, checked)
        ref = nrm[:, 1]
    runs = []
    for seed in range(WAVE_SEEDS):
        o, b, d, f, on = wave(N_RAYS, np.random.default_rng(1000 + seed), cosine)
        runs.append(_estimates(engine, o, b, d, f, on, xs, ys, nrm))
    name = "wave_" + ("cosine" if cosine else "parallel")
    per_set = {k: float(np.mean([np.mean(np.abs(r[k] / ref - 1)) for r in runs]))
               for k in ("photonmap", "raymap")}
    averaged = {k: np.mean([r[k] for r in runs], axis=0) for k in ("photonmap", "raymap")}
    err = _errors(name, averaged, ref, np.ones(len(xs), bool))
    print(name, "per set", per_set)
    if cosine:
        assert err["photonmap"] < 0.02 and err["raymap"] < 0.035, err
    else:
        # over a period the hemisphere-disc has less topological bias at crests and
        # troughs than the photon map's disc
        assert err["raymap"] < min(0.7 * err["photonmap"], 0.012), err
        assert per_set["raymap"] < per_set["photonmap"], per_set
