"""The INS's accelerometers (``novatel_oem7_corrimu``) as the body's sway between frames.

A train's body sways on its suspension: millimetres sideways and up at about 1 Hz, 2-3 mm
from one lidar frame to the next. A placed object moves against the scene by as much
(0.5 px at 20 m on rgb_highres_center), and nothing else in ``fused`` follows it: the
scan pairs measure lags of 10 and 30 frames, KISS-ICP's steps are 5-30 mm noisy on
sparse clouds, the gyros see rotation only. The corrected IMU's accelerations do: per
record, the INS body's kinematic acceleration along its X / Y / Z axes per IMU sample,
averaged over the logging window before the record (gravity removed, NovAtel's CORRIMU).

Their sum, turned into one frame by the gyros' rotation (:class:`.gyro.GyroChain`),
gives the velocity and, summed again, the position of the body at every record up to an
unknown start velocity and position, which a second difference of the positions at three
consecutive lidar times (the stencil of ``fused``'s smoothness prior) is blind to. So
that is what is measured: per frame the acceleration the accelerometers see, times the
step squared, in the base axes of the stencil's middle frame, to be matched by the
solution's positions. An accelerometer's bias and the gravity the INS's own attitude
error leaves in add a slowly varying acceleration: ``fused`` estimates it with the poses
(a third difference would be blind to it, and also to the lateral drift of a short
sequence that nothing else holds: 7 mm over 10 frames on fire_site where the second
differences keep 2). The lever arm between the INS and the base is left out: the body's
rotation sway (a few hundredths of a degree) moves a point a metre away by a tenth of a
millimetre, which the block's variance factor takes up.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry.poses import R_INS_BASE_NOMINAL
from worker.preparation.localization.base import Health, LocalizationInput
from worker.preparation.localization.gyro import (
    GyroChain,
    lagrange_at,
    read_corrimu,
    rotations_at,
)

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


#: A stencil over a missing record's window (its acceleration interpolated) has its sigma
#: multiplied by 1 + this per such window.
BRIDGE_SIGMA_FACTOR = 1.0


@dataclass(frozen=True)
class AccelDifferences:
    """The accelerometers' differences of the base positions over a stencil of lidar times.

    value : (n-q, 3) sum_i c_ki p(t_(k+i)) in the base axes of frame k + 1 (m), c the
        stencil weights given (q + 1 per row, q the order)
    ok : (n-q,) the stencil's times lie inside the records, no window of irregular length
        between them
    bridged : (n-q,) windows of missing records between them (interpolated)
    """

    value: F64
    ok: NDArray[np.bool_]
    bridged: F64


def read_accelerations(inp: LocalizationInput, imu_rate_hz: float) -> tuple[F64, F64] | None:
    """(m,) record stamps and (m, 3) accelerations (m/s^2 along INS X, Y, Z) of the
    sequence's ``novatel_oem7_corrimu``, None when it has none (or fewer than four)."""
    got = read_corrimu(inp, ("lateral_acc", "longitudinal_acc", "vertical_acc"), imu_rate_hz)
    return got if got is not None and len(got[0]) >= 4 else None


@dataclass(frozen=True)
class PositionChain:
    """The body's motion at the ends of the accelerometers' windows, in the axes of the
    gyro chain's first point, from zero velocity and position at the first window's start.

    t : (M + 1,) times (record clock, s); p, v : (M + 1, 3) position (m), velocity (m/s)
    rough : (M,) windows of irregular length (integrated with the trapezoid)
    bridged : (M,) windows of missing records (their acceleration interpolated)
    """

    t: F64
    p: F64
    v: F64
    rough: NDArray[np.bool_]
    bridged: NDArray[np.bool_]


