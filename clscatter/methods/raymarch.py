"""Brute-force single scattering of direct light: the reference for volumetric shadows."""
from __future__ import annotations

from ..estimators.density_march import has_density, march_density, upload
from ..estimators.segment_march import march_segments
from ..transport.context import PassContext
from . import register
from .base import AutoRole, Estimate, Method, Param, PassResult, camera_samples


@register
class RayMarch(Method):
    """``raymarch``: march every view segment, shadow-test every step.

    For each view segment in the medium (from the view-path tracer, so segments seen
    through mirrors and glass are included) and each light, ``steps`` stratified,
    jittered samples; each sample casts a shadow ray to the light through the BVH and
    adds ``sigma_s * phase * E * T_light * T_view * dt``. Point and spot lights place
    their samples equiangularly (uniform in the angle subtended at the light), which
    integrates the 1/d^2 peak near the light without noise; directional lights step
    uniformly. Where the transmittance along a segment (the view's and the light path's,
    fitted as exp(-r t)) spans more than three optical depths over the segment, or over
    the light's distance, half the steps sample exp(-r t) and every sample is weighted by
    the balance heuristic of the two strategies (multiple importance sampling): thick
    fog's light comes from the first optical depths of a segment. Only direct light is
    marched (no caustics):
    light bounced by mirrors or bent by glass is the caustic methods' job.

    Inside glass (a dielectric's ``interior_sigma_s``): not rendered, and the plan says so
    in one note. A shadow ray reaches a light only in a straight line, and every straight
    line from a point inside a closed glass object to a light meets its surface, where the
    light would have been refracted: the direct light raymarch computes is none there (it
    would be exact only for glass of index 1, which bends nothing). The view segments
    inside glass are not among those it marches; ``lsg`` gathers the refracted light
    inside.

    Heterogeneous media (``[[volumes]]`` with a ``density`` grid and no index grid): the
    pass traces its own view paths (``density_view.cl``: segments across the grid boxes,
    view rays and every shadow ray, the surfaces' included, attenuated through the grids)
    and marches them with ``density_march.cl``: sigma_s(x) = density(x) sigma_s at every
    sample, and the view's and light's transmittance as exact optical depths (the
    trilinear density is integrated piece by piece between voxel-centre planes, Simpson's
    rule on each piece, exact for its cubic). Samples sit at the middle of their
    strata, no jitter, so the image is free of noise (the glow of a point light too); the
    error left is the quadrature's, which ``steps`` lowers. Its surface term, smoke's
    shadows included, replaces the session's.

    Usage: ``clscatter render scene.toml --method raymarch --set render.raymarch.steps=128``
    """

    NAME = "raymarch"
    PARAMS = (
        Param("steps", 32, "samples per segment and light", lo=1),
        Param("segments_per_launch", 65536, "most segments per kernel launch; launches are "
              "timed to about 0.25 s", lo=1),
    )
    TERMS = frozenset({"direct"})
    AUTO = {"direct": AutoRole(priority=10)}
    DENSITY = True

    @classmethod
    def estimate(cls, scene, params):
        segs = 2.0 * camera_samples(scene)          # primary segments plus specular branches
        grids = sum(4.0 * v.density.size for v in scene.density_volumes())
        return [Estimate("raymarch", "render.raymarch.steps", segs * (64 + 16 + 16) + grids,
                         segs * params["steps"] * max(1, len(scene.lights)), "shadow-ray steps")]

    @property
    def steps(self) -> int:
        return self.params["steps"]

    @classmethod
    def programs(cls, scene, params: dict) -> list[tuple[str, dict | None]]:
        if has_density(scene):
            return [("density_view", None), ("density_march", None)]
        return [("raymarch", None)]

    def render(self, ctx: PassContext) -> PassResult:
        """Single-scattered radiance of every view segment, in the medium term."""
        ps = ctx.ps
        if has_density(ps.scene):
            return self._render_density(ctx)
        if len(ctx.paths) == 0 or ps.num_lights == 0:
            return PassResult(medium=ctx.zeros())
        img = march_segments(ps, ctx.segments(), self.steps, ctx.stats, ctx.show_progress,
                             self.params["segments_per_launch"])
        ctx.stats.set(raymarch_steps=self.steps,
                      shadow_rays=int(len(ctx.paths)) * self.steps * int(ps.num_lights))
        return PassResult(medium=img)

    def _render_density(self, ctx: PassContext) -> PassResult:
        """The medium and surface terms of a scene with density grids (see the class
        docstring); the grids stay on the device between renders while they are unchanged."""
        dens = upload(ctx.ps, ctx.cache.get("density"))
        ctx.cache["density"] = dens
        medium, surface = march_density(ctx.ps, dens, self.steps, ctx.stats, ctx.show_progress,
                                        self.params["segments_per_launch"],
                                        ctx.paths.sample_range)
        ctx.stats.set(raymarch_steps=self.steps)
        return PassResult(medium=medium, view_surface=surface)
