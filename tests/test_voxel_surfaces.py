"""Light on surfaces from the voxel pipeline's photons (``surface_photons``).

Photons that reach a diffuse surface in the grid, or beyond it going on straight, are a
photon map; the view paths' diffuse hits get its estimate, and the straight direct light
only from lights whose shadow ray misses the grid's box (``voxel_shadow``'s occluder), so
volumes cast shadows and caustics on surfaces and nothing is counted twice. Along the
outline of the grid's straight shadow the estimate's blur is corrected with the same
photons gone on straight (``seam_correction``). Here:

* ``photon_surface`` and ``voxel_seam`` against NumPy (plane intersections, the medium's
  transmittance, which surfaces count; the straight light the occluder takes and which
  hits lie near the outline);
* (a) a volume with n = 1 and no extinction: the floor equals ``raymarch``'s straight
  direct light, exactly along the outline and outside, within the density estimate's
  noise where the photons light it;
* (b) a glass ball and an n = 1 ball in fog above a wide floor under a directional light:
  the flux of the photons landing on the floor against what the light sends through the
  grid's top face times the Fresnel transmittance of a sharp ball, and times the fog's
  transmittance;
* (c) a constant-density smoke box: its shadow on the floor against the closed form
  exp(-kappa L).
"""
from __future__ import annotations

import copy
import math

import numpy as np

from clscatter.device import AppendBuffer, structs
from clscatter.methods import configure
from clscatter.methods.voxel import as_volume_scene
from clscatter.methods.voxel.pipeline import Pipeline
from clscatter.pipeline.render import render
from clscatter.scene.loader import scene_from_dict
from clscatter.transport.prepared import prepare_scene

FLOOR = {"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
         "edge_v": [0.0, 0.0, 4.0], "material": "floor"}


def _base(lights: list, volumes: list, objects: list | None = None, medium: dict | None = None,
          camera: dict | None = None) -> dict:
    d = {"camera": camera or {"origin": [0.0, 3.2, 3.6], "target": [0.0, 0.0, 0.2],
                              "up": [0.0, 1.0, 0.0], "fov": 55.0, "resolution": [64, 48],
                              "spp": 2},
         "lights": lights,
         "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                       "chrome": {"type": "mirror", "reflectance": 0.9},
                       "glass": {"type": "dielectric", "ior": 1.5}},
         "objects": [copy.deepcopy(FLOOR), *(objects or [])],
         "volumes": volumes,
         "render": {"seed": 3}}
    if medium is not None:
        d["medium"] = medium
    return d


# ---- the kernels against NumPy ---------------------------------------------------------------

def _kernel_scene(engine):
    """A diffuse floor (y = 0) and a mirror wall (x = 1.5) in a fog box, prepared."""
    d = _base([{"type": "point", "position": [0.0, 3.0, 0.0], "intensity": 10.0}], [],
              objects=[{"shape": "quad", "origin": [1.5, 0.0, -2.0], "edge_u": [0.0, 0.0, 4.0],
                        "edge_v": [0.0, 3.0, 0.0], "material": "chrome"}],
              medium={"sigma_s": 0.2, "sigma_a": 0.1, "g": 0.0,
                      "bounds": {"min": [-2.0, 0.0, -2.0], "max": [2.0, 2.0, 2.0]}})
    return prepare_scene(scene_from_dict(d), engine)


