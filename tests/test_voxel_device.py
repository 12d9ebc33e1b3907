"""The voxel view pass on the device against the host computation it replaced.

``_host_view_pass`` is the old ``view_pass``: the same tracer and march kernels, but every
per-ray array read back, the per-pixel sums done by ``np.bincount`` (float64), the
throughput filter in NumPy and the segments ordered by ``np.lexsort``. The device pass sums
in float32 (one running sum per pixel), hence the tolerances.
"""
from __future__ import annotations

import numpy as np
import pytest

from clscatter.device import AppendBuffer, launch_appending, structs
from clscatter.methods import configure
from clscatter.methods.voxel.grid import VOX_RAY
from clscatter.methods.voxel.photons import exits_by_photon
from clscatter.methods.voxel.pipeline import (
    Pipeline,
    direct_outside,
    gather_exits,
    outer_view,
)
from clscatter.methods.voxel.view import (
    MIN_THROUGHPUT,
    keep_rays,
    march_args,
    tracer_medium,
    view_pass,
)
from clscatter.scene.builtin.volumes import VOLUME_SCENES
from clscatter.scene.loader import scene_from_dict
from clscatter.transport.prepared import prepare_scene
from clscatter.transport.view_paths import (
    DeviceSegments,
    ViewPaths,
    accumulate_segments,
)

ROUNDS = 4


def _pixel_offsets(eng, pixels: np.ndarray, npix: int):
    """Device int32 offsets of each pixel's run in a pixel-sorted array."""
    return eng.to_device(np.searchsorted(pixels, np.arange(npix + 1)).astype(np.int32))


def test_keep_rays_matches_numpy(engine):
    """vox_keep_flags + compaction: the rays kept are NumPy's ``thr.max() > min_thr``
    selection, in order, byte for byte, and their pixel offsets are NumPy's."""
    rng = np.random.default_rng(3)
    n, w, h, thr = 5000, 16, 12, np.float32(2.5e-5)
    rays = np.zeros(n, VOX_RAY)
    t = rng.choice([0.0, 1e-6, thr, np.nextafter(thr, np.float32(1)), 1e-3, 0.5], (n, 4))
    rays["thr"] = rng.permutation(t.ravel()).reshape(n, 4).astype(np.float32)
    rays["thr"][:, 3] = 1.0                 # w is not a colour: must not count
    rays["pixel"] = np.sort(rng.integers(0, w * h, n))
    rays["sample"] = np.arange(n)
    rays["o"] = rng.normal(size=(n, 4))
    want = rays[rays["thr"][:, :3].max(axis=1) > thr]
    assert 0 < len(want) < n
    order = DeviceSegments(engine, engine.to_device(rays), n,
                           _pixel_offsets(engine, rays["pixel"], w * h), w, h)
    kept = keep_rays(engine, order.buf, order, float(thr))
    try:
        got = engine.read(kept.buf, kept.count, VOX_RAY)
        off = engine.read(kept.pix_off, w * h + 1, np.int32)
    finally:
        kept.release()
        order.release()
    assert kept.count == len(want) and got.tobytes() == want.tobytes()
    assert np.array_equal(off, np.searchsorted(want["pixel"], np.arange(w * h + 1)))


def test_exits_by_photon_matches_lexsort(engine):
    """Exits appended in no fixed order come back sorted by photon, as np.lexsort sorts."""
    rng = np.random.default_rng(5)
    photons = 3000
    ex = np.zeros(1200, structs.LIGHT_SEGMENT)
    ex["ray"] = rng.choice(photons, len(ex), replace=False)
    ex["flux"] = rng.random((len(ex), 4))
    ex["light"] = 2
    app = AppendBuffer(engine, structs.LIGHT_SEGMENT, len(ex))
    try:
        engine.cl.enqueue_copy(engine.queue, app.buf, ex)
        got = exits_by_photon(engine, app, len(ex), photons)
    finally:
        app.release()
    assert got.tobytes() == ex[np.lexsort((ex["ray"], ex["light"]))].tobytes()


