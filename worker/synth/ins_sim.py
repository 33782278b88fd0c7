"""Synthetic NovAtel INS: INSPVA, INSSTDEV and CORRIMU tables from a true trajectory.

Input: the true pose of the base frame (merged lidar: x forward, y left, z up) over time, in
the *true* world frame (ENU around ``true_world``, Hamburg by default), the frame timestamps
and counters, and an :class:`InsErrorModel`. Output: the three tables the sequence's CSVs
are written from, the true INS-to-lidar transform (for ``ground_truth/``) and the world
frame the pipeline will use.

Model, per frame k with stamp t_k (all errors are deterministic from ``model.seed``):

1. true time ``t_k - latency_s`` (the record is stamped late by the latency, the
   convention of :class:`geometry.poses.InsToLidar`);
2. true INS pose ``T_world_ins = T_world_base(t) @ T_base_ins``, with the TRUE misalignment
   ``T_base_ins = make_T(R_bore @ R_base_ins_nominal, lever_arm)`` (see
   :meth:`InsErrorModel.T_base_ins`). With the nominal assumption the pipeline therefore sees
   the base pose ``T_world_base @ make_T(R_bore, lever_arm)``;
3. position error in the local ENU frame at that point: random walk + white noise + GNSS
   jumps (steps, optionally decaying), converted to WGS84 lat / lon / ellipsoidal height;
4. attitude = true INS orientation in the local tangent frame at the reported position,
   converted to NovAtel roll / pitch / azimuth, plus random walk + white noise (deg);
5. velocity = central difference of the true INS position (local ENU) + white noise;
6. INSSTDEV: cm-level position sigmas (larger for a few seconds after a jump), small
   velocity and attitude sigmas, with a 10 % random fluctuation;
7. CORRIMU: increments *per IMU sample* assuming a 100 Hz IMU (``IMU_RATE_HZ``), averaged
   over the ``CORRIMU_WINDOW_S`` before the record's true time: pitch_rate / roll_rate /
   yaw_rate = body-frame rotation about INS X / Y / Z per sample (rad/sample),
   lateral / longitudinal / vertical_acc = kinematic acceleration (gravity removed, as in
   NovAtel's corrected IMU) along INS X / Y / Z per sample (m/s/sample). The gyros have
   a constant bias per axis and angle random walk (``gyro_bias_deg_h``,
   ``gyro_noise_deg_rt_h``: a tactical-grade IMU in "paper", 2 deg/h and 0.15 deg/sqrt(h));
   the accelerometers a constant bias per axis and velocity random walk
   (``accel_bias_mg``, ``accel_noise_mps_rt_h``: 1 mg and 0.05 m/s/sqrt(h) in "paper");
8. dropouts remove whole frames from all three tables.

The world frame written to ``ground_truth/world.json`` is, by the project's definition, the
FIRST INS record's reported position (:func:`worker.osdar.ins_poses.world_frame_from_ins`); use
:func:`reexpress` to express the true poses in it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator
from scipy.spatial.transform import Rotation

from geometry.geodesy import WorldFrame
from geometry.poses import (
    R_INS_BASE_NOMINAL,
    InsToLidar,
    PoseTrack,
    novatel_attitude_from_R,
    reexpress,
)
from geometry.transforms import invert_T, make_T
from worker.osdar.ins_poses import world_frame_from_ins
from worker.osdar.ins_tables import CorrImu, InsPva, InsStdDev

F64 = NDArray[np.float64]

logger = logging.getLogger(__name__)

__all__ = [
    "CORRIMU_WINDOW_S",
    "HAMBURG",
    "IMU_RATE_HZ",
    "InsErrorModel",
    "SimulatedIns",
    "reexpress",
    "simulate_ins",
    "unix_to_gps_week",
]

#: Default true world origin of synthetic sequences (Hamburg, ellipsoidal height).
HAMBURG = WorldFrame(53.5511, 9.9937, 40.0)

#: Assumed IMU sample rate behind the CORRIMU increments (per-sample units).
IMU_RATE_HZ = 100.0
#: CORRIMU rows average the motion over this window before the record's time (one frame).
CORRIMU_WINDOW_S = 0.1

_VELOCITY_STEP_S = 1.0 / IMU_RATE_HZ  # central-difference step for velocities
_JUMP_STDEV_GAIN = 10.0  # position sigma right after a jump, in multiples of the baseline
_JUMP_STDEV_DECAY_S = 3.0
_GPS_EPOCH_UNIX = 315964800.0  # 1980-01-06T00:00:00Z
_GPS_MINUS_UTC_S = 18.0  # leap seconds since 2017-01-01 (OSDaR23 was recorded in 2021)
_SECONDS_PER_WEEK = 604800.0

Vec3 = tuple[float, float, float]


class InsErrorModel(BaseModel):
    """Errors of the synthetic INS, and its true mounting.

    Frames and units:

    - ``lever_arm_m``: position of the INS origin in the base frame (x forward, y left,
      z up), m;
    - ``boresight_deg``: (roll, pitch, yaw) of the INS mounting error, intrinsic rotations
      about base z (yaw), then y (pitch), then x (roll): ``R_bore`` = scipy
      ``from_euler("ZYX", [yaw, pitch, roll])``. The true ``R_base_ins = R_bore @
      R_base_ins_nominal``; a positive yaw makes the raw INS see the vehicle turned left,
      a positive pitch (about y left) nose down;
    - ``latency_s``: the record stamped t reports the true state at ``t - latency_s``;
    - position errors are in the local East, North, Up axes: random walk in m/sqrt(s) and
      white noise in m (one value per axis);
    - heading (azimuth) and attitude (roll and pitch) random walk in deg/sqrt(s) and white
      noise in deg;
    - slow drift (the GNSS/INS filter wandering over tens of seconds: large errors that
      change little from one frame to the next): ``position_drift_m`` (E, N, U),
      ``heading_drift_deg`` and ``attitude_drift_deg`` are standard deviations of smooth
      errors, each a sum of three sinusoids with periods ``drift_period_s`` x (0.6, 1, 1.7)
      and random phases;
    - ``jumps``: explicit GNSS jumps as (frame counter, (E, N, U) offset m) steps, plus random
      ones at ``jump_rate_hz`` with N(0, ``jump_magnitude_m``) horizontal components (half
      that vertically); ``jump_decay_s`` None keeps the step, else it decays exponentially;
    - dropouts: each frame independently missing with ``dropout_fraction``, plus the
      explicit ``dropout_frames`` (frame counters);
    - ``position_stdev_m``: the baseline INSSTDEV position sigmas (E/lon, N/lat, U);
    - the CORRIMU gyros: ``gyro_bias_deg_h`` the standard deviation of a constant bias per
      axis (deg/h), ``gyro_noise_deg_rt_h`` angle random walk (deg/sqrt(h));
    - the CORRIMU accelerometers: ``accel_bias_mg`` the standard deviation of a constant
      bias per axis (mg, 1 mg = 9.81 mm/s^2), ``accel_noise_mps_rt_h`` velocity random walk
      (m/s/sqrt(h));
    - ``seed``: everything random comes from ``numpy.random.default_rng`` streams spawned
      from it, one per error source (changing one magnitude does not reshuffle the others).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    lever_arm_m: Vec3 = (0.0, 0.0, 0.0)
    boresight_deg: Vec3 = (0.0, 0.0, 0.0)
    latency_s: float = 0.0
    position_random_walk_m: Vec3 = (0.0, 0.0, 0.0)
    position_noise_m: Vec3 = (0.0, 0.0, 0.0)
    heading_random_walk_deg: float = Field(0.0, ge=0.0)
    heading_noise_deg: float = Field(0.0, ge=0.0)
    attitude_random_walk_deg: float = Field(0.0, ge=0.0)
    attitude_noise_deg: float = Field(0.0, ge=0.0)
    velocity_noise_mps: float = Field(0.0, ge=0.0)
    jumps: list[tuple[int, Vec3]] = Field(default_factory=list)
    jump_rate_hz: float = Field(0.0, ge=0.0)
    jump_magnitude_m: float = Field(0.0, ge=0.0)
    jump_decay_s: float | None = Field(None, gt=0.0)
    position_drift_m: Vec3 = (0.0, 0.0, 0.0)
    heading_drift_deg: float = Field(0.0, ge=0.0)
    attitude_drift_deg: float = Field(0.0, ge=0.0)
    drift_period_s: float = Field(30.0, gt=0.0)
    dropout_fraction: float = Field(0.0, ge=0.0, lt=1.0)
    dropout_frames: list[int] = Field(default_factory=list)
    position_stdev_m: Vec3 = (0.02, 0.02, 0.04)
    gyro_noise_deg_rt_h: float = Field(0.0, ge=0.0)
    gyro_bias_deg_h: float = Field(0.0, ge=0.0)
    accel_noise_mps_rt_h: float = Field(0.0, ge=0.0)
    accel_bias_mg: float = Field(0.0, ge=0.0)
    seed: int = 0

    @field_validator(
        "position_random_walk_m", "position_noise_m", "position_stdev_m", "position_drift_m"
    )
    @classmethod
    def _non_negative(cls, v: Vec3) -> Vec3:
        if any(x < 0.0 for x in v):
            raise ValueError(f"must be non-negative, got {v}")
        return v

    # -- presets ----------------------------------------------------------------------------

    @classmethod
    def profile(cls, name: str = "paper", **overrides: Any) -> InsErrorModel:
        """Preset error models; keyword arguments override single fields.

        - ``"perfect"``: no error at all (the INS reports the truth, nominal mounting);
        - ``"good"``: a well calibrated system: cm lever arm, 0.05 deg boresight, 5 ms
          latency, cm noise;
        - ``"paper"``: raw-INS reprojection errors of the order of the OSDaR-AR paper (tens
          of px at f = 4609 px for landmarks 30-80 m ahead): lever arm tens of cm, boresight
          yaw 0.5 deg / pitch 0.3 deg, 20 ms latency, ~dm drift over seconds. Measured on
          a 10 m/s arc, 100 frames, seeds 0-2: 60-90 px mean raw-INS error on rgb_center
          and about 3 px frame-to-frame jitter (paper: 49-81 px, 1.2-3.1 px);
        - ``"hard"``: "paper" plus GNSS jumps, 50 ms latency and 5 % dropouts;
        - ``"osdar23"``: "paper" plus the slow drift of the real sequences' INS: the paper's
          raw-INS errors are large (31-89 px mean on rgb_highres_center, std as large) but
          change little per frame (jitter 1.2-5.9 px), so a smooth wander of decimetres and
          tenths of a degree over tens of seconds, not a faster random walk. The bench's
          synthetic counterparts of the paper's sequences use it.
        """
        presets: dict[str, dict[str, Any]] = {
            "perfect": {},
            "good": {
                "lever_arm_m": (0.03, -0.02, 0.02),
                "boresight_deg": (0.03, 0.04, 0.05),
                "latency_s": 0.005,
                "position_random_walk_m": (0.01, 0.01, 0.01),
                "position_noise_m": (0.005, 0.005, 0.008),
                "heading_random_walk_deg": 0.002,
                "heading_noise_deg": 0.005,
                "attitude_random_walk_deg": 0.001,
                "attitude_noise_deg": 0.003,
                "velocity_noise_mps": 0.005,
                "position_stdev_m": (0.01, 0.01, 0.02),
                "gyro_noise_deg_rt_h": 0.05,
                "gyro_bias_deg_h": 0.5,
                "accel_noise_mps_rt_h": 0.02,
                "accel_bias_mg": 0.1,
            },
            "paper": {
                "lever_arm_m": (0.40, 0.30, -0.15),
                "boresight_deg": (0.15, 0.30, 0.50),
                "latency_s": 0.020,
                "position_random_walk_m": (0.10, 0.10, 0.05),
                "position_noise_m": (0.015, 0.015, 0.02),
                "heading_random_walk_deg": 0.01,
                "heading_noise_deg": 0.01,
                "attitude_random_walk_deg": 0.005,
                "attitude_noise_deg": 0.01,
                "velocity_noise_mps": 0.02,
                "position_stdev_m": (0.02, 0.02, 0.04),
                "gyro_noise_deg_rt_h": 0.15,
                "gyro_bias_deg_h": 2.0,
                "accel_noise_mps_rt_h": 0.05,
                "accel_bias_mg": 1.0,
            },
        }
        presets["hard"] = {
            **presets["paper"],
            "latency_s": 0.050,
            "jump_rate_hz": 0.1,
            "jump_magnitude_m": 0.5,
            "jump_decay_s": 5.0,
            "dropout_fraction": 0.05,
            "position_stdev_m": (0.03, 0.03, 0.06),
            "gyro_noise_deg_rt_h": 0.3,
            "gyro_bias_deg_h": 5.0,
            "accel_noise_mps_rt_h": 0.15,
            "accel_bias_mg": 3.0,
        }
        presets["osdar23"] = {
            **presets["paper"],
            "position_drift_m": (0.5, 0.5, 0.15),
            "heading_drift_deg": 0.5,
            "attitude_drift_deg": 0.15,
            "drift_period_s": 10.0,
        }
        if name not in presets:
            raise ValueError(f"unknown INS error profile {name!r}; known: {sorted(presets)}")
        return cls(**{**presets[name], **overrides})

    # -- the true mounting ------------------------------------------------------------------

    @property
    def R_bore(self) -> F64:
        """(3, 3) boresight rotation in base axes (see the class docstring)."""
        roll, pitch, yaw = np.radians(np.asarray(self.boresight_deg, dtype=np.float64))
        return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()

    @property
    def T_base_ins(self) -> F64:
        """(4, 4) TRUE pose of the INS body frame in the base frame."""
        return make_T(self.R_bore @ R_INS_BASE_NOMINAL.T, self.lever_arm_m)

    def true_ins_to_lidar(self) -> InsToLidar:
        """The TRUE INS-to-lidar calibration (for ``ground_truth/``), latency included."""
        return InsToLidar.from_T(invert_T(self.T_base_ins), latency_s=self.latency_s)


