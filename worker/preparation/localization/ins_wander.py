"""How fast the INS's error wanders, measured against the lidar odometry.

An INS's error has a slow part (its filter wandering by decimetres and tenths of a degree
over seconds: multipath, a poor heading alignment) on top of its white noise. How large it
is differs by orders of magnitude between systems and runs (OSDaR23's INS: tens of pixels
of raw reprojection error; a well-aligned RTK system: a few), so ``fused`` measures it per
sequence instead of assuming it: over a lag of about one knot spacing the INS's relative
motion is compared with KISS-ICP's, whose drift over a second is millimetres and hundredths
of a degree. The robust spread of the difference is the size of the INS's change over that
lag, plus the odometry's own (which only makes the estimate conservative).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import median_abs_deviation

from geometry.columns import zero_centre

F64 = NDArray[np.float64]

#: Values beyond this many robust sigmas (MAD about zero) are outliers (GNSS jumps).
OUTLIER_SIGMAS = 5.0
#: At least this many frame pairs to measure anything.
MIN_PAIRS = 5
#: Shortest lag (frames) a short sequence's wander is measured over: the one-step
#: difference is the white noise taken out of it.
MIN_LAG = 2


@dataclass(frozen=True)
class InsWander:
    """Robust RMS change over ``lag_s`` of the INS's error against the odometry.

    rotation_rad : (3,) about the base axes (roll x, pitch y, heading z), rad.
    position_m : (3,) along the world axes (east, north, up), m.
    lag_s : the lag it is scaled to (s); pairs : how many frame pairs.
    measured_lag_s : the lag it was measured over: shorter than ``lag_s`` on a sequence too
    short for enough pairs at ``lag_s`` (then scaled up as a steady drift, in proportion).
    """

    rotation_rad: F64
    position_m: F64
    lag_s: float
    pairs: int
    measured_lag_s: float

    @property
    def shortened(self) -> bool:
        """Measured over a shorter lag than asked (a short sequence)."""
        return self.measured_lag_s < self.lag_s - 1e-9


def inliers(x: F64) -> NDArray[np.bool_]:
    """(m, k) the values of each column of ``x`` (m, k) within ``OUTLIER_SIGMAS`` robust
    sigmas (MAD about zero) of zero: those :func:`robust_rms` keeps."""
    a = np.abs(np.asarray(x, dtype=np.float64))
    limit = OUTLIER_SIGMAS * median_abs_deviation(a, axis=0, center=zero_centre, scale="normal")
    keep: NDArray[np.bool_] = a <= limit[None, :]
    return keep


def robust_rms(x: F64) -> F64:
    """(k,) RMS about zero of each column of ``x`` (m, k), leaving out the values beyond
    ``OUTLIER_SIGMAS`` robust sigmas (a few GNSS jumps do not count; a steady drift, whose
    values are all alike, is measured as it is)."""
    a = np.abs(np.asarray(x, dtype=np.float64))
    keep = inliers(a)
    return np.sqrt(np.sum(np.where(keep, a * a, 0.0), axis=0) / np.maximum(keep.sum(axis=0), 1))


def ins_wander(
    T_ins: F64, T_odo: F64, times: F64, covered: NDArray[np.bool_], lag_s: float
) -> InsWander | None:
    """The INS's wander against the odometry over ``lag_s`` (None: too few frame pairs).

    Parameters
    ----------
    T_ins : (n, 4, 4) INS T_world_base at the frames (jumps removed from the positions).
    T_odo : (n, 4, 4) odometry T_world_base at the same frames.
    times : (n,) frame times (s), increasing.
    covered : (n,) frames with an INS record of their own.
    lag_s : the lag (s), e.g. the bias knot spacing.
    """
    n = len(times)
    if n < 2:
        return None
    dt = float(np.median(np.diff(times)))
    want = max(1, round(lag_s / dt)) if dt > 0 else 1
    lag, i = want, _pairs(covered, want)
    while len(i) < MIN_PAIRS and lag > MIN_LAG:
        lag -= 1
        i = _pairs(covered, lag)
    if len(i) < MIN_PAIRS:
        return None
    rot, pos = _differences(T_ins, T_odo, i, lag)
    rot_var, pos_var = robust_rms(rot) ** 2, robust_rms(pos) ** 2
    if lag >= 2:
        # White noise enters every lag's difference alike: what the one-step difference
        # shows of it is no wander (a good INS's 0.004 deg attitude noise read as 0.006
        # deg of wander a second, and its roll then followed the odometry's drift).
        one = np.arange(n - 1)
        one = one[covered[one] & covered[one + 1]]
        if len(one) >= MIN_PAIRS:
            rot1, pos1 = _differences(T_ins, T_odo, one, 1)
            rot_var = np.maximum(rot_var - robust_rms(rot1) ** 2, 0.0)
            pos_var = np.maximum(pos_var - robust_rms(pos1) ** 2, 0.0)
    # a steady drift grows in proportion to the lag (a random walk would grow as its
    # square root: the proportion is the larger, so the INS is not trusted beyond what
    # the short sequence showed)
    scale = want / lag
    return InsWander(
        rotation_rad=np.sqrt(rot_var) * scale,
        position_m=np.sqrt(pos_var) * scale,
        lag_s=want * dt,
        pairs=len(i),
        measured_lag_s=lag * dt,
    )


def _pairs(covered: NDArray[np.bool_], lag: int) -> NDArray[np.int64]:
    """Frames i with an INS record at i and at i + lag."""
    i = np.arange(len(covered) - lag)
    return i[covered[i] & covered[i + lag]]


def _differences(T_ins: F64, T_odo: F64, i: NDArray[np.int64], lag: int) -> tuple[F64, F64]:
    """(m, 3) rotation vectors (base axes, rad) and (m, 3) world displacements (m) of the
    INS's motion from frames ``i`` to ``i + lag`` against the odometry's."""
    j = i + lag
    R_ins, R_odo = T_ins[:, :3, :3], T_odo[:, :3, :3]
    rel_ins = np.swapaxes(R_ins[i], 1, 2) @ R_ins[j]
    rel_odo = np.swapaxes(R_odo[i], 1, 2) @ R_odo[j]
    rot = Rotation.from_matrix(np.swapaxes(rel_odo, 1, 2) @ rel_ins).as_rotvec()
    d_ins = T_ins[j, :3, 3] - T_ins[i, :3, 3]
    d_odo = T_odo[j, :3, 3] - T_odo[i, :3, 3]
    return rot, d_ins - d_odo
