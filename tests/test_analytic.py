"""Tests of the analytic / quadrature references in ``tests/analytic.py``."""
from __future__ import annotations

import math

import numpy as np
import pytest

try:  # tests/ as a rootdir-inserted folder (no __init__.py) or as a package
    import analytic as A
except ImportError:  # pragma: no cover
    from tests import analytic as A


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perp(w):
    """A unit vector perpendicular to w."""
    a = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return _unit(np.cross(w, a))


LIGHT = np.array([0.7, 1.9, -0.4])
O = np.array([0.1, 0.3, 3.2])


def _near_light_rays(h_values):
    """Directions from O whose line passes at exactly distance h from LIGHT."""
    to = LIGHT - O
    dist = np.linalg.norm(to)
    w0 = to / dist
    n = _perp(w0)
    dirs = []
    for h in h_values:
        ang = math.asin(h / dist)
        dirs.append(math.cos(ang) * w0 + math.sin(ang) * n)
    return np.array(dirs)


# --------------------------------------------------------------------------------------
# phase function
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("g", [-0.8, -0.3, 0.0, 0.5, 0.9])
def test_hg_normalised(g):
    from scipy import integrate

    val = integrate.quad(lambda c: 2 * math.pi * float(A.hg(c, g)), -1, 1, epsabs=0, epsrel=1e-12,
                         limit=200)[0]
    assert val == pytest.approx(1.0, rel=1e-9)
    assert float(A.hg(0.3, 0.0)) == pytest.approx(1 / (4 * math.pi), rel=1e-15)
    if g != 0:  # forward scattering: g > 0 favours cos = +1 (light keeps going to the eye)
        assert (A.hg(1.0, g) > A.hg(-1.0, g)) == (g > 0)


# --------------------------------------------------------------------------------------
# point light
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("t_max", [np.inf, 6.0, 1.5])
def test_point_quad_vs_closed_form(t_max):
    rng = np.random.default_rng(7)
    dirs = np.concatenate([
        _near_light_rays([1e-6, 1e-3, 1e-2, 0.1, 1.0]),
        _unit(rng.normal(size=(10, 3))),
        -_near_light_rays([1e-3, 0.2]),            # light behind the camera
    ])
    ref = A.airlight_point_closed_form(O, dirs, LIGHT, 7.0, 0.3, t_max=t_max)
    for method in ("quad", "quad_t", "gauss"):
        got = A.airlight_point(O, dirs, LIGHT, 7.0, 0.3, 0.0, 0.0, t_max=t_max, method=method)
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=0, err_msg=method)
    # the angle form itself is far better than 1e-6
    got = A.airlight_point(O, dirs, LIGHT, 7.0, 0.3, 0.0, 0.0, t_max=t_max)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=0)


def test_point_closed_form_textbook_formula():
    """The per-side atan2 evaluation equals the textbook atan difference."""
    rng = np.random.default_rng(3)
    dirs = _unit(rng.normal(size=(20, 3)))
    w = dirs
    t_c = (LIGHT - O) @ w.T
    h = np.linalg.norm(O + t_c[:, None] * w - LIGHT, axis=1)
    for t_max in (np.inf, 2.5):
        text = 0.3 * 7.0 / (4 * math.pi * h) * (np.arctan((t_max - t_c) / h) - np.arctan(-t_c / h))
        np.testing.assert_allclose(A.airlight_point_closed_form(O, dirs, LIGHT, 7.0, 0.3, t_max),
                                   text, rtol=1e-12)


