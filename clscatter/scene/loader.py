"""TOML scene loader: file or built-in scene + ``--set`` overrides -> validated :class:`Scene`.

The format is ``docs/scene_format.md`` (the contract). Everything is checked here, once:
unknown keys and tables at any level, types, vector/colour lengths, value ranges and
cross-key constraints. Every failure is a :class:`SceneError` whose ``key`` is the full
dotted path (``lights[1].cutoff_angle``, ``render.lsg.radius``, ``objects[0].file``) and
whose message is one line.

Defaults (where the contract gives none, chosen here):

==========================  ======================================================
camera                      up [0, 1, 0], fov 45, fov_axis "x", resolution
                            [512, 384], spp 4; origin and target are required
medium                      sigma_s 0, sigma_a 0, g 0, bounds absent (unbounded)
lights                      every key the contract shows is required (point:
                            position, intensity; spot: + target, cutoff_angle;
                            directional: direction, irradiance)
materials                   type required; diffuse albedo 0.5, mirror reflectance
                            1.0, dielectric ior 1.5, interior_sigma_a/s 0
objects                     shape and material required; shape keys required;
                            transform translate 0, rotate [0, 1, 0, 0], scale 1
volumes                     ior required (shapes), sigma_s 0, sigma_a 0, resolution 128;
                            bounds required for a .npy index or density grid, else
                            from the density file (.vdb transform, .vol box);
                            density_grid "density" (files: ``grids.py``)
render                      method "auto", max_depth 16, seed 0, time_budget absent
                            (auto: 10 s, others none; 0: none), target_error 0
                            (none); ``[render.<m>]``
                            tables are kept raw (clscatter.methods.configure
                            checks them against each method's declared PARAMS)
==========================  ======================================================

Extensions (keys not in the contract, documented here): ``subdivisions`` on spheres
(icosphere levels, 0..7, default 4 = 5120 triangles), and ``smooth`` (bool, default
false: per-vertex normals from the file or area-weighted, for smooth shading) and
``close_holes`` (bool, default false: the holes of an open surface triangulated) on meshes.
"""
from __future__ import annotations

import copy
import difflib
import math
import os
import re
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from ..errors import SceneError
from ..geometry import unit
from . import grids, shapes
from .model import (
    Camera,
    Light,
    Material,
    Medium,
    Object,
    RenderSettings,
    Scene,
    Volume,
)

_REQUIRED = object()

TOP_KEYS = ("camera", "medium", "lights", "materials", "objects", "volumes", "render")
CAMERA_KEYS = ("origin", "target", "up", "fov", "fov_axis", "resolution", "spp")
MEDIUM_KEYS = ("sigma_s", "sigma_a", "g", "bounds")
LIGHT_KEYS = {
    "point": ("type", "position", "intensity"),
    "spot": ("type", "position", "target", "intensity", "cutoff_angle"),
    "directional": ("type", "direction", "irradiance"),
}
MATERIAL_KEYS = {
    "diffuse": ("type", "albedo"),
    "mirror": ("type", "reflectance"),
    "dielectric": ("type", "ior", "interior_sigma_a", "interior_sigma_s", "interior_g"),
    "black": ("type",),
}
SHAPE_KEYS = {
    "mesh": ("file", "smooth", "close_holes"),
    "sphere": ("center", "radius", "subdivisions"),
    "box": ("min", "max"),
    "quad": ("origin", "edge_u", "edge_v"),
}
TRANSFORM_KEYS = ("translate", "rotate", "scale")
VOLUME_KEYS = ("ior", "sigma_s", "sigma_a", "resolution")
VOLUME_GRID_KEYS = ("grid", "bounds", "sigma_s", "sigma_a", "sigma_s_grid", "sigma_a_grid")
VOLUME_DENSITY_KEYS = ("density", "density_grid", "grid", "bounds", "sigma_s", "sigma_a")
RENDER_KEYS = ("method", "max_depth", "seed", "time_budget", "target_error")

# a --set value that is not TOML but looks like one word is taken as a string
_BARE_WORD = re.compile(r"[^\s\"'\[\]{}=,#]+")


# ---- Small helpers ----------------------------------------------------------------------

