"""Photons of volumetric photon mapping (``vpm``) and their map over the estimators' tree.

Photons (:data:`PHOTON`, 20 bytes, as compact as Jensen's photon map)
    position as three float32, the incident direction (the way the light travels) as a
    32-bit octahedral code (16 bits per coordinate, < 1e-4 rad), and the rgb power as
    one RGB9E5 word (shared 5-bit exponent, 9-bit mantissas, rounding error <= 2^-9 of
    the largest channel) holding ``power / power_scale``, so that every scene's powers
    sit in the format's range; the kernels multiply ``power_scale`` back.

Map (:class:`PhotonMap`)
    The photons sorted by leaf of the estimators' *balanced* point tree
    (:meth:`clscatter.estimators.segment_tree.SegmentTree.balanced`: median splits along
    the widest axis, ``2^levels`` leaves of ``leaf_size`` to ``2 leaf_size`` photons) and
    that tree's compact nodes (:data:`~clscatter.estimators.segment_tree.POINT_NODE`, 24
    bytes: a box per node of a perfect breadth-first tree; ``point_tree.h``), which is all
    the kernels need: no child pointers, split planes or per-node counts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...device import structs
from ...estimators.segment_tree import SegmentTree

PHOTON = structs.register_struct("vpm.h", "Photon", np.dtype(
    [("x", np.float32), ("y", np.float32), ("z", np.float32), ("dir", np.uint32),
     ("power", np.uint32)]))

# transient bytes per photon of build_photon_map beyond the photon array (the positions,
# their per-level sorted columns, the sort key and its temporaries, the argsort result,
# the tree's references and the sorted copy of the photons at the end), measured with
# tracemalloc
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


# ---- The map ------------------------------------------------------------------------------
@dataclass
class PhotonMap:
    """A photon map ready for upload (see the module docstring for the layout)."""

    photons: np.ndarray      # PHOTON, in leaf order
    nodes: np.ndarray        # POINT_NODE, breadth-first perfect binary tree
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


def build_photon_map(photons: np.ndarray, leaf_size: int = 8,
                     power_scale: float = 1.0) -> PhotonMap:
    """The map of packed photons: the balanced point tree over their float32 positions
    (:meth:`SegmentTree.balanced`), the photons sorted by its leaves and its compact nodes.
    Works for no photons (one empty root). Working set: about
    :data:`BUILD_BYTES_PER_PHOTON` bytes per photon on top of the photons themselves."""
    photons = np.ascontiguousarray(photons)
    # the positions: a (N, 3) view of the records' first three floats, no copy
    pos = photons.view(np.float32).reshape(-1, PHOTON.itemsize // 4)[:, :3]
    tree = SegmentTree.balanced(pos, leaf_size)
    n = len(photons)
    lo = tree.lo[0].copy() if n else np.zeros(3)
    hi = tree.hi[0].copy() if n else np.zeros(3)
    return PhotonMap(photons[tree.order], tree.point_nodes(), tree.levels, tree.leaf_size,
                     float(power_scale), lo, hi)


def photon_map_of(positions: np.ndarray, directions: np.ndarray, powers: np.ndarray,
                  leaf_size: int = 8) -> PhotonMap:
    """Pack photons and build their map in one go (positions (N, 3), unit travel
    directions (N, 3), non-negative rgb powers (N, 3)); ``power_scale`` is the largest
    power."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    pw = np.asarray(powers, np.float64).reshape(-1, 3)
    scale = float(pw.max()) if len(pw) and pw.max() > 0 else 1.0
    return build_photon_map(pack_photons(pos, directions, pw, scale), leaf_size, scale)