def test_photon_surface_matches_numpy(engine):
    """``photon_surface`` over hand-made photon states: a photon beyond the grid (pos.w =
    -1) or at a surface in it (-2) that heads for the floor gives one record at the floor's
    crossing, its flux times exp(-kappa x the length in the fog box) for the first (not for
    the second, which the march attenuated already); photons heading for the mirror, up
    into nothing, live (1) or faded (0) give none; with straight = 1 exactly the live ones
    go on. Positions within 1e-5, fluxes within 1e-5 relative."""
    ps = _kernel_scene(engine)
    f = ps.frame
    rng = np.random.default_rng(4)
    m = 800
    pos = np.zeros((m, 4))
    pos[:, :3] = f.point(np.stack([rng.uniform(-1.0, 1.0, m), rng.uniform(0.5, 2.8, m),
                                   rng.uniform(-1.0, 1.0, m)], 1))
    pos[:, 3] = rng.choice([-1.0, -2.0, 1.0, 0.0], m)
    d = np.stack([rng.uniform(-0.9, 0.9, m), rng.uniform(-1.0, 0.3, m), rng.uniform(-0.6, 0.6, m)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vel = np.zeros((m, 4))
    vel[:, :3] = d * rng.uniform(0.8, 1.5, (m, 1))
    flux = np.zeros((m, 4))
    flux[:, :3] = rng.uniform(0.1, 1.0, (m, 3))
    kappa = f.coefficient(np.array([0.3, 0.3, 0.3]))
    lo, hi = f.point([-2.0, 0.0, -2.0]), f.point([2.0, 2.0, 2.0])
    x_mirror = f.point([1.5, 0.0, 0.0])[0]
    fl_lo, fl_hi = f.point([-2.0, 0.0, -2.0]), f.point([2.0, 0.0, 2.0])
    bufs = [engine.to_device(a.astype(np.float32)) for a in (pos, vel, flux)]

    def run(straight: int) -> np.ndarray:
        app = AppendBuffer(engine, structs.RAY_PIECE, 16)
        try:
            n = app.call_on_device("voxel", "photon_surface", m, pos=bufs[0], vel=bufs[1],
                                   flux=bufs[2], count=m, light_index=2, straight=straight,
                                   **ps.scene_args("voxel", "photon_surface"))
            out = engine.read(app.buf, n, structs.RAY_PIECE) if n else np.zeros(0, structs.RAY_PIECE)
        finally:
            app.release()
        return out[np.argsort(out["ray"])]

    try:
        for straight in (0, 1):
            got = run(straight)
            o = pos[:, :3]
            down, east = d[:, 1] < 0, d[:, 0] > 0
            t_floor = np.where(down, (fl_lo[1] - o[:, 1]) / np.where(down, d[:, 1], -1.0), np.inf)
            t_mirror = np.where(east, (x_mirror - o[:, 0]) / np.where(east, d[:, 0], 1.0), np.inf)
            hit = o + np.where(down, t_floor, 0.0)[:, None] * d
            on_floor = (down & (t_floor < t_mirror)
                        & np.all((hit[:, [0, 2]] > fl_lo[[0, 2]]) & (hit[:, [0, 2]] < fl_hi[[0, 2]]), axis=1))
            state = pos[:, 3]
            want = on_floor & ((state == 1.0) if straight else ((state == -1.0) | (state == -2.0)))
            idx = np.flatnonzero(want)
            assert len(idx) > 50 and np.array_equal(got["ray"], idx)
            assert np.all(got["end"] == 0) and np.all(got["light"] == 2)
            np.testing.assert_allclose(got["b"][:, :3], hit[idx], atol=1e-5)
            np.testing.assert_allclose(got["a"][:, :3], o[idx], atol=1e-6)
            # length in the fog box along [o, hit] (slab clipping)
            t0, t1 = np.zeros(len(idx)), t_floor[idx].copy()
            for a in range(3):
                with np.errstate(divide="ignore", invalid="ignore"):
                    ta = (lo[a] - o[idx, a]) / d[idx, a]
                    tb = (hi[a] - o[idx, a]) / d[idx, a]
                t0 = np.maximum(t0, np.nan_to_num(np.minimum(ta, tb), nan=-np.inf))
                t1 = np.minimum(t1, np.nan_to_num(np.maximum(ta, tb), nan=np.inf))
            length = np.clip(t1 - t0, 0, None)
            att = np.where((state[idx] == -2.0)[:, None], 1.0, np.exp(-np.outer(length, kappa)))
            np.testing.assert_allclose(got["flux"][:, :3], flux[idx, :3] * att, rtol=1e-5)
    finally:
        engine.free(*bufs)
        ps.release()


def test_voxel_seam_matches_numpy(engine):
    """``voxel_seam`` at floor hits under a point light and a box: the straight direct
    irradiance I cos / d^2 x exp(-kappa x the length in the fog) where the shadow ray
    crosses the box (else 0), within 1e-4 relative (the shadow ray leaves from the hit
    lifted by the ray offset: 3e-5 measured); the near flag where it meets the box
    grown by delta but not the box shrunk by delta, as NumPy's slab test says (rays
    within 1e-4 of either box's surface are left out of the comparison)."""
    ps = _kernel_scene(engine)
    f = ps.frame
    rng = np.random.default_rng(9)
    n = 3000
    hits = np.zeros(n, structs.DIFFUSE_HIT)
    p = np.stack([rng.uniform(-1.8, 1.4, n), np.zeros(n), rng.uniform(-1.8, 1.8, n)], 1)
    hits["p"][:, :3] = f.point(p)
    hits["n"][:, 1] = hits["g"][:, 1] = 1.0
    hits["weight"][:, :3] = 1.0
    box_lo, box_hi = f.point([-0.4, 1.0, -0.3]), f.point([0.5, 1.6, 0.4])
    delta = f.length(0.15)
    hb, out = engine.to_device(hits), engine.empty(16 * n)
    try:
        ps.call("voxel", "voxel_seam", n, hits=hb, n=n, light_index=0,
                glo=np.array([*box_lo, 0], np.float32), ghi=np.array([*box_hi, 0], np.float32),
                delta=np.float32(delta), out=out)
        got = engine.read(out, (n, 4), np.float32)
    finally:
        engine.free(hb, out)
        ps.release()
    light = f.point([0.0, 3.0, 0.0])
    to = light - hits["p"][:, :3].astype(np.float64)
    dist = np.linalg.norm(to, axis=1)
    wi = to / dist[:, None]

    def slab(lo, hi):
        """Entry and exit parameters of the segments [p, light] in the box (t in [0, dist])."""
        o = hits["p"][:, :3].astype(np.float64)
        t0, t1 = np.zeros(n), dist.copy()
        for a in range(3):
            with np.errstate(divide="ignore"):
                ta, tb = (lo[a] - o[:, a]) / wi[:, a], (hi[a] - o[:, a]) / wi[:, a]
            t0, t1 = np.maximum(t0, np.minimum(ta, tb)), np.minimum(t1, np.maximum(ta, tb))
        return t0, t1

    def meets(lo, hi, margin=0.0):
        t0, t1 = slab(lo, hi)
        return t1 - t0 > margin, np.abs(t1 - t0) <= 1e-4

    through, edge0 = meets(box_lo, box_hi)
    grown, edge1 = meets(box_lo - delta, box_hi + delta)
    shrunk, edge2 = meets(box_lo + delta, box_hi - delta)
    clear = ~(edge0 | edge1 | edge2)
    # irradiance: I / d^2 cos, the fog box [-2, 2] x [0, 2] x [-2, 2] on the way
    inten = 10.0 / f.scale ** 2
    t0, t1 = slab(f.point([-2.0, 0.0, -2.0]), f.point([2.0, 2.0, 2.0]))
    kappa = f.coefficient(0.3)
    want = inten / dist ** 2 * wi[:, 1] * np.exp(-kappa * np.clip(t1 - t0, 0, None)) * through
    near = grown & ~shrunk
    print(f"\nthrough {np.count_nonzero(through)}, near {np.count_nonzero(near)} of {n}")
    assert 200 < np.count_nonzero(near[clear]) < np.count_nonzero(clear) - 200
    assert np.count_nonzero(through & ~near) > 100
    assert np.array_equal(got[clear, 3] > 0, near[clear])
    np.testing.assert_allclose(got[clear, 0], want[clear], rtol=1e-4, atol=1e-7 * want.max())


# ---- (a) nothing in the grid: the photons give the straight direct light -----------------------

def _grid_box(stats: dict, frame=None) -> tuple[np.ndarray, np.ndarray]:
    g = stats["voxel_grid"]
    return np.array(g["min"]), np.array(g["max"])


def _floor_points(cam: dict) -> np.ndarray:
    """The floor point (y = 0) of every pixel centre's camera ray, (H, W, 3); NaN where the
    ray misses the plane in front. The camera model of docs/scene_format.md (fov along x)."""
    o, t, up = (np.asarray(cam[k], float) for k in ("origin", "target", "up"))
    w, h = cam["resolution"]
    fwd = (t - o) / np.linalg.norm(t - o)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    upv = np.cross(right, fwd)
    tx = math.tan(math.radians(cam["fov"]) / 2)
    ty = tx * h / w
    u = ((np.arange(w) + 0.5) / w * 2 - 1) * tx
    v = (1 - (np.arange(h) + 0.5) / h * 2) * ty
    d = fwd + u[None, :, None] * right + v[:, None, None] * upv
    t_hit = -o[1] / d[..., 1]
    p = o + t_hit[..., None] * d
    p[~(t_hit > 0)] = np.nan
    return p


def _shadow_meets(p: np.ndarray, light: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether the segments from the points ``p`` (.., 3) to ``light`` meet the box."""
    d = light - p
    t0, t1 = np.zeros(p.shape[:-1]), np.ones(p.shape[:-1])
    for a in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo[a] - p[..., a]) / d[..., a], (hi[a] - p[..., a]) / d[..., a]
        t0, t1 = np.maximum(t0, np.minimum(ta, tb)), np.minimum(t1, np.maximum(ta, tb))
    return t1 > t0


def test_index_one_floor_matches_the_straight_direct_light(engine):
    """A sphere volume with n = 1 and no extinction, no medium, a point light above: the
    photons fall where the straight light falls. The floor's radiance by ``voxel`` (32^3,
    2^16 photons, k = 64, ``surface_radius`` 0.03) against ``raymarch``'s straight direct
    light, same camera samples: every floor pixel whose shadow ray misses the grid's box
    shrunk by half the estimation radius (the outline's band, where the straight photons
    correct the estimate, and outside it) equals it within 1e-4 (measured: to float
    rounding); the pixels lit by the photons alone (the box shrunk by 1.5 radii crossed;
    the floor's edge 2 radii away) have mean ratio within 1.5% of 1 (measured -0.2%) and
    an RMS relative deviation below 5% (measured 2.5%: the estimate's noise)."""
    light = np.array([0.3, 4.5, 0.2])
    d = _base([{"type": "point", "position": light.tolist(), "intensity": 40.0}],
              [{"shape": "sphere", "center": [0.0, 1.4, 0.0], "radius": 0.6, "ior": 1.0}])
    s = scene_from_dict(copy.deepcopy(d))
    s.render.params = {"voxel": {"resolution": 32, "photons": 1 << 16, "surface_radius": 0.03}}
    v = render(s, method="voxel", engine=engine, show_progress=False)
    r = render(scene_from_dict(copy.deepcopy(d)), method="raymarch", engine=engine,
               show_progress=False)
    lo, hi = _grid_box(v.stats)
    radius = 0.03 * s.scene_extent()
    p = _floor_points(d["camera"])
    on = np.all(np.abs(p[..., [0, 2]]) < 2.0 - 1e-3, axis=-1)
    inner = (on & _shadow_meets(p, light, lo + 1.5 * radius, hi - 1.5 * radius)
             & np.all(np.abs(p[..., [0, 2]]) < 2.0 - 2 * radius, axis=-1))
    rest = on & ~_shadow_meets(p, light, lo + 0.5 * radius, hi - 0.5 * radius)
    vs, rs = v.surface[..., 0], r.surface[..., 0]
    ratio = vs / np.where(rs > 0, rs, 1.0)
    dev = ratio[inner] - 1
    off = np.abs(vs[rest] - rs[rest]) / np.maximum(rs[rest], 1e-30)
    print(f"\nphoton-lit pixels {inner.sum()}: mean ratio {ratio[inner].mean():.4f}, RMS "
          f"{np.sqrt(np.mean(dev ** 2)):.4f}; straight-lit pixels {rest.sum()}: max relative "
          f"difference {off[rs[rest] > 0].max():.1e}; seam hits {v.stats['voxel_surface_seam_hits']}")
    assert inner.sum() > 500 and rest.sum() > 500 and np.all(rs[inner] > 0)
    assert v.stats["voxel_surface_photons"] > 10_000 and v.stats["voxel_surface_seam_hits"] > 100
    assert abs(ratio[inner].mean() - 1) < 0.015 and np.sqrt(np.mean(dev ** 2)) < 0.05
    assert np.all(np.abs(vs[rest] - rs[rest]) <= 1e-4 * rs[rest])


# ---- (b) energy on the floor ---------------------------------------------------------------------

WIDE = {"shape": "quad", "origin": [-40.0, 0.0, -40.0], "edge_u": [80.0, 0.0, 0.0],
        "edge_v": [0.0, 0.0, 80.0], "material": "floor"}


def _floor_photons(engine, d: dict, res: int = 64) -> tuple[np.ndarray, object, object]:
    """The voxel pipeline's photons on the floor for scene ``d`` (lighting stage only):
    (RAY_PIECE records, the grid box, the prepared scene's frame)."""
    s = as_volume_scene(scene_from_dict(d), True)
    ps = prepare_scene(s, engine)
    pipe = Pipeline(configure("voxel", {"resolution": res, "photons": 1 << 16, "margin": 0.25}))
    try:
        pipe._geometry(ps)
        pipe._material(ps)
        pipe._lighting(ps)
        return pipe.radiance.surface.copy(), pipe.box, ps.frame
    finally:
        pipe.release(engine)
        ps.release()


def test_glass_ball_photons_carry_the_fresnel_transmitted_flux_to_the_floor(engine):
    """A glass ball (ior 1.5, radius 0.4, voxelised at 64^3) under a directional light
    straight down (E = 2), a floor 80 wide (rim rays bend up to 75 degrees), no medium: the
    photons landing on the floor carry E x (the grid's top face - pi R^2) + E pi R^2 x the
    mean over the disc of a sharp ball's T(theta)^2, within 0.6% of the ball's share E pi
    R^2 (measured +0.28%: the w = 1/2 surface of the blurred sphere lies about 0.1 voxel
    inside its radius, and the mesh is inscribed, so slightly less light meets the ball)."""
    d = _base([{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}], [],
              objects=[{"shape": "sphere", "center": [0.0, 1.3, 0.0], "radius": 0.4,
                        "material": "glass", "subdivisions": 5}])
    d["objects"][0] = copy.deepcopy(WIDE)
    photons, box, frame = _floor_photons(engine, d)
    top = float(np.prod((box.hi - box.lo)[[0, 2]])) * frame.scale ** 2
    R = 0.4
    b = np.sqrt((np.arange(200_000) + 0.5) / 200_000)          # b / R, uniform over the disc
    ci = np.sqrt(1 - b ** 2)
    st = b / 1.5
    ct = np.sqrt(1 - st ** 2)
    rs = ((ci - 1.5 * ct) / (ci + 1.5 * ct)) ** 2
    rp = ((1.5 * ci - ct) / (1.5 * ci + ct)) ** 2
    t2 = (1 - 0.5 * (rs + rp)) ** 2
    want = 2.0 * (top - math.pi * R ** 2) + 2.0 * math.pi * R ** 2 * t2.mean()
    got = float(photons["flux"][:, 0].sum()) * frame.scale ** 2
    ball_share = 2.0 * math.pi * R ** 2
    print(f"\nflux on the floor {got:.5f}, want {want:.5f} (ball's share {ball_share:.4f}): "
          f"{(got - want) / ball_share:+.4%} of it")
    assert abs(got - want) < 0.006 * ball_share


def test_photons_through_fog_carry_its_transmittance_to_the_floor(engine):
    """An n = 1 ball of the fog's own coefficients in fog (kappa 0.3, up to y = 3) under a
    directional light straight down (E = 2), no bending: the photons on the floor carry
    E x the grid's top face x exp(-kappa x 3) (every path vertical through 3 units of fog),
    within 0.1% (measured to float rounding)."""
    fog = {"sigma_s": 0.1, "sigma_a": 0.2, "g": 0.0,
           "bounds": {"min": [-40.0, 0.0, -40.0], "max": [40.0, 3.0, 40.0]}}
    d = _base([{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}],
              [{"shape": "sphere", "center": [0.0, 1.3, 0.0], "radius": 0.4, "ior": 1.0,
                "sigma_s": 0.1, "sigma_a": 0.2}], medium=fog)
    d["objects"][0] = copy.deepcopy(WIDE)
    photons, box, frame = _floor_photons(engine, d, res=32)
    top = float(np.prod((box.hi - box.lo)[[0, 2]])) * frame.scale ** 2
    want = 2.0 * top * math.exp(-0.3 * 3.0)
    got = float(photons["flux"][:, 0].sum()) * frame.scale ** 2
    print(f"\nflux on the floor {got:.5f}, want {want:.5f}: {got / want - 1:+.3%}")
    assert abs(got / want - 1) < 1e-3


# ---- (c) a smoke box's shadow ----------------------------------------------------------------------

def test_smoke_box_shadow_on_the_floor(engine, tmp_path):
    """A constant-density box (density 1, sigma_s 0.5, sigma_a 1.5 per unit density,
    0.5 thick) under a directional light straight down, no medium, seen from below the
    grid (the view rays to the floor miss the smoke): the floor under the box's middle is
    darker than the floor beside the grid's shadow by exp(-2 x 0.5) = 0.368 (the closed
    form), within 3% (measured 0.369, +0.3%). Without the box it is as bright (1%;
    measured 1.003)."""
    np.save(tmp_path / "ones.npy", np.ones((8, 8, 8), np.float32))
    cam = {"origin": [0.0, 0.55, 3.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
           "fov": 60.0, "resolution": [64, 48], "spp": 2}
    box = {"min": [-0.6, 1.0, -0.6], "max": [0.6, 1.5, 0.6]}
    vol = {"density": "ones.npy", "bounds": box, "sigma_s": 0.5, "sigma_a": 1.5}
    light = [{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}]
    images = {}
    for name, density in (("smoke", 1.0), ("clear", 0.0)):
        v = dict(vol, sigma_s=0.5 * density, sigma_a=1.5 * density)
        d = _base(light, [v], camera=cam)
        s = scene_from_dict(d, tmp_path, "smoke")
        s.render.params = {"voxel": {"resolution": 32, "photons": 1 << 16}}
        res = render(s, method="voxel", engine=engine, show_progress=False)
        assert res.stats["voxel_surface_photons"] > 10_000
        images[name] = res
    lo, hi = _grid_box(images["smoke"].stats)
    p = _floor_points(cam)
    under = np.all(np.abs(p[..., [0, 2]]) < 0.3, axis=-1)
    beside = (np.all(np.abs(p[..., [0, 2]]) < 1.8, axis=-1)
              & ((np.abs(p[..., 0]) > hi[0] + 0.3) | (np.abs(p[..., 2]) > hi[2] + 0.3)))
    sm, cl = images["smoke"].surface[..., 0], images["clear"].surface[..., 0]
    shadow = sm[under].mean() / sm[beside].mean()
    clear = cl[under].mean() / cl[beside].mean()
    want = math.exp(-2.0 * 0.5)
    print(f"\nunder {under.sum()} px, beside {beside.sum()} px: shadow {shadow:.4f} "
          f"(closed form {want:.4f}), without the smoke {clear:.4f}")
    assert under.sum() > 15 and beside.sum() > 200
    assert abs(shadow / want - 1) < 0.03
    assert abs(clear - 1) < 0.01
