"""Mitsuba 3 scenes in: scene XML, or a Mitsuba-style dict (what ``mi.load_dict`` takes),
read into the scene dict of docs/scene_format.md (the TOML form that
:func:`~clscatter.scene.loader.scene_from_dict` takes), together with a list of notes.

The mapping, element by element, is docs/mitsuba.md. In short: a ``perspective`` sensor
becomes the camera; ``point``, ``spot`` and ``directional`` emitters the lights; ``obj``,
``ply``, ``sphere``, ``cube``, ``rectangle`` and ``disk`` shapes the objects; ``diffuse``,
``dielectric`` and smooth ``conductor`` BSDFs (inside ``twosided`` or not) the materials.
The ``homogeneous`` medium the sensor sits in, or that an axis-aligned ``cube`` with a
``null`` BSDF holds, is the scene medium; media in other ``null`` shapes are
``[[volumes]]`` (a ``heterogeneous`` one with a ``gridvolume`` a ``density`` volume); a
``dielectric``'s interior medium is its material's ``interior_*`` keys.

Units and conventions are Mitsuba's own, which are the scene format's: intensity in W/sr,
irradiance in W/m², ``sigma_t``/``albedo``/``scale`` as extinction, single-scattering
albedo and multiplier, ``rgb`` values linear (as Mitsuba's RGB variants use them for these
plugins). Numbers carry over unchanged except where docs/mitsuba.md gives a formula.

Every element or parameter outside that subset gives one note naming it and saying what
was done (approximated or dropped). A scene whose meaning would change beyond a note (an
area light as its only light, a rough dielectric, no light at all) is a
:class:`~clscatter.errors.SceneError` naming the element. Everything the loader checks is
left to the loader.
"""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SceneError
from ..geometry import unit
from . import shapes

#: the unit disk (radius 1 in the z = 0 plane, facing +z) that a ``disk`` shape becomes
DISK_MESH = Path(__file__).resolve().parent / "meshes" / "disk.obj"


def _classes(cls: str, names: str) -> dict[str, str]:
    return dict.fromkeys(names.split(), cls)


#: Mitsuba 3's plugins by class (the XML tag of their elements)
PLUGIN_CLASSES: dict[str, str] = {
    **_classes("bsdf", "blendbsdf bumpmap circular conductor dielectric diffuse hair mask "
                       "measured measured_polarized normalmap null plastic polarizer pplastic "
                       "principled principledthin retarder roughconductor roughdielectric "
                       "roughplastic thindielectric twosided"),
    **_classes("emitter", "area constant directional directionalarea envmap point projector spot"),
    **_classes("film", "hdrfilm specfilm"),
    **_classes("integrator", "aov depth direct direct_projective moment path prb prb_basic "
                             "prb_projective prbvolpath ptracer stokes volpath volpathmis"),
    **_classes("medium", "heterogeneous homogeneous"),
    **_classes("phase", "blendphase hg isotropic rayleigh sggx tabphase"),
    **_classes("rfilter", "box catmullrom gaussian lanczos mitchell tent"),
    **_classes("sampler", "independent ldsampler multijitter orthogonal stratified"),
    **_classes("sensor", "batch distant irradiancemeter orthographic perspective "
                         "radiancemeter thinlens"),
    **_classes("shape", "bsplinecurve cube cylinder disk ellipsoids ellipsoidsmesh instance "
                        "linearcurve obj ply rectangle sdfgrid serialized shapegroup sphere"),
    **_classes("texture", "bitmap checkerboard mesh_attribute volume"),
    **_classes("spectrum", "blackbody d65 irregular regular srgb uniform"),
    **_classes("volume", "constvolume gridvolume"),
}

#: Mitsuba's named indices of refraction (``int_ior``/``ext_ior`` of a dielectric)
IOR_NAMES = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.5750, "diamond": 2.419,
}

DEFAULT_NEAR_CLIP = 0.01      # Mitsuba's defaults: a scene within them needs no note
DEFAULT_FAR_CLIP = 1e4


@dataclass(frozen=True, eq=False)
class Transform:
    """A ``to_world`` transform: the affine 4x4 ``matrix`` and, when it is exactly one
    ``lookat``, its (origin, target, up), so that the point looked at is kept (the
    matrix holds only the direction)."""

    matrix: np.ndarray
    look_at: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @classmethod
    def looking(cls, origin: Any, target: Any, up: Any) -> Transform:
        """Mitsuba's ``look_at``: local +z towards ``target``, +y towards ``up``."""
        o, t, u = (np.asarray(v, np.float64) for v in (origin, target, up))
        return cls(look_at_matrix(o, t, u), (o, t, u))


