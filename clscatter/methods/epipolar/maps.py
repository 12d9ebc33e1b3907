"""Ray-traced shadow map and camera depth map (``epi_shadow_map``, ``epi_depth_map``).

Directional light: an orthographic map looking along the light, over the projection of
the medium box onto the plane normal to the light (axes ``b1, b2`` of the epipolar
frame, so that a light ray ``eye + gamma w`` lands at ``gamma (w.b1, w.b2)``); rays start
beyond every object and the medium on the light's side, and the map stores the axial
coordinate ``z = (hit - eye).u`` of the first hit. Spot light: perspective maps over the
cone (:func:`spot_faces`: one map up to 60 degrees, five cube faces beyond, up to 90),
storing the distance of the first hit from the light. ``T_INF`` (1e30) marks texels whose ray hits nothing.
"""
from __future__ import annotations

import math

import numpy as np

from ...accel import tile_grid
from ...device import structs
from ...geometry import box_corners, perpendicular_axes
from ...transport.prepared import PreparedScene
from .geometry import EPI_FACE, Axis, CameraGeom, medium_box

T_INF = 1e30


def _scene_corners(ps: PreparedScene, light_dir: np.ndarray | None = None) -> np.ndarray:
    """Corners of the near triangles' box (:meth:`PreparedScene.near_box`: far objects
    left out) and of the medium box (normalised frame); with ``light_dir`` (a directional
    light's unit travel direction) also of the far objects that may shadow them from it
    (:meth:`~clscatter.scene.model.Scene.far_in_beam`)."""
    pts = []
    near = ps.near_box()
    if near is not None:
        pts.append(near)
    if light_dir is not None:
        pts += [(ps.frame.point(lo), ps.frame.point(hi))
                for _, lo, hi in ps.scene.far_in_beam(light_dir)]
    box = medium_box(ps.medium)
    if box is not None:
        pts.append(box)
    return np.concatenate([box_corners(lo, hi) for lo, hi in pts]) if pts else np.zeros((0, 3))


WIDE = math.radians(60.0)     # cones wider than this get five cube faces
MAX_FACE = 8192               # texels along a face


def cube_resolution(axis: Axis, ps: PreparedScene, res: int, pixel_angle: float) -> int:
    """Texels across a cube face (90 degrees) that the image needs: a texel of angle
    ``delta`` seen from the light spans ``r delta`` at distance ``r`` from it, which the
    camera at distance ``t`` sees under ``r delta / t``; half a pixel of that at the
    medium's (or the scene's) centre gives ``delta = 0.5 p t / r``. Clamped to [512, res]:
    a wide cone costs at most 3 res^2 texels, and no more than the image resolves."""
    box = medium_box(ps.medium)
    pts = _scene_corners(ps) if box is None else np.array(box)
    c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    r = max(float(np.linalg.norm(c - axis.light)), 1e-6)
    t = max(float(np.linalg.norm(c - axis.eye)), 1e-6)
    delta = 0.5 * pixel_angle * t / r
    return int(min(res, max(512, math.ceil(2.0 / delta))))