@dataclass
class SimulatedIns:
    """Output of :func:`simulate_ins`.

    ``inspva``, ``insstdev``, ``corrimu``: one row per kept frame (same frames in all three);
    ``ins_to_lidar``: the TRUE calibration; ``world``: the world frame defined by the first
    INS record (what the pipeline and ``ground_truth/world.json`` use); ``dropped_frames``:
    frame counters without a row.
    """

    inspva: InsPva
    insstdev: InsStdDev
    corrimu: CorrImu
    ins_to_lidar: InsToLidar
    world: WorldFrame
    dropped_frames: NDArray[np.int64]


def unix_to_gps_week(t_unix: ArrayLike) -> tuple[NDArray[np.int64], F64]:
    """UNIX seconds (n,) -> GPS week number (n,) and milliseconds into the week (n,)."""
    gps = np.asarray(t_unix, dtype=np.float64) - _GPS_EPOCH_UNIX + _GPS_MINUS_UTC_S
    week = np.floor(gps / _SECONDS_PER_WEEK)
    ms = (gps - week * _SECONDS_PER_WEEK) * 1000.0
    return week.astype(np.int64), ms


def _pose_function(
    true_base: PoseTrack | Callable[[F64], F64],
) -> Callable[[F64], F64]:
    if isinstance(true_base, PoseTrack):
        # The simulation reads slightly outside the track (latency, differences): a generous
        # constant-velocity extrapolation is the right model of the truth there.
        return lambda t: true_base.interpolate(t, max_extrapolation_s=1.0)

    def f(t: F64) -> F64:
        T = np.asarray(true_base(t), dtype=np.float64)
        if T.shape != (len(t), 4, 4):
            raise ValueError(f"true pose function must return ({len(t)}, 4, 4), got {T.shape}")
        return T

    return f