def _err(key: str, message: object) -> SceneError:
    """A SceneError whose message is guaranteed to be one line."""
    return SceneError(key, " ".join(str(message).split()))


def _tname(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "a table"
    return type(value).__name__


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _fmt(x: float) -> str:
    return f"{x:g}"


def _unknown_key_message(name: str, allowed: Iterable[str], context: str) -> str:
    allowed = list(allowed)
    msg = f"unknown key{context}"
    close = difflib.get_close_matches(name, allowed, n=1)
    if close:
        msg += f" (did you mean '{close[0]}'?)"
    if allowed:
        msg += f"; allowed: {', '.join(allowed)}"
    return msg


class _Table:
    """A TOML table being read: typed accessors that name the full dotted key on error."""

    def __init__(self, data: Any, key: str):
        if not isinstance(data, dict):
            raise _err(key, f"expected a table, got {_tname(data)}")
        self.data = data
        self.key = key

    def k(self, name: str) -> str:
        return f"{self.key}.{name}" if self.key else name

    def has(self, name: str) -> bool:
        return name in self.data

    def allow(self, names: Iterable[str], context: str = "") -> None:
        names = tuple(names)
        for name in self.data:
            if name not in names:
                raise _err(self.k(name), _unknown_key_message(name, names, context))

    def raw(self, name: str, default: Any = _REQUIRED) -> Any:
        if name in self.data:
            return self.data[name]
        if default is _REQUIRED:
            raise _err(self.k(name), "missing required key")
        return default

    def table(self, name: str, default: Any = _REQUIRED) -> "_Table":
        return _Table(self.raw(name, default), self.k(name))

    def number(self, name: str, default: Any = _REQUIRED, *, lo: float | None = None,
               lo_open: bool = False, hi: float | None = None, hi_open: bool = False) -> float:
        if name not in self.data and default is not _REQUIRED:
            return default
        return _check_number(self.raw(name), self.k(name), lo, lo_open, hi, hi_open)

    def integer(self, name: str, default: Any = _REQUIRED, *, lo: int | None = None,
                hi: int | None = None) -> int:
        if name not in self.data and default is not _REQUIRED:
            return default
        v = self.raw(name)
        if not isinstance(v, int) or isinstance(v, bool):
            raise _err(self.k(name), f"expected an integer, got {_tname(v)}")
        if lo is not None and v < lo:
            raise _err(self.k(name), f"must be >= {lo} (got {v})")
        if hi is not None and v > hi:
            raise _err(self.k(name), f"must be <= {hi} (got {v})")
        return int(v)

    def boolean(self, name: str, default: Any = _REQUIRED) -> bool:
        v = self.raw(name, default)
        if not isinstance(v, bool):
            raise _err(self.k(name), f"expected true or false, got {_tname(v)}")
        return v

    def string(self, name: str, default: Any = _REQUIRED) -> str:
        v = self.raw(name, default)
        if not isinstance(v, str):
            raise _err(self.k(name), f"expected a string, got {_tname(v)}")
        return v

    def choice(self, name: str, options: Sequence[str], default: Any = _REQUIRED) -> str:
        v = self.string(name, default)
        if v not in options:
            raise _err(self.k(name), f"unknown {name} '{v}' (one of {', '.join(options)})")
        return v

    def vec3(self, name: str, default: Any = _REQUIRED, *, nonzero: bool = False) -> np.ndarray:
        if name not in self.data and default is not _REQUIRED:
            return np.array(default, dtype=np.float64)
        v = _check_vector(self.raw(name), self.k(name), 3)
        if nonzero and not np.any(v):
            raise _err(self.k(name), "must not be the zero vector")
        return v

    def colour(self, name: str, default: Any = _REQUIRED) -> np.ndarray:
        """A non-negative colour: one number (all three channels) or [r, g, b]."""
        if name not in self.data and default is not _REQUIRED:
            return np.broadcast_to(np.asarray(default, dtype=np.float64), (3,)).copy()
        v = self.raw(name)
        key = self.k(name)
        if _is_number(v):
            c = np.full(3, _check_number(v, key, None, False, None, False))
        elif isinstance(v, list):
            c = _check_vector(v, key, 3, what="colour")
        else:
            raise _err(key, f"expected a number or [r, g, b], got {_tname(v)}")
        if np.any(c < 0.0):
            raise _err(key, f"must be non-negative (got {_fmt_vec(c)})")
        return c


def _fmt_vec(v: np.ndarray) -> str:
    return "[" + ", ".join(_fmt(float(x)) for x in v) + "]"


FLOAT32_MAX = float(np.finfo(np.float32).max)   # larger scene numbers are refused


def _check_number(v: Any, key: str, lo: float | None, lo_open: bool, hi: float | None,
                  hi_open: bool) -> float:
    if not _is_number(v):
        raise _err(key, f"expected a number, got {_tname(v)}")
    x = float(v)
    if not math.isfinite(x):
        raise _err(key, f"must be finite (got {v})")
    if abs(x) > FLOAT32_MAX:
        raise _err(key, f"{_fmt(x)} is beyond float32's range (+-3.4e38), in which the "
                        "device computes")
    bad = ((lo is not None and (x <= lo if lo_open else x < lo))
           or (hi is not None and (x >= hi if hi_open else x > hi)))
    if bad:
        left = "-inf" if lo is None else _fmt(lo)
        right = "inf" if hi is None else _fmt(hi)
        interval = (("(" if lo_open or lo is None else "[") + f"{left}, {right}"
                    + (")" if hi_open or hi is None else "]"))
        raise _err(key, f"must be in {interval} (got {_fmt(x)})")
    return x


def _check_vector(v: Any, key: str, n: int, what: str = "vector") -> np.ndarray:
    if not isinstance(v, list) or len(v) != n or not all(_is_number(x) for x in v):
        got = f"an array of length {len(v)}" if isinstance(v, list) else _tname(v)
        if isinstance(v, list) and len(v) == n:
            got = "an array with non-numbers"
        raise _err(key, f"expected a {what} of {n} numbers, got {got}")
    a = np.array([float(x) for x in v], dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise _err(key, "must be finite")
    if np.any(np.abs(a) > FLOAT32_MAX):
        raise _err(key, f"{_fmt_vec(a)} is beyond float32's range (+-3.4e38), in which the "
                        "device computes")
    return a


def _array_of_tables(root: _Table, name: str) -> list[tuple[str, _Table]]:
    v = root.raw(name, [])
    if not isinstance(v, list):
        raise _err(root.k(name), f"expected an array of tables ([[{name}]]), got {_tname(v)}")
    return [(f"{root.k(name)}[{i}]", _Table(t, f"{root.k(name)}[{i}]")) for i, t in enumerate(v)]


# ---- Sections ---------------------------------------------------------------------------

def _camera(t: _Table) -> Camera:
    t.allow(CAMERA_KEYS)
    origin = t.vec3("origin")
    target = t.vec3("target")
    up = t.vec3("up", (0.0, 1.0, 0.0), nonzero=True)
    fov = t.number("fov", 45.0, lo=0.0, lo_open=True, hi=180.0, hi_open=True)
    fov_axis = t.choice("fov_axis", ("x", "y"), "x")
    width, height = 512, 384
    if t.has("resolution"):
        r = t.raw("resolution")
        if (not isinstance(r, list) or len(r) != 2
                or not all(isinstance(x, int) and not isinstance(x, bool) for x in r)):
            raise _err(t.k("resolution"), f"expected [width, height] (2 integers), got "
                       f"{_tname(r) if not isinstance(r, list) else 'an array of ' + str(len(r))}")
        if r[0] <= 0 or r[1] <= 0:
            raise _err(t.k("resolution"), f"width and height must be > 0 (got {r})")
        width, height = int(r[0]), int(r[1])
    spp = t.integer("spp", 4, lo=1)
    view = target - origin
    if not np.any(view):
        raise _err(t.k("target"), "camera target equals its origin (no view direction)")
    if np.linalg.norm(np.cross(unit(view), unit(up))) < 1e-6:
        raise _err(t.k("up"), "up is parallel to the view direction (target - origin)")
    return Camera(origin=origin, target=target, up=up, fov=fov, fov_axis=fov_axis,
                  width=width, height=height, spp=spp)


def _bounds(t: _Table) -> tuple[np.ndarray, np.ndarray]:
    t.allow(("min", "max"))
    lo = t.vec3("min")
    hi = t.vec3("max")
    if np.any(lo >= hi):
        raise _err(t.key, f"min must be < max on every axis (min {_fmt_vec(lo)}, "
                   f"max {_fmt_vec(hi)})")
    return lo, hi


def _medium(t: _Table) -> Medium:
    t.allow(MEDIUM_KEYS)
    sigma_s = t.colour("sigma_s", 0.0)
    sigma_a = t.colour("sigma_a", 0.0)
    g = t.number("g", 0.0, lo=-1.0, lo_open=True, hi=1.0, hi_open=True)
    bounds = _bounds(t.table("bounds")) if t.has("bounds") else None
    return Medium(sigma_s=sigma_s, sigma_a=sigma_a, g=g, bounds=bounds)


def _light(t: _Table) -> Light:
    kind = t.choice("type", tuple(LIGHT_KEYS))
    t.allow(LIGHT_KEYS[kind], f" for a {kind} light")
    if kind == "point":
        return Light(type=kind, power=t.colour("intensity"), position=t.vec3("position"))
    if kind == "spot":
        position = t.vec3("position")
        target = t.vec3("target")
        if not np.any(target - position):
            raise _err(t.k("target"), "spot light target equals its position (no direction)")
        cutoff = t.number("cutoff_angle", lo=0.0, lo_open=True, hi=90.0)
        return Light(type=kind, power=t.colour("intensity"), position=position,
                     direction=unit(target - position), cutoff_angle=cutoff)
    direction = t.vec3("direction", nonzero=True)
    return Light(type=kind, power=t.colour("irradiance"), direction=unit(direction))


def _material(t: _Table, name: str) -> Material:
    kind = t.choice("type", tuple(MATERIAL_KEYS))
    t.allow(MATERIAL_KEYS[kind], f" for a {kind} material")
    m = Material(name=name, type=kind, key=t.key)
    if kind == "diffuse":
        m.albedo = t.colour("albedo", 0.5)
    elif kind == "mirror":
        m.reflectance = t.colour("reflectance", 1.0)
    elif kind == "dielectric":
        m.ior = t.number("ior", 1.5, lo=0.0, lo_open=True)
        m.interior_sigma_a = t.colour("interior_sigma_a", 0.0)
        m.interior_sigma_s = t.colour("interior_sigma_s", 0.0)
        if t.has("interior_g"):
            m.interior_g = t.number("interior_g", lo=-1.0, lo_open=True, hi=1.0, hi_open=True)
    return m


def _materials(root: _Table) -> dict[str, Material]:
    if not root.has("materials"):
        return {}
    t = root.table("materials")
    return {name: _material(t.table(name), name) for name in t.data}


def _transform(t: _Table) -> np.ndarray:
    t.allow(TRANSFORM_KEYS)
    translate = t.vec3("translate", (0.0, 0.0, 0.0))
    rotate = (0.0, 1.0, 0.0, 0.0)
    if t.has("rotate"):
        r = t.raw("rotate")
        rotate = tuple(_check_vector(r, t.k("rotate"), 4, what="[axis x, y, z, degrees] list"))
        if rotate[3] != 0.0 and not any(rotate[:3]):
            raise _err(t.k("rotate"), "rotation axis must not be the zero vector")
    scale = np.ones(3)
    if t.has("scale"):
        s = t.raw("scale")
        if _is_number(s):
            scale = np.full(3, _check_number(s, t.k("scale"), None, False, None, False))
        else:
            scale = _check_vector(s, t.k("scale"), 3, what="scale (a number or [sx, sy, sz])")
        if np.any(scale == 0.0):
            raise _err(t.k("scale"), "scale must not be zero on any axis (degenerate shape)")
    return shapes.transform_matrix(translate, rotate, scale)


def _shape_geometry(t: _Table, shape: str, base_dir: Path) -> shapes.Mesh:
    """Triangulate the shape described by ``t`` (keys already checked) and transform it."""
    if shape == "mesh":
        file = t.string("file")
        smooth = t.boolean("smooth", False)
        mesh = shapes.load_mesh(base_dir / file, t.k("file"), smooth,
                                t.boolean("close_holes", False))
    elif shape == "sphere":
        center = t.vec3("center")
        radius = t.number("radius", lo=0.0, lo_open=True)
        subdivisions = t.integer("subdivisions", 4, lo=0, hi=7)
        mesh = shapes.sphere(center, radius, subdivisions)
    elif shape == "box":
        lo, hi = t.vec3("min"), t.vec3("max")
        if np.any(lo >= hi):
            raise _err(t.k("max"), f"box min must be < max on every axis (min {_fmt_vec(lo)}, "
                       f"max {_fmt_vec(hi)})")
        mesh = shapes.box(lo, hi)
    else:  # quad
        origin, eu, ev = t.vec3("origin"), t.vec3("edge_u"), t.vec3("edge_v")
        area = float(np.linalg.norm(np.cross(eu, ev)))
        if area <= 1e-12 * float(np.linalg.norm(eu) * np.linalg.norm(ev)):
            raise _err(t.k("edge_v"), "quad has zero area (edge_u and edge_v are zero or parallel)")
        mesh = shapes.quad(origin, eu, ev)
    if t.has("transform"):
        mesh = shapes.apply_transform(*mesh, _transform(t.table("transform")))
    return mesh


def _object(t: _Table, materials: dict[str, Material], base_dir: Path) -> Object:
    shape = t.choice("shape", tuple(SHAPE_KEYS))
    t.allow(("shape", "material", "transform", *SHAPE_KEYS[shape]), f" for a {shape}")
    m = t.raw("material")
    if isinstance(m, str):
        if m not in materials:
            known = ", ".join(materials) if materials else "none defined"
            raise _err(t.k("material"), f"unknown material '{m}' (in [materials]: {known})")
        material = materials[m]
    elif isinstance(m, dict):
        material = _material(t.table("material"), t.k("material"))
    else:
        raise _err(t.k("material"), f"expected a material name or an inline table, got {_tname(m)}")
    v, f, n = _shape_geometry(t, shape, base_dir)
    f, dropped = shapes.drop_degenerate(v, f)
    if len(f) == 0:
        raise _err(t.k("file") if shape == "mesh" else t.key,
                   "every triangle of this object has zero area")
    return Object(shape=shape, material=material, vertices=v, faces=f, normals=n, key=t.key,
                  dropped_triangles=dropped)


#: host bytes a scene triangle costs while a render runs (loader arrays, BVH build, the
#: device's copies): a scene whose triangles would need more than the machine's memory
#: is refused before it is built
BYTES_PER_TRIANGLE = 512
SHAPE_TRIANGLES = {"box": 12, "quad": 2}


def _max_triangles() -> int:
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        memory = 1 << 40
    return int(memory // BYTES_PER_TRIANGLE)


def _objects(root: _Table, materials: dict[str, Material], base_dir: Path) -> list[Object]:
    """Every ``[[objects]]`` entry, built in order. The triangles of spheres, boxes and
    quads are counted from the keys first, so a scene with more than the machine's memory
    holds (:data:`BYTES_PER_TRIANGLE`) is refused before any of them is built, naming the
    object that crosses the limit; meshes are counted as they load."""
    tables = [t for _, t in _array_of_tables(root, "objects")]
    limit, total = _max_triangles(), 0
    for t in tables:
        shape = t.data.get("shape") if isinstance(t.data, dict) else None
        sub = t.data.get("subdivisions", 4) if shape == "sphere" else None
        if shape == "sphere" and isinstance(sub, int) and 0 <= sub <= 7:
            total += 20 * 4 ** sub
        else:
            total += SHAPE_TRIANGLES.get(shape, 0)
        if total > limit:
            key = t.k("subdivisions") if shape == "sphere" else t.key
            raise _err(key, f"the scene's objects up to here have {total:,} triangles, more "
                       f"than this machine's memory holds for a render (about {limit:,}); "
                       "use fewer or coarser objects")
    objects = []
    for t in tables:
        obj = _object(t, materials, base_dir)
        if obj.shape == "mesh":
            total += len(obj.faces)
            if total > limit:
                raise _err(t.k("file"), f"the scene's objects up to here have {total:,} "
                           f"triangles, more than this machine's memory holds for a render "
                           f"(about {limit:,})")
        objects.append(obj)
    return objects


def _volume(t: _Table, base_dir: Path) -> Volume:
    sigma_s = t.colour("sigma_s", 0.0)
    sigma_a = t.colour("sigma_a", 0.0)
    if t.has("density"):
        return _density_volume(t, base_dir, sigma_s, sigma_a)
    if t.has("grid"):
        t.allow(VOLUME_GRID_KEYS, " for a grid volume (the grid holds the index of refraction)")
        grid = grids.load_grid(base_dir / t.string("grid"), t.k("grid"))
        bounds = _bounds(t.table("bounds"))
        per_voxel = {}
        for name in ("sigma_s_grid", "sigma_a_grid"):
            if t.has(name):
                g = grids.load_grid(base_dir / t.string(name), t.k(name), positive=False)
                if g.shape != grid.shape:
                    raise _err(t.k(name), f"shape {g.shape} differs from grid's {grid.shape}")
                per_voxel[name] = g
        return Volume(ior=float(grid.max()), sigma_s=sigma_s, sigma_a=sigma_a,
                      resolution=int(max(grid.shape)), grid=grid, grid_bounds=bounds, key=t.key,
                      **per_voxel)
    if not t.has("shape"):
        raise _err(t.k("shape"), "missing required key (a volume needs a shape, a grid or a "
                                 "density)")
    if t.raw("shape") == "quad":
        raise _err(t.k("shape"), "a quad encloses nothing: a volume needs a closed shape "
                                 "(mesh, sphere, box) or a grid")
    shape = t.choice("shape", ("mesh", "sphere", "box"))
    t.allow(("shape", "transform", *VOLUME_KEYS, *SHAPE_KEYS[shape]), f" for a {shape} volume")
    ior = t.number("ior", lo=0.0, lo_open=True)
    resolution = t.integer("resolution", 128, lo=1)
    v, f, n = _shape_geometry(t, shape, base_dir)
    material = Material(name=t.key, type="dielectric", ior=ior,
                        interior_sigma_a=sigma_a.copy(), interior_sigma_s=sigma_s.copy())
    mesh = Object(shape=shape, material=material, vertices=v, faces=f, normals=n, key=t.key)
    return Volume(ior=ior, sigma_s=sigma_s, sigma_a=sigma_a, resolution=resolution,
                  mesh=mesh, key=t.key)


def _density_volume(t: _Table, base_dir: Path, sigma_s: np.ndarray,
                    sigma_a: np.ndarray) -> Volume:
    """A heterogeneous medium: ``density`` (.npy, .vdb, .vol), optionally with an index
    ``grid``. Its box is ``bounds`` when given, else where the density file places it
    (.vdb transform, .vol box); a .npy density or an index grid needs ``bounds``."""
    t.allow(VOLUME_DENSITY_KEYS, " for a density volume")
    name = t.string("density_grid") if t.has("density_grid") else None
    dens = grids.load_density(base_dir / t.string("density"), t.k("density"), name,
                              t.k("density_grid"), placed=t.has("bounds"))
    bounds = _bounds(t.table("bounds")) if t.has("bounds") else dens.bounds
    if bounds is None or (t.has("grid") and not t.has("bounds")):
        why = "an index grid" if t.has("grid") else "a .npy density"
        raise _err(t.k("bounds"), f"missing required key ({why} carries no placement)")
    grid, ior = None, 1.0
    if t.has("grid"):
        grid = grids.load_grid(base_dir / t.string("grid"), t.k("grid"))
        ior = float(grid.max())
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)
            and np.all(np.abs(np.concatenate([lo, hi])) <= FLOAT32_MAX)):
        raise _err(t.k("density"), f"the file places the grid in an empty or unbounded box "
                   f"(min {_fmt_vec(lo)}, max {_fmt_vec(hi)}); give bounds")
    if dens.colour is not None:          # a three-channel .vol: density x colour
        sigma_s, sigma_a = sigma_s * dens.colour, sigma_a * dens.colour
    shapes_ = [dens.values.shape] + ([grid.shape] if grid is not None else [])
    return Volume(ior=ior, sigma_s=sigma_s, sigma_a=sigma_a,
                  resolution=int(max(max(s) for s in shapes_)), grid=grid,
                  grid_bounds=(lo, hi), key=t.key, density=dens.values)


def _render(root: _Table) -> RenderSettings:
    """``[render]``: its own keys, and one raw table per method. The scene knows no
    method: the names and the tables are checked against the registry of methods before
    any device work (:func:`clscatter.methods.configure_scene`)."""
    t = root.table("render", {})
    for name, value in t.data.items():
        if name not in RENDER_KEYS and not isinstance(value, dict):
            raise _err(t.k(name), _unknown_key_message(name, RENDER_KEYS, "") +
                       " (or a [render.<method>] table)")
    method = t.string("method", "auto")
    max_depth = t.integer("max_depth", 16, lo=0)
    seed = t.integer("seed", 0, lo=0)
    time_budget = t.number("time_budget", None, lo=0.0)
    target_error = t.number("target_error", 0.0, lo=0.0)
    # method tables stay raw: clscatter.methods.configure checks them before any device work
    params = {m: copy.deepcopy(v) for m, v in t.data.items() if m not in RENDER_KEYS}
    return RenderSettings(method=method, max_depth=max_depth, seed=seed,
                          time_budget=time_budget, target_error=target_error, params=params)


# ---- Public API -------------------------------------------------------------------------

def scene_from_dict(data: dict, base_dir: Path | str = ".", source: str = "<memory>") -> Scene:
    """Validate a parsed scene (TOML schema of docs/scene_format.md) and build the :class:`Scene`.

    ``base_dir`` is the folder relative file paths (meshes, grids) are resolved against.
    Raises :class:`SceneError` naming the dotted key of the first problem found.
    """
    base_dir = Path(base_dir)
    root = _Table(data, "")
    root.allow(TOP_KEYS)
    camera = _camera(root.table("camera"))
    medium = _medium(root.table("medium")) if root.has("medium") else None
    lights = [_light(t) for _, t in _array_of_tables(root, "lights")]
    for i, light in enumerate(lights):
        if light.type == "directional" and medium is not None and medium.bounds is None:
            raise _err(f"lights[{i}].type", "a directional light needs a bounded medium: "
                       "give medium.bounds (an unbounded medium would scatter infinitely much)")
    materials = _materials(root)
    objects = _objects(root, materials, base_dir)
    volumes = [_volume(t, base_dir) for _, t in _array_of_tables(root, "volumes")]
    dense = [v for v in volumes if v.density is not None]
    if len(dense) > grids.MAX_DENSITY_VOLUMES:
        raise _err(f"{dense[grids.MAX_DENSITY_VOLUMES].key}.density", f"at most "
                   f"{grids.MAX_DENSITY_VOLUMES} density volumes per scene (merge their grids)")
    render = _render(root)
    return Scene(camera=camera, medium=medium, lights=lights, materials=materials,
                 objects=objects, volumes=volumes, render=render, source=source)


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split one ``--set key=value`` into path tokens and the parsed TOML value.

    ``lights[0].intensity`` and ``lights.0.intensity`` both give ``['lights', '0',
    'intensity']``; a value that is not valid TOML but is one bare word is a string.
    """
    if "=" not in text:
        raise _err(text.strip() or "--set", "an override must look like key=value")
    path, _, value = text.partition("=")
    path, value = path.strip(), value.strip()
    dotted = re.sub(r"\[\s*(\d+)\s*\]", r".\1", path)
    tokens = [s.strip() for s in dotted.split(".")]
    if not path or any(not s or "[" in s or "]" in s for s in tokens):
        raise _err(path or "--set", f"bad key in override '{text}' (expected a dotted path "
                   "like render.lsg.radius or lights[0].intensity)")
    try:
        parsed = tomllib.loads(f"v = {value}\n")["v"]
    except tomllib.TOMLDecodeError:
        if not _BARE_WORD.fullmatch(value):
            raise _err(path, f"invalid value '{value}' in --set (expected a TOML value, e.g. "
                       "1.5, [1, 2, 3], \"text\", true)") from None
        parsed = value
    return tokens, parsed


def apply_overrides(data: dict, overrides: Sequence[str]) -> dict:
    """A deep copy of ``data`` with every ``--set key=value`` applied in order.

    Missing tables on the way are created (``render.raymarch.steps=64``); a list index
    equal to the list's length appends a new table. What the path names is validated
    afterwards by :func:`scene_from_dict`, so an unknown key is still an error.
    """
    data = copy.deepcopy(data)
    for text in overrides:
        tokens, value = parse_override(text)
        node: Any = data
        shown = ""
        for pos, tok in enumerate(tokens):
            last = pos == len(tokens) - 1
            if isinstance(node, list):
                if not tok.isdigit():
                    raise _err(shown, f"is an array: index it with {shown}[i], not .{tok}")
                i = int(tok)
                if i > len(node):
                    raise _err(f"{shown}[{i}]", f"index out of range ({shown} has {len(node)} "
                               f"entries; index {len(node)} appends one)")
                shown = f"{shown}[{i}]"
                if i == len(node):
                    node.append(None)
                    if not last:
                        node[i] = [] if tokens[pos + 1].isdigit() else {}
            elif isinstance(node, dict):
                i = tok
                shown = f"{shown}.{tok}" if shown else tok
                if not last and i not in node:
                    node[i] = [] if tokens[pos + 1].isdigit() else {}
            else:
                raise _err(shown, f"is {_tname(node)}, not a table: cannot set "
                           f"{'.'.join(tokens)}")
            if last:
                node[i] = value
            else:
                node = node[i]
    return data


def read_toml(path: Path | str) -> dict:
    """Parse a TOML scene file; SceneError naming the file (with TOML's line/column)."""
    name = str(path)
    path = Path(path)
    if not path.exists():
        raise _err(name, "scene file not found")
    if not path.is_file():
        raise _err(name, "scene path is not a file")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _err(name, f"scene file is not UTF-8 text ({exc.reason} at byte "
                   f"{exc.start})") from None
    except OSError as exc:
        raise _err(name, f"cannot read scene file: {exc.strerror or exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        if "(at end of document)" in msg:   # tomllib gives no line there: say which it is
            msg = msg.replace("(at end of document)",
                              f"(at end of document, line {max(1, len(text.splitlines()))})")
        raise _err(name, f"invalid TOML: {msg}") from None


def scene_source(spec: str | Path, on_note: Callable[[str], None] | None = None
                 ) -> tuple[dict, Path]:
    """The raw scene dict of ``spec`` (a .toml path, a Mitsuba 3 .xml path or
    ``builtin:NAME``) and the folder its relative paths are resolved against; nothing is
    validated yet. ``on_note`` receives each note of a Mitsuba scene's conversion (one
    line each: what was approximated or dropped, docs/mitsuba.md)."""
    spec = str(spec)
    if spec.startswith("builtin:"):
        from .builtin import BUILTIN

        name = spec[len("builtin:"):]
        if name not in BUILTIN:
            raise _err(spec, f"unknown built-in scene '{name}' (one of {', '.join(BUILTIN)})")
        return BUILTIN[name](), Path.cwd()
    if Path(spec).suffix.lower() == ".xml":
        from .mitsuba_in import read_xml

        data, notes = read_xml(spec)
        for line in notes if on_note is not None else ():
            on_note(line)
        return data, Path(spec).parent
    return read_toml(spec), Path(spec).parent


def load_scene(spec: str | Path, overrides: Sequence[str] = (),
               on_note: Callable[[str], None] | None = None) -> Scene:
    """Load a scene: ``spec`` is a .toml or Mitsuba 3 .xml path or ``builtin:NAME``;
    ``overrides`` are ``--set key=value`` strings applied before validation; ``on_note``
    receives the notes of a Mitsuba scene's conversion."""
    data, base_dir = scene_source(spec, on_note)
    return scene_from_dict(apply_overrides(data, overrides), base_dir, str(spec))
