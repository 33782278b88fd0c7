"""Where an object may stand in a prepared sequence: zones, footprints and the scene.

Everything here works in the ego track's coordinates (s, lateral): s the arc length on the
prepared ego centreline (m), lateral the horizontal offset from it (m, left +). An
object's footprint is its bounding box on the ground (object frame: x forward, y left),
placed at (s, offset) and turned by its yaw relative to the track direction. On the
curves of a railway (radius >= 150 m) a footprint of a few metres is the same rectangle
in track coordinates as on the ground to within centimetres.

The scene, from the preparation (:class:`SequenceGeometry`): the ego centreline, the
train's arc length at every frame, the platforms (their outlines in track coordinates)
and the poles. :meth:`SequenceGeometry.conflict` says why a footprint may not stand
where it is (beyond the prepared track, in a pole, across a platform's edge, half on the
track bed, too near another object), :meth:`SequenceGeometry.zone_offsets` where a zone
lets its centre be, :meth:`SequenceGeometry.first_view` when it comes into view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from worker.augmentation.gauge import GaugeOutline, smoothed_curvature, train_arc_length
from worker.augmentation.placement import RAIL_HEIGHT_ABOVE_BED
from worker.augmentation.proxies import BED_HALF_WIDTH

F64 = NDArray[np.float64]

#: How far beyond the envelope's edge the zone ``beside`` reaches (object centre, m).
BESIDE_WIDTH_M = 5.0
#: Platform pieces on one side closer than this along the track (m) are one platform: the
#: preparation fits a plane per 40 m of track and outlines it through its bins' centres,
#: which leaves gaps of about one outline step between the pieces of one real platform.
PLATFORM_JOIN_GAP_M = 5.0
#: Footprint samples per side for the platform tests (n x n points).
_SAMPLES = 7


class GeometryError(ValueError):
    """A sequence whose preparation cannot place objects by rules (no ego track...)."""


@dataclass(frozen=True)
class Footprint:
    """An object's bounding box on the ground, in its own frame (m): x (back, front),
    y (right, left), and its height."""

    x: tuple[float, float]
    y: tuple[float, float]
    height: float

    @classmethod
    def from_bounds(cls, bounds: Any) -> Footprint:
        """From a mesh's (2, 3) bounds [[min x, y, z], [max x, y, z]]."""
        b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        return cls((float(b[0, 0]), float(b[1, 0])), (float(b[0, 1]), float(b[1, 1])),
                   float(b[1, 2] - min(b[0, 2], 0.0)))  # fmt: skip

    @property
    def size(self) -> tuple[float, float]:
        """(length, width) m."""
        return (self.x[1] - self.x[0], self.y[1] - self.y[0])

    def corners(self, grow: float = 0.0) -> F64:
        """(4, 2) corners in the object frame, counter-clockwise, grown by ``grow`` m."""
        x0, x1 = self.x[0] - grow, self.x[1] + grow
        y0, y1 = self.y[0] - grow, self.y[1] + grow
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


