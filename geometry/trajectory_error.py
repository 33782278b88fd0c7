"""Relative pose error over a lag in frames, as odometry benchmarks measure it.

For a lag ``L`` and every frame ``i`` with a frame ``i + L``, the error of the estimated
relative motion against the true one::

    E_i = (T_i^-1 T_(i+L))_true^-1 (T_i^-1 T_(i+L))_est

Its translation norm (m) and rotation angle (deg) are what an augmentation needs: a point
mapped in frame ``i`` must project right in frame ``i + L``. A rigid shift of the whole
trajectory (and of a map made with it) cancels out. This is evo's ``RPE`` with
``delta_unit=frames``, ``all_pairs=True`` and the ``translation_part`` /
``rotation_angle_deg`` relations (``tests/geometry/test_trajectory_error.py`` checks
the two agree).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry.transforms import invert_T

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LagError:
    """Relative pose errors over one lag: per pair (n - lag,) translation m, rotation deg."""

    lag: int
    translation_m: F64
    rotation_deg: F64

    def summary(self) -> dict[str, float | int | None]:
        """Mean, median, max and RMSE of both parts (None where there is no pair)."""
        out: dict[str, float | int | None] = {"lag": self.lag, "pairs": len(self.translation_m)}
        for name, v in (("t", self.translation_m), ("r", self.rotation_deg)):
            unit = "m" if name == "t" else "deg"
            ok = len(v) > 0
            out[f"{name}_mean_{unit}"] = float(np.mean(v)) if ok else None
            out[f"{name}_median_{unit}"] = float(np.median(v)) if ok else None
            out[f"{name}_max_{unit}"] = float(np.max(v)) if ok else None
            out[f"{name}_rmse_{unit}"] = float(np.sqrt(np.mean(v**2))) if ok else None
        return out


def relative_pose_error(T_est: F64, T_true: F64, lag: int) -> LagError:
    """Relative pose errors of ``T_est`` against ``T_true`` over ``lag`` frames.

    Parameters
    ----------
    T_est, T_true : (n, 4, 4) poses of the same frames, in any world frames of their own.
    lag : frames between the two poses of a pair (>= 1).

    Returns
    -------
    LagError with (max(n - lag, 0),) arrays.
    """
    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    if T_est.shape != T_true.shape or T_est.ndim != 3 or T_est.shape[1:] != (4, 4):
        raise ValueError(f"poses must both be (n, 4, 4), got {T_est.shape} and {T_true.shape}")
    if lag < 1:
        raise ValueError(f"lag must be >= 1, got {lag}")
    n = len(T_est)
    if n <= lag:
        return LagError(lag, np.zeros(0), np.zeros(0))
    D_est = invert_T(T_est[:-lag]) @ T_est[lag:]
    D_true = invert_T(T_true[:-lag]) @ T_true[lag:]
    E = invert_T(D_true) @ D_est
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    # angle from the trace, clipped: exact enough above 1e-4 deg, and E is near identity
    # here; below, the skew part is the better-conditioned measure
    R = E[:, :3, :3]
    skew = 0.5 * np.stack(
        [R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1
    )
    cos = np.clip(0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    angle = np.arctan2(np.linalg.norm(skew, axis=1), cos)
    return LagError(lag, t, np.degrees(angle))


def relative_pose_errors(
    T_est: F64, T_true: F64, lags: tuple[int, ...] = (1, 10, 30)
) -> dict[int, LagError]:
    """:func:`relative_pose_error` for each lag (lags without a pair give empty arrays)."""
    return {lag: relative_pose_error(T_est, T_true, lag) for lag in lags}
