"""What the surface density estimators (``raymap``, ``photonmap``) share as methods: their
common parameters, the surface-caustic pass, and the medium method the planner runs
beside them when one is chosen explicitly. Not a method itself (nothing registers here)."""
from __future__ import annotations

from ..estimators.ray_density import DensitySettings
from ..estimators.surface_passes import SurfacePasses, progressive_surface_caustics
from ..transport.context import PassContext
from ..transport.prepared import PreparedScene
from . import check_method_param
from .base import Method, Param, PassResult, camera_samples, costs

#: bytes one lighting ray costs the estimators: its traced pieces (about two of 80 bytes),
#: their references in the tree and the device copies
BYTES_PER_RAY = 512
#: most passes under an error target (the target or a deadline should end them first)
MAX_PASSES = 1024
#: the learnt cost of a first pass (``<method>_first_pass``), in seconds per lighting ray
#: plus diffuse hit: a guide that errs long (the queries grow more slowly than the hits),
#: so a first pass sized from it fits its share of a deadline
FIRST_PASS_STAGE = "first_pass"

#: the parameters every surface density estimator declares
DENSITY_PARAMS = (
    Param("photons", 50_000, "lighting rays aimed at mirrors and glass, shared among lights by "
          "the power they send there", lo=1),
    Param("k", 64, "nearest rays (photons) per estimate", lo=2, hi=1024),
    Param("kernel", "epanechnikov", "density estimation kernel", choices=("epanechnikov", "box")),
    Param("max_radius", 0.05, "largest estimation radius, relative to the scene extent", lo=0,
          lo_open=True),
    Param("radius", 0.0, "first pass's gather radius relative to the scene extent (k bounds "
          "the rays it gathers); 0: automatic, every hit's k-th nearest distance", lo=0),
    Param("passes", 1, "progressive passes of fresh rays, radii shrinking by ppm_alpha (under "
          "a time budget: fewer if they do not fit; with an error target: more until it is met)",
          lo=1),
    Param("time_budget", 0.0, "seconds for this pass (0: none; render.time_budget also "
          "limits it)", lo=0),
    Param("ppm_alpha", 2.0 / 3.0, "progressive radius reduction r_(i+1)^2 = r_i^2 (i + "
          "ppm_alpha) / (i + 1)", lo=0, hi=1, lo_open=True, hi_open=True),
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
    estimator's name) and :meth:`settings`.

    *Gather radius and progressive passes* (``clscatter.estimators.surface_passes``). With
    ``radius = 0`` (automatic) the first pass's radius at a hit is the distance of its
    ``k``-th nearest ray or photon (at most ``max_radius``), in the normalised frame
    (independent of the scene's scale); ``passes = 1`` is that estimate alone. Pass i > 1
    traces fresh rays and gathers all within ``s_i B(x)``, ``B = max(R_1, pixel footprint
    / 16)``, ``s_(i+1)^2 = s_i^2 (i + ppm_alpha) / (i + 1)`` (progressive photon mapping,
    2-D kernel); the image is the mean of the passes, which converges. Passes stop at
    ``passes``, at the deadline (this pass's share of ``render.time_budget``, or
    ``time_budget``) or at ``render.target_error``; their own images give the render's
    error estimate. Under a deadline the passes' rays are sized to their share of it from
    a session's earlier first pass, or else from this device's learnt cost of a first pass
    (seconds per lighting ray plus diffuse hit, kept across runs); ``<name>_sized_from``
    says which."""

    TERMS = frozenset({"surface_caustics"})
    PREVIEW_SCALE = {"photons": 0.125, "passes": 0.0, "time_budget": 0.0}
    PROGRESSIVE = True

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
        """Surface caustics, in the surface term: the mean of the progressive passes
        (:mod:`clscatter.estimators.surface_passes`), run by ``ctx.progression``."""
        p, ps = self.params, ctx.ps
        planned = int(p["passes"])
        prog = ctx.progression(planned, planned, float(p["time_budget"]))
        if prog.target_error > 0:
            prog.max_passes = MAX_PASSES
        s = self.settings()
        s.max_radius = p["max_radius"] * scene_relative(ps)
        # under a deadline, a session's earlier first pass over as many hits sizes this
        # one's, or else this device's learnt cost of a first pass (FIRST_PASS_STAGE)
        slot = ("first_pass", len(ctx.paths), ctx.paths.sample_range)
        stage = f"{self.NAME}_{FIRST_PASS_STAGE}"
        res = progressive_surface_caustics(ps, self.NAME, p["photons"], s, ctx.stats, prog,
                                           p["ppm_alpha"], p["radius"] * scene_relative(ps),
                                           show_progress=ctx.show_progress,
                                           sample_range=ctx.paths.sample_range,
                                           first_cost=ctx.cache.get(slot),
                                           predict_first=lambda rays, hits:
                                           ctx.predict(stage, rays + hits),
                                           kept_hits=ctx.paths.hits)
        if res.rays:
            ctx.cache[slot] = (res.rays[0], res.seconds[0])
            ctx.learn(stage, res.rays[0] + res.hits, res.seconds[0])
        self._report(ctx, prog, res, ps)
        return PassResult(surface=res.image)

    def _report(self, ctx: PassContext, prog, res: SurfacePasses, ps: PreparedScene) -> None:
        """The passes' statistics, and a note when the first pass alone broke the budget."""
        name = self.NAME
        ctx.stats.set(**{f"{name}_radius": res.radius,
                         f"{name}_radius_world": res.radius * ps.frame.scale,
                         f"{name}_radius_last": res.radius * float(res.scales[-1])
                         if len(res.scales) else 0.0,
                         f"{name}_passes": len(res.seconds),
                         f"{name}_pass_seconds": res.seconds,
                         f"{name}_pass_rays": res.rays,
                         f"{name}_time_budget": self.params["time_budget"],
                         f"{name}_stopped_by": res.stopped_by,
                         f"{name}_sized_from": res.sized_from,
                         f"{name}_error_estimate": res.error})
        rays = res.rays[0] if res.rays else int(self.params["photons"])
        if rays >= int(self.params["photons"]):
            unit, lower = "a pass of all its photons", f"render.{name}.photons"
        else:   # sized down: what is left is the k-nearest queries of every diffuse hit
            unit = (f"a first pass, in which each of the {res.hits} diffuse hits gathers its "
                    f"k nearest of {rays} lighting rays,")
            lower = f"render.{name}.k, camera.resolution or camera.spp"
        ctx.overrun(prog, prog.overrun_note(name, unit, lower))