def _random_walk(rng: np.random.Generator, dt: F64, sigma: F64) -> F64:
    """(n, k) random walk starting at 0: increments N(0, sigma^2 dt)."""
    steps = rng.standard_normal((len(dt), len(sigma))) * np.sqrt(dt)[:, None] * sigma
    steps[0] = 0.0
    return np.cumsum(steps, axis=0)


def _smooth_drift(rng: np.random.Generator, t: F64, sigma: F64, period: float) -> F64:
    """(n, k) smooth errors of standard deviation ``sigma`` (k,): per component a sum of
    three sinusoids with periods ``period`` x (0.6, 1, 1.7) and random phases."""
    out = np.zeros((len(t), len(sigma)))
    amp = np.asarray(sigma, dtype=np.float64) * np.sqrt(2.0 / 3.0)
    for factor in (0.6, 1.0, 1.7):
        phase = rng.uniform(0.0, 2.0 * np.pi, len(sigma))
        out += amp * np.sin(2.0 * np.pi * (t[:, None] - t[0]) / (period * factor) + phase)
    return out


@dataclass(frozen=True)
class _Streams:
    """The simulation's independent random streams (spawned from ``model.seed``)."""

    position_walk: np.random.Generator
    position_noise: np.random.Generator
    heading_walk: np.random.Generator
    heading_noise: np.random.Generator
    attitude_walk: np.random.Generator
    attitude_noise: np.random.Generator
    velocity: np.random.Generator
    jump: np.random.Generator
    misc: np.random.Generator  # stdev fluctuations, then dropouts
    drift: np.random.Generator
    gyro: np.random.Generator
    accel: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int) -> _Streams:
        # (spawned children are the same whatever their number: a new source goes last)
        return cls(*[np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(12)])


