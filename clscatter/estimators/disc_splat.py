"""Fixed-radius surface estimates by splatting: the ray map's and the photon map's later
progressive passes formed from the lighting segments' side.

Once every diffuse hit q has its own radius ``R_q`` (a progressive pass after the first,
:mod:`.surface_passes`), eq. (1) of ``cl_kernels/estimators/raymap.cl`` is a plain sum
over the segments that qualify for q (incoming, within q's domain, metric at most
``R_q``): no K-nearest search is needed. The hits are the same in every pass and the
segments are new, so the structure is built over the hits, once (:class:`HitDiscs`: a
balanced tree by median splits, :mod:`.median_split`), and each pass only refits its boxes
to the new radii; one work-item per segment walks it (``rm_splat``) and adds its weighted
flux to every hit it qualifies for, with the same per-pair test and kernel weights as the
K-nearest query (``rm_qualify`` in ``raymap.h``). The lazy tree over the segments (the
paper's structure, which the first, K-nearest pass still uses) is not built at all.

The sums are exact 64-bit fixed-point integers (each term rounded once), so the estimate
is the same whatever order the device adds in, and a hit gathers every qualifying segment
(the K-nearest form keeps at most its heap's ``2 k``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..transport import primitives as prim
from .fixed_sum import fixed_scale
from .knn_queries import METRICS, _f4, heap_define
from .segment_tree import EMPTY, POINT_NODE, SegmentTree, level_boxes

#: hits per leaf of the tree over the hits (at least; at most twice as many)
LEAF_SIZE = 8
#: segments per kernel launch (each launch well under a second)
LAUNCH_SEGMENTS = 1 << 16
#: the box of a hit's domain is grown by this fraction of its radius and of the
#: coordinates' size (float32 rounding of the kernel's own test)
BOX_SLACK = 1e-5


@dataclass
class HitDiscs:
    """The diffuse hits (positions ``x``, unit normals ``n``, normalised frame) in the
    order of their balanced tree, on the device: the tree's depth ``levels``, ``order``
    (tree position -> hit index) and the buffers of normals and of that order."""

    engine: object
    x: np.ndarray              # (N, 3) float64, tree order
    levels: int
    order: np.ndarray          # int32: tree position -> the caller's hit index
    buf: dict

    @classmethod
    def build(cls, engine, x: np.ndarray, n: np.ndarray) -> "HitDiscs":
        """The tree over hits ``x`` (N, 3) with normals ``n`` (N, 3), uploaded."""
        x = np.asarray(x, np.float64).reshape(-1, 3)
        tree = SegmentTree.balanced(x, LEAF_SIZE)
        order = np.asarray(tree.order, np.int32)
        normals = np.asarray(n, np.float64).reshape(-1, 3)[order]
        buf = {"hn": engine.to_device(_f4(normals)),
               "ids": engine.to_device(order if len(order) else np.zeros(1, np.int32))}
        return cls(engine, x[order], tree.levels, order, buf)

    def __len__(self) -> int:
        return len(self.x)

    def boxes(self, radii: np.ndarray) -> np.ndarray:
        """The tree's nodes (:data:`POINT_NODE`, breadth-first) bounding every hit's ball
        of radius ``radii`` (tree order), grown by :data:`BOX_SLACK`."""
        r = np.asarray(radii, np.float64)
        grow = r * (1 + BOX_SLACK) + BOX_SLACK * (1.0 + np.abs(self.x).max(axis=1))
        lo, hi = level_boxes(self.x - grow[:, None], self.x + grow[:, None], self.levels)
        nodes = np.zeros(len(lo), POINT_NODE)
        nodes["bmin"], nodes["bmax"] = lo, hi
        if not len(self.x):
            nodes["bmin"], nodes["bmax"] = EMPTY, -EMPTY
        return nodes

    def release(self) -> None:
        self.engine.free(*self.buf.values())
        self.buf = {}


def flux_bound(flux: np.ndarray) -> float:
    """The most any hit's sum can be, in flux: every segment's largest channel times the
    largest kernel weight (2)."""
    f = np.asarray(flux, np.float64).reshape(-1, 3)
    return 2.0 * float(f.max(axis=1).sum()) if len(f) else 0.0


def splat_on_device(discs: HitDiscs, a: np.ndarray, b: np.ndarray, d: np.ndarray,
                    flux: np.ndarray, radii: np.ndarray, estimator: str, kernel: str,
                    variant_k: int = 64):
    """Irradiance at every hit of ``discs`` with radius ``radii`` (the caller's hit order)
    from the segments ``a -> b`` (unit directions ``d``, rgb ``flux``; a photon map reads
    its points ``b`` only), left on the device: ``(E, work)``, a float4 per hit in the
    caller's order and the nodes visited and hits tested in total. ``estimator``:
    ``raymap`` (hemisphere-disc, plane-distance weights) or ``photonmap`` (distance);
    ``kernel``: ``box`` or ``epanechnikov``; ``variant_k``: the K of the render's
    K-nearest queries (the splat runs in that build of the ray-map program)."""
    eng = discs.engine
    nh, ns = len(discs), len(a)
    out_e = eng.zeros(16 * max(nh, 1))
    if nh == 0 or ns == 0:
        return out_e, (0, 0)
    if estimator == "photonmap":
        a = b
    r = np.asarray(radii, np.float64)[discs.order]
    hx = _f4(discs.x)
    hx[:, 3] = r
    scale = fixed_scale(flux_bound(flux))
    metric = METRICS["hemidisc" if estimator == "raymap" else "segment"]
    bufs = [eng.to_device(discs.boxes(r)), eng.to_device(hx), eng.to_device(_f4(a)),
            eng.to_device(_f4(b)), eng.to_device(_f4(d)), eng.to_device(_f4(flux)),
            eng.zeros(24 * nh), eng.zeros(8 * ns)]
    nodes, hx_buf, a_buf, b_buf, d_buf, f_buf, acc, work = bufs
    defines = heap_define(variant_k)
    try:
        for first in range(0, ns, LAUNCH_SEGMENTS):
            eng.call("raymap", "rm_splat", min(LAUNCH_SEGMENTS, ns - first), defines,
                     nodes=nodes, levels=discs.levels, num_hits=nh, hx=hx_buf,
                     hn=discs.buf["hn"], seg_a=a_buf, seg_b=b_buf, seg_d=d_buf, seg_flux=f_buf,
                     first=first, num_segs=ns, metric=metric,
                     plane_weights=int(estimator == "raymap"),
                     epanechnikov=int(kernel == "epanechnikov"), fixed_scale=scale, acc=acc,
                     out_work=work)
        eng.call("raymap", "rm_splat_finish", nh, defines, acc=acc, hx=hx_buf,
                 ids=discs.buf["ids"], num_hits=nh, inv_scale=1.0 / scale, out_e=out_e)
        totals = prim.int_totals(eng, work, ns, 2)
    finally:
        eng.free(*bufs)
    return out_e, (int(totals[0]), int(totals[1]))
