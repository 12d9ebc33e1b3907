"""Closing the holes of a scanned mesh (a mesh object's ``close_holes``).

Glass and volumes need a closed surface. A scan often has holes (the Stanford bunny has
five in its base); each hole is bounded by a loop of edges that one triangle alone uses
(holes that touch at a vertex are separate loops). :func:`fill_holes` triangulates every
such loop in the plane that fits it best (ear clipping of its projection, with no ear
whose new side is an edge of the mesh already), so the fill adds no vertices and k - 2
triangles a loop of k. The fill's triangles take the winding of the triangles around the
hole: each of the loop's edges is used once by its old triangle and once, the other way
round, by the fill, so a consistently wound surface stays so. Where no ear is left (the
loop's projection is not a simple polygon) or the loop is longer than
:data:`MAX_CLIPPED`, the rest of the loop is fanned around its centroid, which adds one
vertex.
"""
from __future__ import annotations

import numpy as np

from ..geometry import boundary_edges, edge_keys, mesh_edges

#: loops longer than this are fanned around their centroid (ear clipping takes O(k^2)
#: corner tests, O(k^3) at worst)
MAX_CLIPPED = 512


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The loops of edges that only one triangle uses (vertex indices; shared vertices
    merged), each in the direction opposite to its triangles' winding: the order a fill
    with matching winding runs through it. Holes that touch at a vertex are separate loops
    (each passes a vertex once); every boundary edge is in exactly one loop."""
    ahead: dict[int, list[int]] = {}
    for a, b in boundary_edges(faces).tolist():     # a -> b as its triangle winds
        ahead.setdefault(b, []).append(a)            # the fill runs b -> a
    loops = []
    while ahead:
        start = next(iter(ahead))
        loop, cur = [start], start
        while True:
            outs = ahead.get(cur)
            if not outs:                             # an open chain (not manifold): stop
                break
            nxt = outs.pop()
            if not outs:
                del ahead[cur]
            if nxt == start:
                break
            loop.append(nxt)
            cur = nxt
        loops += [np.array(x, np.int64) for x in _simple_loops(loop) if len(x) >= 3]
    return loops


def _simple_loops(loop: list[int]) -> list[list[int]]:
    """``loop`` cut at the vertices it passes twice (holes that touch at a corner) into
    loops that pass each vertex once, in the same order and direction."""
    path: list[int] = []
    where: dict[int, int] = {}
    out = []
    for x in loop:
        if x in where:                    # back at x: what ran since is a loop of its own
            j = where[x]
            out.append(path[j:])
            for y in path[j + 1:]:
                del where[y]
            del path[j + 1:]
        else:
            where[x] = len(path)
            path.append(x)
    out.append(path)
    return out


def _ear_clip(q: np.ndarray, joined=lambda a, c: False
              ) -> tuple[list[tuple[int, int, int]], list[int]]:
    """Triangles (positions in ``q``, kept in its order's winding) that ear clipping of the
    2-D polygon ``q`` cuts off, and the positions left when no ear remains (3 or fewer:
    the last triangle is among the triangles). ``joined(a, c)``: positions a and c are
    joined by an edge already (an ear there would use that edge a third time)."""
    x, y = q[:, 0], q[:, 1]
    sign = 1.0 if float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)) >= 0 else -1.0
    rem = list(range(len(q)))
    tris: list[tuple[int, int, int]] = []

    def cross(a: int, b: int, c: int) -> float:
        return float((q[b, 0] - q[a, 0]) * (q[c, 1] - q[a, 1])
                     - (q[b, 1] - q[a, 1]) * (q[c, 0] - q[a, 0])) * sign

    def side(a: int, b: int, pts: np.ndarray) -> np.ndarray:
        """(b - a) x (p - a) for each row p of pts, times sign."""
        return ((q[b, 0] - q[a, 0]) * (pts[:, 1] - q[a, 1])
                - (q[b, 1] - q[a, 1]) * (pts[:, 0] - q[a, 0])) * sign

    def is_ear(i: int) -> bool:
        m = len(rem)
        a, b, c = rem[(i - 1) % m], rem[i], rem[(i + 1) % m]
        if cross(a, b, c) <= 0.0 or joined(a, c):    # reflex or flat, or an edge already
            return False
        others = [p for p in rem if p != a and p != b and p != c]
        pts = q[others]                               # no other corner inside (or on) it
        inside = (side(a, b, pts) >= 0.0) & (side(b, c, pts) >= 0.0) & (side(c, a, pts) >= 0.0)
        return not bool(inside.any())

    i, tried = 0, 0
    while len(rem) > 3 and tried < len(rem):
        i %= len(rem)
        if is_ear(i):
            m = len(rem)
            tris.append((rem[(i - 1) % m], rem[i], rem[(i + 1) % m]))
            rem.pop(i)
            tried = 0
        else:
            i += 1
            tried += 1
    if len(rem) == 3:                    # its sides: the loop's edges or diagonals cut above
        tris.append((rem[0], rem[1], rem[2]))
        rem = []
    return tris, rem


def fill_holes(vertices: np.ndarray, faces: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, int]:
    """``(vertices, faces, holes)``: the mesh with every boundary loop triangulated (see
    the module docstring) and how many loops there were. A closed mesh comes back as it
    is."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    loops = boundary_loops(f)
    if not loops:
        return v, f, 0
    n = len(v) + len(loops)
    e = mesh_edges(f)
    edges = set(edge_keys(e[:, 0], e[:, 1], n).tolist())
    new_faces: list[np.ndarray] = []
    new_verts: list[np.ndarray] = []
    for loop in loops:
        p = v[loop]
        centre = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
        q = (p - centre) @ vt[:2].T                  # the loop in its best-fitting plane

        def joined(a: int, c: int, loop=loop) -> bool:
            x, y = int(loop[a]), int(loop[c])
            return int(edge_keys(x, y, n)) in edges
        tris, rest = (_ear_clip(q, joined) if len(loop) <= MAX_CLIPPED
                      else ([], list(range(len(loop)))))
        if tris:
            new_faces.append(loop[np.array(tris, np.int64)])
        if rest:                                      # fan the rest around its centroid
            c = len(v) + len(new_verts)
            new_verts.append(v[loop[rest]].mean(axis=0))
            ring = loop[np.array(rest, np.int64)]
            new_faces.append(np.stack([ring, np.roll(ring, -1), np.full(len(ring), c)], 1))
    if new_verts:
        v = np.concatenate([v, np.array(new_verts)])
    return v, np.concatenate([f, *new_faces]), len(loops)
