"""Moving objects: a path walked at a speed, the object's pose at any sensor timestamp.

A :class:`~worker.augmentation.spec.MotionModel` gives waypoints in track coordinates
``(s, offset)`` (the track placement's: m along the ego track from the first frame's
position, m to the left) or world ``(x, y)``, and a speed. The object leaves the first
waypoint ``start_s`` seconds after the first frame of the range (time ``t_first``, the
lidar's clock), walks the polyline at ``speed_mps`` and stops at the last waypoint (or
walks back, ``end: bounce``). Arc length along a track path is measured in the (s,
offset) plane: on a curve of radius R the ground distance differs by offset / R (0.1 %
at 3 m from a 3 km curve).

At each requested time the pose is: the path point in the world (track paths through
the ego centreline's point and tangent), its height snapped onto the scene proxies (the
lowest hit of five downward rays, the centre and +-0.1 m around it, so a walker crossing
a rail head steps over it instead of onto it), heading along the direction of travel
plus ``yaw_deg``. Velocity: ``speed_mps`` along the direction of travel while walking,
zero while waiting or stopped (world frame, m/s). Every pose's footprint is checked
against the poles as a static placement is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from renderer.mesh import ObjectMesh, ProxyMesh
from worker.augmentation.placement import (
    RAIL_HEIGHT_ABOVE_BED,
    SNAP_FROM_ABOVE,
    PlacementError,
    check_poles,
)
from worker.augmentation.spec import MotionModel

F64 = NDArray[np.float64]

#: Offsets (m) of the snapping rays around the footprint centre.
SNAP_SPREAD_M = 0.1


@dataclass(frozen=True)
class MovingPoses:
    """A moving object at n times.

    T_world_obj : (n, 4, 4) poses; velocity_world : (n, 3) m/s; walked_m : (n,) distance
    walked since the start (the walk cycle's clock); s_offset : (n, 2) track coordinates
    (s from the first frame's position, offset) or None for a world path.
    """

    T_world_obj: F64
    velocity_world: F64
    walked_m: F64
    s_offset: F64 | None


def path_position(motion: MotionModel, t_rel: F64) -> tuple[F64, F64, F64]:
    """Where on the path the object is ``t_rel`` (n,) seconds after the first frame.

    Returns (points (n, 2) in the path's coordinates, unit directions of travel (n, 2)
    (defined while waiting or stopped too: the segment's), distance walked (n,) m).
    """
    pts = np.asarray(motion.path, dtype=np.float64)
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    keep = seg_len > 1e-9
    pts = np.vstack([pts[:1], pts[1:][keep]])
    seg, seg_len = seg[keep], seg_len[keep]
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = float(cum[-1])
    walked = motion.speed_mps * np.clip(np.asarray(t_rel, dtype=np.float64) - motion.start_s,
                                        0.0, None)  # fmt: skip
    if motion.end == "stop":
        walked = np.minimum(walked, total)
        along = walked
        sign = np.ones_like(walked)
    else:
        cyc = np.mod(walked, 2.0 * total)
        back = cyc > total
        along = np.where(back, 2.0 * total - cyc, cyc)
        sign = np.where(back, -1.0, 1.0)
    k = np.clip(np.searchsorted(cum, along, side="right") - 1, 0, len(seg) - 1)
    frac = (along - cum[k]) / seg_len[k]
    p = pts[k] + frac[:, None] * seg[k]
    d = seg[k] / seg_len[k, None] * sign[:, None]
    return p, d, walked


def _moving(motion: MotionModel, t_rel: F64) -> NDArray[np.bool_]:
    """Whether the object is walking at each time (not waiting, not stopped)."""
    total = float(np.linalg.norm(np.diff(np.asarray(motion.path), axis=0), axis=1).sum())
    dt = np.asarray(t_rel, dtype=np.float64) - motion.start_s
    if motion.end == "stop":
        return (dt >= 0.0) & (motion.speed_mps * dt < total)
    return dt >= 0.0


def snap_heights(proxies: ProxyMesh | None, p_world: F64) -> F64:
    """(n, 3) points -> (n,) height of the proxy surface below each (module docstring:
    the lowest of five rays), NaN where no ray hits."""
    out = np.full(len(p_world), np.nan)
    if proxies is None or len(proxies.faces) == 0 or len(p_world) == 0:
        return out
    origin = p_world.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((proxies.vertices - origin).astype(np.float32)),
        o3d.core.Tensor(proxies.faces.astype(np.uint32)),
    )
    r = SNAP_SPREAD_M
    around = np.array([[0.0, 0.0], [r, 0.0], [-r, 0.0], [0.0, r], [0.0, -r]])
    start = (p_world - origin)[:, None, :] + np.zeros((1, 5, 3))
    start[:, :, :2] += around[None]
    start[:, :, 2] += SNAP_FROM_ABOVE
    rays = np.concatenate([start.reshape(-1, 3), np.tile([0.0, 0.0, -1.0], (start.size // 3, 1))],
                          axis=1).astype(np.float32)  # fmt: skip
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64).reshape(-1, 5)
    z = p_world[:, None, 2] + SNAP_FROM_ABOVE - t  # inf where a ray misses
    lowest = z.min(axis=1)
    return np.where(np.isfinite(lowest), lowest, np.nan)


def moving_poses(
    motion: MotionModel,
    obj: ObjectMesh,
    *,
    ego: Any,
    track: Any,
    t_first: float,
    times: F64,
    proxies: ProxyMesh | None,
    poles: list[Any],
) -> MovingPoses:
    """The object's poses at ``times`` (n,) (sensor timestamps, s) (module docstring).

    ego : the ego Centreline (track paths need it); track : the vehicle's PoseTrack (the
    first frame's position and the nominal height of world paths).

    Raises PlacementError: a track path without an ego track or off its extent, a pose
    whose footprint cuts a pole.
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    t_rel = times - t_first
    q, d, walked = path_position(motion, t_rel)
    T_first = track.interpolate(np.array([t_first]))[0]
    yaw = math.radians(motion.yaw_deg)
    s_off = None
    if motion.mode == "track":
        if ego is None:
            raise PlacementError(
                "a track path needs the ego track, and preparation found no rails: give the "
                "motion in mode world"
            )
        s0 = float(ego.project(T_first[None, :3, 3]).s[0])
        s_abs = s0 + q[:, 0]
        bad = (s_abs < 0.0) | (s_abs > ego.length)
        if np.any(bad):
            raise PlacementError(
                f"the motion path reaches s={q[bad, 0][0]:g} m, off the prepared track: the "
                f"ego track extends from {-s0:.1f} m to {ego.length - s0:.1f} m relative to "
                "the first frame"
            )
        c = ego.point(s_abs)
        tg = ego.tangent(s_abs)
        left = np.column_stack([-tg[:, 1], tg[:, 0], np.zeros(len(tg))])
        left /= np.linalg.norm(left, axis=1, keepdims=True)
        tg_h = np.column_stack([tg[:, 0], tg[:, 1], np.zeros(len(tg))])
        tg_h /= np.linalg.norm(tg_h, axis=1, keepdims=True)
        p = c + q[:, 1:2] * left
        p[:, 2] = c[:, 2] - np.where(np.abs(q[:, 1]) < 1.0, RAIL_HEIGHT_ABOVE_BED, 0.0)
        dir_w = d[:, 0:1] * tg_h + d[:, 1:2] * left
        s_off = q.copy()
    else:
        p = np.column_stack([q, np.full(len(q), T_first[2, 3])])
        dir_w = np.column_stack([d, np.zeros(len(d))])
    z = snap_heights(proxies, p)
    p[:, 2] = np.where(np.isfinite(z), z, p[:, 2])
    heading = np.arctan2(dir_w[:, 1], dir_w[:, 0]) + yaw
    T = np.tile(np.eye(4), (len(p), 1, 1))
    c_h, s_h = np.cos(heading), np.sin(heading)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c_h, -s_h, s_h, c_h
    T[:, :3, 3] = p
    for k in range(len(p)):
        try:
            check_poles(p[k], obj, float(heading[k]), poles)
        except PlacementError as exc:
            raise PlacementError(f"moving object at t = {t_rel[k]:.2f} s: {exc}") from None
    v = dir_w / np.maximum(np.linalg.norm(dir_w, axis=1, keepdims=True), 1e-12)
    v = v * motion.speed_mps * _moving(motion, t_rel)[:, None]
    return MovingPoses(T, v, walked, s_off)


__all__ = ["MovingPoses", "moving_poses", "path_position", "snap_heights"]
