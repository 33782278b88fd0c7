"""Reprojection error of known 3D landmarks under a pose track (the paper's RPE and jitter).

RPE_i = ||GT_i - p_i|| (px) between a landmark's observed pixel and the projection of its
3D point with frame i's estimated pose (at that camera's own timestamp);
J_i = |RPE_{i+1} - RPE_i|. See ../shared/design/OSDAR23.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel
from geometry.poses import PoseTrack

F64 = NDArray[np.float64]


@dataclass
class LandmarkErrors:
    """Per observation: frame counter, landmark index, RPE (px); jitter per landmark run."""

    frame_idx: NDArray[np.int64]
    landmark: NDArray[np.int64]
    rpe: F64
    jitter: F64

    def summary(self) -> dict[str, float]:
        """Mean and std of RPE and jitter (px); NaN-free (empty gives NaN means)."""

        def ms(x: F64) -> tuple[float, float]:
            return (float(np.mean(x)), float(np.std(x))) if len(x) else (float("nan"),) * 2

        rm, rs = ms(self.rpe)
        jm, js = ms(self.jitter)
        return {
            "rpe_mean": rm,
            "rpe_std": rs,
            "jitter_mean": jm,
            "jitter_std": js,
            "observations": len(self.rpe),
        }


def landmark_errors(
    cam: CameraModel,
    track: PoseTrack,
    xyz_world: F64,
    observations: list[dict[int, tuple[float, float] | None]],
    camera_times: dict[int, float],
) -> LandmarkErrors:
    """RPE of every observed landmark in every frame, and jitter between consecutive frames.

    Parameters
    ----------
    cam : the camera at the resolution the observations are in.
    track : estimated T_world_base over time.
    xyz_world : (m, 3) landmark positions in the world frame.
    observations : per landmark, {frame counter: (u, v) or None}.
    camera_times : {frame counter: the camera's timestamp (s)}.
    """
    frames, lms, rpes, jit = [], [], [], []
    for j, obs in enumerate(observations):
        seen = sorted(f for f, uv in obs.items() if uv is not None and f in camera_times)
        if not seen:
            continue
        t = np.array([camera_times[f] for f in seen])
        T = track.interpolate(t)
        e = np.full(len(seen), np.nan)
        for k in range(len(seen)):
            uv, ok = cam.project_world(xyz_world[j : j + 1], T[k])
            if ok[0]:
                e[k] = float(np.linalg.norm(uv[0] - np.asarray(obs[seen[k]], dtype=float)))
        good = np.isfinite(e)
        frames += [f for f, g in zip(seen, good, strict=True) if g]
        lms += [j] * int(good.sum())
        rpes += e[good].tolist()
        # jitter between consecutive frame counters only
        f_arr = np.asarray(seen)
        consecutive = (np.diff(f_arr) == 1) & good[1:] & good[:-1]
        jit += np.abs(np.diff(e))[consecutive].tolist()
    return LandmarkErrors(
        np.asarray(frames, dtype=np.int64),
        np.asarray(lms, dtype=np.int64),
        np.asarray(rpes, dtype=np.float64),
        np.asarray(jit, dtype=np.float64),
    )