def position_chain(chain: GyroChain, acc_ins: F64) -> PositionChain:
    """Integrate the records' accelerations (m, 3), along INS X, Y, Z averaged over the
    window before each record, twice (see :class:`PositionChain`).

    Each acceleration, turned into base axes and by the gyros' rotation at its window's
    middle, gives the velocity change over its window exactly. A missing record's window
    gets the cubic through the two windows' accelerations before and after it (a mean
    of its neighbours' misses a 1.3 Hz bounce's curvature by 9 mm/s over the window). The
    positions integrate the cubic through four neighbouring velocities ((-1, 13, 13, -1) /
    24 per window, one-sided at the ends): holding each window's mean acceleration
    instead misses win^3 / 12 times the acceleration's rate a window, 0.18 mm for a 4 mm
    bounce at 1.3 Hz, a tenth of its third difference.
    """
    a_base = np.asarray(acc_ins, dtype=np.float64) @ R_INS_BASE_NOMINAL
    win = chain.window
    R_mid, _, _ = rotations_at(chain, chain.t[1:] - 0.5 * win)
    a_rec = np.einsum("nij,nj->ni", R_mid, a_base)
    ends, acc, lengths, rough, bridged = [], [], [], [], []
    for i, dt in enumerate(np.diff(chain.t)):
        k = round(dt / win)
        if k >= 1 and abs(dt - k * win) <= 0.01 * win:
            for q in range(k - 1, 0, -1):  # missing windows before the record's own
                ends.append(chain.t[i + 1] - q * dt / k)
                acc.append(np.full(3, np.nan))
                lengths.append(dt / k)
                rough.append(False)
                bridged.append(True)
            ends.append(chain.t[i + 1])
            lengths.append(dt / k)
            rough.append(False)
        else:
            ends.append(chain.t[i + 1])
            lengths.append(dt)
            rough.append(True)
        acc.append(a_rec[i])
        bridged.append(False)
    a = np.array(acc)
    h = np.array(lengths)
    t = np.concatenate([[chain.t[0]], ends])
    gone = np.flatnonzero(np.isnan(a[:, 0]))
    have = np.flatnonzero(~np.isnan(a[:, 0]))
    mid = t[1:] - 0.5 * h
    for g in gone:
        before, after = have[have < g][-2:], have[have > g][:2]
        idx = np.concatenate([before, after])
        if len(before) == 2 and len(after) == 2:
            a[g] = lagrange_at(mid[idx], a[idx], float(mid[g]))
        else:
            a[g] = np.mean(a[idx], axis=0)
    v = np.vstack([np.zeros((1, 3)), np.cumsum(a * h[:, None], axis=0)])
    m = len(a)
    step = 0.5 * (v[:-1] + v[1:]) * h[:, None]  # trapezoid
    todo = np.ones(m, dtype=bool)
    even = ~np.array(rough) & (np.abs(h - win) <= 0.01 * win)
    # the cubic through four velocities around window i: centred, then one-sided at the ends
    for first, weights in ((-1, _CENTRED), (0, _FORWARD), (-2, _BACKWARD)):
        i = np.flatnonzero(todo & even)
        i = i[(i + first >= 0) & (i + first + 3 <= m)]
        if len(i):
            i = i[np.all([even[i + first + d] for d in range(3)], axis=0)]
        if len(i):
            step[i] = sum(w * v[i + first + d] for d, w in enumerate(weights)) * h[i, None]
            todo[i] = False
    p = np.vstack([np.zeros((1, 3)), np.cumsum(step, axis=0)])
    return PositionChain(t, p, v, np.array(rough) | (todo & ~even), np.array(bridged))


#: Integration weights of the cubic through four equally spaced values over one interval:
#: the interval between the middle two, the first two, the last two.
_CENTRED = np.array([-1.0, 13.0, 13.0, -1.0]) / 24.0
_FORWARD = np.array([9.0, 19.0, -5.0, 1.0]) / 24.0
_BACKWARD = np.array([1.0, -5.0, 19.0, 9.0]) / 24.0


def _hermite_at(t_pts: F64, p: F64, v: F64, t: F64) -> F64:
    """(k, 3) the cubic Hermite interpolant of positions ``p`` and velocities ``v``
    (m, 3) at increasing ``t_pts`` (m,), at times ``t`` (k,), held at the ends' velocity
    beyond them. With the velocities, a 4 mm bounce at 1.3 Hz is interpolated to 5 um
    between points 0.1 s apart, where a cubic through four positions was 40 um off."""
    m = len(t_pts)
    i = np.clip(np.searchsorted(t_pts, t, side="right") - 1, 0, m - 2)
    h = t_pts[i + 1] - t_pts[i]
    f = np.clip((t - t_pts[i]) / h, 0.0, 1.0)[:, None]
    h00 = 2 * f**3 - 3 * f**2 + 1
    h10 = f**3 - 2 * f**2 + f
    h01 = -2 * f**3 + 3 * f**2
    h11 = f**3 - f**2
    hh = h[:, None]
    out = h00 * p[i] + h10 * hh * v[i] + h01 * p[i + 1] + h11 * hh * v[i + 1]
    before, after = t < t_pts[0], t > t_pts[-1]
    out[before] = p[0] + v[0] * (t[before] - t_pts[0])[:, None]
    out[after] = p[-1] + v[-1] * (t[after] - t_pts[-1])[:, None]
    return out


