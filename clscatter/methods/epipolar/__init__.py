"""Hierarchical volumetric shadows: epipolar rectification with Fenwick-tree integration."""
from __future__ import annotations

import dataclasses

import numpy as np

from ... import structs
from .pipeline import LOOKUPS, Settings, render_light
from ...prepared import PreparedScene
from ...view_paths import ViewPaths, accumulate_segments
from ...stats import Stats
from .. import check, register, settings
from ..raymarch import RayMarch


@register
class Epipolar:
    """``epipolar``: single scattering of directional and spot lights by epipolar sweeps.

    Baran, Chen, Ragan-Kelley, Durand, Lehtinen 2010, "A Hierarchical Volumetric Shadow
    Algorithm for Single Scattering". For each directional or spot light: a shadow map is
    ray traced (orthographic over the medium box, or perspective over the cone); the
    image is cut into epipolar slices (half-planes around the line through the eye and
    the light) placed by the sinh distribution so that every pixel is within half a
    pixel of one; in each slice view rays are indexed by their angle ``beta`` from the
    light and light rays by ``gamma``; the shadow map is rectified into the blocker
    ``beta`` of every light ray (four sub-samples clustered into weighted modes). One
    work-item per slice sweeps the view rays away from the light, removing light rays
    from a Fenwick tree as they are blocked, and integrates every view ray with prefix
    sums in O(log d). The visibility-free part of the integrand is a truncated SVD (of
    a 64 x 64 sampling, once per frame and light); the light's attenuation up to the
    medium and the spot cone enter as per-light-ray initial values. Camera samples in a
    ring around the epipole are ray marched. The result is in the same units as
    ``raymarch`` (radiance per camera sample).

    What it does not do, and hands to ``raymarch`` (listed in ``--stats`` under
    ``epipolar_fallback``): view segments seen through mirrors or glass (depth > 0),
    point lights (the slices of a point light would need the full sphere of
    directions), and the epipole ring. Mirrors and glass are opaque occluders in the
    shadow map (direct light only; caustics are not this method's job).

    ===================  =====  =========  ==============================================
    parameter            type   default    meaning
    ===================  =====  =========  ==============================================
    slices               int    0          0: the sinh distribution at one-pixel spacing
                                           (the half-pixel bound); N: about N slices
    lookup               str    "segment"  "segment": every camera sample is swept at its
                                           own beta and depth in its two neighbouring
                                           slices; "grid": the paper's rectified depth
                                           map and bilinear unrectification
    rays_per_slice       int    0          grid lookup: view rays per slice (0: the
                                           longest slice's length in pixels)
    depth_map            int    0          grid lookup: depth-map width (0: image width)
    light_rays           int    0          light rays per slice, d (0: 2 max(W, H))
    shadow_map           int    0          shadow map resolution (0: 2 max(W, H),
                                           clamped to 1024 .. 4096)
    svd_terms            int    4          SVD terms N
    svd_samples          int    64         the SVD samples an n x n grid
    prefilter            bool   true       four depth sub-samples per light ray,
                                           clustered into weighted modes
    prefilter_tolerance  float  1.0        sub-samples within this many pixel angles of
                                           beta form one mode
    epipole_ring         float  8.0        radius (pixels) around the epipole that is
                                           ray marched (0: none)
    raymarch_steps       int    64         steps of the ray marcher for the ring and the
                                           fallbacks
    batch_slices         int    256        slices per kernel launch (memory/progress)
    ===================  =====  =========  ==============================================

    The default ``segment`` lookup is this implementation's choice over the paper's
    ``grid``: with many depth edges the grid's bilinear unrectification blends samples
    across them (``epi_forest`` at 640 x 480: relMSE 1.9e-3 against 1.1e-5); prefiltering
    cuts the error 3 .. 25 x at 160 light rays (thin occluders gain most).

    Accuracy and limits (tests/test_epipolar*.py). Against raymarch with 256 steps at
    64 x 48 the medium image's relMSE is 6e-5 .. 4e-4 on the built-in shaft scenes; with
    no occluders a sample is within 2.5e-3 (99 %) of the closed form. What remains:
    the shadow map's resolution (nearest texel, as in shadow mapping); one slice's light
    used for a sample up to half a pixel away (visible where the light's attenuation or
    a spot cone's silhouette changes within a pixel, and near the epipole); the SVD,
    whose 4th singular value stays below 1/40 of the first for directional lights and
    for spot lights in front of the camera, but reaches ~0.08 for a spot light behind
    it (``svd_singular_values`` in ``--stats`` shows it; raise ``svd_terms``).

    Statistics: ``slices``, ``light_rays_per_slice``, ``rays_per_slice``,
    ``tree_updates``, ``tree_queries``, ``svd_singular_values``, per-light details in
    ``epipolar_lights``, the fallbacks in ``epipolar_fallback``, and the stages
    ``epipolar_maps``, ``epipolar_rectify``, ``epipolar_svd``, ``epipolar_integrate``,
    ``epipolar_unrectify``, ``epipolar_ring`` (seconds).

    Usage: ``clscatter render scene.toml --method epipolar --set render.epipolar.light_rays=4096``
    """

    NAME = "epipolar"
    PARAMS = {
        "slices": 0,
        "lookup": "segment",
        "rays_per_slice": 0,
        "depth_map": 0,
        "light_rays": 0,
        "shadow_map": 0,
        "svd_terms": 4,
        "svd_samples": 64,
        "prefilter": True,
        "prefilter_tolerance": 1.0,
        "epipole_ring": 8.0,
        "raymarch_steps": 64,
        "batch_slices": 256,
    }

    def __init__(self, params: dict | None = None):
        p = settings(type(self), params)
        check(type(self), p, (
            ("lookup", p["lookup"] in LOOKUPS, f"must be one of {', '.join(LOOKUPS)}"),
            *((name, int(p[name]) >= 0, "must be >= 0 (0: automatic)")
              for name in ("slices", "rays_per_slice", "depth_map", "light_rays", "shadow_map")),
            ("svd_terms", 1 <= int(p["svd_terms"]) <= 16, "must be between 1 and 16"),
            ("svd_samples", int(p["svd_samples"]) >= int(p["svd_terms"]), "must be at least svd_terms"),
            ("light_rays", int(p["light_rays"]) != 1, "must be 0 (automatic) or >= 2"),
            *((name, float(p[name]) >= 0, "must be >= 0")
              for name in ("prefilter_tolerance", "epipole_ring"))))
        self.settings = Settings(
            slices=int(p["slices"]), rays_per_slice=int(p["rays_per_slice"]),
            light_rays=int(p["light_rays"]), shadow_map=int(p["shadow_map"]),
            depth_map=int(p["depth_map"]), svd_terms=int(p["svd_terms"]),
            svd_samples=int(p["svd_samples"]), prefilter=bool(p["prefilter"]),
            prefilter_tolerance=float(p["prefilter_tolerance"]),
            epipole_ring=float(p["epipole_ring"]), lookup=str(p["lookup"]),
            batch_slices=max(1, int(p["batch_slices"])))
        self.raymarch_steps = max(1, int(p["raymarch_steps"]))

    # ---- the fallback: raymarch on some segments with some lights ----
    def _raymarch(self, ps: PreparedScene, paths: ViewPaths, segs: np.ndarray, lights,
                  stats: Stats, show_progress: bool) -> np.ndarray:
        cam = ps.scene.camera
        if len(segs) == 0 or len(lights) == 0:
            return np.zeros((cam.height, cam.width, 3), np.float32)
        sub = ViewPaths(paths.surface, paths.escaped, segs)
        lights = np.asarray(lights, np.int64)
        if len(lights) == ps.num_lights:
            sub_ps = ps
            buf = None
        else:
            buf = ps.engine.to_device(ps.lights[lights])
            sub_ps = dataclasses.replace(ps, lights=ps.lights[lights], buf={**ps.buf, "lights": buf})
        try:
            return RayMarch({"steps": self.raymarch_steps}).render_medium(sub_ps, sub, stats,
                                                                          show_progress)
        finally:
            if buf is not None:
                ps.engine.free(buf)

    def render_medium(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
                      show_progress: bool = True) -> np.ndarray:
        """Single-scattered radiance (H, W, 3) for all view segments of ``paths``."""
        cam = ps.scene.camera
        img = np.zeros((cam.height, cam.width, 3), np.float32)
        segs = paths.segments
        if len(segs) == 0 or ps.num_lights == 0 or not ps.has_medium:
            return img
        fallback: list[str] = []
        primary = segs["depth"] == 0
        types = ps.lights["type"]
        handled = [i for i in range(ps.num_lights)
                   if types[i] in (structs.LIGHT_DIRECTIONAL, structs.LIGHT_SPOT)]
        others = [i for i in range(ps.num_lights) if i not in handled]
        with stats.stage("epipolar_fallback"):
            if (~primary).any():
                img += self._raymarch(ps, paths, segs[~primary], range(ps.num_lights), stats,
                                      show_progress)
                fallback.append(f"raymarch: {int((~primary).sum())} view segments behind "
                                "mirrors/glass (depth > 0)")
            if others:
                img += self._raymarch(ps, paths, segs[primary], others, stats, show_progress)
                fallback.append(f"raymarch: point lights {others} (no epipolar slices for "
                                "a point light's full sphere)")
        prim = segs[primary]
        per_light = []
        for li in handled:
            try:
                out = render_light(ps, li, prim, self.settings, stats, show_progress)
            except ValueError as e:        # degenerate axis (spot light at the eye)
                with stats.stage("epipolar_fallback"):
                    img += self._raymarch(ps, paths, prim, [li], stats, show_progress)
                fallback.append(f"raymarch: light {li}: {e}")
                continue
            w = prim["weight"][:, :3].astype(np.float64)
            img += accumulate_segments(out.values * w, prim["pixel"], cam.width, cam.height)
            if out.ring.any():
                with stats.stage("epipolar_ring"):
                    img += self._raymarch(ps, paths, prim[out.ring], [li], stats, show_progress)
                fallback.append(f"raymarch: light {li}: {int(out.ring.sum())} samples in the "
                                f"epipole ring ({self.settings.epipole_ring:g} px)")
            per_light.append({"light": li, **out.info})
        s = self.settings
        stats.set(epipolar_fallback=fallback, epipolar_lights=per_light,
                  epipolar_ring_steps=self.raymarch_steps)
        if per_light:
            first = per_light[0]
            stats.set(slices=first["slices"], light_rays_per_slice=first["light_rays"],
                      rays_per_slice=first["rays_per_slice"],
                      tree_updates=int(sum(x["tree_updates"] for x in per_light)),
                      tree_queries=int(sum(x["tree_queries"] for x in per_light)),
                      svd_singular_values=first["svd_singular_values"],
                      svd_terms=s.svd_terms)
        return img
