"""Hierarchical volumetric shadows: epipolar rectification with Fenwick-tree integration."""
from __future__ import annotations

import numpy as np

from ...device import structs
from ...errors import SceneError
from ...estimators.segment_march import march_lights
from ...transport.context import PassContext
from .. import register
from ..base import AutoRole, Fallback, Method, PassResult, camera_samples, costs
from .pipeline import render_light, split_segments, start_defines
from .settings import MIN_LIGHT_RAYS, PARAMS, Settings

# Where auto passes epipolar over (Epipolar.unreliable): its estimate exceeded the
# tolerance there, or came near it, in the regime sweep (tools/bench_epipolar_regimes.py
# at 160 x 120 and 640 x 480, docs/bench/epipolar_regimes*.json;
# tests/test_epipolar_regimes.py at 32 x 24). Optical depth across the medium
# (Scene.optical_depth_across) from which auto passes it over, (any light, a light
# travelling along the view), with the camera outside the medium and inside it:
THICK = {False: (8.0, 4.0), True: (24.0, 12.0)}
ALONG_COS = 0.5      # "along the view": cosine of the light's travel and the camera's forward
# Spot lights wider than this (half-angle, degrees) are left to ray marching by auto: from
# 60 degrees on, epipolar's error at equal samples was 2.6-6.9x ray marching's
# (tools/bench_epipolar_wide_spot.py, docs/bench/epipolar_wide_spot.json)
WIDE_SPOT = 55.0


def _travel(light, scene) -> np.ndarray:
    """Unit direction light travels in towards the medium: a directional light's own, a
    spot's from its position to the medium box's centre (its axis, unbounded)."""
    if light.type == "directional":
        d = np.asarray(light.direction, np.float64)
    elif scene.medium is not None and scene.medium.bounds is not None:
        lo, hi = scene.medium.bounds
        d = 0.5 * (np.asarray(lo) + np.asarray(hi)) - np.asarray(light.position, np.float64)
    else:
        d = np.asarray(light.direction, np.float64)
    n = float(np.linalg.norm(d))
    return d / n if n > 0 else d


