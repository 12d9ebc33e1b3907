"""Ray marching of view segments: the brute-force estimator of single scattering of
direct light, shared by the ``raymarch`` method and by every method that marches part of
its segments (epipolar's epipole ring and fallbacks)."""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..device.launch import timed_launches
from ..io.stats import Stats, progress
from ..transport.prepared import PreparedScene
from ..transport.view_paths import DeviceSegments


def march_segments(ps: PreparedScene, segs: DeviceSegments, steps: int, stats: Stats,
                   show_progress: bool = True, per_launch: int = 65536,
                   scale=None, program: str = "raymarch") -> np.ndarray:
    """``raymarch.cl`` over device segments, accumulated into an (H, W, 3) image on the
    device. ``scale``: a device buffer of one float per segment multiplying its result
    (0 skips it): how another method ray-marches part of the segments (epipolar's ring
    and fallbacks) without compacting them. ``program``: a build of ``raymarch.cl`` with
    the same kernel (``density_march``: density grids, :mod:`.density_march`)."""
    eng = ps.engine
    n = segs.count
    out_buf = eng.empty(16 * max(n, 1))
    seed = np.uint32((ps.scene.render.seed * 7919 + 17) & 0xFFFFFFFF)
    try:
        with stats.stage("raymarch"), progress(n, "raymarch", show_progress) as bar:
            for start, m in timed_launches(n, per_launch):
                ps.call(program, "raymarch", m, segs=segs.buf, seg_offset=start, num_segs=m,
                        scale=scale if scale is not None else out_buf,
                        use_scale=int(scale is not None), steps=steps, seed=seed, out=out_buf)
                eng.finish()                # progress that means something
                bar.update(m)
            return segs.accumulate(out_buf)
    finally:
        eng.free(out_buf)


def march_lights(ps: PreparedScene, segs: DeviceSegments, steps: int, stats: Stats,
                 show_progress: bool, scale, lights: Sequence[int]) -> np.ndarray:
    """:func:`march_segments` with the lights ``lights`` (indices) only: the prepared
    scene's light buffer is replaced by theirs for the launches."""
    lights = np.asarray(list(lights), np.int64)
    if len(lights) == ps.num_lights:
        return march_segments(ps, segs, steps, stats, show_progress, scale=scale)
    buf = ps.engine.to_device(ps.lights[lights])
    sub = dataclasses.replace(ps, lights=ps.lights[lights],
                              dev=dataclasses.replace(ps.dev, lights=buf))
    try:
        return march_segments(sub, segs, steps, stats, show_progress, scale=scale)
    finally:
        ps.engine.free(buf)
