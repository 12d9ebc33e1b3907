"""``photonmap``: surface caustics from a photon map (Jensen 1996), the ray map's baseline.

Everything but the query is shared with ``raymap`` (:mod:`clscatter.methods.surface_density`):
the same lighting rays, the same kd-tree code (indexing the photons' hit points only),
the same estimation kernel.
"""
from __future__ import annotations

from ...estimators.ray_density import DensitySettings
from ...estimators.segment_tree import TreeParams
from .. import register
from ..base import AutoRole, Param
from ..surface_density import DENSITY_PARAMS, SurfaceDensityMethod


@register
class PhotonMapMethod(SurfaceDensityMethod):
    """``photonmap``: diffuse surfaces lit through mirrors and glass, by density estimation
    over a photon map (Jensen 1996); chosen explicitly, with the ``medium`` method beside it.

    The lighting rays of ``raymap`` (after at least one specular bounce) that end on a
    diffuse surface are stored as photons (hit point, incoming direction, flux) in a
    kd-tree (the ray map's, over points: spatial median split, ``leaf_size`` photons per
    leaf). Every diffuse point seen by a camera path gets ``E = sum w_i Phi_i / (pi R^2)``
    from its ``k`` nearest incoming photons (R: distance of the k-th, at most
    ``max_radius``), with ``kernel`` weights on the photon distance; the pixel gets
    ``albedo / pi * E`` times the path's throughput. Near edges and corners the disc
    covers area without photons and the estimate darkens (boundary bias): ``raymap``
    removes that at 2-5x the cost.

    *Gather radius and progressive passes*: as every surface density estimator's
    (:class:`~clscatter.methods.surface_density.SurfaceDensityMethod`; automatic per-hit
    radii, progressive passes that shrink them, under the render's budget and error target).

    Chosen explicitly it renders the whole picture (the planner runs the ``medium`` method
    beside it); ``auto`` prefers ``raymap`` for surface caustics.

    Statistics: as ``raymap`` with the prefix ``photonmap_``.

    Usage: ``clscatter render builtin:caustic_sphere --method photonmap``
    """

    NAME = "photonmap"
    PARAMS = DENSITY_PARAMS + (
        Param("leaf_size", 16, "split kd-tree nodes holding more photons than this", lo=1),
    )
    AUTO = {"surface_caustics": AutoRole(priority=5, params={"medium": "none"})}

    def settings(self) -> DensitySettings:
        p = self.params
        tree = TreeParams(c_min=p["leaf_size"], r_min=0.0, d_max=40, alpha_deg=0.0)
        return DensitySettings(k=p["k"], kernel=p["kernel"], batch=p["batch"], lazy=False, tree=tree)
