"""The INS's gyros (``novatel_oem7_corrimu``) as frame-to-frame rotations of the base.

The INS solution's attitude (``inspva``) carries its filter's white noise and wander
(hundredths of a degree a record, tenths over seconds); the corrected IMU increments
behind it are the gyros themselves: per record, the rotation of the INS body about its
X / Y / Z axes per IMU sample, averaged over the logging window before the record
(NovAtel's CORRIMU). Summed record after record they give the body's rotation between
any two records with the gyros' own noise, a few thousandths of a degree over a frame for
a tactical-grade IMU, against the 4-10 mdeg of KISS-ICP's steps or the INS attitude's.
That is what a placed object's frame-to-frame stability needs: 1 mdeg of heading is
0.13 px on rgb_highres_center.

Four things are not in the files and are handled here:

- the IMU rate (rad/sample -> rad/s): the option ``imu_rate_hz`` (default
  :data:`DEFAULT_IMU_RATE_HZ`), checked against the reference below (a gain fitted with
  the offset; taken, with a warning, when it is plainly not 1);
- the time of the increments against the lidar's clock: the INS stamps its records late by
  its latency (tens of ms); the offset is found by matching the gyros' roll and pitch
  steps to the ground's (:func:`time_offset`; the ground pairs of
  :mod:`.ground_pairs`, good to a few mdeg a frame, KISS-ICP's steps where there is no
  ground: theirs lag the truth and pulled the offset 20-70 ms early): the body's pitch and
  roll sway change by several mdeg a frame, so 50 ms of offset is several mdeg of error;
- records that are missing (dropouts): the gap's rotation is the neighbouring rates'
  mean over it, and the steps across it are down-weighted;
- the INS's boresight: rotation vectors in the INS frame (X right, Y forward, Z up) map to
  the base frame (x forward, y left, z up) through the nominal mounting
  (:data:`geometry.poses.R_INS_BASE_NOMINAL`), and a boresight of tenths of a degree tilts
  each step's axis by that much: negligible for the sway, but in a tight curve it puts
  1 mdeg a frame of the yaw into roll and pitch; the tilt is fitted where a curve shows
  it (:func:`fit_alignment`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from geometry.poses import R_INS_BASE_NOMINAL
from worker.osdar.sequence import CORRIMU_DIR
from worker.preparation.localization.base import Health, LocalizationInput

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

#: IMU samples per second when the option ``imu_rate_hz`` does not say (NovAtel's
#: CORRIMU gives rotation per IMU sample; the synthetic INS simulates a 100 Hz IMU).
DEFAULT_IMU_RATE_HZ = 100.0
#: Candidate offsets (s) of the INS record clock against the lidar's: the record stamped
#: t holds the window ending at t - offset.
OFFSET_GRID_S = np.arange(-0.05, 0.2001, 0.0025)
#: Fewest usable reference pairs to estimate the offset from (else 0 and a warning).
MIN_OFFSET_PAIRS = 5
#: Share of a window by which a record interval must exceed the window to count as a gap
#: (stamps jitter by microseconds).
GAP_MIN = 0.05

#: The interpolation's standard error per unit of f (1 - f) x window x the third
#: difference of the windows' rates (:func:`rotations_at`).
BEND_SD_FACTOR = 0.5
#: A third difference of the rates counts as a bend beyond this many times its robust
#: level (1.4826 x its median over the sequence).
BEND_LEVELS = 3.0
#: Fewest frames between a reference pair's two frames for the alignment fit
#: (:func:`fit_alignment`).
ALIGN_MIN_LAG = 5
#: The alignment is taken when its tilt is this many standard errors from zero (the root
#: of the sum of both components' squared ratios) ...
ALIGN_SIGNIFICANCE = 3.0
#: ... and smaller than this (rad): a boresight, not a gyro mounted another way.
ALIGN_MAX_TILT = np.radians(2.0)
#: Bounds of the gyros' fitted gain (an IMU rate off by more than 4x is not a rate error).
GAIN_BOUNDS = (0.25, 4.0)
#: The gain is taken (the rates rescaled, with a warning) when it differs from 1 by more
#: than this share and by three standard errors: a CORRIMU from an IMU of another rate than
#: ``imu_rate_hz`` (100, 125, 200 Hz are common: 20 % apart or more) scales every rotation
#: by their ratio. At 5 % the ground pairs' own attenuation of the sway (a synthetic
#: sequence's gain came out 0.94 at 100 Hz) rescaled good gyros.
GAIN_TOLERANCE = 0.15
#: A step across a missing record counts this much less (sigma factor per missing window).
GAP_SIGMA_FACTOR = 3.0


@dataclass(frozen=True)
class GyroSteps:
    """The gyros' rotation of the base between consecutive frames.

    D : (n-1, 3, 3) R_base(k)^T R_base(k+1)
    ok : (n-1,) the step lies within the records
    gap : (n-1,) missing record windows within the step (0 for most)
    sd_interp : (n-1, 3) the interpolation's standard error per base axis (rad)
    offset_s : the record clock's offset against the lidar's (s)
    imu_rate_hz : samples per second used to turn rad/sample into rad/s
    chain : the records' chain the steps were read from (for the accelerometers)
    """

    D: F64
    ok: NDArray[np.bool_]
    gap: F64
    sd_interp: F64
    offset_s: float
    imu_rate_hz: float
    chain: GyroChain | None = None


@dataclass(frozen=True)
class GyroChain:
    """The body's rotation at the record windows' ends, relative to the first.

    t : (m,) times (record clock, s), increasing
    R : (m, 3, 3) R_base(t_0)^T R_base(t_i)
    gap : (m,) missing windows between point i-1 and i (0 for the first)
    rates : (m, 3) the rate (rad/s, base axes) of the window ending at each point (the
        first point's: the first record's); beyond its ends the chain goes on at the end
        records' rates for up to ``window`` s
    window : the records' window (s)
    """

    t: F64
    R: F64
    gap: F64
    rates: F64
    window: float


def gyro_chain(
    times: F64,
    rates_ins: F64,
    window_s: float | None = None,
    R_align: F64 | None = None,
) -> GyroChain:
    """Sum the records' increments into the body's rotation over time.

    times : (m,) record stamps (s), increasing; rates_ins : (m, 3) angular rate (rad/s)
    about INS X, Y, Z averaged over the ``window_s`` before each stamp (default the
    median record interval); R_align : (3, 3) the INS axes' small rotation against the
    base beyond the nominal mounting (:func:`fit_alignment`; None: none). Returns the
    chain at ``times[0] - window_s`` and at every record (m + 1 points), in base axes.
    """
    times = np.asarray(times, dtype=np.float64)
    w_base = np.asarray(rates_ins, dtype=np.float64) @ R_INS_BASE_NOMINAL  # R^T.T: ins->base
    if R_align is not None:
        w_base = w_base @ np.asarray(R_align, dtype=np.float64).T
    m = len(times)
    if m < 2:
        raise ValueError("the gyro chain needs two records or more")
    dt = np.diff(times)
    window = float(np.median(dt)) if window_s is None else float(window_s)
    t = np.concatenate([[times[0] - window], times])
    R = np.empty((m + 1, 3, 3))
    R[0] = np.eye(3)
    R[1] = Rotation.from_rotvec(w_base[0] * window).as_matrix()
    gap = np.zeros(m + 1)
    for i in range(1, m):
        covered = min(dt[i - 1], window)
        rest = max(dt[i - 1] - window, 0.0)
        # the uncovered part of a longer interval (a missing record) at the mean rate
        phi = w_base[i] * covered + 0.5 * (w_base[i - 1] + w_base[i]) * rest
        R[i + 1] = R[i] @ Rotation.from_rotvec(phi).as_matrix()
        gap[i + 1] = rest / window if rest > GAP_MIN * window else 0.0
    return GyroChain(t, R, gap, np.vstack([w_base[:1], w_base]), window)


def rotations_at(chain: GyroChain, t: F64) -> tuple[F64, NDArray[np.bool_], F64]:
    """The chain's rotation at times ``t`` (record clock): (k, 3, 3), (k,) which lie in
    its span (its ends extended by one window at the end records' rates), and (k, 3) the
    interpolation's standard error per base axis (rad).

    Between points i and i + 1 the rotation is a cubic through points i - 1 to i + 2 in
    the rotation vectors relative to point i (small angles: no wrap, no non-commutativity
    of a rotation vector of the whole sequence): 0.2 mdeg on a coach's sway, where holding
    each window's average rate was 2.6. Where the rate bends sharply (a cant ramp starting:
    the roll rate steps by 0.8 deg/s) the cubic is 15-20 mdeg off on the two frames
    around it; the third difference of the windows' rates shows such a bend, beyond
    :data:`BEND_LEVELS` times its robust level over the sequence (the gyros' noise and a
    sway's smooth bends, which the cubic follows), and half of that excess times
    f (1 - f) times the window is the standard error given (f: the time's fraction of
    its window).
    """
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    ok = (t >= chain.t[0] - chain.window) & (t <= chain.t[-1] + chain.window)
    out = np.tile(np.eye(3), (len(t), 1, 1))
    sd = np.zeros((len(t), 3))
    m = len(chain.t)
    d3 = np.abs(np.diff(chain.rates, n=3, axis=0)) if m >= 4 else np.zeros((1, 3))
    # the third differences' own level (the gyros' noise, a smooth sway) is not a bend
    d3 = np.maximum(d3 - BEND_LEVELS * 1.4826 * np.median(d3, axis=0), 0.0)
    i_all = np.clip(np.searchsorted(chain.t, t, side="right") - 1, 0, m - 2)
    inner = ok & (t >= chain.t[0]) & (t <= chain.t[-1]) & (i_all >= 1) & (i_all + 2 <= m - 1)
    if np.any(inner):  # four neighbours: all at once (the loop below does the rest)
        q = np.flatnonzero(inner)
        i = i_all[q]
        idx = i[:, None] + np.arange(-1, 3)[None, :]  # (Q, 4)
        rel = np.swapaxes(chain.R[i], 1, 2)[:, None] @ chain.R[idx]  # (Q, 4, 3, 3)
        phi = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec().reshape(-1, 4, 3)
        x = chain.t[idx]
        basis = np.ones((len(q), 4))
        for a in range(4):
            for b in range(4):
                if a != b:
                    basis[:, a] *= (t[q] - x[:, b]) / (x[:, a] - x[:, b])
        phi_t = np.einsum("qa,qac->qc", basis, phi)
        out[q] = chain.R[i] @ Rotation.from_rotvec(phi_t).as_matrix()
        span = chain.t[i + 1] - chain.t[i]
        f = (t[q] - chain.t[i]) / span
        lo = np.clip(i - 2, 0, len(d3) - 1)
        win = np.clip(lo[:, None] + np.arange(4)[None, :], 0, len(d3) - 1)
        win = np.where(win < np.minimum(i + 2, len(d3))[:, None], win, lo[:, None])
        bend = np.max(d3[win], axis=1)
        sd[q] = BEND_SD_FACTOR * (f * (1.0 - f) * span)[:, None] * bend
    for q in np.flatnonzero(ok & ~inner):
        if t[q] < chain.t[0] or t[q] > chain.t[-1]:  # beyond the ends: at the end's rate
            end = 0 if t[q] < chain.t[0] else -1
            step = chain.rates[end] * (t[q] - chain.t[end])
            out[q] = chain.R[end] @ Rotation.from_rotvec(step).as_matrix()
            change = np.abs(chain.rates[end] - chain.rates[1 if end == 0 else -2])
            sd[q] = change * abs(t[q] - chain.t[end])
            continue
        i = int(np.clip(np.searchsorted(chain.t, t[q], side="right") - 1, 0, m - 2))
        idx = np.arange(max(i - 1, 0), min(i + 3, m))
        phi = Rotation.from_matrix(chain.R[i].T @ chain.R[idx]).as_rotvec()  # (len(idx), 3)
        out[q] = (
            chain.R[i]
            @ Rotation.from_rotvec(lagrange_at(chain.t[idx], phi, float(t[q]))).as_matrix()
        )
        span = chain.t[i + 1] - chain.t[i]
        f = (t[q] - chain.t[i]) / span
        bend = np.max(d3[max(i - 2, 0) : min(i + 2, len(d3))], axis=0)
        sd[q] = BEND_SD_FACTOR * f * (1.0 - f) * span * bend
    return out, ok, sd


def lagrange_at(x: F64, y: F64, at: float) -> F64:
    """The polynomial through points (x, y) (y: (p, 3)) evaluated at ``at``."""
    out = np.zeros(y.shape[1])
    for a in range(len(x)):
        basis = 1.0
        for b in range(len(x)):
            if b != a:
                basis *= (at - x[b]) / (x[a] - x[b])
        out += basis * y[a]
    return out


def steps_at(
    chain: GyroChain, t_lidar: F64, offset_s: float
) -> tuple[F64, NDArray[np.bool_], F64, F64]:
    """The chain's rotation between consecutive lidar times shifted by ``offset_s``:
    D (n-1, 3, 3), ok (n-1,), the missing windows within each step (n-1,) and the
    interpolation's standard error of each step per base axis (n-1, 3) (rad)."""
    tq = np.asarray(t_lidar, dtype=np.float64) + offset_s
    R, inside, sd = rotations_at(chain, tq)
    D = np.swapaxes(R[:-1], 1, 2) @ R[1:]
    ok = inside[:-1] & inside[1:]
    cum = np.cumsum(chain.gap)
    idx = np.clip(np.searchsorted(chain.t, tq, side="right") - 1, 0, len(chain.t) - 1)
    # the gaps of the chain points passed between the two frames (and of the next one)
    nxt = np.clip(idx + 1, 0, len(chain.t) - 1)
    gap = cum[nxt[1:]] - cum[idx[:-1]]
    # beyond the chain's ends the rate is held: counted as that share of a missing window
    outside = np.maximum(chain.t[0] - tq, 0.0) + np.maximum(tq - chain.t[-1], 0.0)
    gap = gap + (outside[:-1] + outside[1:]) / chain.window
    return D, ok, gap, np.hypot(sd[:-1], sd[1:])


@dataclass(frozen=True)
class ClockFit:
    """The gyros against a reference (:func:`time_offset`): the record clock's offset (s)
    and its standard error (inf: no minimum inside the grid), the gain on the gyros'
    rotations that fits best there (1: the IMU rate is right) and its standard error, and
    the reference pairs used."""

    offset_s: float
    offset_se_s: float
    gain: float
    gain_se: float
    pairs: int


def time_offset(
    chain: GyroChain,
    t_lidar: F64,
    k: NDArray[np.int64],
    j: NDArray[np.int64],
    R_ref: F64,
    w_ref: F64,
) -> ClockFit:
    """The record clock's offset against the lidar's that best matches the gyros'
    rotation between frames ``k`` and ``j`` (Q,) to reference rotations ``R_ref``
    (Q, 3, 3) (R_k^T R_j) weighted per base axis by ``w_ref`` (Q, 3) (1/sigma; 0: that
    axis does not count), with the gyros' rotations scaled by the gain that fits best at
    each offset (small angles: rotation vectors compared). Misfit: the weighted squared
    differences, each term capped at 3 sigma (a failed registration does not decide)."""
    use = np.any(w_ref > 0, axis=1)
    n_use = int(np.sum(use))
    none = ClockFit(0.0, np.inf, 1.0, np.inf, n_use)
    if n_use < MIN_OFFSET_PAIRS:
        return none
    k, j, w_ref = k[use], j[use], w_ref[use]
    rho = Rotation.from_matrix(R_ref[use]).as_rotvec()
    cost = np.full(len(OFFSET_GRID_S), np.inf)
    gains = np.ones(len(OFFSET_GRID_S))
    gain_se = np.full(len(OFFSET_GRID_S), np.inf)
    for q, c in enumerate(OFFSET_GRID_S):
        R, inside, _ = rotations_at(chain, np.asarray(t_lidar, dtype=np.float64) + float(c))
        sel = inside[k] & inside[j]
        if np.sum(sel) < max(MIN_OFFSET_PAIRS, 0.8 * n_use):
            continue
        phi = Rotation.from_matrix(np.swapaxes(R[k[sel]], 1, 2) @ R[j[sel]]).as_rotvec()
        w2 = w_ref[sel] ** 2
        den = float(np.sum(w2 * phi**2))
        if den > 0:
            gains[q] = float(np.clip(np.sum(w2 * rho[sel] * phi) / den, *GAIN_BOUNDS))
            gain_se[q] = 1.0 / np.sqrt(den)
        e = rho[sel] - gains[q] * phi
        z2 = np.minimum((e * w_ref[sel]) ** 2, 9.0)
        cost[q] = float(np.sum(z2)) / float(np.sum(sel))
    if not np.any(np.isfinite(cost)):
        return none
    q = int(np.argmin(cost))
    best, se = float(OFFSET_GRID_S[q]), np.inf
    if 0 < q < len(cost) - 1 and np.all(np.isfinite(cost[q - 1 : q + 2])):
        a, b, c = cost[q - 1 : q + 2]
        h = float(OFFSET_GRID_S[1] - OFFSET_GRID_S[0])
        curv = (a - 2 * b + c) / h**2
        if curv > 0:
            best += 0.5 * h * (a - c) / (a - 2 * b + c)
            # the misfit is a mean of chi-square terms: curvature x pairs / 2 = information
            se = float(np.sqrt(2.0 / (curv * n_use)))
    return ClockFit(best, se, float(gains[q]), float(gain_se[q]), n_use)


def fit_alignment(
    chain: GyroChain,
    t_lidar: F64,
    offset_s: float,
    k: NDArray[np.int64],
    j: NDArray[np.int64],
    R_ref: F64,
    w_ref: F64,
) -> tuple[F64, F64] | None:
    """The small rotation ``a`` (3,) (rad, base axes) that turns the gyros' rotation
    vectors onto the reference's (``rho ~ phi + a x phi``, weighted by ``w_ref``, pairs at
    least :data:`ALIGN_MIN_LAG` frames apart), and its standard errors (3,); None when
    too few pairs.

    The INS is mounted with a boresight of tenths of a degree that the nominal mounting
    leaves out: in a tight curve (200 mdeg of yaw a frame) 0.3 deg of tilt puts 1 mdeg a
    frame of the yaw into roll or pitch, which the chain adds up (tight_curve, 100 frames:
    -0.94 mdeg of pitch a frame against the truth). The ground pairs' roll and pitch see
    the tilt as that leak, growing with the yaw; pairs over several frames, because a
    lag-1 ground pair carries a bias of its own of the same size."""
    use = np.any(w_ref > 0, axis=1) & ((j - k) >= ALIGN_MIN_LAG)
    if int(np.sum(use)) < MIN_OFFSET_PAIRS:
        return None
    k, j, w = k[use], j[use], w_ref[use]
    R, inside, _ = rotations_at(chain, np.asarray(t_lidar, dtype=np.float64) + offset_s)
    sel = inside[k] & inside[j]
    if int(np.sum(sel)) < MIN_OFFSET_PAIRS:
        return None
    phi = Rotation.from_matrix(np.swapaxes(R[k[sel]], 1, 2) @ R[j[sel]]).as_rotvec()
    rho = Rotation.from_matrix(R_ref[use][sel]).as_rotvec()
    w, lag = w[sel], (j - k)[sel]
    # the tilt only (a_z stays 0): (a x phi)_x = a_y phi_z, (a x phi)_y = -a_x phi_z on
    # the rows the reference weighs (roll, pitch)
    A = np.zeros((len(phi), 2, 2))
    A[:, 0, 1], A[:, 1, 0] = phi[:, 2], -phi[:, 2]
    Aw = (A * w[:, :2, None]).reshape(-1, 2)
    bw = ((rho - phi)[:, :2] * w[:, :2]).reshape(-1)
    N = Aw.T @ Aw
    if np.linalg.cond(N) > 1e12:
        return None
    cov = np.linalg.inv(N)
    x = cov @ (Aw.T @ bw)
    # pairs a lag apart share most of their frames (one independent pair per lag), and the
    # residuals' own scatter scales the formal errors
    dof = max(len(bw) - 2, 1)
    chi2 = float(np.sum((bw - Aw @ x) ** 2)) / dof
    se = np.sqrt(np.diag(cov) * max(chi2, 1.0) * float(np.mean(lag)))
    return np.array([x[0], x[1], 0.0]), np.array([se[0], se[1], np.inf])


def read_corrimu(
    inp: LocalizationInput, fields: tuple[str, str, str], per_second: float
) -> tuple[F64, F64] | None:
    """(m,) record stamps and (m, 3) columns ``fields`` of the sequence's
    ``novatel_oem7_corrimu`` times ``per_second`` (per IMU sample -> per second), sorted,
    one record per stamp, records with a non-finite value left out; None when it has none
    (or fewer than two records)."""
    ci = inp.options.get("_corrimu")  # read once for the gyros and the accelerometers
    if ci is None:
        try:
            ci = inp.sequence.corr_imu()
        except (FileNotFoundError, ValueError, KeyError) as exc:
            log.info("no IMU records: %s", exc)
            return None
        inp.options["_corrimu"] = ci
    t = np.asarray(ci.timestamp, dtype=np.float64)
    vals = np.column_stack([getattr(ci, f) for f in fields]).astype(np.float64)
    keep = np.isfinite(t) & np.all(np.isfinite(vals), axis=1)
    t, vals = t[keep], vals[keep] * per_second
    if len(t) < 2:
        return None
    order = np.argsort(t, kind="stable")
    t, vals = t[order], vals[order]
    uniq = np.concatenate([[True], np.diff(t) > 0])
    t, vals = t[uniq], vals[uniq]
    if len(t) < 2:
        return None
    return t, vals


def read_rates(inp: LocalizationInput, imu_rate_hz: float) -> tuple[F64, F64] | None:
    """(m,) record stamps and (m, 3) rates (rad/s about INS X, Y, Z) of the sequence's
    ``novatel_oem7_corrimu``, None when it has none (or fewer than two records)."""
    return read_corrimu(inp, ("pitch_rate", "roll_rate", "yaw_rate"), imu_rate_hz)


def gyro_steps(
    inp: LocalizationInput,
    ref: tuple[NDArray[np.int64], NDArray[np.int64], F64, F64],
    health: Health,
) -> GyroSteps | None:
    """The gyros' frame-to-frame base rotations at the lidar times (see the module
    docstring), the record clock's offset found against the reference ``ref`` = (k, j,
    R_k_j, w) of :func:`time_offset`. None when the sequence has no gyro records."""
    rate_hz = float(inp.options.get("imu_rate_hz", DEFAULT_IMU_RATE_HZ))
    got = read_rates(inp, rate_hz)
    if got is None:
        health.metrics["fused_gyro_steps"] = 0.0
        folder = getattr(inp.sequence, "folder", None)
        if folder is not None and (folder / CORRIMU_DIR).is_dir():
            health.warn(
                f"fused: {CORRIMU_DIR} holds no readable gyro records (fewer than two "
                "rows with finite timestamps and rates); running without the gyros"
            )
        return None
    t_rec, rates = got
    chain = gyro_chain(t_rec, rates)
    t_lidar = np.asarray(inp.times, dtype=np.float64)
    fixed = inp.options.get("gyro_offset_s")
    if fixed is not None:
        offset, se = float(fixed), 0.0
    else:
        fit = time_offset(chain, t_lidar, *ref)
        offset, se = fit.offset_s, fit.offset_se_s
        if not np.isfinite(se):
            health.warn(
                f"fused: gyro clock offset not measurable ({fit.pairs} usable reference "
                "pairs); taken as 0 s"
            )
            offset = 0.0
        elif abs(fit.gain - 1.0) > max(GAIN_TOLERANCE, 3.0 * fit.gain_se):
            rate_hz *= fit.gain
            health.warn(
                f"fused: the gyros' rotations fit the reference's at {fit.gain:.2f}x: the "
                f"CORRIMU's IMU rate looks like {rate_hz:.0f} Hz; rescaled (set the "
                "option imu_rate_hz if it is known)"
            )
            rates = rates * fit.gain
            chain = gyro_chain(t_rec, rates)
        health.metrics["fused_gyro_gain"] = fit.gain
    got_a = fit_alignment(chain, t_lidar, offset, *ref)
    if got_a is not None:
        a, a_se = got_a
        z2 = float(np.sum((a[:2] / a_se[:2]) ** 2))
        tilt = float(np.linalg.norm(a[:2]))
        if z2 > ALIGN_SIGNIFICANCE**2 and tilt < ALIGN_MAX_TILT:
            chain = gyro_chain(t_rec, rates, R_align=Rotation.from_rotvec(a).as_matrix())
            health.metrics["fused_gyro_tilt_deg"] = float(np.degrees(tilt))
    D, ok, gap, sd = steps_at(chain, t_lidar, offset)
    health.metrics["fused_gyro_offset_ms"] = 1000.0 * offset
    health.metrics["fused_gyro_offset_se_ms"] = 1000.0 * se if np.isfinite(se) else -1.0
    health.metrics["fused_gyro_steps"] = float(np.sum(ok))
    health.metrics["fused_gyro_imu_rate_hz"] = rate_hz
    return GyroSteps(D, ok, gap, sd, offset, rate_hz, chain)
