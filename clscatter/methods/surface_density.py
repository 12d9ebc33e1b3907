"""What the surface density estimators (``raymap``, ``photonmap``) share as methods: their
common parameters, the surface-caustic pass, and the medium method the planner runs
beside them when one is chosen explicitly. Not a method itself (nothing registers here)."""
from __future__ import annotations

import numpy as np

from ..io.stats import Stats
from ..transport.context import PassContext
from ..transport.prepared import PreparedScene
from . import check_method_param
from .base import Method, Param, PassResult, camera_samples, costs

#: bytes one lighting ray costs the estimators: its traced pieces (about two of 80 bytes),
#: their references in the tree and the device copies
BYTES_PER_RAY = 512
from ..estimators.ray_density import DensitySettings, surface_caustics

#: the parameters every surface density estimator declares
DENSITY_PARAMS = (
    Param("photons", 50_000, "lighting rays aimed at mirrors and glass, shared among lights by "
          "the power they send there", lo=1),
    Param("k", 64, "nearest rays (photons) per estimate", lo=2, hi=1024),
    Param("kernel", "epanechnikov", "density estimation kernel", choices=("epanechnikov", "box")),
    Param("max_radius", 0.05, "largest estimation radius, relative to the scene extent", lo=0,
          lo_open=True),
    Param("batch", 32768, "queries per kernel launch (and per lazy refinement step)", lo=1),
    Param("medium", "lsg", "when chosen explicitly: the method the planner runs beside it for "
          "the medium (any method that computes direct light; 'none': surfaces only)"),
)


def scene_relative(ps: PreparedScene) -> float:
    """Normalised length of one scene extent (radii are given relative to it)."""
    return ps.scene.scene_extent() / ps.frame.scale


class SurfaceDensityMethod(Method):
    """Surface caustics by density estimation over lighting rays that reached diffuse
    surfaces after at least one specular bounce. A subclass gives ``NAME`` (also the
    estimator's name) and :meth:`settings`."""

    TERMS = frozenset({"surface_caustics"})
    PREVIEW_SCALE = {"photons": 0.125}

    @classmethod
    def check_params(cls, params: dict) -> None:
        check_method_param(cls.NAME, "medium", params["medium"], "direct")

    @classmethod
    def estimate(cls, scene, params):
        """Working set: the lighting rays' pieces and tree (:data:`BYTES_PER_RAY` each) and
        one query per camera sample; work: tree building over the rays and the k-nearest
        queries."""
        rays = float(params["photons"])
        queries = float(camera_samples(scene))
        key = f"render.{cls.NAME}.photons"
        return costs(cls.NAME, {key: rays * BYTES_PER_RAY, "camera.resolution": queries * 96},
                     {key: rays * 40, "camera.resolution": queries * params["k"] * 40},
                     "tree and query steps (order of magnitude)")

    @classmethod
    def companions(cls, params: dict) -> list[str]:
        return [] if params["medium"] == "none" else [params["medium"]]

    def settings(self) -> DensitySettings:
        """The estimator's settings from the checked parameters."""
        raise NotImplementedError

    def render(self, ctx: PassContext) -> PassResult:
        """Surface caustics, in the surface term."""
        return PassResult(surface=self.surface_caustics(ctx.ps, ctx.stats, ctx.show_progress,
                                                        ctx.paths.sample_range))

    def surface_caustics(self, ps: PreparedScene, stats: Stats, show_progress: bool = True,
                         sample_range: tuple[int, int] | None = None) -> np.ndarray:
        """The surface-caustic image alone (H, W, 3)."""
        s = self.settings()
        s.max_radius = self.params["max_radius"] * scene_relative(ps)
        return surface_caustics(ps, self.NAME, self.params["photons"], s, stats, show_progress,
                                sample_range=sample_range)
