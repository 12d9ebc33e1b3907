"""Stanford PLY meshes read with NumPy: vertex positions and polygon faces.

:func:`read_ply` reads ``ascii``, ``binary_little_endian`` and ``binary_big_endian``
files: the ``vertex`` element's ``x``, ``y``, ``z`` (any numeric type, other properties
skipped) and the ``face`` element's ``vertex_indices`` (or ``vertex_index``) list,
polygons fanned into triangles. Elements before those two are skipped (a list property in
one is read item by item); elements after them are never read. A binary face element
whose lists all have the same length is read in one ``frombuffer``. It returns ``None``
for a file it does not cover (no ``face`` element, a face without an index list), so the
caller can hand that file to a general reader; a file that is not valid PLY, or is cut
short, raises :class:`ValueError` naming the problem.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: PLY scalar type names (both spellings) -> NumPy type codes
TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
         "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
         "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
         "float64": "f8"}
INDEX_NAMES = ("vertex_indices", "vertex_index")


class _Element:
    """One ``element`` of the header: its name, count and properties, each ``(name,
    type)`` for a scalar or ``(name, (count type, item type))`` for a list."""

    def __init__(self, name: str, count: int):
        self.name, self.count = name, count
        self.props: list[tuple[str, object]] = []

    @property
    def has_list(self) -> bool:
        return any(isinstance(t, tuple) for _, t in self.props)


def _type(name: str) -> str:
    if name not in TYPES:
        raise ValueError(f"unknown PLY property type {name!r}")
    return TYPES[name]


def _header(data: bytes) -> tuple[str, list[_Element], int]:
    """The format, the elements and where the body begins."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file (no 'ply' line or no 'end_header')")
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    fmt = None
    elements: list[_Element] = []
    for raw in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            if len(words) == 5 and words[1] == "list":
                elements[-1].props.append((words[4], (_type(words[2]), _type(words[3]))))
            elif len(words) == 3:
                elements[-1].props.append((words[2], _type(words[1])))
            else:
                raise ValueError(f"cannot read the PLY header line {raw.strip()!r}")
        else:
            raise ValueError(f"cannot read the PLY header line {raw.strip()!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"unknown PLY format {fmt!r}")
    return fmt, elements, body


def _fan(lists: list[np.ndarray]) -> np.ndarray:
    """Polygons (index arrays) fanned into triangles ``(0, k, k + 1)``."""
    tris = [np.stack([np.full(len(p) - 2, p[0]), p[1:-1], p[2:]], axis=1)
            for p in lists if len(p) >= 3]
    return np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)


def _faces_from_rows(idx: np.ndarray) -> np.ndarray:
    """Triangles from polygons that all have ``idx.shape[1]`` corners."""
    k = idx.shape[1]
    if k < 3:
        return np.zeros((0, 3), np.int64)
    fans = [idx[:, [0, j, j + 1]] for j in range(1, k - 1)]
    return np.stack(fans, axis=1).reshape(-1, 3).astype(np.int64)


