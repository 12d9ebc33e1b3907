"""Mitsuba 3 scenes out: a clscatter scene as Mitsuba 3 scene XML (with its meshes as OBJ
files and its density grids as ``.vol`` files in a folder beside it) or as a dict for
``mi.load_dict``; and ``clscatter convert`` (:func:`write_scene`), which writes any scene
as TOML or XML.

Every object is written as the triangle mesh clscatter renders (an OBJ file in world space,
with its vertex normals where it is smooth), so Mitsuba sees exactly clscatter's geometry.
The rest, with its units and conventions, is docs/mitsuba.md; in short:

=====================  ================================================================
clscatter              Mitsuba 3
=====================  ================================================================
camera                 ``perspective`` (``fov``, ``fov_axis``, ``to_world`` = lookat,
                       ``near_clip`` 1e-4 so that no medium in front of the lens is
                       skipped), ``hdrfilm`` with a ``box`` filter, a ``stratified``
                       sampler for spp 4^k (else ``independent``) and the seed
point / spot light     ``point`` / ``spot`` (``intensity`` W/sr; ``beam_width`` =
                       ``cutoff_angle``: a hard cone)
directional light      ``directional`` (``direction``, ``irradiance`` W/m²)
medium                 ``homogeneous``: ``sigma_t`` = kappa / max(kappa) with ``scale`` =
                       max(kappa), ``albedo`` = sigma_s / kappa; ``hg`` phase
                       (``isotropic`` for g = 0). Bounds: a ``cube`` with a ``null`` BSDF
                       holding it; the sensor's medium when the camera is inside it
materials              ``diffuse`` and ``black`` (reflectance 0), ``mirror`` (``conductor``),
                       each in ``twosided``; ``dielectric`` (``int_ior`` = ior,
                       ``ext_ior`` = 1) with its interior medium on each shape
volumes of ior 1       a ``null`` shape holding a ``homogeneous`` medium
density volumes        a ``null`` ``cube`` (the bounds) holding a ``heterogeneous`` medium:
                       ``sigma_t`` a ``gridvolume`` (a ``.vol`` file, its ``to_world``
                       the bounds) of density x kappa / max(kappa), ``scale`` =
                       max(kappa), ``albedo`` = sigma_s / kappa
render                 ``volpath``, ``max_depth`` 2 (single scattering) or, with mirrors or
                       glass, render.max_depth + 2 (noted)
=====================  ================================================================
"""
from __future__ import annotations

import copy
import io
import math
import os
import re
import struct
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SceneError
from ..geometry import unit
from .loader import scene_from_dict, scene_source
from .mitsuba_in import PLUGIN_CLASSES, Transform
from .model import Material, Scene

#: Mitsuba's max_depth for single scattering: the camera's segment and the light's
SINGLE_SCATTERING_DEPTH = 2
NEAR_CLIP = 1e-4          # Mitsuba's default 0.01 would skip that much medium at the lens
FAR_CLIP = 1e7

Mesh = tuple[np.ndarray, np.ndarray, "np.ndarray | None"]


@dataclass
class Conversion:
    """A clscatter scene in Mitsuba 3 form.

    ``tree`` is a Mitsuba-style dict (what ``mi.load_dict`` takes, with :class:`Transform`
    values, and files named by their paths relative to the scene file), ``files`` the
    content of each such file (OBJ meshes, ``.vol`` grids), ``notes`` one line for each
    thing Mitsuba renders differently from clscatter."""

    tree: dict
    files: dict[str, bytes] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def convert(scene: Scene | Mapping[str, Any], base_dir: str | Path = ".", *,
            folder: str = "files", spp: int | None = None, seed: int | None = None,
            sampler: str | None = None) -> Conversion:
    """The Mitsuba 3 form of ``scene`` (a :class:`Scene`, or a scene dict validated here
    with relative paths resolved against ``base_dir``). Its files are named
    ``<folder>/object_<i>.obj`` (``volume_<i>.obj`` or ``.vol`` for volumes). ``spp``,
    ``seed`` and ``sampler`` (a Mitsuba sampler type) replace the scene's own. A volume
    with a graded index of refraction is a SceneError naming it: Mitsuba has none."""
    if not isinstance(scene, Scene):
        scene = scene_from_dict(copy.deepcopy(dict(scene)), base_dir)
    return _Writer(scene, folder).conversion(spp, seed, sampler)


