"""Voxelisation (Sun et al. 2008, sec. 4.1): meshes and sampled grids -> n, sigma grids.

Stages, each a kernel of ``cl_kernels/voxel.cl`` except the per-volume mix:

1. **Inside test at the output resolution** (``vox_inside``): one ray per x-column of
   voxel centres, parity of the mesh crossings before each centre (a watertight mesh is
   entered and left alternately; this is the slice-by-slice counting of the paper done
   along rays).
2. **Coverage** (``vox_coverage``): where the 3x3x3 neighbourhood of the inside grid
   agrees, the voxel is wholly in or out; elsewhere 4x4x4 sub-samples give the covered
   fraction (the paper's 4x supersampling, only near the surface).
3. **Blur** (``vox_blur``): separable Gaussian, 9 taps per axis, sigma = 9/6 = 1.5 voxels,
   edges clamped. Blurring coverage and then mixing is the paper's "coverage -> index ->
   blur", since the index is affine in coverage.
4. **Mix** (NumPy, per voxel, vectorised): with blurred weights w_v of the volumes,
   n = 1 + sum_v w_v (n_v(x) - 1), sigma = (1 - sum_v w_v) sigma_medium(x) + sum_v w_v
   sigma_v(x) (docs/scene_format.md: coefficients blend with the index's weights; outside
   every volume the scene medium holds).
5. **Gradient** (``vox_gradient``): central differences of n.
6. **Boundary sides** (``boundary_sides``, NumPy): per voxel the blurred weight w of
   the volume weighing most there and the indices just outside and inside its boundary.
   A path whose w passes 1/2 (the sharp boundary) crosses from n1 to n2 by Snell's law
   and keeps the Fresnel transmittance of a sharp n1 -> n2 interface (``vox_cut``,
   ``vox_cross``); the ray equation elsewhere follows the interior gradient
   (``interior_gradient``: grad n without the boundaries' jumps), since bending through
   the smoothed band under-deviates grazing rays at a curved boundary.

A grid volume (``grid = "*.npy"``) has n_v(x) = the grid's value trilinear between its
centres, clamped at its outermost centres; its weight is the exact fraction of each voxel
inside its bounds box, blurred like a shape's coverage, so the jump at the box faces is
smoothed the same way while the interior keeps its sampled values unblurred. A density
volume is a grid volume whose coefficients are per unit density: sigma_v(x) = density(x)
sigma_v, the density sampled at the voxel centres as the index is (n_v = 1 without an
index grid).
"""
from __future__ import annotations

import numpy as np

from ...accel.bvh import build_bvh
from ...device import Engine
from ...scene.model import Volume
from ...scene.normalised import Frame
from .grid import GridBox

GAUSS_WINDOW = 9        # taps per axis (the paper's 9^3 window)
SMOOTH_TAPS = np.array([0.25, 0.5, 0.25], np.float32)   # 3x3x3 binomial ~ Gaussian (sec. 4.4)


def gaussian_taps(window: int = GAUSS_WINDOW) -> np.ndarray:
    """Normalised Gaussian taps, sigma = window / 6 (the paper's choice)."""
    r = window // 2
    x = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / (window / 6.0)) ** 2)
    return (w / w.sum()).astype(np.float32)


def inside_grid(eng: Engine, box: GridBox, triangles: np.ndarray) -> np.ndarray:
    """0/1 inside test of a watertight mesh (T, 3, 3) at every voxel centre (uint8 grid)."""
    bufs = build_bvh(np.asarray(triangles, np.float64)).upload(eng)
    out = eng.empty(box.size)
    try:
        eng.call("voxel", "vox_inside", box.dims[1] * box.dims[2], nodes=bufs.nodes,
                 tris=bufs.triangles, lo=box.lo4(), dims=box.dims4(), h=box.h, inside=out)
        return eng.read(out, box.dims, np.uint8)
    finally:
        eng.free(out)
        bufs.free(eng)


def mesh_coverage(eng: Engine, box: GridBox, triangles: np.ndarray, refine_all: bool = False) -> np.ndarray:
    """Fraction of every voxel inside a watertight mesh (float32 grid): the inside test
    at the centres, refined by 4^3 sub-samples where the 3x3x3 neighbourhood disagrees
    (everywhere when ``refine_all``)."""
    bufs = build_bvh(np.asarray(triangles, np.float64)).upload(eng)
    inside = eng.empty(box.size)
    cov = eng.empty(4 * box.size)
    try:
        eng.call("voxel", "vox_inside", box.dims[1] * box.dims[2], nodes=bufs.nodes,
                 tris=bufs.triangles, lo=box.lo4(), dims=box.dims4(), h=box.h, inside=inside)
        eng.call("voxel", "vox_coverage", box.size, nodes=bufs.nodes, tris=bufs.triangles,
                 lo=box.lo4(), dims=box.dims4(), h=box.h, inside=inside, refine_all=refine_all,
                 coverage=cov)
        return eng.read(cov, box.dims, np.float32)
    finally:
        eng.free(inside, cov)
        bufs.free(eng)


