"""Registration: the lidar clouds of a sequence merged into the world frame.

OSDaR23 clouds are motion-compensated into the base frame at the lidar timestamp of their
frame, so one pose per frame places a whole cloud: p_world = T_world_base(t_lidar) p_base.
Each kept point remembers its frame and sensor_index.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry.columns import finite_rows
from geometry.poses import PoseTrack
from geometry.transforms import transform_points
from geometry.voxels import unique_first
from worker.osdar.sequence import Sequence
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


def register_clouds(
    seq: Sequence,
    track: PoseTrack,
    voxel_size: float = 0.05,
    frames: Iterable[int] | None = None,
    max_range: float | None = None,
    sensors: Iterable[int] | None = None,
    clouds: FrameClouds | None = None,
    lateral_limit: float | None = None,
) -> RegisteredCloud:
    """Merge the frames' clouds into the world frame with ``track`` (T_world_base).

    One point per world voxel is kept: the first in (frame order, point order), i.e. the
    same result as :func:`voxel_keep` on the concatenation, computed frame by frame (a
    per-frame unique, then a sorted array of the voxels already taken) so memory stays
    linear in the number of kept points. (With ``max_range`` None, points beyond the span
    the keys were sized for share the border voxels.)

    Parameters
    ----------
    seq : the sequence.
    track : poses T_world_base; evaluated at each frame's lidar timestamp.
    voxel_size : m; 0 keeps every point.
    frames : frame counters to use (default all).
    max_range : drop points farther than this from the base origin (m).
    sensors : sensor_index values to keep (default all).
    clouds : the frames' clouds already read and filtered (a FrameClouds of the same
        sequence); read from the files when None.
    lateral_limit : drop points with |y| beyond this in the base frame (m): everything
        preparation builds lies in a corridor along the track.
    """
    lidar = seq.lidar_stream
    if lidar is None:
        raise ValueError(f"sequence {seq.name} has no lidar stream")
    counters = list(seq.frame_indices if frames is None else frames)
    ts = dict(zip(seq.frame_indices, seq.timestamps(lidar), strict=True))
    keep_sensors = None if sensors is None else np.asarray(list(sensors), dtype=np.uint8)
    T_all = track.interpolate(np.array([ts[f] for f in counters])) if counters else []
    dedup = _VoxelSet(voxel_size, T_all, max_range)
    parts = []
    for f, T in zip(counters, T_all, strict=True):
        p_base, si, inten = _frame_points(seq, f, clouds)
        # FrameClouds has dropped the non-finite points already
        mask = np.ones(len(p_base), bool) if clouds is not None else finite_rows(p_base)
        if max_range is not None:
            mask &= np.einsum("ij,ij->i", p_base, p_base) <= max_range**2
        if lateral_limit is not None:
            mask &= np.abs(p_base[:, 1]) <= lateral_limit
        if keep_sensors is not None:
            mask &= np.isin(si, keep_sensors)
        kept = np.flatnonzero(mask)
        p_world = transform_points(T, p_base.take(kept, axis=0))
        k = dedup.first_new(p_world)
        kk = kept[k]
        parts.append(RegisteredCloud(p_world[k], np.full(len(k), f, np.int32), si[kk], inten[kk]))
    merged = RegisteredCloud.concatenate(parts)
    log.info(
        "registered %d frames: %d points (voxel %.3f m)", len(counters), len(merged), voxel_size
    )
    return merged


def points_near(
    seq: Sequence,
    track: PoseTrack,
    centre_world: F64,
    radius: float,
    clouds: FrameClouds | None = None,
    frames: Iterable[int] | None = None,
) -> F64:
    """Every frame's points within ``radius`` of ``centre_world``, at full density.

    The registered cloud is voxel-filtered and built from every ``frame_step``-th frame, so
    its nearest point to a small landmark (a pole top) can sit a voxel or a beam gap away
    from it; this gathers all the points of all the frames near one place instead, each
    registered with ``track`` (T_world_base at the frame's lidar timestamp).

    centre_world : (3,) world point; radius : m. Returns (n, 3) float64 world points.
    """
    lidar = seq.lidar_stream
    if lidar is None:
        raise ValueError(f"sequence {seq.name} has no lidar stream")
    ts = dict(zip(seq.frame_indices, seq.timestamps(lidar), strict=True))
    counters = [f for f in (seq.frame_indices if frames is None else frames) if np.isfinite(ts[f])]
    if not counters:
        return np.zeros((0, 3))
    T_all = track.interpolate(np.array([ts[f] for f in counters]))
    c = np.asarray(centre_world, dtype=np.float64).reshape(3)
    out = []
    for f, T in zip(counters, T_all, strict=True):
        p_base = _frame_points(seq, f, clouds)[0]
        c_base = (c - T[:3, 3]) @ T[:3, :3]
        d = p_base - c_base
        near = np.einsum("ij,ij->i", d, d) <= radius * radius
        if np.any(near):
            out.append(transform_points(T, p_base[near]))
    return np.concatenate(out) if out else np.zeros((0, 3))


def dense_points(
    seq: Sequence, track: PoseTrack, clouds: FrameClouds | None = None
) -> Callable[[F64, float], F64]:
    """``points_near`` bound to a sequence, a pose track and its frame clouds: the
    ``dense`` argument of the calibration point's full-density refinement."""
    return lambda centre, radius: points_near(seq, track, centre, radius, clouds=clouds)


def _frame_points(
    seq: Sequence, frame: int, clouds: FrameClouds | None
) -> tuple[F64, NDArray[np.uint8], NDArray[np.float32]]:
    """(p_base (n, 3) float64, sensor_index (n,), intensity (n,)) of one frame."""
    if clouds is not None:
        fc = clouds.get(frame)
        return fc.p_base, fc.sensor_index, fc.intensity
    cloud = seq.pcd(frame, allow_nonfinite=True)
    p_base = cloud.xyz
    n = len(p_base)
    si = cloud.fields.get("sensor_index")
    si = np.zeros(n, np.uint8) if si is None else si.astype(np.uint8)
    inten = cloud.fields.get("intensity")
    inten = np.zeros(n, np.float32) if inten is None else inten.astype(np.float32)
    return p_base, si, inten


class _VoxelSet:
    """World voxels already taken, across frames: a sorted array of voxel keys.

    Keys are the voxel indices relative to a corner below the whole trajectory, packed into
    one int64 (21 bits per axis) when the sequence spans fewer than 2^21 voxels per axis,
    else the three int64 indices viewed as one 24-byte value (both sort and search the
    same way). Each frame adds its new keys with one ``searchsorted`` and one ``insert``,
    which copies the keys taken so far: time per frame linear in the frame's cloud plus the
    kept points (fine for the few dozen frames of a registration), memory one key per kept
    point.
    """

    def __init__(self, voxel_size: float, T_all: F64, max_range: float | None) -> None:
        self.voxel = float(voxel_size)
        self.enabled = self.voxel > 0 and len(T_all) > 0
        if not self.enabled:
            return
        reach = (max_range if max_range is not None else 500.0) + 1.0
        pos = np.asarray(T_all)[:, :3, 3]
        self.lo = np.floor((pos.min(0) - reach) / self.voxel).astype(np.int64)
        span = np.floor((pos.max(0) + reach) / self.voxel).astype(np.int64) - self.lo
        self.packable = bool(np.all(span < (1 << 21)))
        self.taken: NDArray = np.zeros(0, np.int64 if self.packable else np.dtype((np.void, 24)))

    def _keys(self, p_world: F64) -> NDArray:
        """(n,) voxel keys of (n, 3) world points."""
        if not self.packable:
            key = np.floor(p_world / self.voxel).astype(np.int64) - self.lo
            return np.ascontiguousarray(key).view(np.dtype((np.void, 24))).ravel()
        # Column by column (geometry/columns.py: the (n, 3) loops are several times
        # slower), the same integers. Points beyond the range the keys were sized for
        # (max_range=None) are clipped onto the border voxels (kept apart from each other
        # only up to that border).
        out = self._axis_key(p_world[:, 0], 0) << 42
        out |= self._axis_key(p_world[:, 1], 1) << 21
        out |= self._axis_key(p_world[:, 2], 2)
        return out

    def _axis_key(self, coord: F64, axis: int) -> NDArray[np.int64]:
        """(n,) voxel index along one axis of (n,) world coordinates, from ``lo``,
        clipped to 21 bits."""
        key = np.floor(coord / self.voxel).astype(np.int64)
        key -= self.lo[axis]
        return np.clip(key, 0, (1 << 21) - 1, out=key)

    def first_new(self, p_world: F64) -> NDArray[np.int64]:
        """Indices (sorted) of the first point of every voxel not taken by earlier frames."""
        if not self.enabled or len(p_world) == 0:
            return np.arange(len(p_world))
        uniq, first = unique_first(self._keys(p_world))
        at = np.searchsorted(self.taken, uniq)
        seen = at < len(self.taken)
        seen[seen] = self.taken[at[seen]] == uniq[seen]
        new = ~seen
        self.taken = np.insert(self.taken, at[new], uniq[new])
        return np.sort(first[new])