# ---------------------------------------------------------------- the whole view pass --

def _scene():
    """volume_sphere between two mirrors, one behind the grid, one behind the camera
    (rays leave the grid and come back: more rounds than ROUNDS) and a glass ball beside
    it (Fresnel branches outside the grid), 2 spp; the volume absorbs strongly, so that
    some rays leave the grid too dark to go on (sigma_a 3: rays per round 404, 149, 14, 5;
    9 dropped), while rays through its rim still reach the last round."""
    d = VOLUME_SCENES["volume_sphere"]()
    d["camera"].update(resolution=[40, 30], spp=2)
    d["volumes"][0]["sigma_a"] = 3.0
    d["materials"].update(chrome={"type": "mirror", "reflectance": 0.9},
                          glass={"type": "dielectric", "ior": 1.5})
    d["objects"] += [{"shape": "quad", "origin": [-1.5, 0.3, -1.3], "edge_u": [3.0, 0.0, 0.0],
                      "edge_v": [0.0, 2.6, 0.0], "material": "chrome"},
                     {"shape": "quad", "origin": [-1.5, 0.3, 6.0], "edge_u": [3.0, 0.0, 0.0],
                      "edge_v": [0.0, 2.6, 0.0], "material": "chrome"},
                     {"shape": "sphere", "center": [1.2, 0.7, 0.3], "radius": 0.35,
                      "material": "glass"}]
    return scene_from_dict(d)


@pytest.fixture(scope="module")
def staged(engine):
    """The prepared scene with the voxel pipeline's geometry, material and lighting."""
    ps = prepare_scene(_scene(), engine)
    pipe = Pipeline(configure("voxel", {"resolution": 24, "photons": 1 << 12}))
    try:
        pipe._geometry(ps)
        pipe._material(ps)
        pipe._lighting(ps)
        yield ps, pipe
    finally:
        pipe.release(engine)
        ps.release()


def _host_tracer(ps, kernel: str, n: int, apps: dict, **args):
    """One straight-tracer launch with everything read back: (surface per work-item,
    stopped rays, segments), the last two in append order."""
    eng = ps.engine
    surface = eng.empty(16 * n)
    try:
        got = launch_appending(eng, "voxel", kernel, n, apps,
                               **{**ps.scene_args("voxel", kernel), **args},
                               max_depth=ps.scene.render.max_depth, surface=surface)
        recs = [eng.read(apps[k].buf, got[k], dt) if got[k] else np.zeros(0, dt)
                for k, dt in (("stopped", VOX_RAY), ("segs", structs.VIEW_SEGMENT))]
        return (eng.read(surface, (n, 4), np.float32), *recs)
    finally:
        eng.free(surface)


def _bincount(img: np.ndarray, pixels: np.ndarray, values: np.ndarray) -> None:
    """img (3, npix) += per-pixel float64 sums of values[:, :3]."""
    for c in range(3):
        img[c] += np.bincount(pixels, weights=values[:, c], minlength=img.shape[1])


def _image(img: np.ndarray, w: int, h: int) -> np.ndarray:
    """(3, npix) float64 sums as an (H, W, 3) float32 image."""
    return img.T.reshape(h, w, 3).astype(np.float32)