def test_point_through_light():
    # light ahead on the ray: infinite; light behind: 1/d^2 integral along the axis
    d = LIGHT - O
    assert np.isinf(A.airlight_point(O, d, LIGHT, 1.0, 0.2, 0.1, 0.3)[0])
    assert np.isinf(A.airlight_point_closed_form(O, d, LIGHT, 1.0, 0.2)[0])
    r = np.linalg.norm(d)
    ref = 0.2 * 1.0 / (4 * math.pi) * (1 / r - 1 / (r + 2.0))
    assert A.airlight_point_closed_form(O, -d, LIGHT, 1.0, 0.2, t_max=2.0)[0] == pytest.approx(ref, rel=1e-12)
    assert A.airlight_point(O, -d, LIGHT, 1.0, 0.2, 0.0, 0.0, t_max=2.0)[0] == pytest.approx(ref, rel=1e-10)
    # light beyond the end of the segment
    ref2 = 0.2 / (4 * math.pi) * (1 / (r - 1.0) - 1 / r)
    assert A.airlight_point_closed_form(O, d, LIGHT, 1.0, 0.2, t_max=1.0)[0] == pytest.approx(ref2, rel=1e-12)
    assert A.airlight_point(O, d, LIGHT, 1.0, 0.2, 0.0, 0.0, t_max=1.0)[0] == pytest.approx(ref2, rel=1e-10)


@pytest.mark.parametrize("g", [-0.6, 0.4, 0.85])
def test_point_reversal_symmetry(g):
    """kappa = 0: a segment seen from its far end with -g gives the same radiance
    (every phase cosine changes sign when the view direction is reversed)."""
    rng = np.random.default_rng(11)
    dirs = np.concatenate([_near_light_rays([1e-3, 0.05, 0.7]), _unit(rng.normal(size=(6, 3)))])
    T = 5.0
    fwd = A.airlight_point(O, dirs, LIGHT, 3.0, 0.4, 0.0, g, t_max=T)
    ends = O + T * dirs
    back = A.airlight_point(ends, -dirs, LIGHT, 3.0, 0.4, 0.0, -g, t_max=T)
    np.testing.assert_allclose(back, fwd, rtol=1e-9)
    # g != 0 breaks the symmetry without the sign change
    same = A.airlight_point(ends, -dirs, LIGHT, 3.0, 0.4, 0.0, g, t_max=T)
    assert np.max(np.abs(same / fwd - 1)) > 1e-2


def test_point_rotation_invariance():
    rng = np.random.default_rng(5)
    dirs = np.concatenate([_near_light_rays([1e-3, 0.3]), _unit(rng.normal(size=(6, 3)))])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    shift = np.array([3.0, -1.0, 2.0])
    a = A.airlight_point(O, dirs, LIGHT, 2.0, 0.3, 0.25, 0.6, t_max=8.0)
    b = A.airlight_point(q @ O + shift, dirs @ q.T, q @ LIGHT + shift, 2.0, 0.3, 0.25, 0.6, t_max=8.0)
    np.testing.assert_allclose(b, a, rtol=1e-9)


def _trapezoid_point(o, w, light, intensity, sigma_s, kappa, g, t_max, n=200_001):
    """Brute force: trapezoid in t on a grid that is dense near the closest approach."""
    t_c = float((light - o) @ w)
    h = float(np.linalg.norm(o + t_c * w - light))
    # t = t_c + h sinh(xi): spacing ~ h near the peak, growing geometrically away
    xi = np.linspace(math.asinh((0.0 - t_c) / h), math.asinh((t_max - t_c) / h), n)
    t = t_c + h * np.sinh(xi)
    x = o + t[:, None] * w
    dv = x - light
    d = np.linalg.norm(dv, axis=1)
    cos = -(dv @ w) / d
    f = sigma_s * A.hg(cos, g) * intensity / d**2 * np.exp(-kappa * (d + t))
    return np.trapezoid(f, t)


@pytest.mark.parametrize("kappa,g", [(0.3, 0.5), (1.2, -0.7), (0.05, 0.9), (0.0, -0.3)])
def test_point_vs_trapezoid(kappa, g):
    rng = np.random.default_rng(13)
    dirs = np.concatenate([_near_light_rays([1e-3, 0.02, 0.5]), _unit(rng.normal(size=(4, 3))),
                           -_near_light_rays([0.1])])
    t_max = 12.0
    got = A.airlight_point(O, dirs, LIGHT, 5.0, 0.25, kappa, g, t_max=t_max)
    for i, w in enumerate(dirs):
        ref = _trapezoid_point(O, w, LIGHT, 5.0, 0.25, kappa, g, t_max)
        assert got[i] == pytest.approx(ref, rel=1e-4)
    gauss = A.airlight_point(O, dirs, LIGHT, 5.0, 0.25, kappa, g, t_max=t_max, method="gauss")
    np.testing.assert_allclose(gauss, got, rtol=1e-8)


