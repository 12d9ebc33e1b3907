"""Epipolar method across its hard regimes, against ``raymarch``: optical depth, camera
inside/outside the medium, light behind/beside/in front of the camera and along the view
axis, directional and spot lights, wide spot cones; the error estimate and the fallback.

Scenes: ``clscatter.scene.builtin.epipolar.epi_sweep`` (a 4 x 3 x 4 fog box with four
black pillars) and ``epi_wide_spot`` (the grate under a spot light), small images.
Where the method's own error estimate exceeds its tolerance it must ray march the light
and say so (``epipolar_lights[i]["fallback"]``); those configurations are asserted to be
the ones the estimate flags, and the image is checked either way.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from clscatter.io.image import relmse
from clscatter.methods.epipolar import Epipolar
from clscatter.methods.raymarch import RayMarch
from clscatter.transport.prepared import prepare_scene
from clscatter.pipeline.render import render
from clscatter.scene.builtin.epipolar import epi_fog, epi_sweep, epi_wide_spot
from clscatter.scene.loader import apply_overrides, scene_from_dict
from clscatter.io.stats import Stats
from clscatter.transport.view_paths import trace_view_paths

RES = (32, 24)
REF_STEPS = 192
DEPTHS = (0.1, 1.0, 3.0, 10.0)
LIGHTS = ("behind", "beside", "front", "axis")
CAMERAS = ("outside", "inside")

# bounds for every configuration (medium image, 32 x 24, 1 spp, defaults)
SWEEP_RELMSE = 1e-4
SWEEP_MEAN = 0.01


def _pair(engine, d: dict, ref_steps: int = REF_STEPS, params: dict | None = None):
    """(epipolar image, raymarch image, epipolar stats) on the same view paths."""
    ps = prepare_scene(scene_from_dict(d), engine)
    try:
        paths = trace_view_paths(ps, show_progress=False)
        ref = RayMarch({"steps": ref_steps}).run(ps, paths, Stats(), False).radiance()
        st = Stats()
        got = Epipolar(params or {}).run(ps, paths, st, False).radiance()
    finally:
        ps.release()
    return got, ref, st.values


@pytest.mark.parametrize("kind", ["directional", "spot"])
def test_sweep_against_raymarch(engine, kind):
    """Optical depth across the box {0.1, 1, 3, 10} x light {behind, beside, in front of
    the camera, along the view axis} x camera {outside, inside the medium}: relMSE <= 1e-4
    and mean within 1 % everywhere (measured: relMSE <= 5.2e-5, mean 0.995 .. 1.005).
    Where its estimate exceeds the tolerance the light is ray marched (the ring's steps)
    and said so, with the estimate above the tolerance in --stats, and ``auto`` would not
    have picked the method (``Epipolar.unreliable``)."""
    swept, fell = [], []
    for cam, light, depth in itertools.product(CAMERAS, LIGHTS, DEPTHS):
        name = f"{kind} {cam} {light} depth {depth:g}"
        d = epi_sweep(depth, light, cam, kind, RES)
        passed_over = Epipolar.unreliable(scene_from_dict(d))
        got, ref, st = _pair(engine, d)
        info = st["epipolar_lights"][0]
        err = relmse(got, ref)
        ratio = float(got.mean() / ref.mean())
        print(f"{name:38s} relMSE {err:.2e} mean {ratio:.4f} "
              f"{info.get('fallback', 'swept')} {info.get('svd_tried', [])[-1:]} slices {info.get('slice_error', {}).get('rms', 0):.3g} {info.get('slice_spacing_px')}")
        assert ref.mean() > 0.0, name
        assert err <= SWEEP_RELMSE, (name, err)
        assert abs(ratio - 1.0) <= SWEEP_MEAN, (name, ratio)
        if "fallback" in info:
            fell.append(name)
            # auto never picks epipolar where it falls back
            assert passed_over, name
            assert info["svd_error"]["rms"] > Epipolar({}).settings.svd_tolerance
            assert any("estimated error" in x for x in st["epipolar_fallback"])
        else:
            swept.append(name)
            assert info["tree_queries"] > 0
    print(f"{kind}: {len(swept)} swept, {len(fell)} ray marched: {fell}")
    # Everything is swept but where the estimate is expected to exceed the tolerance:
    # optical depth 10 seen from outside, and a spot light behind the camera on the view
    # axis (the anti-diagonal beta + gamma -> pi where the paper's singular-value claim
    # fails, test_epipolar.py): measured, those (and only those) fall back, the rest is
    # swept (directional 30 of 32, spot 26 of 32).
    may_fall = lambda n: "outside" in n and ("depth 10" in n or ("spot" in n and "axis" in n))
    assert not [n for n in fell if not may_fall(n)]
    assert len(swept) >= 24


def test_thick_fog_seen_from_outside(engine):
    """A thick fog (sigma_s = 1, sigma_a = 0.1, sun behind the camera, camera outside):
    previously 16.9 x too bright at 48 x 36 (relMSE 126); now relMSE <= 1e-4 (measured
    5e-7) and the mean within 1 % (measured 1.001), swept (not ray marched) with the
    terms its estimate asks for (16, where 4 are estimated at an RMS error of ~100), and
    the estimate reported in --stats; capped at 4 terms it falls back instead."""
    d = apply_overrides(epi_fog(), ["camera.resolution=[48, 36]", "camera.spp=1"])
    got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    err, ratio = relmse(got, ref), float(got.mean() / ref.mean())
    print(f"thick fog: relMSE {err:.3g}, mean {ratio:.4f}, {info['svd_tried'][-1]}")
    assert "fallback" not in info
    assert err <= 1e-4 and abs(ratio - 1.0) <= 0.01
    assert info["svd_error"]["rms"] <= Epipolar({}).settings.svd_tolerance
    assert st["svd_error"] == info["svd_error"]["rms"]
    # with the previous setting (4 terms, no escalation) the estimate flags it
    forced = Epipolar({})
    import dataclasses
    forced.settings = dataclasses.replace(forced.settings, svd_max_terms=4)
    ps = prepare_scene(scene_from_dict(d), engine)
    try:
        st2 = Stats()
        forced.run(ps, trace_view_paths(ps, show_progress=False), st2, False).radiance()
    finally:
        ps.release()
    assert st2.values["epipolar_lights"][0].get("fallback") == "raymarch"


@pytest.mark.parametrize("cutoff", [10.0, 30.0, 60.0, 80.0, 90.0])
def test_spot_cutoffs_with_a_grille(engine, cutoff):
    """The grate under spot lights of half-angle 10 .. 90 degrees, 48 x 36, 1 spp: relMSE
    <= 2e-4 for every cutoff (one bound, whatever the cone; measured 3.0e-6 (10), 9.3e-6
    (30), 7.3e-5 (60), 9.2e-5 (80), 9.3e-5 (90); raymarch's own noise floor here is
    1.4e-6; what remains at wide cones is the half-pixel slice spacing across shafts
    fanning out in every direction: 2.7 x the slices halve it), mean within 1 % (0.997 ..
    1.008); cones wider than 60 degrees use five cube faces, so no light ray goes
    unshadowed (otherwise a 90-degree cone is 5 % too bright, relMSE 9.5e-4)."""
    d = epi_wide_spot(cutoff, (48, 36))
    d["camera"]["spp"] = 1
    got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    err, ratio = relmse(got, ref), float(got.mean() / ref.mean())
    print(f"cutoff {cutoff:g}: relMSE {err:.3g}, mean {ratio:.4f}, faces {info.get('shadow_map_faces')}")
    assert "fallback" not in info
    assert err <= 2e-4 and abs(ratio - 1.0) <= 0.01
    assert len(info["shadow_map_faces"]) == (5 if cutoff > 60 else 1)


def test_auto_end_to_end(engine):
    """``auto`` on the thick-fog scene and the 90-degree spot (40 x 30, 1 spp): the medium
    image against ``raymarch`` (256 steps): relMSE <= 1e-4 / 2e-4 (measured 2.4e-6 /
    1.2e-4), mean within 1 %. The thick fog (sun along the view through optical depth
    4.4, camera outside) is ray marched, and the plan says why epipolar was passed over;
    the spot is swept, and the epipolar statistics (estimate, terms) reach --stats."""
    fog = apply_overrides(epi_fog(), ["camera.resolution=[40, 30]", "camera.spp=1"])
    for d, bound, method in ((fog, 1e-4, "raymarch"),
                             (epi_wide_spot(90.0, (40, 30)), 2e-4, "epipolar")):
        d["camera"]["spp"] = 1
        scene = scene_from_dict(d)
        ref_scene = scene_from_dict(d)
        ref_scene.render.params["raymarch"] = {"steps": 256}
        ref = render(ref_scene, "raymarch", engine, show_progress=False)
        got = render(scene, "auto", engine, show_progress=False)
        err = relmse(got.medium, ref.medium)
        print(f"auto ({method}): relMSE {err:.3g} mean {got.medium.mean() / ref.medium.mean():.4f}")
        assert err <= bound
        assert abs(got.medium.mean() / ref.medium.mean() - 1.0) <= 0.01
        notes = got.stats["plan"]
        assert f"direct by {method}" in notes, notes
        if method == "epipolar":
            lights = got.stats["epipolar_lights"]
            assert lights and "svd_error" in lights[0] and "svd_terms" in lights[0]
        else:
            assert "epipolar_lights" not in got.stats
            assert any(n.startswith("direct: not epipolar (light 0 travels along the view")
                       for n in notes), notes


def test_epipole_ring_in_angle_with_a_blended_band(engine):
    """``epi_sun`` (the sun on screen) at 96 x 72, 1 spp, against raymarch (512 steps): the
    ring is 2 degrees around the epipole whatever the resolution, and the sweep and the
    ring's ray marcher are blended across 2 .. 4 degrees. Measured on the annulus 1 .. 4
    degrees: relMSE 2.1e-3 with a hard edge (band 0), 6.0e-4 blended; asserted: blended
    <= 1e-3 and at most half the hard edge's; whole image <= 5e-4."""
    import dataclasses
    from clscatter.methods.epipolar import geometry as geo
    from clscatter.scene.builtin.epipolar import EPIPOLAR_SCENES
    W, H = 96, 72
    d = apply_overrides(EPIPOLAR_SCENES["epi_sun"](), [f"camera.resolution=[{W}, {H}]", "camera.spp=1"])
    ps = prepare_scene(scene_from_dict(d), engine)
    try:
        paths = trace_view_paths(ps, show_progress=False)
        ref = RayMarch({"steps": 512}).run(ps, paths, Stats(), False).radiance()
        cam = geo.CameraGeom.from_struct(ps.camera)
        axis = geo.make_axis(ps.lights[0], cam.origin)
        xy = np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2)
        _, beta = axis.coords(cam.direction(xy))
        ang = np.degrees(beta).reshape(H, W)
        near = (ang >= 1.0) & (ang < 4.0)
        out = {}
        for band in (0.0, 1.0):
            m = Epipolar({})
            m.settings = dataclasses.replace(m.settings, epipole_band=band)
            st = Stats()
            got = m.run(ps, paths, st, False).radiance()
            out[band] = (relmse(got[near], ref[near]), relmse(got, ref), st.values)
    finally:
        ps.release()
    print({b: (f"{a:.3g}", f"{w:.3g}") for b, (a, w, _) in out.items()})
    info = out[1.0][2]["epipolar_lights"][0]
    assert info["epipole_in_front"] and abs(info["ring_degrees"] - 2.0) < 1e-9
    assert info["ring_band_samples"] > 0
    assert near.sum() > 60
    assert out[1.0][0] <= 1e-3 and out[1.0][0] <= 0.5 * out[0.0][0]
    assert out[1.0][1] <= 5e-4


def test_extreme_optical_depth_falls_back_quietly(engine):
    """Optical depth 4000 across the box (sigma_s = 900 per unit, the sun behind the camera):
    the estimate's exponentials overflow on most held-out samples. Those count as failures
    (they were dropped once, which could let such an estimate pass), so the light is ray
    marched, no NumPy warning reaches the user, and the image is finite and within relMSE
    1e-4 of raymarch with 256 steps (measured 3.2e-6; raymarch's transmittance strategy
    puts its samples in the first thousandth of each segment, where the light is)."""
    import warnings
    d = epi_sweep(4000.0, "behind", "outside", "directional", RES)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    err = relmse(got, ref)
    print(f"depth 4000: relMSE {err:.3g}; {info.get('reason')}")
    assert info.get("fallback") == "raymarch"
    assert info["svd_error"]["nonfinite"] > 0 and "not finite" in info["reason"]
    assert np.isfinite(got).all() and ref.mean() > 0
    assert err <= 1e-4
