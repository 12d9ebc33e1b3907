"""Tile grids: triangles binned over a plane for families of rays (``tile_grid.h``).

A directional light's rays are all parallel. Its shadow map (1.6 M texels at the default
1280 x 1280) sent through the BVH costs ~180 ns a ray on the CPU device, most of it in
traversal of boxes whose outcome is the same for neighbouring rays. The tile grid does
that culling once per light instead of once per ray, as a rasteriser's binning does:

- a rectangle in the plane normal to the rays' direction ``dir`` (axes ``s1``, ``s2``,
  origin ``origin``) is cut into ``nx x ny`` tiles;
- every triangle is listed in each tile its projection overlaps, widened by :data:`PAD`
  of the scene's extent (so a superset of the triangles a ray of the tile can hit,
  whatever float32 does to the ray's origin);
- within a tile the triangles are sorted by ``near``, the smallest axial coordinate
  ``(v - origin).dir`` of their vertices (minus the pad): a ray from ``o`` along ``dir``
  stops testing once ``near - (o - origin).dir`` is past its closest hit so far.

The rays of such a grid all share the watertight test's projection (Woop et al.: a
permutation and shear that depend on the direction only), so it is done once per triangle
here (:func:`raster_triangles`) and a ray evaluates three edge functions in the plane and
a weighted depth (``grid_raster_try``): watertight as the BVH's test, hit distances within
float rounding of the BVH's. The lists are built here in NumPy, row by row of tiles (2-12 ms
for the built-in scenes' 1280-texel maps, which then take 0.04-0.09 s against 0.22-0.39 s
through the BVH: ``tools/bench_tile_grids.py``); :func:`worth_it` says when a grid beats
the BVH.

A *perspective* grid serves rays that share an origin instead (a pinhole camera, a spot
light): plane coordinates are divided by the depth along ``dir`` and the key is a
triangle's least depth, a lower bound of its distance along any unit ray from the
origin. Rays that *end* at the origin (a spot light's shadow rays) use the same lists
from the other side (``grid_any_toward``). Perspective grids test with the BVH's own
function (:c:func:`bvh_triangle`), so the closest distance, and any-hit answers, are the
BVH's to the bit; only which of two triangles at exactly the same distance is reported may
differ. The grids of a scene: :func:`camera_grid`,
:func:`light_grid` (kept in ``SceneBuffers`` and rebuilt when the camera or the lights
change); the shadow maps' own are built in ``methods/epipolar/maps.py``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..device import structs
from ..geometry import box_corners, perpendicular_axes
from .bvh import BVH

F4 = (np.float32, 4)

TILE_GRID = structs.register_struct("tile_grid.h", "TileGrid", np.dtype([
    ("origin", *F4), ("s1", *F4), ("s2", *F4), ("dir", *F4), ("rect", *F4),
    ("nx", np.int32), ("ny", np.int32), ("items", np.int32), ("perspective", np.int32),
    ("light", np.int32), ("starts_at", np.int32), ("items_at", np.int32), ("keys_at", np.int32),
    ("faces", np.int32), ("next", np.int32), ("raster_at", np.int32), ("pad1", np.int32),
], align=True))
HEAD_WORDS = TILE_GRID.itemsize // 4

PAD = 1e-4          # bounding boxes and near keys are widened by this much of the extent
MAX_ITEMS = 1 << 20  # a grid with more (triangle, tile) entries is not built
MAX_MEAN_LIST = 16   # ... nor used when its tiles list more triangles than this on average
MAX_RASTER = 1 << 18  # orthographic grids of more triangles test them as the BVH does
RASTER_WORDS = 20     # per triangle: three edges, their signs, the vertices' depths


@dataclass
class TileGrid:
    """Host side of a tile grid: the TILE_GRID record, per-tile ``starts`` (nx ny + 1,
    int32: tile k lists ``items[starts[k]:starts[k+1]]``), the listed triangles' slots in
    the BVH's reordered array (int32) and their ``keys`` (float32 near coordinates); an
    orthographic grid also has ``raster``, each slot's triangle projected on the grid's
    plane (:func:`raster_triangles`)."""

    record: np.ndarray
    starts: np.ndarray
    items: np.ndarray
    keys: np.ndarray
    raster: np.ndarray | None = None

    @property
    def tiles(self) -> int:
        return len(self.starts) - 1

    @property
    def mean_list(self) -> float:
        """Triangles listed per tile on average (every tile covers as many rays)."""
        return len(self.items) / max(self.tiles, 1)

    def stats(self) -> dict:
        return {"tiles": self.tiles, "entries": int(len(self.items)),
                "mean_list": round(self.mean_list, 2),
                "max_list": int(np.diff(self.starts).max()) if self.tiles else 0}

    def packed(self) -> np.ndarray:
        """The one int32 buffer the kernels take: the TILE_GRID record, then ``starts``,
        ``items``, the ``keys``' float32 bits and the raster's (16-byte aligned, for
        float4 loads; ``raster_at`` 0 without one), at the offsets (in words) the record
        holds, so a kernel threads one parameter through instead of five."""
        rec = self.record.copy()
        rec["faces"] = max(int(rec["faces"]), 1)
        rec["starts_at"] = HEAD_WORDS
        rec["items_at"] = HEAD_WORDS + len(self.starts)
        rec["keys_at"] = HEAD_WORDS + len(self.starts) + len(self.items)
        end = int(rec["keys_at"]) + len(self.keys)
        gap = np.zeros(-end % 4, np.int32)
        raster = np.zeros(0, np.int32)
        rec["raster_at"] = 0
        if self.raster is not None:
            rec["raster_at"] = end + len(gap)
            raster = self.raster.astype(np.float32).ravel().view(np.int32)
        out = np.concatenate([rec.reshape(1).view(np.int32), self.starts.astype(np.int32),
                              self.items.astype(np.int32),
                              self.keys.astype(np.float32).view(np.int32), gap, raster])
        # a whole number of 16-byte words, so a grid packed after this one (a cube's next
        # face) starts aligned for the record's float4 fields
        return np.concatenate([out, np.zeros(-len(out) % 4, np.int32)])


def tiles_for(res: int) -> int:
    """Tiles along each side of a ``res``-texel map: one per ~10 texels, 8 to 128 (finer
    tiles shorten the lists little more while their entries, and the host's binning
    time, grow as the square; measured on the built-in scenes at 1280 texels: 32 tiles
    88-204 ms of kernel, 128 tiles 66-88 ms, 256 tiles 63-85 ms but 9-25 ms to bin)."""
    return int(min(128, max(8, res // 10)))


def build_grid(bvh: BVH, origin, s1, s2, direction, rect, nx: int, ny: int,
               perspective: bool = False) -> TileGrid | None:
    """Bin the BVH's usable triangles (its first ``n_valid`` slots) over ``rect`` =
    (lo1, lo2, hi1, hi2) of the plane spanned by unit ``s1``, ``s2`` through ``origin``,
    for rays along unit ``direction``. A triangle is listed in every tile its projection,
    widened by the pad, overlaps (exactly: row by row, :func:`_strip_extent`); one that
    misses the rectangle is listed nowhere, as rays of the grid cannot hit it. None when
    the lists would exceed :data:`MAX_ITEMS` entries.

    ``perspective``: the rays all start at ``origin`` (a pinhole camera) and the plane
    coordinates are ``(q.s1 / q.dir, q.s2 / q.dir)`` for ``q = p - origin``; the key is
    the triangle's smallest depth ``q.dir``, a lower bound of the distance to any of its
    points for unit rays. A triangle wholly behind the origin is left out; one that
    crosses the plane ``q.dir = 0`` is clipped to its part in front
    (:func:`_perspective_rows`), or listed in every tile when its plane passes near the
    origin."""
    origin, s1, s2, d = (np.asarray(a, np.float64)[:3] for a in (origin, s1, s2, direction))
    lo1, lo2, hi1, hi2 = (float(x) for x in rect)
    w1, w2 = max(hi1 - lo1, 1e-30), max(hi2 - lo2, 1e-30)
    n = int(bvh.n_valid)
    v = bvh.triangles[:n, :, :3].astype(np.float64) - origin            # (n, 3, 3)
    x1, x2, z = v @ s1, v @ s2, v @ d
    scale = max(float(np.abs(v).max()) if n else 0.0, w1, w2, 1.0)
    pad = PAD * scale
    slot, whole = np.arange(n), np.zeros(n, bool)
    if perspective:
        x1, x2, slot, whole = _perspective_rows(v, x1, x2, z, pad, (lo1, lo2, hi1, hi2))
        pad = PAD * max(w1, w2, 1.0)
    fx = (x1 - lo1) * (nx / w1)                   # vertices in tile units
    fy = (x2 - lo2) * (ny / w2)
    px, py = pad * nx / w1, pad * ny / w2
    # every (triangle, tile row) pair of the padded bounding boxes ...
    j0 = np.clip(np.floor(fy.min(axis=1) - py), 0, ny - 1).astype(np.int64)
    j1 = np.clip(np.floor(fy.max(axis=1) + py), -1, ny - 1).astype(np.int64)
    rows = np.maximum(j1 - j0 + 1, 0)
    tri = np.repeat(np.arange(len(slot)), rows)
    row = np.arange(len(tri)) - np.repeat(np.cumsum(rows) - rows, rows) + j0[tri]
    # ... and the columns the triangle covers in that row's (padded) strip
    xmin, xmax = _strip_extent(fx[tri], fy[tri], row - py, row + 1.0 + py)
    everywhere = whole[tri]
    xmin[everywhere], xmax[everywhere] = 0.0, float(nx)
    i0 = np.clip(np.floor(xmin - px), 0, nx - 1).astype(np.int64)
    i1 = np.clip(np.floor(xmax + px), -1, nx - 1).astype(np.int64)
    i1[(xmax + px < 0) | (xmin - px >= nx)] = -1
    cols = np.maximum(i1 - i0 + 1, 0)
    total = int(cols.sum())
    if total > MAX_ITEMS:
        return None
    pair = np.repeat(np.arange(len(tri)), cols)
    ti = np.arange(total) - np.repeat(np.cumsum(cols) - cols, cols) + i0[pair]
    tile = row[pair] * nx + ti
    owner = slot[tri[pair]]
    near = z.min(axis=1) - PAD * scale
    # one sort: by tile, then by near within a tile (near scaled into [0, 0.5))
    lo_near = float(near.min()) if n else 0.0
    span = max(float(near.max()) - lo_near if n else 0.0, 1e-30)
    order = np.argsort(tile + 0.5 * (near[owner] - lo_near) / span, kind="stable")
    tile, owner = tile[order], owner[order]
    if len(slot) > n:               # clipped triangles come in two parts: list them once
        keep = np.ones(len(tile), bool)
        keep[1:] = (tile[1:] != tile[:-1]) | (owner[1:] != owner[:-1])
        tile, owner = tile[keep], owner[keep]
        total = len(tile)
    starts = np.zeros(nx * ny + 1, np.int32)
    np.cumsum(np.bincount(tile, minlength=nx * ny), out=starts[1:])
    rec = np.zeros((), TILE_GRID)
    rec["origin"] = structs.vec4(origin)
    rec["s1"] = structs.vec4(s1)
    rec["s2"] = structs.vec4(s2)
    rec["dir"] = structs.vec4(d)
    rec["rect"] = (lo1, lo2, hi1, hi2)
    rec["nx"], rec["ny"], rec["items"] = nx, ny, total
    rec["perspective"], rec["light"] = int(perspective), -1
    raster = None if perspective or n > MAX_RASTER else raster_triangles(x1, x2, z)
    return TileGrid(rec, starts, owner.astype(np.int32), near[owner].astype(np.float32),
                    raster)


def raster_triangles(x1: np.ndarray, x2: np.ndarray, z: np.ndarray) -> np.ndarray:
    """An orthographic grid's triangles as its rays see them (``grid_raster_try``):
    float32 (n, :data:`RASTER_WORDS`) from the vertices' plane coordinates ``x1``,
    ``x2`` and axial coordinates ``z`` (n, 3), relative to the grid's origin.

    Rays along the grid's direction all share the watertight test's projection, so it is
    done once here: the edge opposite vertex i (from vertex i + 1 to i + 2) is stored as
    a start point and a direction in the plane, in a canonical order (the lesser end
    first, as ``bvh_edge`` orders its operands) with the sign that restores the
    triangle's orientation. Two triangles sharing an edge store it identically, with
    opposite signs, so their edge functions at any ray are exact negatives and a ray
    through the edge meets one of them (or both, exactly on it). Words: the three edges
    (start x, start y, direction x, direction y), then the three signs and 0, then the
    three vertex depths and 0."""
    n = len(x1)
    a1, a2 = x1.astype(np.float32), x2.astype(np.float32)
    out = np.zeros((n, RASTER_WORDS), np.float32)
    for e in range(3):
        i, j = (e + 1) % 3, (e + 2) % 3
        ax, ay, bx, by = a1[:, i], a2[:, i], a1[:, j], a2[:, j]
        swap = (ax > bx) | ((ax == bx) & (ay > by))
        px, py = np.where(swap, bx, ax), np.where(swap, by, ay)
        qx, qy = np.where(swap, ax, bx), np.where(swap, ay, by)
        out[:, 4 * e:4 * e + 4] = np.stack([px, py, qx - px, qy - py], 1)
        out[:, 12 + e] = np.where(swap, -1.0, 1.0)
    out[:, 16:19] = z
    return out


def _perspective_rows(v, x1, x2, z, pad: float, rect):
    """The rows a perspective grid bins, from triangles ``v`` (n, 3, 3; relative to the
    origin) with plane coordinates ``x1``, ``x2`` and depths ``z`` (n, 3): projected
    triangles ``(x1 / z, x2 / z)``, each row's triangle slot, and which rows cover the
    whole rectangle.

    - In front (every depth above ``zc = pad``): projected as they are.
    - Behind (no depth above 0): left out, as rays of the grid go forwards.
    - Crossing: clipped to ``z >= zc`` (a triangle or a quad, binned as one or two
      triangles). The part left out, at depths below ``zc``, projects into the rectangle
      only within ``zc (1 + sqrt(2) R)`` of the origin (R: the rectangle's largest
      tangent), so a crossing triangle whose plane passes that close is listed everywhere
      instead. A camera inside a room sees its walls and floor clipped, not everywhere.
    - Between (every depth below ``zc``, some above 0; e.g. a ball lying on a cube face's
      axis, seen from a light far above it, for the side faces): listed everywhere when
      its plane passes that close to the origin, else left out, as no ray of the grid
      meets it (nothing would be left of it to project).
    """
    lo1, lo2, hi1, hi2 = rect
    zc = pad
    zmin, zmax = z.min(axis=1), z.max(axis=1)
    front = zmin > zc
    crossing = ~front & (zmax > 0.0)
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = np.abs(np.einsum("ij,ij->i", nrm, v[:, 0])) / np.linalg.norm(nrm, axis=1)
    reach = 2.0 * zc * (1.0 + math.sqrt(2.0) * max(abs(lo1), abs(hi1), abs(lo2), abs(hi2)))
    everywhere = crossing & ~(plane > reach)
    clip = np.nonzero(crossing & ~everywhere & (zmax >= zc))[0]
    # Sutherland-Hodgman against z >= zc: up to 4 vertices per clipped triangle, in order
    P = np.stack([x1[clip], x2[clip], z[clip]], axis=-1)                 # (m, 3, 3)
    pts = np.zeros((len(clip), 6, 3))
    ok = np.zeros((len(clip), 6), bool)
    for e in range(3):
        a, b = P[:, e], P[:, (e + 1) % 3]
        ina, inb = a[:, 2] >= zc, b[:, 2] >= zc
        pts[:, 2 * e], ok[:, 2 * e] = a, ina
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (zc - a[:, 2]) / (b[:, 2] - a[:, 2])
        t = np.where(ina != inb, t, 0.0)               # used only where the edge crosses
        pts[:, 2 * e + 1] = a + t[:, None] * (b - a)
        pts[:, 2 * e + 1, 2] = zc
        ok[:, 2 * e + 1] = ina != inb
    first = np.argsort(~ok, axis=1, kind="stable")[:, :4]               # valid ones, in order
    poly = np.take_along_axis(pts, first[:, :, None], axis=1)           # (m, 4, 3)
    quad = ok.sum(axis=1) == 4
    sub = np.concatenate([poly[:, [0, 1, 2]], poly[quad][:, [0, 2, 3]]])  # fan
    sub_slot = np.concatenate([clip, clip[quad]])
    keep = np.nonzero(front)[0]
    wide = np.nonzero(everywhere)[0]
    zs = np.concatenate([z[keep], sub[:, :, 2]])
    rx1 = np.concatenate([x1[keep], sub[:, :, 0]]) / zs
    rx2 = np.concatenate([x2[keep], sub[:, :, 1]]) / zs
    # everywhere: a triangle spanning the whole rectangle's rows and columns
    rx1 = np.concatenate([rx1, np.tile([lo1, hi1, lo1], (len(wide), 1))])
    rx2 = np.concatenate([rx2, np.tile([lo2, hi2, hi2], (len(wide), 1))])
    slot = np.concatenate([keep, sub_slot, wide])
    whole = np.concatenate([np.zeros(len(keep) + len(sub), bool), np.ones(len(wide), bool)])
    return rx1, rx2, slot, whole


def _strip_extent(fx: np.ndarray, fy: np.ndarray, ylo: np.ndarray, yhi: np.ndarray):
    """x-extent of each triangle (rows of ``fx``, ``fy``: its three projected vertices)
    inside the strip ``ylo <= y <= yhi``: the part of a convex polygon in a strip is
    spanned by its edges clipped to the strip, so the extent is that of the clipped
    edges' end points (+inf, -inf where the triangle misses the strip). A triangle seen
    edge-on is a segment and gets the segment's extent."""
    xmin = np.full(len(fx), np.inf)
    xmax = np.full(len(fx), -np.inf)
    for e in range(3):
        xa, ya = fx[:, e], fy[:, e]
        xb, yb = fx[:, (e + 1) % 3], fy[:, (e + 1) % 3]
        dy = yb - ya
        flat = dy == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = np.where(flat, 0.0, (ylo - ya) / np.where(flat, 1.0, dy))
            t2 = np.where(flat, 1.0, (yhi - ya) / np.where(flat, 1.0, dy))
        lo = np.maximum(np.minimum(t1, t2), 0.0)
        hi = np.minimum(np.maximum(t1, t2), 1.0)
        ok = np.where(flat, (ya >= ylo) & (ya <= yhi), lo <= hi)
        xl, xh = xa + lo * (xb - xa), xa + hi * (xb - xa)
        xmin = np.where(ok, np.minimum(xmin, np.minimum(xl, xh)), xmin)
        xmax = np.where(ok, np.maximum(xmax, np.maximum(xl, xh)), xmax)
    return xmin, xmax