def _host_view_pass(ps, pipe, chunk: int):
    """The old host view pass: (surface, inside, segments, rays per round, rays dropped by
    the throughput filter)."""
    eng, box, cam = ps.engine, pipe.fields.box, ps.scene.camera
    w, h, spp = cam.width, cam.height, cam.spp
    total = w * h * spp
    apps = {"stopped": AppendBuffer(eng, VOX_RAY, 1), "segs": AppendBuffer(eng, structs.VIEW_SEGMENT, 1),
            "hits": AppendBuffer(eng, structs.DIFFUSE_HIT, 1)}
    med = tracer_medium(ps, box, False)
    bounds = {"gmin": box.lo4(), "gmax": box.hi4(), "want_hits": 0, "medium": med}
    surface, inside = np.zeros((3, w * h)), np.zeros((3, w * h))
    seg_parts, ray_parts, per_round, dropped = [], [], [], 0
    try:
        for start in range(0, total, chunk):
            n = min(chunk, total - start)
            surf, rays, sg = _host_tracer(ps, "voxel_trace_camera", n, apps, **bounds,
                                          seed=np.uint32(ps.scene.render.seed & 0xFFFFFFFF),
                                          sample_offset=start, num_samples=n)
            _bincount(surface, np.arange(start, start + n) // spp, surf)
            seg_parts.append(sg)
            ray_parts.append(rays)
        rays = np.concatenate(ray_parts)
        margs = march_args(ps, pipe.fields, pipe.radiance, True)
        for rnd in range(ROUNDS):
            if len(rays) == 0:
                break
            per_round.append(len(rays))
            n = len(rays)
            rin, rout, light = eng.to_device(rays), eng.empty(n * VOX_RAY.itemsize), eng.empty(16 * n)
            try:
                ps.call("voxel", "voxel_view_march", n, rays=rin, count=n, radiance=light,
                         rays_out=rout, **margs)
                _bincount(inside, rays["pixel"], eng.read(light, (n, 4), np.float32))
                out = eng.read(rout, n, VOX_RAY)
            finally:
                eng.free(rin, rout, light)
            keep = out["thr"][:, :3].max(axis=1) > MIN_THROUGHPUT / spp
            dropped += int(np.count_nonzero(~keep))
            out = out[keep]
            if len(out) == 0 or rnd == ROUNDS - 1:
                break
            rbuf = eng.to_device(out)
            try:
                surf, rays, sg = _host_tracer(ps, "voxel_trace_rays", len(out), apps, **bounds,
                                              min_weight=MIN_THROUGHPUT / spp, rays=rbuf,
                                              count=len(out))
            finally:
                eng.free(rbuf)
            _bincount(surface, out["pixel"], surf)
            seg_parts.append(sg)
    finally:
        for app in apps.values():
            app.release()
        eng.free(med)
    segs = np.concatenate(seg_parts)
    segs = segs[np.lexsort((segs["branch"], segs["sample"]))]
    return _image(surface, w, h), _image(inside, w, h), segs, per_round, dropped


@pytest.fixture(scope="module")
def passes(staged):
    """The device view pass (several launches: 701 samples each, a pixel split across
    two) and the host reference."""
    ps, pipe = staged
    vr = view_pass(ps, pipe.fields, pipe.radiance, ROUNDS, show_progress=False,
                   samples_per_launch=701, surface_photons=False)
    try:
        yield vr, _host_view_pass(ps, pipe, 701)
    finally:
        vr.segments.release()


def _read(d: DeviceSegments) -> np.ndarray:
    """The device segments as a host array (ViewPaths' lazy copy)."""
    return ViewPaths(None, None, device=d).segments


def _close(got: np.ndarray, want: np.ndarray, rtol: float = 1e-5) -> None:
    """float32 running sums (a few hundred terms per pixel at most) vs float64 bincount:
    within rtol of the value plus 1e-6 of the image's peak (near-zero pixels)."""
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=rtol, atol=1e-6 * float(want.max()))