@dataclass(frozen=True)
class Placed:
    """A footprint placed in track coordinates: centre (s, offset), yaw (rad) relative to
    the track direction."""

    footprint: Footprint
    s: float
    offset: float
    yaw: float

    def _to_track(self, p_obj: F64) -> F64:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        R = np.array([[c, -s], [s, c]])
        out: F64 = p_obj @ R.T + np.array([self.s, self.offset])
        return out

    def corners(self, grow: float = 0.0) -> F64:
        """(4, 2) corners [s, lateral], counter-clockwise."""
        return self._to_track(self.footprint.corners(grow))

    def samples(self, grow: float = 0.0) -> F64:
        """(n*n, 2) points [s, lateral] covering the (grown) footprint, edges included."""
        c = self.footprint.corners(grow)
        u = np.linspace(c[0, 0], c[1, 0], _SAMPLES)
        v = np.linspace(c[0, 1], c[2, 1], _SAMPLES)
        uu, vv = np.meshgrid(u, v)
        return self._to_track(np.column_stack([uu.ravel(), vv.ravel()]))

    def s_range(self) -> tuple[float, float]:
        c = self.corners()
        return float(c[:, 0].min()), float(c[:, 0].max())

    def lateral_range(self, grow: float = 0.0) -> tuple[float, float]:
        c = self.corners(grow)
        return float(c[:, 1].min()), float(c[:, 1].max())

    def distance_to_point(self, p_sl: F64) -> float:
        """Distance (m) from a point [s, lateral] to the footprint (0 inside)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        d = np.asarray(p_sl, dtype=np.float64) - np.array([self.s, self.offset])
        q = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])  # into the object frame
        f = self.footprint
        dx = max(f.x[0] - q[0], 0.0, q[0] - f.x[1])
        dy = max(f.y[0] - q[1], 0.0, q[1] - f.y[1])
        return math.hypot(dx, dy)

    def distance_to(self, other: Placed) -> float:
        """Distance (m) between two footprints (0 when they overlap)."""
        return rectangle_distance(self.corners(), other.corners())


def rotated_extent(fp: Footprint, yaw: float) -> tuple[float, float, float, float]:
    """(along lo, along hi, lateral lo, lateral hi) of a footprint turned by ``yaw`` (rad)
    about its origin, in track axes (m)."""
    c = Placed(fp, 0.0, 0.0, yaw).corners()
    return float(c[:, 0].min()), float(c[:, 0].max()), float(c[:, 1].min()), float(c[:, 1].max())


def _separated(a: F64, b: F64) -> bool:
    """Whether two convex polygons (k, 2) have a separating axis (an edge normal)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.column_stack([-edges[:, 1], edges[:, 0]])
        pa, pb = a @ normals.T, b @ normals.T
        if np.any((pa.max(0) < pb.min(0)) | (pb.max(0) < pa.min(0))):
            return True
    return False


def _point_segment_distance(p: F64, a: F64, b: F64) -> F64:
    """Distances (n, m) of points p (n, 2) to the segments a -> b (m, 2 each)."""
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None, :] - a[None], ab)
                / np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-18), 0.0, 1.0)  # fmt: skip
    closest = a[None] + t[..., None] * ab[None]
    d: F64 = np.linalg.norm(p[:, None, :] - closest, axis=2)
    return d


def rectangle_distance(a: F64, b: F64) -> float:
    """Distance between two convex polygons (k, 2) (0 when they overlap)."""
    if not _separated(a, b):
        return 0.0
    d1 = _point_segment_distance(a, b, np.roll(b, -1, axis=0)).min()
    d2 = _point_segment_distance(b, a, np.roll(a, -1, axis=0)).min()
    return float(min(d1, d2))


def points_in_polygon(p: F64, poly: F64) -> NDArray[np.bool_]:
    """Even-odd test of points (n, 2) against a simple polygon (k, 2)."""
    x, y = p[:, 0][:, None], p[:, 1][:, None]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    hits = crosses & (x < x_at)
    return np.asarray(np.count_nonzero(hits, axis=1) % 2 == 1)


@dataclass(frozen=True)
class PlatformOutline:
    """A platform in track coordinates: its near edge and far side as rows [s, lateral]
    (k, 2) each, in track order; its side and the index of its (first) preparation plane."""

    index: int
    side: str
    near: F64
    far: F64

    @property
    def outline(self) -> F64:
        """(2k, 2) the closed outline [s, lateral]."""
        return np.vstack([self.near, self.far[::-1]])

    @property
    def s_range(self) -> tuple[float, float]:
        o = self.outline
        return float(o[:, 0].min()), float(o[:, 0].max())

    @property
    def lateral(self) -> tuple[float, float]:
        o = self.outline
        return float(o[:, 1].min()), float(o[:, 1].max())

    def contains(self, p_sl: F64) -> NDArray[np.bool_]:
        return points_in_polygon(np.asarray(p_sl, dtype=np.float64).reshape(-1, 2), self.outline)


