"""BVHs of large meshes kept on disk across runs, keyed by the triangles they were built over.

A scene's BVH depends only on its triangles (as float32, in the scene's normalised frame)
and the builder's settings, not on the device, the lights or the camera, so rendering the
same mesh again (another light, another method, another process) need not build it
again. :func:`cached_bvh` builds with :func:`~clscatter.accel.bvh.build_bvh` and keeps
the result in ``bvh/`` beside the other cached results
(:func:`clscatter.device.cache.cache_dir`) when the mesh has at least
:data:`MIN_TRIANGLES` triangles (smaller ones build in milliseconds); a later call with
the same triangles and settings reads it back, array for array the same BVH. The file's
name is a SHA-256 of the triangles' bytes, the settings and what makes the file (the
builder's source, this module's and the node layout: a changed builder writes new files,
as an edited kernel is built again). The folder holds at most :data:`MAX_BYTES`, the
least recently used files going first; a file that cannot be read or written is ignored
(the BVH is then built).
"""
from __future__ import annotations

import functools
import hashlib
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from ..device.cache import cache_dir
from ..device.structs import BVH_NODE
from . import bvh as _builder
from .bvh import BVH, MAX_LEAF, build_bvh

#: meshes with fewer triangles are built, not cached
MIN_TRIANGLES = 20_000
#: the most the cached BVHs may take on disk together
MAX_BYTES = 512 << 20


def bvh_folder() -> Path:
    """Where cached BVHs live: ``bvh/`` under :func:`~clscatter.device.cache.cache_dir`."""
    return cache_dir() / "bvh"


@functools.lru_cache(maxsize=1)
def _maker() -> bytes:
    """What the cached files depend on besides their triangles and settings: the builder's
    source, this module's (the file's layout) and the node layout."""
    h = hashlib.sha256()
    for source in (Path(_builder.__file__), Path(__file__)):
        h.update(source.read_bytes())
    h.update(str(BVH_NODE.descr).encode())
    return h.digest()


def bvh_key(tri32: np.ndarray, leaf_size: int, bins: int, max_leaf: int) -> str:
    """The cache key of a BVH over ``tri32`` ((T, 3, 3) float32) with these settings."""
    h = hashlib.sha256(_maker())
    h.update(f"bvh {tri32.shape} {leaf_size} {bins} {max_leaf}".encode())
    h.update(np.ascontiguousarray(tri32).data)
    return h.hexdigest()


def cached_bvh(triangles: np.ndarray, leaf_size: int = 4, bins: int = 16,
               max_leaf: int = MAX_LEAF) -> tuple[BVH, bool]:
    """(the BVH :func:`~clscatter.accel.bvh.build_bvh` builds over ``triangles`` with these
    settings, whether it was read from the cache). Its ``build_seconds`` is the time this
    call took."""
    t0 = time.perf_counter()
    tri32 = np.ascontiguousarray(triangles, dtype=np.float32)
    if tri32.ndim != 3 or len(tri32) < MIN_TRIANGLES:
        return build_bvh(triangles, leaf_size, bins, max_leaf), False
    path = bvh_folder() / f"{bvh_key(tri32, leaf_size, bins, max_leaf)}.npz"
    bvh = _read(path)
    if bvh is not None:
        bvh.build_seconds = time.perf_counter() - t0
        return bvh, True
    bvh = build_bvh(tri32, leaf_size, bins, max_leaf)
    _write(path, bvh)
    return bvh, False


def _read(path: Path) -> BVH | None:
    try:
        with np.load(path, allow_pickle=False) as f:
            bvh = BVH(nodes=f["nodes"], triangles=f["triangles"], order=f["order"],
                      depth=int(f["depth"]), n_valid=int(f["n_valid"]))
        os.utime(path)                          # recently used: pruned last
        return bvh
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _write(path: Path, bvh: BVH) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, nodes=bvh.nodes, triangles=bvh.triangles, order=bvh.order,
                 depth=np.int64(bvh.depth), n_valid=np.int64(bvh.n_valid))
        tmp.replace(path)
        prune(path.parent, MAX_BYTES)
    except OSError:
        pass


def prune(folder: Path, max_bytes: int) -> None:
    """Remove the least recently used ``*.npz`` files of ``folder`` until the rest take at
    most ``max_bytes``."""
    files = []
    for p in folder.glob("*.npz"):
        try:
            st = p.stat()
            files.append((st.st_mtime, st.st_size, p))
        except OSError:
            continue
    total = sum(size for _, size, _ in files)
    for _, size, p in sorted(files, key=lambda f: f[0]):
        if total <= max_bytes:
            break
        try:
            p.unlink()
            total -= size
        except OSError:
            pass
