"""The records the surface-caustic methods are built from: lighting-ray pieces that end on
surfaces (light_paths.cl -DRAY_PIECES) and the diffuse hits of camera paths
(view_paths.cl trace_view asked for hits only), checked against flux / throughput bookkeeping."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np

from clscatter.device import structs
from clscatter.scene import scene_from_dict
from clscatter.transport.light_paths import trace_light_paths
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import trace_diffuse_hits, trace_view_paths

HERE = Path(__file__).resolve().parent
CAM = {"origin": [0.0, 3.0, 3.0], "target": [0.0, 0.0, 0.0], "resolution": [24, 16], "spp": 4}
BALL = {"camera": CAM,
        "lights": [{"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}],
        "materials": {"floor": {"type": "diffuse", "albedo": 0.5},
                      "glass": {"type": "dielectric", "ior": 1.5}},
        "objects": [{"shape": "quad", "origin": [-2.0, 0.0, -2.0], "edge_u": [4.0, 0.0, 0.0],
                     "edge_v": [0.0, 0.0, 4.0], "material": "floor"},
                    {"shape": "sphere", "center": [0.0, 1.0, 0.0], "radius": 0.5,
                     "material": "glass"}],
        "render": {"max_depth": 16}}


def _prep(engine, d):
    return prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "t"), engine)


def test_ray_pieces_end_on_surfaces_and_conserve_flux(engine):
    ps = _prep(engine, BALL)
    lp = trace_light_paths(ps, 20000, show_progress=False, pieces=True)
    ps.release()
    p = lp.segments
    assert p.dtype == structs.RAY_PIECE and len(p) > 20000
    # no medium: every unit of flux entering the scene box (E times the 4 x 4 floor, in
    # normalised units) ends in exactly one piece (up to the branches dropped below 1e-4
    # of a ray's flux and depth 16); rays on the emission rectangle's margin miss the box
    entering = 2.0 * (4.0 / ps.frame.scale) ** 2
    total = p["flux"][:, :3].sum(0)
    assert np.allclose(total, entering, rtol=2e-3)
    assert np.all(total <= lp.flux_per_ray[0] * lp.rays[0])
    # diffuse pieces end on the floor (y = 0 in world units)
    diffuse = p[p["end"] == structs.PIECE_DIFFUSE]
    y_world = diffuse["b"][:, 1] * ps.frame.scale + ps.frame.centre[1]
    assert np.abs(y_world).max() < 1e-4
    # light straight from the sun: depth 0 pieces are vertical and carry E * area each
    d0 = p[p["depth"] == 0]
    assert np.allclose(d0["flux"][:, :3], lp.flux_per_ray[0], rtol=1e-6)
    # the ball's shadow on the floor holds only refracted (depth >= 2) light
    r_world = np.hypot(*(diffuse["b"][:, [0, 2]] * ps.frame.scale + ps.frame.centre[[0, 2]]).T)
    assert np.all(diffuse["depth"][r_world < 0.45] >= 1)
    assert np.all(p["end"][p["depth"] == 0] != structs.PIECE_BLACK)


def test_diffuse_hits_account_for_every_camera_path(engine):
    d = copy.deepcopy(BALL)
    d["objects"] = d["objects"][:1]
    ps = _prep(engine, d)
    paths = trace_view_paths(ps, show_progress=False)
    hits = trace_diffuse_hits(ps)
    ps.release()
    w, h = CAM["resolution"]
    seen = np.bincount(hits["pixel"], weights=hits["weight"][:, 0] * math.pi / 0.5, minlength=w * h)
    # per pixel: throughput on the floor + throughput that escaped = 1
    assert np.allclose(seen + paths.escaped[..., 0].ravel(), 1.0, atol=1e-5)
    # and the surface image is weight * E * cos: a directional light of E = 2 straight down
    surf = np.bincount(hits["pixel"], weights=hits["weight"][:, 0] * 2.0, minlength=w * h)
    assert np.allclose(surf, paths.surface[..., 0].ravel(), rtol=1e-4, atol=1e-7)
    assert np.allclose(hits["n"][:, 1], 1.0, atol=1e-6)


def test_diffuse_hits_through_glass_carry_fresnel_weights(engine):
    ps = _prep(engine, BALL)
    paths = trace_view_paths(ps, show_progress=False)
    hits = trace_diffuse_hits(ps)
    ps.release()
    assert hits["depth"].max() >= 2                      # the floor seen through the ball
    w, h = CAM["resolution"]
    seen = np.bincount(hits["pixel"], weights=hits["weight"][:, 0] * math.pi / 0.5, minlength=w * h)
    assert np.all(seen + paths.escaped[..., 0].ravel() <= 1.0 + 1e-5)
    assert np.allclose(seen + paths.escaped[..., 0].ravel(), 1.0, atol=2e-3)
