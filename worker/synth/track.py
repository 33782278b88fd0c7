"""Railway alignment geometry: straights, circular arcs, clothoids, gradient and cant.

A :class:`Track` is a 3D curve parametrised by its horizontal arc length ``s`` (metres).
Conventions (float64 throughout, vectorised over ``s``):

- horizontal alignment: heading ``theta(s)`` (rad, counter-clockwise from world +x = East)
  integrated from a curvature that is piecewise linear in ``s`` (straight: 0, arc: 1/R,
  clothoid: linear ramp; positive curvature turns left). Positions integrate
  ``(cos theta, sin theta)`` exactly per segment with Gauss-Legendre quadrature on a
  0.5 m table (error far below a micrometre);
- vertical profile: gradient (dz/ds) piecewise linear between knots, elevation its
  integral;
- cant (superelevation, metres, signed: positive lifts the right rail, i.e. banks a
  left-hand curve) piecewise linear per segment, so it ramps along the transitions; the
  roll angle is ``-asin(cant / RAIL_HEAD_SPACING)`` about the tangent;
- the centreline is at rail-head mid-height: the base (lidar) frame of a vehicle sits on
  it at top-of-rail height and the rails rotate about it with the cant;
- gauge: 1.435 m between the inner edges of the rail heads, which with a 0.065 m
  measuring offset per side gives ``RAIL_HEAD_SPACING = 1.500`` m between the rail-head
  centres (the points :meth:`Track.rail_points` returns).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

GAUGE = 1.435
RAIL_HEAD_SPACING = 1.500
_TABLE_STEP = 0.5
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


@dataclass(frozen=True)
class Segment:
    """One alignment element: length (m), curvature and cant at its start and end."""

    length: float
    k0: float
    k1: float
    cant0: float
    cant1: float


@dataclass
class Alignment:
    """Builder for a horizontal alignment with cant, chained element by element.

    Example: ``Alignment().straight(100).clothoid(60, 1 / 500, 0.08).arc(200)``.
    """

    segments: list[Segment] = field(default_factory=list)

    @property
    def _end(self) -> tuple[float, float]:
        if not self.segments:
            return 0.0, 0.0
        return self.segments[-1].k1, self.segments[-1].cant1

    def straight(self, length: float) -> Alignment:
        """Append a straight (curvature and cant 0; previous element must end at 0)."""
        self.segments.append(Segment(float(length), 0.0, 0.0, 0.0, 0.0))
        return self

    def arc(
        self, length: float, radius: float | None = None, cant: float | None = None
    ) -> Alignment:
        """Append a circular arc (radius > 0 turns left, < 0 right; default: continue)."""
        k_prev, c_prev = self._end
        k = k_prev if radius is None else 1.0 / radius
        c = c_prev if cant is None else cant
        self.segments.append(Segment(float(length), k, k, c, c))
        return self

    def clothoid(self, length: float, radius_end: float | None, cant_end: float = 0.0) -> Alignment:
        """Append a transition curve: curvature and cant ramp linearly to the given ends.

        ``radius_end=None`` ramps the curvature to 0 (exit transition).
        """
        k_prev, c_prev = self._end
        k_end = 0.0 if radius_end is None else 1.0 / radius_end
        self.segments.append(Segment(float(length), k_prev, k_end, c_prev, float(cant_end)))
        return self


@dataclass(frozen=True)
class Profile:
    """Vertical profile: gradient (dz/ds, e.g. 0.005 = 5 per mille) piecewise linear.

    s_knots: (m,) increasing arc lengths; grades: (m,) gradients at the knots (constant
    outside).
    """

    s_knots: tuple[float, ...] = (0.0,)
    grades: tuple[float, ...] = (0.0,)

    def grade(self, s: F64) -> F64:
        return np.interp(s, self.s_knots, self.grades)

    def elevation(self, s: F64) -> F64:
        """Integral of the gradient from s = 0 (exact for the piecewise-linear gradient)."""
        pts = np.unique(np.concatenate([[0.0], np.asarray(self.s_knots, dtype=np.float64)]))
        g = self.grade(pts)
        zk = np.concatenate([[0.0], np.cumsum(np.diff(pts) * 0.5 * (g[1:] + g[:-1]))])
        zk -= np.interp(0.0, pts, zk)
        s = np.asarray(s, dtype=np.float64)
        i = np.clip(np.searchsorted(pts, s, side="right") - 1, 0, len(pts) - 1)
        return zk[i] + (s - pts[i]) * 0.5 * (g[i] + self.grade(s))


class Track:
    """A railway track: 3D centreline with heading, gradient and cant.

    Subclasses provide the horizontal geometry (:meth:`_horizontal`); everything else
    (points, tangents, vehicle frames, rails) is derived here.

    Attributes
    ----------
    track_id : int, 0 for the ego track.
    length : float, usable arc length (m), s in [0, length].
    """

    track_id: int
    length: float

    @property
    def id(self) -> int:
        """Alias of track_id (0 = ego)."""
        return self.track_id

    # --- to be provided by subclasses -------------------------------------------------
    def _horizontal(self, s: F64) -> tuple[F64, F64, F64]:
        """(xy (n, 2), heading (n,), curvature (n,)) at arc lengths s (n,)."""
        raise NotImplementedError

    def _vertical(self, s: F64) -> tuple[F64, F64]:
        """(z (n,), grade (n,))."""
        raise NotImplementedError

    def cant(self, s: ArrayLike) -> F64:
        """Signed cant (m) at s (n,): positive lifts the right rail."""
        raise NotImplementedError

    # --- derived ----------------------------------------------------------------------
    @staticmethod
    def _s(s: ArrayLike) -> F64:
        return np.atleast_1d(np.asarray(s, dtype=np.float64))

    def heading(self, s: ArrayLike) -> F64:
        """Heading (rad, CCW from +x) at s, shape (n,)."""
        return self._horizontal(self._s(s))[1]

    def curvature(self, s: ArrayLike) -> F64:
        """Horizontal curvature (1/m, positive = left) at s, shape (n,)."""
        return self._horizontal(self._s(s))[2]

    def point(self, s: ArrayLike) -> F64:
        """Centreline points (n, 3) in world at top-of-rail height."""
        s = self._s(s)
        xy = self._horizontal(s)[0]
        z = self._vertical(s)[0]
        return np.column_stack([xy, z])

    def roll(self, s: ArrayLike) -> F64:
        """Roll angle (rad) of the rail plane about the tangent, shape (n,)."""
        c = np.clip(self.cant(self._s(s)) / RAIL_HEAD_SPACING, -1.0, 1.0)
        return -np.arcsin(c)

    def tangent(self, s: ArrayLike) -> F64:
        """Unit 3D tangents (n, 3) including the gradient."""
        return self._axes(self._s(s), canted=True)[1][:, :, 0]

    def _axes(self, s: F64, canted: bool) -> tuple[F64, F64]:
        """(points (n, 3), rotation R_world_base (n, 3, 3))."""
        xy, th, _ = self._horizontal(s)
        z, g = self._vertical(s)
        alpha = np.arctan(g)
        ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(th), np.sin(th)
        x = np.column_stack([ct * ca, st * ca, sa])
        y0 = np.column_stack([-st, ct, np.zeros_like(st)])
        z0 = np.cross(x, y0)
        if canted:
            phi = self.roll(s)[:, None]
            y = np.cos(phi) * y0 + np.sin(phi) * z0
            zz = -np.sin(phi) * y0 + np.cos(phi) * z0
        else:
            y, zz = y0, z0
        return np.column_stack([xy, z]), np.stack([x, y, zz], axis=-1)

    def frame_at(self, s: ArrayLike, canted: bool = True) -> F64:
        """Vehicle frames T_world_base (n, 4, 4) on the centreline at s.

        x along the tangent, y left, z normal to the (canted) rail plane; origin on the
        centreline at top-of-rail height. ``canted=False`` gives the frame without roll
        (y horizontal), used to place structures such as platforms.
        """
        s = self._s(s)
        p, R = self._axes(s, canted)
        T = np.zeros((len(s), 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return T

    def rail_points(self, s: ArrayLike, side: str) -> F64:
        """Rail-head centre points (n, 3), side 'left' or 'right', 1.500 m apart."""
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        p, R = self._axes(self._s(s), canted=True)
        sign = 1.0 if side == "left" else -1.0
        return p + sign * 0.5 * RAIL_HEAD_SPACING * R[:, :, 1]

    def lateral_point(self, s: ArrayLike, offset: ArrayLike, height: ArrayLike = 0.0) -> F64:
        """Points (n, 3) at horizontal lateral ``offset`` (left +) and ``height`` above the
        centreline (uncanted frame), e.g. for poles and platforms."""
        p, R = self._axes(self._s(s), canted=False)
        off = np.asarray(offset, dtype=np.float64).reshape(-1, 1)
        h = np.asarray(height, dtype=np.float64).reshape(-1, 1)
        return p + off * R[:, :, 1] + h * np.array([0.0, 0.0, 1.0])

    def sample(self, step: float, s0: float = 0.0, s1: float | None = None) -> F64:
        """Arc lengths from s0 to s1 (default length) with at most ``step`` spacing."""
        s1 = self.length if s1 is None else s1
        n = max(2, int(np.ceil((s1 - s0) / step)) + 1)
        return np.linspace(s0, s1, n)

    def offset(self, lateral: float, track_id: int) -> OffsetTrack:
        """A parallel track at a horizontal lateral distance (left +) of this one."""
        return OffsetTrack(self, lateral, track_id)

    def branch(
        self,
        s_start: float,
        radius: float,
        side: str,
        length: float,
        track_id: int,
        turn_angle: float | None = None,
        cant: float = 0.0,
    ) -> AlignedTrack:
        """A diverging track leaving this one at ``s_start`` (a switch).

        It starts on this track's centreline with the same heading and elevation, follows
        an arc of ``radius`` towards ``side`` until it has turned ``turn_angle`` (rad;
        default: all of ``length``), then runs straight. Tangent-continuous at the switch.
        """
        sign = 1.0 if side == "left" else -1.0
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        arc_len = length if turn_angle is None else min(length, abs(turn_angle) * radius)
        al = Alignment().arc(arc_len, sign * radius, sign * cant)
        if length > arc_len:
            if cant:
                al.clothoid(0.0, None, 0.0)
            al.straight(length - arc_len)
        p0 = self.point(s_start)[0]
        th0 = float(self.heading(s_start)[0])
        g0 = float(self._vertical(self._s(s_start))[1][0])
        return AlignedTrack(al, p0, th0, Profile((0.0,), (g0,)), track_id)


class AlignedTrack(Track):
    """A track defined by an :class:`Alignment`, a start pose and a :class:`Profile`.

    start_xyz: (3,) world position of s = 0 (may carry a large far-origin offset);
    start_heading: rad CCW from +x.
    """

    def __init__(
        self,
        alignment: Alignment,
        start_xyz: ArrayLike = (0.0, 0.0, 0.0),
        start_heading: float = 0.0,
        profile: Profile | None = None,
        track_id: int = 0,
    ) -> None:
        segs = [sg for sg in alignment.segments if sg.length > 0]
        if not segs:
            raise ValueError("alignment has no element with positive length")
        self.alignment = alignment
        self.track_id = track_id
        self.start_xyz = np.asarray(start_xyz, dtype=np.float64).reshape(3)
        self.start_heading = float(start_heading)
        self.profile = profile or Profile()
        self._L = np.array([sg.length for sg in segs])
        self._k0 = np.array([sg.k0 for sg in segs])
        self._k1 = np.array([sg.k1 for sg in segs])
        self._c0 = np.array([sg.cant0 for sg in segs])
        self._c1 = np.array([sg.cant1 for sg in segs])
        self._s0 = np.concatenate([[0.0], np.cumsum(self._L)[:-1]])
        self.length = float(np.sum(self._L))
        # heading at segment starts
        dth = self._k0 * self._L + 0.5 * (self._k1 - self._k0) * self._L
        self._th0 = self.start_heading + np.concatenate([[0.0], np.cumsum(dth)[:-1]])
        self._build_table()

    def _seg(self, s: F64) -> tuple[NDArray[np.int64], F64]:
        i = np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self._L) - 1)
        return i, s - self._s0[i]

    def _heading_curv(self, s: F64) -> tuple[F64, F64]:
        i, u = self._seg(s)
        dk = (self._k1[i] - self._k0[i]) / self._L[i]
        # beyond the ends the last/first element continues with its end curvature
        u_in = np.clip(u, 0.0, self._L[i])
        k_in = self._k0[i] + dk * u_in
        th = self._th0[i] + self._k0[i] * u_in + 0.5 * dk * u_in**2 + k_in * (u - u_in)
        return th, k_in

    def _integrate(self, a: F64, b: F64) -> F64:
        """Exact-to-roundoff integral of (cos th, sin th) over [a, b] (n,) -> (n, 2).

        Intervals must not cross a segment boundary by more than the table step; heading
        is a quadratic per segment, 8-point Gauss-Legendre on <= 0.5 m is exact to 1e-15.
        """
        mid, half = 0.5 * (a + b), 0.5 * (b - a)
        s = mid[:, None] + half[:, None] * _GL_X[None, :]
        th, _ = self._heading_curv(s.ravel())
        th = th.reshape(s.shape)
        w = half[:, None] * _GL_W[None, :]
        return np.column_stack([(w * np.cos(th)).sum(1), (w * np.sin(th)).sum(1)])

    def _build_table(self) -> None:
        bounds = np.concatenate([self._s0, [self.length]])
        grid = np.unique(np.concatenate([np.arange(0.0, self.length, _TABLE_STEP), bounds]))
        d = self._integrate(grid[:-1], grid[1:])
        self._grid = grid
        self._xy = self.start_xyz[:2] + np.vstack([[0.0, 0.0], np.cumsum(d, axis=0)])

    def _horizontal(self, s: F64) -> tuple[F64, F64, F64]:
        j = np.clip(np.searchsorted(self._grid, s, side="right") - 1, 0, len(self._grid) - 1)
        xy = self._xy[j] + self._integrate(self._grid[j], s)
        th, k = self._heading_curv(s)
        return xy, th, k

    def _vertical(self, s: F64) -> tuple[F64, F64]:
        return self.start_xyz[2] + self.profile.elevation(s), self.profile.grade(s)

    def cant(self, s: ArrayLike) -> F64:
        s = self._s(s)
        i, u = self._seg(s)
        f = np.clip(u / self._L[i], 0.0, 1.0)
        return self._c0[i] + (self._c1[i] - self._c0[i]) * f


class OffsetTrack(Track):
    """A track parallel to a parent at a constant horizontal lateral distance.

    Its own arc length s' relates to the parent's s by ds' = (1 - d k(s)) ds; the map is
    tabulated every 0.25 m and inverted by interpolation (positions are always exactly at
    the lateral distance; only the parametrisation is interpolated). Cant and elevation
    follow the parent at the same station.
    """

    def __init__(self, parent: Track, lateral: float, track_id: int) -> None:
        self.parent = parent
        self.lateral = float(lateral)
        self.track_id = track_id
        sp = parent.sample(0.25, 0.0, parent.length)
        k = parent.curvature(sp)
        f = 1.0 - self.lateral * k
        if np.any(f <= 0):
            raise ValueError("offset larger than the parent's radius of curvature")
        self._sp = sp
        self._so = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(sp))])
        self.length = float(self._so[-1])

    def to_parent(self, s: ArrayLike) -> F64:
        """Parent arc length (n,) at this track's arc length s."""
        s = self._s(s)
        return np.interp(s, self._so, self._sp)

    def from_parent(self, s_parent: ArrayLike) -> F64:
        """This track's arc length (n,) at the parent's arc length."""
        return np.interp(self._s(s_parent), self._sp, self._so)

    def _horizontal(self, s: F64) -> tuple[F64, F64, F64]:
        sp = self.to_parent(s)
        xy, th, k = self.parent._horizontal(sp)
        n = np.column_stack([-np.sin(th), np.cos(th)])
        return xy + self.lateral * n, th, k / (1.0 - self.lateral * k)

    def _vertical(self, s: F64) -> tuple[F64, F64]:
        sp = self.to_parent(s)
        z, g = self.parent._vertical(sp)
        k = self.parent._horizontal(sp)[2]
        return z, g / (1.0 - self.lateral * k)

    def cant(self, s: ArrayLike) -> F64:
        return self.parent.cant(self.to_parent(s))