def _rgb(value: Any) -> dict:
    return {"type": "rgb", "value": [float(x) for x in np.broadcast_to(value, (3,))]}


def _perpendicular_up(d: np.ndarray) -> np.ndarray:
    """An up vector not parallel to ``d`` (for a light's look_at, where roll is irrelevant)."""
    return np.array([1.0, 0.0, 0.0]) if abs(float(unit(d)[1])) > 0.9 else np.array([0.0, 1.0, 0.0])


#: the least ``sigma_t`` channel written, relative to the largest: Mitsuba's media give NaN
#: for a channel of exactly zero extinction (this one changes transmittance by 1e-7 x the
#: optical depth, below float32's resolution)
MIN_SIGMA_T = 1e-7


def _extinction(sigma_s: Any, sigma_a: Any) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(kappa / max(kappa), at least :data:`MIN_SIGMA_T`; max(kappa); albedo = sigma_s /
    kappa, 0 where kappa is 0), or None when kappa is 0: Mitsuba's ``sigma_t`` (rgb within
    [0, 1]), ``scale`` and ``albedo``."""
    ss = np.broadcast_to(np.asarray(sigma_s, np.float64), (3,))
    kappa = ss + np.broadcast_to(np.asarray(sigma_a, np.float64), (3,))
    if not np.any(kappa > 0.0):
        return None
    scale = float(kappa.max())
    albedo = np.where(kappa > 0.0, ss / np.where(kappa > 0.0, kappa, 1.0), 0.0)
    return np.maximum(kappa / scale, MIN_SIGMA_T), scale, albedo


def _phase(g: float) -> dict:
    return {"type": "isotropic"} if g == 0.0 else {"type": "hg", "g": float(g)}


def homogeneous(sigma_s: Any, sigma_a: Any, g: float) -> dict | None:
    """A ``homogeneous`` medium with these coefficients (None when kappa is 0): ``sigma_t``
    = kappa / max(kappa) with ``scale`` = max(kappa), ``albedo`` = sigma_s / kappa, phase
    ``hg`` with ``g`` (``isotropic`` at 0)."""
    ext = _extinction(sigma_s, sigma_a)
    if ext is None:
        return None
    sigma_t, scale, albedo = ext
    return {"type": "homogeneous", "sigma_t": _rgb(sigma_t), "scale": scale,
            "albedo": _rgb(albedo), "phase": _phase(g)}


def _box(lo: np.ndarray, hi: np.ndarray, unit: tuple[float, float]) -> Transform:
    """The to_world that maps the cube [unit[0], unit[1]]^3 onto the box [lo, hi]."""
    size = (hi - lo) / (unit[1] - unit[0])
    m = np.diag([*size, 1.0])
    m[:3, 3] = lo - unit[0] * size
    return Transform(m)


def bsdf(material: Material) -> dict:
    """The BSDF of a material: diffuse, black and mirror in ``twosided`` (Mitsuba's are
    black from behind; clscatter's surfaces are two-sided), glass as ``dielectric``."""
    if material.type == "dielectric":
        return {"type": "dielectric", "int_ior": float(material.ior), "ext_ior": 1.0}
    if material.type == "mirror":
        inner = {"type": "conductor", "specular_reflectance": _rgb(material.reflectance)}
    else:
        albedo = material.albedo if material.type == "diffuse" else np.zeros(3)
        inner = {"type": "diffuse", "reflectance": _rgb(albedo)}
    return {"type": "twosided", "material": inner}


def _ref(key: str) -> dict:
    return {"type": "ref", "id": key}


class _Writer:
    """One scene being written (:func:`convert`)."""

    def __init__(self, scene: Scene, folder: str):
        self.scene, self.folder = scene, folder
        self.tree: dict = {"type": "scene"}
        self.out = Conversion(self.tree)
        m = scene.medium
        self.g = float(m.g) if m is not None else 0.0
        self.medium = homogeneous(m.sigma_s, m.sigma_a, self.g) if scene.has_medium() else None
        self.bounds = m.bounds if self.medium is not None else None
        self.bsdf_ids: dict[int, str] = {}        # id(Material) -> its top-level id
        self.interior_ids: dict[int, str] = {}    # id(Material) -> its interior medium's

    def conversion(self, spp: int | None, seed: int | None, sampler: str | None) -> Conversion:
        self.tree["integrator"] = {"type": "volpath", "max_depth": self.depth()}
        if self.medium is not None:
            self.tree["medium"] = self.medium
        for name, material in self.scene.materials.items():
            key = self.key(re.sub(r"[^A-Za-z0-9_.-]", "_", name))
            self.tree[key] = bsdf(material)
            self.bsdf_ids[id(material)] = key
            interior = self.interior(material)
            if interior is not None:
                self.interior_ids[id(material)] = self.key(f"{key}_interior")
                self.tree[self.interior_ids[id(material)]] = interior
        self.tree["sensor"] = self.sensor(spp, seed, sampler)
        for i, light in enumerate(self.scene.lights):
            self.tree[self.key(f"light_{i}")] = self.light(light)
        straddling = []
        for i, obj in enumerate(self.scene.objects):
            self.tree[self.key(f"object_{i}")] = self.solid(obj, i)
            if self.in_medium(obj.vertices) == "straddles":
                straddling.append(obj.key)
        if straddling:
            self.out.notes.append(
                f"{', '.join(straddling)}: partly inside and partly outside the medium's "
                "bounds; Mitsuba keeps the medium a ray arrives in, so where such a surface "
                "meets the bounds' faces it may be lit without the medium")
        for i, volume in enumerate(self.scene.volumes):
            self.tree[self.key(f"volume_{i}")] = self.volume(volume, i)
        if self.bounds is not None:
            lo, hi = (np.asarray(b, np.float64) for b in self.bounds)
            self.tree[self.key("medium_bounds")] = {"type": "cube", "bsdf": {"type": "null"},
                                                    "interior": _ref("medium"),
                                                    "to_world": _box(lo, hi, (-1.0, 1.0))}
        return self.out

    def key(self, name: str) -> str:
        n, out = 1, name
        while out in self.tree:
            n += 1
            out = f"{name}_{n}"
        return out

    def depth(self) -> int:
        """2 (single scattering) without mirrors and glass; with them, render.max_depth + 2
        (noted: Mitsuba then also renders multiple scattering)."""
        if not any(o.material.type in ("mirror", "dielectric") for o in self.scene.objects):
            return SINGLE_SCATTERING_DEPTH
        depth = self.scene.render.max_depth + SINGLE_SCATTERING_DEPTH
        self.out.notes.append(
            f"the scene has mirrors or glass: Mitsuba's volpath has no single-scattering mode, "
            f"so max_depth = render.max_depth + 2 = {depth} keeps their specular paths but "
            "also renders multiple scattering")
        return depth

    def sensor(self, spp: int | None, seed: int | None, sampler: str | None) -> dict:
        cam = self.scene.camera
        spp = cam.spp if spp is None else spp
        if sampler is None:      # Mitsuba's stratified rounds up to a power-of-two square
            side = math.isqrt(spp)
            sampler = "stratified" if side * side == spp and side & (side - 1) == 0 \
                else "independent"
        sensor = {
            "type": "perspective", "fov": float(cam.fov), "fov_axis": cam.fov_axis,
            "near_clip": NEAR_CLIP, "far_clip": FAR_CLIP,
            "to_world": Transform.looking(cam.origin, cam.target, cam.up),
            "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb",
                     "component_format": "float32"},
            "sampler": {"type": sampler, "sample_count": int(spp),
                        "seed": int(self.scene.render.seed if seed is None else seed)},
        }
        if self.in_medium(np.asarray(cam.origin, np.float64)[None]) == "inside":
            sensor["medium"] = _ref("medium")
        return sensor

    def light(self, light) -> dict:
        if light.type == "point":
            return {"type": "point", "position": [float(x) for x in light.position],
                    "intensity": _rgb(light.power)}
        if light.type == "spot":
            pos = np.asarray(light.position, np.float64)
            return {"type": "spot", "intensity": _rgb(light.power),
                    "cutoff_angle": float(light.cutoff_angle),
                    "beam_width": float(light.cutoff_angle),
                    "to_world": Transform.looking(pos, pos + unit(light.direction),
                                                  _perpendicular_up(light.direction))}
        return {"type": "directional", "direction": [float(x) for x in unit(light.direction)],
                "irradiance": _rgb(light.power)}

    def in_medium(self, points: np.ndarray) -> str:
        """Where the points (a surface's vertices) lie: "inside" the medium (all of them in
        its bounds, or an unbounded medium), "outside" (no medium, or their bounding box
        apart from the bounds) or "straddles" the bounds' faces."""
        if self.medium is None:
            return "outside"
        if self.bounds is None:
            return "inside"
        lo, hi = self.bounds
        if np.all((points >= lo) & (points <= hi)):
            return "inside"
        apart = np.any(points.min(axis=0) > hi) or np.any(points.max(axis=0) < lo)
        return "outside" if apart else "straddles"

    def interior(self, material: Material) -> dict | None:
        if material.type != "dielectric":
            return None
        g = self.g if material.interior_g is None else material.interior_g
        return homogeneous(material.interior_sigma_s, material.interior_sigma_a, g)

    def mesh(self, name: str, mesh: Mesh) -> dict:
        filename = f"{self.folder}/{name}.obj"
        self.out.files[filename] = obj_text(mesh).encode()
        node: dict = {"type": "obj", "filename": filename}
        if mesh[2] is None:
            node["face_normals"] = True
        return node

    def solid(self, obj, i: int) -> dict:
        node = self.mesh(f"object_{i}", (obj.vertices, obj.faces, obj.normals))
        m = obj.material
        node["bsdf"] = _ref(self.bsdf_ids[id(m)]) if id(m) in self.bsdf_ids else bsdf(m)
        where = self.in_medium(obj.vertices)
        if where == "inside":
            node["exterior"] = _ref("medium")
        interior = self.interior(m)
        if interior is not None:
            node["interior"] = (_ref(self.interior_ids[id(m)]) if id(m) in self.interior_ids
                                else interior)
        elif where == "inside" and m.type != "dielectric":
            node["interior"] = _ref("medium")
        return node

    def volume(self, volume, i: int) -> dict:
        """A shape volume of ior 1 as a ``null`` shape holding a homogeneous medium; a
        density volume as a ``null`` cube holding a heterogeneous one (its phase is the
        scene medium's, as a volume's is)."""
        if volume.grid is not None or volume.ior != 1.0:
            raise SceneError(volume.key, "a graded index of refraction has no Mitsuba 3 "
                                         "equivalent; only volumes of ior 1 convert")
        if volume.mesh is not None:
            interior = homogeneous(volume.sigma_s, volume.sigma_a, self.g)
            mesh = volume.mesh
            node = self.mesh(f"volume_{i}", (mesh.vertices, mesh.faces, mesh.normals))
            points = mesh.vertices
        else:
            interior = self.heterogeneous(volume, f"{self.folder}/volume_{i}.vol")
            lo, hi = (np.asarray(b, np.float64) for b in volume.grid_bounds)
            node = {"type": "cube", "to_world": _box(lo, hi, (-1.0, 1.0))}
            points = np.array([lo, hi])
        if interior is None:
            raise SceneError(volume.key, "a volume of ior 1 with no medium changes nothing; "
                                         "leave it out")
        node.update(bsdf={"type": "null"}, interior=interior)
        if self.in_medium(points) == "inside":
            node["exterior"] = _ref("medium")
        return node

    def heterogeneous(self, volume, filename: str) -> dict | None:
        """The ``heterogeneous`` medium of a density volume: ``sigma_t`` a grid of density x
        kappa / max(kappa) (one channel where kappa is grey, else three), ``scale`` =
        max(kappa), ``albedo`` = sigma_s / kappa; the grid's file written as ``filename``."""
        ext = _extinction(volume.sigma_s, volume.sigma_a)
        if ext is None:
            return None
        sigma_t, scale, albedo = ext
        density = np.asarray(volume.density, np.float64)
        values = density if np.all(sigma_t == 1.0) else density[..., None] * sigma_t
        lo, hi = (np.asarray(b, np.float64) for b in volume.grid_bounds)
        self.out.files[filename] = vol_bytes(values, lo, hi)
        grid = {"type": "gridvolume", "filename": filename, "to_world": _box(lo, hi, (0.0, 1.0))}
        return {"type": "heterogeneous", "sigma_t": grid, "scale": scale,
                "albedo": _rgb(albedo), "phase": _phase(self.g)}


