"""Epipolar geometry for one light: the axis, the slices and the (alpha, beta, gamma) coordinates.

Baran et al. 2010, Sec. 3, 8 and 9. Everything here is float64 NumPy in the normalised
device frame (``clscatter/scene/normalised.py``).

The axis
    The line through the eye ``e`` towards the light: ``u = -direction`` for a
    directional light, ``u = (L - e) / D`` for a spot light at ``L`` with ``D = |L - e|``.
    An epipolar *slice* is a half-plane bounded by the axis; it is given by a unit vector
    ``w`` normal to ``u`` and its angle ``phi = atan2(w.b2, w.b1)`` around the axis, with
    ``(b1, b2)`` a fixed orthonormal basis of the plane normal to ``u``.

Coordinates of a point ``p`` in its slice (``z = (p - e).u``, ``rho = (p - e).w >= 0``)
    beta   the angle at the eye between the view ray through ``p`` and ``u``
           (0 looks straight at the light; a view ray is ``v = cos(beta) u + sin(beta) w``);
    gamma  directional: the distance ``rho`` of the light ray through ``p`` from the eye;
           spot: the angle at the light between the light ray through ``p`` and the
           direction from the light to the eye (paper, Sec. 9).
    A view ray at ``beta`` reaches ``gamma = t sin(beta)`` (directional) or
    ``gamma = atan2(t sin(beta), D - t cos(beta))`` (spot) at distance ``t``. Sweeping
    ``beta`` upwards at fixed ``gamma`` walks along the light ray in the direction the
    light travels, which is what makes visibility incremental: a light ray blocked at
    ``beta_b`` stays blocked for every ``beta > beta_b``.

The image
    Every view ray of a slice projects onto one image half-line from ``P``, the image of
    the axis' vanishing point (the *epipole* where the light is in front of the camera,
    ``beta = 0`` there; the *anti-epipole* where it is behind, ``beta = pi`` there).
    :func:`slice_points` places the half-lines by the sinh distribution of Sec. 8 so that
    every pixel centre lies within half a pixel of one of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...device import structs
from ...geometry import perpendicular_axes
from ..base import Fallback

F4 = (np.float32, 4)

# ---- host mirrors of the structs in cl_kernels/epipolar.h (layout: tests/test_epipolar.py)
EPI_FRAME = np.dtype([
    ("eye", *F4), ("u", *F4), ("b1", *F4), ("b2", *F4), ("light", *F4), ("kappa", *F4),
    ("bmin", *F4), ("bmax", *F4), ("cone", *F4), ("sm_s1", *F4), ("sm_s2", *F4),
    ("sm_rect", *F4),
    ("D", np.float32), ("z_start", np.float32), ("beta_tol", np.float32), ("lspan", np.float32),
    ("type", np.int32), ("bounded", np.int32), ("sm_res", np.int32), ("d", np.int32),
    ("prefilter", np.int32), ("rays", np.int32), ("nch", np.int32), ("sm_faces", np.int32),
], align=True)

EPI_FACE = np.dtype([("c", *F4), ("e1", *F4), ("e2", *F4), ("rect", *F4)], align=True)

EPI_SLICE = np.dtype([
    ("w", *F4),
    ("beta_lo", np.float32), ("beta_hi", np.float32),
    ("gamma_lo", np.float32), ("gamma_hi", np.float32),
    ("cone_lo", np.float32), ("cone_hi", np.float32),
    ("phi", np.float32), ("group", np.int32),
], align=True)

structs.register_struct("epipolar.h", "EpiFrame", EPI_FRAME)
structs.register_struct("epipolar.h", "EpiSlice", EPI_SLICE)
structs.register_struct("epipolar.h", "EpiFace", EPI_FACE)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraGeom:
    """The pinhole camera of view_paths.cl in float64: ``dir = fwd + sx right + sy up``."""

    origin: np.ndarray
    fwd: np.ndarray
    right: np.ndarray     # scaled by tan(fov_x / 2)
    up: np.ndarray        # scaled by tan(fov_y / 2)
    width: int
    height: int

    @staticmethod
    def from_struct(cam: np.ndarray) -> CameraGeom:
        g = lambda k: np.asarray(cam[k][:3], np.float64)
        return CameraGeom(g("origin"), g("forward"), g("right"), g("up"),
                          int(cam["width"]), int(cam["height"]))

    def project(self, dirs: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates ``(N, 2)`` (x right, y down; centres at +0.5) of
        directions in front of the camera (the convention of tests/analytic.camera_rays)."""
        d = np.atleast_2d(dirs)
        z = d @ self.fwd
        sx = (d @ self.right) / (self.right @ self.right) / z
        sy = (d @ self.up) / (self.up @ self.up) / z
        return np.stack([(sx + 1.0) * 0.5 * self.width, (1.0 - sy) * 0.5 * self.height], axis=-1)

    def direction(self, xy: np.ndarray) -> np.ndarray:
        """Unit directions ``(N, 3)`` through continuous pixel coordinates ``(N, 2)``."""
        xy = np.atleast_2d(xy)
        sx = 2.0 * xy[:, 0] / self.width - 1.0
        sy = 1.0 - 2.0 * xy[:, 1] / self.height
        return _unit(self.fwd + sx[:, None] * self.right + sy[:, None] * self.up)

    def pixel_angle(self) -> float:
        """Angle subtended by one pixel at the image centre (radians)."""
        return 2.0 * math.atan(float(np.linalg.norm(self.right)) / self.width)

    def min_angle_to(self, a: np.ndarray, samples: int = 512) -> float:
        """A lower bound of the angle between the direction ``a`` and every direction
        through the image rectangle: 0 when ``a`` is in view; else the least angle to the
        image's border (where the least angle to a spherical quadrilateral that does not
        hold ``a`` lies), sampled ``samples`` times a side, less the largest angle between
        neighbouring samples."""
        a = _unit(np.asarray(a, np.float64))
        if a @ self.fwd > 0.0:
            x, y = self.project(a)[0]
            if 0.0 <= x <= self.width and 0.0 <= y <= self.height:
                return 0.0
        t = np.linspace(0.0, 1.0, int(samples) + 1)
        w, h = float(self.width), float(self.height)
        border = np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([w + 0 * t, t * h], 1),
                                 np.stack([(1 - t) * w, h + 0 * t], 1),
                                 np.stack([0 * t, (1 - t) * h], 1)])
        d = self.direction(border)
        step = float(np.arccos(np.clip(np.sum(d[1:] * d[:-1], axis=1), -1.0, 1.0)).max())
        least = float(np.arccos(np.clip(d @ a, -1.0, 1.0)).min())
        return max(0.0, least - step)


