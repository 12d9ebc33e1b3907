"""Requests beyond the machine are refused in one line before anything is allocated: every
parameter that scales memory or work, set to 1e9 (or the largest its type allows), in a
process whose address space is capped (so an allocation that slipped through would fail
loudly instead of swapping), names the key to lower and exits 2 with nothing written.
And work that legitimately exceeds one allocation is chunked instead of refused."""
from __future__ import annotations

import resource
import subprocess
import sys

import numpy as np
import pytest

CAP = 6 << 30          # bytes of address space: Python, NumPy, PyOpenCL and PoCL fit easily
# a GPU driver reserves far more address space than any such cap (NVIDIA's OpenCL finds no
# platform under it): there the refusal is checked without the cap

CASES = [
    ("builtin:occluder", "raymarch", ["render.raymarch.steps=1000000000"], "render.raymarch.steps"),
    ("builtin:caustic_sphere", "lsg", ["render.lsg.light_rays=1000000000"], "render.lsg.light_rays"),
    ("builtin:caustic_sphere", "vpm", ["render.vpm.photons=1000000000"], "render.vpm.photons"),
    ("builtin:caustic_sphere", "raymap", ["render.raymap.photons=1000000000"],
     "render.raymap.photons"),
    ("builtin:caustic_sphere", "photonmap", ["render.photonmap.photons=1000000000"],
     "render.photonmap.photons"),
    ("builtin:volume_sphere", "voxel", ["render.voxel.resolution=1024"], "render.voxel.resolution"),
    ("builtin:volume_sphere", "voxel", ["render.voxel.photons=1000000000"], "render.voxel.photons"),
    ("builtin:shafts", "epipolar", ["render.epipolar.light_rays=1000000000"],
     "render.epipolar.light_rays"),
    ("builtin:shafts", "epipolar", ["render.epipolar.shadow_map=1000000000"],
     "render.epipolar.shadow_map"),
    ("builtin:shafts", "auto", ["camera.spp=1000000000"], "camera.spp"),
    ("builtin:shafts", "auto", ["camera.resolution=[100000,100000]"], "camera.resolution"),
]


def _capped():
    resource.setrlimit(resource.RLIMIT_AS, (CAP, CAP))


@pytest.fixture(scope="module")
def cap(engine):
    import pyopencl as cl
    return _capped if engine.device.type & cl.device_type.CPU else None


def _render(args: list[str], tmp_path, cap):
    out = tmp_path / "out.npy"
    r = subprocess.run([sys.executable, "-m", "clscatter", "render", *args, "-o", str(out),
                        "--no-progress"], capture_output=True, text=True, timeout=120,
                       preexec_fn=cap)
    return r, out


@pytest.mark.parametrize("scene, method, sets, key", CASES,
                         ids=[f"{c[1]}-{c[3]}" for c in CASES])
def test_a_request_beyond_the_machine_is_refused_before_allocation(scene, method, sets, key,
                                                                    tmp_path, cap):
    args = [scene, "--method", method]
    for kv in sets:
        args += ["--set", kv]
    r, out = _render(args, tmp_path, cap)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith(f"clscatter: error: {key}: "), lines
    assert f"lower {key}" in lines[0]
    assert not out.exists()


def test_a_scene_with_too_many_triangles_is_refused_before_it_is_built(tmp_path, cap):
    """2000 spheres of 327,680 triangles each: the loader counts them from the keys and
    names the object that crosses the machine's limit, before building any of them."""
    spheres = "\n".join(
        f'[[objects]]\nshape = "sphere"\ncenter = [{i % 50}, {i // 50}, 0]\nradius = 0.4\n'
        f'subdivisions = 7\nmaterial = "grey"\n' for i in range(2000))
    scene = tmp_path / "many.toml"
    scene.write_text('[camera]\norigin = [25, 20, 80]\ntarget = [25, 20, 0]\n\n'
                     '[[lights]]\ntype = "point"\nposition = [25, 60, 20]\nintensity = 100\n\n'
                     '[materials.grey]\ntype = "diffuse"\nalbedo = 0.5\n\n' + spheres)
    r, out = _render([str(scene)], tmp_path, cap)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(lines) == 1 and "objects[" in lines[0] and ".subdivisions: " in lines[0], lines
    assert "triangles" in lines[0] and not out.exists()


def test_work_beyond_one_allocation_is_chunked_not_refused(engine):
    """LSG's lighting rays are processed in chunks bounded by ``max_bytes``: a budget far
    below one pass's working set is met by more chunks, and (with a fixed radius) the
    image is the unchunked one."""
    from clscatter.pipeline.session import RenderSession
    sets = ["camera.resolution=[24,18]", "camera.spp=1", "render.lsg.light_rays=20000",
            "render.lsg.radius=0.01"]
    images, chunks = [], []
    for extra in ([], ["render.lsg.max_bytes=1000000"]):
        with RenderSession.from_source("builtin:caustic_sphere", sets + extra, method="lsg",
                                       engine=engine) as s:
            res = s.render(show_progress=False)
        images.append(res.image)
        chunks.append(res.stats["chunks"])
    assert chunks[0] == 1 and chunks[1] > 4
    np.testing.assert_allclose(images[1], images[0], rtol=1e-4, atol=1e-6 * images[0].max())