def worth_it(grid: TileGrid | None) -> bool:
    """A grid replaces the BVH for its rays when it exists and its lists are short: a
    ray tests its tile's triangles up to its closest hit (~5 ns each on the CPU device)
    against ~180 ns for a BVH traversal of the built-in scenes."""
    return grid is not None and grid.mean_list <= MAX_MEAN_LIST


SCENE_TILES = 128     # tiles along each side of a light grid


def light_grid(bvh: BVH, lights: np.ndarray,
               box: tuple[np.ndarray, np.ndarray] | None = None) -> TileGrid | None:
    """The grid for the shadow rays of one light; its record's ``light`` is that light's
    index. The scene's first directional light gets an orthographic grid (rays from
    surface points towards the light are parallel) over the projection of ``box`` (the
    scene's bounding box in the normalised frame, far objects left out; None: the BVH's
    box), so every surface point near the camera falls in a tile; the grid lists every
    triangle, far ones included, whose projection meets it, and points outside it ask the
    BVH. Keeping far objects out of the rectangle keeps the grid's plane coordinates, taken
    from its centre, as precise as the near geometry needs. Without one, the first spot
    light of at most 60 degrees gets a perspective grid from its position over its cone,
    else the first point (or wider spot) light a cube of six (:class:`CubeGrid`); their
    shadow rays all end at the light (``grid_any_toward``). None without lights, or where
    the grid would not pay."""
    lights = np.atleast_1d(lights)
    kinds = [int(li["type"]) for li in lights]
    if int(bvh.n_valid) == 0:
        return None
    if structs.LIGHT_DIRECTIONAL in kinds:
        li = kinds.index(structs.LIGHT_DIRECTIONAL)
        grid = _parallel_grid(bvh, -np.asarray(lights[li]["direction"][:3], np.float64), box)
    else:
        cone = [i for i, k in enumerate(kinds) if k == structs.LIGHT_SPOT
                and float(lights[i]["cos_cutoff"]) >= SPOT_GRID_COS]
        if cone:
            li = cone[0]
            grid = _cone_grid(bvh, lights[li])
        else:
            point = [i for i, k in enumerate(kinds) if k in (structs.LIGHT_POINT, structs.LIGHT_SPOT)]
            if not point:
                return None
            li = point[0]
            faces = _cube_grids(bvh, lights[li])
            if faces is None:
                return None
            for f in faces:
                f.record["light"] = li
            return CubeGrid(faces)
    if not worth_it(grid):
        return None
    grid.record["light"] = li
    return grid