def _record_times(
    frame_timestamps: ArrayLike, frame_idx: ArrayLike
) -> tuple[F64, NDArray[np.int64]]:
    """(n,) stamps and (n,) frame counters, checked."""
    ts = np.asarray(frame_timestamps, dtype=np.float64).reshape(-1)
    fi = np.asarray(frame_idx, dtype=np.int64).reshape(-1)
    n = len(ts)
    if n == 0 or fi.shape != ts.shape:
        raise ValueError(f"need matching non-empty timestamps and frame_idx, got {n}, {fi.shape}")
    if not np.all(np.isfinite(ts)) or np.any(np.diff(ts) <= 0.0):
        raise ValueError("frame timestamps must be finite and strictly increasing")
    return ts, fi


def _drift(rngs: _Streams, model: InsErrorModel, ts: F64) -> F64:
    """(n, 6) smooth errors: position E, N, U (m), heading, roll, pitch (deg)."""
    return _smooth_drift(
        rngs.drift,
        ts,
        np.array(
            [*model.position_drift_m, model.heading_drift_deg, *[model.attitude_drift_deg] * 2]
        ),
        model.drift_period_s,
    )


def _position_errors(
    rngs: _Streams, model: InsErrorModel, ts: F64, fi: NDArray[np.int64], dt: F64, drift: F64
) -> tuple[F64, list[float]]:
    """(n, 3) position errors in local ENU (random walk, noise, drift, GNSS jumps) and the
    jumps' times."""
    n = len(ts)
    err_enu = _random_walk(rngs.position_walk, dt, np.asarray(model.position_random_walk_m))
    err_enu += rngs.position_noise.standard_normal((n, 3)) * np.asarray(model.position_noise_m)
    err_enu += drift[:, :3]
    jump_frames = [(int(f), np.asarray(off, dtype=np.float64)) for f, off in model.jumps]
    if model.jump_rate_hz > 0.0:
        happens = rngs.jump.random(n) < model.jump_rate_hz * dt
        offsets = rngs.jump.standard_normal((n, 3)) * model.jump_magnitude_m * [1.0, 1.0, 0.5]
        jump_frames += [(int(fi[k]), offsets[k]) for k in np.flatnonzero(happens)]
    t_jumps: list[float] = []
    for f, off in jump_frames:
        hit = np.flatnonzero(fi >= f)
        if len(hit) == 0:
            continue
        k0 = int(hit[0])
        age = ts[k0:] - ts[k0]
        decay = 1.0 if model.jump_decay_s is None else np.exp(-age / model.jump_decay_s)
        err_enu[k0:] += np.asarray(decay)[..., None] * off
        t_jumps.append(float(ts[k0]))
    if t_jumps:
        logger.info("INS simulation: %d GNSS jumps at t = %s", len(t_jumps), t_jumps)
    return err_enu, t_jumps