@register
class Epipolar(Method):
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
    directions), the epipole ring (2 degrees around the epipole or anti-epipole, blended
    with the sweep over 2 .. 4 degrees), and any light whose estimated error stays above
    the tolerance (below; ray marched with ``raymarch_steps``). Mirrors and glass are
    opaque occluders in the shadow map (direct light only; caustics are not this
    method's job).

    Accuracy control (pipeline.py, svd.py): per light and frame the error is
    estimated on held-out camera samples (the truncated SVD and the tree's float32 sums,
    the sum over light rays, reading a sample in its neighbouring slices) and the
    cheapest setting within the tolerance (1 %, RMS relative) is used: more SVD terms
    (4, 8, 16), a referenced formulation of the visibility-free term (transmittances
    relative to envelopes of the view and light entries, per group of slices), 2 or 4 x
    the light rays, half or a quarter of the slice spacing; else ``raymarch``. Spot
    cones up to 90 degrees: five cube-face shadow maps beyond 60 degrees.

    The default ``segment`` lookup is this implementation's choice over the paper's
    ``grid``: with many depth edges the grid's bilinear unrectification blends samples
    across them; prefiltering helps thin occluders most.

    Limits (tests/test_epipolar*.py hold the measured bounds; docs/benchmarks.md the
    numbers): the shadow map's resolution (nearest texel); one slice's light used for a
    sample up to half a pixel away (visible with wide spot cones, whose shafts cross the
    epipolar lines); the error estimate's host time. ``auto`` passes the method over where
    its estimate is expected to fail (:meth:`unreliable`: thick media, lights along the
    view seen from outside).

    Statistics: ``slices``, ``light_rays_per_slice``, ``rays_per_slice``,
    ``tree_updates``, ``tree_queries``, ``svd_singular_values``, ``svd_terms``,
    ``svd_error`` (the largest estimate of a swept light), per-light details in
    ``epipolar_lights`` (among them ``shadow_map_caster``: ``grid``, with the tile grid's
    list lengths, or ``bvh``; ``ring_in_view``: whether a camera ray comes within the
    ring's outer edge, else its weights are 0 and it costs nothing), the fallbacks in
    ``epipolar_fallback``, and the stages ``epipolar_maps``, ``epipolar_rectify``,
    ``epipolar_svd``, ``epipolar_integrate``, ``epipolar_unrectify``, ``epipolar_ring``
    (seconds).

    Usage: ``clscatter render scene.toml --method epipolar --set render.epipolar.light_rays=4096``
    """

    NAME = "epipolar"
    PARAMS = PARAMS
    TERMS = frozenset({"direct"})
    LIGHTS = frozenset({"spot", "directional"})
    AUTO = {"direct": AutoRole(priority=20)}

    @classmethod
    def check_params(cls, p: dict) -> None:
        if p["svd_samples"] < p["svd_terms"]:
            raise SceneError("render.epipolar.svd_samples",
                             f"must be at least svd_terms ({p['svd_terms']}) (got {p['svd_samples']})")
        if p["svd_max_terms"] < p["svd_terms"]:
            raise SceneError("render.epipolar.svd_max_terms",
                             f"must be at least svd_terms ({p['svd_terms']}) (got {p['svd_max_terms']})")
        if p["light_rays"] == 1:
            raise SceneError("render.epipolar.light_rays", "must be 0 (automatic) or >= 2 (got 1)")

    @classmethod
    def unreliable(cls, scene) -> str:
        """Why ``auto`` should not pick epipolar for ``scene`` ('' when it may): a spot light
        wider than ``WIDE_SPOT``, a medium thicker than ``THICK`` allows across (optical depth 8 seen from outside, 24 from
        inside), or a directional or spot light travelling along the view (cosine with
        the camera's forward above ``ALONG_COS``) through more than 4 from outside or 12
        from inside, or, with the camera outside, a spot light behind the camera shining
        along the view (the anti-epipole at the image's centre, beta + gamma -> pi: its
        estimate fails even in thin media). Measured where the estimate exceeds the
        tolerance or comes near it; conservative (some of these scenes would be swept)."""
        for i, light in enumerate(scene.lights):
            if light.type == "spot" and light.cutoff_angle > WIDE_SPOT:
                return (f"light {i}: a spot light of half-angle {light.cutoff_angle:g} degrees "
                        f"(> {WIDE_SPOT:g}): its shafts cross the epipolar lines, and ray "
                        "marching is more accurate at the same samples")
        tau = scene.optical_depth_across()
        if tau == 0.0:
            return ""
        inside = scene.camera_in_medium()
        where = "inside" if inside else "outside"
        thick, thick_along = THICK[inside]
        if tau >= thick:
            return (f"optical depth {tau:.3g} across the medium >= {thick:g}, camera {where} "
                    "it: the SVD of its transmittance is expected to exceed the tolerance")
        eye = np.asarray(scene.camera.origin, np.float64)
        fwd = np.asarray(scene.camera.target, np.float64) - eye
        fwd /= max(float(np.linalg.norm(fwd)), 1e-300)
        for i, light in enumerate(scene.lights):
            if light.type not in cls.LIGHTS or float(_travel(light, scene) @ fwd) <= ALONG_COS:
                continue
            if (not inside and light.type == "spot"
                    and float((eye - light.position) @ fwd) > 0.0):
                return (f"light {i}: a spot light behind the camera shining along the view, "
                        "camera outside the medium")
            if tau >= thick_along:
                return (f"light {i} travels along the view through optical depth {tau:.3g} "
                        f"(>= {thick_along:g}), camera {where} the medium")
        return ""

    @classmethod
    def estimate(cls, scene, params):
        w, h = scene.camera.width, scene.camera.height
        smap = params["shadow_map"] or min(max(2 * max(w, h), 1024), 4096)
        d = params["light_rays"] or max(w, h, MIN_LIGHT_RAYS)
        slices = params["slices"] or 4 * (w + h)
        n = camera_samples(scene)
        image = "camera.spp" if scene.camera.spp > 64 else "camera.resolution"
        k_map = "render.epipolar.shadow_map" if params["shadow_map"] else image
        k_sweep = ("render.epipolar.light_rays" if params["light_rays"] >= params["slices"] else
                   "render.epipolar.slices") if params["light_rays"] or params["slices"] else image
        # per camera sample: ~64 bytes of per-light tables, 24 kept with the view segments
        # (their directions and the primary list, pipeline.view_dirs/_primary_samples)
        memory: dict[str, float] = {}
        for key, b in ((k_map, 4.0 * smap * smap * 2), (k_sweep, slices * d * 64.0),
                       (image, n * 88.0)):
            memory[key] = memory.get(key, 0.0) + b
        work: dict[str, float] = {}
        for key, w_ in ((k_sweep, slices * d * 20.0), (image, n * 40.0)):
            work[key] = work.get(key, 0.0) + w_
        return costs("epipolar", memory, work, "tree operations")

    def __init__(self, params: dict | None = None):
        super().__init__(params)
        self.settings = Settings.from_params(self.params)

    @classmethod
    def programs(cls, scene, params: dict) -> list[tuple[str, dict | None]]:
        """The epipolar program with the defines a render starts with (start_defines; the
        scene's coefficients are grey exactly when the normalised ones are)."""
        m = scene.medium
        kappa = np.asarray(m.sigma_s, np.float64) + np.asarray(m.sigma_a, np.float64) \
            if m is not None else np.zeros(3)
        return [("epipolar", start_defines(params["svd_terms"], kappa))]

    def render(self, ctx: PassContext) -> PassResult:
        """Single-scattered radiance of every view segment, in the medium term.

        Everything per segment stays on the device (:func:`pipeline.render_light`); the
        ray-marched parts (segments behind mirrors and glass, point lights, the epipole
        ring, lights that fall back) run ``raymarch`` over the same device segments with a
        per-segment scale, and each part is summed into pixels there."""
        ps, stats, show_progress = ctx.ps, ctx.stats, ctx.show_progress
        img = ctx.zeros()
        if len(ctx.paths) == 0 or ps.num_lights == 0 or not ps.has_medium:
            return PassResult(medium=img)
        eng = ps.engine
        steps = self.settings.raymarch_steps
        segs = ctx.segments()
        n = segs.count
        fallback: list[str] = []
        types = ps.lights["type"]
        handled = [i for i in range(ps.num_lights)
                   if types[i] in (structs.LIGHT_DIRECTIONAL, structs.LIGHT_SPOT)]
        others = [i for i in range(ps.num_lights) if i not in handled]
        weighted = ctx.scratch(16 * n)
        defines = start_defines(self.settings.svd_terms, ps.medium["kappa"][:3])
        with stats.stage("epipolar_rectify"):
            primary, deeper, n_deep = split_segments(eng, segs, defines)
        with stats.stage("epipolar_fallback"):
            if n_deep:
                img += march_lights(ps, segs, steps, stats, show_progress, deeper,
                                    range(ps.num_lights))
                fallback.append(f"raymarch: {n_deep} view segments behind "
                                "mirrors/glass (depth > 0)")
            if others:
                img += march_lights(ps, segs, steps, stats, show_progress, primary, others)
                fallback.append(f"raymarch: point lights {others} (no epipolar slices "
                                "for a point light's full sphere)")
        per_light = []
        for li in handled:
            try:
                out = render_light(ps, li, segs, self.settings, stats, show_progress)
            except Fallback as e:          # degenerate axis, or the SVD's error too large
                with stats.stage("epipolar_fallback"):
                    # a thick medium is what sends lights here: the ray marcher's
                    # transmittance strategy keeps its steps enough there
                    img += march_lights(ps, segs, steps, stats, show_progress, primary, [li])
                fallback.append(f"raymarch: light {li}: {e}")
                per_light.append({"light": li, "fallback": "raymarch", "reason": str(e),
                                  **e.info})
                continue
            try:
                with stats.stage("epipolar_unrectify"):
                    ctx.call("epipolar", "epi_weighted", n, defines, values=out.values_buf,
                             segs=segs.buf, n=n, weighted=weighted)
                    img += segs.accumulate(weighted)
                if out.ring_samples:
                    # the ring and its blended band: ray marched with weight ring_weight
                    with stats.stage("epipolar_ring"):
                        img += march_lights(ps, segs, steps, stats, show_progress,
                                            out.ring_buf, [li])
                    fallback.append(
                        f"raymarch: light {li}: {out.ring_samples} samples in the "
                        f"epipole ring ({out.info['ring_degrees']:.3g} degrees, "
                        f"{out.info['ring_band_samples']} of them in its blended band)")
            finally:
                out.release()
            per_light.append({"light": li, **out.info})
        stats.set(epipolar_fallback=fallback, epipolar_lights=per_light,
                  epipolar_ring_steps=steps)
        # lights swept over at least one sample (not every medium segment behind glass)
        swept = [x for x in per_light if "fallback" not in x and "slices" in x]
        if swept:
            first = swept[0]
            stats.set(slices=first["slices"], light_rays_per_slice=first["light_rays"],
                      rays_per_slice=first["rays_per_slice"],
                      tree_updates=int(sum(x["tree_updates"] for x in swept)),
                      tree_queries=int(sum(x["tree_queries"] for x in swept)),
                      svd_singular_values=first["svd_singular_values"],
                      svd_terms=max(x["svd_terms"] for x in swept),
                      svd_error=max(x["svd_error"]["rms"] for x in swept))
        return PassResult(medium=img)