# ---- XML text, OBJ files, the mitsuba dict --------------------------------------------

def xml_text(conversion: Conversion) -> str:
    """The Mitsuba 3 scene XML of a conversion (its meshes referred to by file name)."""
    root = ET.Element("scene", version="3.0.0")
    for key, node in conversion.tree.items():
        if key != "type":
            root.append(_element(key, node, top=True))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def _numbers(values: Any) -> str:
    return ", ".join(repr(float(x)) for x in values)


def _element(key: str, value: Any, top: bool = False) -> ET.Element:
    """The XML element of one entry of a Mitsuba-style dict."""
    if isinstance(value, Mapping) and value["type"] == "ref":
        return ET.Element("ref", id=value["id"], name=key)
    if isinstance(value, Mapping) and value["type"] == "rgb":
        return ET.Element("rgb", name=key, value=_numbers(value["value"]))
    if isinstance(value, Mapping):
        el = ET.Element(PLUGIN_CLASSES[value["type"]], type=value["type"],
                        **({"id": key} if top else {"name": key}))
        for k, v in value.items():
            if k != "type":
                el.append(_element(k, v))
        return el
    if isinstance(value, Transform):
        el = ET.Element("transform", name=key)
        if value.look_at is not None:
            o, t, u = value.look_at
            ET.SubElement(el, "lookat", origin=_numbers(o), target=_numbers(t), up=_numbers(u))
        else:
            ET.SubElement(el, "matrix", value=" ".join(repr(float(x)) for x in value.matrix.ravel()))
        return el
    if isinstance(value, bool):
        return ET.Element("boolean", name=key, value="true" if value else "false")
    if isinstance(value, int):
        return ET.Element("integer", name=key, value=str(value))
    if isinstance(value, float):
        return ET.Element("float", name=key, value=repr(value))
    if isinstance(value, str):
        return ET.Element("string", name=key, value=value)
    return ET.Element("vector" if key == "direction" else "point", name=key,
                      value=_numbers(value))