def _attitude(
    rngs: _Streams, model: InsErrorModel, R_enu_ins: F64, dt: F64, drift: F64
) -> tuple[F64, F64, F64]:
    """NovAtel roll, pitch, azimuth (deg) of ``R_enu_ins`` with their errors."""
    n = len(dt)
    roll, pitch, azimuth = novatel_attitude_from_R(R_enu_ins)
    heading_err = _random_walk(rngs.heading_walk, dt, np.array([model.heading_random_walk_deg]))
    heading_err = heading_err[:, 0]
    heading_err += rngs.heading_noise.standard_normal(n) * model.heading_noise_deg + drift[:, 3]
    att_err = _random_walk(rngs.attitude_walk, dt, np.full(2, model.attitude_random_walk_deg))
    att_err += rngs.attitude_noise.standard_normal((n, 2)) * model.attitude_noise_deg + drift[:, 4:]
    roll = roll + att_err[:, 0]
    pitch = pitch + att_err[:, 1]
    azimuth = np.mod(azimuth + heading_err, 360.0)
    azimuth = np.where(azimuth >= 360.0, 0.0, azimuth)
    return roll, pitch, azimuth


def _stdevs(
    rng: np.random.Generator,
    model: InsErrorModel,
    ts: F64,
    fi: NDArray[np.int64],
    t_jumps: list[float],
) -> InsStdDev:
    """INSSTDEV: baseline sigmas, raised for a few seconds after each jump, fluctuating."""
    n = len(ts)
    base = np.sqrt(
        np.asarray(model.position_stdev_m) ** 2 + np.asarray(model.position_noise_m) ** 2
    )
    gain = np.ones(n)
    for tj in t_jumps:
        age = ts - tj
        gain = np.maximum(
            gain,
            np.where(
                age >= 0.0,
                1.0
                + (_JUMP_STDEV_GAIN - 1.0) * np.exp(-np.maximum(age, 0.0) / _JUMP_STDEV_DECAY_S),
                1.0,
            ),
        )
    fluct = np.exp(0.1 * rng.standard_normal((n, 9)))
    pos_sd = base[None, :] * gain[:, None] * fluct[:, :3]
    vel_sd = max(model.velocity_noise_mps, 0.005) * gain[:, None] * fluct[:, 3:6]
    att_base = max(model.attitude_noise_deg, 0.005)
    az_base = max(model.heading_noise_deg, 0.01)
    return InsStdDev(
        frame_idx=fi.copy(),
        timestamp=ts.copy(),
        latitude_stdev=pos_sd[:, 1],
        longitude_stdev=pos_sd[:, 0],
        height_stdev=pos_sd[:, 2],
        north_velocity_stdev=vel_sd[:, 1],
        east_velocity_stdev=vel_sd[:, 0],
        up_velocity_stdev=vel_sd[:, 2],
        roll_stdev=att_base * fluct[:, 6],
        pitch_stdev=att_base * fluct[:, 7],
        azimuth_stdev=az_base * fluct[:, 8],
    )


