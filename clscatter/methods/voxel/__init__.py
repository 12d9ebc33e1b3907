"""``voxel``: graded-index volumes by voxelisation and adaptive curved photon marching."""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass

import numpy as np

from ...device import Engine
from ...errors import SceneError
from ...estimators.density_march import upload
from ...estimators.segment_march import march_segments
from ...scene.model import Scene, Volume
from ...transport.context import PassContext
from ...transport.prepared import (
    PreparedScene,
    geometry_key,
    prepare_scene,
    refresh,
    same_frame,
)
from .. import register
from ..base import AutoRole, Method, Param, PassResult, camera_samples, costs
from .pipeline import Pipeline, beyond_mode, release_contributions


def as_volume_scene(scene: Scene, voxelise_dielectrics: bool) -> Scene:
    """``scene`` with its dielectric objects turned into constant-index volumes (their
    interior absorption and scattering as the volume's coefficients), when asked and when
    there are any; the scene itself otherwise."""
    if not voxelise_dielectrics:
        return scene
    keep, vols = [], []
    for o in scene.objects:
        if o.material.type == "dielectric":
            vols.append(Volume(ior=o.material.ior, sigma_s=np.asarray(o.material.interior_sigma_s, float),
                               sigma_a=np.asarray(o.material.interior_sigma_a, float), resolution=0,
                               mesh=o, key=o.key))
        else:
            keep.append(o)
    if not vols:
        return scene
    return dataclasses.replace(scene, objects=keep, volumes=[*scene.volumes, *vols])