@dataclass(frozen=True)
class PoleSpot:
    """A pole in track coordinates: id, s, lateral, radius (m)."""

    id: str
    s: float
    lateral: float
    radius: float


@dataclass
class SequenceGeometry:
    """One prepared sequence as the expansion sees it (module docstring).

    frames : (m,) the frames of the range; T_world_base : (m, 4, 4) the train's pose at
    them; s_train : (m,) the base origin's arc length on the ego centreline;
    s0_job : the arc length a job's track placement ``s`` counts from (the sequence's
    first frame, as :func:`worker.augmentation.placement.resolve_placement` has it).
    """

    key: str
    label: str
    ego: Any
    frames: NDArray[np.int64]
    T_world_base: F64
    s_train: F64
    s0_job: float
    platforms: list[PlatformOutline]
    poles: list[PoleSpot]
    outline: GaugeOutline

    @classmethod
    def from_prepared(
        cls,
        prepared: Any,
        *,
        key: str,
        label: str,
        frame_range: tuple[int, int] | None = None,
        outline: GaugeOutline | None = None,
    ) -> SequenceGeometry:
        """From a PreparedSequence (ego centreline, pose track, planes, poles). Raises
        GeometryError when it has no ego track or no frame in ``frame_range``."""
        ego = prepared.ego
        if ego is None:
            raise GeometryError(
                f"{label}: the preparation found no ego track, so no position can be drawn "
                "by rules: use explicit placements (mode world or lidar_frame)"
            )
        track = prepared.track
        all_frames = (
            np.arange(len(track.T)) if track.frame_idx is None else np.asarray(track.frame_idx)
        )
        keep = np.ones(len(all_frames), dtype=bool)
        if frame_range is not None:
            keep = (all_frames >= frame_range[0]) & (all_frames <= frame_range[1])
            if not np.any(keep):
                raise GeometryError(
                    f"{label}: frame_range {list(frame_range)} holds no frame of the "
                    f"sequence ({int(all_frames.min())}..{int(all_frames.max())})"
                )
        T = np.asarray(track.T, dtype=np.float64)
        s0_job = float(ego.project(T[:1, :3, 3]).s[0])
        platforms = platform_outlines(prepared.planes, ego)
        poles = []
        for pole in prepared.poles:
            axis = np.asarray(pole.axis_xy, dtype=np.float64)[:2]
            pr = ego.project(np.array([[axis[0], axis[1], 0.0]]))
            poles.append(PoleSpot(pole.id, float(pr.s[0]), float(pr.lateral[0]),
                                  float(pole.radius)))  # fmt: skip
        return cls(
            key=key,
            label=label,
            ego=ego,
            frames=all_frames[keep].astype(np.int64),
            T_world_base=T[keep],
            s_train=train_arc_length(ego, T[keep]),
            s0_job=s0_job,
            platforms=platforms,
            poles=poles,
            outline=outline or GaugeOutline(),
        )

    # ------------------------------------------------------------------ the track
    @property
    def length(self) -> float:
        return float(self.ego.length)

    @property
    def s_first(self) -> float:
        """The train's arc length at the first frame of the range."""
        return float(self.s_train[0])

    def edge(self, s: float) -> float:
        """The envelope's half-width (m) at arc length s (curve widening included)."""
        return float(self.outline.half_width(smoothed_curvature(self.ego, [s]))[0])

    def pose(self, s: float, offset: float, yaw_deg: float) -> tuple[F64, float]:
        """The nominal world point (3,) of a track placement and its heading (deg from
        East), as resolve_placement computes them before snapping."""
        c = self.ego.point([s])[0]
        t = self.ego.tangent([s])[0]
        left = np.array([-t[1], t[0], 0.0])
        left /= np.linalg.norm(left)
        p = c + offset * left
        p[2] = c[2] - (RAIL_HEIGHT_ABOVE_BED if abs(offset) < 1.0 else 0.0)
        heading = math.degrees(math.atan2(t[1], t[0])) + yaw_deg
        return p, heading

    def track_position(self, p_world: F64, heading_deg: float) -> tuple[float, float, float]:
        """(s, offset, yaw_deg relative to the track) of a world point and heading."""
        pr = self.ego.project(np.asarray(p_world, dtype=np.float64).reshape(1, 3))
        s = float(pr.s[0])
        t = self.ego.tangent([s])[0]
        yaw = heading_deg - math.degrees(math.atan2(t[1], t[0]))
        return s, float(pr.lateral[0]), (yaw + 180.0) % 360.0 - 180.0

    # ------------------------------------------------------------------ zones
    def zone_offsets(
        self,
        zone: str,
        side: str,
        lateral_extent: tuple[float, float],
        s: float,
        clearance: float,
    ) -> list[tuple[float, float]]:
        """Intervals of the object centre's offset (m) that put a footprint of lateral
        extent ``(lo, hi)`` (about its centre, turned) into the zone at arc length s."""
        lo, hi = lateral_extent
        W, B = self.edge(s), BED_HALF_WIDTH
        left, right = side in ("left", "either"), side in ("right", "either")
        out: list[tuple[float, float]] = []
        if zone == "track":  # within the envelope, the centre on the bed
            out.append((max(-W - lo, -B), min(W - hi, B)))
        elif zone == "crossing":  # spanning the centreline, the centre on the bed
            out.append((max(-hi, -B), min(-lo, B)))
        elif zone == "gauge_edge":  # straddling the envelope's side, off the centreline
            if left:
                out.append((max(W - hi, -lo), W - lo))
            if right:
                out.append((-W - hi, min(-W - lo, -hi)))
        elif zone == "beside":  # outside the envelope, the centre within BESIDE_WIDTH_M
            if left:
                out.append((W + clearance - lo, W + BESIDE_WIDTH_M))
            if right:
                out.append((-W - BESIDE_WIDTH_M, -W - clearance - hi))
        elif zone == "platform":
            for p in self.platforms:
                wanted = (left and p.side == "left") or (right and p.side == "right")
                if wanted and p.s_range[0] <= s <= p.s_range[1]:
                    out.append((p.lateral[0] + clearance - lo, p.lateral[1] - clearance - hi))
        else:
            raise ValueError(f"unknown zone {zone!r}")
        return [(a, b) for a, b in out if b > a]

    def platforms_on(self, side: str) -> list[PlatformOutline]:
        return [p for p in self.platforms if side == "either" or p.side == side]

    # ------------------------------------------------------------------ conflicts
    def conflict(
        self,
        placed: Placed,
        *,
        clearance: float,
        others: Sequence[Placed] = (),
        min_spacing: float = 0.0,
        zone: str | None = None,
    ) -> str | None:
        """Why the footprint may not stand there (None: it may). ``zone`` "platform"
        requires its centre on a platform; other zones keep it off the platforms' edges."""
        s_lo, s_hi = placed.s_range()
        if s_lo < 0.0 or s_hi > self.length:
            return f"beyond the prepared ego track (0..{self.length:.0f} m)"
        for pole in self.poles:
            if placed.distance_to_point(np.array([pole.s, pole.lateral])) < (
                pole.radius + clearance
            ):
                return f"in pole {pole.id}"
        centre = np.array([[placed.s, placed.offset]])
        samples = placed.samples(clearance)
        on = {p.index for p in self.platforms if bool(p.contains(centre)[0])}
        if zone == "platform" and not on:
            return "not on a platform"
        for p in self.platforms:
            inside = p.contains(samples)
            if (p.index in on and not inside.all()) or (p.index not in on and inside.any()):
                return f"across the edge of platform {p.index}"
        if not on and abs(placed.offset) > BED_HALF_WIDTH:
            lo, hi = placed.lateral_range(clearance)
            if lo < BED_HALF_WIDTH and hi > -BED_HALF_WIDTH:
                return "half on the track bed (its footprint reaches over the bed's edge)"
        for other in others:  # (a moving object's every position is one of them)
            if placed.distance_to(other) < min_spacing:
                return f"nearer than {min_spacing:g} m to another object of the variant"
        return None

    # ------------------------------------------------------------------ view
    def first_view(
        self, p_world: F64, s_obj: float, far_m: float, half_angle_deg: float
    ) -> tuple[int, float] | None:
        """(frame, distance along the track) of the first frame of the range where the
        point ``p_world`` (3,) lies ahead within ``half_angle_deg`` of the train's heading
        and at most ``far_m`` along the track; None: never."""
        d = p_world[None, :] - self.T_world_base[:, :3, 3]
        p_base = np.einsum("nij,ni->nj", self.T_world_base[:, :3, :3], d)  # R^T d
        ahead = s_obj - self.s_train
        angle = np.degrees(np.arctan2(np.abs(p_base[:, 1]), p_base[:, 0]))
        seen = (p_base[:, 0] > 0.0) & (angle <= half_angle_deg) & (ahead > 0.0) & (ahead <= far_m)
        if not np.any(seen):
            return None
        i = int(np.argmax(seen))
        return int(self.frames[i]), float(ahead[i])