def _corrimu(
    ins_pose: Callable[[F64], F64],
    t_true: F64,
    ts: F64,
    fi: NDArray[np.int64],
    R_now: F64,
    v_world: F64,
) -> CorrImu:
    """CORRIMU: rotation and kinematic acceleration per IMU sample over the window before
    each record's true time (body frame R_now, velocity v_world at the true times)."""
    win = CORRIMU_WINDOW_S
    hv = _VELOCITY_STEP_S
    samples = win * IMU_RATE_HZ
    R_prev = ins_pose(t_true - win)[:, :3, :3]
    dtheta_ins = Rotation.from_matrix(np.swapaxes(R_prev, -1, -2) @ R_now).as_rotvec()
    v_prev = (ins_pose(t_true - win + hv)[:, :3, 3] - ins_pose(t_true - win - hv)[:, :3, 3]) / (
        2.0 * hv
    )
    a_world = (v_world - v_prev) / win
    R_mid = (Rotation.from_matrix(R_prev) * Rotation.from_rotvec(0.5 * dtheta_ins)).as_matrix()
    a_ins = np.einsum("nji,nj->ni", R_mid, a_world)
    week, ms = unix_to_gps_week(ts)
    return CorrImu(
        frame_idx=fi.copy(),
        timestamp=ts.copy(),
        gps_week_number=week,
        gps_week_milliseconds=ms,
        pitch_rate=dtheta_ins[:, 0] / samples,
        roll_rate=dtheta_ins[:, 1] / samples,
        yaw_rate=dtheta_ins[:, 2] / samples,
        lateral_acc=a_ins[:, 0] / IMU_RATE_HZ,
        longitudinal_acc=a_ins[:, 1] / IMU_RATE_HZ,
        vertical_acc=a_ins[:, 2] / IMU_RATE_HZ,
    )