def test_point_methods_agree_unbounded_attenuating():
    rng = np.random.default_rng(17)
    dirs = np.concatenate([_near_light_rays([1e-5, 1e-3, 0.3]), _unit(rng.normal(size=(6, 3)))])
    for kappa, g in ((0.4, 0.3), (5.0, -0.5)):
        a = A.airlight_point(O, dirs, LIGHT, 5.0, 0.25, kappa, g)
        b = A.airlight_point(O, dirs, LIGHT, 5.0, 0.25, kappa, g, method="quad_t")
        c = A.airlight_point(O, dirs, LIGHT, 5.0, 0.25, kappa, g, method="gauss")
        np.testing.assert_allclose(b, a, rtol=1e-7)
        np.testing.assert_allclose(c, a, rtol=1e-7)
    # a per-ray t_max and per-ray origins broadcast
    tm = np.linspace(0.5, 9.0, len(dirs))
    per = A.airlight_point(np.broadcast_to(O, dirs.shape), dirs, LIGHT, 5.0, 0.25, 0.4, 0.3, t_max=tm)
    one = [A.airlight_point(O, d, LIGHT, 5.0, 0.25, 0.4, 0.3, t_max=t)[0] for d, t in zip(dirs, tm)]
    np.testing.assert_allclose(per, one, rtol=1e-13)


# --------------------------------------------------------------------------------------
# spot light
# --------------------------------------------------------------------------------------
SPOT_AXIS = _unit([0.2, -1.0, 0.1])


def test_spot_outside_cone_is_zero():
    # a ray starting above the light going up never enters a downward 30 degree cone
    o = LIGHT + np.array([0.3, 0.5, 0.0])
    dirs = np.array([[0.0, 1.0, 0.0], [0.3, 1.0, -0.2], [1.0, 0.2, 0.0]])
    val = A.airlight_spot(o, dirs, LIGHT, SPOT_AXIS, 30.0, 5.0, 0.3, 0.2, 0.4)
    assert np.all(val == 0.0)
    assert np.all(A.airlight_point(o, dirs, LIGHT, 5.0, 0.3, 0.2, 0.4) > 0)


def test_spot_inside_cone_equals_point():
    # rays starting inside the cone and moving away from the apex within the cone
    o = LIGHT + 2.0 * SPOT_AXIS
    dirs = np.array([SPOT_AXIS, _unit(SPOT_AXIS + 0.1 * _perp(SPOT_AXIS))])
    for t_max in (np.inf, 3.0):
        spot = A.airlight_spot(o, dirs, LIGHT, SPOT_AXIS, 25.0, 5.0, 0.3, 0.2, 0.4, t_max=t_max)
        point = A.airlight_point(o, dirs, LIGHT, 5.0, 0.3, 0.2, 0.4, t_max=t_max)
        np.testing.assert_allclose(spot, point, rtol=1e-12)
    # a finite segment crossing the cone's interior near the apex, entirely inside
    o2 = LIGHT + 1.0 * SPOT_AXIS - 0.05 * _perp(SPOT_AXIS)
    d2 = _perp(SPOT_AXIS)
    spot = A.airlight_spot(o2, d2, LIGHT, SPOT_AXIS, 25.0, 5.0, 0.3, 0.2, 0.4, t_max=0.1)
    point = A.airlight_point(o2, d2, LIGHT, 5.0, 0.3, 0.2, 0.4, t_max=0.1)
    np.testing.assert_allclose(spot, point, rtol=1e-12)


