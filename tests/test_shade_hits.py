"""shade_hits (view_paths.cl), the warm path's re-shading of recorded diffuse hits, against
NumPy: weight x sum over lights of E cos T, with E = power / d^2 (point) or the
irradiance (directional), T = exp(-kappa x the shadow ray's length inside the medium box),
lights behind the surface giving nothing; and the per-pixel sum equals the view paths' own surface image."""
from __future__ import annotations

import numpy as np

from clscatter.device import structs
from clscatter.scene.loader import scene_from_dict
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import (
    shade_hits,
    trace_diffuse_hits_on_device,
    trace_view_paths,
)

SCENE = {
    "camera": {"origin": [0.0, 2.0, 0.01], "target": [0.0, 0.0, 0.0], "fov": 60.0,
               "resolution": [23, 17], "spp": 3},
    "medium": {"sigma_s": 0.0, "sigma_a": [0.05, 0.1, 0.2],
               "bounds": {"min": [-3.0, -1.0, -3.0], "max": [3.0, 3.0, 3.0]}},
    "lights": [{"type": "point", "position": [0.4, 1.5, -0.3], "intensity": [5.0, 4.0, 3.0]},
               {"type": "directional", "direction": [0.2, 1.0, 0.1], "irradiance": 2.0},
               {"type": "directional", "direction": [0.3, -1.0, 0.2], "irradiance": 0.5}],
    "objects": [{"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
                 "edge_v": [0.0, 0.0, 4.0],
                 "material": {"type": "diffuse", "albedo": [0.7, 0.5, 0.3]}}],
}


def test_shade_hits_matches_numpy_and_the_view_paths(engine):
    ps = prepare_scene(scene_from_dict(SCENE), engine)
    hits = trace_diffuse_hits_on_device(ps)
    out = engine.empty(16 * hits.count)
    try:
        ps.call("view_paths", "shade_hits", hits.count, hits=hits.buf, n=hits.count, out=out)
        got = engine.read(out, (hits.count, 4), np.float32)
        h = engine.read(hits.buf, hits.count, structs.DIFFUSE_HIT)
        image = shade_hits(ps, hits)
        surface = trace_view_paths(ps, show_progress=False).surface
    finally:
        engine.free(out)
        hits.release()
        ps.release()
    assert hits.count == 23 * 17 * 3             # every sample sees the floor
    p = h["p"][:, :3].astype(np.float64)
    n = h["n"][:, :3].astype(np.float64)
    kappa = ps.medium["kappa"][:3].astype(np.float64)
    hi = ps.medium["bmax"][:3].astype(np.float64)
    lo = ps.medium["bmin"][:3].astype(np.float64)
    E = np.zeros((len(h), 3))
    for L in ps.lights:
        if L["type"] == structs.LIGHT_DIRECTIONAL:
            wi = np.broadcast_to(-L["direction"][:3].astype(np.float64), p.shape)
            e = np.broadcast_to(L["power"][:3].astype(np.float64), p.shape)
            with np.errstate(divide="ignore"):        # the hits lie inside the box: exit
                d = np.min(np.where(wi > 0, (hi - p) / wi, np.where(wi < 0, (lo - p) / wi,
                                                                     np.inf)), axis=1)
        else:
            to = L["position"][:3].astype(np.float64) - p
            d = np.linalg.norm(to, axis=1)
            wi = to / d[:, None]
            e = L["power"][:3].astype(np.float64) / d[:, None] ** 2
        tr = np.exp(-kappa * d[:, None])
        c = np.einsum("ij,ij->i", n, wi)
        E += np.where(c[:, None] > 0, e * c[:, None] * tr, 0.0)
    want = h["weight"][:, :3].astype(np.float64) * E
    assert (E[:, 0] > 0).all() and want.max() > 0
    np.testing.assert_allclose(got[:, :3], want, rtol=2e-5, atol=1e-9)
    np.testing.assert_allclose(image, surface, rtol=1e-5, atol=1e-8)


GLASS = {**SCENE, "medium": {**SCENE["medium"], "sigma_s": 0.3},
         "objects": SCENE["objects"] + [
             {"shape": "sphere", "center": [0.3, 0.6, 0.2], "radius": 0.5,
              "material": {"type": "dielectric", "ior": 1.5}}]}


def test_hits_recorded_with_the_view_paths_equal_a_hits_only_trace(engine):
    """One launch gives segments, surface and hits (a session's first render): the hits
    equal those of the hits-only trace record for record (sorted by (sample, branch)),
    and recording them changes neither the segments nor the surface image. Glass splits
    paths into branches, so several hits per sample occur."""
    ps = prepare_scene(scene_from_dict(GLASS), engine)
    both = trace_view_paths(ps, show_progress=False, keep_hits=True,
                            samples_per_launch=300)        # several launches, 4 stores
    plain = trace_view_paths(ps, show_progress=False)
    alone = trace_diffuse_hits_on_device(ps, samples_per_launch=500)
    try:
        h_both = engine.read(both.hits.buf, both.hits.count, structs.DIFFUSE_HIT)
        h_alone = engine.read(alone.buf, alone.count, structs.DIFFUSE_HIT)
        off_both = engine.read(both.hits.pix_off, 23 * 17 + 1, np.int32)
        off_alone = engine.read(alone.pix_off, 23 * 17 + 1, np.int32)
        segs_both, segs_plain = both.segments, plain.segments
        surf_both, surf_plain = both.surface, plain.surface
    finally:
        both.release()
        plain.release()
        alone.release()
        ps.release()
    assert len(h_both) > 23 * 17 * 3                  # the glass's extra branches
    assert plain.hits is None and both.hits is None   # released with the paths
    np.testing.assert_array_equal(h_both.view(np.uint8), h_alone.view(np.uint8))
    np.testing.assert_array_equal(off_both, off_alone)
    assert len(segs_both) == len(segs_plain) > 0
    np.testing.assert_array_equal(segs_both.view(np.uint8), segs_plain.view(np.uint8))
    np.testing.assert_array_equal(surf_both, surf_plain)
