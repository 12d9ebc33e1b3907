"""Sampled 3-D grids in files: what the loader reads for ``grid``, ``sigma_s_grid``,
``sigma_a_grid`` and ``density`` of a ``[[volumes]]`` entry, and the OpenVDB writer behind
``clscatter volume convert``.

Every grid is a float array of shape (nx, ny, nz), axis 0 = x, holding the values at the
voxel centres of a box (docs/scene_format.md, "What a volume means"). Formats:

=========  ==========================================================================
``.npy``   NumPy array; carries no placement (the scene gives ``bounds``)
``.vdb``   OpenVDB, one float grid by name; the dense array spans the grid's active
           voxels (and tiles) and is placed by its index-to-world transform: voxel
           (i, j, k) is centred at transform(i, j, k), so the box runs from
           transform(imin - 0.5) to transform(imax + 0.5). Needs the ``pyopenvdb`` module
           (Debian's ``python3-openvdb``); only its value iterator, accessor and
           transform calls on tuples are used, never anything that passes through its
           NumPy interop (built for NumPy 1.x, that crashes under NumPy 2: array copies,
           a transform from a matrix)
``.vol``   Mitsuba's binary grid volume: ``VOL``, version 3, encoding int32 (1 =
           float32), xres, yres, zres, channels (1, or 3: a density times a colour),
           the box as 6 float32 (min, max), then the values with x fastest; placed by
           that box
=========  ==========================================================================

Every failure is a one-line :class:`~clscatter.errors.SceneError` naming the scene key.
"""
from __future__ import annotations

import contextlib
import io
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import SceneError

#: the suffixes a grid file may have, and what reads them
SUFFIXES = (".npy", ".vdb", ".vol")
#: the Debian package that provides ``pyopenvdb``
OPENVDB_PACKAGE = "python3-openvdb"
#: density volumes one scene may hold (the device merges their boxes along a ray in
#: registers: ``cl_kernels/shared/density.h``, DENSITY_MAX_GRIDS)
MAX_DENSITY_VOLUMES = 8
#: the most voxels a .vdb grid's dense array may have (float32: 4 GiB)
MAX_DENSE_VOXELS = 1 << 30
_VOL_HEADER = struct.Struct("<3sBiiiii6f")


@dataclass(frozen=True)
class GridFile:
    """A grid as read from a file: ``values`` (nx, ny, nz) at voxel centres, and the box
    the file itself places it in (``None`` for ``.npy``, which carries no placement)."""

    values: np.ndarray
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    colour: np.ndarray | None = None    # a 3-channel .vol's channels over its density


def _err(key: str, message: str) -> SceneError:
    return SceneError(key, " ".join(str(message).split()))


# ---- OpenVDB ----------------------------------------------------------------------------

_OPENVDB: list = []      # [module or None], once imported


def openvdb() -> ModuleType | None:
    """The ``pyopenvdb`` module, or None when it is not installed. Importing it prints a
    NumPy ABI warning (it was built for NumPy 1.x); that text is swallowed, from Python's
    ``sys.stderr`` and from file descriptor 2 alike."""
    if not _OPENVDB:
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as null, contextlib.redirect_stderr(io.StringIO()):
                os.dup2(null.fileno(), 2)
                try:
                    import pyopenvdb as module
                except ImportError:
                    module = None
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        _OPENVDB.append(module)
    return _OPENVDB[0]


def _need_openvdb(key: str, path: Path) -> ModuleType:
    vdb = openvdb()
    if vdb is None:
        raise _err(key, f"reading or writing {path.name} (OpenVDB) needs the Python module "
                   f"pyopenvdb: install the Debian package {OPENVDB_PACKAGE} (scripts/setup.sh "
                   "does), or convert the grid to .npy elsewhere")
    return vdb


