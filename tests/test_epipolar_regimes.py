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
from reference_checks import assert_matches_reference

from clscatter.io.image import relmse
from clscatter.io.stats import Stats
from clscatter.methods.epipolar import Epipolar
from clscatter.methods.raymarch import RayMarch
from clscatter.pipeline.render import render
from clscatter.scene.builtin.epipolar import epi_fog, epi_sweep, epi_wide_spot
from clscatter.scene.loader import apply_overrides, scene_from_dict
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_view_paths

RES = (32, 24)
REF_STEPS = 192
DEPTHS = (0.1, 1.0, 3.0, 10.0)
LIGHTS = ("behind", "beside", "front", "axis")
CAMERAS = ("outside", "inside")

# Bounds for the sweep (medium image, 32 x 24, 1 spp, defaults; relMSE as
# clscatter.io.image.relmse, checked by reference_checks.assert_matches_reference).
# Measured over the 64 configurations: relMSE <= 2.1e-4 wherever the light is not in front
# of the camera; the typical lit pixel's error (reference_checks.pixel_error) <= 0.54 %
# everywhere; means 0.9967 .. 1.0043.
SWEEP_RELMSE = 4e-4
SWEEP_PIXEL = 0.01
SWEEP_MEAN = 0.01
# With the light in front of the camera the pillars' shadows are seen against the light,
# and a one-pixel leak of light into a black shadow pixel at their edges (the slices are
# a pixel apart) dominates relMSE: per (kind, camera), the worst over the depths measured
# 1.05e-3, 1.6e-3, 5.6e-2 (spot, outside, optical depth 0.1; 5.5e-6 at depth 10) and
# 2.9e-3. There the bias is caught by the mean and the noise by the per-pixel bound.
FRONT_RELMSE = {("directional", "outside"): 2e-3, ("directional", "inside"): 3e-3,
                ("spot", "outside"): 0.1, ("spot", "inside"): 5e-3}


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
    the camera, along the view axis} x camera {outside, inside the medium}: relMSE <= 4e-4
    (measured <= 2.1e-4) with the light not in front of the camera, FRONT_RELMSE with it
    in front, the typical lit pixel within 1 % (measured <= 0.54 %) and the mean within
    1 % everywhere (measured 0.9967 .. 1.0043).
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
        print(f"{name:38s} {info.get('fallback', 'swept')} {info.get('svd_tried', [])[-1:]} "
              f"slices {info.get('slice_error', {}).get('rms', 0):.3g} {info.get('slice_spacing_px')}")
        assert ref.mean() > 0.0, name
        bound = FRONT_RELMSE[kind, cam] if light == "front" else SWEEP_RELMSE
        assert_matches_reference(got, ref, bound, name, per_pixel=SWEEP_PIXEL,
                                 mean_tol=SWEEP_MEAN)
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
    previously 16.9 x too bright at 48 x 36; now relMSE <= 3e-5 (measured 1.7e-5) and the
    mean within 1 % (measured 1.0013), swept (not ray marched) with the
    terms its estimate asks for (16, where 4 are estimated at an RMS error of ~100), and
    the estimate reported in --stats; capped at 4 terms it falls back instead."""
    d = apply_overrides(epi_fog(), ["camera.resolution=[48, 36]", "camera.spp=1"])
    got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    print(f"thick fog: {info['svd_tried'][-1]}")
    assert "fallback" not in info
    assert_matches_reference(got, ref, 3e-5, "thick fog", mean_tol=0.01)
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


# relMSE per cone half-angle (measured 4.1, 0.37, 5.7e-2, 2.3e-2, 2.3e-2): the grate's
# shadows, and for narrow cones the cone's own edge, leak light into black pixels at
# their edges (the slices are a pixel apart), and against a black pixel any light is a
# large relative error; the narrower the cone the smaller the mean and the larger such
# a leak relative to it.
CUTOFF_RELMSE = {10.0: 8.0, 30.0: 0.7, 60.0: 0.1, 80.0: 0.05, 90.0: 0.05}


@pytest.mark.parametrize("cutoff", sorted(CUTOFF_RELMSE))
def test_spot_cutoffs_with_a_grille(engine, cutoff):
    """The grate under spot lights of half-angle 10 .. 90 degrees, 48 x 36, 1 spp, against
    raymarch (256 steps): relMSE <= CUTOFF_RELMSE (edge leaks; see there), so the teeth
    are the typical lit pixel's error <= 2 % (measured 1.13 % (10), 0.73 % (30), 0.68 %
    (60), 0.79 % (80), 0.78 % (90)) and the mean within 1 % (measured 0.997 .. 1.0078;
    the 10-degree cone's leaks add 0.8 %). Cones wider than 60 degrees use five cube
    faces, so no light ray goes unshadowed (otherwise a 90-degree cone is 5 % too
    bright)."""
    d = epi_wide_spot(cutoff, (48, 36))
    d["camera"]["spp"] = 1
    got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    print(f"cutoff {cutoff:g}: faces {info.get('shadow_map_faces')}")
    assert "fallback" not in info
    assert_matches_reference(got, ref, CUTOFF_RELMSE[cutoff], f"cutoff {cutoff:g}",
                             per_pixel=0.02, mean_tol=0.01)
    assert len(info["shadow_map_faces"]) == (5 if cutoff > 60 else 1)


def test_auto_end_to_end(engine):
    """``auto`` on the thick-fog scene and the grate under spot lights of half-angle 50 and
    90 degrees (40 x 30, 1 spp), the medium image against ``raymarch``. The thick fog (sun
    along the view through optical depth 4.4, camera outside) and the 90-degree spot
    (wider than ``WIDE_SPOT``) are ray marched, and the plan says why epipolar was passed
    over; the 50-degree spot is swept, and the epipolar statistics (estimate, terms) reach
    --stats. References: ``raymarch`` with 256 steps (fog: relMSE 2.9e-5 measured, bound
    6e-5; 50-degree spot: relMSE 0.066, dominated by one-pixel leaks at the bars' shadow
    edges, so the teeth are the typical lit pixel's error, 0.70 % measured, bound 1.4 %,
    and the mean within 1 %). The 90-degree spot ray marched at its default steps differs
    from 256 steps by 2.4 % per lit pixel (relMSE 5.2e-3): no bound there could catch 5 %
    noise, so it is compared with ``raymarch`` at the same settings, which it must equal
    (ray marching's own accuracy on this scene: test_spot_cutoffs_with_a_grille)."""
    fog = apply_overrides(epi_fog(), ["camera.resolution=[40, 30]", "camera.spp=1"])
    cases = ((fog, "raymarch", "light 0 travels along the view", 256, 6e-5, None),
             (epi_wide_spot(50.0, (40, 30)), "epipolar", None, 256, 0.13, 0.014),
             (epi_wide_spot(90.0, (40, 30)), "raymarch", "light 0: a spot light of half-angle",
              None, 1e-12, None))
    for d, method, why, ref_steps, bound, per_pixel in cases:
        d["camera"]["spp"] = 1
        scene = scene_from_dict(d)
        ref_scene = scene_from_dict(d)
        if ref_steps:
            ref_scene.render.params["raymarch"] = {"steps": ref_steps}
        ref = render(ref_scene, "raymarch", engine, show_progress=False)
        got = render(scene, "auto", engine, show_progress=False)
        assert_matches_reference(got.medium, ref.medium, bound, f"auto ({method}, {why})",
                                 mean_tol=0.01, per_pixel=per_pixel)
        notes = got.stats["plan"]
        assert f"direct by {method}" in notes, notes
        if method == "epipolar":
            lights = got.stats["epipolar_lights"]
            assert lights and "svd_error" in lights[0] and "svd_terms" in lights[0]
        else:
            assert "epipolar_lights" not in got.stats
            assert any(n.startswith(f"direct: not epipolar ({why}") for n in notes), notes


def test_epipole_ring_in_angle_with_a_blended_band(engine):
    """``epi_sun`` (the sun on screen) at 96 x 72, 1 spp, against raymarch (512 steps): the
    ring is 2 degrees around the epipole whatever the resolution, and the sweep and the
    ring's ray marcher are blended across 2 .. 4 degrees. Measured on the annulus 1 .. 4
    degrees: relMSE 0.102 with a hard edge (band 0), 0.0385 blended; asserted: blended at
    most half the hard edge's. The annulus alone is where the two estimates meet (its
    mean 2.6 % low, the typical pixel 9.7 % off): no bound there could catch a 2 % bias
    or 5 % noise, so it is held to relMSE <= 0.08 only, and the teeth are on the whole
    image: relMSE <= 0.05 (measured 0.0246, edge leaks at the grate's shadows), the
    typical lit pixel within 2.5 % (measured 1.5 %), the mean within 1 % (0.999)."""
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
            out[band] = (relmse(got[near], ref[near]), relmse(got, ref), st.values, got)
    finally:
        ps.release()
    print({b: (f"{a:.3g}", f"{w:.3g}") for b, (a, w, _, _) in out.items()})
    info = out[1.0][2]["epipolar_lights"][0]
    assert info["epipole_in_front"] and abs(info["ring_degrees"] - 2.0) < 1e-9
    assert info["ring_band_samples"] > 0
    assert near.sum() > 60
    blended = out[1.0][3]
    assert out[1.0][0] <= 0.08 and out[1.0][0] <= 0.5 * out[0.0][0]
    assert_matches_reference(blended, ref, 0.05, "whole image, blended", per_pixel=0.025,
                             mean_tol=0.01)


def test_extreme_optical_depth_falls_back_quietly(engine):
    """Optical depth 4000 across the box (sigma_s = 900 per unit, the sun behind the camera):
    the estimate's exponentials overflow on most held-out samples. Those count as failures
    (they were dropped once, which could let such an estimate pass), so the light is ray
    marched, no NumPy warning reaches the user, and the image is finite and within relMSE
    5e-5 of raymarch with 256 steps (measured 2.9e-5; raymarch's transmittance strategy
    puts its samples in the first thousandth of each segment, where the light is)."""
    import warnings
    d = epi_sweep(4000.0, "behind", "outside", "directional", RES)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got, ref, st = _pair(engine, d, 256)
    info = st["epipolar_lights"][0]
    print(f"depth 4000: {info.get('reason')}")
    assert info.get("fallback") == "raymarch"
    assert info["svd_error"]["nonfinite"] > 0 and "not finite" in info["reason"]
    assert np.isfinite(got).all() and ref.mean() > 0
    assert_matches_reference(got, ref, 5e-5, "depth 4000")
