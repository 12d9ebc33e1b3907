"""The normalised device frame, and the flat arrays the kernels read.

Kernels work in float32, so the host first moves the scene into a *normalised frame*:
centred on the scene's bounding box and scaled so its longest side is 1
(``x' = (x - centre) / scale``). That box leaves far objects out (``Scene.bbox``): they
stay at their large normalised coordinates, where float32 still places them to ~1e-7 of
their distance, while what is near the camera keeps its precision.
A scene translated by 1e4 or scaled by 1e-3 then looks the same to the device, and
fixed epsilons (``RAY_EPS`` in common.h) keep their meaning. Radiance is invariant under
the change of units when coefficients and intensities change with it:

* lengths:            t' = t / scale
* coefficients:       sigma' = sigma * scale           (sigma t stays the same)
* point/spot intensity: I' = I / scale^2               (I / d^2 stays the same)
* directional irradiance and all radiances: unchanged

All of this is computed in float64 on the host before conversion to float32.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device import structs
from ..errors import SceneError
from .model import Camera, Light, Medium, Scene


def _fits_float32(value, key: str, what: str) -> np.ndarray:
    """``value`` (float64, normalised) if float32 holds it; else a SceneError naming the
    scene key whose value, rescaled for the frame, overflows."""
    a = np.asarray(value, np.float64)
    if np.any(np.abs(a) > np.finfo(np.float32).max):
        raise SceneError(key, f"overflows float32 once the scene is normalised ({what}); "
                              "use smaller units or a smaller value")
    return a


# An unbounded medium ends (for view and light paths) where the transmittance of the
# least attenuated channel falls below this; the tail beyond carries < this fraction.
TRANSMITTANCE_CUTOFF = 1e-5


@dataclass(frozen=True)
class Frame:
    """Affine map world -> normalised device coordinates (uniform scale)."""

    centre: np.ndarray
    scale: float

    def point(self, p) -> np.ndarray:
        return (np.asarray(p, np.float64) - self.centre) / self.scale

    def length(self, t: float) -> float:
        return float(t) / self.scale

    def coefficient(self, sigma) -> np.ndarray:
        return np.asarray(sigma, np.float64) * self.scale

    @staticmethod
    def for_scene(scene: Scene) -> "Frame":
        """Centre and scale from the scene's bounding box (:meth:`Scene.bbox`: the objects
        and volumes that are not far), else the medium's bounds, else lights and camera."""
        bb = scene.bbox()
        if bb is None and scene.medium is not None and scene.medium.bounds is not None:
            bb = scene.medium.bounds
        if bb is None:
            pts = [scene.camera.origin] + [l.position for l in scene.lights if l.position is not None]
            pts = np.array(pts, np.float64)
            bb = (pts.min(axis=0), pts.max(axis=0))
        lo, hi = (np.asarray(b, np.float64) for b in bb)
        ext = float(np.max(hi - lo))
        if not np.isfinite(ext) or ext <= 0:
            ext = 1.0  # a single point (one light and the camera at it): any scale works
        return Frame(centre=(lo + hi) / 2, scale=ext)


def camera_struct(cam: Camera, frame: Frame, scene: Scene | None = None) -> np.ndarray:
    """The Camera struct: orthonormal basis with right/up scaled by the half-fov tangents;
    with ``scene`` (whose camera ``cam`` is), inside a closed glass object
    (:meth:`Scene.camera_glass`): that glass's material index (as the triangle soup numbers
    them) and its ior^2 (else -1 and 1: in air)."""
    fwd = cam.target - cam.origin
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    aspect = cam.width / cam.height
    half = math.tan(math.radians(cam.fov) / 2)
    tan_x, tan_y = (half, half / aspect) if cam.fov_axis == "x" else (half * aspect, half)
    c = np.zeros((), structs.CAMERA)
    c["origin"] = structs.vec4(frame.point(cam.origin))
    c["forward"] = structs.vec4(fwd)
    c["right"] = structs.vec4(right * tan_x)
    c["up"] = structs.vec4(up * tan_y)
    c["width"], c["height"], c["spp"] = cam.width, cam.height, cam.spp
    side = int(round(math.sqrt(cam.spp)))
    c["spp_side"] = side if side * side == cam.spp else 0
    glass = scene.camera_glass() if scene is not None else None
    c["inside"] = -1 if glass is None else material_order(scene)[id(glass.material)]
    c["radiance_scale"] = 1.0 if glass is None else glass.material.ior ** 2
    return c


def material_order(scene: Scene) -> dict[int, int]:
    """The device material table's order: ``id(material)`` -> index, each object's material
    at its first appearance."""
    order: dict[int, int] = {}
    for obj in scene.objects:
        order.setdefault(id(obj.material), len(order))
    return order