def vol_bytes(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bytes:
    """A grid (nx, ny, nz) or (nx, ny, nz, channels) as a Mitsuba ``.vol`` file: ``VOL``,
    version 3, float32 encoding, the resolution and channels, the box, then the values
    with x fastest (Mitsuba places the grid by its ``to_world``; the box is for readers
    that use it)."""
    v = np.asarray(values, np.float32)
    v = v[..., None] if v.ndim == 3 else v
    nx, ny, nz, channels = v.shape
    header = struct.pack("<3sBiiiii6f", b"VOL", 3, 1, nx, ny, nz, channels, *lo, *hi)
    return header + np.ascontiguousarray(v.transpose(2, 1, 0, 3)).astype("<f4").tobytes()


def obj_text(mesh: Mesh) -> str:
    """A triangle mesh as Wavefront OBJ text (positions to full precision; ``vn`` and
    ``f a//a ...`` where it has vertex normals)."""
    vertices, faces, normals = mesh
    buf = io.StringIO()
    np.savetxt(buf, np.asarray(vertices, np.float64), fmt="v %.17g %.17g %.17g")
    f = np.asarray(faces, np.int64) + 1
    if normals is not None:
        np.savetxt(buf, np.asarray(normals, np.float64), fmt="vn %.17g %.17g %.17g")
        np.savetxt(buf, np.repeat(f, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
    else:
        np.savetxt(buf, f, fmt="f %d %d %d")
    return buf.getvalue()


def mitsuba_dict(conversion: Conversion, folder: str | Path) -> dict:
    """The dict ``mi.load_dict`` takes: the conversion's files written under ``folder``
    (by their names) and referred to there, transforms as Mitsuba's. Needs the ``mitsuba``
    package with a variant set."""
    import mitsuba as mi

    folder = Path(folder)
    for name, content in conversion.files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(content)

    def plain(key: str, value: Any) -> Any:
        if isinstance(value, Transform):
            if value.look_at is not None:
                o, t, u = (v.tolist() for v in value.look_at)
                return mi.ScalarTransform4f().look_at(origin=o, target=t, up=u)
            return mi.ScalarTransform4f(value.matrix.tolist())
        if isinstance(value, Mapping):
            return {k: plain(k, v) for k, v in value.items()}
        if key == "filename" and value in conversion.files:
            return str(folder / value)
        return value
    return plain("", conversion.tree)


# ---- files: convert -------------------------------------------------------------------

def write_xml(scene: Scene | Mapping[str, Any], path: str | Path, base_dir: str | Path = "."
              ) -> list[str]:
    """Write ``scene`` as Mitsuba 3 XML to ``path`` and its files (OBJ meshes, ``.vol``
    grids) into the folder ``<stem>_files`` beside it, all or nothing; returns the notes."""
    from ..io.outputs import write_all

    path = Path(path)
    conversion = convert(scene, base_dir, folder=f"{path.stem}_files")
    text = xml_text(conversion)
    writes = [(path.parent / name, lambda tmp, c=content: tmp.write_bytes(c))
              for name, content in conversion.files.items()]
    writes.append((path, lambda tmp: tmp.write_text(text)))
    folder = path.parent / f"{path.stem}_files"
    created = bool(conversion.files) and not folder.is_dir()
    if created:
        folder.mkdir()
    try:
        write_all(writes)
    except BaseException:
        if created:
            try:
                folder.rmdir()
            except OSError:
                pass
        raise
    return conversion.notes


def write_scene(spec: str, dst: str | Path) -> list[str]:
    """``clscatter convert SPEC -o DST``: read the scene ``spec`` (a .toml or .xml file, or
    ``builtin:NAME``), validate it, and write it to ``dst`` as a TOML scene or Mitsuba 3
    XML by dst's suffix. Returns the notes of both conversions; on any error nothing is
    written."""
    from ..io.outputs import check_output, write_all
    from .builtin import to_toml

    dst = check_output(dst, (".toml", ".xml"), "-o")
    notes: list[str] = []
    data, base_dir = scene_source(spec, on_note=notes.append)
    scene = scene_from_dict(copy.deepcopy(data), base_dir, str(spec))
    if dst.suffix.lower() == ".xml":
        return notes + write_xml(scene, dst)
    text = f"# clscatter scene converted from {spec}\n" + to_toml(
        _rebased(data, Path(base_dir), dst.resolve().parent))
    write_all([(dst, lambda tmp: tmp.write_text(text))])
    return notes


def _rebased(data: dict, base_dir: Path, folder: Path) -> dict:
    """``data`` with the relative file names of objects and volumes made relative to
    ``folder`` instead of ``base_dir``."""
    data = copy.deepcopy(data)
    for section in ("objects", "volumes"):
        for item in data.get(section, []):
            for key in ("file", "grid", "density", "sigma_s_grid", "sigma_a_grid"):
                if isinstance(item.get(key), str) and not Path(item[key]).is_absolute():
                    item[key] = os.path.relpath((base_dir / item[key]).resolve(), folder)
    return data