def look_at_matrix(origin: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Mitsuba's look_at matrix: columns left = up x dir, up' = dir x left, dir, origin."""
    d = unit(target - origin)
    left = unit(np.cross(up, d))
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, origin
    return m



# ---- XML -> Mitsuba-style dict ---------------------------------------------------------

_PARAM = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_OBJECT_TAGS = frozenset(PLUGIN_CLASSES.values())


def read_xml(path: str | Path, params: Mapping[str, Any] | None = None) -> tuple[dict, list[str]]:
    """The scene dict and the notes of the Mitsuba 3 scene file ``path`` (``params`` as
    ``mi.load_file``'s keyword arguments: values for ``$name``). Relative file names in
    the dict are relative to the file's folder, as Mitsuba resolves them."""
    path = Path(path)
    return from_mitsuba(parse_xml(_read_text(path), path.parent, params, str(path)))


def parse_xml(text: str, base_dir: str | Path = ".", params: Mapping[str, Any] | None = None,
              name: str = "<xml>") -> dict:
    """Mitsuba 3 scene XML as the Mitsuba-style dict ``mi.load_dict`` takes: ``<default>``
    and ``$name`` substituted, ``<include>`` files merged in, ``<ref>`` kept as
    ``{"type": "ref", "id": ...}``, transforms as :class:`Transform`, ``rgb`` and
    ``spectrum`` values as ``{"type": "rgb" | "spectrum", "value": ...}``. Top-level
    objects are keyed by id (by tag and number without one), nested ones by ``name``."""
    reader = _XmlReader(Path(base_dir), params)
    tree: dict = {"type": "scene"}
    reader.scene(reader.root(text, name), Path(base_dir), tree)
    return tree


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneError(str(path), "scene file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(str(path), f"cannot read scene file: {exc}") from None


def _unique(mapping: Mapping, key: str) -> str:
    n, out = 1, key
    while out in mapping:
        n += 1
        out = f"{key}_{n}"
    return out


def _where(el: ET.Element) -> str:
    attrs = " ".join(f'{k}="{v}"' for k, v in el.attrib.items() if k in ("type", "id", "name"))
    return f"<{el.tag}{' ' + attrs if attrs else ''}>"


class _XmlReader:
    """One scene file and the files it includes, with the ``$name`` values in force."""

    def __init__(self, main_dir: Path, params: Mapping[str, Any] | None):
        self.main_dir = main_dir
        self.params = {k: str(v) for k, v in (params or {}).items()}
        self.including: list[Path] = []

    def root(self, text: str, name: str) -> ET.Element:
        try:
            root = ET.fromstring(text)
        except ET.ParseError as exc:
            raise SceneError(name, f"invalid XML: {exc}") from None
        if root.tag != "scene":
            raise SceneError(name, f"the root element is <{root.tag}>, not <scene>")
        version = root.get("version", "")
        if not re.fullmatch(r"3(\.\d+)*", version):
            raise SceneError(name, f"scene version '{version}': only Mitsuba 3 scenes "
                                   "(version 3.x) are read")
        return root

    def scene(self, root: ET.Element, folder: Path, tree: dict) -> None:
        for el in root:      # defaults first: they hold for the whole file
            if el.tag == "default":
                self.params.setdefault(self.attr(el, "name"), self.attr(el, "value"))
        for el in root:
            if el.tag == "default":
                continue
            if el.tag == "include":
                self.include(el, folder, tree)
            elif el.tag in _OBJECT_TAGS and "type" in el.attrib:
                node = self.object(el, folder)
                tree[_unique(tree, node.get("id", el.tag))] = node
            else:
                raise SceneError(_where(el), "not a scene element this reader knows")

    def include(self, el: ET.Element, folder: Path, tree: dict) -> None:
        path = self.resolve(self.attr(el, "filename"), folder).resolve()
        if not path.is_file():
            raise SceneError(_where(el), f"included file not found: {path}")
        if path in self.including:
            raise SceneError(_where(el), f"{path} includes itself")
        self.including.append(path)
        self.scene(self.root(_read_text(path), str(path)), path.parent, tree)
        self.including.pop()

    def resolve(self, filename: str, folder: Path) -> Path:
        """A file name as Mitsuba finds it: beside the XML file naming it, else beside the
        main scene file."""
        p = Path(filename)
        if p.is_absolute():
            return p
        return next((base / p for base in (folder, self.main_dir) if (base / p).exists()),
                    folder / p)

    def filename(self, value: str, folder: Path) -> str:
        """A file name for the scene dict: as written when it is relative to the main
        scene file's folder, absolute when only an included file's folder holds it."""
        p = Path(value)
        if p.is_absolute() or folder == self.main_dir or not (folder / p).exists():
            return value
        return str((folder / p).resolve())

    def attr(self, el: ET.Element, name: str, default: str | None = None) -> str:
        value = el.get(name)
        if value is None:
            if default is None:
                raise SceneError(_where(el), f"missing attribute '{name}'")
            return default

        def sub(m: re.Match) -> str:
            if m.group(1) not in self.params:
                raise SceneError(_where(el), f"${m.group(1)} has no value (no <default> or "
                                             "parameter of that name)")
            return self.params[m.group(1)]
        return _PARAM.sub(sub, value)

    def object(self, el: ET.Element, folder: Path) -> dict:
        node: dict = {"type": self.attr(el, "type")}
        if "id" in el.attrib:
            node["id"] = self.attr(el, "id")
        for child in el:
            key, value = self.property(child, folder)
            node[_unique(node, key)] = value
        return node

    def property(self, el: ET.Element, folder: Path) -> tuple[str, Any]:
        tag = el.tag
        if tag == "ref":
            return self.attr(el, "name", "ref"), {"type": "ref", "id": self.attr(el, "id")}
        if tag in _OBJECT_TAGS and "type" in el.attrib:
            return self.attr(el, "name", tag), self.object(el, folder)
        name = self.attr(el, "name")
        if tag == "transform":
            return name, self.transform(el)
        if tag in ("point", "vector"):
            return name, self.xyz(el, 0.0)
        if tag == "rgb":
            return name, {"type": "rgb", "value": self.floats(el, "value", (1, 3))}
        if tag == "spectrum":
            return name, self.spectrum(el, folder)
        value = self.attr(el, "value")
        if tag == "float":
            return name, self.floats(el, "value", (1,))[0]
        if tag == "integer":
            try:
                return name, int(value)
            except ValueError:
                raise SceneError(_where(el), f"'{value}' is not an integer") from None
        if tag == "boolean":
            if value.lower() not in ("true", "false"):
                raise SceneError(_where(el), f"'{value}' is not true or false")
            return name, value.lower() == "true"
        if tag == "string":
            return name, self.filename(value, folder) if name == "filename" else value
        raise SceneError(_where(el), "not an element this reader knows")

    def floats(self, el: ET.Element, attr: str, counts: tuple[int, ...]) -> list[float]:
        text = self.attr(el, attr)
        try:
            values = [float(x) for x in re.split(r"[,\s]+", text.strip()) if x]
        except ValueError:
            raise SceneError(_where(el), f"{attr}='{text}' is not a list of numbers") from None
        if len(values) not in counts:
            want = " or ".join(map(str, counts))
            raise SceneError(_where(el), f"{attr}='{text}' needs {want} numbers")
        return values

    def xyz(self, el: ET.Element, default: float) -> list[float]:
        """A 3-vector from ``value`` (one number for all three, or three) or from ``x``,
        ``y``, ``z`` (each ``default`` when absent)."""
        if "value" in el.attrib:
            v = self.floats(el, "value", (1, 3))
            return v * 3 if len(v) == 1 else v
        out = []
        for axis in "xyz":
            text = self.attr(el, axis, str(default))
            try:
                out.append(float(text))
            except ValueError:
                raise SceneError(_where(el), f"{axis}='{text}' is not a number") from None
        return out

    def spectrum(self, el: ET.Element, folder: Path) -> dict:
        if "filename" in el.attrib:
            return {"type": "spectrum", "filename": self.filename(self.attr(el, "filename"),
                                                                   folder)}
        text = self.attr(el, "value")
        if ":" not in text:
            return {"type": "spectrum", "value": self.floats(el, "value", (1,))[0]}
        try:
            pairs = [tuple(float(x) for x in p.split(":")) for p in re.split(r"[,\s]+", text.strip())
                     if p]
        except ValueError:
            pairs = []
        if not pairs or any(len(p) != 2 for p in pairs):
            raise SceneError(_where(el), f"value='{text}' is not wavelength:value pairs")
        return {"type": "spectrum", "value": pairs}

    def transform(self, el: ET.Element) -> Transform:
        """The product of the transform's steps, the first applied first."""
        m = np.eye(4)
        for op in el:
            m = self.step(op) @ m
        if len(el) == 1 and el[0].tag == "lookat":
            return Transform(m, self.look_at(el[0]))
        return Transform(m)

    def look_at(self, op: ET.Element) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o, t, u = (np.array(self.floats(op, a, (3,))) for a in ("origin", "target", "up"))
        if not np.any(t - o) or np.linalg.norm(np.cross(u, t - o)) == 0.0:
            raise SceneError(_where(op), "target equals origin, or up is parallel to the "
                                         "view direction")
        return o, t, u

    def step(self, op: ET.Element) -> np.ndarray:
        m = np.eye(4)
        if op.tag == "translate":
            m[:3, 3] = self.xyz(op, 0.0)
        elif op.tag == "scale":
            m[:3, :3] = np.diag(self.xyz(op, 1.0))
        elif op.tag == "rotate":
            angle = self.floats(op, "angle", (1,))[0]
            m[:3, :3] = shapes.rotation_matrix(np.array(self.xyz(op, 0.0)), angle)
        elif op.tag == "matrix":
            v = self.floats(op, "value", (9, 16))
            if len(v) == 9:
                m[:3, :3] = np.reshape(v, (3, 3))
            else:
                m = np.reshape(v, (4, 4))
        elif op.tag == "lookat":
            m = look_at_matrix(*self.look_at(op))
        else:
            raise SceneError(_where(op), "not a transform step (translate, rotate, scale, "
                                         "matrix, lookat)")
        return m


# ---- Mitsuba-style dict -> scene dict -------------------------------------------------

def from_mitsuba(tree: Mapping[str, Any]) -> tuple[dict, list[str]]:
    """The scene dict (TOML form) and the notes of a Mitsuba-style scene dict: what
    ``mi.load_dict`` takes (``mitsuba`` objects such as ``ScalarTransform4f`` included)
    or what :func:`parse_xml` gives."""
    reader = _Reader(tree)
    data = reader.scene()
    return data, list(dict.fromkeys(reader.notes))


def _num(x: float) -> float:
    """A computed number to 15 significant digits: what float64 holds of a decimal, so
    that 0.22 - 0.2 reads 0.02."""
    return float(f"{x:.15g}")


def _out(c: np.ndarray) -> float | list[float]:
    """A colour for the scene dict (to 15 digits): one number when the channels agree."""
    c = [_num(x) for x in np.asarray(c, np.float64)]
    return c[0] if c.count(c[0]) == 3 else c


def _floats(value: Any, n: int) -> np.ndarray | None:
    """``value`` (a sequence, a NumPy or Dr.Jit array) as ``n`` floats, or None."""
    if isinstance(value, (str, bytes, Mapping)):
        return None
    try:
        v = np.array([float(x) for x in value], np.float64)
    except (TypeError, ValueError):
        return None
    return v if len(v) == n else None


class _Obj:
    """One Mitsuba object (a plugin dict) being read: getters that remember which
    parameters were read, so that every other one gives a note at the end."""

    def __init__(self, reader: _Reader, node: Mapping, where: str):
        self.reader, self.node, self.where = reader, node, where
        self.type = str(node.get("type", ""))
        self.cls = PLUGIN_CLASSES.get(self.type, "object")
        self.read = {"type", "id"}

    @property
    def label(self) -> str:
        return f'{self.cls} "{self.type}" ({self.where})'

    def note(self, text: str) -> None:
        self.reader.notes.append(f"{self.label}: {text}")

    def error(self, text: str) -> SceneError:
        return SceneError(self.label, text)

    def drop(self, text: str) -> None:
        """One note for the whole element (its parameters give none)."""
        self.note(text)
        self.read.update(self.node)

    def has(self, key: str) -> bool:
        return key in self.node

    def raw(self, key: str, default: Any = None) -> Any:
        self.read.add(key)
        return self.node.get(key, default)

    def skip(self, *keys: str) -> None:
        """Parameters that do not change what clscatter renders (read without a note)."""
        self.read.update(keys)

    def number(self, key: str, default: float) -> float:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
            raise self.error(f"{key} must be a number (got {v!r})")
        return float(v)

    def integer(self, key: str, default: int) -> int:
        v = self.number(key, default)
        if v != int(v):
            raise self.error(f"{key} must be an integer (got {v:g})")
        return int(v)

    def boolean(self, key: str, default: bool) -> bool:
        v = self.raw(key, default)
        if not isinstance(v, (bool, np.bool_)):
            raise self.error(f"{key} must be true or false (got {v!r})")
        return bool(v)

    def string(self, key: str, default: str | None = None) -> str:
        v = self.raw(key, default)
        if not isinstance(v, str):
            raise self.error(f"{key} must be a string (got {v!r})" if v is not None
                             else f"{key} is missing")
        return v

    def vector(self, key: str, default: Any = None) -> np.ndarray:
        v = self.raw(key, default)
        out = _floats(v, 3)
        if out is None:
            raise self.error(f"{key} must be 3 numbers (got {v!r})")
        return out

    def transform(self, key: str = "to_world") -> Transform:
        v = self.raw(key)
        if v is None:
            return Transform(np.eye(4))
        if isinstance(v, Transform):
            return v
        m = np.asarray(getattr(v, "matrix", v), dtype=np.float64) if not isinstance(v, str) \
            else None
        if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise self.error(f"{key} must be a transform (a 4x4 matrix)")
        return Transform(m)

    def colour(self, key: str, default: float) -> np.ndarray:
        """An rgb value or a number (a texture, sampled spectrum ... gives a note)."""
        c, problem = self.reader.spectrum(self.raw(key, default))
        if problem is not None:
            if c is None:
                c = np.full(3, default)
                problem += f"; {default:g} used"
            self.note(f"{key}: {problem}")
        return c

    def children(self, cls: str) -> list[_Obj]:
        """The nested objects (or references) of a class, in order."""
        out = []
        for key, value in self.node.items():
            node = self.reader.resolve(value, self) if isinstance(value, Mapping) else None
            if node is not None and PLUGIN_CLASSES.get(node.get("type")) == cls:
                self.read.add(key)
                out.append(self.reader.obj(node, self.reader.name_of(node, f"{self.where}.{key}")))
        return out

    def child(self, key: str) -> _Obj | None:
        value = self.raw(key)
        node = self.reader.resolve(value, self) if isinstance(value, Mapping) else None
        return None if node is None else self.reader.obj(node, self.reader.name_of(
            node, f"{self.where}.{key}"))

    def one(self, cls: str) -> _Obj | None:
        """The first nested object of a class; more than one gives a note."""
        found = self.children(cls)
        for extra in found[1:]:
            extra.drop(f"{self.label} has more than one {cls}: only the first is read; dropped")
        return found[0] if found else None

    def leftovers(self) -> None:
        for key in self.node:
            if key not in self.read:
                self.read.add(key)
                value = self.node[key]
                if isinstance(value, Mapping) and "type" in value:
                    what = f'{PLUGIN_CLASSES.get(value["type"], "object")} "{value["type"]}"'
                    self.note(f"{key} ({what}) is not supported here; dropped")
                else:
                    self.note(f"parameter {key} is not supported; ignored")


class _Reader:
    """A Mitsuba-style scene dict being read into a scene dict (:func:`from_mitsuba`)."""

    def __init__(self, tree: Mapping[str, Any]):
        if not isinstance(tree, Mapping) or tree.get("type") != "scene":
            raise SceneError("type", 'a Mitsuba scene is a dict with "type": "scene"')
        self.tree = tree
        self.notes: list[str] = []
        self.ids: dict[str, Mapping] = {}
        self.objs: dict[int, _Obj] = {}
        for key, value in tree.items():
            if isinstance(value, Mapping):
                self.ids[str(value.get("id", key))] = value
                self._nested_ids(value)

    def _nested_ids(self, node: Mapping) -> None:
        for value in node.values():
            if isinstance(value, Mapping):
                if "id" in value and value.get("type") != "ref":
                    self.ids[str(value["id"])] = value
                self._nested_ids(value)

    def name_of(self, node: Mapping, where: str) -> str:
        """How notes name an object: its id, else where it sits."""
        for key, value in self.ids.items():
            if value is node:
                return key
        return where

    def resolve(self, value: Mapping, owner: _Obj) -> Mapping | None:
        if value.get("type") != "ref":
            return value if "type" in value else None
        target = self.ids.get(str(value.get("id")))
        if target is None:
            raise owner.error(f"reference to id '{value.get('id')}', which the scene does "
                              "not define")
        return target

    def obj(self, node: Mapping, where: str) -> _Obj:
        if id(node) not in self.objs:
            self.objs[id(node)] = _Obj(self, node, where)
        return self.objs[id(node)]

    # ---- values -------------------------------------------------------------------------

    def spectrum(self, value: Any) -> tuple[np.ndarray | None, str | None]:
        """(rgb, problem): the colour of a spectrum value, and a note's text where it is
        approximated or cannot be read (then rgb is None)."""
        if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
            return np.full(3, float(value)), None
        if isinstance(value, Mapping):
            kind = value.get("type")
            if kind == "ref":
                return self.spectrum(self.ids.get(str(value.get("id"))))
            if kind in ("rgb", "constvolume", "uniform") or (
                    kind == "spectrum" and not isinstance(value.get("value"), (list, tuple))):
                return self.spectrum(value.get("value"))
            if kind == "spectrum" and "filename" in value:
                return None, "a spectrum file is not read"
            if kind == "spectrum" and value.get("value"):
                values = [float(v) for _, v in value["value"]]
                mean = sum(values) / len(values)
                return np.full(3, mean), f"a sampled spectrum, approximated by its mean {mean:g}"
            return None, f'"{kind}" is not an rgb value or a number'
        v = _floats(value, 3) if _floats(value, 1) is None else np.repeat(_floats(value, 1), 3)
        if v is None:
            return None, f"{value!r} is not an rgb value or a number"
        return v, None

    # ---- the scene ----------------------------------------------------------------------

    def scene(self) -> dict:
        top = []
        for key, value in self.tree.items():
            if key == "type":
                continue
            if not isinstance(value, Mapping) or "type" not in value:
                self.notes.append(f"top-level entry '{key}' is not an object; ignored")
                continue
            cls = PLUGIN_CLASSES.get(value["type"], "object")
            if cls in ("sensor", "integrator", "emitter", "shape", "object"):
                top.append(self.obj(value, str(value.get("id", key))))
        for o in top:
            if o.cls == "object":
                o.drop("not a Mitsuba 3 plugin this reader knows; dropped")
        sensors = [o for o in top if o.cls == "sensor"]
        shape_objs = [o for o in top if o.cls == "shape"]
        camera, seed, sensor_medium = self.camera(sensors)
        render = self.render([o for o in top if o.cls == "integrator"], seed)
        emitters = [e for o in top for e in ([o] if o.cls == "emitter"
                                             else o.children("emitter") if o.cls == "shape"
                                             else [])]
        data: dict = {"camera": camera}
        lights = self.lights(emitters)
        objects, volumes, materials, medium = self.shapes(shape_objs, sensor_medium)
        if medium is not None:
            data["medium"] = medium
        data["lights"] = lights
        if materials:
            data["materials"] = materials
        data["objects"] = objects
        if volumes:
            data["volumes"] = volumes
        data["render"] = render
        for o in list(self.objs.values()):
            o.leftovers()
        return data

    # ---- camera and render settings ------------------------------------------------------

    def camera(self, sensors: list[_Obj]) -> tuple[dict, int, _Obj | None]:
        sensor = sensors[0] if sensors else self.obj({"type": "perspective"}, "default sensor")
        for extra in sensors[1:]:
            extra.drop("only the first sensor is read; dropped")
        if sensor.type == "thinlens":
            sensor.skip("aperture_radius", "focus_distance")
            sensor.note("read as a pinhole camera (perspective): the depth of field is dropped")
        elif sensor.type != "perspective":
            raise sensor.error("only perspective (and thinlens) sensors are read")
        sensor.skip("shutter_open", "shutter_close")
        tf = sensor.transform()
        m = tf.matrix
        origin, up = m[:3, 3], m[:3, 1]
        target = origin + unit(m[:3, 2])
        if tf.look_at is not None:
            origin, target, up = tf.look_at
        if float(np.dot(m[:3, 0], np.cross(m[:3, 1], m[:3, 2]))) < 0.0:
            sensor.note("to_world mirrors the image; clscatter renders it unmirrored")
        film = sensor.one("film") or self.obj({"type": "hdrfilm"}, f"{sensor.where}.film")
        width, height = self.film(film)
        fov, fov_axis = self.fov(sensor, width, height)
        near, far = sensor.number("near_clip", DEFAULT_NEAR_CLIP), sensor.number("far_clip",
                                                                                 DEFAULT_FAR_CLIP)
        if near > DEFAULT_NEAR_CLIP:
            sensor.note(f"near_clip {near:g} dropped: clscatter's view rays start at the lens")
        if far < DEFAULT_FAR_CLIP:
            sensor.note(f"far_clip {far:g} dropped: clscatter's view rays are unbounded")
        sampler = sensor.one("sampler") or self.obj({"type": "independent"},
                                                    f"{sensor.where}.sampler")
        sampler.skip("jitter", "scramble_seed")
        spp, seed = sampler.integer("sample_count", 4), sampler.integer("seed", 0)
        media = sensor.children("medium")
        camera = {"origin": [float(x) for x in origin], "target": [float(x) for x in target],
                  "up": [float(x) for x in up], "fov": fov, "fov_axis": fov_axis,
                  "resolution": [width, height], "spp": spp}
        return camera, seed, media[0] if media else None

    def film(self, film: _Obj) -> tuple[int, int]:
        if film.type != "hdrfilm":
            film.note("read as an hdrfilm (clscatter's images are linear RGB)")
        film.skip("pixel_format", "component_format", "file_format", "banner", "sample_border")
        rfilter = film.one("rfilter")
        if rfilter is not None and rfilter.type != "box":
            rfilter.drop("approximated by clscatter's box filter (a pixel's own area)")
        elif rfilter is not None:
            rfilter.skip("radius")
        return film.integer("width", 768), film.integer("height", 576)

    def fov(self, sensor: _Obj, width: int, height: int) -> tuple[float, str]:
        """(fov, "x" | "y"): Mitsuba's ``fov``/``fov_axis`` (``diagonal``, ``smaller``,
        ``larger`` converted exactly) or ``focal_length`` (a 36 x 24 mm film's diagonal)."""
        if sensor.has("fov"):
            fov, axis = sensor.number("fov", 0.0), sensor.string("fov_axis", "x").lower()
        else:
            text = str(sensor.raw("focal_length", "50mm"))
            try:
                focal = float(text.removesuffix("mm"))
            except ValueError:
                raise sensor.error(f"focal_length '{text}' is not a length in mm") from None
            fov, axis = math.degrees(2.0 * math.atan(math.hypot(36.0, 24.0) / (2.0 * focal))), \
                "diagonal"
        if axis == "smaller":
            axis = "x" if width <= height else "y"
        elif axis == "larger":
            axis = "x" if width >= height else "y"
        elif axis == "diagonal":
            half = math.tan(math.radians(fov) / 2.0) * width / math.hypot(width, height)
            fov, axis = math.degrees(2.0 * math.atan(half)), "x"
        if axis not in ("x", "y"):
            raise sensor.error(f"fov_axis '{axis}' is not x, y, diagonal, smaller or larger")
        return fov, axis

    def render(self, integrators: list[_Obj], seed: int) -> dict:
        """``render``: the seed, and ``max_depth`` = Mitsuba's ``max_depth`` - 2 (Mitsuba
        counts path segments; two of them are the camera's and the light's)."""
        out: dict = {"seed": seed}
        if not integrators:
            return out
        integ = integrators[0]
        for extra in integrators[1:]:
            extra.drop("only the first integrator is read; dropped")
        integ.skip("rr_depth", "hide_emitters")
        depth = integ.integer("max_depth", -1)
        if depth in (0, 1):
            raise integ.error(f"max_depth {depth} leaves no path with a scattering event "
                              "(single scattering needs 2)")
        reasons = []
        if integ.type not in ("volpath", "volpathmis"):
            reasons.append("read as volpath")
        if depth == -1 or depth > 2:
            reasons.append(f"max_depth {depth} also allows multiple scattering, which clscatter "
                           "leaves out (it renders single scattering)")
        if depth >= 2:
            out["max_depth"] = depth - 2
        if reasons:
            integ.note("; ".join(reasons))
        return out

    # ---- lights -------------------------------------------------------------------------

    def lights(self, emitters: list[_Obj]) -> list[dict]:
        lights, dropped = [], []
        for e in emitters:
            e.skip("sampling_weight", "medium")
            light = self.light(e)
            if light is None:
                dropped.append(e)
            else:
                lights.append(light)
        if not lights:
            if dropped:
                raise dropped[0].error("clscatter has point, spot and directional lights only, "
                                       "and the scene has no other light")
            raise SceneError("scene", "no light: clscatter needs a point, spot or directional "
                                      "emitter")
        for e in dropped:
            e.drop("clscatter has point, spot and directional lights only; dropped")
        return lights

    def light(self, e: _Obj) -> dict | None:
        if e.type == "point":
            position = e.vector("position") if e.has("position") else e.transform().matrix[:3, 3]
            return {"type": "point", "position": [float(x) for x in position],
                    "intensity": _out(e.colour("intensity", 1.0))}
        if e.type == "spot":
            tf = e.transform()
            position = tf.matrix[:3, 3]
            target = tf.look_at[1] if tf.look_at is not None else position + unit(tf.matrix[:3, 2])
            cutoff = e.number("cutoff_angle", 20.0)
            beam = e.number("beam_width", 0.75 * cutoff)
            if beam < cutoff:
                e.note(f"the soft edge between beam_width {beam:g} and cutoff_angle {cutoff:g} "
                       f"degrees (intensity falling linearly with the angle) is dropped: a hard "
                       f"cone of half-angle {cutoff:g} degrees at full intensity")
            return {"type": "spot", "position": [float(x) for x in position],
                    "target": [float(x) for x in target], "intensity": _out(e.colour("intensity", 1.0)),
                    "cutoff_angle": cutoff}
        if e.type == "directional":
            direction = e.vector("direction") if e.has("direction") else e.transform().matrix[:3, 2]
            return {"type": "directional", "direction": [float(x) for x in direction],
                    "irradiance": _out(e.colour("irradiance", 1.0))}
        return None

    # ---- shapes, materials, media --------------------------------------------------------

    def shapes(self, shape_objs: list[_Obj], sensor_medium: _Obj | None
               ) -> tuple[list[dict], list[dict], dict, dict | None]:
        """(objects, volumes, materials, medium) from the shapes and the sensor's medium."""
        solid, held = [], []      # (shape, geometry, bsdf, interior, exterior); null shapes
        for shape in shape_objs:
            geometry = self.geometry(shape)
            if geometry is None:
                continue
            bsdf = shape.one("bsdf") or self.obj({"type": "diffuse"}, f"{shape.where}.bsdf")
            interior, exterior = shape.child("interior"), shape.child("exterior")
            if self.core(bsdf).type == "null":
                if interior is not None:
                    held.append((shape, geometry, interior))
            else:
                solid.append((shape, geometry, bsdf, interior, exterior))
        medium, bounds_shape = self.scene_medium(sensor_medium, held)
        scene_g = 0.0 if medium is None else self.homogeneous(medium)[2]
        out_medium = None
        if medium is not None:
            ss, sa, g = self.homogeneous(medium)
            out_medium = {"sigma_s": _out(ss), "sigma_a": _out(sa), "g": g}
            if bounds_shape is not None:
                geo = next(geo for s, geo, _ in held if s is bounds_shape)
                out_medium["bounds"] = {"min": geo["min"], "max": geo["max"]}
        materials: dict = {}
        named: dict[str, tuple[int, int]] = {}
        objects = []
        for shape, geometry, bsdf, interior, exterior in solid:
            if exterior is not None and exterior is not medium:
                shape.note("its exterior medium is dropped: the scene medium holds outside "
                           "closed objects")
            material = self.material(bsdf, interior, scene_g)
            name = self.name_of(bsdf.node, "")
            key = (id(bsdf.node), id(interior.node) if interior is not None and
                   material.get("type") == "dielectric" else 0)
            if name and named.setdefault(name, key) == key:
                materials[name] = material
                material = name
            objects.append({**geometry, "material": material})
        volumes = [v for shape, geometry, med in held if shape is not bounds_shape
                   for v in [self.volume(shape, geometry, med, scene_g)] if v is not None]
        return objects, volumes, materials, out_medium

    def scene_medium(self, sensor_medium: _Obj | None, held: list[tuple[_Obj, dict, _Obj]]
                     ) -> tuple[_Obj | None, _Obj | None]:
        """(the scene medium, the shape bounding it): the homogeneous medium the sensor sits
        in (unbounded unless an axis-aligned null cube holds it), else the one the first
        axis-aligned null cube holds."""
        if sensor_medium is not None and sensor_medium.type != "homogeneous":
            sensor_medium = None
        for shape, geometry, med in held:
            box = shape.type == "cube" and "transform" not in geometry
            if box and med.type == "homogeneous" and sensor_medium in (None, med):
                return med, shape
        if any(med is sensor_medium for _, _, med in held):
            return None, None          # held by another shape: a volume, not everywhere
        return sensor_medium, None

    def homogeneous(self, med: _Obj) -> tuple[np.ndarray, np.ndarray, float]:
        """(sigma_s, sigma_a, g): sigma_s = albedo sigma_t scale, sigma_a = (1 - albedo)
        sigma_t scale."""
        med.skip("sample_emitters")
        sigma_t = med.colour("sigma_t", 1.0) * med.number("scale", 1.0)
        albedo = med.colour("albedo", 0.75)
        return albedo * sigma_t, (1.0 - albedo) * sigma_t, self.phase(med.one("phase"))

    def phase(self, phase: _Obj | None) -> float:
        if phase is None or phase.type == "isotropic":
            return 0.0
        if phase.type == "hg":
            return phase.number("g", 0.8)
        phase.drop("approximated by an isotropic phase function")
        return 0.0

    def volume(self, shape: _Obj, geometry: dict, med: _Obj, scene_g: float) -> dict | None:
        if med.type == "heterogeneous":
            sigma_t = med.raw("sigma_t")
            node = self.resolve(sigma_t, med) if isinstance(sigma_t, Mapping) else None
            if node is not None and node.get("type") == "gridvolume":
                return self.density_volume(shape, geometry, med, self.obj(node, self.name_of(
                    node, f"{med.where}.sigma_t")), scene_g)
            med.read.discard("sigma_t")      # a constant: the same as a homogeneous medium
        elif med.type != "homogeneous":
            med.drop("not a medium clscatter reads; dropped")
            return None
        if shape.type in ("rectangle", "disk"):
            shape.note("an open surface encloses no medium; its medium is dropped")
            return None
        ss, sa, g = self.homogeneous(med)
        self.phase_note(med, g, scene_g)
        return {**geometry, "ior": 1.0, "sigma_s": _out(ss), "sigma_a": _out(sa)}

    def density_volume(self, shape: _Obj, geometry: dict, med: _Obj, grid: _Obj,
                       scene_g: float) -> dict:
        """A ``density`` volume: sigma_s and sigma_a per unit density are albedo scale and
        (1 - albedo) scale; the bounds are the grid's unit cube under its to_world."""
        m = grid.transform().matrix
        if np.count_nonzero(np.abs(m[:3, :3]) > 1e-12 * np.abs(m[:3, :3]).max()) != 3:
            raise grid.error("to_world rotates the grid; a density volume is an axis-aligned box")
        corners = [m[:3, :3] @ c + m[:3, 3] for c in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))]
        lo, hi = np.minimum(*corners), np.maximum(*corners)
        filename = grid.string("filename")
        scale = med.number("scale", 1.0)
        albedo = med.colour("albedo", 0.75)
        med.skip("sample_emitters", "has_spectral_extinction")
        g = self.phase(med.one("phase"))
        self.phase_note(med, g, scene_g)
        held = (np.array(geometry["min"]), np.array(geometry["max"])) if (
            geometry.get("shape") == "box" and "transform" not in geometry) else None
        if held is None or not (np.allclose(held[0], lo) and np.allclose(held[1], hi)):
            shape.note("the density grid's box is the volume's bounds; where this shape clips "
                       "it or reaches beyond it, the shape is dropped")
        return {"density": filename, "bounds": {"min": lo.tolist(), "max": hi.tolist()},
                "sigma_s": _out(albedo * scale), "sigma_a": _out((1.0 - albedo) * scale)}

    def phase_note(self, med: _Obj, g: float, scene_g: float) -> None:
        if g != scene_g:
            med.note(f"its phase g = {g:g} is approximated by the scene medium's g = {scene_g:g} "
                     "(a volume has the scene medium's phase function)")

    def core(self, bsdf: _Obj) -> _Obj:
        """The BSDF inside ``twosided`` (clscatter's surfaces are two-sided) and other
        wrappers (mask, bump and normal maps: noted)."""
        while bsdf.type in ("twosided", "mask", "bumpmap", "normalmap"):
            inner = bsdf.children("bsdf")
            if not inner:
                raise bsdf.error("holds no BSDF")
            if bsdf.type != "twosided":
                bsdf.drop("approximated by the BSDF inside it")
            elif len(inner) > 1:
                inner[1].drop("the back side's BSDF is dropped: the front one is used on both "
                              "sides")
            bsdf = inner[0]
        return bsdf

    def material(self, bsdf: _Obj, interior: _Obj | None, scene_g: float) -> dict:
        core = self.core(bsdf)
        table = self.bsdf_table(core)
        if table["type"] == "dielectric" and interior is not None:
            if interior.type != "homogeneous":
                interior.drop("only a homogeneous medium is read inside glass; dropped")
            else:
                ss, sa, g = self.homogeneous(interior)
                table.update(interior_sigma_s=_out(ss), interior_sigma_a=_out(sa))
                if g != scene_g:
                    table["interior_g"] = g
        return table

    def bsdf_table(self, core: _Obj) -> dict:
        t = core.type
        if t == "diffuse":
            albedo = core.colour("reflectance", 0.5)
            return {"type": "black"} if not np.any(albedo) else {"type": "diffuse",
                                                                  "albedo": _out(albedo)}
        if t == "dielectric":
            for key in ("specular_reflectance", "specular_transmittance"):
                if core.has(key) and np.any(core.colour(key, 1.0) != 1.0):
                    core.note(f"{key} dropped (clscatter's glass has Fresnel weights alone)")
            return {"type": "dielectric", "ior": _num(self.ior(core, "int_ior", "bk7")
                                                      / self.ior(core, "ext_ior", "air"))}
        if t in ("conductor", "roughconductor"):
            if t == "roughconductor":
                core.skip("distribution", "sample_visible")
                keys = ("alpha_u", "alpha_v") if core.has("alpha_u") else ("alpha",)
                if any(core.number(k, 0.1) > 0.0 for k in keys):
                    raise core.error("a rough conductor (alpha > 0): clscatter's mirrors are "
                                     "smooth")
            return {"type": "mirror", "reflectance": _out(self.conductor(core))}
        if t in ("roughdielectric", "thindielectric"):
            raise core.error("clscatter's glass is smooth and closed (dielectric); this one "
                             "would change the scene")
        colour = next((core.colour(k, 0.5) for k in ("diffuse_reflectance", "base_color",
                                                     "reflectance") if core.has(k)),
                      np.full(3, 0.5))
        core.drop(f"approximated by a diffuse material of albedo {_out(colour)}")
        return {"type": "diffuse", "albedo": _out(colour)}

    def ior(self, core: _Obj, key: str, default: str) -> float:
        v = core.raw(key, default)
        if isinstance(v, str):
            if v.lower() not in IOR_NAMES:
                raise core.error(f"{key} '{v}' is not an index of refraction Mitsuba names")
            return IOR_NAMES[v.lower()]
        return core.number(key, 0.0)

    def conductor(self, core: _Obj) -> np.ndarray:
        """The mirror's reflectance: ``specular_reflectance``, times the Fresnel reflectance
        at normal incidence where eta and k are given (noted: its rise towards grazing
        angles is dropped); a named metal's colour is dropped (noted)."""
        refl = core.colour("specular_reflectance", 1.0)
        material = str(core.raw("material", "none"))
        if core.has("eta") or core.has("k"):
            eta, k = core.colour("eta", 0.0), core.colour("k", 1.0)
            refl = refl * ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
            core.note("its Fresnel reflectance is taken at normal incidence for every angle")
        elif material != "none":
            core.note(f"the colour of metal '{material}' is dropped: a mirror of reflectance "
                      "specular_reflectance")
        return refl

    # ---- geometry -----------------------------------------------------------------------

    def geometry(self, shape: _Obj) -> dict | None:
        """The object keys (shape and its keys, transform) of a shape, or None (dropped)."""
        if shape.boolean("flip_normals", False):
            shape.note("flip_normals dropped: clscatter's surfaces are two-sided and a closed "
                       "object's inside is its enclosed volume")
        m = shape.transform().matrix
        t = shape.type
        if t in ("obj", "ply"):
            shape.skip("flip_tex_coords")
            return {"shape": "mesh", "file": shape.string("filename"),
                    "smooth": not shape.boolean("face_normals", False), **_trs(m, shape)}
        if t == "sphere":
            center = m[:3, :3] @ shape.vector("center", (0.0, 0.0, 0.0)) + m[:3, 3]
            scale = _similarity(m, shape)
            return {"shape": "sphere", "center": center.tolist(),
                    "radius": _num(scale * shape.number("radius", 1.0))}
        if t == "cube":
            a = m[:3, :3]
            if np.count_nonzero(np.abs(a) > 1e-12 * np.abs(a).max()) == 3:   # axis-aligned
                half = np.abs(a).sum(axis=1)
                return {"shape": "box", "min": (m[:3, 3] - half).tolist(),
                        "max": (m[:3, 3] + half).tolist()}
            return {"shape": "box", "min": [-1.0] * 3, "max": [1.0] * 3, **_trs(m, shape)}
        if t == "rectangle":
            return {"shape": "quad", "origin": (m[:3, 3] - m[:3, 0] - m[:3, 1]).tolist(),
                    "edge_u": (2.0 * m[:3, 0]).tolist(), "edge_v": (2.0 * m[:3, 1]).tolist()}
        if t == "disk":
            return {"shape": "mesh", "file": str(DISK_MESH), **_trs(m, shape)}
        shape.drop("not a shape clscatter reads; dropped")
        return None


def _similarity(m: np.ndarray, shape: _Obj) -> float:
    """The scale of a to_world without shear or non-uniform scale (a sphere's)."""
    a = m[:3, :3]
    s = float(abs(np.linalg.det(a))) ** (1.0 / 3.0)
    if s == 0.0 or not np.allclose(a.T @ a, s * s * np.eye(3), rtol=1e-6, atol=1e-9 * s * s):
        raise shape.error("to_world scales the sphere non-uniformly (Mitsuba's sphere "
                          "allows no such scale)")
    return s


def _trs(m: np.ndarray, shape: _Obj) -> dict:
    """``{"transform": {translate, rotate, scale}}`` (M = T R S, the scene format's) for
    the affine ``m``, empty for the identity; SceneError for a shear."""
    a = m[:3, :3]
    scale = np.linalg.norm(a, axis=0)
    if np.any(scale == 0.0):
        raise shape.error("to_world collapses the shape (a zero scale)")
    r = a / scale
    if np.linalg.det(r) < 0.0:
        scale[0], r[:, 0] = -scale[0], -r[:, 0]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6):
        raise shape.error("to_world shears the shape; the scene format's transform is a scale, "
                          "a rotation and a translation")
    axis, angle = _axis_angle(r)
    out: dict = {}
    if np.any(m[:3, 3]):
        out["translate"] = m[:3, 3].tolist()
    if angle != 0.0:
        out["rotate"] = [*axis, angle]
    if np.any(scale != 1.0):
        out["scale"] = float(scale[0]) if np.all(scale == scale[0]) else scale.tolist()
    return {"transform": out} if out else {}


def _axis_angle(r: np.ndarray) -> tuple[list[float], float]:
    """Axis (unit) and angle (degrees) of a rotation matrix, via its quaternion (stable at
    every angle)."""
    tr = float(np.trace(r))
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 0.0))
        v = [0.0, 0.0, 0.0]
        v[i], v[j], v[k] = 0.25 * s, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
        q = ((r[k, j] - r[j, k]) / s, *v)
    w, xyz = q[0], np.array(q[1:])
    n = float(np.linalg.norm(xyz))
    if n < 1e-15:
        return [0.0, 1.0, 0.0], 0.0
    return (xyz / n).tolist(), math.degrees(2.0 * math.atan2(n, w))