@pytest.mark.parametrize("cutoff", [15.0, 60.0, 90.0, 135.0])
def test_spot_complementary_cones_sum_to_point(cutoff):
    """A cone and the opposite cone of the supplementary angle partition space."""
    rng = np.random.default_rng(23)
    dirs = np.concatenate([_near_light_rays([1e-3, 0.1]), _unit(rng.normal(size=(10, 3)))])
    a = A.airlight_spot(O, dirs, LIGHT, SPOT_AXIS, cutoff, 4.0, 0.3, 0.2, 0.5)
    b = A.airlight_spot(O, dirs, LIGHT, -SPOT_AXIS, 180.0 - cutoff, 4.0, 0.3, 0.2, 0.5)
    p = A.airlight_point(O, dirs, LIGHT, 4.0, 0.3, 0.2, 0.5)
    np.testing.assert_allclose(a + b, p, rtol=1e-9)
    assert np.all(a >= 0) and np.all(b >= 0)


def test_spot_partial_vs_trapezoid():
    """A ray crossing the cone: compare with a brute-force sum using the indicator."""
    o = np.array([-2.0, 0.5, 0.0])
    w = _unit([1.0, 0.05, 0.02])
    cut = 20.0
    val = A.airlight_spot(o, w, LIGHT, SPOT_AXIS, cut, 4.0, 0.3, 0.2, 0.5, t_max=6.0)[0]
    assert val > 0
    t = np.linspace(0.0, 6.0, 2_000_001)
    x = o + t[:, None] * w
    dv = x - LIGHT
    d = np.linalg.norm(dv, axis=1)
    inside = dv @ SPOT_AXIS >= math.cos(math.radians(cut)) * d
    f = 0.3 * A.hg(-(dv @ w) / d, 0.5) * 4.0 / d**2 * np.exp(-0.2 * (d + t)) * inside
    assert val == pytest.approx(np.trapezoid(f, t), rel=1e-4)


# --------------------------------------------------------------------------------------
# directional light, box medium
# --------------------------------------------------------------------------------------
BMIN = np.array([-1.0, -0.5, -2.0])
BMAX = np.array([2.0, 1.5, 1.0])


@pytest.mark.parametrize("light_dir", [[0.3, -1.0, -0.2], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0],
                                       [0.3, 0.0, -0.7], [-0.5, 0.4, 0.8]])
def test_directional_closed_form_vs_quad(light_dir):
    rng = np.random.default_rng(29)
    inside_o = np.array([0.2, 0.1, -0.3])
    outside_o = np.array([0.5, 3.0, 5.0])
    # inside: random directions; outside: directions at points of the box, some jittered off
    d_in = rng.normal(size=(25, 3))
    d_out = (rng.uniform(BMIN, BMAX, size=(25, 3)) - outside_o) + 0.4 * rng.normal(size=(25, 3))
    d_out = np.concatenate([d_out, [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])  # sure misses
    for o, dirs in ((inside_o, d_in), (outside_o, d_out)):
        for kappa, g in ((0.7, 0.3), (2.5, -0.6)):
            a = A.directional_slab(o, dirs, light_dir, 1.3, 0.2, kappa, g, BMIN, BMAX)
            b = A.directional_slab_quad(o, dirs, light_dir, 1.3, 0.2, kappa, g, BMIN, BMAX)
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)
        t_in, t_out, hit = A.ray_box(o, dirs, BMIN, BMAX)
        hit &= t_out > 0
        assert np.all((a > 0) == hit)
        if o is outside_o:
            assert 0 < hit.sum() < len(dirs) and a[-1] == 0 and a[-2] == 0
        else:
            assert hit.all()


def test_directional_t_max_and_vacuum_limit():
    rng = np.random.default_rng(31)
    o = np.array([0.2, 0.1, -0.3])
    dirs = _unit(rng.normal(size=(10, 3)))
    ld = [0.3, -1.0, -0.2]
    tm = rng.uniform(0.1, 2.0, size=10)
    a = A.directional_slab(o, dirs, ld, 1.3, 0.2, 0.9, 0.3, BMIN, BMAX, t_max=tm)
    b = A.directional_slab_quad(o, dirs, ld, 1.3, 0.2, 0.9, 0.3, BMIN, BMAX, t_max=tm)
    np.testing.assert_allclose(a, b, rtol=1e-6)
    # kappa = 0: sigma_s p E times the chord length inside the box
    _, t_out, _ = A.ray_box(o, dirs, BMIN, BMAX)
    chord = np.minimum(t_out, tm)
    cos = -(dirs @ _unit(ld))
    ref = 0.2 * A.hg(cos, 0.3) * 1.3 * chord
    np.testing.assert_allclose(A.directional_slab(o, dirs, ld, 1.3, 0.2, 0.0, 0.3, BMIN, BMAX, t_max=tm),
                               ref, rtol=1e-13)


