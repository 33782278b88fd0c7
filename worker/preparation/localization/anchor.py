"""Anchoring a lidar-odometry trajectory in the world with every INS record, not one.

KISS-ICP gives motion relative to the first frame; anchoring it by the first INS pose
copies that one record's heading and attitude error (boresight, noise: ~0.6 deg on the
synthetic "paper" profile) into the whole trajectory, and into every map built from it
(the rails, the centreline, the poles), where 0.6 deg is 0.5 m of lateral error 50 m ahead.

Here the odometry trajectory is moved by the rigid transform that best maps its positions
onto the INS positions of all frames (a robust least-squares fit). Positions along a path
determine its heading and its climb, but not the roll about the path itself: that rotation
is kept from the first INS pose. A standstill (or a path too short to carry a direction)
keeps the first-pose anchor.

Where the INS has velocities, the path's direction is taken from their integral instead
of from its positions: over a few seconds the position solution wanders by decimetres
sideways (osdar23 profile, station, 20 frames: 0.6 m over an 11 m path, a 4.9 deg heading
error in the map and in every strategy that follows the rails), while the velocity
(cm/s) traces the path's shape; the positions then only place it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from geometry.poses import PoseTrack

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# Below this path length (m) the fit has no direction to work with.
MIN_PATH_M = 10.0
# Robust loss scale (m): GNSS jumps of metres must not pull the fit.
LOSS_SCALE_M = 0.5


def fit_anchor(
    p_track: F64, p_ins: F64, p_shape: F64 | None = None
) -> tuple[F64, dict[str, float]]:
    """Rigid transform T (4, 4) with T p_track ~ p_ins, roll about the path direction fixed.

    Parameters
    ----------
    p_track : (n, 3) positions of the trajectory to move (world frame, first-pose anchor).
    p_ins : (n, 3) INS positions at the same times.
    p_shape : (n, 3) the path's shape from the INS velocity integral (any offset): the
        rotation is fitted to it, the translation to ``p_ins`` (None: both to ``p_ins``).

    Returns
    -------
    T (4, 4) to left-multiply the trajectory's poses with (identity when the path is too
    short), and diagnostics (path length m, RMS residual before / after m, rotation deg).
    """
    p = np.asarray(p_track, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(p_ins, dtype=np.float64).reshape(-1, 3)
    s = q if p_shape is None else np.asarray(p_shape, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(p).all(1) & np.isfinite(q).all(1) & np.isfinite(s).all(1)
    p, q, s = p[ok], q[ok], s[ok]
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
    rms0 = float(np.sqrt(np.mean(np.sum((p - q) ** 2, 1)))) if len(p) else 0.0
    info = {"path_m": length, "rms_before_m": rms0, "rms_after_m": rms0, "rotation_deg": 0.0}
    if len(p) < 3 or length < MIN_PATH_M:
        return np.eye(4), info
    c = p.mean(0)
    d = p[-1] - p[0]
    d /= max(np.linalg.norm(d), 1e-12)  # path direction: the axis whose roll is unobservable
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(up, d)
    side /= max(np.linalg.norm(side), 1e-12)
    axes = np.stack([up, side])  # rotations allowed: yaw (about up) and climb (about side)

    def residual(x: F64, target: F64) -> F64:
        R = Rotation.from_rotvec(x[:2] @ axes).as_matrix()
        return ((p - c) @ R.T + c + x[2:] - target).ravel()

    x0 = np.concatenate([[0.0, 0.0], (s - p).mean(0)])
    sol = least_squares(
        residual, x0, loss="soft_l1", f_scale=LOSS_SCALE_M, x_scale="jac", args=(s,)
    )
    R = Rotation.from_rotvec(sol.x[:2] @ axes).as_matrix()
    shift = sol.x[2:]
    if p_shape is not None:  # the shape gave the rotation; the positions place it
        shift = np.median(q - ((p - c) @ R.T + c), axis=0)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + shift
    moved = p @ R.T + T[:3, 3]
    info["rms_after_m"] = float(np.sqrt(np.mean(np.sum((moved - q) ** 2, 1))))
    info["rotation_deg"] = float(np.degrees(np.linalg.norm(sol.x[:2])))
    return T, info


def velocity_path(v_world: F64, times: F64) -> F64 | None:
    """(n, 3) the path traced by integrating the INS velocity (trapezoids) from 0, or None
    without velocities."""
    v = np.asarray(v_world, dtype=np.float64).reshape(-1, 3)
    if len(v) < 2 or not np.any(np.linalg.norm(v, axis=1) > 0):
        return None
    dt = np.diff(np.asarray(times, dtype=np.float64))
    steps = 0.5 * (v[1:] + v[:-1]) * dt[:, None]
    return np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])


def anchored_to_ins(
    track: PoseTrack, ins_track: PoseTrack, v_world: F64 | None = None
) -> tuple[PoseTrack, dict[str, float]]:
    """``track`` moved by :func:`fit_anchor` onto the INS positions at its own timestamps
    (its direction from the INS velocity ``v_world`` (n, 3) at those times, when given)."""
    p_ins = ins_track.interpolate(track.timestamps, max_extrapolation_s=1.0)[:, :3, 3]
    shape = None if v_world is None else velocity_path(v_world, track.timestamps)
    T, info = fit_anchor(track.T[:, :3, 3], p_ins, shape)
    log.info(
        "odometry anchored on %d INS positions over %.0f m: rotation %.3f deg, RMS %.3f -> %.3f m",
        len(track),
        info["path_m"],
        info["rotation_deg"],
        info["rms_before_m"],
        info["rms_after_m"],
    )
    return PoseTrack(track.timestamps, T @ track.T, track.frame_idx), info