SPOT_GRID_COS = 0.5 - 1e-6   # spot cones up to 60 degrees get a light grid (one face)


def _parallel_grid(bvh: BVH, d: np.ndarray,
                   box: tuple[np.ndarray, np.ndarray] | None = None) -> TileGrid | None:
    """Orthographic grid along unit-ised ``d`` over ``box`` (None: the BVH's box)."""
    d = d / np.linalg.norm(d)
    s1, s2 = perpendicular_axes(d)
    if box is None:
        box = (bvh.nodes[0]["bmin"], bvh.nodes[0]["bmax"])
    lo, hi = (np.asarray(b, np.float64) for b in box)
    centre = 0.5 * (lo + hi)
    corners = box_corners(lo, hi) - centre
    c1, c2 = corners @ s1, corners @ s2
    m1, m2 = 1e-3 * np.ptp(c1) + 1e-6, 1e-3 * np.ptp(c2) + 1e-6
    return build_grid(bvh, centre, s1, s2, d, (c1.min() - m1, c2.min() - m2,
                                               c1.max() + m1, c2.max() + m2),
                      SCENE_TILES, SCENE_TILES)


CUBE_TILES = 64    # tiles along each side of a cube face (a point light's grid)
_CUBE_AXES = np.eye(3)


def _cube_grids(bvh: BVH, light) -> list[TileGrid] | None:
    """Six perspective grids from a point light, one per cube face (face ``2 k + s``: axis
    ``k``, ``s = 1`` the negative side; each a thousandth wider than 90 degrees), or None
    when one would not pay."""
    faces = []
    for k in range(3):
        s1, s2 = _CUBE_AXES[(k + 1) % 3], _CUBE_AXES[(k + 2) % 3]
        for sign in (1.0, -1.0):
            g = build_grid(bvh, light["position"][:3], s1, s2, sign * _CUBE_AXES[k],
                           (-1.001, -1.001, 1.001, 1.001), CUBE_TILES, CUBE_TILES,
                           perspective=True)
            if not worth_it(g):
                return None
            faces.append(g)
    return faces