def test_directional_simple_geometry():
    """Light straight down, horizontal ray at height y inside: s = ymax - y is constant."""
    y = 0.4
    o = np.array([-3.0, y, 0.0])       # outside, left of the box
    w = np.array([1.0, 0.0, 0.0])
    kappa, E, ss = 0.8, 2.0, 0.3
    L = A.directional_slab(o, w, [0.0, -1.0, 0.0], E, ss, kappa, 0.0, BMIN, BMAX)[0]
    length = BMAX[0] - BMIN[0]
    ref = ss / (4 * math.pi) * E * math.exp(-kappa * (BMAX[1] - y)) * (1 - math.exp(-kappa * length)) / kappa
    assert L == pytest.approx(ref, rel=1e-13)


# --------------------------------------------------------------------------------------
# camera
# --------------------------------------------------------------------------------------
CAM = dict(origin=[0.0, 1.0, 6.0], target=[0.3, 0.5, 0.0], up=[0.0, 1.0, 0.0])


@pytest.mark.parametrize("fov_axis", ["x", "y"])
@pytest.mark.parametrize("size", [(7, 5), (9, 9), (33, 17)])
def test_camera_centre_ray_is_forward(fov_axis, size):
    W, H = size
    d = A.camera_rays(CAM["origin"], CAM["target"], CAM["up"], 50.0, fov_axis, W, H, 0.5, 0.5)
    assert d.shape == (H, W, 3)
    fwd = _unit(np.subtract(CAM["target"], CAM["origin"]))
    np.testing.assert_allclose(d[H // 2, W // 2], fwd, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-15)


def _angle(a, b):
    return math.degrees(math.acos(np.clip(a @ b, -1, 1)))


@pytest.mark.parametrize("W,H", [(64, 48), (65, 47), (40, 80)])
def test_camera_edges_span_fov(W, H):
    fov = 47.0
    args = (CAM["origin"], CAM["target"], CAM["up"], fov)
    # fov_axis x: left edge (px 0, u 0) to right edge (px W-1, u 1) on the middle row
    u = np.zeros((H, W))
    u[:, -1] = 1.0
    v = np.full((H, W), 0.5 * H % 1.0)   # py + v = H / 2 on row floor(H / 2)
    d = A.camera_rays(*args, "x", W, H, u, v)
    row = H // 2
    assert _angle(d[row, 0], d[row, -1]) == pytest.approx(fov, abs=1e-10)
    # fov_axis y: top edge to bottom edge on the middle column
    u = np.full((H, W), 0.5 * W % 1.0)
    v = np.zeros((H, W))
    v[-1, :] = 1.0
    d = A.camera_rays(*args, "y", W, H, u, v)
    col = W // 2
    assert _angle(d[0, col], d[-1, col]) == pytest.approx(fov, abs=1e-10)
    # the other axis follows the aspect ratio
    d = A.camera_rays(*args, "x", W, H, 0.5, 0.5)
    fwd = _unit(np.subtract(CAM["target"], CAM["origin"]))
    right = _unit(np.cross(fwd, CAM["up"]))
    up = np.cross(right, fwd)
    # row 0 is the top, column 0 the left
    assert d[0, W // 2] @ up > 0 and d[-1, W // 2] @ up < 0
    assert d[H // 2, 0] @ right < 0 and d[H // 2, -1] @ right > 0
    # corner ray: tan components along right / up are tan_x, tan_y (scaled by 1 / forward)
    du = A.camera_rays(*args, "x", W, H, 0.0, 0.0)[0, 0]
    tan_x = math.tan(math.radians(fov / 2))
    assert (du @ right) / (du @ fwd) == pytest.approx(-tan_x, rel=1e-12)
    assert (du @ up) / (du @ fwd) == pytest.approx(tan_x * H / W, rel=1e-12)


def test_camera_matches_renderer_struct():
    """The same basis and tangents as clscatter.scene.normalised.camera_struct (if importable)."""
    frame = pytest.importorskip("clscatter.scene.normalised")
    model = pytest.importorskip("clscatter.scene.model")
    for axis in ("x", "y"):
        cam = model.Camera(origin=np.array(CAM["origin"]), target=np.array(CAM["target"]),
                           up=np.array(CAM["up"]), fov=41.0, fov_axis=axis, width=40, height=30, spp=1)
        c = frame.camera_struct(cam, frame.Frame(centre=np.zeros(3), scale=1.0))
        fwd, right, up = (np.asarray(c[k], np.float64)[:3] for k in ("forward", "right", "up"))
        d = A.camera_rays(**A.camera_kwargs(cam), u=0.25, v=0.75)
        for py, px in ((0, 0), (7, 31), (29, 39)):
            sx = 2 * (px + 0.25) / 40 - 1
            sy = 1 - 2 * (py + 0.75) / 30
            np.testing.assert_allclose(d[py, px], _unit(fwd + sx * right + sy * up), atol=1e-6)


def test_pixel_average():
    kw = A.camera_kwargs({"origin": CAM["origin"], "target": CAM["target"], "up": CAM["up"],
                          "fov": 40.0, "resolution": [6, 4]})
    assert kw["fov_axis"] == "x" and (kw["width"], kw["height"]) == (6, 4)
    one = A.pixel_average(lambda o, d: np.ones(len(d)), **kw, sub=3)
    assert one.shape == (4, 6) and np.all(one == 1.0)
    fn = lambda o, d: d[:, 0] ** 2 + d[:, 1]
    centre = A.pixel_average(fn, **kw, sub=1)
    d = A.camera_rays(**kw, u=0.5, v=0.5)
    np.testing.assert_allclose(centre, d[..., 0] ** 2 + d[..., 1], rtol=1e-15)
    quarters = np.mean([fn(None, A.camera_rays(**kw, u=u, v=v).reshape(-1, 3)).reshape(4, 6)
                        for u in (0.25, 0.75) for v in (0.25, 0.75)], axis=0)
    np.testing.assert_allclose(A.pixel_average(fn, **kw, sub=2), quarters, rtol=1e-14)
    rgb = A.pixel_average(lambda o, d: np.stack([d[:, 0], d[:, 1], d[:, 2]], axis=1), **kw, sub=2)
    assert rgb.shape == (4, 6, 3)
    # an image of the point-light reference (the vectorised method)
    img = A.pixel_average(lambda o, d: A.airlight_point(o, d, [0.3, 0.6, 0.0], 10.0, 0.2, 0.3, 0.2,
                                                        method="gauss"), **kw, sub=2)
    assert img.shape == (4, 6) and np.all(np.isfinite(img)) and np.all(img > 0)


# --------------------------------------------------------------------------------------
# diffuse helpers
# --------------------------------------------------------------------------------------
def test_diffuse_helpers():
    v = A.diffuse_point_lit(0.5, 10.0, 0.8, 2.0, kappa=0.1, t_cam=3.0)
    assert v == pytest.approx(0.5 / math.pi * 10.0 * 0.8 / 4.0 * math.exp(-0.2) * math.exp(-0.3))
    v = A.diffuse_point_lit(0.5, 10.0, 0.8, 2.0, kappa=0.1, d_light=0.5)
    assert v == pytest.approx(0.5 / math.pi * 10.0 * 0.8 / 4.0 * math.exp(-0.05))
    assert A.diffuse_point_lit(0.5, 10.0, -0.3, 2.0) == 0.0
    v = A.diffuse_directional_lit([0.2, 0.4, 0.6], 2.0, 0.5, kappa=0.3, s_light=1.0, t_cam=2.0)
    np.testing.assert_allclose(v, np.array([0.2, 0.4, 0.6]) / math.pi * 2.0 * 0.5 * math.exp(-0.9))
