"""Vehicle poses from the NovAtel INS tables of a sequence: its world frame and the base
poses per INS record (the geometry itself is in :mod:`geometry.poses` and
:mod:`geometry.geodesy`)."""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from geometry.geodesy import WorldFrame
from geometry.poses import InsToLidar, PoseTrack, R_enu_ins_from_novatel
from worker.osdar.ins_tables import InsPva

F64 = NDArray[np.float64]

logger = logging.getLogger(__name__)


def world_frame_from_ins(ins: InsPva) -> WorldFrame:
    """The sequence's world frame: origin at the first (earliest) INS record's position.

    The reported position is used as is (with its errors): this is the project's definition
    of the world frame, and the synthetic sequences' ``ground_truth/world.json`` follows it.
    """
    if len(ins) == 0:
        raise ValueError("cannot define a world frame from an empty INS table")
    ts = np.asarray(ins.timestamp, dtype=np.float64)
    lat = np.asarray(ins.latitude, dtype=np.float64)
    lon = np.asarray(ins.longitude, dtype=np.float64)
    h = np.asarray(ins.height, dtype=np.float64)
    ok = np.isfinite(ts) & np.isfinite(lat) & np.isfinite(lon) & np.isfinite(h)
    if not np.any(ok):
        raise ValueError("no INS record has a finite timestamp and position")
    i = int(np.flatnonzero(ok)[np.argmin(ts[ok])])
    frame = WorldFrame(float(lat[i]), float(lon[i]), float(h[i]))
    logger.debug("world frame from INS record %d: %s", i, frame)
    return frame


def ins_to_T_world_ins(ins: InsPva, world: WorldFrame) -> F64:
    """(n, 4, 4) pose of the INS body frame in the world frame for every INSPVA row.

    Position from lat/lon/height; orientation ``R_world_enu_at(lat, lon) @ R_enu_ins`` with
    the NovAtel attitude, so meridian convergence is applied exactly.
    """
    p_world = world.geodetic_to_world(ins.latitude, ins.longitude, ins.height)
    R_world_ins = world.R_world_enu_at(ins.latitude, ins.longitude) @ R_enu_ins_from_novatel(
        ins.roll, ins.pitch, ins.azimuth
    )
    T = np.tile(np.eye(4), (len(p_world), 1, 1))
    T[:, :3, :3] = R_world_ins
    T[:, :3, 3] = p_world
    return T


def ins_to_base_poses(
    ins: InsPva, world: WorldFrame, ins_to_lidar: InsToLidar | None = None
) -> PoseTrack:
    """Base (merged lidar) poses ``T_world_base = T_world_ins @ T_ins_base`` per INS record.

    Records with non-finite values are dropped (with a warning). Each pose is stamped at the
    true time ``timestamp - latency_s``. ``ins_to_lidar`` defaults to the nominal ASSUMPTION
    (:meth:`InsToLidar.nominal`).
    """
    cal = InsToLidar.nominal() if ins_to_lidar is None else ins_to_lidar
    cols = [
        ins.timestamp,
        ins.latitude,
        ins.longitude,
        ins.height,
        ins.roll,
        ins.pitch,
        ins.azimuth,
    ]
    ok = np.logical_and.reduce([np.isfinite(np.asarray(c, dtype=np.float64)) for c in cols])
    if not np.all(ok):
        logger.warning(
            "INS: dropping %d of %d records with non-finite values", int(np.sum(~ok)), len(ok)
        )
        ins = ins.take(ok)  # type: ignore[assignment]
    if len(ins) == 0:
        raise ValueError("no usable INS records")
    T_world_base = ins_to_T_world_ins(ins, world) @ cal.T_ins_base
    ts = np.asarray(ins.timestamp, dtype=np.float64) - cal.latency_s
    return PoseTrack(ts, T_world_base, np.asarray(ins.frame_idx, dtype=np.int64))