@dataclass
class CubeGrid:
    """A point light's six face grids, packed one after another (each record's ``next``
    is the offset in words to the following face; ``faces`` = 6 in the first)."""

    faces: list[TileGrid]

    def stats(self) -> dict:
        st = [f.stats() for f in self.faces]
        return {"faces": len(st), "tiles": sum(x["tiles"] for x in st),
                "entries": sum(x["entries"] for x in st),
                "mean_list": round(sum(x["entries"] for x in st) / max(sum(x["tiles"] for x in st), 1), 2),
                "max_list": max(x["max_list"] for x in st)}

    def packed(self) -> np.ndarray:
        parts = [f.packed() for f in self.faces]
        for i, p in enumerate(parts):
            rec = p[:HEAD_WORDS].view(TILE_GRID)
            rec["faces"] = len(parts) if i == 0 else 1
            rec["next"] = len(p) if i + 1 < len(parts) else 0
        return np.concatenate(parts)


def _cone_grid(bvh: BVH, light) -> TileGrid | None:
    """Perspective grid from a spot light over its cone (a hundredth wider)."""
    a = np.asarray(light["direction"][:3], np.float64)
    a /= np.linalg.norm(a)
    s1, s2 = perpendicular_axes(a)
    c = float(np.clip(light["cos_cutoff"], 1e-6, 1.0))
    ext = 1.01 * math.sqrt(max(1.0 - c * c, 0.0)) / c + 1e-6
    return build_grid(bvh, light["position"][:3], s1, s2, a, (-ext, -ext, ext, ext),
                      SCENE_TILES, SCENE_TILES, perspective=True)


