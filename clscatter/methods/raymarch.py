"""Brute-force single scattering of direct light: the reference for volumetric shadows."""
from __future__ import annotations

import numpy as np

from ..prepared import PreparedScene
from ..view_paths import ViewPaths, accumulate_segments
from ..stats import Stats, progress
from . import check, register, settings


@register
class RayMarch:
    """``raymarch``: march every view segment, shadow-test every step.

    For each view segment in the medium (from the view-path tracer, so segments seen
    through mirrors and glass are included) and each light, ``steps`` stratified,
    jittered samples; each sample casts a shadow ray to the light through the BVH and
    adds ``sigma_s * phase * E * T_light * T_view * dt``. Point and spot lights place
    their samples equiangularly (uniform in the angle subtended at the light), which
    integrates the 1/d^2 peak near the light without noise; directional lights step
    uniformly. Only direct light is marched (no caustics): light bounced by mirrors or
    bent by glass is the caustic methods' job.

    ==============  =====  =======  ============================================
    parameter       type   default  meaning
    ==============  =====  =======  ============================================
    steps           int    32       samples per segment and light
    segments_per_launch int 65536  segments per kernel launch (progress/memory)
    ==============  =====  =======  ============================================

    Usage: ``clscatter render scene.toml --method raymarch --set render.raymarch.steps=128``
    """

    NAME = "raymarch"
    PARAMS = {"steps": 32, "segments_per_launch": 65536}

    def __init__(self, params: dict | None = None):
        p = settings(type(self), params)
        self.steps = int(p["steps"])
        self.per_launch = int(p["segments_per_launch"])
        check(type(self), p, (("steps", self.steps >= 1, "must be >= 1"),
                              ("segments_per_launch", self.per_launch >= 1, "must be >= 1")))

    def render_medium(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
                      show_progress: bool = True) -> np.ndarray:
        """Single-scattered radiance (H, W, 3) for all view segments of ``paths``."""
        cam = ps.scene.camera
        segs = paths.segments
        n = len(segs)
        if n == 0 or ps.num_lights == 0:
            return np.zeros((cam.height, cam.width, 3), np.float32)
        eng = ps.engine
        kern = eng.kernel("raymarch", "raymarch")
        seg_buf = eng.to_device(segs)
        chunk = min(self.per_launch, n)
        out_buf = eng.empty(chunk * 16)
        values = np.zeros((n, 4), np.float32)
        seed = np.uint32((ps.scene.render.seed * 7919 + 17) & 0xFFFFFFFF)
        with stats.stage("raymarch"), progress(n, "raymarch", show_progress) as bar:
            for start in range(0, n, chunk):
                m = min(chunk, n - start)
                eng.launch(kern, m, ps.buf["nodes"], ps.buf["tris"], ps.buf["lights"],
                           np.int32(ps.num_lights), ps.buf["medium"], seg_buf, np.int32(start),
                           np.int32(m), np.int32(self.steps), seed, out_buf)
                values[start:start + m] = eng.read(out_buf, (chunk, 4), np.float32)[:m]
                bar.update(m)
        eng.free(seg_buf, out_buf)
        stats.set(raymarch_steps=self.steps,
                  shadow_rays=int(n) * self.steps * int(ps.num_lights))
        return accumulate_segments(values, segs["pixel"], cam.width, cam.height)