def _platform_outline(index: int, plane: Any, ego: Any) -> PlatformOutline:
    """A platform plane's outline in track coordinates. The preparation's outline is its
    near rows then its far rows reversed (scene_elements._outline); the half nearer the
    centreline is taken as the near edge."""
    poly = np.asarray(plane.polygon, dtype=np.float64).reshape(-1, 3)
    pr = ego.project(poly)
    sl = np.column_stack([pr.s, pr.lateral])
    k = len(sl) // 2
    a, b = sl[:k], sl[k:][::-1]
    if len(sl) % 2 or k < 2:  # not the preparation's layout: its s-extent at its lateral range
        s0, s1 = float(sl[:, 0].min()), float(sl[:, 0].max())
        lat = sorted((float(sl[:, 1].min()), float(sl[:, 1].max())), key=abs)
        a = np.array([[s0, lat[0]], [s1, lat[0]]])
        b = np.array([[s0, lat[1]], [s1, lat[1]]])
    if np.mean(np.abs(a[:, 1])) > np.mean(np.abs(b[:, 1])):
        a, b = b, a
    side = "left" if float(np.median(sl[:, 1])) > 0 else "right"
    near, far = (a, b) if a[0, 0] <= a[-1, 0] else (a[::-1], b[::-1])
    return PlatformOutline(index=index, side=side, near=near, far=far)


