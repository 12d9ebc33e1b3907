"""Progressive surface density estimation (``photonmap``, ``raymap``;
``clscatter/estimators/surface_passes.py``): the radius rule in closed form, the per-query
radius kernel against NumPy, refinement converging on the glass ball's floor caustic, the
automatic radius's scale invariance, and a budgeted run on a fake clock."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from test_invariance import transform_scene
from test_raymap_density import _density_np

from clscatter.estimators import surface_passes
from clscatter.estimators.knn_queries import RayMap
from clscatter.estimators.ray_density import DensitySettings, estimate_on_device
from clscatter.estimators.segment_tree import TreeParams
from clscatter.io.stats import Stats
from clscatter.methods import get_method
from clscatter.scene import load_scene, scene_from_dict
from clscatter.scene.builtin import BUILTIN
from clscatter.transport.context import PassContext
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

ESTIMATORS = ["photonmap", "raymap"]


class FakeClock:
    """A clock that moves only when told to."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_ppm_scales_closed_form():
    """s_n^2 = prod_{i<n} (i + a) / (i + 1) = Gamma(n + a) / (Gamma(1 + a) Gamma(n + 1)),
    to 1e-12, for a in (2/3, 0.7, 0.5)."""
    for a in (2.0 / 3.0, 0.7, 0.5):
        s = surface_passes.ppm_scales(a, 40)
        n = np.arange(1, 41)
        want = np.exp(0.5 * np.array([math.lgamma(k + a) - math.lgamma(1 + a) - math.lgamma(k + 1)
                                      for k in n]))
        assert s[0] == 1.0
        assert np.allclose(s, want, rtol=1e-12, atol=0)
        assert np.all(np.diff(s) < 0)


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_per_query_radius_matches_numpy(engine, estimator):
    """rm_density with a radius per query (later passes) and its R read back: each query's
    estimate equals the NumPy reference at that query's radius (rtol 2e-4), and R is the
    k-th distance where k rays lie within, else the query's radius."""
    rng = np.random.default_rng(5)
    m = 3000
    b = np.c_[rng.uniform(-0.5, 0.5, m), rng.uniform(-0.05, 0.02, m), rng.uniform(-0.5, 0.5, m)]
    d = np.c_[rng.normal(0, 0.4, m), -np.ones(m), rng.normal(0, 0.4, m)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = b - rng.uniform(0.1, 0.6, m)[:, None] * d
    flux = rng.uniform(0.5, 1.5, (m, 3))
    nq = 48
    x = np.c_[rng.uniform(-0.4, 0.4, nq), np.zeros(nq), rng.uniform(-0.4, 0.4, nq)]
    n = np.tile([0.0, 1.0, 0.0], (nq, 1))
    radii = rng.uniform(0.02, 0.12, nq).astype(np.float32)
    s = DensitySettings(k=64, kernel="epanechnikov", max_radius=0.5, batch=20,
                        tree=TreeParams(c_min=16, alpha_deg=10.0, dir_min_depth=2, dir_max_diag=1.0))
    rm = RayMap(engine, a, b, d, flux, s.tree, points=estimator == "photonmap", lazy=True)
    r_buf = engine.empty(4 * nq)
    e_buf, w_buf = estimate_on_device(rm, x, n, estimator, s, radii=radii, out_r=r_buf)
    got = engine.read(e_buf, (nq, 4), np.float32)[:, :3]
    got_r = engine.read(r_buf, nq, np.float32)
    engine.free(e_buf, w_buf, r_buf)
    rm.release()
    pts_a = b if estimator == "photonmap" else a
    want = np.array([_density_np(estimator, x[q], n[q], pts_a, b, d, flux, 64, float(radii[q]),
                                 "epanechnikov") for q in range(nq)])
    assert want.min() > 0
    assert np.allclose(got, want, rtol=2e-4, atol=0)
    assert np.all(got_r <= radii) and np.any(got_r == radii) and np.any(got_r < radii)


@pytest.fixture(scope="module")
def ball(engine):
    scene = load_scene("builtin:caustic_sphere", ["camera.resolution=[48,36]", "camera.spp=1"])
    ps = prepare_scene(scene, engine)
    paths = trace_view_paths(ps, Stats(), False)
    yield ps, paths
    paths.release()
    ps.release()


def _surface(ps, paths, method: str, params: dict, **ctx_kw) -> tuple[np.ndarray, dict]:
    stats = Stats()
    with PassContext(ps, paths, stats, False, **ctx_kw) as ctx:
        img = get_method(method)(params).render(ctx).surface
    return img, stats.to_dict()


@pytest.mark.parametrize("method", ESTIMATORS)
def test_progressive_passes_converge(ball, method):
    """Floor caustic of the glass ball (48 x 36, 1 spp), against a long run (12 passes of
    20000 rays, k = 64): 16 passes of 2000 rays (k = 16) have at most 0.75 x the relative
    RMS error of one such pass (measured: 0.0120 -> 0.0049, both methods), the radius
    shrinks by s_16, and the passes' error estimate is reported."""
    ps, paths = ball
    ref, _ = _surface(ps, paths, method, {"photons": 20000, "passes": 12})

    def err(img):
        return float(np.sqrt(np.mean((img - ref) ** 2)) / np.sqrt(np.mean(ref ** 2)))

    one, _ = _surface(ps, paths, method, {"photons": 2000, "passes": 1, "k": 16})
    many, st = _surface(ps, paths, method, {"photons": 2000, "passes": 16, "k": 16})
    assert st[f"{method}_passes"] == 16
    # the 15 later passes splat: their work is counted apart from the K-nearest pass's,
    # which splats only for the hits whose K nearest lie within their camera sample's cell
    assert st[f"{method}_splat_hits_tested"] > 0 and st[f"{method}_refs_tested"] > 0
    single = _surface(ps, paths, method, {"photons": 2000})[1]
    assert (f"{method}_splat_hits_tested" in single) == (single[f"{method}_cell_floored"] > 0)
    print(f"\n{method}: relative RMS error {err(one):.4f} (1 pass), {err(many):.4f} (16)")
    assert err(many) <= 0.75 * err(one), (err(one), err(many))
    s16 = surface_passes.ppm_scales(2.0 / 3.0, 16)[-1]
    assert st[f"{method}_radius_last"] == pytest.approx(st[f"{method}_radius"] * s16, rel=1e-12)
    assert st[f"{method}_error_estimate"] is not None and st[f"{method}_error_estimate"] > 0


@pytest.mark.parametrize("method", ESTIMATORS)
def test_automatic_radius_is_scale_invariant(engine, method):
    """The glass-ball scene scaled by 100 (every length; optical depths and irradiance
    kept, tests/test_invariance.py) gives the same normalised automatic radius (1e-6
    relative), 100x the world radius, and the same image after 3 passes (4e-7 of the
    peak)."""
    d = BUILTIN["caustic_sphere"]()
    d["camera"].update(resolution=[24, 18], spp=1)
    d["render"].update(seed=7)
    out = []
    for scale in (1.0, 100.0):
        scene = scene_from_dict(transform_scene(copy.deepcopy(d), scale, 0.0))
        ps = prepare_scene(scene, engine)
        paths = trace_view_paths(ps, Stats(), False)
        try:
            out.append(_surface(ps, paths, method, {"photons": 3000, "passes": 3}))
        finally:
            paths.release()
            ps.release()
    (a, sa), (b, sb) = out
    assert sa[f"{method}_radius"] > 0
    assert sb[f"{method}_radius"] == pytest.approx(sa[f"{method}_radius"], rel=1e-6)
    assert sb[f"{method}_radius_world"] == pytest.approx(100 * sa[f"{method}_radius_world"], rel=1e-6)
    assert float(np.max(np.abs(a - b))) <= 4e-7 * float(np.max(np.abs(a)))


@pytest.mark.parametrize("method", ESTIMATORS)
def test_budgeted_passes_keep_the_budget_on_a_fake_clock(ball, method, monkeypatch):
    """Every pass's tracing advances a fake clock by 1 s; with a 5.5 s deadline and 100
    passes allowed, the passes stop by the time budget within 1.2x of it, after several."""
    ps, paths = ball
    clock = FakeClock()
    real = surface_passes.caustic_pieces

    def costly(*a, **kw):
        clock.now += 1.0
        return real(*a, **kw)

    monkeypatch.setattr(surface_passes, "caustic_pieces", costly)
    started = clock()
    _, st = _surface(ps, paths, method, {"photons": 1000, "passes": 100},
                     deadline=clock() + 5.5, clock=clock)
    assert clock() - started <= 1.2 * 5.5
    assert st[f"{method}_stopped_by"] == "time_budget"
    assert 3 <= st[f"{method}_passes"] <= 6


@pytest.mark.parametrize("method", ESTIMATORS)
def test_overrun_note_names_what_a_sized_first_pass_is_left_with(ball, method, monkeypatch):
    """A first pass sized down from the learnt cost (1e-4 s per ray and hit: 1 s of a 4 s
    deadline shared by 4 planned passes) that still overruns (the fake clock: 1 s per 2,000
    rays) says that what is left is its rays over every diffuse hit, and names k and the
    resolution, not the photon count it no longer traces all of."""
    ps, paths = ball
    clock = _tracing_costs_a_second_per_10000_rays(monkeypatch, rays_per_second=2000)
    _, st = _surface(ps, paths, method, {"photons": 40000, "passes": 4}, deadline=4.0,
                     clock=clock, costs=(lambda stage, work: 1e-4 * work, lambda *a: None))
    rays = st[f"{method}_pass_rays"][0]
    assert rays < 40000 and st[f"{method}_sized_from"] == "calibration"
    note = [n for n in st["notes"] if "first pass alone" in n]
    assert len(note) == 1, st["notes"]
    assert (f"a first pass, in which each of the {st['diffuse_hits']} diffuse hits gathers "
            f"its k nearest of {rays} lighting rays, is the smallest unit of work") in note[0]
    assert f"render.{method}.k" in note[0] and f"render.{method}.photons" not in note[0]


def test_sized_rays_rule():
    """Rays for a pass from a measured one: in proportion to the time wanted, at most the
    parameter's count, at least MIN_PASS_RAYS, within RESIZE of the measured pass."""
    sized = surface_passes.sized_rays
    assert sized(40000, None, 1.0) == 40000
    assert sized(40000, (40000, 4.0), 1.0) == 10000
    assert sized(40000, (10000, 1.0), 100.0) == 40000            # never beyond the parameter
    assert sized(40000, (40000, 4.0), 1e-6) == 40000 / surface_passes.RESIZE
    assert sized(40000, (2000, 4.0), 1e-3) == surface_passes.MIN_PASS_RAYS
    assert sized(1000, (1000, 4.0), 1e-3) == 1000                # fewer than the least: all


def _tracing_costs_a_second_per_10000_rays(monkeypatch, rays_per_second: float = 10000.0
                                            ) -> FakeClock:
    """A fake clock that the surface passes' lighting rays advance by 1 s per 10,000 (or
    per ``rays_per_second``)."""
    clock = FakeClock()
    real = surface_passes.caustic_pieces

    def costly(ps_, rays, *a, **kw):
        clock.now += rays / rays_per_second
        return real(ps_, rays, *a, **kw)

    monkeypatch.setattr(surface_passes, "caustic_pieces", costly)
    return clock


@pytest.mark.parametrize("method", ESTIMATORS)
def test_budgeted_passes_are_sized_from_an_earlier_first_pass(ball, method, monkeypatch):
    """Tracing advances a fake clock by 1 s per 10,000 rays; 40,000 rays a pass, 4 passes
    planned. Nothing measured yet: the passes trace all 40,000 rays each and stop by a
    10 s deadline after two (4 s each; a third would end at 12 s). A second render given
    the first's first-pass cost (a session's cache) and a 2 s deadline sizes its passes to
    2 s / 4 (5,000 rays), all alike, and keeps the budget within 1.2x."""
    ps, paths = ball
    clock = _tracing_costs_a_second_per_10000_rays(monkeypatch)
    started = clock()
    cache = {}
    params = {"photons": 40000, "passes": 4}
    _, st = _surface(ps, paths, method, params, deadline=clock() + 10.0, clock=clock, cache=cache)
    assert st[f"{method}_pass_rays"] == [40000, 40000]
    assert clock() - started <= 10.0
    started = clock()
    _, st = _surface(ps, paths, method, params, deadline=clock() + 2.0, clock=clock, cache=cache)
    rays = st[f"{method}_pass_rays"]
    assert len(rays) == 4 and all(r == pytest.approx(5000, abs=1) for r in rays), rays
    assert clock() - started <= 1.2 * 2.0
    assert st[f"{method}_sized_from"] == "session"


@pytest.mark.parametrize("method", ESTIMATORS)
def test_budgeted_first_pass_is_sized_from_the_devices_learnt_cost(ball, method, monkeypatch):
    """No earlier pass in the session, but the device has learnt 1e-4 s per lighting ray
    plus diffuse hit for a first pass (``ctx.predict``): 40,000 rays, 4 passes planned
    under a 4 s deadline are sized to 1 s / (1e-4 (40,000 + hits)) of the 40,000 rays
    each, the budget holds, and the first pass's own cost is learnt (``ctx.learn``, work
    = its rays plus the hits). Tracing advances a fake clock by 1 s per 10,000 rays."""
    ps, paths = ball
    clock = _tracing_costs_a_second_per_10000_rays(monkeypatch)
    asked, learnt = [], []

    def predict(stage, work):
        asked.append((stage, work))
        return 1e-4 * work

    def learn(stage, work, seconds):
        learnt.append((stage, work, seconds))

    started = clock()
    _, st = _surface(ps, paths, method, {"photons": 40000, "passes": 4},
                     deadline=clock() + 4.0, clock=clock, costs=(predict, learn))
    hits = st["diffuse_hits"]
    want = 40000 * 1.0 / (1e-4 * (40000 + hits))
    rays = st[f"{method}_pass_rays"]
    assert asked == [(f"{method}_first_pass", 40000 + hits)]
    assert len(rays) == 4 and all(r == pytest.approx(want, abs=1) for r in rays), (rays, want)
    assert st[f"{method}_sized_from"] == "calibration"
    assert clock() - started <= 1.2 * 4.0
    assert learnt == [(f"{method}_first_pass", rays[0] + hits, pytest.approx(rays[0] / 1e4))]
    # many passes allowed: the deadline is still shared among at most MAX_SPLIT when
    # sizing them (4 s / 4 passes again, not 4 s / 1000)
    _, st = _surface(ps, paths, method, {"photons": 40000, "passes": 1000},
                     deadline=clock() + 4.0, clock=clock, costs=(predict, learn))
    assert st[f"{method}_pass_rays"][0] == pytest.approx(want, abs=1)
    # without a deadline nothing is predicted and every pass traces all its rays
    asked.clear()
    _, st = _surface(ps, paths, method, {"photons": 4000, "passes": 2}, clock=clock,
                     costs=(predict, learn))
    assert asked == [] and st[f"{method}_pass_rays"] == [4000, 4000]
    assert st[f"{method}_sized_from"] == "none"