# --------------------------------------------------------------------------------------
# The axis
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Axis:
    """The epipolar axis of one light (see the module docstring)."""

    kind: int                 # structs.LIGHT_DIRECTIONAL or structs.LIGHT_SPOT
    eye: np.ndarray
    u: np.ndarray             # unit, from the eye towards the light
    b1: np.ndarray
    b2: np.ndarray
    D: float = math.inf       # spot: distance eye -> light
    light: np.ndarray | None = None
    cone_axis: np.ndarray | None = None
    cos_cut: float = -2.0

    @property
    def spot(self) -> bool:
        return self.kind == structs.LIGHT_SPOT

    def coords(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(phi, beta)`` of view directions ``(N, 3)`` (need not be unit)."""
        d = np.atleast_2d(dirs)
        c = d @ self.u
        perp = d - c[:, None] * self.u
        beta = np.arctan2(np.linalg.norm(perp, axis=1), c)
        phi = np.arctan2(perp @ self.b2, perp @ self.b1)
        return phi, beta

    def gamma(self, t: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """gamma of the point at distance ``t`` along the view ray ``beta``."""
        if self.spot:
            return np.arctan2(t * np.sin(beta), self.D - t * np.cos(beta))
        return t * np.sin(beta)


def make_axis(light: np.ndarray, eye: np.ndarray) -> Axis:
    """The axis of a LIGHT struct (directional or spot) seen from ``eye``."""
    kind = int(light["type"])
    eye = np.asarray(eye, np.float64)[:3]
    if kind == structs.LIGHT_DIRECTIONAL:
        u = -_unit(np.asarray(light["direction"][:3], np.float64))
        D, pos = math.inf, None
    elif kind == structs.LIGHT_SPOT:
        pos = np.asarray(light["position"][:3], np.float64)
        D = float(np.linalg.norm(pos - eye))
        if D <= 0.0:
            raise Fallback("the spot light sits at the eye: no epipolar axis")
        u = (pos - eye) / D
    else:
        raise ValueError("epipolar slices need a directional or spot light")
    b1, b2 = perpendicular_axes(u)
    cone = None
    cos_cut = -2.0
    if kind == structs.LIGHT_SPOT:
        cone = _unit(np.asarray(light["direction"][:3], np.float64))
        cos_cut = float(light["cos_cutoff"])
    return Axis(kind, eye, u, b1, b2, D, pos, cone, cos_cut)


def epipole(axis: Axis, cam: CameraGeom) -> tuple[np.ndarray, bool]:
    """Image position of the axis' vanishing point and whether it is the epipole proper
    (light in front: ``beta = 0`` there) rather than the anti-epipole (``beta = pi``).

    An axis parallel to the image plane has its vanishing point at infinity; it is then
    placed 1e9 pixels away in the right direction, which changes nothing measurable."""
    z = float(axis.u @ cam.fwd)
    front = z > 0.0
    zz = z if abs(z) > 1e-9 else math.copysign(1e-9, z if z != 0.0 else 1.0)
    sx = (axis.u @ cam.right) / (cam.right @ cam.right) / zz
    sy = (axis.u @ cam.up) / (cam.up @ cam.up) / zz
    P = np.array([(sx + 1.0) * 0.5 * cam.width, (1.0 - sy) * 0.5 * cam.height])
    return P, front


# --------------------------------------------------------------------------------------
# Slice placement: the sinh distribution (Sec. 8)
# --------------------------------------------------------------------------------------
def slice_points(P: np.ndarray, width: int, height: int, spacing: float = 1.0) -> np.ndarray:
    """Points ``(n, 2)`` on the image border, one per slice, sorted by angle around ``P``.

    For each border edge through which half-lines from ``P`` *leave* the image (all
    four when ``P`` is inside), with ``h`` the distance from ``P`` to the edge's line and
    ``x`` the position along it measured from the foot of the perpendicular, the lines
    cross the edge at ``x = h sinh(alpha)`` for ``alpha`` in equal steps of at most
    ``spacing / h``: neighbouring lines are then at most ``spacing`` pixels apart, measured
    perpendicular to them, on the edge (``dx / sqrt(1 + (x/h)^2) = h d alpha``, Eq. 5), and
    closer everywhere between ``P`` and the edge. Both ends of each edge are included so
    that the corners are covered; duplicates are removed.
    """
    P = np.asarray(P, np.float64)
    corners = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]], np.float64)
    pts = []
    for i in range(4):
        c0, c1 = corners[i], corners[(i + 1) % 4]
        t = (c1 - c0) / np.linalg.norm(c1 - c0)
        n = np.array([t[1], -t[0]])           # outward normal (the corners run clockwise on screen)
        h = -float((P - c0) @ n)               # > 0: P on the image side of this edge
        if h <= 1e-9:
            continue
        foot = P + h * n
        a0 = math.asinh(float((c0 - foot) @ t) / h)
        a1 = math.asinh(float((c1 - foot) @ t) / h)
        # first-order spacing h * d_alpha; the exact spacing exceeds it by a factor below
        # 1 + d_alpha^2, so a 2 % reserve keeps the bound for any d_alpha <= 0.1
        steps = max(1, int(math.ceil((a1 - a0) * h / (0.98 * spacing))))
        alpha = np.linspace(a0, a1, steps + 1)
        pts.append(foot + (h * np.sinh(alpha))[:, None] * t)
    p = np.concatenate(pts)
    theta = np.arctan2(p[:, 1] - P[1], p[:, 0] - P[0])
    order = np.argsort(theta, kind="stable")
    p, theta = p[order], theta[order]
    keep = np.ones(len(p), bool)
    keep[1:] = np.abs(np.diff(p, axis=0)).max(axis=1) > 1e-7 * max(width, height)
    return p[keep]


def line_distance(P: np.ndarray, pts: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance (pixels) from each point ``xy`` (M, 2) to the nearest half-line from ``P``
    through ``pts`` (n, 2) (the test of the half-pixel bound)."""
    d = pts - P
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rel = xy - P
    best = np.full(len(xy), np.inf)
    for s in range(0, len(d), 256):        # blocks of lines, vectorised over points
        blk = d[s:s + 256]
        along = rel @ blk.T                                     # (M, b)
        cross = np.abs(rel[:, 0:1] * blk[:, 1] - rel[:, 1:2] * blk[:, 0])
        dist = np.where(along >= 0.0, cross, np.linalg.norm(rel, axis=1)[:, None])
        best = np.minimum(best, dist.min(axis=1))
    return best


# --------------------------------------------------------------------------------------
# Slices in 3-D
# --------------------------------------------------------------------------------------
@dataclass
class Slices:
    """The slices of one frame, sorted by ``phi`` (continuous: ``phi_sorted`` increases by
    less than 2 pi over the set; ``full`` when they go all the way round the axis)."""

    table: np.ndarray          # EPI_SLICE array
    phi: np.ndarray            # (n,) float64, increasing, unwrapped
    full: bool                 # True: the last slice's neighbour is the first (+2 pi)
    P: np.ndarray              # epipole in pixels
    front: bool
    border: np.ndarray         # (n, 2) the border points that defined them
    length: np.ndarray         # (n,) pixels of each half-line inside the image, outside the ring

    def __len__(self) -> int:
        return len(self.table)

    @staticmethod
    def _base(phi: np.ndarray, full: bool) -> float:
        """Where the angles start: the first slice (full fan), or the middle of an open
        fan's gap before it."""
        return phi[0] if full else phi[0] - 0.5 * (2.0 * math.pi - (phi[-1] - phi[0]))

    def lookup_table(self, bins: int | None = None) -> np.ndarray:
        """Where the kernels' slice search starts (``epi_bracket``): int32 ``T`` of
        ``bins + 1`` entries (default ``4 n``), ``T[b]`` = slices with ``phi`` (as float32)
        at most ``base + b 2 pi / bins``, ``base`` as in :meth:`bracket`. An angle in bin
        ``b`` then has its count within ``[T[b - 1], T[b + 2]]`` even with the kernel's
        float32 rounding of its bin, so a few steps of binary search replace ~log2(n)."""
        n = len(self.phi)
        bins = int(bins or 4 * n)
        p32 = self.phi.astype(np.float32).astype(np.float64)
        base = self._base(p32, self.full)
        edges = base + np.arange(bins + 1) * (2.0 * math.pi / bins)
        return np.searchsorted(p32, edges, side="right").astype(np.int32)

    def bracket(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Neighbouring slices ``k0, k1`` of angles ``phi`` and the weight ``f`` of ``k1``
        (linear in phi). A full fan wraps from the last slice to the first; an open fan is
        cut in the middle of its gap and angles beyond its ends clamp to the end slices.
        (``epi_bracket`` in epipolar.cl is the same code.)"""
        n = len(self.phi)
        two_pi = 2.0 * math.pi
        base = self._base(self.phi, self.full)
        x = base + np.mod(np.asarray(phi, np.float64) - base, two_pi)
        i = np.searchsorted(self.phi, x, side="right") - 1          # -1 .. n-1
        first, last = i < 0, i == n - 1
        i = np.clip(i, 0, n - 1)
        if self.full:
            k1 = np.where(last, 0, np.minimum(i + 1, n - 1))
            nxt = np.where(last, self.phi[0] + two_pi, self.phi[np.minimum(i + 1, n - 1)])
        else:
            k1 = np.minimum(i + 1, n - 1)
            nxt = self.phi[k1]
        gap = nxt - self.phi[i]
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(gap > 0, (x - self.phi[i]) / gap, 0.0)
        if not self.full:
            f = np.where(first | last, 0.0, f)
            k1 = np.where(first | last, i, k1)
        return i, k1, np.clip(f, 0.0, 1.0)


def line_box(o: np.ndarray, d: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> tuple[float, float]:
    """Parameter interval ``[lo, hi]`` of the line ``o + s d`` inside a box (lo > hi: miss)."""
    lo, hi = -math.inf, math.inf
    for k in range(3):
        if d[k] == 0.0:
            if not bmin[k] <= o[k] <= bmax[k]:
                return math.inf, -math.inf
            continue
        a, b = (bmin[k] - o[k]) / d[k], (bmax[k] - o[k]) / d[k]
        lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
    return lo, hi


def _box_points(axis: Axis, w: np.ndarray, bmin: np.ndarray, bmax: np.ndarray):
    """Vertices ``(z, rho)`` of the polygons box ∩ slice half-plane: (S, 14) arrays, NaN
    where a candidate is not a vertex (12 edge crossings plus the 2 axis/box points)."""
    c = np.array([[bmin[0], bmin[1], bmin[2]]]) + np.array(
        [[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) * (bmax - bmin)
    edges = [(a, b) for a in range(8) for b in range(8) if a < b and bin(a ^ b).count("1") == 1]
    p0 = c[[a for a, _ in edges]] - axis.eye              # (12, 3)
    p1 = c[[b for _, b in edges]] - axis.eye
    n = np.cross(axis.u, w)                                # (S, 3) slice plane normals
    d0, d1 = p0 @ n.T, p1 @ n.T                            # (12, S)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = d0 / (d0 - d1)
    ok = (s >= 0.0) & (s <= 1.0) & np.isfinite(s)
    s = np.where(ok, s, 0.0)
    q = p0[:, None, :] + s[..., None] * (p1 - p0)[:, None, :]   # (12, S, 3)
    z = q @ axis.u
    rho = np.einsum("esk,sk->es", q, w)
    ok &= rho >= -1e-12
    z = np.where(ok, z, np.nan).T
    rho = np.where(ok, np.maximum(rho, 0.0), np.nan).T
    # the axis' own stretch inside the box lies on the edge of every half-plane
    lo, hi = line_box(axis.eye, axis.u, bmin, bmax)
    az = np.array([lo, hi]) if lo <= hi else np.array([np.nan, np.nan])
    S = len(w)
    z = np.concatenate([z, np.broadcast_to(az, (S, 2))], axis=1)
    rho = np.concatenate([rho, np.where(np.isnan(az), np.nan, 0.0)[None, :].repeat(S, 0)], axis=1)
    return z, rho


def _cone_interval(axis: Axis, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """gamma interval of each slice's light rays inside the spot cone (lo > hi: none).
    A light ray of the slice points along ``-cos(gamma) u + sin(gamma) w``, whose dot with
    the cone axis is ``R cos(gamma - g*)``."""
    a = axis.cone_axis
    ua, wa = float(axis.u @ a), w @ a
    R = np.hypot(ua, wa)
    gstar = np.arctan2(wa, -ua)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(R > 0, axis.cos_cut / R, 2.0)
    delta = np.arccos(np.clip(c, -1.0, 1.0))
    lo = np.full(len(w), 1.0)
    hi = np.full(len(w), 0.0)
    for shift in (-2.0 * math.pi, 0.0, 2.0 * math.pi):
        a0 = np.maximum(gstar - delta + shift, 0.0)
        a1 = np.minimum(gstar + delta + shift, math.pi)
        take = (a1 > a0) & (c <= 1.0)
        lo = np.where(take, a0, lo)
        hi = np.where(take, a1, hi)
    return lo, hi


def _nan_range(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-wise min and max ignoring NaN (inf, -inf for an all-NaN row)."""
    bad = np.isnan(x)
    return np.where(bad, np.inf, x).min(axis=1), np.where(bad, -np.inf, x).max(axis=1)


def gamma_ranges(axis: Axis, w: np.ndarray, box: tuple[np.ndarray, np.ndarray] | None):
    """Per-slice light-ray range ``[lo, hi]`` covering box ∩ half-plane (and the cone),
    plus the cone interval (spot; ``(-inf, inf)`` otherwise)."""
    S = len(w)
    if axis.spot:
        clo, chi = _cone_interval(axis, w)
    else:
        clo, chi = np.full(S, -1e30), np.full(S, 1e30)
    if box is None:                     # unbounded (spot only): the cone is the range
        lo, hi = np.maximum(clo, 0.0), np.minimum(chi, math.pi)
        return lo, hi, clo, chi
    bmin, bmax = box
    z, rho = _box_points(axis, w, bmin, bmax)
    if axis.spot:
        inside = bool(np.all(axis.light >= bmin) and np.all(axis.light <= bmax))
        if inside:
            lo, hi = np.zeros(S), np.full(S, math.pi)
        else:
            lo, hi = _nan_range(np.arctan2(rho, axis.D - z))
        lo, hi = np.maximum(lo, clo), np.minimum(hi, chi)
    else:
        lo, hi = _nan_range(rho)
    empty = ~(hi > lo)
    lo = np.where(empty, 0.0, lo)
    hi = np.where(empty, 0.0, hi)
    return lo, hi, clo, chi


def _clip_halfline(P, d, width, height):
    """Parameter interval ``[s0, s1]`` (s >= 0) of the half-lines ``P + s d`` inside the image."""
    s0 = np.zeros(len(d))
    s1 = np.full(len(d), np.inf)
    for k, size in ((0, width), (1, height)):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (0.0 - P[k]) / d[:, k]
            tb = (size - P[k]) / d[:, k]
        par = d[:, k] == 0
        lo = np.where(par, np.where((P[k] >= 0) & (P[k] <= size), -np.inf, np.inf), np.minimum(ta, tb))
        hi = np.where(par, np.where((P[k] >= 0) & (P[k] <= size), np.inf, -np.inf), np.maximum(ta, tb))
        s0 = np.maximum(s0, lo)
        s1 = np.minimum(s1, hi)
    return s0, s1


def make_slices(axis: Axis, cam: CameraGeom, box, spacing: float = 1.0,
                ring: float = 0.0) -> Slices:
    """The slices of one frame: placed by :func:`slice_points`, each with its ``w``,
    ``phi``, the beta range of its half-line inside the image outside the epipole ring of
    ``ring`` pixels, and its gamma ranges (hull of its own and its neighbours' ranges, so
    that a view ray between two slices can be looked up in either)."""
    P, front = epipole(axis, cam)
    pts = slice_points(P, cam.width, cam.height, spacing)
    dirs = cam.direction(pts)
    perp = dirs - (dirs @ axis.u)[:, None] * axis.u
    w = _unit(perp)
    phi = np.arctan2(w @ axis.b2, w @ axis.b1)
    order = np.argsort(phi, kind="stable")
    pts, w, phi = pts[order], w[order], phi[order]
    # unwrap: cut the circle in its widest gap, so that an open fan is one interval
    gaps = np.diff(np.concatenate([phi, [phi[0] + 2 * math.pi]]))
    cut = int(np.argmax(gaps))
    roll = (cut + 1) % len(phi)
    pts, w, phi = np.roll(pts, -roll, 0), np.roll(w, -roll, 0), np.roll(phi, -roll)
    phi = phi[0] + np.mod(phi - phi[0], 2 * math.pi)
    inside = (0.0 <= P[0] <= cam.width) and (0.0 <= P[1] <= cam.height)
    full = bool(inside)
    # beta range of each half-line (image part, outside the ring)
    hd = pts - P
    hd /= np.linalg.norm(hd, axis=1, keepdims=True)
    s0, s1 = _clip_halfline(P, hd, cam.width, cam.height)
    s0 = np.maximum(s0, ring)
    s1 = np.maximum(s1, s0)
    b0 = axis.coords(cam.direction(P + s0[:, None] * hd))[1]
    b1 = axis.coords(cam.direction(P + s1[:, None] * hd))[1]
    if s0.min() <= 0.0:          # a half-line starting at the epipole itself
        b0 = np.where(s0 <= 0.0, 0.0 if front else math.pi, b0)
    glo, ghi, clo, chi = gamma_ranges(axis, w, box)
    # hull with the neighbours (wrapping when the fan is full)
    nb_lo, nb_hi = glo.copy(), ghi.copy()
    for sh in (-1, 1):
        rl, rh = np.roll(glo, sh), np.roll(ghi, sh)
        if not full:
            idx = 0 if sh == 1 else -1
            rl[idx], rh[idx] = glo[idx], ghi[idx]
        has = rh > rl
        nb_lo = np.where(has, np.minimum(nb_lo, rl), nb_lo)
        nb_hi = np.where(has, np.maximum(nb_hi, rh), nb_hi)
    pad = 1e-3 * np.maximum(nb_hi - nb_lo, 0.0)
    nb_lo = np.maximum(nb_lo - pad, 0.0)
    nb_hi = nb_hi + pad
    if axis.spot:
        nb_hi = np.minimum(nb_hi, math.pi)
    t = np.zeros(len(w), EPI_SLICE)
    t["w"][:, :3] = w
    t["beta_lo"], t["beta_hi"] = np.minimum(b0, b1), np.maximum(b0, b1)
    t["gamma_lo"], t["gamma_hi"] = nb_lo, nb_hi
    t["cone_lo"], t["cone_hi"] = clo, chi
    t["phi"] = phi
    return Slices(t, phi, full, P, front, pts, s1 - s0)


# --------------------------------------------------------------------------------------
# Frame struct
# --------------------------------------------------------------------------------------
def frame_struct(axis: Axis, medium: np.ndarray, d: int) -> np.ndarray:
    """EPI_FRAME with the axis, the medium box and extinction; the shadow-map fields are
    filled by :mod:`clscatter.methods.epipolar.maps`."""
    f = np.zeros((), EPI_FRAME)
    f["eye"] = structs.vec4(axis.eye)
    f["u"] = structs.vec4(axis.u)
    f["b1"] = structs.vec4(axis.b1)
    f["b2"] = structs.vec4(axis.b2)
    if axis.spot:
        f["light"] = structs.vec4(axis.light)
        f["cone"] = structs.vec4(axis.cone_axis, axis.cos_cut)
        f["D"] = axis.D
    f["kappa"] = medium["kappa"]
    f["bmin"] = medium["bmin"]
    f["bmax"] = medium["bmax"]
    f["bounded"] = int(medium["bounded"])
    f["type"] = axis.kind
    f["d"] = int(d)
    return f


def medium_box(medium: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The medium's bounds in float64, or None when unbounded."""
    if not int(medium["bounded"]):
        return None
    return (np.asarray(medium["bmin"][:3], np.float64), np.asarray(medium["bmax"][:3], np.float64))