def camera_grid(bvh: BVH, camera: np.ndarray) -> TileGrid | None:
    """The perspective grid for the camera's primary rays (all from its origin; the
    image's field of view, a thousandth wider, cut into ~10-pixel tiles). None where it
    would not pay."""
    if int(bvh.n_valid) == 0:
        return None
    cam = np.asarray(camera).reshape(())
    right = np.asarray(cam["right"][:3], np.float64)
    up = np.asarray(cam["up"][:3], np.float64)
    tx, ty = float(np.linalg.norm(right)), float(np.linalg.norm(up))
    if not (tx > 0 and ty > 0):
        return None
    nx = int(min(SCENE_TILES, max(8, int(cam["width"]) // 10)))
    ny = int(min(SCENE_TILES, max(8, int(cam["height"]) // 10)))
    grid = build_grid(bvh, cam["origin"][:3], right / tx, up / ty, cam["forward"][:3],
                      (-1.001 * tx, -1.001 * ty, 1.001 * tx, 1.001 * ty), nx, ny,
                      perspective=True)
    return grid if worth_it(grid) else None


def empty_packed() -> np.ndarray:
    """A packed grid with no tiles (nx = 0): kernels given it use the BVH."""
    rec = np.zeros((), TILE_GRID)
    rec["light"] = -1
    return rec.reshape(1).view(np.int32).copy()


def upload(engine, grid: TileGrid | CubeGrid | None):
    """A device buffer of ``grid`` packed (:meth:`TileGrid.packed`); None gives an empty
    grid (the kernels then use the BVH). The caller frees it."""
    return engine.to_device(grid.packed() if grid is not None else empty_packed())


def trace_grid(engine, bvh: BVH, grid: TileGrid, origins: np.ndarray, tmin: float = 0.0,
               tmax: float = np.inf, any_hit: bool = False, dirs: np.ndarray | None = None):
    """Rays from ``origins`` (N, 3) along the grid's direction (or along unit ``dirs``, for
    a perspective grid) through the ``grid_hit`` test kernel (``cl_kernels/bvh.cl``), the counterpart of :func:`bvh.trace`: closest hit
    ``(t, slot)`` (t: inf on a miss, NaN outside the grid; slot: the BVH's reordered
    triangle, -1 miss, -2 outside) or, with ``any_hit``, a bool array."""
    o = np.zeros((len(origins), 4), np.float32)
    o[:, :3] = np.asarray(origins, np.float64)[:, :3]
    n = len(o)
    bufs = bvh.device_buffers(engine)
    gb = upload(engine, grid)
    ob, tb, ib = engine.to_device(o), engine.empty(4 * max(n, 1)), engine.empty(4 * max(n, 1))
    db = engine.to_device(np.zeros((max(len(o), 1), 4), np.float32) if dirs is None else
                          np.concatenate([np.asarray(dirs, np.float32)[:, :3],
                                          np.zeros((len(o), 1), np.float32)], axis=1))
    try:
        engine.call("bvh", "grid_hit", n, tris=bufs.triangles, grid=gb, orig=ob, dir=db,
                    own_dir=int(dirs is not None), tmin=tmin, tmax=min(tmax, 3e38),
                    any=int(any_hit), n=n, t_out=tb, tri_out=ib)
        t = engine.read(tb, n, np.float32)
        slot = engine.read(ib, n, np.int32)
    finally:
        engine.free(ob, db, tb, ib, gb)
    return t == 1.0 if any_hit else (t, slot)


def trace_toward(engine, bvh: BVH, grid: TileGrid | CubeGrid, origins: np.ndarray,
                 tmin: float = 0.0):
    """Shadow rays from ``origins`` (N, 3) to a perspective grid's origin through the
    ``grid_toward_hit`` test kernel: int array, 1 blocked, 0 clear, -1 outside the grid."""
    o = np.zeros((len(origins), 4), np.float32)
    o[:, :3] = np.asarray(origins, np.float64)[:, :3]
    n = len(o)
    bufs = bvh.device_buffers(engine)
    gb = upload(engine, grid)
    ob, out = engine.to_device(o), engine.empty(4 * max(n, 1))
    try:
        engine.call("bvh", "grid_toward_hit", n, tris=bufs.triangles, grid=gb, orig=ob,
                    tmin=tmin, n=n, out=out)
        return engine.read(out, n, np.int32)
    finally:
        engine.free(ob, out, gb)
