"""``raymap``: surface caustics from ray maps (Havran, Bittner, Herzog, Seidel 2005).

The estimators it shares with ``photonmap`` live in :mod:`clscatter.estimators`:
:mod:`~clscatter.estimators.segment_tree` (the lazy kd-tree over ray segments,
LRU-bounded, with directional nodes), :mod:`~clscatter.estimators.knn_queries` (batched
device queries and their NumPy references), :mod:`~clscatter.estimators.ray_density`
(surface density estimation).
"""
from __future__ import annotations

from ...estimators.ray_density import DensitySettings
from ...estimators.segment_tree import TreeParams
from .. import register
from ..base import AutoRole, Param
from ..surface_density import DENSITY_PARAMS, SurfaceDensityMethod


@register
class RayMapMethod(SurfaceDensityMethod):
    """``raymap``: diffuse surfaces lit through mirrors and glass, by density estimation over
    a ray map (Havran et al. 2005), plus the medium by the engine's ``medium`` method.

    Lighting rays aimed at the mirrors and glass (``clscatter.transport.emission``, exact pdf
    weights) are traced through them (``clscatter.transport.light_paths``, Fresnel split,
    ``render.max_depth``) and kept as *segments*: the last piece of every
    branch after at least one specular bounce (ending on a diffuse or black surface, or
    leaving the scene), with the flux it delivers. A kd-tree over the segments (every leaf
    lists the segments crossing its cell; spatial median of the longest axis; split while
    more than ``c_min`` references, cell diagonal above ``r_min`` of the scene diagonal,
    depth below ``d_max``) is refined lazily by the queries, with directional nodes
    (``alpha``) and an LRU bound (``memory_mb``) that collapses cold subtrees.

    Every point where a camera path meets a diffuse surface gets the irradiance
    ``E = sum w_i Phi_i / (pi R^2)`` from its ``k`` nearest incoming rays under the
    paper's *hemisphere-disc* metric (a ray counts when it comes within R of the point
    above the tangent plane and its prolongation meets the disc of radius R), weighted
    by ``kernel`` on the distance where the ray meets the tangent plane; the pixel gets
    ``albedo / pi * E`` times the path's throughput. Rays passing a boundary are counted
    as if the surface went on, so edges and corners keep their brightness where a photon
    map darkens them (boundary bias).

    *Gather radius and progressive passes*: as every surface density estimator's
    (:class:`~clscatter.methods.surface_density.SurfaceDensityMethod`; automatic per-hit
    radii, progressive passes that shrink them, under the render's budget and error target).

    Chosen explicitly it renders the whole picture: the planner runs the ``medium`` method
    beside it (``lsg`` by default: direct single scattering and volumetric caustics). In
    ``auto`` it is the surface-caustic pass only.

    Statistics: ``raymap_rays_stored``, ``diffuse_hits``, ``raymap_tree_nodes``,
    ``raymap_tree_refs``, ``raymap_index_peak_bytes``, ``raymap_collapses``,
    ``raymap_nodes_visited``, ``raymap_refs_tested`` (those of the K-nearest pass),
    ``raymap_splat_nodes_visited``, ``raymap_splat_hits_tested`` (summed over the later,
    splatted passes); stages ``raymap_trace`` (lighting
    rays and diffuse hits), ``raymap_build`` (the tree's root), ``raymap_radius`` (how far
    each batch of queries refines: the K-th nearest ray end point), ``raymap_refine`` (the
    lazy refinement on the host and the tree's upload), ``raymap_estimate`` (the queries
    on the device), ``raymap_splat`` (the later passes' splats and the hits' tree); per
    pass ``raymap_radius`` (median first radius, normalised),
    ``raymap_radius_world``, ``raymap_radius_last``, ``raymap_passes``,
    ``raymap_pass_seconds``, ``raymap_stopped_by``, ``raymap_error_estimate``,
    ``raymap_sized_from`` (under a deadline: ``session``, ``calibration`` or ``none``).

    Usage: ``clscatter render builtin:caustic_sphere --method raymap --set render.raymap.k=128``
    """

    NAME = "raymap"
    PARAMS = DENSITY_PARAMS + (
        Param("c_min", 32, "split kd-tree nodes with more references than this (C_min)", lo=1),
        Param("r_min", 0.001, "... whose diagonal exceeds this fraction of the scene diagonal (R_min)",
              lo=0),
        Param("d_max", 30, "... and whose depth is below this (D_max)", lo=1, hi=40),
        Param("alpha", 10.0, "directional nodes: extension angle in degrees (0: none)", lo=0, hi=45),
        Param("memory_mb", 128.0, "LRU bound on the kd-tree index in MB (0: none)", lo=0),
        Param("lazy", True, "build the kd-tree lazily, driven by the queries"),
    )
    AUTO = {"surface_caustics": AutoRole(priority=10, params={"medium": "none"})}

    def settings(self) -> DensitySettings:
        p = self.params
        tree = TreeParams(c_min=p["c_min"], r_min=p["r_min"], d_max=p["d_max"], alpha_deg=p["alpha"],
                          max_bytes=int(p["memory_mb"] * (1 << 20)))
        return DensitySettings(k=p["k"], kernel=p["kernel"], batch=p["batch"], lazy=p["lazy"], tree=tree)
