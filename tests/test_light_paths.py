"""The light-path tracer: emitted flux adds up to the light's power, directions are
stratified and uniform, mirrors and glass split flux without creating any."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from clscatter.scene import scene_from_dict
from clscatter.transport.light_paths import chunk_rays, emission, trace_light_paths
from clscatter.transport.prepared import prepare_scene

HERE = Path(__file__).resolve().parent
CAM = {"origin": [0.0, 0.0, 5.0], "target": [0.0, 0.0, 0.0], "resolution": [8, 8], "spp": 1}


def _prep(engine, d):
    return prepare_scene(scene_from_dict(copy.deepcopy(d), HERE, "t"), engine)


def test_point_light_rays_cover_the_sphere_uniformly(engine):
    d = {"camera": CAM, "medium": {"sigma_s": 0.1, "sigma_a": 0.0},
         "lights": [{"type": "point", "position": [0.0, 0.0, 0.0], "intensity": [2.0, 1.0, 0.5]}]}
    ps = _prep(engine, d)
    lp = trace_light_paths(ps, 4096, show_progress=False)
    ps.release()
    s = lp.segments
    assert len(s) == 4096 and np.all(s["depth"] == 0)
    dirs = s["b"][:, :3] - s["a"][:, :3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # uniform on the sphere: mean ~0, <z^2> = 1/3, every octant ~1/8
    assert np.abs(dirs.mean(0)).max() < 0.01
    assert abs((dirs[:, 2] ** 2).mean() - 1 / 3) < 0.01
    octant = (dirs > 0) @ np.array([1, 2, 4])
    assert np.abs(np.bincount(octant, minlength=8) / 4096 - 1 / 8).max() < 0.01
    # total flux = 4 pi I (normalised units: I / scale^2)
    total = s["flux"][:, :3].sum(0)
    assert np.allclose(total, 4 * math.pi * np.array([2.0, 1.0, 0.5]) / ps.frame.scale ** 2, rtol=1e-4)


def test_spot_and_directional_emission(engine):
    d = {"camera": CAM, "medium": {"sigma_s": 0.1, "sigma_a": 0.0,
                                   "bounds": {"min": [-1, -1, -1], "max": [1, 1, 1]}},
         "lights": [{"type": "spot", "position": [0.0, 0.0, 0.0], "target": [0.0, 1.0, 0.0],
                     "intensity": 3.0, "cutoff_angle": 30.0},
                    {"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 2.0}]}
    ps = _prep(engine, d)
    lp = trace_light_paths(ps, 20000, show_progress=False)
    s = lp.segments
    spot = s[s["light"] == 0]
    dirs = spot["b"][:, :3] - spot["a"][:, :3]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    assert dirs[:, 1].min() >= math.cos(math.radians(30.0)) - 1e-5
    assert np.isclose(spot["flux"][:, 0].sum(),
                      2 * math.pi * (1 - math.cos(math.radians(30))) * 3.0 / ps.frame.scale ** 2, rtol=1e-5)
    sun = s[s["light"] == 1]
    # rays that enter the unit box carry E * (box cross-section) in total
    em = emission(ps, 1)
    assert np.isclose(em.power[0] / (np.linalg.norm(em.rect[1]) * np.linalg.norm(em.rect[2])), 2.0)
    box_area = (2.0 / ps.frame.scale) ** 2
    assert np.isclose(sun["flux"][:, 0].sum(), 2.0 * box_area, rtol=0.02)
    assert np.allclose(sun["a"][:, 1], 1.0 / ps.frame.scale * 1.0 - ps.frame.point([0, 0, 0])[1], atol=1e-5)
    ps.release()


def test_glass_and_mirror_conserve_flux(engine):
    d = {"camera": CAM, "medium": {"sigma_s": 1e-6, "sigma_a": 0.0,
                                   "bounds": {"min": [-3, -3, -3], "max": [3, 3, 3]}},
         "lights": [{"type": "point", "position": [0.0, 2.0, 0.0], "intensity": 1.0}],
         "objects": [{"shape": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0,
                      "material": {"type": "dielectric", "ior": 1.5}}],
         "render": {"max_depth": 32}}
    ps = _prep(engine, d)
    s = trace_light_paths(ps, 2000, show_progress=False).segments
    ps.release()
    # every lighting ray ends on the medium box: sum of the flux of the segments that leave
    # the box (the last piece of each branch) equals the emitted power
    out = s[np.abs(np.abs(s["b"][:, :3]).max(axis=1) - 3.0 / ps.frame.scale) < 1e-4]
    emitted = 4 * math.pi / ps.frame.scale ** 2
    assert abs(out["flux"][:, 0].sum() / emitted - 1) < 2e-3
    assert s["depth"].max() >= 2                      # paths went through the glass
    d["objects"][0]["material"] = {"type": "mirror", "reflectance": 0.5}
    ps = _prep(engine, d)
    s = trace_light_paths(ps, 2000, show_progress=False).segments
    ps.release()
    out = s[np.abs(np.abs(s["b"][:, :3]).max(axis=1) - 3.0 / ps.frame.scale) < 1e-4]
    hit_fraction = (1 - math.sqrt(1 - (1 / 2) ** 2)) / 2     # solid angle of the sphere seen from the light
    assert abs(out["flux"][:, 0].sum() / emitted - (1 - 0.5 * hit_fraction)) < 5e-3


@pytest.mark.parametrize("interleaved", [False, True])
def test_chunks_reproduce_the_full_trace(engine, interleaved):
    """The chunks of a trace are the full trace's rays, each once: contiguous runs of
    them, or (interleaved) rays k, k + n, ... that spread over all the directions."""
    d = {"camera": CAM, "medium": {"sigma_s": 0.1, "sigma_a": 0.0},
         "lights": [{"type": "point", "position": [0.0, 0.0, 0.0], "intensity": 1.0}]}
    ps = _prep(engine, d)
    full = trace_light_paths(ps, 1000, show_progress=False).segments
    parts = [trace_light_paths(ps, 1000, show_progress=False, chunk=(k, 3),
                               interleaved=interleaved).segments for k in range(3)]
    ps.release()
    joined = np.concatenate(parts)
    assert np.array_equal(np.sort(joined["ray"]), np.sort(full["ray"]))
    assert np.allclose(np.sort(joined["b"][:, 0]), np.sort(full["b"][:, 0]))
    for k, part in enumerate(parts):
        rays = np.unique(part["ray"])
        assert len(rays) == chunk_rays(np.array([1000]), k, 3, interleaved)
        # the Hammersley point's first coordinate is the ray's index over the count
        # (rotated): a contiguous run is a band of a third of the cosines (in at most 3 of
        # 6 equal bins, 4 if it straddles), an interleaved chunk spans them all
        d = (part["b"] - part["a"])[:, :3]
        z = d[:, 2] / np.linalg.norm(d, axis=1)
        bins = len(np.unique(np.clip(np.floor((z + 1) * 3), 0, 5)))
        if interleaved:
            assert np.all(rays % 3 == k) and bins == 6
            # and every azimuth alike (the radical inverse, with an odd stride): 8 wedges
            # of about 1/8 each (333 rays: a multinomial spread of about 6 %)
            phi = np.histogram(np.arctan2(d[:, 1], d[:, 0]), 8, (-np.pi, np.pi))[0] / len(d)
            assert np.abs(phi - 1 / 8).max() < 0.03
        else:
            assert rays.max() - rays.min() + 1 == len(rays) and bins <= 4


def test_interleaved_chunks_come_in_odd_counts(engine):
    """An even count of interleaved chunks would make each a wedge of directions: it is
    refused, and ``interleaved_parts`` gives the odd count that holds at most about the
    asked rays a chunk."""
    from clscatter.transport.light_paths import interleaved_parts

    assert [interleaved_parts(r, 100) for r in (50, 100, 101, 200, 250, 301, 400)] == \
        [1, 1, 3, 3, 3, 5, 5]
    d = {"camera": CAM, "medium": {"sigma_s": 0.1, "sigma_a": 0.0},
         "lights": [{"type": "point", "position": [0.0, 0.0, 0.0], "intensity": 1.0}]}
    ps = _prep(engine, d)
    try:
        with pytest.raises(ValueError, match="odd"):
            trace_light_paths(ps, 1000, show_progress=False, chunk=(0, 4), interleaved=True)
        assert len(trace_light_paths(ps, 1000, show_progress=False, chunk=(0, 4)).segments)
    finally:
        ps.release()