def test_view_pass_matches_host_reference(passes):
    """Surface and inside images within float32 summation error; segments identical,
    record for record and in the same (sample, branch) order; the same rays per round.
    The scene has every round run (the mirrors send rays back in) and the throughput
    filter drop rays (the absorbing volume)."""
    vr, (surface, inside, segs, per_round, dropped) = passes
    assert len(per_round) == ROUNDS and dropped > 0   # every round ran, the filter dropped some
    assert vr.counters["voxel_view_rounds"] == len(per_round)
    assert vr.counters["voxel_view_rays"] == sum(per_round)
    _close(vr.surface, surface)
    _close(vr.inside, inside)
    keys = segs["sample"].astype(np.int64) * (1 << 31) + segs["branch"]
    assert len(np.unique(keys)) == len(segs) > 0     # (sample, branch) unique: one order
    got = _read(vr.segments)
    assert vr.counters["voxel_segments_outside"] == len(got)
    assert got.tobytes() == segs.tobytes()
    d = vr.segments
    pix = d.engine.read(d.pix_off, d.width * d.height + 1, np.int32)
    assert np.array_equal(pix, np.searchsorted(segs["pixel"], np.arange(len(pix))))


def test_view_pass_is_reproducible(staged, passes):
    """A second device pass, in launches of another size, gives the same bits for the
    rounds' sums and the segments (every sum runs in a sorted order)."""
    ps, pipe = staged
    vr = passes[0]
    again = view_pass(ps, pipe.fields, pipe.radiance, ROUNDS, show_progress=False,
                      surface_photons=False)
    try:
        assert np.array_equal(again.inside, vr.inside)
        assert _read(again.segments).tobytes() == _read(vr.segments).tobytes()
        _close(again.surface, vr.surface)     # camera launches split pixels differently
    finally:
        again.segments.release()


def _host_values(eng, n: int, launch) -> np.ndarray:
    """Per-segment float4 values of ``launch(out)`` (a kernel writing n of them), read back."""
    out = eng.empty(16 * n)
    try:
        launch(out)
        return eng.read(out, (n, 4), np.float32)
    finally:
        eng.free(out)


def test_segment_consumers_match_host_sums(staged, passes):
    """direct_outside, outer_view and gather_exits sum on the device what the host summed
    with bincount from per-segment values read back (the same kernels over the segments
    uploaded from the host)."""
    ps, pipe = staged
    eng, cam, rad = ps.engine, ps.scene.camera, pipe.radiance
    dev = passes[0].segments
    host = _read(dev)
    n, box = len(host), pipe.fields.box

    def image(values: np.ndarray) -> np.ndarray:
        return accumulate_segments(values, host["pixel"], cam.width, cam.height)

    med2 = np.zeros(2, ps.medium.dtype)
    med2[0] = ps.medium
    med2[1]["bmin"][:3], med2[1]["bmax"][:3] = box.lo, box.hi
    segs, med = eng.to_device(host), eng.to_device(med2)
    try:
        outer = _host_values(eng, n, lambda out: ps.call(
            "voxel", "outer_view", n, segs=segs, count=n, olo=rad.outer.lo4(), od=rad.outer.dims4(), oh=rad.outer.h, rad=rad.outer_rad,
            dirs=rad.outer_dirs, out=out))
        direct = _host_values(eng, n, lambda out: ps.call(
            "voxel_direct", "raymarch", n, **ps.scene_args("voxel_direct", "raymarch", medium=med),
            medium=med, segs=segs, seg_offset=0, num_segs=n, scale=out, use_scale=0, steps=8,
            seed=np.uint32((ps.scene.render.seed * 7919 + 17) & 0xFFFFFFFF), out=out))
    finally:
        eng.free(segs, med)
    _close(outer_view(ps, rad, dev), image(outer))
    _close(direct_outside(ps, box, dev, 8, per_launch=777), image(direct))
    from clscatter.estimators.line_gather import Gatherer
    ex = rad.exits
    assert len(ex) and np.array_equal(ex, ex[np.lexsort((ex["ray"], ex["light"]))])
    gat = Gatherer(eng, host, ps.medium, 0.02)
    try:
        gat.add(ex)
        want = image(gat.values())
    finally:
        gat.release()
    _close(gather_exits(ps, dev, ex, 0.02, show_progress=False), want)