def _add_gyro_errors(corrimu: CorrImu, rng: np.random.Generator, model: InsErrorModel) -> None:
    """The gyros' errors, in place: a constant bias per axis (``gyro_bias_deg_h``, drawn
    once per sequence) and angle random walk (``gyro_noise_deg_rt_h``): over a window of
    ``CORRIMU_WINDOW_S`` the angle's white noise is ARW * sqrt(window)."""
    if model.gyro_noise_deg_rt_h <= 0.0 and model.gyro_bias_deg_h <= 0.0:
        return
    samples = CORRIMU_WINDOW_S * IMU_RATE_HZ
    bias = np.radians(model.gyro_bias_deg_h / 3600.0) * rng.standard_normal(3)  # rad/s
    arw = np.radians(model.gyro_noise_deg_rt_h / 60.0)  # rad/sqrt(s)
    n = len(corrimu.timestamp)
    angle = bias * CORRIMU_WINDOW_S + arw * np.sqrt(CORRIMU_WINDOW_S) * rng.standard_normal((n, 3))
    corrimu.pitch_rate = corrimu.pitch_rate + angle[:, 0] / samples
    corrimu.roll_rate = corrimu.roll_rate + angle[:, 1] / samples
    corrimu.yaw_rate = corrimu.yaw_rate + angle[:, 2] / samples


def _add_accel_errors(corrimu: CorrImu, rng: np.random.Generator, model: InsErrorModel) -> None:
    """The accelerometers' errors, in place: a constant bias per axis (``accel_bias_mg``,
    drawn once per sequence) and velocity random walk (``accel_noise_mps_rt_h``): over a
    window of ``CORRIMU_WINDOW_S`` the velocity's white noise is VRW * sqrt(window)."""
    if model.accel_noise_mps_rt_h <= 0.0 and model.accel_bias_mg <= 0.0:
        return
    bias = 9.80665e-3 * model.accel_bias_mg * rng.standard_normal(3)  # m/s^2
    vrw = model.accel_noise_mps_rt_h / 60.0  # m/s/sqrt(s)
    n = len(corrimu.timestamp)
    dv = bias * CORRIMU_WINDOW_S + vrw * np.sqrt(CORRIMU_WINDOW_S) * rng.standard_normal((n, 3))
    # m/s per sample: the window's velocity change spread over its samples
    samples = CORRIMU_WINDOW_S * IMU_RATE_HZ
    corrimu.lateral_acc = corrimu.lateral_acc + dv[:, 0] / samples
    corrimu.longitudinal_acc = corrimu.longitudinal_acc + dv[:, 1] / samples
    corrimu.vertical_acc = corrimu.vertical_acc + dv[:, 2] / samples


