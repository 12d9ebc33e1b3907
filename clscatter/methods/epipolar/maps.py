"""Ray-traced shadow map and camera depth map (``epi_shadow_map``, ``epi_depth_map``).

Directional light: an orthographic map looking along the light, over the projection of
the medium box onto the plane normal to the light (axes ``b1, b2`` of the epipolar
frame, so that a light ray ``eye + gamma w`` lands at ``gamma (w.b1, w.b2)``); rays start
beyond every object and the medium on the light's side, and the map stores the axial
coordinate ``z = (hit - eye).u`` of the first hit. Spot light: a perspective map over the
cone (half-angle plus half a texel), storing the distance of the first hit from the
light. ``T_INF`` (1e30) marks texels whose ray hits nothing.
"""
from __future__ import annotations

import math

import numpy as np

from ... import structs
from ...prepared import PreparedScene
from .geometry import Axis, medium_box

T_INF = 1e30


def _scene_corners(ps: PreparedScene) -> np.ndarray:
    """Corners of the objects' bounding box and of the medium box (normalised frame)."""
    pts = []
    if len(ps.bvh.nodes) and int(ps.bvh.n_valid) > 0:
        root = ps.bvh.nodes[0]
        pts.append((np.asarray(root["bmin"], np.float64), np.asarray(root["bmax"], np.float64)))
    box = medium_box(ps.medium)
    if box is not None:
        pts.append(box)
    out = []
    for lo, hi in pts:
        for i in range(8):
            out.append([hi[k] if (i >> k) & 1 else lo[k] for k in range(3)])
    return np.array(out, np.float64).reshape(-1, 3)


def setup_shadow_map(frame: np.ndarray, axis: Axis, ps: PreparedScene, res: int) -> None:
    """Fill the shadow-map fields of an EPI_FRAME (extent, axes, start plane)."""
    frame["sm_res"] = int(res)
    if axis.spot:
        a = axis.cone_axis
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        s1 = np.cross(a, helper)
        s1 /= np.linalg.norm(s1)
        s2 = np.cross(a, s1)
        half = math.acos(max(min(axis.cos_cut, 1.0), -1.0))
        ext = math.tan(min(half, math.radians(89.0)))
        ext *= 1.0 + 1.0 / res                        # half a texel beyond the cone's edge
        frame["sm_s1"] = structs.vec4(s1)
        frame["sm_s2"] = structs.vec4(s2)
        frame["sm_rect"] = [-ext, -ext, ext, ext]
        return
    box = medium_box(ps.medium)
    corners = _scene_corners(ps)
    box_c = corners if box is None else np.array(
        [[box[1][k] if (i >> k) & 1 else box[0][k] for k in range(3)] for i in range(8)])
    rel = box_c - axis.eye
    c1, c2 = rel @ axis.b1, rel @ axis.b2
    pad1 = 0.5 * (c1.max() - c1.min()) / res + 1e-6
    pad2 = 0.5 * (c2.max() - c2.min()) / res + 1e-6
    frame["sm_s1"] = structs.vec4(axis.b1)
    frame["sm_s2"] = structs.vec4(axis.b2)
    frame["sm_rect"] = [c1.min() - pad1, c2.min() - pad2, c1.max() + pad1, c2.max() + pad2]
    z = (corners - axis.eye) @ axis.u
    frame["z_start"] = float(z.max() + 1e-3 * max(float(np.ptp(z)), 1e-3))


def trace_shadow_map(ps: PreparedScene, frame_buf, res: int, defines: dict | None = None):
    """Device buffer (res * res floats) of the shadow map of the frame in ``frame_buf``
    (``defines``: those of the epipolar program in use, so it is built once)."""
    eng = ps.engine
    out = eng.empty(4 * res * res)
    eng.launch(eng.kernel("epipolar", "epi_shadow_map", defines), res * res, ps.buf["nodes"],
               ps.buf["tris"], frame_buf, out)
    return out


def trace_depth_map(ps: PreparedScene, width: int, height: int, defines: dict | None = None):
    """Device buffer (height * width floats): distance to the first surface along the
    camera ray through each pixel centre of a width x height raster (T_INF: none)."""
    eng = ps.engine
    out = eng.empty(4 * width * height)
    eng.launch(eng.kernel("epipolar", "epi_depth_map", defines), width * height, ps.buf["nodes"],
               ps.buf["tris"], ps.buf["camera"], np.int32(width), np.int32(height), out)
    return out