class _Binary:
    """A cursor over a binary body."""

    def __init__(self, data: bytes, at: int, order: str):
        self.data, self.at, self.order = data, at, order

    def take(self, dtype: np.dtype, count: int) -> np.ndarray:
        need = dtype.itemsize * count
        if self.at + need > len(self.data):
            raise ValueError("the PLY file ends before its last element")
        out = np.frombuffer(self.data, dtype, count, self.at)
        self.at += need
        return out

    def scalar_dtype(self, el: _Element) -> np.dtype:
        return np.dtype([(f"p{i}", self.order + t) for i, (_, t) in enumerate(el.props)])

    def rows(self, el: _Element) -> dict[str, object]:
        """Every row of ``el``: scalars as arrays, lists as lists of arrays."""
        if not el.has_list:
            arr = self.take(self.scalar_dtype(el), el.count)
            return {name: arr[f"p{i}"] for i, (name, _) in enumerate(el.props)}
        out: dict[str, list] = {name: [] for name, _ in el.props}
        for _ in range(el.count):
            for name, t in el.props:
                if isinstance(t, tuple):
                    n = int(self.take(np.dtype(self.order + t[0]), 1)[0])
                    out[name].append(self.take(np.dtype(self.order + t[1]), n))
                else:
                    out[name].append(self.take(np.dtype(self.order + t), 1)[0])
        return out

    def faces(self, el: _Element, index: str) -> np.ndarray:
        """The face element's triangles: in one read when every list has the length of the
        first, else row by row."""
        start = self.at
        if el.count and all(isinstance(t, tuple) and name == index or not isinstance(t, tuple)
                            for name, t in el.props):
            head = self.at
            fields, k = [], None
            for i, (name, t) in enumerate(el.props):     # the first row's list length
                if isinstance(t, tuple):
                    k = int(np.frombuffer(self.data, self.order + t[0], 1, head)[0])
                    fields += [("count", self.order + t[0]), ("idx", self.order + t[1], (k,))]
                    head += np.dtype(t[0]).itemsize + k * np.dtype(t[1]).itemsize
                else:
                    fields.append((f"p{i}", self.order + t))
                    head += np.dtype(t).itemsize
            dt = np.dtype(fields)
            if self.at + dt.itemsize * el.count <= len(self.data):
                rows = np.frombuffer(self.data, dt, el.count, self.at)
                if np.all(rows["count"] == k):
                    self.at += dt.itemsize * el.count
                    return _faces_from_rows(rows["idx"].reshape(el.count, k))
        self.at = start
        return _fan(self.rows(el)[index])


def _ascii_rows(lines: list[bytes], el: _Element) -> dict[str, object]:
    """Every row of ``el`` from its text lines."""
    if not el.has_list:
        vals = np.array(b" ".join(lines).split(), np.float64)
        if vals.size != el.count * len(el.props):
            raise ValueError(f"PLY element {el.name!r} has the wrong number of values")
        vals = vals.reshape(el.count, len(el.props))
        return {name: vals[:, i] for i, (name, _) in enumerate(el.props)}
    out: dict[str, list] = {name: [] for name, _ in el.props}
    for line in lines:
        words, at = line.split(), 0
        for name, t in el.props:
            if isinstance(t, tuple):
                n = int(words[at])
                out[name].append(np.array(words[at + 1:at + 1 + n], np.int64))
                at += 1 + n
            else:
                out[name].append(float(words[at]))
                at += 1
    return out


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """``(vertices (V, 3) float64, triangles (F, 3) int64)`` of a PLY file, or ``None``
    where the file is valid PLY of a kind this reader does not cover (see the module)."""
    data = Path(path).read_bytes()
    fmt, elements, at = _header(data)
    names = [e.name for e in elements]
    if "vertex" not in names or "face" not in names:
        return None
    vel = elements[names.index("vertex")]
    fel = elements[names.index("face")]
    vnames = [n for n, _ in vel.props]
    index = next((n for n, t in fel.props if n in INDEX_NAMES and isinstance(t, tuple)), None)
    if index is None or not all(c in vnames for c in "xyz"):
        return None
    last = max(names.index("vertex"), names.index("face"))
    found: dict[str, object] = {}
    if fmt == "ascii":
        lines = [ln for ln in data[at:].splitlines() if ln.strip()]
        row = 0
        for el in elements[:last + 1]:
            if row + el.count > len(lines):
                raise ValueError("the PLY file ends before its last element")
            found[el.name] = _ascii_rows(lines[row:row + el.count], el)
            row += el.count
        faces = _fan(found["face"][index])
    else:
        cur = _Binary(data, at, "<" if fmt == "binary_little_endian" else ">")
        faces = None
        for el in elements[:last + 1]:
            if el.name == "face":
                faces = cur.faces(el, index)
            else:
                found[el.name] = cur.rows(el)
    v = found["vertex"]
    verts = np.stack([np.asarray(v[c], np.float64) for c in "xyz"], axis=1).reshape(-1, 3)
    return verts, faces