def platform_outlines(planes: Sequence[Any], ego: Any) -> list[PlatformOutline]:
    """The platforms of a preparation in track coordinates, the pieces of one platform
    joined (:data:`PLATFORM_JOIN_GAP_M`)."""
    pieces = [_platform_outline(i, p, ego) for i, p in enumerate(planes)
              if p.kind == "platform" and len(p.polygon) >= 3]  # fmt: skip
    out: list[PlatformOutline] = []
    for side in ("left", "right"):
        mine = sorted((p for p in pieces if p.side == side), key=lambda p: p.s_range[0])
        for p in mine:
            last = out[-1] if out and out[-1].side == side else None
            if last is not None and p.s_range[0] - last.s_range[1] <= PLATFORM_JOIN_GAP_M:
                out[-1] = PlatformOutline(last.index, side, np.vstack([last.near, p.near]),
                                          np.vstack([last.far, p.far]))  # fmt: skip
            else:
                out.append(p)
    return out


__all__ = [
    "BESIDE_WIDTH_M",
    "PLATFORM_JOIN_GAP_M",
    "Footprint",
    "GeometryError",
    "Placed",
    "PlatformOutline",
    "PoleSpot",
    "SequenceGeometry",
    "platform_outlines",
    "points_in_polygon",
    "rectangle_distance",
    "rotated_extent",
]