def _axis_aligned(transform, key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(origin, voxel size): the world position of index (0, 0, 0) and the step along each
    index axis, for a linear transform that scales and translates only."""
    origin = np.array(transform.indexToWorld((0, 0, 0)), np.float64)
    cols = np.array([np.array(transform.indexToWorld(e), np.float64) - origin
                     for e in ((1, 0, 0), (0, 1, 0), (0, 0, 1))])
    size = np.diag(cols).copy()
    off = cols - np.diag(size)
    if (not transform.isLinear or np.any(np.abs(off) > 1e-9 * np.abs(size).max())
            or np.any(size <= 0)):
        raise _err(key, f"{path.name}: its index-to-world transform is not a positive scale "
                   "and a translation (rotated, sheared, mirrored or a frustum); give the "
                   "volume's bounds to place it")
    return origin, size


def read_vdb(path: Path, key: str, name: str = "density", name_key: str | None = None,
             placed: bool = False) -> GridFile:
    """Float grid ``name`` of an OpenVDB file as a dense array over its active voxels and
    tiles (the rest of that box holds the grid's background value), placed by its
    transform (see the module docstring) unless ``placed`` (the scene gives the box: the
    transform is not read, and may be any). Unknown names are an error at ``name_key``
    listing the file's grids."""
    vdb = _need_openvdb(key, path)
    try:
        found, _ = vdb.readAll(str(path))
    except Exception as exc:  # the library raises several kinds
        raise _err(key, f"cannot read {path} as an OpenVDB file: {exc}") from None
    by_name = {g.name: g for g in found}
    if name not in by_name:
        raise _err(name_key or key, f"{path.name} has no grid named '{name}' (its grids: "
                   f"{', '.join(repr(n) for n in by_name) or 'none'})")
    grid = by_name[name]
    if grid.valueTypeName != "float":
        raise _err(name_key or key, f"grid '{name}' of {path.name} holds {grid.valueTypeName} "
                   "values, not float")
    if grid.activeVoxelCount() == 0:
        raise _err(key, f"grid '{name}' of {path.name} has no active voxels")
    lo, hi = (np.array(c, np.int64) for c in grid.evalActiveVoxelBoundingBox())
    dims = tuple(int(n) for n in hi - lo + 1)
    if np.prod(dims, dtype=np.float64) > MAX_DENSE_VOXELS:
        raise _err(key, f"grid '{name}' of {path.name}: its active voxels span "
                   f"{' x '.join(map(str, dims))} voxels, more than a dense grid of "
                   f"{MAX_DENSE_VOXELS:,} (4 GiB) holds")
    values = np.full(dims, float(grid.background), np.float32)
    for item in grid.iterOnValues():          # voxels and tiles (a tile covers min..max)
        a = np.array(item["min"], np.int64) - lo
        b = np.array(item["max"], np.int64) - lo + 1
        values[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = item["value"]
    if placed:
        return GridFile(values)
    origin, size = _axis_aligned(grid.transform, key, path)
    box = [origin + (lo - 0.5) * size, origin + (hi + 0.5) * size]
    return GridFile(values, tuple(np.where(np.abs(b) < 1e-9 * size, 0.0, b) for b in box))


def write_vdb(path: Path | str, values: np.ndarray, bounds=None, name: str = "density",
              key: str = "output") -> None:
    """Write ``values`` (nx, ny, nz) as float grid ``name`` of a new OpenVDB file: voxel
    (i, j, k) holds ``values[i, j, k]``, non-zero values active, and the two corner voxels
    active whatever their value, so :func:`read_vdb` gives back the same array and box.
    ``bounds`` (min, max) places it (voxel size (max - min) / shape); without it voxel
    (i, j, k) is centred at (i, j, k)."""
    path = Path(path)
    vdb = _need_openvdb(key, path)
    values = np.asarray(values, np.float32)
    shape = np.array(values.shape, np.float64)
    if bounds is None:
        lo, size = np.full(3, -0.5), np.ones(3)
    else:
        lo = np.asarray(bounds[0], np.float64)
        size = (np.asarray(bounds[1], np.float64) - lo) / shape
    centre0 = lo + 0.5 * size
    transform = vdb.createLinearTransform(1.0)     # (a matrix argument goes through NumPy)
    transform.scale(tuple(float(s) for s in size))
    transform.translate(tuple(float(c) for c in centre0))
    grid = vdb.FloatGrid()
    grid.name = name
    grid.transform = transform
    acc = grid.getAccessor()
    for i, j, k in zip(*np.nonzero(values)):
        acc.setValueOn((int(i), int(j), int(k)), float(values[i, j, k]))
    last = tuple(int(n) - 1 for n in values.shape)
    for corner in ((0, 0, 0), last):
        acc.setValueOn(corner, float(values[corner]))
    try:
        vdb.write(str(path), grids=[grid])
    except Exception as exc:  # the library's own errors
        raise _err(key, f"cannot write {path}: {exc}") from None


# ---- Mitsuba .vol -----------------------------------------------------------------------

def read_vol(path: Path, key: str) -> GridFile:
    """A Mitsuba binary grid volume (see the module docstring): float32, one channel
    (values (nx, ny, nz)) or several ((nx, ny, nz, channels))."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise _err(key, f"cannot read {path}: {exc.strerror or exc}") from None
    if len(data) < _VOL_HEADER.size:
        raise _err(key, f"{path.name} is too short for a .vol header ({len(data)} bytes)")
    tag, version, encoding, nx, ny, nz, channels, *box = _VOL_HEADER.unpack_from(data)
    if tag != b"VOL" or version != 3:
        raise _err(key, f"{path.name} is not a version-3 Mitsuba .vol file")
    if encoding != 1 or channels not in (1, 3):
        raise _err(key, f"{path.name}: only float32 (encoding 1) grids of one or three "
                   f"channels are read (encoding {encoding}, {channels} channels)")
    if min(nx, ny, nz) <= 0:
        raise _err(key, f"{path.name}: bad resolution {nx} x {ny} x {nz}")
    count = nx * ny * nz * channels
    if len(data) - _VOL_HEADER.size != 4 * count:
        raise _err(key, f"{path.name}: {len(data) - _VOL_HEADER.size} data bytes, expected "
                   f"{4 * count} for {nx} x {ny} x {nz} x {channels} float32 values")
    flat = np.frombuffer(data, "<f4", count, _VOL_HEADER.size)
    values = np.ascontiguousarray(flat.reshape(nz, ny, nx, channels).transpose(2, 1, 0, 3))
    if channels == 1:
        values = values[..., 0]
    lo, hi = np.array(box[:3], np.float64), np.array(box[3:], np.float64)
    if not (np.all(np.isfinite(box)) and np.all(lo < hi)):
        raise _err(key, f"{path.name}: its box must have min < max on every axis "
                   f"(min {lo.tolist()}, max {hi.tolist()})")
    return GridFile(values, (lo, hi))


# ---- NumPy ------------------------------------------------------------------------------

def read_npy(path: Path, key: str) -> np.ndarray:
    """A non-empty 3-D array of real numbers from a ``.npy`` file (any real dtype)."""
    try:
        grid = np.load(path, allow_pickle=False)
    except Exception as exc:  # bad header, pickled object, truncated file...
        raise _err(key, f"cannot read grid {path} as a .npy array: {exc}") from None
    if not isinstance(grid, np.ndarray) or grid.ndim != 3 or grid.size == 0:
        raise _err(key, f"grid {path} must be a non-empty 3-D array (got shape "
                   f"{getattr(grid, 'shape', '?')})")
    if not np.issubdtype(grid.dtype, np.number) or np.issubdtype(grid.dtype, np.complexfloating):
        raise _err(key, f"grid {path} must hold real numbers (got {grid.dtype})")
    return grid


# ---- What the loader calls --------------------------------------------------------------

def _exists(path: Path, key: str, what: str) -> None:
    if not path.is_file():
        raise _err(key, f"{what} file not found: {path}")


def load_grid(path: Path, key: str, positive: bool = True) -> np.ndarray:
    """An index grid (``positive``: finite values > 0) or a per-voxel coefficient grid
    (finite values >= 0) from a ``.npy`` file, as float64."""
    _exists(path, key, "grid")
    grid = read_npy(path, key).astype(np.float64)
    if positive and (not np.all(np.isfinite(grid)) or np.any(grid <= 0.0)):
        raise _err(key, f"grid {path} must hold finite indices of refraction > 0")
    if not positive and (not np.all(np.isfinite(grid)) or np.any(grid < 0.0)):
        raise _err(key, f"grid {path} must hold finite coefficients >= 0")
    return grid


def load_density(path: Path, key: str, name: str | None = None,
                 name_key: str | None = None, placed: bool = False) -> GridFile:
    """A density grid (``.npy``, ``.vdb`` grid ``name`` (default ``density``) or ``.vol``)
    as float32, checked finite and >= 0; the first offending voxel is named. ``placed``:
    the scene gives the box, so a ``.vdb``'s transform is not needed."""
    _exists(path, key, "density")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise _err(key, f"{path.name}: unknown density format '{path.suffix}' (one of "
                   f"{', '.join(SUFFIXES)})")
    if name is not None and suffix != ".vdb":
        raise _err(name_key or key, f"names a grid inside a .vdb file, but {path.name} is a "
                   f"{suffix} file (one grid)")
    if suffix == ".npy":
        got = GridFile(read_npy(path, key))
    elif suffix == ".vdb":
        got = read_vdb(path, key, name or "density", name_key, placed)
    else:
        got = read_vol(path, key)
    with np.errstate(invalid="ignore"):
        values = np.asarray(got.values, np.float64)
        bad = ~np.isfinite(values) | (values < 0.0)
    if bad.any():
        ijk = tuple(int(i) for i in np.argwhere(bad)[0])
        raise _err(key, f"density in {path.name} must be finite and >= 0 (voxel {ijk} holds "
                   f"{values[ijk]!r})")
    if np.any(np.abs(values) > np.finfo(np.float32).max):
        raise _err(key, f"density in {path.name} is beyond float32's range")
    if values.ndim == 4:
        values, colour = _density_and_colour(values, key, path)
        return GridFile(values.astype(np.float32), got.bounds, colour)
    return GridFile(values.astype(np.float32), got.bounds)


def _density_and_colour(values: np.ndarray, key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A three-channel grid that is a density times a colour (what a Mitsuba scene with
    extinction differing between r, g and b holds): the density (the brightest channel)
    and each channel over it. Channels that are not proportional are an error."""
    means = values.reshape(-1, values.shape[-1]).mean(axis=0)
    top = int(np.argmax(means))
    if not means[top] > 0:
        return values[..., top], np.ones(values.shape[-1])
    density = values[..., top]
    colour = means / means[top]
    if not np.allclose(values, density[..., None] * colour, rtol=1e-5,
                       atol=1e-6 * float(np.abs(density).max())):
        raise _err(key, f"{path.name}: its {values.shape[-1]} channels are not one density "
                   "times a colour; a density grid has one channel")
    return density, colour