@register
class Voxel(Method):
    """``voxel``: refractive volumes relit interactively (Sun et al. 2008).

    The region around the scene's ``[[volumes]]`` (their union's box grown by ``margin``)
    becomes a grid of ``resolution`` voxels along its longest side. Volumes are voxelised
    (inside test at voxel centres, 4^3 coverage where the 3x3x3 neighbourhood disagrees,
    9^3 Gaussian blur with sigma 1.5 voxels) into the index n, scattering and extinction
    (mixed with the scene medium by the blurred weights) and grad n without the volumes'
    boundary jumps (the interior gradient: boundaries are crossed by Snell's law); an
    octree stored as a
    dense level grid (min/max pyramid, tolerance ``eps``) and a step limit (``step_max``
    voxels where the node's index range lies between ``eps`` and ``eps2``) pace the
    photons. ``photons`` photons per light start where its light enters the grid
    (stratified, shadowed and attenuated on the way) and march the ray equation
    x += ds/n v, v += ds grad n with adaptive steps, depositing flux x length into every
    voxel each step's segment crosses; the result is smoothed 3x3x3. View rays are traced
    as the engine traces them until they enter the grid, then bent through it at one-voxel
    steps, collecting sigma_s p_HG(stored mean direction) x fluence with attenuation, then
    continue straight.

    The join: every piece of every view path lies inside the grid (all its light from the
    photons: direct light and light bent by volumes alike) or outside it (direct single
    scattering by ``raymarch``, shadow rays through the scene). Nothing is counted twice.
    Surfaces (``surface_photons``): photons that reach a diffuse surface in the grid, or
    beyond it going on straight, are stored as a photon map (hit point, incoming
    direction, flux); every diffuse hit of the view paths gets its estimate from the
    ``surface_k`` nearest (within ``surface_radius``; the estimator of ``photonmap``), and
    the straight direct light only from the lights whose shadow ray misses the grid's box
    (the rest is the photons'), so volumes cast shadows and caustics on the floor without
    being counted twice. The seam along the outline of the grid's straight shadow is the
    photon map's boundary bias (about one estimation radius wide).

    Approximations: outside the grid light is not bent (a caustic beyond the grid's faces
    is cut there: grow ``margin`` to include it); photons end at mirrors and glass (no
    specular bounces of photons); dielectric objects are voxelised as constant-index volumes
    (``voxelise_dielectrics``). Sharp boundaries: a volume's boundary lies where its
    blurred weight is 1/2; a photon or view ray meeting it from index n1 to n2 is cut
    there, refracted by Snell's law (the normal from the blurred weight's gradient) and
    keeps the unpolarised Fresnel transmittance of the sharp interface (bending through
    the smoothed band instead under-deviates a curved surface's grazing rays, by several
    degrees at typical resolutions: docs/voxel.md); the reflected part is dropped (no
    reflected photons, no reflection of the scene in a voxelised ball), and a path past
    the critical angle is mirrored whole (total internal reflection; ``render.max_depth``
    of them end it).

    Density volumes (heterogeneous media) are voxelised like grid volumes, their
    coefficients the sampled density times ``sigma_s`` and ``sigma_a``; the surface photons
    carry the smoke's shadow (without them the straight tracers' shadow rays are attenuated
    through the density grids themselves, ``density.h``, exact optical depths).

    Usage: ``clscatter render scene.toml --method voxel --set render.voxel.resolution=128``;
    ``--stats`` reports the grid (``voxel_grid``: min, max, dims, voxel size in scene
    units), photons, marching steps and launches, per-stage seconds, and which volumes the
    geometry stage voxelised (``voxel_revoxelised``: in a session only the volumes whose
    shape moved, or all of them when the grid box changed; docs/voxel.md).
    """

    NAME = "voxel"
    CAMERA_IN_GLASS = False     # its viewing pass starts at the index the camera sees in the grid
    PARAMS = (
        Param("resolution", 64, "voxels along the grid's longest side", lo=8, hi=1024),
        Param("margin", 0.25, "grid margin around the volumes, per side, relative to their extent", lo=0.0),
        Param("photons", 1 << 16, "photons per light (rounded up to a square)", lo=1),
        Param("eps", 0.005, "octree tolerance: index range of a node marched to its face", lo=0.0, lo_open=True),
        Param("eps2", 0.02, "second tolerance: nodes with range in [eps, eps2) limit steps to step_max",
              lo=0.0, lo_open=True),
        Param("step_min", 1.0, "smallest photon step, voxels", lo=0.0, lo_open=True),
        Param("step_max", 8.0, "photon step limit in nodes with range in [eps, eps2), voxels", lo=0.0, lo_open=True),
        Param("adaptive", True, "octree-adaptive photon steps (false: every step is step_min)"),
        Param("steps_per_launch", 16, "photon steps per kernel launch", lo=1),
        Param("done_fraction", 0.999, "stop marching when this fraction of photons has finished",
              lo=0.0, hi=1.0, lo_open=True),
        Param("min_flux", 1e-3, "a photon ends below this fraction of its starting flux", lo=0.0),
        Param("smoothing", True, "3x3x3 smoothing of the deposited radiance"),
        Param("view_rounds", 4, "grid passes per view path (in, out, back in after a mirror...); "
              "at most 4: branch ids grow 64x a round and must stay exact as float32 sort keys",
              lo=1, hi=4),
        Param("direct_steps", 32, "raymarch samples per view segment outside the grid", lo=1),
        Param("beyond", "auto", "how light that left the grid scatters outside it: 'grid' (deposited "
              "in a coarse outer grid over the medium's bounds), 'lsg' (line-space gathering of "
              "the photons' rays: sharper, slower, and right in an unbounded medium), 'none'; "
              "'auto': 'grid' in a bounded medium, 'lsg' in an unbounded one",
              choices=("auto", "grid", "lsg", "none")),
        Param("outer_resolution", 64, "outer grid: voxels along the medium's longest side", lo=4, hi=1024),
        Param("exit_radius", 0.005, "gather radius for beyond = 'lsg', relative to the scene extent",
              lo=0.0, lo_open=True),
        Param("voxelise_dielectrics", True, "voxelise dielectric objects as constant-index volumes"),
        Param("surface_photons", True, "diffuse surfaces get the light that crosses the grid from "
              "the photons that reach them (a photon-map estimate at the view paths' diffuse "
              "hits) and no straight direct light where their shadow ray crosses the grid: "
              "volumes cast shadows and caustics on surfaces; false: the engine's straight "
              "direct light everywhere (density grids' shadows only)"),
        Param("surface_k", 64, "surface photons per estimate (the k nearest)", lo=2, hi=1024),
        Param("surface_radius", 0.05, "largest surface estimation radius, relative to the "
              "scene extent", lo=0.0, lo_open=True),
    )
    TERMS = frozenset({"direct", "volumes"})

    @classmethod
    def computes(cls, scene, params: dict) -> frozenset[str]:
        """Its ``TERMS``, and where it voxelises the glass of a scene without mirrors (whose
        light its photons do not follow), the glass's caustics: in the medium, and on
        surfaces with ``surface_photons``."""
        kinds = {o.material.type for o in scene.objects}
        if not params["voxelise_dielectrics"] or "mirror" in kinds or "dielectric" not in kinds:
            return cls.TERMS
        return cls.TERMS | {"caustics"} | ({"surface_caustics"} if params["surface_photons"]
                                           else set())
    PREVIEW_SCALE = {"photons": 0.25}
    AUTO = {"volumes": AutoRole(priority=10)}
    # When auto picks this method it must render the whole image alone: it computes the
    # direct term itself (raymarch outside its grid, photons inside) and voxelises glass,
    # so a separate direct, caustic or surface-caustic pass would count light twice (the
    # planner honours ALONE; see docs/voxel.md).
    ALONE = True
    INTERIOR_SCATTERING = True    # voxelised glass carries its interior coefficients
    DENSITY = True                # density volumes are voxelised like grid volumes

    # bytes per voxel of the grid while a frame renders: n, grad, sigma_s, kappa, octree
    # level and limit, deposits (2 float4), a blur temporary, the volumes' weights, the
    # boundary sides (Fresnel)
    BYTES_PER_VOXEL = 4 + 16 + 16 + 16 + 1 + 4 + 32 + 16 + 8 + 16

    @classmethod
    def estimate(cls, scene, params):
        """Working set: the grid (its resolution cubed, an upper bound), the outer grid,
        the photon states of one light (48 bytes each) with, for the surface photon map, two
        records per photon and light (80 bytes each: marched and straight), and the view
        rays (2 x 64 bytes per camera sample, an upper bound)."""
        if not scene.volumes and not any(o.material.type == "dielectric" for o in scene.objects):
            return []
        grid = float(params["resolution"]) ** 3
        outer = (float(params["outer_resolution"]) ** 3
                 if beyond_mode(params["beyond"], scene.medium) == "grid" else 0.0)
        photons = float(params["photons"]) * max(1, len(scene.lights))
        on_surfaces = photons * 160.0 if params["surface_photons"] else 0.0
        return costs("voxel", {"render.voxel.resolution": grid * cls.BYTES_PER_VOXEL,
                               "render.voxel.outer_resolution": outer * 48,
                               "render.voxel.photons": float(params["photons"]) * 48 + on_surfaces,
                               "camera.resolution": camera_samples(scene) * 128.0},
                     {"render.voxel.photons": photons * 30},
                     "photon steps (order of magnitude)")

    @classmethod
    def check_params(cls, params: dict) -> None:
        if params["eps2"] < params["eps"]:
            raise SceneError("render.voxel.eps2", f"must be >= eps (got {params['eps2']!r})")
        if params["step_max"] < params["step_min"]:
            raise SceneError("render.voxel.step_max", f"must be >= step_min (got {params['step_max']!r})")

    def render(self, ctx: PassContext) -> PassResult:
        """The medium seen through the grid and outside it, and the surface term of the
        pipeline's own view paths (bent through the grid), which replaces the session's."""
        ps, stats = ctx.ps, ctx.stats
        scene = as_volume_scene(ps.scene, self.params["voxelise_dielectrics"])
        if not scene.volumes:
            stats.set(voxel_note="no volumes (and no dielectric objects to voxelise): nothing to do")
            if len(ctx.paths) == 0 or ps.num_lights == 0:
                return PassResult(medium=ctx.zeros())
            return PassResult(medium=march_segments(ps, ctx.segments(), self.params["direct_steps"],
                                                    stats, ctx.show_progress))
        vps = self._variant(ctx, scene) if scene is not ps.scene else ps
        pipe = self._pipeline(ctx, vps)
        dens = None
        if scene.density_volumes() and not self.params["surface_photons"]:
            # surfaces' shadow rays through the grids (with surface photons the photons
            # carry the grids' shadows)
            dens = ctx.cache["density"] = upload(vps, ctx.cache.get("density"))
        try:
            out = pipe.update(vps, stats, ctx.show_progress,
                              medium=dens.buf if dens is not None else None)
        except BaseException:
            ctx.cache.release()
            raise
        stats.set(**{k: v for k, v in pipe.counters.items()}, voxel_stages_run=list(pipe.ran),
                  voxel_stage_seconds=dict(pipe.timings), voxel_revoxelised=list(pipe.revoxelised))
        return PassResult(medium=out["medium"], view_surface=out["surface"])

    @staticmethod
    def release_cache(engine: Engine | None = None) -> None:
        """Drop the volumes' voxelised contributions kept for ``engine`` (every engine's
        when None) past the sessions' caches (``pipeline.kept_contributions``); the next
        render voxelises every volume."""
        release_contributions(engine)

    # ---- what the session keeps between renders (ctx.cache) ----
    @staticmethod
    def _variant(ctx: PassContext, scene: Scene) -> PreparedScene:
        """The prepared scene with dielectrics voxelised, kept in the session: prepared (a
        BVH build) once per geometry, its light, camera, medium and material buffers
        refreshed after other changes."""
        key = geometry_key(scene)
        old = ctx.cache.get("variant")
        if old is not None and old.key == key and same_frame(old.ps, scene):
            refresh(old.ps, scene, ctx.stats)
            return old.ps
        if old is not None:
            old.release()
        ctx.cache["variant"] = _Variant(key, prepare_scene(scene, ctx.engine, ctx.stats))
        return ctx.cache["variant"].ps

    def _pipeline(self, ctx: PassContext, ps: PreparedScene) -> Pipeline:
        """The pipeline of the session's previous render with the stages whose inputs
        changed dropped (a fresh one the first time): a warm re-render after a light move
        runs lighting and view only. A geometry change makes the session drop this cache
        (it prepares the scene anew); the geometry stage then voxelises again only the
        volumes whose own shape, or the grid box, changed, reusing the contributions kept
        per engine (``pipeline.contribution_key``, ``pipeline.kept_contributions``; the
        stats' ``voxel_revoxelised`` lists the volumes voxelised)."""
        keys = stage_keys(ps, self.params)
        old = ctx.cache.get("pipeline")
        if old is None:
            pipe = Pipeline(self.params, engine=ps.engine)
        else:
            pipe = old.pipe
            pipe.params = self.params
            for stage, k_old, k_new in zip(("geometry", "material", "lighting"), old.keys, keys):
                if k_old != k_new:
                    pipe.invalidate(stage, ps.engine)
                    break
        ctx.cache["pipeline"] = _Kept(keys, pipe)
        return pipe


