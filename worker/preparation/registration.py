"""Registration: the lidar clouds of a sequence merged into the world frame.

OSDaR23 clouds are motion-compensated into the base frame at the lidar timestamp of their
frame, so one pose per frame places a whole cloud: p_world = T_world_base(t_lidar) p_base.
Each kept point remembers its frame and sensor_index.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from renderer.transforms import transform_points
from worker.osdar.sequence import Sequence
from worker.poses import PoseTrack
from worker.preparation.frame_clouds import FrameClouds

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class RegisteredCloud:
    """Merged cloud in the world frame.

    xyz : (n, 3) float64 world points; frame_idx : (n,) int32 frame counter of each point;
    sensor_index : (n,) uint8; intensity : (n,) float32.
    """

    xyz: F64
    frame_idx: NDArray[np.int32]
    sensor_index: NDArray[np.uint8]
    intensity: NDArray[np.float32]

    def __len__(self) -> int:
        return len(self.xyz)

    def select(self, mask: NDArray) -> RegisteredCloud:
        return RegisteredCloud(
            self.xyz[mask], self.frame_idx[mask], self.sensor_index[mask], self.intensity[mask]
        )

    @staticmethod
    def concatenate(parts: list[RegisteredCloud]) -> RegisteredCloud:
        if not parts:
            return RegisteredCloud(
                np.zeros((0, 3)),
                np.zeros(0, np.int32),
                np.zeros(0, np.uint8),
                np.zeros(0, np.float32),
            )
        return RegisteredCloud(
            np.concatenate([p.xyz for p in parts]),
            np.concatenate([p.frame_idx for p in parts]),
            np.concatenate([p.sensor_index for p in parts]),
            np.concatenate([p.intensity for p in parts]),
        )


def voxel_keep(xyz: F64, voxel_size: float) -> NDArray[np.int64]:
    """Indices of one point per occupied voxel (the first in input order), sorted.

    Deterministic and attribute-preserving (the kept point is a real measurement, not a
    centroid, so its frame, sensor and intensity stay meaningful). Voxel indices are
    packed into one int64 (21 bits per axis, relative to the cloud's minimum corner) so the
    uniqueness test is a fast 1-D sort; a cloud spanning more than 2^21 voxels along an
    axis falls back to the row-wise unique.
    """
    if voxel_size <= 0 or len(xyz) == 0:
        return np.arange(len(xyz))
    key = np.floor(xyz / voxel_size).astype(np.int64)
    key -= key.min(axis=0)
    if int(key.max()) < (1 << 21):
        packed = (key[:, 0] << 42) | (key[:, 1] << 21) | key[:, 2]
        _, first = np.unique(packed, return_index=True)
    else:
        _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def register_clouds(
    seq: Sequence,
    track: PoseTrack,
    voxel_size: float = 0.05,
    frames: Iterable[int] | None = None,
    max_range: float | None = None,
    sensors: Iterable[int] | None = None,
    clouds: FrameClouds | None = None,
) -> RegisteredCloud:
    """Merge the frames' clouds into the world frame with ``track`` (T_world_base).

    Parameters
    ----------
    seq : the sequence.
    track : poses T_world_base; evaluated at each frame's lidar timestamp.
    voxel_size : m; 0 keeps every point. Applied per frame and again to the union.
    frames : frame counters to use (default all).
    max_range : drop points farther than this from the base origin (m).
    sensors : sensor_index values to keep (default all).
    clouds : the frames' clouds already read and filtered (a FrameClouds of the same
        sequence); read from the files when None.
    """
    lidar = seq.lidar_stream
    if lidar is None:
        raise ValueError(f"sequence {seq.name} has no lidar stream")
    counters = list(seq.frame_indices if frames is None else frames)
    ts = dict(zip(seq.frame_indices, seq.timestamps(lidar), strict=True))
    keep_sensors = None if sensors is None else np.asarray(list(sensors), dtype=np.uint8)
    parts = []
    for f in counters:
        if clouds is not None:
            fc = clouds.get(f)
            p_base, si, inten = fc.p_base, fc.sensor_index, fc.intensity
        else:
            cloud = seq.pcd(f, allow_nonfinite=True)
            p_base = cloud.xyz
            si = cloud.fields.get("sensor_index")
            si = np.zeros(len(p_base), np.uint8) if si is None else si.astype(np.uint8)
            inten = cloud.fields.get("intensity")
            n = len(p_base)
            inten = np.zeros(n, np.float32) if inten is None else inten.astype(np.float32)
        mask = np.isfinite(p_base).all(axis=1)
        if max_range is not None:
            mask &= np.einsum("ij,ij->i", p_base, p_base) <= max_range**2
        if keep_sensors is not None:
            mask &= np.isin(si, keep_sensors)
        p_base, si, inten = p_base[mask], si[mask], inten[mask]
        T = track.interpolate(np.array([ts[f]]))[0]
        p_world = transform_points(T, p_base)
        k = voxel_keep(p_world, voxel_size)
        parts.append(RegisteredCloud(p_world[k], np.full(len(k), f, np.int32), si[k], inten[k]))
    merged = RegisteredCloud.concatenate(parts)
    k = voxel_keep(merged.xyz, voxel_size)
    log.info("registered %d frames: %d points (voxel %.3f m)", len(counters), len(k), voxel_size)
    return merged.select(k)
