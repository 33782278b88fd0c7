"""Each frame's lidar cloud read once per preparation and kept, filtered, in memory.

Preparation needs every cloud several times (odometry, pre-registration for the rails,
final registration with the chosen poses). Reading and parsing the PCDs dominates all but
KISS-ICP itself, so a :class:`FrameClouds` reads each file once (``Sequence.pcd`` drops the
non-finite points), drops points beyond ``max_range``, optionally thins it with a voxel
filter in the base frame, and serves it to every consumer.

Per-lidar corrections (:mod:`worker.preparation.lidar_alignment`, the merge's calibration
errors measured between the lidars) are applied here, once, when a frame is read: set them
with :meth:`FrameClouds.set_corrections` before the stages that should see them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry.voxels import voxel_keep
from worker.osdar.sequence import Sequence

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameCloud:
    """One frame's cloud in its base frame at the lidar timestamp.

    p_base32 : (n, 3) float32 as stored in the PCD (half the memory of float64);
    sensor_index : (n,) uint8; intensity : (n,) float32; t_frame : the frame's lidar
    timestamp (s).
    """

    p_base32: NDArray[np.float32]
    sensor_index: NDArray[np.uint8]
    intensity: NDArray[np.float32]
    t_frame: float

    @property
    def p_base(self) -> NDArray[np.float64]:
        """(n, 3) float64 base points (exact: the PCD stores float32)."""
        return self.p_base32.astype(np.float64)


class FrameClouds:
    """Lazy, memoised access to the frames' filtered clouds.

    Parameters
    ----------
    seq : the sequence.
    max_range : points farther than this from the base origin are dropped (m).
    voxel_size : voxel filter in the base frame (m); 0 keeps every point.
    """

    def __init__(self, seq: Sequence, max_range: float = 100.0, voxel_size: float = 0.0) -> None:
        if seq.lidar_stream is None:
            raise ValueError(f"sequence {seq.name} has no lidar stream")
        self.seq = seq
        self.max_range = float(max_range)
        self.voxel_size = float(voxel_size)
        ts = seq.timestamps(seq.lidar_stream)
        self.frame_times = {
            int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)
        }
        self._cache: dict[int, FrameCloud] = {}
        #: sensor_index -> (4, 4) correction applied to that sensor's base points
        self.corrections: dict[int, NDArray[np.float64]] = {}

    def set_corrections(self, corrections: dict[int, NDArray[np.float64]]) -> None:
        """Apply ``corrections`` (sensor_index -> (4, 4), ``p' = R p + t`` in the base
        frame) to every frame served from now on; frames read before are read again."""
        self.corrections = {int(k): np.asarray(v, dtype=np.float64) for k, v in corrections.items()}
        self._cache.clear()

    @property
    def frames(self) -> list[int]:
        return sorted(self.frame_times)

    def get(self, frame: int) -> FrameCloud:
        """The filtered cloud of one frame (read on first use)."""
        hit = self._cache.get(frame)
        if hit is not None:
            return hit

        # Sequence.pcd has dropped (and warned about) non-finite points already.
        cloud = self.seq.pcd(frame, allow_nonfinite=True)
        f = cloud.fields
        p = np.stack([np.asarray(f[k], dtype=np.float32) for k in ("x", "y", "z")], axis=1)
        n = len(p)
        si = f.get("sensor_index")
        si = np.zeros(n, np.uint8) if si is None else np.asarray(si).astype(np.uint8, copy=False)
        it = f.get("intensity")
        it = np.zeros(n, np.float32) if it is None else np.asarray(it, dtype=np.float32)
        move_per_sensor(p, si, self.corrections)
        r2 = _squared_norms(p)
        if float(r2.max(initial=0.0)) > self.max_range**2:
            keep = np.flatnonzero(r2 <= self.max_range**2)
            p, si, it = p.take(keep, axis=0), si[keep], it[keep]
        if self.voxel_size > 0:
            k = voxel_keep(p.astype(np.float64), self.voxel_size)
            p, si, it = p[k], si[k], it[k]
        fc = FrameCloud(p, si, it, self.frame_times.get(frame, np.nan))
        self._cache[frame] = fc
        return fc

    def __iter__(self) -> Iterator[tuple[int, FrameCloud]]:
        for f in self.frames:
            yield f, self.get(f)

    def memory_bytes(self) -> int:
        return sum(
            c.p_base32.nbytes + c.sensor_index.nbytes + c.intensity.nbytes
            for c in self._cache.values()
        )


def move_per_sensor(
    p_base: NDArray[np.floating],
    sensor_index: NDArray[np.uint8],
    by: dict[int, NDArray[np.float64]],
) -> None:
    """Move sensor s's rows of the (n, 3) base points ``p_base`` by ``by[s]`` (4, 4),
    ``p' = R p + t``, in place (computed in float64, stored in ``p_base``'s dtype)."""
    for s, T in by.items():
        sel = sensor_index == s
        if np.any(sel):
            q = p_base[sel].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            p_base[sel] = q.astype(p_base.dtype, copy=False)


def _squared_norms(p: NDArray[np.float32]) -> NDArray[np.float32]:
    """(n,) squared length of each row of (n, 3) float32 points, column by column:
    ``einsum("ij,ij->i", p, p)``'s float32 numbers at a quarter of its time (the same on
    every point of the 100-frame fire_site)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r2 = x * x
    r2 += y * y
    r2 += z * z
    return r2