def test_a_pass_over_the_memory_budget_is_fitted_in_smaller_chunks(engine):
    """A render whose LSG pass, as set, needs more than ``max_memory`` is not refused: its
    chunk bound (``max_bytes``) is lowered to what the budget leaves beside the view paths
    and the scene, with a note naming the key; the estimated peak then fits, the rays are
    gathered in more chunks, and (fixed radius) the image is the one without a budget.
    Below what the smallest chunk needs it is still refused, naming the key to lower."""
    from clscatter.errors import ClscatterError
    from clscatter.pipeline import budget
    from clscatter.pipeline.check import check
    from clscatter.pipeline.render import render
    from clscatter.scene import load_scene

    sets = ["camera.resolution=[24,18]", "camera.spp=1", "render.lsg.light_rays=60000",
            "render.lsg.radius=0.01"]
    scene = load_scene("builtin:caustic_sphere", sets)
    req = check(scene, "lsg")
    kept = sum(e.bytes for e in req.estimates[:2])
    whole = budget.peak_bytes(req.estimates)            # one chunk: 60k rays x 3 x 560 bytes
    views = req.estimates[2].bytes - 60000 * 3 * 560
    limit = kept + views + 12e6                         # leaves 12 MB for a chunk
    assert whole > limit
    notes: list[str] = []
    fitted = render(scene, "lsg", engine=engine, show_progress=False, max_memory=limit,
                    on_note=notes.append)
    free = render(scene, "lsg", engine=engine, show_progress=False)
    assert any("render.lsg.max_bytes" in n and "to fit" in n for n in notes), notes
    assert fitted.stats["estimated_peak_bytes"] <= limit < free.stats["estimated_peak_bytes"]
    assert free.stats["chunks"] == 1 and fitted.stats["chunks"] > 1
    np.testing.assert_allclose(fitted.image, free.image, rtol=1e-4, atol=1e-6 * free.image.max())
    with pytest.raises(ClscatterError, match="render.lsg.light_rays"):
        render(scene, "lsg", engine=engine, show_progress=False,
               max_memory=kept + views + 2e6)               # under the least chunk, 4 MiB


@pytest.mark.parametrize("view_bytes, key", [(150e6, "camera.resolution"),
                                             (50e6, "render.lsg.light_rays")])
def test_a_refusal_names_the_key_that_would_help(view_bytes, key):
    """Over budget, the refusal names the largest estimate's key, except where the view
    paths and the scene alone exceed the budget: then no pass setting would help, and it
    names theirs."""
    from clscatter.errors import ClscatterError
    from clscatter.methods.base import Estimate
    from clscatter.pipeline import budget

    est = [Estimate("view_paths", "camera.resolution", view_bytes),
           Estimate("scene", "objects", 1e6), Estimate("lsg", "render.lsg.light_rays", 500e6)]
    with pytest.raises(ClscatterError, match=rf"^{key}: .*lower {key}$"):
        budget.check_budget(est, 100e6, "--max-memory")


def test_lsg_refused_for_its_view_segments_names_the_resolution():
    """Where even LSG's least chunk does not fit beside its view segments, its estimate is
    of that least chunk and the refusal names ``camera.resolution``: fewer lighting rays
    would not help."""
    from clscatter.errors import ClscatterError
    from clscatter.methods.lsg import MIN_CHUNK_BYTES
    from clscatter.pipeline import budget
    from clscatter.pipeline.check import check
    from clscatter.scene import load_scene

    scene = load_scene("builtin:caustic_sphere", [])
    req = check(scene, "lsg")
    kept = sum(e.bytes for e in req.estimates[:2])
    rays = scene.render.params.get("lsg", {}).get("light_rays", 200_000)
    chunk = min(2.0 ** 30, rays * 3 * 560)
    views = req.estimates[2].bytes - chunk
    assert views > 10 * MIN_CHUNK_BYTES and req.estimates[2].key == "render.lsg.light_rays"
    limit = kept + 0.5 * views
    assert budget.fit_memory(scene, req, limit, "--max-memory") == []
    assert req.estimates[2].bytes == pytest.approx(views + MIN_CHUNK_BYTES)
    with pytest.raises(ClscatterError, match=r"^camera.resolution: .*lower camera.resolution$"):
        budget.check_budget(req.estimates, limit, "--max-memory")