def medium_struct(medium: Medium | None, frame: Frame) -> np.ndarray:
    """The Medium struct in normalised units (``present = 0`` for no or a void medium)."""
    m = np.zeros((), structs.MEDIUM)
    m["g"] = 0.0
    big = 1e30
    m["bmin"] = structs.vec4([-big] * 3)
    m["bmax"] = structs.vec4([big] * 3)
    if medium is None:
        return m
    why = "coefficients times the scene's size"
    sigma_s = _fits_float32(frame.coefficient(medium.sigma_s), "medium.sigma_s", why)
    sigma_a = _fits_float32(frame.coefficient(medium.sigma_a), "medium.sigma_a", why)
    kappa = _fits_float32(sigma_s + sigma_a, "medium.sigma_a", "sigma_s + sigma_a, " + why)
    if not np.any(kappa > 0):
        return m
    m["present"] = 1
    m["sigma_s"] = structs.vec4(sigma_s)
    m["sigma_a"] = structs.vec4(sigma_a)
    m["kappa"] = structs.vec4(kappa)
    m["g"] = medium.g
    m["t_far"] = math.log(1 / TRANSMITTANCE_CUTOFF) / float(np.min(kappa[kappa > 0]))
    if medium.bounds is not None:
        m["bounded"] = 1
        m["bmin"] = structs.vec4(frame.point(medium.bounds[0]))
        m["bmax"] = structs.vec4(frame.point(medium.bounds[1]))
    return m


def light_structs(lights: list[Light], frame: Frame) -> np.ndarray:
    """Light structs; intensities rescaled for the frame (irradiance unchanged)."""
    out = np.zeros(len(lights), structs.LIGHT)
    for i, l in enumerate(lights):
        out[i]["type"] = structs.LIGHT_TYPES[l.type]
        out[i]["cos_cutoff"] = -2.0
        if l.position is not None:
            out[i]["position"] = structs.vec4(frame.point(l.position))
        if l.direction is not None:
            d = np.asarray(l.direction, np.float64)
            out[i]["direction"] = structs.vec4(d / np.linalg.norm(d))
        if l.type == "directional":
            out[i]["power"] = structs.vec4(l.power)
        else:
            out[i]["power"] = structs.vec4(_fits_float32(
                np.asarray(l.power) / frame.scale ** 2, f"lights[{i}].intensity",
                "intensities over the scene's size squared"))
        if l.type == "spot":
            out[i]["cos_cutoff"] = math.cos(math.radians(l.cutoff_angle))
    return out


@dataclass
class TriangleSoup:
    """All objects' triangles in the normalised frame, with per-vertex shading normals
    (flat shapes get the face normal three times) and a material index per triangle."""

    triangles: np.ndarray     # (T, 3, 3) float64
    normals: np.ndarray       # (T, 3, 3) float64, unit
    material: np.ndarray      # (T,) int32 index into `materials`
    materials: np.ndarray     # structs.MATERIAL array


def triangle_soup(scene: Scene, frame: Frame, materials_only: bool = False) -> TriangleSoup:
    """Flatten every object of ``scene`` into one triangle soup in the normalised frame
    (``materials_only``: just the material table, in the same order; no triangles)."""
    mat_index = material_order(scene)
    mats: list = [None] * len(mat_index)
    tris, norms, tri_mat = [], [], []
    for obj in scene.objects:
        key = id(obj.material)
        mats[mat_index[key]] = obj.material
        if materials_only:
            continue
        v = frame.point(obj.vertices)
        f = np.asarray(obj.faces, np.int64)
        t = v[f]
        if obj.normals is not None:
            n = np.asarray(obj.normals, np.float64)[f]
        else:
            fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
            ln = np.linalg.norm(fn, axis=1, keepdims=True)
            fn = np.divide(fn, ln, out=np.zeros_like(fn), where=ln > 0)
            n = np.repeat(fn[:, None, :], 3, axis=1)
        tris.append(t)
        norms.append(n)
        tri_mat.append(np.full(len(f), mat_index[key], np.int32))
    m = np.zeros(max(len(mats), 1), structs.MATERIAL)
    for i, mat in enumerate(mats):
        m[i]["type"] = structs.MATERIAL_TYPES[mat.type]
        m[i]["color"] = structs.vec4(mat.color)
        m[i]["ior"] = mat.ior
        m[i]["interior_sigma_a"] = structs.vec4(frame.coefficient(mat.interior_sigma_a))
        m[i]["interior_sigma_s"] = structs.vec4(frame.coefficient(mat.interior_sigma_s))
    if tris:
        return TriangleSoup(np.concatenate(tris), np.concatenate(norms), np.concatenate(tri_mat), m)
    return TriangleSoup(np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int32), m)
