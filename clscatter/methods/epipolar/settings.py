"""Epipolar's parameters, declared once (:data:`PARAMS`), and :class:`Settings`, the same
values as typed attributes for the pipeline's functions."""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from ..base import Param

LOOKUPS = ("segment", "grid")
MIN_LIGHT_RAYS = 256       # the automatic light rays per slice never go below this

PARAMS = (
    Param("slices", 0, "0: the sinh distribution at one-pixel spacing (the half-pixel "
          "bound); N: about N slices", lo=0),
    Param("lookup", "segment", '"segment": every camera sample is swept at its own beta '
          'and depth in its two neighbouring slices; "grid": the paper\'s rectified depth '
          "map and bilinear unrectification", choices=LOOKUPS),
    Param("rays_per_slice", 0, "grid lookup: view rays per slice (0: the longest slice's "
          "length in pixels)", lo=0),
    Param("depth_map", 0, "grid lookup: depth-map width (0: image width)", lo=0),
    Param("light_rays", 0, "light rays per slice, d (0: max(W, H, 256), one per pixel of the "
          "longer side, each with four depth sub-samples when prefiltering); not 1", lo=0),
    Param("shadow_map", 0, "shadow map resolution (0: 2 max(W, H), clamped to 1024 .. 4096)",
          lo=0),
    Param("svd_terms", 4, "SVD terms N", lo=1, hi=16),
    Param("svd_samples", 64, "the SVD samples an n x n grid (n >= svd_terms)", lo=1, hi=1024),
    Param("prefilter", True, "four depth sub-samples per light ray, clustered into "
          "weighted modes"),
    Param("prefilter_tolerance", 1.0, "sub-samples within this many pixel angles of beta "
          "form one mode", lo=0),
    Param("epipole_ring", 2.0, "radius (degrees) around the epipole or anti-epipole that "
          "is ray marched (0: none)", lo=0, hi=45),
    Param("epipole_band", 1.0, "band beyond the ring where ray marching and the sweep "
          "are blended, as a fraction of the ring's radius", lo=0),
    Param("svd_tolerance", 0.01, "RMS relative error the sweep must meet on held-out "
          "samples; above it more terms, light rays or slices, else raymarch", lo=0,
          lo_open=True),
    Param("svd_max_terms", 16, "most SVD terms the error control may use", lo=1, hi=16),
    Param("raymarch_steps", 64, "steps of the ray marcher for the ring and the fallbacks",
          lo=1),
    Param("batch_slices", 256, "slices per kernel launch (memory/progress)", lo=1),
)


@dataclass(frozen=True)
class Settings:
    """Checked ``[render.epipolar]`` values under the parameters' own names (``0``:
    automatic, resolved per image by the pipeline); defaults come from :data:`PARAMS`
    alone (:func:`settings`)."""

    slices: int
    lookup: str
    rays_per_slice: int
    depth_map: int
    light_rays: int
    shadow_map: int
    svd_terms: int
    svd_samples: int
    prefilter: bool
    prefilter_tolerance: float
    epipole_ring: float          # degrees (0: no ring)
    epipole_band: float          # the blended band, a fraction of the ring's radius
    svd_tolerance: float
    svd_max_terms: int
    raymarch_steps: int
    batch_slices: int

    @classmethod
    def from_params(cls, params: dict[str, Any]) -> "Settings":
        """The settings of checked parameters ``params`` (every key of :data:`PARAMS`)."""
        return cls(**{f.name: params[f.name] for f in fields(cls)})


def settings(**overrides: Any) -> Settings:
    """The defaults of :data:`PARAMS` with ``overrides`` (tests and tools)."""
    return Settings.from_params({**{p.name: p.default for p in PARAMS}, **overrides})