def _dropped(
    rng: np.random.Generator, model: InsErrorModel, fi: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """(n,) the records the dropout model removes (never all of them)."""
    n = len(fi)
    drop = rng.random(n) < model.dropout_fraction
    drop |= np.isin(fi, np.asarray(model.dropout_frames, dtype=np.int64))
    if np.all(drop):
        raise ValueError("the dropout model removed every INS record")
    if np.any(drop):
        logger.info("INS simulation: %d of %d frames dropped", int(np.sum(drop)), n)
    return drop


def simulate_ins(
    true_base: PoseTrack | Callable[[F64], F64],
    frame_timestamps: ArrayLike,
    frame_idx: ArrayLike,
    model: InsErrorModel | None = None,
    true_world: WorldFrame = HAMBURG,
) -> SimulatedIns:
    """Simulate the three NovAtel tables of a sequence (see the module docstring).

    Parameters
    ----------
    true_base : the true ``T_world_base`` in ``true_world``: a :class:`PoseTrack` or a
        function mapping (m,) UNIX times to (m, 4, 4) poses. It is read up to
        ``latency_s + CORRIMU_WINDOW_S + 0.01`` s before the first frame.
    frame_timestamps : (n,) UNIX seconds of the INS records (strictly increasing).
    frame_idx : (n,) frame counters.
    model : error model, default ``InsErrorModel.profile("paper")``.
    true_world : world frame of ``true_base`` (default Hamburg).
    """
    model = InsErrorModel.profile("paper") if model is None else model
    ts, fi = _record_times(frame_timestamps, frame_idx)
    pose_at = _pose_function(true_base)
    rngs = _Streams.from_seed(model.seed)
    T_base_ins = model.T_base_ins
    t_true = ts - model.latency_s
    dt = np.concatenate([[0.0], np.diff(ts)])

    def ins_pose(t: F64) -> F64:
        return pose_at(t) @ T_base_ins

    # the true INS state at the true times, the reported position
    T_world_ins = ins_pose(t_true)
    p_true = T_world_ins[:, :3, 3]
    lat_t, lon_t, _ = true_world.world_to_geodetic(p_true)
    R_world_enu_true = true_world.R_world_enu_at(lat_t, lon_t)
    drift = _drift(rngs, model, ts)
    err_enu, t_jumps = _position_errors(rngs, model, ts, fi, dt, drift)
    p_meas = p_true + np.einsum("nij,nj->ni", R_world_enu_true, err_enu)
    lat, lon, h = true_world.world_to_geodetic(p_meas)
    R_world_enu = true_world.R_world_enu_at(lat, lon)

    R_enu_ins = np.swapaxes(R_world_enu, -1, -2) @ T_world_ins[:, :3, :3]
    roll, pitch, azimuth = _attitude(rngs, model, R_enu_ins, dt, drift)

    # velocity: local ENU at the reported position
    hv = _VELOCITY_STEP_S
    v_world = (ins_pose(t_true + hv)[:, :3, 3] - ins_pose(t_true - hv)[:, :3, 3]) / (2.0 * hv)
    v_enu = np.einsum("nji,nj->ni", R_world_enu, v_world)
    v_enu += rngs.velocity.standard_normal((len(ts), 3)) * model.velocity_noise_mps

    inspva = InsPva(
        frame_idx=fi.copy(),
        timestamp=ts.copy(),
        latitude=lat,
        longitude=lon,
        height=h,
        north_velocity=v_enu[:, 1],
        east_velocity=v_enu[:, 0],
        up_velocity=v_enu[:, 2],
        roll=roll,
        pitch=pitch,
        azimuth=azimuth,
    )
    insstdev = _stdevs(rngs.misc, model, ts, fi, t_jumps)
    corrimu = _corrimu(ins_pose, t_true, ts, fi, T_world_ins[:, :3, :3], v_world)
    _add_gyro_errors(corrimu, rngs.gyro, model)
    _add_accel_errors(corrimu, rngs.accel, model)
    drop = _dropped(rngs.misc, model, fi)
    keep = ~drop
    inspva = inspva.take(keep)  # type: ignore[assignment]
    insstdev = insstdev.take(keep)  # type: ignore[assignment]
    corrimu = corrimu.take(keep)  # type: ignore[assignment]
    return SimulatedIns(
        inspva=inspva,
        insstdev=insstdev,
        corrimu=corrimu,
        ins_to_lidar=model.true_ins_to_lidar(),
        world=world_frame_from_ins(inspva),
        dropped_frames=fi[drop],
    )
