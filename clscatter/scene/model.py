"""The scene model: plain dataclasses filled by the TOML loader (``loader.py``).

Everything is in *scene units* and world space, as the scene file says (float64 on the
host). Shapes are already triangulated and transformed: an :class:`Object` holds a
triangle mesh. Conversion to the normalised device frame happens later, in
``clscatter/scene/normalised.py``; nothing here knows about OpenCL.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..geometry import (
    PARITY_RAY,
    box_corners,
    open_edges,
    perpendicular_axes,
    ray_crossings,
)

RGB = np.ndarray  # shape (3,), float64

#: An object or volume is *far* when its bounding box lies more than this many times the
#: near region's longest side away from that region (``Scene._near_mask``): far geometry
#: is rendered, but the scene's bounding box (the device frame, relative radii) leaves it
#: out, so float32 keeps resolving what is near the camera.
FAR_FACTOR = 1e3


@dataclass
class Camera:
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float = 45.0           # full field of view, degrees, along fov_axis
    fov_axis: str = "x"         # "x" or "y"
    width: int = 512
    height: int = 384
    spp: int = 4                # a square number is stratified n x n


@dataclass
class Medium:
    sigma_s: RGB
    sigma_a: RGB
    g: float = 0.0
    bounds: tuple[np.ndarray, np.ndarray] | None = None   # (min, max); None = unbounded

    @property
    def kappa(self) -> RGB:
        """Extinction coefficient sigma_s + sigma_a (rgb)."""
        return self.sigma_s + self.sigma_a


@dataclass
class Light:
    type: str                   # "point" | "spot" | "directional"
    power: RGB                  # intensity (W/sr) for point/spot, irradiance (W/m^2) for directional
    position: np.ndarray | None = None
    direction: np.ndarray | None = None   # unit; spot axis, or directional travel direction
    cutoff_angle: float = 0.0   # spot half-angle, degrees


@dataclass
class Material:
    name: str
    type: str                   # "diffuse" | "mirror" | "dielectric" | "black"
    albedo: RGB = field(default_factory=lambda: np.full(3, 0.5))
    reflectance: RGB = field(default_factory=lambda: np.ones(3))
    ior: float = 1.5
    interior_sigma_a: RGB = field(default_factory=lambda: np.zeros(3))
    interior_sigma_s: RGB = field(default_factory=lambda: np.zeros(3))
    interior_g: float | None = None   # phase inside (None: the scene medium's g)
    key: str = ""               # its table's dotted key, for messages ("materials.glass")

    @property
    def color(self) -> RGB:
        """The colour the device needs: albedo (diffuse) or reflectance (mirror)."""
        return self.reflectance if self.type == "mirror" else self.albedo


@dataclass
class Object:
    """A triangle mesh in world space with one material.

    ``normals`` are per-vertex shading normals (unit) for smooth shapes (meshed spheres,
    meshes that carry them); None means flat shading with face normals.
    """

    shape: str                  # "mesh" | "sphere" | "box" | "quad"
    material: Material
    vertices: np.ndarray        # (V, 3) float64
    faces: np.ndarray           # (F, 3) int64
    normals: np.ndarray | None = None
    key: str = ""               # e.g. "objects[2]", for messages
    dropped_triangles: int = 0  # zero-area triangles removed when loading


@dataclass
class Volume:
    """A ``[[volumes]]`` region (docs/scene_format.md, "What a volume means"): a shape with a
    constant index (``mesh``), or a box (``grid_bounds``) holding an index grid (``grid``),
    a density grid (``density``) or both.

    ``density`` (nx, ny, nz) float32 holds the density at the box's voxel centres; the
    coefficients are then per unit density: sigma_s(x) = density(x) * ``sigma_s``, and
    likewise ``sigma_a``. A density volume without an index grid has ``ior`` 1 and bends no
    light (:attr:`refracts` is False)."""

    ior: float
    sigma_s: RGB
    sigma_a: RGB
    resolution: int = 128
    mesh: Object | None = None
    grid: np.ndarray | None = None
    grid_bounds: tuple[np.ndarray, np.ndarray] | None = None
    key: str = ""
    sigma_s_grid: np.ndarray | None = None   # per-voxel coefficients of a grid volume
    sigma_a_grid: np.ndarray | None = None
    density: np.ndarray | None = None        # density at the box's voxel centres (float32)

    @property
    def refracts(self) -> bool:
        """True for a shape or an index grid: a region whose index the voxel pipeline
        models (a pure density volume has n = 1 everywhere)."""
        return self.mesh is not None or self.grid is not None


# the method names the scene format reserves (render.method, [render.<name>] tables)


@dataclass
class RenderSettings:
    method: str = "auto"
    max_depth: int = 16
    seed: int = 0
    time_budget: float | None = None  # seconds for the whole render; 0: none; None: the default
    target_error: float = 0.0   # relMSE the progressive passes stop at; 0: none
    params: dict[str, dict[str, Any]] = field(default_factory=dict)  # [render.<method>] tables


@dataclass
class Scene:
    camera: Camera
    medium: Medium | None = None
    lights: list[Light] = field(default_factory=list)
    materials: dict[str, Material] = field(default_factory=dict)
    objects: list[Object] = field(default_factory=list)
    volumes: list[Volume] = field(default_factory=list)
    render: RenderSettings = field(default_factory=RenderSettings)
    source: str = "<memory>"    # file path or "builtin:NAME"

    def dropped_triangles(self) -> int:
        """Zero-area triangles removed from the objects when the scene was loaded."""
        return sum(o.dropped_triangles for o in self.objects)

    def scatters_inside_glass(self) -> list[Material]:
        """The dielectric materials of the objects that scatter light inside
        (``interior_sigma_s`` above 0), once each."""
        seen: dict[int, Material] = {}
        for o in self.objects:
            m = o.material
            if m.type == "dielectric" and float(np.max(m.interior_sigma_s)) > 0.0:
                seen.setdefault(id(m), m)
        return list(seen.values())

    def density_volumes(self) -> list[Volume]:
        """The volumes with a density grid (heterogeneous media), in scene order."""
        return [v for v in self.volumes if v.density is not None]

    def has_medium(self) -> bool:
        """True when a medium exists and extinguishes light somewhere (a void medium, all
        coefficients 0, is no medium)."""
        return self.medium is not None and bool(np.any(self.medium.kappa > 0))

    def _item_boxes(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """Keys and bounding boxes (lo, hi: (n, 3)) of the objects, then the volumes, that
        have geometry (a mesh with vertices, or a grid's box)."""
        keys, boxes = [], []
        for o in self.objects:
            if len(o.vertices):
                keys.append(o.key)
                boxes.append((o.vertices.min(axis=0), o.vertices.max(axis=0)))
        for v in self.volumes:
            if v.mesh is not None and len(v.mesh.vertices):
                keys.append(v.key)
                boxes.append((v.mesh.vertices.min(axis=0), v.mesh.vertices.max(axis=0)))
            elif v.grid_bounds is not None:
                keys.append(v.key)
                gb = np.asarray(v.grid_bounds, np.float64)
                boxes.append((gb.min(axis=0), gb.max(axis=0)))
        lo = np.array([b[0] for b in boxes], np.float64).reshape(-1, 3)
        hi = np.array([b[1] for b in boxes], np.float64).reshape(-1, 3)
        return keys, lo, hi

    def _near_mask(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Which of the boxes ``lo``, ``hi`` (:meth:`_item_boxes`) are near (bool, same
        order); see :data:`FAR_FACTOR`.

        The near region starts as the box around the camera's origin, the positions of the
        point and spot lights and a bounded medium's box. Repeatedly the item whose box is
        nearest to the region (Euclidean distance between the boxes, 0 when they meet)
        joins it and widens it, unless its distance is more than :data:`FAR_FACTOR` times
        the region's longest side; that item and every one still left are far. The first
        item to join always joins (a region of the camera alone has no size)."""
        near = np.zeros(len(lo), bool)
        anchors = [np.asarray(self.camera.origin, np.float64)]
        anchors += [np.asarray(l.position, np.float64) for l in self.lights
                    if l.position is not None]
        m = self.medium
        if m is not None and m.bounds is not None:
            anchors += [np.asarray(b, np.float64) for b in m.bounds]
        a = np.array(anchors)
        rlo, rhi = a.min(axis=0), a.max(axis=0)
        while not near.all():
            gap = np.maximum(0.0, np.maximum(lo - rhi, rlo - hi))
            dist = np.where(near, -np.inf, np.linalg.norm(gap, axis=1))
            reach = FAR_FACTOR * float(np.max(rhi - rlo))
            if near.any() and np.all(dist <= reach):
                near[:] = True      # all within reach now, so at every later step too
                break
            i = int(np.argmin(np.where(near, np.inf, dist)))
            if near.any() and not dist[i] <= reach:
                break
            near[i] = True
            rlo, rhi = np.minimum(rlo, lo[i]), np.maximum(rhi, hi[i])
        return near

    def far_items(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """Key (``objects[3]``, ``volumes[0]``) and bounding box (lo, hi) of every far
        object and volume: those the scene's bounding box leaves out (:meth:`bbox`)."""
        keys, lo, hi = self._item_boxes()
        near = self._near_mask(lo, hi)
        return [(k, lo[i], hi[i]) for i, k in enumerate(keys) if not near[i]]

    def far_in_beam(self, direction) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The far items (:meth:`far_items`) that may shadow the near region from a
        directional light travelling along ``direction``: their box reaches upstream of
        the region's downstream end and its projection along the light overlaps the
        region's (the region: :meth:`bbox` and a bounded medium's box)."""
        far = self.far_items()
        boxes = [b for b in (self.bbox(), self.medium.bounds if self.medium else None)
                 if b is not None]
        if not far or not boxes:
            return []
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        axes = np.stack([*perpendicular_axes(d), d])
        near = np.concatenate([box_corners(*b) for b in boxes]) @ axes.T
        out = []
        for key, lo, hi in far:
            c = box_corners(lo, hi) @ axes.T
            if (np.all(c[:, :2].min(axis=0) <= near[:, :2].max(axis=0))
                    and np.all(c[:, :2].max(axis=0) >= near[:, :2].min(axis=0))
                    and c[:, 2].min() <= near[:, 2].max()):
                out.append((key, lo, hi))
        return out

    def bbox(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The scene's bounding box (docs/scene_format.md): the box of the objects and
        volumes that are not far (:data:`FAR_FACTOR`); None without objects or volumes.
        The normalised device frame, relative radii and step sizes all derive from it."""
        _, lo, hi = self._item_boxes()
        if not len(lo):
            return None
        near = self._near_mask(lo, hi)
        return lo[near].min(axis=0), hi[near].max(axis=0)

    def scene_extent(self) -> float:
        """Longest side of :meth:`bbox` (1.0 when the scene has no geometry); relative radii
        and step sizes in ``[render.*]`` tables are multiples of this."""
        bb = self.bbox()
        if bb is None:
            return 1.0
        ext = float(np.max(bb[1] - bb[0]))
        return ext if ext > 0 else 1.0

    def camera_glass(self) -> Object | None:
        """The closed glass object the camera's origin lies inside (the innermost, by the
        volume of its bounding box, where several nest), or None: a camera there starts its
        view paths inside that glass (the parity of a ray's crossings of its surface)."""
        eye = np.asarray(self.camera.origin, np.float64)
        found = []
        for o in self.objects:
            if o.material.type != "dielectric" or not len(o.faces):
                continue
            lo, hi = o.vertices.min(axis=0), o.vertices.max(axis=0)
            if np.any(eye < lo) or np.any(eye > hi) or open_edges(o.faces):
                continue
            if ray_crossings(eye, PARITY_RAY, o.vertices[o.faces]) % 2:
                found.append((float(np.prod(hi - lo)), o))
        return min(found, key=lambda f: f[0])[1] if found else None

    def camera_in_medium(self) -> bool:
        """True when the camera's origin lies in the medium (always, for an unbounded one)."""
        m = self.medium
        if m is None or m.bounds is None:
            return m is not None
        eye = np.asarray(self.camera.origin, np.float64)
        return bool(np.all(eye >= m.bounds[0]) and np.all(eye <= m.bounds[1]))

    def optical_depth_across(self) -> float:
        """The largest extinction times the longest side of the medium's box (of the scene's
        bounding box for an unbounded medium): how thick the medium is, from the scene alone
        (0 without a medium)."""
        if not self.has_medium():
            return 0.0
        m = self.medium
        side = float(np.max(m.bounds[1] - m.bounds[0])) if m.bounds is not None \
            else self.scene_extent()
        return float(np.max(m.kappa)) * side

    def triangle_count(self) -> int:
        return int(sum(len(o.faces) for o in self.objects))
