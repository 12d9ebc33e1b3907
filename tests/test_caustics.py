"""The caustic scenes (clscatter/scene/builtin/caustics.py): their meshes, that each loads
and renders, and LSG against a converged VPM on one of them."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import tomllib
import trimesh
from reference_checks import assert_matches_reference

from clscatter.io.image import relmse
from clscatter.pipeline.render import render
from clscatter.scene import procedural, scene_from_dict
from clscatter.scene.builtin import to_toml
from clscatter.scene.builtin.caustics import CAUSTIC_SCENES, MESH_DIR


# ---- meshes ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(procedural.MESHES))
def test_committed_meshes_match_their_generators(name):
    path = MESH_DIR / f"{name}.obj"
    assert path.is_file() and path.stat().st_size < 200_000
    mesh = trimesh.load(str(path), force="mesh", process=False)
    v, f = procedural.MESHES[name]()
    assert np.array_equal(np.asarray(mesh.faces), f)
    np.testing.assert_allclose(np.asarray(mesh.vertices), v, atol=1e-5)   # 5 decimals in the file


@pytest.mark.parametrize("name", ["torus", "gem", "blob"])
def test_glass_meshes_are_closed_and_wound_outward(name):
    v, f = procedural.MESHES[name]()
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0          # counter-clockwise seen from outside
    if name == "torus":             # 2 pi^2 R r^2, within the polygonal approximation
        assert mesh.volume == pytest.approx(2 * math.pi ** 2 * 1.0 * 0.35 ** 2, rel=0.02)
    if name == "gem":               # a convex solid with flat facets
        assert mesh.is_convex and len(f) < 100


def test_dish_is_a_concave_cap():
    v, f = procedural.dish(radius=1.0, curvature_radius=2.2)
    rim = np.hypot(v[:, 0], v[:, 1])
    assert rim.max() == pytest.approx(1.0, abs=1e-9)
    # every vertex lies on the sphere of radius 2.2 centred on the axis at z = 2.2
    np.testing.assert_allclose(np.linalg.norm(v - [0, 0, 2.2], axis=1), 2.2, rtol=1e-12)
    assert not trimesh.Trimesh(v, f).is_watertight


# ---- every scene loads and renders -----------------------------------------------------------
def _small(d: dict, w: int = 40, h: int = 30) -> dict:
    d = copy.deepcopy(d)
    d["camera"]["resolution"] = [w, h]
    d["camera"]["spp"] = 1
    return d


@pytest.mark.parametrize("name", sorted(CAUSTIC_SCENES))
def test_scene_loads_from_any_directory_and_as_toml(name, tmp_path):
    d = CAUSTIC_SCENES[name]()
    a = scene_from_dict(copy.deepcopy(d), tmp_path, name)     # mesh paths do not depend on it
    b = scene_from_dict(tomllib.loads(to_toml(d)), tmp_path, name)
    assert a.triangle_count() == b.triangle_count() > 2
    assert a.medium is not None and a.medium.bounds is not None
    kinds = {o.material.type for o in a.objects}
    assert "diffuse" in kinds and kinds & {"dielectric", "mirror"}
    lo, hi = a.bbox()
    mlo, mhi = a.medium.bounds
    assert np.all(mlo <= lo + 1e-9) and np.all(hi <= mhi + 1e-9)   # the medium box holds it all
    for light in a.lights:         # lights inside the medium: their glows are visible
        assert np.all(light.position > mlo) and np.all(light.position < mhi)


@pytest.mark.parametrize("name", sorted(CAUSTIC_SCENES))
def test_scene_renders_with_raymarch(name, engine):
    res = render(scene_from_dict(_small(CAUSTIC_SCENES[name]()), ".", name), "raymarch",
                 engine=engine, show_progress=False)
    img = res.image
    assert np.all(np.isfinite(img)) and img.min() >= 0
    assert res.stats.get("nonfinite_pixels_zeroed", 0) == 0
    assert res.medium.max() > 0.02 and res.surface.max() > 0.02   # lit medium and floor
    assert 0.005 < img.mean() < 1.0 and img.max() < 50


# ---- LSG against a converged VPM --------------------------------------------------------------
def test_lsg_matches_converged_vpm_on_caustic_sphere(engine):
    """At 64 x 48: VPM with 2M photons, knn 32, dx 0.003 against LSG with 400k rays,
    r = 0.002. Measured (seed 0): LSG vs VPM relMSE 1.2e-3 (bound 2.4e-3), the typical
    lit pixel 1.43 % off (bound 2.5 %), means within 0.04 % (bound 1 %); VPM vs raymarch
    (no caustics: the glass blocks the light) 5.0e-3, 4.1 x LSG's (asserted: > 3 x). With
    the earlier absolute-floor relMSE (seeds 0-2): LSG vs VPM 1.6e-4 .. 2.0e-4, VPM vs
    raymarch 2.1e-3 .. 2.3e-3. The light raymarch lacks, summed over the 12 brightest
    caustic pixels of both: LSG / VPM = 0.71 .. 0.94 over VPM's light seeds 0-3, its
    photons deposited in one part or in parts (relMSE 1.24e-3 .. 1.51e-3 then): the
    pixels are picked where the sum is brightest, so VPM's noise weighs in, and its
    k-nearest estimate spreads a caustic's light beyond it (its region totals come out
    above an independent tracer's: tests/test_caustic_reference.py)."""
    pytest.importorskip("clscatter.methods.lsg")
    d = _small(CAUSTIC_SCENES["caustic_sphere"](), 64, 48)
    d["render"]["vpm"] = {"photons": 2_000_000, "knn": 32, "dx": 0.003}
    d["render"]["lsg"] = {"light_rays": 400_000, "radius": 0.002}
    scene = scene_from_dict(d, ".", "caustic_sphere")
    img = {m: render(scene, m, engine=engine, show_progress=False).image
           for m in ("vpm", "lsg", "raymarch")}
    err = assert_matches_reference(img["lsg"], img["vpm"], 2.4e-3, "LSG vs VPM", per_pixel=0.025,
                                   mean_tol=0.01)["relmse"]
    assert relmse(img["raymarch"], img["vpm"]) > 3 * err      # the caustic matters here
    assert img["lsg"].sum() / img["vpm"].sum() == pytest.approx(1.0, abs=0.02)
    # the caustic: light that raymarch does not have, brightest 12 pixels of both methods
    extra = {m: (img[m] - img["raymarch"]).sum(-1) for m in ("vpm", "lsg")}
    top = np.argsort((extra["vpm"] + extra["lsg"]).ravel())[-12:]
    v, l = extra["vpm"].ravel()[top].sum(), extra["lsg"].ravel()[top].sum()
    assert v > 0.5 and 0.6 < l / v < 1.1, (v, l)
