"""``photonmap``: surface caustics from a photon map (Jensen 1996), the ray map's baseline.

Everything but the query is shared with ``raymap`` (:mod:`clscatter.methods.raymap.density`):
the same lighting rays, the same kd-tree code (indexing the photons' hit points only),
the same estimation kernel.
"""
from __future__ import annotations

import numpy as np

from ...transport.prepared import PreparedScene
from ...io.stats import Stats
from ...transport.view_paths import ViewPaths
from .. import register
from ..base import AutoRole, Method, Param
from ..raymap import COMMON_PARAMS, render_surface_and_medium, scene_relative
from ..raymap.density import DensitySettings, surface_caustics
from ..raymap.kdtree import TreeParams


@register
class PhotonMapMethod(Method):
    """``photonmap``: diffuse surfaces lit through mirrors and glass, by density estimation
    over a photon map (Jensen 1996), plus the medium by the engine's ``medium`` method.

    The lighting rays of ``raymap`` (after at least one specular bounce) that end on a
    diffuse surface are stored as photons (hit point, incoming direction, flux) in a
    kd-tree (the ray map's, over points: spatial median split, ``leaf_size`` photons per
    leaf). Every diffuse point seen by a camera path gets ``E = sum w_i Phi_i / (pi R^2)``
    from its ``k`` nearest incoming photons (R: distance of the k-th, at most
    ``max_radius``), with ``kernel`` weights on the photon distance; the pixel gets
    ``albedo / pi * E`` times the path's throughput. Near edges and corners the disc
    covers area without photons and the estimate darkens (boundary bias): ``raymap``
    removes that at 2-5x the cost.

    Run alone it renders the whole picture (direct surface light + surface caustics + the
    medium by ``medium``); ``auto`` prefers ``raymap`` for surface caustics.

    Statistics: as ``raymap`` with the prefix ``photonmap_``.

    Usage: ``clscatter render builtin:caustic_sphere --method photonmap``
    """

    NAME = "photonmap"
    PARAMS = COMMON_PARAMS + (
        Param("leaf_size", 16, "split kd-tree nodes holding more photons than this", lo=1),
    )
    TERMS = frozenset({"surface_caustics", "direct", "caustics"})
    PREVIEW_SCALE = {"photons": 0.125}
    AUTO = {"surface_caustics": AutoRole(priority=5, params={"medium": "none"})}

    def settings(self) -> DensitySettings:
        p = self.params
        tree = TreeParams(c_min=p["leaf_size"], r_min=0.0, d_max=40, alpha_deg=0.0)
        return DensitySettings(k=p["k"], kernel=p["kernel"], batch=p["batch"], lazy=False, tree=tree)

    def render(self, ps: PreparedScene, paths: ViewPaths, stats: Stats,
               show_progress: bool = True) -> np.ndarray | dict:
        """Surface caustics (H, W, 3); run alone, ``{"surface", "medium"}``."""
        return render_surface_and_medium(self, "photonmap", self.settings(), ps, paths, stats,
                                         show_progress)

    def surface_caustics(self, ps: PreparedScene, stats: Stats, show_progress: bool = True) -> np.ndarray:
        """The surface-caustic image alone (H, W, 3)."""
        s = self.settings()
        s.max_radius = self.params["max_radius"] * scene_relative(ps)
        return surface_caustics(ps, "photonmap", self.params["photons"], s, stats, show_progress)
