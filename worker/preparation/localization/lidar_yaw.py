"""The merged lidar cloud's yaw against the base frame, from the train's own motion.

OSDaR23 publishes one cloud merged from six lidars whose extrinsics are good to a few
hundredths of a degree; what the registrations see is a blend of them, turned against the
base by an angle ``delta`` of that size (0.65 mrad on a synthetic osdar23 sequence with
the default merge error). Every lidar-derived relative pose is then the base's turned by
``delta``: frame j's lateral position in frame k is off by ``delta`` times the distance
between them, 17 mm over 27 m, three times the scan pairs' own sigma; ``fused`` bent its
heading towards it and the placed object drifted by 8 px on rgb_highres_center over 60
frames.

A train runs on its rails: on straight track its base moves along its own x axis, so over
a pair ``(k, j)`` the direction of travel in frame k, less half the turn between the two
frames (the chord of a constant curvature), is zero, and what remains is ``delta``::

    a = y_k_j / x_k_j - yaw_k_j / 2 = delta    (|curvature| small)

In curves a base that is not over a bogie moves at an angle of its own to its x axis
(curvature times its distance from the bogies' midpoint: 12 mrad at 12.5 m in a 1 km
curve), so only pairs on near-straight track are used (curvature below
:data:`MAX_CURVATURE`, which keeps that angle under 0.3 mrad for a base 15 m from the
midpoint) and long enough that the body's sway (a few millimetres) is a small angle.
The relative yaw itself is not changed by ``delta`` (to first order), so the curvature is
taken from the pairs' own yaw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from geometry.transforms import make_T

F64 = NDArray[np.float64]

#: Pairs used: at least this far apart along the track (m) ...
MIN_DISTANCE_M = 15.0
#: ... on track of curvature below this (1/m; radius above 50 km) ...
MAX_CURVATURE = 2e-5
#: ... and at least this many of them.
MIN_PAIRS = 8


@dataclass(frozen=True)
class YawOffset:
    """The estimate: ``rad`` (the lidar cloud turned by it about the base z axis against the
    base, positive to the left), its standard error, and the pairs behind it."""

    rad: float
    se_rad: float
    pairs: int

    @property
    def significant(self) -> bool:
        """Larger than twice its standard error."""
        return abs(self.rad) > 2.0 * self.se_rad


def non_holonomic_angles(T_k_j: F64) -> tuple[F64, F64]:
    """Per pair the angle of travel in frame k less half the relative yaw (rad), and the
    curvature (1/m) the relative yaw implies. ``T_k_j`` (Q, 4, 4) frame j's base pose in
    frame k's; a reversing train (x < 0) gives the same angle."""
    x = T_k_j[:, 0, 3]
    yaw = np.arctan2(T_k_j[:, 1, 0], T_k_j[:, 0, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        a = T_k_j[:, 1, 3] / x - 0.5 * yaw
        kappa = yaw / x
    return a, kappa


def lidar_yaw_offset(
    T_k_j: F64,
    ok: NDArray[np.bool_],
    lag: NDArray[np.int64],
    *,
    min_distance_m: float = MIN_DISTANCE_M,
    max_curvature: float = MAX_CURVATURE,
    min_pairs: int = MIN_PAIRS,
) -> YawOffset | None:
    """The cloud's yaw against the base from registered pairs, or None (too few pairs on
    straight track far enough apart).

    T_k_j : (Q, 4, 4) relative poses from the lidar; ok : (Q,) those to use; lag : (Q,)
    frames between the pair's two frames. The estimate is the median of the pairs' angles;
    pairs of one lag share most of their frames with their neighbours, so the standard
    error counts one independent pair per lag of frames spanned.
    """
    a, kappa = non_holonomic_angles(np.asarray(T_k_j, dtype=np.float64))
    return _median_angle(
        a, kappa, T_k_j, ok, lag, min_distance_m, max_curvature, min_pairs
    )  # fmt: skip


def _median_angle(
    a: F64,
    kappa: F64,
    T_k_j: F64,
    ok: NDArray[np.bool_],
    lag: NDArray[np.int64],
    min_distance_m: float,
    max_curvature: float,
    min_pairs: int,
) -> YawOffset | None:
    """The median of the per-pair angles ``a`` (Q,) over the pairs far enough apart on
    track of small enough curvature ``kappa`` (Q,); its standard error counts one
    independent pair per lag of frames spanned. None with fewer than ``min_pairs``."""
    x = np.abs(T_k_j[:, 0, 3])
    use = ok & (x >= min_distance_m) & (np.abs(kappa) <= max_curvature) & np.isfinite(a)
    if int(np.sum(use)) < min_pairs:
        return None
    a_used = a[use]
    angle = float(np.median(a_used))
    spread = 1.4826 * float(np.median(np.abs(a_used - angle)))
    lags = np.asarray(lag, dtype=np.float64)[use]
    independent = max(1.0, float(np.sum(1.0 / np.maximum(lags, 1.0))))
    return YawOffset(angle, float(1.2533 * spread / np.sqrt(independent)), int(np.sum(use)))


def vertical_angles(T_k_j: F64) -> tuple[F64, F64]:
    """Per pair the angle of climb in frame k plus half the relative pitch (rad), and the
    vertical curvature (1/m) the relative pitch implies: :func:`non_holonomic_angles` in
    the vertical plane (a pitch about +y, the left axis, lowers the nose). A body following
    its rails has angle 0 on a constant grade; a cloud pitched against the base by ``p``
    gives ``p``."""
    x = T_k_j[:, 0, 3]
    pitch = np.arctan2(-T_k_j[:, 2, 0], T_k_j[:, 0, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        a = T_k_j[:, 2, 3] / x + 0.5 * pitch
        kappa = pitch / x
    return a, kappa


#: Pairs used for the pitch: at least this far apart along the track (m; the body's
#: bounce of a few millimetres is then about a milliradian a pair) ...
MIN_PITCH_DISTANCE_M = 5.0
#: ... on a grade whose curvature, as the pair's relative pitch shows it, is below this
#: (1/m): looser than the horizontal rule, since the body's pitching on its suspension
#: (a few tenths of a milliradian between two frames) is in that relative pitch too.
MAX_VERTICAL_CURVATURE = 1e-4


def lidar_pitch_offset(
    T_k_j: F64,
    ok: NDArray[np.bool_],
    lag: NDArray[np.int64],
    *,
    min_distance_m: float = MIN_PITCH_DISTANCE_M,
    max_curvature: float = MAX_VERTICAL_CURVATURE,
    min_pairs: int = MIN_PAIRS,
) -> YawOffset | None:
    """The cloud's pitch against the base (rad, positive nose down as a pitch about +y),
    from relative poses measured in the cloud (the ground pairs' height and pitch), or
    None: the vertical counterpart of :func:`lidar_yaw_offset`, on pairs of near-constant
    grade. A cloud pitched by ``p`` puts the ground a distance ``x`` ahead ``p x`` off in
    height; the same ground seen again from ``x`` closer is then ``p x`` higher or lower,
    a climb of ``p`` per metre in every relative pose (0.8 mrad: 50 mm over 60 m)."""
    a, kappa = vertical_angles(np.asarray(T_k_j, dtype=np.float64))
    return _median_angle(
        a, kappa, T_k_j, ok, lag, min_distance_m, max_curvature, min_pairs
    )  # fmt: skip


def tilt_lidar_poses(T: F64, pitch: float) -> F64:
    """Relative poses (..., 4, 4) measured in a cloud pitched by ``pitch`` (rad, about the
    base y axis) against the base, expressed in the base: ``R T R^T``, ``R = Ry(pitch)``."""
    R = make_T(Rotation.from_rotvec([0.0, pitch, 0.0]).as_matrix(), np.zeros(3))
    return R @ T @ R.T


def turn_lidar_poses(T: F64, delta: float) -> F64:
    """Relative poses (..., 4, 4) measured in a cloud turned by ``delta`` (rad) about the base
    z axis, expressed in the base: ``R T R^T`` with ``R = Rz(-delta)``."""
    R = make_T(Rotation.from_rotvec([0.0, 0.0, -delta]).as_matrix(), np.zeros(3))
    return R @ T @ R.T
