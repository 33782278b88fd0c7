"""A rotation source's own noise from its third differences, without a second source.

A train's attitude changes smoothly: over three 0.1 s frame steps the change of its
angular rate (a clothoid's yaw acceleration times the step squared) is a few thousandths
of a degree at most. The second difference of a source's frame-to-frame rotations
(the third difference of its attitude) therefore holds its noise almost alone:

- a white error ``e_k`` on every record (an INS's attitude noise; the per-scan
  registration error of scan-to-map odometry) adds ``e_(k+3) - 3 e_(k+2) + 3 e_(k+1) -
  e_k``: variance 20 sigma_e^2;
- a random walk with steps ``d_k`` (a drift) adds ``d_(k+2) - 2 d_(k+1) + d_k``: 6 sigma_d^2.

A frame step's rotation error is ``e_(k+1) - e_k + d_k`` (variance 2 sigma_e^2 +
sigma_d^2): the third differences' variance over 10 is that step variance, less 0.4
sigma_d^2 (a slight underestimate where the drift dominates). An INS record's white noise
is their variance over 20.

Measured against a second source instead (the INS against the odometry, as the fused
smoothing did for the heading), the other source's own step error counts as this one's: a
good INS's heading noise (0.005 deg) measured 0.009-0.03 deg against the odometry, and the
fused heading over 30 frames followed the odometry's drift.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from worker.preparation.localization.ins_wander import robust_rms

F64 = NDArray[np.float64]

#: Fewest third differences for a measurement.
MIN_SAMPLES = 6
#: Steps whose duration differs from the median step's by more than this share (a dropped
#: frame) are left out: their rotation is not comparable with their neighbours'.
STEP_TOLERANCE = 0.1


def third_difference_rms(rel: F64, times: F64, valid: NDArray[np.bool_]) -> F64 | None:
    """(3,) robust RMS (rad) of the second differences of frame-to-frame rotations (the
    third differences of the attitude) about roll, pitch and heading, None with fewer than
    :data:`MIN_SAMPLES` of them.

    rel : (n-1, 3, 3) each step's rotation in its earlier frame's axes (x forward, y left,
    z up); times : (n,) s; valid : (n-1,) the steps to use (both frames measured, not
    skipped). Rates are compared, scaled to the median step.
    """
    rel = np.asarray(rel, dtype=np.float64)
    if len(rel) < 3:
        return None
    dt = np.diff(np.asarray(times, dtype=np.float64))
    rate = Rotation.from_matrix(rel).as_rotvec() / np.maximum(dt, 1e-9)[:, None]
    step = float(np.median(dt))
    ok = np.asarray(valid, dtype=bool) & (np.abs(dt - step) <= STEP_TOLERANCE * step)
    d2 = (rate[2:] - 2.0 * rate[1:-1] + rate[:-2]) * step
    use = ok[2:] & ok[1:-1] & ok[:-2]
    if int(np.sum(use)) < MIN_SAMPLES:
        return None
    return robust_rms(d2[use])


def white_noise(R_world_base: F64, times: F64, valid: NDArray[np.bool_]) -> F64 | None:
    """(3,) a record's white attitude noise (rad) about roll, pitch and heading (module
    docstring) from the attitudes (n, 3, 3); None when it cannot be measured."""
    R = np.asarray(R_world_base, dtype=np.float64)
    rms = third_difference_rms(np.swapaxes(R[:-1], 1, 2) @ R[1:], times, valid)
    return None if rms is None else rms / np.sqrt(20.0)


def step_noise(d_R: F64, times: F64, valid: NDArray[np.bool_]) -> F64 | None:
    """(3,) the rotation error (rad) of one frame step about roll, pitch and heading, from
    the steps ``d_R`` (n-1, 3, 3) themselves (module docstring); None when it cannot be
    measured."""
    rms = third_difference_rms(d_R, times, valid)
    return None if rms is None else rms / np.sqrt(10.0)
