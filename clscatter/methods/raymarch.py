"""Brute-force single scattering of direct light: the reference for volumetric shadows."""
from __future__ import annotations

import numpy as np

from ..prepared import PreparedScene
from ..view_paths import ViewPaths, accumulate_segments
from ..stats import Stats, progress
from .base import AutoRole, Method, Param
from . import register


@register
class RayMarch(Method):
    """``raymarch``: march every view segment, shadow-test every step.

    For each view segment in the medium (from the view-path tracer, so segments seen
    through mirrors and glass are included) and each light, ``steps`` stratified,
    jittered samples; each sample casts a shadow ray to the light through the BVH and
    adds ``sigma_s * phase * E * T_light * T_view * dt``. Point and spot lights place
    their samples equiangularly (uniform in the angle subtended at the light), which
    integrates the 1/d^2 peak near the light without noise; directional lights step
    uniformly. Only direct light is marched (no caustics): light bounced by mirrors or
    bent by glass is the caustic methods' job.

    Usage: ``clscatter render scene.toml --method raymarch --set render.raymarch.steps=128``
    """

    NAME = "raymarch"
    PARAMS = (
        Param("steps", 32, "samples per segment and light", lo=1),
        Param("segments_per_launch", 65536, "segments per kernel launch (progress, memory)", lo=1),
    )
    TERMS = frozenset({"direct"})
    AUTO = {"direct": AutoRole(priority=10)}

    @classmethod
    def estimate(cls, scene, params):
        from ..budget import Estimate, camera_samples
        segs = 2.0 * camera_samples(scene)          # primary segments plus specular branches
        return [Estimate("raymarch", "render.raymarch.steps", segs * (64 + 16 + 16),
                         segs * params["steps"] * max(1, len(scene.lights)), "shadow-ray steps")]

    @property
    def steps(self) -> int:
        return self.params["steps"]

    def render(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
                      show_progress: bool = True) -> np.ndarray:
        """Single-scattered radiance (H, W, 3) for all view segments of ``paths``."""
        cam = ps.scene.camera
        segs = paths.segments
        n = len(segs)
        if n == 0 or ps.num_lights == 0:
            return np.zeros((cam.height, cam.width, 3), np.float32)
        eng = ps.engine
        seg_buf = eng.to_device(segs)
        chunk = min(self.params["segments_per_launch"], n)
        out_buf = eng.empty(chunk * 16)
        values = np.zeros((n, 4), np.float32)
        seed = np.uint32((ps.scene.render.seed * 7919 + 17) & 0xFFFFFFFF)
        with stats.stage("raymarch"), progress(n, "raymarch", show_progress) as bar:
            for start in range(0, n, chunk):
                m = min(chunk, n - start)
                ps.call("raymarch", "raymarch", m, segs=seg_buf, seg_offset=start, num_segs=m,
                        steps=self.steps, seed=seed, out=out_buf)
                values[start:start + m] = eng.read(out_buf, (chunk, 4), np.float32)[:m]
                bar.update(m)
        eng.free(seg_buf, out_buf)
        stats.set(raymarch_steps=self.steps,
                  shadow_rays=int(n) * self.steps * int(ps.num_lights))
        return accumulate_segments(values, segs["pixel"], cam.width, cam.height)
