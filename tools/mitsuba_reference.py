#!/usr/bin/env python3
"""Outside reference images: render a clscatter scene with Mitsuba 3.

Converts a clscatter :class:`~clscatter.scene.model.Scene` (loaded from a TOML file with
``load_scene``) into a Mitsuba 3 scene dict and renders it with ``volpath`` and
``max_depth = 2``: camera vertex, one scattering event (in the medium or on a diffuse
surface), light. That is exactly clscatter's image for scenes without delta-light
caustics (only diffuse and black materials): direct surface light through the medium
plus single scattering. The image (float32 H x W x 3, linear radiance) is written as
``<scene>.npy`` next to the TOML file; ``references.json`` in the same folder records
the Mitsuba version, spp, seconds and Mitsuba's own noise (relMSE between two renders
with different seeds). Mitsuba is a tool-only dependency (``pip install mitsuba``);
tests read the committed images and never import it.

    python3 tools/mitsuba_reference.py tests/data/mitsuba/*.toml [--spp 65536]
    python3 tools/mitsuba_reference.py --verify      # conversion checks against closed forms

The conversion is clscatter's own (``clscatter.scene.mitsuba_out``, the one ``clscatter
convert`` writes XML with; docs/mitsuba.md): every object as the triangle mesh clscatter
renders, ``near_clip = 1e-4``, a ``box`` pixel filter, spot lights with ``beam_width =
cutoff_angle``, the medium as ``sigma_t``/``albedo``/``scale``. ``--verify`` checks it
against closed forms (camera mapping and fov axis, image orientation, radiant intensity,
irradiance, the HG sign, bounded and unbounded media).

A scene the converter gives a note for is refused: mirrors and glass (with delta lights
their caustics are missing from ``max_depth = 2``, and from clscatter's ``raymarch``),
surfaces across the medium's bounds. Such scenes make no reference.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from clscatter.scene import mitsuba_out  # noqa: E402
from clscatter.scene.loader import load_scene  # noqa: E402
from clscatter.scene.model import Scene  # noqa: E402

VARIANT = "scalar_rgb"
MAX_DEPTH = mitsuba_out.SINGLE_SCATTERING_DEPTH


def _mi():
    import mitsuba as mi
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def to_mitsuba(scene: Scene, folder: Path, spp: int = 1024, seed: int = 0,
               sampler: str = "independent") -> dict:
    """The dict ``mi.load_dict`` takes for ``scene``, its meshes written under ``folder``.
    ValueError for a scene whose conversion has notes: Mitsuba's image would not be
    clscatter's."""
    conversion = mitsuba_out.convert(scene, spp=spp, seed=seed, sampler=sampler)
    if conversion.notes:
        raise ValueError("not a reference: " + "; ".join(conversion.notes))
    _mi()
    return mitsuba_out.mitsuba_dict(conversion, folder)


def render_mitsuba(scene: Scene, spp: int = 1024, seed: int = 0,
                   sampler: str = "independent") -> np.ndarray:
    """Mitsuba's image of ``scene`` (float32 H x W x 3, linear radiance)."""
    mi = _mi()
    with tempfile.TemporaryDirectory() as folder:
        ms = mi.load_dict(to_mitsuba(scene, Path(folder), spp, seed, sampler))
    img = mi.render(ms, spp=int(spp), seed=int(seed))
    return np.array(img, dtype=np.float32).reshape(scene.camera.height, scene.camera.width, 3)


def relmse(a: np.ndarray, b: np.ndarray, eps: float = 1e-2) -> float:
    from clscatter.io.image import relmse as _relmse
    return _relmse(a, b, eps=eps)


# ----------------------------------------------------------------------------- checks


def _camera_dirs(cam, u, v) -> np.ndarray:
    """clscatter's pinhole camera (tests/analytic.py camera_rays), (H, W, 3) unit dirs."""
    fwd = _unit(cam["target"] - cam["origin"])
    right = _unit(np.cross(fwd, cam["up"]))
    tup = np.cross(right, fwd)
    w, h = cam["resolution"]
    half = math.tan(math.radians(cam["fov"]) / 2)
    tan_x, tan_y = (half, half * h / w) if cam.get("fov_axis", "x") == "x" else (half * w / h, half)
    px = np.arange(w)[None, :] + u
    py = np.arange(h)[:, None] + v
    sx = 2 * px / w - 1
    sy = 1 - 2 * py / h
    dirs = fwd + (sx * tan_x)[..., None] * right + (sy * tan_y)[..., None] * tup
    return dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)


def _pixel_average(cam, fn, sub=8) -> np.ndarray:
    acc = 0.0
    for j in range(sub):
        for i in range(sub):
            acc = acc + fn(_camera_dirs(cam, (i + 0.5) / sub, (j + 0.5) / sub))
    return acc / (sub * sub)


def _verify_scene(d: dict) -> Scene:
    import copy

    from clscatter.scene.loader import scene_from_dict
    return scene_from_dict(copy.deepcopy(d), REPO, "<verify>")