def box_coverage(box: GridBox, bmin, bmax) -> np.ndarray:
    """Exact fraction of every voxel inside the axis-aligned box [bmin, bmax]."""
    f = []
    for a in range(3):
        e0 = box.lo[a] + np.arange(box.dims[a]) * box.h
        f.append(np.clip((np.minimum(e0 + box.h, bmax[a]) - np.maximum(e0, bmin[a])) / box.h, 0, 1))
    return (f[0][:, None, None] * f[1][None, :, None] * f[2][None, None, :]).astype(np.float32)


def blur(eng: Engine, grid: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable convolution of a (nx, ny, nz[, C]) float grid with ``taps`` along each
    axis on the device (``vox_blur``), edges clamped."""
    g = np.ascontiguousarray(grid, np.float32)
    dims = g.shape[:3]
    ch = 1 if g.ndim == 3 else g.shape[3]
    a, b = eng.to_device(g, writable=True), eng.empty(g.nbytes)
    w = eng.to_device(np.asarray(taps, np.float32))
    try:
        blur_buffers(eng, a, b, dims, ch, w, len(taps) // 2)
        return eng.read(b, g.shape, np.float32)
    finally:
        eng.free(a, b, w)


def blur_buffers(eng: Engine, a, b, dims, channels: int, taps_buf, radius: int) -> None:
    """Blur buffer ``a`` into ``b`` (three passes x, y, z: a->b->a->b); float4 grids
    (``channels == 4``) go through ``vox_blur4``, one work-item per voxel."""
    d4 = np.array([*dims, 0], np.int32)
    n = int(np.prod(dims))
    for axis, (src, dst) in enumerate(((a, b), (b, a), (a, b))):
        if channels == 4:
            eng.call("voxel", "vox_blur4", n, src=src, dst=dst, dims=d4, axis=axis, w=taps_buf,
                     r=radius)
        else:
            eng.call("voxel", "vox_blur", n * channels, src=src, dst=dst, dims=d4,
                     channels=channels, axis=axis, w=taps_buf, r=radius)


def gradient(eng: Engine, box: GridBox, n_buf) -> object:
    """Device buffer of grad n (float4 per voxel) by central differences."""
    g = eng.empty(16 * box.size)
    eng.call("voxel", "vox_gradient", box.size, n=n_buf, dims=box.dims4(), h=box.h, grad=g)
    return g


def interior_gradient(eng: Engine, box: GridBox, grad_buf, boundary_buf) -> None:
    """Take the volumes' boundary jumps out of ``grad_buf`` (from :func:`gradient`), in
    place (``vox_interior_gradient``): per voxel grad n - (n_hi - n_lo) grad w, with the
    boundary record of :func:`boundary_sides` and grad w by the same central differences.
    Paths cross the boundaries by Snell's law where w = 1/2 instead of being bent through
    the smoothed band; a constant-index volume leaves 0, a graded one w grad n_v."""
    eng.call("voxel", "vox_interior_gradient", box.size, grad=grad_buf, boundary=boundary_buf,
             dims=box.dims4(), h=box.h)


def volume_weight(eng: Engine, box: GridBox, v: Volume, frame: Frame) -> np.ndarray:
    """Unblurred weight (coverage) of one volume on the grid."""
    if v.mesh is not None:
        tris = frame.point(v.mesh.vertices)[np.asarray(v.mesh.faces, np.int64)]
        return mesh_coverage(eng, box, tris)
    return box_coverage(box, frame.point(v.grid_bounds[0]), frame.point(v.grid_bounds[1]))


def sample_grid(box: GridBox, values: np.ndarray, bmin, bmax) -> np.ndarray:
    """``values`` (a grid over [bmin, bmax], value at each of its voxel centres) sampled at
    this grid's centres: trilinear between its centres, clamped at the outermost."""
    shape = np.asarray(values.shape[:3], np.float64)
    cx, cy, cz = box.centres()
    coords = [(c - bmin[a]) / (bmax[a] - bmin[a]) * shape[a] - 0.5 for a, c in enumerate((cx, cy, cz))]
    X, Y, Z = np.meshgrid(*coords, indexing="ij")
    from scipy.ndimage import map_coordinates  # lazily: scipy is slow to import
    return map_coordinates(np.asarray(values, np.float64), [X, Y, Z], order=1, mode="nearest").astype(np.float32)


def volume_fields(box: GridBox, v: Volume, frame: Frame) -> tuple:
    """(n_v, sigma_s_v, sigma_a_v) of one volume at the grid's centres: scalars/rgb for
    shapes, sampled grids for grid volumes (per-voxel sigma grids when the volume has
    ``sigma_s_grid`` / ``sigma_a_grid`` attributes, else the scalars), and the sampled
    density times the coefficients for a density volume."""
    ss = frame.coefficient(v.sigma_s).astype(np.float32)
    sa = frame.coefficient(v.sigma_a).astype(np.float32)
    if v.grid is None and v.density is None:
        return np.float32(v.ior), ss, sa
    bmin, bmax = frame.point(v.grid_bounds[0]), frame.point(v.grid_bounds[1])
    n = sample_grid(box, v.grid, bmin, bmax) if v.grid is not None else np.float32(1.0)
    if v.density is not None:
        d = sample_grid(box, v.density, bmin, bmax)[..., None]
        return n, d * ss, d * sa
    for name in ("sigma_s_grid", "sigma_a_grid"):
        g = getattr(v, name, None)
        if g is not None:
            s = sample_grid(box, g, bmin, bmax)[..., None] * np.ones(3, np.float32)
            s = s * np.float32(frame.scale)
            if name == "sigma_s_grid":
                ss = s
            else:
                sa = s
    return n, ss, sa


def medium_at_centres(box: GridBox, medium: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scene-medium sigma_s, sigma_a (rgb) at voxel centres: its values inside its
    bounds, 0 outside (and everywhere without a medium). Shapes (nx, ny, nz, 3)."""
    shape = (*box.dims, 3)
    if not medium["present"]:
        return np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    inside = np.ones(box.dims, bool)
    if medium["bounded"]:
        for a, c in enumerate(box.centres()):
            ok = (c >= medium["bmin"][a]) & (c <= medium["bmax"][a])
            sl = [None, None, None]
            sl[a] = slice(None)
            inside &= ok[tuple(sl)]
    m = inside[..., None].astype(np.float32)
    return m * medium["sigma_s"][:3], m * medium["sigma_a"][:3]


def boundary_sides(weights: list[np.ndarray], fields: list[tuple], n: np.ndarray) -> np.ndarray:
    """Where the volumes' sharp boundaries lie and what they separate, for paths crossing
    them by Snell's law and Fresnel (``vox_cut``, ``vox_cross`` in voxel.cl) and for the
    interior gradient (:func:`interior_gradient`): per voxel (w, n_lo, n_hi,
    0), float32 (nx, ny, nz, 4). w is the blurred weight of the volume weighing most
    there (its sharp boundary lies where w = 1/2); n_lo and n_hi are the index ``n`` (of
    :func:`mix`) with that volume's weight set to 0 and to 1, the indices just outside and
    just inside its boundary. Where no volume weighs anything, w = 0 and n_lo = n_hi = n
    (nothing to cross). ``weights`` and ``fields`` as :func:`mix` takes them."""
    out = np.zeros((*n.shape, 4), np.float32)
    out[..., 1] = out[..., 2] = n
    if not weights:
        return out
    total = np.sum(weights, axis=0)
    scale = np.where(total > 1.0, 1.0 / np.maximum(total, 1e-30), 1.0).astype(np.float32)
    best = np.zeros(n.shape, np.float32)
    for w, (nv, _, _) in zip(weights, fields):
        w = w * scale
        take = w > best
        dn = (np.asarray(nv, np.float32) - 1.0) * scale           # n's change per unit weight
        dn = np.broadcast_to(dn, n.shape)
        out[..., 0] = np.where(take, w, out[..., 0])
        out[..., 1] = np.where(take, n - w * dn, out[..., 1])
        out[..., 2] = np.where(take, n + (1.0 - w) * dn, out[..., 2])
        best = np.maximum(best, w)
    return out


def mix(weights: list[np.ndarray], fields: list[tuple], medium_ss: np.ndarray,
        medium_sa: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n (nx,ny,nz), sigma_s and kappa (nx,ny,nz,4, w = 0) from blurred weights and
    per-volume fields; where weights sum above 1 (overlapping volumes) they are scaled
    down to sum 1."""
    total = np.sum(weights, axis=0) if weights else np.zeros(medium_ss.shape[:3], np.float32)
    scale = np.where(total > 1.0, 1.0 / np.maximum(total, 1e-30), 1.0).astype(np.float32)
    n = np.ones(medium_ss.shape[:3], np.float32)
    ss = medium_ss * (1.0 - np.minimum(total, 1.0))[..., None]
    sa = medium_sa * (1.0 - np.minimum(total, 1.0))[..., None]
    for w, (nv, ssv, sav) in zip(weights, fields):
        w = w * scale
        n += w * (np.asarray(nv, np.float32) - 1.0)
        ss = ss + w[..., None] * np.asarray(ssv, np.float32)
        sa = sa + w[..., None] * np.asarray(sav, np.float32)
    pad = np.zeros((*n.shape, 1), np.float32)
    return (n.astype(np.float32), np.concatenate([ss, pad], -1).astype(np.float32),
            np.concatenate([ss + sa, pad], -1).astype(np.float32))
