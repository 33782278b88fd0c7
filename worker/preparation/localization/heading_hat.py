"""Each heading source's own error: the INS, the lidar odometry and the course over ground.

The heading change between two frames is measured three ways with independent errors:
the INS attitude (its filter's heading wanders), the odometry's relative rotation (scan
matching can turn too little or too much, e.g. on a slow train in a tight curve), and the
direction of the INS velocity (GNSS Doppler: its noise is white and does not follow the
attitude's wander). A train's base turns as its velocity does (in a constant curve the
angle between them is constant), so the three-cornered hat (:mod:`.hat`) gives each its
own error variance over the lag. Without it, the INS's heading wander was measured
against the odometry alone: the odometry's drift counted as the INS's (a good INS read as
wandering 0.02 deg a second and the fused heading followed the odometry), and an odometry
that did not see a slow tight curve (0.5 deg a second) made the INS look as bad.

The velocity's direction is noisy at low speed (5 mm/s of noise at 1.5 m/s is 0.2 deg): it
is averaged over :data:`WINDOW_S` and used only where the train moves faster than
:data:`MIN_SPEED_MPS`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from worker.preparation.localization.hat import hat_variances

F64 = NDArray[np.float64]

#: Averaging window of the velocity (s) before its direction is taken.
WINDOW_S = 1.0
#: Slowest speed (m/s) at which the velocity's direction is used.
MIN_SPEED_MPS = 1.0
#: Fewest frame pairs for the hat: with fewer, its sampling noise (a few pairs of a short
#: sequence) is larger than what it measures (a 25-frame sequence: 15 pairs at a lag of
#: 10, INS error read as 0.07 deg where it was 0.13).
MIN_PAIRS = 20


@dataclass(frozen=True)
class HeadingErrors:
    """Heading error variances (rad^2) over ``lag`` frames of each source."""

    ins: float
    odometry: float
    course: float
    lag: int
    pairs: int


def course_over_ground(v_world: F64, times: F64) -> F64:
    """(n,) direction (rad, about world z) of the velocity averaged over WINDOW_S, the window
    shrunk symmetrically near either end (a one-sided average lags in a curve); NaN where
    the averaged speed is below MIN_SPEED_MPS.

    v_world : (n, 3) m/s; times : (n,) s.
    """
    v = np.asarray(v_world, dtype=np.float64)[:, :2]
    n = len(v)
    dt = float(np.median(np.diff(times))) if n > 1 else 1.0
    half = np.minimum(
        round(WINDOW_S / max(dt, 1e-6)) // 2, np.minimum(np.arange(n), n - 1 - np.arange(n))
    )
    c = np.vstack([np.zeros((1, 2)), np.cumsum(v, axis=0)])
    i = np.arange(n)
    v_avg = (c[i + half + 1] - c[i - half]) / (2 * half + 1)[:, None]
    course = np.unwrap(np.arctan2(v_avg[:, 1], v_avg[:, 0]))
    course[np.linalg.norm(v_avg, axis=1) < MIN_SPEED_MPS] = np.nan
    return course


def heading_errors(
    R_ins: F64,
    R_odo: F64,
    v_world: F64,
    times: F64,
    valid: NDArray[np.bool_],
    lag: int,
) -> HeadingErrors | None:
    """The three sources' heading error variances over ``lag`` frames, None with fewer than
    :data:`MIN_PAIRS` frame pairs where the train moves.

    R_ins, R_odo : (n, 3, 3) attitudes; v_world : (n, 3) INS velocity; valid : (n,) frames
    with an INS record of their own.
    """
    n = len(times)
    if lag < 1 or n <= lag:
        return None
    course = course_over_ground(v_world, np.asarray(times, dtype=np.float64))
    k = np.arange(n - lag)
    j = k + lag
    use = valid[k] & valid[j] & np.isfinite(course[k]) & np.isfinite(course[j])
    k, j = k[use], j[use]
    if len(k) < MIN_PAIRS:
        return None
    about_z = np.zeros((len(k), 3))
    about_z[:, 2] = course[j] - course[k]
    rel = {
        "ins": np.swapaxes(R_ins[k], 1, 2) @ R_ins[j],
        "odometry": np.swapaxes(R_odo[k], 1, 2) @ R_odo[j],
        "course": Rotation.from_rotvec(about_z).as_matrix(),
    }
    v = hat_variances(rel, axes=slice(2, 3))
    if v is None:
        return None
    return HeadingErrors(
        ins=float(v["ins"][0]),
        odometry=float(v["odometry"][0]),
        course=float(v["course"][0]),
        lag=lag,
        pairs=len(k),
    )
