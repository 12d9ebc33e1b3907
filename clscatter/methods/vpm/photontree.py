"""Photon map for volumetric photon mapping (``vpm``): compact photons in a balanced kd-tree.

Photons (:data:`PHOTON`, 20 bytes, as compact as Jensen's photon map)
    position as three float32, the incident direction (the way the light travels) as a
    32-bit octahedral code (16 bits per coordinate, < 1e-4 rad), and the rgb power as
    one RGB9E5 word (shared 5-bit exponent, 9-bit mantissas, rounding error <= 2^-9 of
    the largest channel) holding ``power / power_scale``, so that every scene's powers
    sit in the format's range; the kernels multiply ``power_scale`` back.

Tree (:data:`PHOTON_NODE`, 24 bytes per node)
    A balanced kd-tree: every node's photons are split at their median along the node's
    widest axis, ``levels`` times, so that each of the ``2^levels`` leaves holds
    ``leaf_size`` to ``2 leaf_size`` photons. It is stored as a *perfect* binary tree of
    axis-aligned boxes, breadth-first (heap order: node i has children 2i+1 and 2i+2;
    leaf j is node ``2^levels - 1 + j``), with the photons sorted by leaf; leaf j holds
    photons ``[floor(j N / 2^levels), floor((j + 1) N / 2^levels))`` (:func:`leaf_ranges`),
    which is exactly how the medians cut them. So the kernel needs no child pointers, no
    split planes and no per-node counts. The build is one argsort per level plus one
    min/max reduction per level: O(N log^2 N) in NumPy, no Python loop over photons or
    nodes (~1.5 us per photon on one core at 4M photons).

An empty map is one root with the empty box ``bmin = +1e30, bmax = -1e30``, whose
distance to any point is huge, so a query ends at once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...device import structs

PHOTON = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32),
                   ("dir", np.uint32), ("power", np.uint32)])

PHOTON_NODE = np.dtype([("bmin", np.float32, 3), ("bmax", np.float32, 3)])

# name in vpm.h -> dtype (for the layout test)
ALL = {"Photon": structs.register_struct("vpm.h", "Photon", PHOTON),
       "PhotonNode": structs.register_struct("vpm.h", "PhotonNode", PHOTON_NODE)}

EMPTY = 1e30

# transient bytes per photon of build_tree beyond the photon array (coordinates and their
# permuted copies, the order, the sort key and its temporaries, the argsort result, and
# the sorted copy of the photons at the end): 50 measured with tracemalloc
BUILD_BYTES_PER_PHOTON = 52

# ---- RGB9E5 (EXT_texture_shared_exponent) -------------------------------------------------
_N, _B = 9, 15
_MAX_E = 31
RGB9E5_MAX = (2 ** _N - 1) / 2 ** _N * 2.0 ** (_MAX_E - _B)


def encode_rgb9e5(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) non-negative floats -> (N,) uint32 RGB9E5 words (round to nearest)."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, RGB9E5_MAX)
    maxc = c.max(axis=1)
    floor_log2 = np.frexp(maxc)[1] - 1          # exact, unlike floor(log2(x))
    e = np.where(maxc > 0, np.maximum(-_B - 1, floor_log2) + 1 + _B, 0).astype(np.float64)
    maxm = np.floor(maxc / np.exp2(e - _B - _N) + 0.5)
    e = np.where(maxm >= 2 ** _N, e + 1, e)
    m = np.floor(c / np.exp2(e - _B - _N)[:, None] + 0.5).astype(np.uint32)
    m = np.minimum(m, 2 ** _N - 1)
    return (m[:, 0] | (m[:, 1] << 9) | (m[:, 2] << 18) | (e.astype(np.uint32) << 27)).astype(np.uint32)


def decode_rgb9e5(words: np.ndarray) -> np.ndarray:
    """(N,) uint32 -> (N, 3) float64 (the inverse of :func:`encode_rgb9e5`)."""
    w = np.asarray(words, np.uint32)
    scale = np.exp2((w >> 27).astype(np.float64) - _B - _N)
    m = np.stack([w & 511, (w >> 9) & 511, (w >> 18) & 511], axis=1).astype(np.float64)
    return m * scale[:, None]


# ---- Octahedral unit vectors ---------------------------------------------------------------
def encode_direction(d: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors -> (N,) uint32: 16-bit octahedral u (low) and v (high)."""
    d = np.asarray(d, np.float64)
    p = d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-300)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    sx = np.where(x >= 0, 1.0, -1.0)
    sy = np.where(y >= 0, 1.0, -1.0)
    u = np.where(z < 0, (1 - np.abs(y)) * sx, x)
    v = np.where(z < 0, (1 - np.abs(x)) * sy, y)
    qu = np.round((np.clip(u, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint32)
    qv = np.round((np.clip(v, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint32)
    return (qu | (qv << 16)).astype(np.uint32)


def decode_direction(codes: np.ndarray) -> np.ndarray:
    """(N,) uint32 -> (N, 3) unit float64 vectors (the inverse of :func:`encode_direction`)."""
    c = np.asarray(codes, np.uint32)
    u = (c & 0xFFFF).astype(np.float64) / 65535 * 2 - 1
    v = (c >> 16).astype(np.float64) / 65535 * 2 - 1
    z = 1 - np.abs(u) - np.abs(v)
    t = np.maximum(-z, 0.0)
    x = u - np.where(u >= 0, t, -t)
    y = v - np.where(v >= 0, t, -t)
    d = np.stack([x, y, z], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ---- The tree ------------------------------------------------------------------------------
@dataclass
class PhotonTree:
    """A photon map ready for upload (see the module docstring for the layout)."""

    photons: np.ndarray      # PHOTON, in leaf order
    nodes: np.ndarray        # PHOTON_NODE, breadth-first perfect binary tree
    levels: int              # depth of the leaves (root alone: 0)
    leaf_size: int
    power_scale: float       # decoded power = rgb9e5 value * power_scale
    bmin: np.ndarray         # bounding box of all photons (float64, (3,))
    bmax: np.ndarray

    @property
    def count(self) -> int:
        return int(len(self.photons))

    @property
    def nbytes(self) -> int:
        return int(self.photons.nbytes + self.nodes.nbytes)

    def positions(self) -> np.ndarray:
        return np.stack([self.photons["x"], self.photons["y"], self.photons["z"]], axis=1)

    def powers(self) -> np.ndarray:
        """Decoded rgb powers (N, 3) float64, exactly what the kernels see."""
        return decode_rgb9e5(self.photons["power"]) * self.power_scale

    def directions(self) -> np.ndarray:
        return decode_direction(self.photons["dir"])


def pack_photons(positions: np.ndarray, directions: np.ndarray, powers: np.ndarray,
                 power_scale: float) -> np.ndarray:
    """(N, 3) positions, unit travel directions and rgb powers -> a PHOTON array."""
    pos = np.asarray(positions, np.float32).reshape(-1, 3)
    photons = np.zeros(len(pos), PHOTON)
    photons["x"], photons["y"], photons["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
    photons["dir"] = encode_direction(np.asarray(directions).reshape(-1, 3))
    photons["power"] = encode_rgb9e5(np.asarray(powers, np.float64).reshape(-1, 3) / power_scale)
    return photons


def leaf_ranges(n: int, levels: int) -> np.ndarray:
    """Start of every leaf's photon range, plus n: leaf j holds [r[j], r[j + 1])."""
    j = np.arange((1 << levels) + 1, dtype=np.int64)
    return (j * n) >> levels


def build_tree(photons: np.ndarray, leaf_size: int = 8, power_scale: float = 1.0) -> PhotonTree:
    """Balanced kd-tree over packed photons, as the implicit perfect BVH of the module
    docstring. Every node's photons are split at their median along the node's widest
    axis; one float64 argsort per level (key: node index + coordinate scaled into [0, 1)
    within the node), so there is no Python loop over nodes or photons. ``levels`` is
    the largest with at least ``leaf_size`` photons per leaf. Works for no photons (one
    empty root). Working set: about :data:`BUILD_BYTES_PER_PHOTON` bytes per photon on
    top of the photons themselves."""
    leaf_size = max(1, int(leaf_size))
    n = len(photons)
    levels = max(0, math.floor(math.log2(max(n / leaf_size, 1.0))))
    pos = [np.ascontiguousarray(photons[c]) for c in ("x", "y", "z")]
    order = np.arange(n, dtype=np.int32 if n < 2 ** 31 else np.int64)
    for level in range(levels):
        bounds = leaf_ranges(n, level)
        starts, sizes = bounds[:-1], np.diff(bounds)
        lo = np.stack([np.minimum.reduceat(p, starts) for p in pos], axis=1)
        ext = np.stack([np.maximum.reduceat(p, starts) for p in pos], axis=1) - lo
        axis = np.argmax(ext, axis=1).astype(np.int8)
        nodes = np.arange(len(starts))
        lo_ax = lo[nodes, axis].astype(np.float64)
        inv = 1.0 / (np.maximum(ext[nodes, axis].astype(np.float64), 1e-30) * (1 + 1e-6))
        # key = node + (coordinate along the node's axis - its min) / its extent, in place
        ax = np.repeat(axis, sizes)
        key = np.where(ax == 0, pos[0], np.where(ax == 1, pos[1], pos[2])).astype(np.float64)
        del ax
        key -= np.repeat(lo_ax, sizes)
        key *= np.repeat(inv, sizes)
        key += np.repeat(nodes.astype(np.float64), sizes)
        perm = np.argsort(key)
        del key
        pos = [p[perm] for p in pos]
        order = order[perm]
        del perm
    photons = photons[order]
    pos = np.stack(pos, axis=1) if n else np.zeros((0, 3), np.float32)
    width = 1 << levels
    if n:
        starts = leaf_ranges(n, levels)[:-1]
        lv_min = [np.minimum.reduceat(pos, starts, axis=0)]
        lv_max = [np.maximum.reduceat(pos, starts, axis=0)]
    else:
        lv_min = [np.full((1, 3), EMPTY, np.float32)]
        lv_max = [np.full((1, 3), -EMPTY, np.float32)]
    while len(lv_min[-1]) > 1:   # one reduction per level, leaves up to the root
        lv_min.append(lv_min[-1].reshape(-1, 2, 3).min(axis=1))
        lv_max.append(lv_max[-1].reshape(-1, 2, 3).max(axis=1))
    nodes = np.zeros(2 * width - 1, PHOTON_NODE)
    nodes["bmin"] = np.concatenate(lv_min[::-1])
    nodes["bmax"] = np.concatenate(lv_max[::-1])
    lo = pos.min(axis=0).astype(np.float64) if n else np.zeros(3)
    hi = pos.max(axis=0).astype(np.float64) if n else np.zeros(3)
    return PhotonTree(photons, nodes, levels, leaf_size, float(power_scale), lo, hi)


def build_photon_tree(positions: np.ndarray, directions: np.ndarray, powers: np.ndarray,
                      leaf_size: int = 8) -> PhotonTree:
    """Pack photons and build the tree in one go (positions (N, 3), unit travel
    directions (N, 3), non-negative rgb powers (N, 3)); ``power_scale`` is the largest
    power."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    pw = np.asarray(powers, np.float64).reshape(-1, 3)
    scale = float(pw.max()) if len(pw) and pw.max() > 0 else 1.0
    return build_tree(pack_photons(pos, directions, pw, scale), leaf_size, scale)