@dataclass
class _Variant:
    """A prepared variant of the scene and the geometry it was prepared for."""

    key: tuple
    ps: PreparedScene

    def release(self) -> None:
        self.ps.release()


@dataclass
class _Kept:
    """The voxel stages of the last render and the fingerprints of their inputs."""

    keys: tuple
    pipe: Pipeline

    def release(self) -> None:
        self.pipe.release()


def _digest(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(np.ascontiguousarray(p).tobytes() if isinstance(p, np.ndarray) else repr(p).encode())
    return h.hexdigest()


def stage_keys(ps, params: dict) -> tuple[str, str, str]:
    """Fingerprints of what the geometry, material and lighting stages read. The geometry
    stage reads the volumes' shapes (meshes, a grid volume's bounds), their ``resolution``
    and the grid parameters; a grid volume's values are the material stage's (sampled
    there, like the densities); each key folds in those before it."""
    vols = ps.scene.volumes
    geo = [ps.frame.scale, ps.frame.centre, params["resolution"], params["margin"]]
    mat = [ps.medium, params["eps"], params["eps2"], params["step_max"]]
    for v in vols:
        geo += [v.resolution, None if v.mesh is None else v.mesh.vertices,
                None if v.mesh is None else v.mesh.faces, repr(v.grid_bounds)]
        mat += [v.ior, v.sigma_s, v.sigma_a, v.grid, getattr(v, "sigma_s_grid", None),
                getattr(v, "sigma_a_grid", None), v.density]
    g, m = _digest(*geo), _digest(*mat)
    light = _digest(g, m, ps.lights, ps.bvh.triangles, ps.scene.render.seed, ps.scene.render.max_depth,
                    *(params[k] for k in ("photons", "adaptive", "step_min", "min_flux", "steps_per_launch",
                                          "done_fraction", "smoothing", "beyond", "outer_resolution",
                                          "surface_photons")))
    return g, _digest(g, m), light