def verify(spp: int = 256) -> list[tuple[str, float]]:
    """Conversion checks against closed forms; returns (name, relMSE) pairs.

    1. Diffuse floor quad (albedo rgb) under a point light, no medium, oblique camera
       with fov_axis "y": albedo/pi * I cos / d^2 per pixel (camera mapping, image
       orientation, fov, point intensity, diffuse, box filter).
    2. The same quad seen from below (Mitsuba's diffuse is black from behind; twosided).
    3. A spot light with cutoff 25 deg onto the quad: uniform inside the cone (beam_width).
    4. A directional light onto the quad: albedo/pi * E cos.
    5. Unbounded medium, point light, no geometry, camera in the medium (near_clip,
       sensor medium, sigma_t/albedo/scale, hg phase g = 0.6): 1-D quadrature per ray.
    6. Bounded medium box, directional light, g = -0.3, camera outside (cube + null bsdf,
       interior): closed form per ray.
    7. The quad inside an unbounded medium under a point light: surface attenuation
       exp(-kappa (d_light + d_eye)) plus airlight.
    """
    results = []
    cam = {"origin": np.array([0.3, 2.0, 3.0]), "target": np.array([0.0, 0.0, -0.2]),
           "up": np.array([0.0, 1.0, 0.0]), "fov": 40.0, "fov_axis": "y", "resolution": [40, 30]}
    cam_t = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in cam.items()}
    quad = {"shape": "quad", "origin": [-1.0, 0.0, -1.5], "edge_u": [2.0, 0.0, 0.0],
            "edge_v": [0.0, 0.0, 2.5], "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.2]}}
    albedo = np.array([0.8, 0.5, 0.2])

    def floor_hits(dirs, o):
        t = -o[1] / dirs[..., 1]
        p = o + t[..., None] * dirs
        ok = (t > 0) & (p[..., 0] >= -1) & (p[..., 0] <= 1) & (p[..., 2] >= -1.5) & (p[..., 2] <= 1.0)
        return t, p, ok

    def floor_image(light_fn, o=cam["origin"], kappa=None):
        def fn(dirs):
            t, p, ok = floor_hits(dirs, o)
            e = light_fn(p)                       # (H, W, 3) irradiance on the floor
            val = albedo / np.pi * e
            if kappa is not None:
                val = val * np.exp(-kappa * t[..., None])
            return np.where(ok[..., None], val, 0.0)
        return _pixel_average(cam, fn)

    lp, I = np.array([0.2, 1.5, -0.3]), np.array([6.0, 5.0, 4.0])

    def point_E(p, kappa=None):
        to = lp - p
        d2 = np.sum(to * to, -1)
        e = I * (to[..., 1] / np.sqrt(d2) / d2)[..., None]
        if kappa is not None:
            e = e * np.exp(-kappa * np.sqrt(d2)[..., None])
        return e

    def run(name, scene_d, ref):
        img = render_mitsuba(_verify_scene(scene_d), spp=spp, seed=1)
        err = relmse(img, ref)
        ratio = float(img.sum() / ref.sum()) if ref.sum() > 0 else float("nan")
        results.append((name, err))
        print(f"  {name:38s} relMSE {err:.2e}  sum ratio {ratio:.5f}", flush=True)

    base = {"camera": dict(cam_t, spp=1), "objects": [quad]}
    run("point light on diffuse quad",
        dict(base, lights=[{"type": "point", "position": lp.tolist(), "intensity": I.tolist()}]),
        floor_image(point_E))

    below = dict(cam_t, origin=[0.3, -2.0, 3.0], up=[0.0, 1.0, 0.0], spp=1)
    lp_below = {"type": "point", "position": [0.2, -1.5, -0.3], "intensity": I.tolist()}
    cam_b = dict(cam, origin=np.array([0.3, -2.0, 3.0]))

    def fn_below(dirs):
        o = cam_b["origin"]
        _, p, ok = floor_hits(dirs, o)
        to = np.array([0.2, -1.5, -0.3]) - p
        d2 = np.sum(to * to, -1)
        e = I * (-to[..., 1] / np.sqrt(d2) / d2)[..., None]
        return np.where(ok[..., None], albedo / np.pi * e, 0.0)
    run("point light, quad seen from below",
        {"camera": below, "objects": [quad], "lights": [lp_below]}, _pixel_average(cam_b, fn_below))

    axis = _unit(np.array([0.0, -1.0, -0.3]))
    cut = 25.0

    def spot_E(p):
        to = lp - p
        d = np.linalg.norm(to, axis=-1)
        inside = np.sum(-to / d[..., None] * axis, -1) >= math.cos(math.radians(cut))
        return np.where(inside[..., None], I * (to[..., 1] / d / d ** 2)[..., None], 0.0)
    run("spot light (cutoff 25) on diffuse quad",
        dict(base, lights=[{"type": "spot", "position": lp.tolist(), "target": (lp + axis).tolist(),
                            "intensity": I.tolist(), "cutoff_angle": cut}]),
        floor_image(spot_E))

    ddir = _unit(np.array([0.4, -1.0, 0.3]))
    E = np.array([1.5, 1.0, 0.5])
    run("directional light on diffuse quad",
        dict(base, lights=[{"type": "directional", "direction": ddir.tolist(),
                            "irradiance": E.tolist()}]),
        floor_image(lambda p: np.broadcast_to(E * -ddir[1], p.shape)))

    # -- media: the project's analytic references (tests/analytic.py: airlight by
    #    Gauss-Legendre in the equiangular variable, the box slab in closed form)
    sys.path.insert(0, str(REPO / "tests"))
    import analytic

    sig_s, sig_a, g = np.array([0.3, 0.2, 0.1]), np.array([0.1, 0.05, 0.2]), 0.6
    kappa = sig_s + sig_a

    def rgb_of(fn1):
        def fn(dirs):
            flat = dirs.reshape(-1, 3)
            return np.stack([fn1(flat, c).reshape(dirs.shape[:-1]) for c in range(3)], -1)
        return fn

    def airlight(dirs, o, t_max=np.inf):
        tm = t_max if np.isscalar(t_max) else np.asarray(t_max).reshape(-1)
        return rgb_of(lambda flat, c: analytic.airlight_point(
            o, flat, lp, I[c], sig_s[c], kappa[c], g, t_max=tm, method="gauss"))(dirs)

    med_d = {"sigma_s": sig_s.tolist(), "sigma_a": sig_a.tolist(), "g": g}
    run("unbounded medium, point light, hg 0.6",
        {"camera": dict(cam_t, spp=1), "medium": med_d,
         "lights": [{"type": "point", "position": lp.tolist(), "intensity": I.tolist()}]},
        _pixel_average(cam, lambda dirs: airlight(dirs, cam["origin"])))

    def fn_surface_medium(dirs):
        o = cam["origin"]
        t, p, ok = floor_hits(dirs, o)
        surf = albedo / np.pi * point_E(p, kappa) * np.exp(-kappa * t[..., None])
        return (np.where(ok[..., None], surf, 0.0)
                + airlight(dirs, o, np.where(ok, t, np.inf)))
    run("quad in unbounded medium, point light",
        {"camera": dict(cam_t, spp=1), "medium": med_d, "objects": [quad],
         "lights": [{"type": "point", "position": lp.tolist(), "intensity": I.tolist()}]},
        _pixel_average(cam, fn_surface_medium))

    bmin, bmax = [-1.0, -0.5, -1.0], [1.0, 1.0, 0.8]
    gb = -0.3
    slab = rgb_of(lambda flat, c: analytic.directional_slab(
        cam["origin"], flat, ddir, E[c], sig_s[c], kappa[c], gb, bmin, bmax))
    run("bounded medium box, directional, hg -0.3",
        {"camera": dict(cam_t, spp=1),
         "medium": dict(med_d, g=gb, bounds={"min": bmin, "max": bmax}),
         "lights": [{"type": "directional", "direction": ddir.tolist(), "irradiance": E.tolist()}]},
        _pixel_average(cam, slab))
    return results


# ------------------------------------------------------------------------------ main


def make_reference(toml: Path, spp: int, sampler: str, noise_check: bool = True) -> dict:
    import mitsuba as mi
    scene = load_scene(toml)
    t0 = time.perf_counter()
    img = render_mitsuba(scene, spp=spp, seed=0, sampler=sampler)
    seconds = time.perf_counter() - t0
    out = toml.with_suffix(".npy")
    np.save(out, img.astype(np.float32))
    rec = {"mitsuba_version": mi.__version__, "variant": VARIANT, "integrator": "volpath",
           "max_depth": MAX_DEPTH, "sampler": sampler, "spp": spp, "seed": 0,
           "seconds": round(seconds, 2), "image": out.name, "scene": toml.name,
           "mean": float(img.mean())}
    if noise_check:
        img2 = render_mitsuba(scene, spp=spp, seed=1, sampler=sampler)
        # relMSE between two independent renders = 2x each one's relMSE to the truth
        rec["self_relmse_seed0_vs_seed1"] = relmse(img2, img)
        rec["noise_relmse_estimate"] = rec["self_relmse_seed0_vs_seed1"] / 2
    print(f"{toml.name}: {seconds:.1f} s, mean {img.mean():.5f}"
          + (f", self relMSE {rec['self_relmse_seed0_vs_seed1']:.2e}" if noise_check else ""),
          flush=True)
    return rec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="*", type=Path, help="scene TOML files")
    ap.add_argument("--spp", type=int, default=65536)
    ap.add_argument("--sampler", default="stratified", choices=["independent", "stratified"])
    ap.add_argument("--no-noise-check", action="store_true",
                    help="skip the second render that measures Mitsuba's own noise")
    ap.add_argument("--verify", action="store_true",
                    help="run the conversion checks against closed forms")
    ap.add_argument("--verify-spp", type=int, default=256)
    args = ap.parse_args(argv)
    if args.verify:
        print("conversion checks (Mitsuba vs closed form):")
        verify(args.verify_spp)
    for toml in args.scenes:
        rec = make_reference(toml.resolve(), args.spp, args.sampler, not args.no_noise_check)
        index = toml.resolve().parent / "references.json"
        data = json.loads(index.read_text()) if index.exists() else {}
        data[toml.stem] = rec
        index.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
