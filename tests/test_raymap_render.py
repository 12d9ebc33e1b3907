"""End to end: ``--method raymap`` / ``photonmap`` render the whole picture, ``auto`` adds a
surface-caustic pass by raymap when glass can light a diffuse surface, and records it."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from clscatter.pipeline.render import render
from clscatter.scene import scene_from_dict

HERE = Path(__file__).resolve().parent
SCENE = {"camera": {"origin": [0.0, 2.2, 2.6], "target": [0.0, 0.3, 0.0], "resolution": [40, 30],
                    "spp": 1, "fov": 50.0},
         "lights": [{"type": "point", "position": [0.0, 2.5, 0.0], "intensity": 4.0}],
         "materials": {"floor": {"type": "diffuse", "albedo": 0.6},
                       "glass": {"type": "dielectric", "ior": 1.5}},
         "objects": [{"shape": "quad", "origin": [-1.5, 0.0, -1.5], "edge_u": [3.0, 0.0, 0.0],
                      "edge_v": [0.0, 0.0, 3.0], "material": "floor"},
                     {"shape": "sphere", "center": [0.0, 0.9, 0.0], "radius": 0.4, "material": "glass"}],
         "render": {"max_depth": 12, "raymap": {"photons": 20000, "k": 32},
                    "photonmap": {"photons": 20000, "k": 32}}}


def _scene():
    return scene_from_dict(copy.deepcopy(SCENE), HERE, "t")


def test_methods_render_the_caustic_in_the_shadow(engine):
    out = {m: render(_scene(), m, engine=engine, show_progress=False) for m in ("raymarch", "raymap", "photonmap")}
    direct = out["raymarch"].image
    for m in ("raymap", "photonmap"):
        img = out[m].image
        assert np.isfinite(img).all() and img.min() >= 0
        extra = img - direct                       # the surface caustic alone
        assert extra.min() > -1e-6                 # adds light, never removes any
        # the focus below the ball: the brightest added pixel is far brighter than the
        # directly lit floor around the shadow
        assert extra.max() > 2 * np.percentile(direct, 90)
        assert out[m].stats["method"] == m
    a, b = (out[m].image - direct for m in ("raymap", "photonmap"))
    assert abs(a.sum() / b.sum() - 1) < 0.05      # same light, two estimators


def test_auto_adds_and_records_the_surface_caustic_pass(engine):
    res = render(_scene(), "auto", engine=engine, show_progress=False)
    st = res.stats
    assert {"method": "raymap", "role": "surface_caustics"} in st["passes"]
    assert any(n.startswith("surface_caustics by raymap") for n in st["plan"])
    assert st["raymap_rays_stored"] > 0 and st["diffuse_hits"] > 0
    no_glass = copy.deepcopy(SCENE)
    no_glass["objects"] = no_glass["objects"][:1]
    st2 = render(scene_from_dict(no_glass, HERE, "t"), "auto", engine=engine, show_progress=False).stats
    assert all(p["role"] != "surface_caustics" for p in st2["passes"])


def test_surface_caustics_sums_on_the_device_as_the_host_would(engine):
    """surface_caustics keeps the hits, their irradiance and the per-pixel sums on the
    device (batches of 100 queries: several launches into one buffer); against the host
    route (hits read back, estimate(), weight x E, bincount by pixel) with the same seeds:
    equal within float32 summation, and the work counters equal exactly."""
    from clscatter.estimators.ray_density import (
        DensitySettings,
        build_map,
        caustic_pieces,
        estimate,
        surface_caustics,
    )
    from clscatter.io.stats import Stats
    from clscatter.transport.prepared import prepare_scene
    from clscatter.transport.view_paths import trace_diffuse_hits
    ps = prepare_scene(_scene(), engine)
    s = DensitySettings(k=16, max_radius=0.2, batch=100)
    try:
        st = Stats()
        img = surface_caustics(ps, "raymap", 5000, s, st, show_progress=False)
        pieces = caustic_pieces(ps, 5000, show_progress=False)
        hits = trace_diffuse_hits(ps)
        rmap = build_map(engine, pieces, "raymap", s)
        try:
            e, work = estimate(rmap, hits["p"][:, :3], hits["n"][:, :3], "raymap", s)
        finally:
            rmap.release()
    finally:
        ps.release()
    w, h = 40, 30
    value = hits["weight"][:, :3].astype(np.float64) * e
    ref = np.stack([np.bincount(hits["pixel"], weights=value[:, c], minlength=w * h)
                    for c in range(3)], axis=1).reshape(h, w, 3)
    assert ref.max() > 0 and len(hits) > 800       # 9 batches of 100
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6 * ref.max())
    assert st.values["raymap_nodes_visited"] == int(work[:, 0].sum()) > 0
    assert st.values["raymap_refs_tested"] == int(work[:, 1].sum()) > 0