def accel_differences(
    chain: GyroChain,
    t_rec: F64,
    acc_ins: F64,
    t_lidar: F64,
    offset_s: float,
    stencil: F64,
) -> AccelDifferences:
    """The accelerometers' differences of the positions at the lidar times (see the
    module docstring). chain : the gyros' chain over the same records (stamps ``t_rec``
    (m,)); acc_ins : (m, 3) accelerations (m/s^2, INS axes); t_lidar : (n,) lidar times;
    offset_s : the record clock's offset (the gyros', :func:`.gyro.time_offset`);
    stencil : (n-q, q+1) the difference weights at the lidar times (q >= 2: second
    differences see the accelerometers' bias, third ones do not)."""
    t_lidar = np.asarray(t_lidar, dtype=np.float64)
    n = len(t_lidar)
    q = stencil.shape[1] - 1
    if n <= q or len(chain.t) != len(t_rec) + 1:
        rows = max(n - q, 0)
        return AccelDifferences(np.zeros((rows, 3)), np.zeros(rows, dtype=bool), np.zeros(rows))
    pc = position_chain(chain, acc_ins)
    tq = t_lidar + offset_s
    P = _hermite_at(pc.t, pc.p, pc.v, tq)
    R, _, _ = rotations_at(chain, tq)
    d_chain = sum(stencil[:, i : i + 1] * P[i : n - q + i] for i in range(q + 1))
    value = np.einsum("nji,nj->ni", R[1 : n - q + 1], d_chain)
    # the stencil's times inside the records (interpolated, not extrapolated)
    inside = (tq > pc.t[0]) & (tq < pc.t[-1])
    ok = inside[: n - q] & inside[q:]
    # the windows between the chain points around the stencil's first and last times:
    # none of irregular length; bridged ones counted
    idx = np.clip(np.searchsorted(pc.t, tq, side="right") - 1, 0, len(pc.t) - 2)
    rough = np.concatenate([[0], np.cumsum(pc.rough)])
    bridged = np.concatenate([[0], np.cumsum(pc.bridged)])
    ok &= rough[idx[q:] + 1] - rough[idx[: n - q]] == 0
    n_bridged = (bridged[idx[q:] + 1] - bridged[idx[: n - q]]).astype(np.float64)
    return AccelDifferences(value, ok, n_bridged)


def accel_block(
    inp: LocalizationInput,
    chain: GyroChain | None,
    offset_s: float,
    imu_rate_hz: float,
    stencil: F64,
    sigma_m: tuple[float, float, float],
    health: Health,
) -> dict | None:
    """``fused``'s accelerometer block: meas (n-q, 3) the differences of the base
    positions the accelerometers see over the stencil's rows (base axes of each
    stencil's second frame, m) and w (n-q, 3) 1/sigma (0 where a record is missing);
    None without records."""
    got = read_accelerations(inp, imu_rate_hz)
    if got is None or chain is None:
        health.metrics["fused_accel_rows"] = 0.0
        return None
    t_rec, acc = got
    if len(t_rec) + 1 != len(chain.t) or not np.allclose(t_rec, chain.t[1:]):
        health.warn("fused: accelerometer records do not match the gyro records; unused")
        return None
    if not np.any(np.abs(acc) > 0):
        health.metrics["fused_accel_rows"] = 0.0
        return None
    got = accel_differences(chain, t_rec, acc, inp.times, offset_s, stencil)
    sigma = np.asarray(sigma_m)[None, :] * (1.0 + BRIDGE_SIGMA_FACTOR * got.bridged[:, None])
    w = np.where(got.ok[:, None], 1.0 / sigma, 0.0)
    health.metrics["fused_accel_rows"] = float(np.sum(got.ok))
    return {"meas": got.value, "w": w}