def spot_faces(axis: Axis, res: int, cube_res: int | None = None) -> np.ndarray:
    """The perspective maps (EPI_FACE array) covering a spot light's cone, ``res`` texels
    across a 90-degree field (the texel pitch, 2 / res in tangent units at a face's centre,
    is what the image asks for; see :func:`map_resolution`).

    Half-angle <= 60 degrees: one map over ``+-tan(half)`` (half a texel beyond the
    cone's edge) with ``max(res, res tan(half))`` texels across, so a wider cone keeps the
    pitch of a 45-degree one instead of stretching the same texels (60 degrees: 1.73 x
    the texels across). Wider, up to 90 (a hemisphere): five faces of a cube around the
    cone axis, the front face over +-45 degrees and the forward halves of the four side
    faces (res x (res/2 + 1) each): every direction of the cone falls in one (cube-map
    selection by the largest component, epi_face_of), none is left unshadowed, and the
    pitch stays 2 / n at the faces' centres (1 / n at their edges) at 3 n^2 texels
    instead of a single map whose pitch grows as 1 / cos^2 towards 90 degrees; ``n`` is
    ``cube_res`` (:func:`cube_resolution`, the image's need) or ``res``."""
    a = axis.cone_axis
    s1, s2 = perpendicular_axes(a)
    half = math.acos(max(min(axis.cos_cut, 1.0), -1.0))
    spec = []
    if half <= WIDE + 1e-5:            # cos_cut is float32: 60.0 must stay one map
        ext = math.tan(half)
        n = int(min(MAX_FACE, max(res, math.ceil(res * ext))))
        ext *= 1.0 + 1.0 / n                          # half a texel beyond the cone's edge
        spec.append((a, s1, s2, (-ext, -ext, ext, ext), n, n))
    else:
        n = int(min(MAX_FACE, cube_res or res))
        spec.append((a, s1, s2, (-1.0, -1.0, 1.0, 1.0), n, n))
        for c, e1 in ((s1, s2), (-s1, s2), (s2, s1), (-s2, s1)):
            # x2 = l.a / l.c in [0, 1]: the half of the side face in front of the light,
            # plus one texel behind it so that the rim of a 90-degree cone (l.a = 0, or
            # a rounding below) is inside
            spec.append((c, e1, a, (-1.0, -2.0 / n, 1.0, 1.0), n, n // 2 + 1))
    faces = np.zeros(len(spec), EPI_FACE)
    off = 0
    for f, (c, e1, e2, rect, nx, ny) in enumerate(spec):
        faces[f]["c"] = structs.vec4(c, float(nx))
        faces[f]["e1"] = structs.vec4(e1, float(ny))
        faces[f]["e2"] = structs.vec4(e2, float(off))
        faces[f]["rect"] = rect
        off += nx * ny
    return faces


def face_texels(faces: np.ndarray) -> int:
    return int(sum(int(f["c"][3]) * int(f["e1"][3]) for f in faces))


def setup_shadow_map(frame: np.ndarray, axis: Axis, ps: PreparedScene, res: int) -> np.ndarray:
    """Fill the shadow-map fields of an EPI_FRAME (extent, axes, start plane); returns the
    spot light's faces (:func:`spot_faces`; one unused face for a directional light)."""
    frame["sm_res"] = int(res)
    if axis.spot:
        cam = CameraGeom.from_struct(ps.camera)
        faces = spot_faces(axis, res, cube_resolution(axis, ps, res, cam.pixel_angle()))
        frame["sm_faces"] = len(faces)
        # the first face's axes, for tools that read one map
        frame["sm_s1"] = structs.vec4(faces[0]["e1"][:3])
        frame["sm_s2"] = structs.vec4(faces[0]["e2"][:3])
        frame["sm_rect"] = faces[0]["rect"]
        return faces
    box = medium_box(ps.medium)
    corners = _scene_corners(ps, -np.asarray(axis.u, np.float64))
    box_c = _scene_corners(ps) if box is None else box_corners(*box)
    rel = box_c - axis.eye
    c1, c2 = rel @ axis.b1, rel @ axis.b2
    pad1 = 0.5 * (c1.max() - c1.min()) / res + 1e-6
    pad2 = 0.5 * (c2.max() - c2.min()) / res + 1e-6
    frame["sm_s1"] = structs.vec4(axis.b1)
    frame["sm_s2"] = structs.vec4(axis.b2)
    frame["sm_rect"] = [c1.min() - pad1, c2.min() - pad2, c1.max() + pad1, c2.max() + pad2]
    z = (corners - axis.eye) @ axis.u
    frame["z_start"] = float(z.max() + 1e-3 * max(float(np.ptp(z)), 1e-3))
    frame["sm_faces"] = 0
    return np.zeros(1, EPI_FACE)


def shadow_map_grid(ps: PreparedScene, frame: np.ndarray,
                    faces: np.ndarray | None = None) -> tile_grid.TileGrid | None:
    """The tile grid over a shadow map (:mod:`clscatter.accel.tile_grid`): orthographic
    for a directional light (its texels are parallel rays along ``-u``), perspective
    from the light for a spot light's single map (its texels are rays from the light
    through the map's plane); None for the five faces of a wide cone, or where the grid
    would not beat the BVH (:func:`tile_grid.worth_it`)."""
    if int(ps.bvh.n_valid) == 0:
        return None
    if int(frame["sm_faces"]) == 0:
        nt = tile_grid.tiles_for(int(frame["sm_res"]))
        grid = tile_grid.build_grid(ps.bvh, frame["eye"], frame["sm_s1"], frame["sm_s2"],
                                    -np.asarray(frame["u"], np.float64), frame["sm_rect"],
                                    nt, nt)
    elif int(frame["sm_faces"]) == 1 and faces is not None:
        f = faces[0]
        nt = tile_grid.tiles_for(int(f["c"][3]))
        grid = tile_grid.build_grid(ps.bvh, frame["light"], f["e1"], f["e2"], f["c"],
                                    f["rect"], nt, nt, perspective=True)
    else:
        return None
    return grid if tile_grid.worth_it(grid) else None


def trace_shadow_map(ps: PreparedScene, frame_buf, res: int, defines: dict | None = None,
                     faces: np.ndarray | None = None, faces_buf=None,
                     frame: np.ndarray | None = None, info: dict | None = None):
    """Device buffer of the shadow map of the frame in ``frame_buf``: res * res floats
    (directional), or the spot faces' texels one face after the other (``defines``: those
    of the epipolar program in use, so it is built once). Given the host ``frame``, the
    texels of a directional map or a spot light's single map go through a tile grid
    where one pays
    (:func:`shadow_map_grid`; the same depths as the BVH); ``info`` then receives
    ``shadow_map_caster`` (``grid`` with the grid's list statistics, or ``bvh``)."""
    eng = ps.engine
    n = res * res if faces is None or not int(faces[0]["c"][3]) else face_texels(faces)
    out = eng.empty(4 * n)
    own = faces_buf is None
    fb = eng.to_device(faces if faces is not None else np.zeros(1, EPI_FACE)) if own else faces_buf
    grid = shadow_map_grid(ps, frame, faces) if frame is not None else None
    if info is not None:
        info["shadow_map_caster"] = ({"kind": "grid", **grid.stats()} if grid is not None
                                     else {"kind": "bvh"})
    gb = tile_grid.upload(eng, grid)
    try:
        ps.call("epipolar", "epi_shadow_map", n, defines, fr=frame_buf, faces=fb, grid=gb, ntex=n, out=out)
    finally:
        eng.finish()
        eng.free(gb)
        if own:
            eng.free(fb)
    return out


def trace_depth_map(ps: PreparedScene, width: int, height: int, defines: dict | None = None):
    """Device buffer (height * width floats): distance to the first surface along the
    camera ray through each pixel centre of a width x height raster (T_INF: none)."""
    eng = ps.engine
    out = eng.empty(4 * width * height)
    ps.call("epipolar", "epi_depth_map", width * height, defines, w=width, h=height, out=out)
    return out
