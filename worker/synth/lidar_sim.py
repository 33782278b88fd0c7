"""Lidar simulation of the synthetic OSDaR23 digital twin.

Six lidars as in OSDaR23 (``sensor_index`` 0..5, see ../shared/design/OSDAR23.md), ray cast
with open3d (Embree) against the scene's :class:`~worker.synth.scene_mesh.SceneMesh`.

Frames and conventions
----------------------
- ``base`` is the merged-lidar frame of OSDaR23: x forward, y left, z up, origin at
  top-of-rail level on the track centreline under the front of the train.
- Each sensor frame is aligned like the base frame (x forward, y left, z up; not optical);
  ``T_base_sensor`` is its mounting pose.
- ``pose_at(times)`` gives the TRUE ``T_world_base`` (m, 4, 4) at UNIX times (m,).

Timing and motion
-----------------
Every ray has its own emission time inside the sweep ``[frame_time - 0.05, frame_time +
0.05)`` (10 Hz): the frame timestamp is MID-SWEEP. The spinning sensors (Pandar64,
Honeycomb) are phase-locked so that they look straight ahead (sensor +x) at the frame time,
like a lidar synchronised to the front cameras; they turn clockwise seen from above, so the
seam of the sweep lies behind the sensor. The Livox rosette fires at a constant rate over
the sweep. The ray origin and direction come from the true pose at the emission time (the
train moves during the sweep); the return is then expressed in the base frame at
``frame_time``: the clouds are motion-compensated (deskewed) like a merged OSDaR23 cloud.

Output (as the fields of an OSDaR23 PCD)
-----------------------------------------
``x, y, z`` float32 (metres, base frame at frame_time), ``intensity`` float32
(sensor-specific scale, see :class:`LidarSensor`), ``timestamp`` float64 (UNIX seconds,
emission time of each point), ``sensor_index`` uint8.

Measurement model: Gaussian range noise along the ray (sensor-specific sigma, truncated at
``NOISE_TRUNCATION`` sigma), a random fraction of returns dropped, no return beyond the
sensor's max range (measured range) or below its min range, no return from the sky. The
own train body is not modelled (no self-occlusion, no self-returns). Intensity =
``intensity_scale * clip(reflectivity * |cos(incidence)| * falloff(range) * (1 + noise),
0, 1)`` with ``falloff(r) = 1 / (1 + (r / intensity_half_range)^2)``; Pandar and Livox
intensities are rounded to integers 0..255 like their uint8 outputs, the Honeycomb's stay a
float in [0, 1].

float32 safety: the mesh vertices are made relative to ``origin`` in float64 before the
float32 cast that Embree needs; ray origins likewise. Pass the position of the sequence's
first pose (or any point near the scanned area) as ``origin``; the default is the centre of
the mesh's bounding box, fine for scenes of a few km.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from geometry.transforms import T_to_pose, invert_T, make_T
from worker.synth.scene_mesh import MATERIALS, SceneMesh

F64 = NDArray[np.float64]
PoseFn = Callable[[np.ndarray], np.ndarray]

logger = logging.getLogger(__name__)

SWEEP_PERIOD_S = 0.1
"""One frame of every lidar: 10 Hz."""

NOISE_TRUNCATION = 4.0
"""Range noise is Gaussian truncated at this many sigma."""

_MASK63 = 2**63 - 1
_FAR_FROM_ORIGIN_M = 3000.0
"""Beyond this distance from ``origin`` float32 rounding reaches ~0.2 mm: warn."""

# Hesai Pandar64 elevation table (deg, channels 1..64), after the user manual: fine 0.167 deg
# spacing between +2 and -6 deg, coarse above and below, from +14.9 to -24.9 deg.
PANDAR64_ELEVATIONS_DEG: tuple[float, ...] = (
    14.882, 11.032, 8.059, 5.057, 3.040, 2.028, 1.860, 1.688,
    1.522, 1.351, 1.184, 1.013, 0.846, 0.675, 0.508, 0.337,
    0.169, 0.000, -0.169, -0.337, -0.508, -0.675, -0.845, -1.013,
    -1.184, -1.351, -1.522, -1.688, -1.860, -2.028, -2.198, -2.365,
    -2.536, -2.700, -2.873, -3.040, -3.210, -3.375, -3.548, -3.712,
    -3.884, -4.050, -4.221, -4.385, -4.558, -4.720, -4.892, -5.057,
    -5.229, -5.391, -5.565, -5.726, -5.898, -6.061, -7.063, -8.059,
    -9.060, -9.885, -11.032, -12.006, -12.974, -13.930, -18.889, -24.897,
)  # fmt: skip


# --------------------------------------------------------------------------------------
# Ray patterns
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RayPattern:
    """Directions and emission-time offsets of one sweep.

    Attributes
    ----------
    dirs_sensor : (n, 3) float64 unit directions in the sensor frame.
    dt : (n,) float64 emission time minus frame time, in [-T/2, T/2).
    """

    dirs_sensor: F64
    dt: F64


def _spherical_dirs(azimuth: F64, elevation: F64) -> F64:
    """Unit vectors (n, 3) from azimuth (CCW from +x towards +y) and elevation (rad)."""
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=-1)


@dataclass(frozen=True)
class SpinningPattern:
    """Spinning multi-beam lidar (Pandar64, Honeycomb).

    All beams of a column fire together. At time offset ``dt`` from the frame time the
    head points at azimuth ``-2 pi dt / period`` (clockwise seen from above, straight ahead
    at the frame time, seam behind).

    Attributes
    ----------
    elevations_deg : beam elevations, degrees.
    n_columns : azimuth steps per revolution at density 1.
    period_s : revolution period.
    """

    elevations_deg: tuple[float, ...]
    n_columns: int
    period_s: float = SWEEP_PERIOD_S

    def n_rays(self, density: float = 1.0) -> int:
        """Rays per sweep at ``density``."""
        return len(self.elevations_deg) * max(1, round(self.n_columns * density))

    def rays(self, frame_time: float, density: float = 1.0) -> RayPattern:
        """Ray directions and time offsets for the sweep around ``frame_time``.

        ``density`` keeps every beam and scales the number of columns.
        """
        del frame_time  # the pattern is identical every revolution
        n_col = max(1, round(self.n_columns * density))
        dt_col = -0.5 * self.period_s + (np.arange(n_col) + 0.5) * self.period_s / n_col
        azimuth = -2.0 * np.pi * dt_col / self.period_s
        elev = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))
        az_grid, el_grid = np.meshgrid(azimuth, elev, indexing="ij")  # (n_col, n_beams)
        dirs = _spherical_dirs(az_grid.ravel(), el_grid.ravel())
        dt = np.repeat(dt_col, len(elev))
        return RayPattern(dirs, dt)


@dataclass(frozen=True)
class RosettePattern:
    """Non-repetitive rosette of a Livox (two counter-rotating Risley prisms).

    The angular offset of the beam from the sensor's +x axis is the sum of two phasors of
    equal amplitude ``fov/4`` turning at ``f1`` and ``-f2`` Hz (incommensurate), which
    draws a rose curve filling a circular field of view of diameter ``fov_deg``, densest
    in its centre and its rim. The phases follow absolute time, so consecutive frames
    sample different points of the field of view. Points are fired at a constant rate.

    Attributes
    ----------
    fov_deg : diameter of the circular field of view, degrees.
    points_per_sweep : points per sweep at density 1.
    f1_hz, f2_hz : prism rotation rates.
    phase_cycles : phase offset of the prisms (distinct sensors are not in step).
    period_s : sweep (frame) period.
    """

    fov_deg: float
    points_per_sweep: int
    f1_hz: float = 131.7
    f2_hz: float = 83.9
    phase_cycles: float = 0.0
    period_s: float = SWEEP_PERIOD_S

    def n_rays(self, density: float = 1.0) -> int:
        """Rays per sweep at ``density``."""
        return max(1, round(self.points_per_sweep * density))

    def rays(self, frame_time: float, density: float = 1.0) -> RayPattern:
        """Ray directions and time offsets for the sweep around ``frame_time``."""
        n = self.n_rays(density)
        dt = -0.5 * self.period_s + (np.arange(n) + 0.5) * self.period_s / n
        # Phase in cycles, reduced early so that UNIX-time magnitudes keep precision.
        whole = np.floor(frame_time)
        frac = frame_time - whole
        c1 = np.mod(self.f1_hz * whole, 1.0) + self.f1_hz * (frac + dt) + self.phase_cycles
        c2 = np.mod(self.f2_hz * whole, 1.0) + self.f2_hz * (frac + dt) - self.phase_cycles
        a = np.deg2rad(self.fov_deg) / 4.0
        u = a * (np.cos(2 * np.pi * c1) + np.cos(2 * np.pi * c2))
        v = a * (np.sin(2 * np.pi * c1) - np.sin(2 * np.pi * c2))
        rho = np.hypot(u, v)
        psi = np.arctan2(v, u)
        sr = np.sin(rho)
        dirs = np.stack([np.cos(rho), sr * np.cos(psi), sr * np.sin(psi)], axis=-1)
        return RayPattern(dirs, dt)


Pattern = SpinningPattern | RosettePattern


# --------------------------------------------------------------------------------------
# Sensors
# --------------------------------------------------------------------------------------


@dataclass
class LidarSensor:
    """One lidar of the rig.

    Attributes
    ----------
    sensor_index : OSDaR23 ``sensor_index`` (0..5).
    name, model : identifiers written to ``lidar_origins.json``.
    T_base_sensor : (4, 4) mounting pose in the base frame (sensor -> base).
    pattern : ray pattern (directions and emission times of a sweep).
    max_range, min_range : metres; returns outside are not reported.
    range_sigma : standard deviation of the Gaussian range noise, metres.
    dropout : fraction of returns randomly lost.
    intensity_scale : full-scale value of ``intensity`` (255 for Pandar / Livox, 1 for
        the Honeycomb).
    intensity_integer : round intensity to integers (uint8-like sensors).
    intensity_half_range : range (m) at which the intensity falloff halves the value.
    intensity_noise : relative (multiplicative) Gaussian intensity noise.
    """

    sensor_index: int
    name: str
    model: str
    T_base_sensor: F64
    pattern: Pattern
    max_range: float
    min_range: float = 0.3
    range_sigma: float = 0.02
    dropout: float = 0.005
    intensity_scale: float = 255.0
    intensity_integer: bool = True
    intensity_half_range: float = 100.0
    intensity_noise: float = 0.05

    def __post_init__(self) -> None:
        self.T_base_sensor = np.asarray(self.T_base_sensor, dtype=np.float64).reshape(4, 4)

    @property
    def sweep_period(self) -> float:
        """Duration of one sweep (s)."""
        return self.pattern.period_s


def mounting_T(xyz: ArrayLike, yaw_deg: float = 0.0, pitch_down_deg: float = 0.0) -> F64:
    """T_base_sensor from a position and a yaw (left positive) / downward pitch, degrees.

    Returns
    -------
    (4, 4) float64; R = Rz(yaw) @ Ry(pitch_down) (a positive rotation about +y tilts +x
    downwards).
    """
    R = Rotation.from_euler("ZY", [yaw_deg, pitch_down_deg], degrees=True).as_matrix()
    return make_T(R, np.asarray(xyz, dtype=np.float64))


def default_sensors() -> list[LidarSensor]:
    """The six lidars of the OSDaR23 rig, with plausible (unpublished) mounting poses.

    0: Hesai Pandar64-like, roof centre 3.5 m above the rail, 64 beams (+14.9..-24.9 deg),
       0.2 deg at 10 Hz (1800 columns, 115 200 rays), 200 m, sigma 2 cm.
    1, 2, 3: Livox Tele-15-like, right / centre / left at 2.9 m, yaw -8 / 0 / +8 deg,
       pitched 3 deg down, 14.5 deg circular rosette, 28 000 points per sweep each
       (~240 kHz), 500 m, sigma 2 cm.
    4, 5: Waymo Honeycomb-like, left / right front corners 1.2 m above the rail, 64 beams
       uniform over 95 deg (+5..-88.5 deg) x 360 deg in 256 columns, 50 m, sigma 2.5 cm,
       intensity in [0, 1].
    """
    pandar = SpinningPattern(PANDAR64_ELEVATIONS_DEG, n_columns=1800)
    livox = [
        RosettePattern(fov_deg=14.5, points_per_sweep=28_000, phase_cycles=ph)
        for ph in (0.0, 0.37, 0.71)
    ]
    honeycomb = SpinningPattern(
        tuple(np.linspace(5.0, -90.0, 64, endpoint=False).round(4).tolist()), n_columns=256
    )
    sensors = [
        LidarSensor(0, "lidar_pandar64", "Hesai Pandar64", mounting_T([0.0, 0.0, 3.5]),
                    pandar, max_range=200.0, range_sigma=0.02, intensity_half_range=100.0),
        LidarSensor(1, "lidar_livox_right", "Livox Tele-15",
                    mounting_T([0.3, -0.45, 2.9], yaw_deg=-8.0, pitch_down_deg=3.0),
                    livox[0], max_range=500.0, min_range=1.0, range_sigma=0.02,
                    intensity_half_range=250.0),
        LidarSensor(2, "lidar_livox_centre", "Livox Tele-15",
                    mounting_T([0.3, 0.0, 2.9], yaw_deg=0.0, pitch_down_deg=3.0),
                    livox[1], max_range=500.0, min_range=1.0, range_sigma=0.02,
                    intensity_half_range=250.0),
        LidarSensor(3, "lidar_livox_left", "Livox Tele-15",
                    mounting_T([0.3, 0.45, 2.9], yaw_deg=8.0, pitch_down_deg=3.0),
                    livox[2], max_range=500.0, min_range=1.0, range_sigma=0.02,
                    intensity_half_range=250.0),
        LidarSensor(4, "lidar_honeycomb_left", "Waymo Honeycomb",
                    mounting_T([0.1, 1.35, 1.2]), honeycomb, max_range=50.0, min_range=0.0,
                    range_sigma=0.025, intensity_scale=1.0, intensity_integer=False,
                    intensity_half_range=30.0),
        LidarSensor(5, "lidar_honeycomb_right", "Waymo Honeycomb",
                    mounting_T([0.1, -1.35, 1.2]), honeycomb, max_range=50.0, min_range=0.0,
                    range_sigma=0.025, intensity_scale=1.0, intensity_integer=False,
                    intensity_half_range=30.0),
    ]  # fmt: skip
    return sensors


def sensors_to_json(sensors: list[LidarSensor]) -> list[dict[str, Any]]:
    """Sensor mounting poses for ``ground_truth/lidar_origins.json``.

    Returns
    -------
    list of {sensor_index, name, model, translation [x, y, z], quaternion [x, y, z, w]},
    the pose of each sensor in the base frame (sensor -> base).
    """
    out = []
    for s in sensors:
        t, q = T_to_pose(s.T_base_sensor)
        out.append(
            {
                "sensor_index": int(s.sensor_index),
                "name": s.name,
                "model": s.model,
                "translation": [float(v) for v in t],
                "quaternion": [float(v) for v in q],
            }
        )
    return out


# --------------------------------------------------------------------------------------
# Simulator
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Returns:
    """Rays that returned: index into the frame's rays, hit face, its normal, true and
    measured range, emitting sensor (position in the simulator's list), the standard normal
    draw of its intensity noise."""

    idx: NDArray[np.int64]
    face: NDArray[np.int64]
    normal: F64
    r_true: F64
    r_meas: F64
    which: NDArray[np.int64]
    u_int: F64


class LidarSimulator:
    """Ray-casts the lidars of a rig against a static scene mesh.

    Parameters
    ----------
    mesh : the scene, float64 world vertices.
    sensors : the rig (default :func:`default_sensors`).
    origin : (3,) world point subtracted from every coordinate before the float32 cast;
        pass the first pose's position of the sequence. Default: the mesh's bounding-box
        centre.
    seed : seed of the noise; a scan is a deterministic function of (seed, frame_time).
    density : 0 < density <= 1 scales the number of rays of every sensor.
    nthreads : Embree threads, 0 = all.
    """

    def __init__(
        self,
        mesh: SceneMesh,
        sensors: list[LidarSensor] | None = None,
        origin: ArrayLike | None = None,
        seed: int = 0,
        density: float = 1.0,
        nthreads: int = 0,
        merge_errors: dict[int, F64] | None = None,
    ) -> None:
        if not 0.0 < density <= 1.0:
            raise ValueError(f"density must be in (0, 1], got {density}")
        if len(mesh.faces) == 0:
            raise ValueError("the scene mesh has no faces")
        self.mesh = mesh
        self.sensors = list(default_sensors() if sensors is None else sensors)
        idx = [s.sensor_index for s in self.sensors]
        if len(set(idx)) != len(idx) or not all(0 <= i < 256 for i in idx):
            raise ValueError(f"sensor indices must be unique uint8 values, got {idx}")
        if origin is None:
            origin = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.seed = int(seed)
        self.density = float(density)
        self.nthreads = int(nthreads)
        #: sensor_index -> (4, 4) error of the calibration the clouds are merged with:
        #: each sensor's points land at ``E @ p_base`` instead of ``p_base``
        self.merge_errors = {int(k): np.asarray(v, dtype=np.float64).reshape(4, 4)
                             for k, v in (merge_errors or {}).items()}  # fmt: skip
        self._face_material = mesh.material
        self._reflectivity = np.array([m.reflectivity for m in MATERIALS], dtype=np.float64)

        v_rel = (mesh.vertices - self.origin).astype(np.float32)
        self._scene = o3d.t.geometry.RaycastingScene(nthreads=self.nthreads)
        self._scene.add_triangles(
            o3d.core.Tensor(v_rel), o3d.core.Tensor(mesh.faces.astype(np.uint32))
        )
        # Embree builds its BVH lazily on the first query: do it now (~1 s per M triangles)
        # so that every scan costs the same.
        probe = np.zeros((1, 6), dtype=np.float32)
        probe[0, 5] = -1.0
        self._scene.cast_rays(o3d.core.Tensor(probe), nthreads=self.nthreads)
        logger.debug(
            "lidar scene: %d triangles, origin %s, %d sensors, density %.3g",
            len(mesh.faces),
            self.origin,
            len(self.sensors),
            self.density,
        )

    def n_rays(self) -> dict[int, int]:
        """Rays cast per sweep, by sensor_index."""
        return {s.sensor_index: s.pattern.n_rays(self.density) for s in self.sensors}

    def scan(self, frame_time: float, pose_at: PoseFn) -> dict[str, np.ndarray]:
        """One merged, deskewed frame of all sensors.

        Parameters
        ----------
        frame_time : UNIX time of the frame (mid-sweep).
        pose_at : times (m,) -> true T_world_base (m, 4, 4).

        Returns
        -------
        dict with x, y, z (n,) float32 (base frame at frame_time), intensity (n,) float32,
        timestamp (n,) float64, sensor_index (n,) uint8; points sorted by sensor then
        emission order.
        """
        cloud, _ = self.scan_with_ground_truth(frame_time, pose_at)
        return cloud

    def scan_with_ground_truth(
        self, frame_time: float, pose_at: PoseFn
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Like :meth:`scan`, plus the ground truth of every returned point.

        Returns
        -------
        cloud : as :meth:`scan`.
        truth : dict with
            hit_world (n, 3) float64 noise-free hit point in the world frame;
            face_id (n,) int64 hit triangle; face_material (n,) int64 index into MATERIALS;
            range_true, range_measured (n,) float64 metres;
            origin_base (n, 3) float64 sensor origin at emission time, expressed in the
            base frame at frame_time (so ``|p_base - origin_base| == range_measured``);
            dir_base (n, 3) float64 ray direction in that frame;
            cos_incidence (n,) float64;
            T_world_base (4, 4) float64 pose at frame_time.
        """
        frame_time = float(frame_time)
        rng = np.random.default_rng([self.seed & _MASK63, round(frame_time * 1e6) & _MASK63])
        dt, which, d_sensor = self._emit(frame_time)
        T_world_base_u, inv, T_world_base_ft = self._true_poses(frame_time, dt, pose_at)
        o_rel, d_world = self._world_rays(which, d_sensor, T_world_base_u, inv)
        ret = self._measure(rng, self._cast(o_rel, d_world, which))

        o_w_rel = o_rel[ret.idx]
        d_w = d_world[ret.idx]
        hit_world = o_w_rel + ret.r_true[:, None] * d_w + self.origin
        p_world_rel = o_w_rel + ret.r_meas[:, None] * d_w

        # deskew: into the base frame at frame_time
        T_base_world_ft = invert_T(T_world_base_ft)
        R_bw = T_base_world_ft[:3, :3]
        t_bw = T_base_world_ft[:3, 3] + R_bw @ self.origin  # maps origin-relative points
        p_base = self._merged(p_world_rel @ R_bw.T + t_bw, ret.which)
        origin_base = o_w_rel @ R_bw.T + t_bw
        dir_base = d_w @ R_bw.T

        intensity, cos_inc, mat = self._intensity(ret, d_w)
        sensor_index = np.array([s.sensor_index for s in self.sensors], dtype=np.uint8)
        cloud = {
            "x": p_base[:, 0].astype(np.float32),
            "y": p_base[:, 1].astype(np.float32),
            "z": p_base[:, 2].astype(np.float32),
            "intensity": intensity.astype(np.float32),
            "timestamp": frame_time + dt[ret.idx],
            "sensor_index": sensor_index[ret.which],
        }
        truth = {
            "hit_world": hit_world,
            "face_id": ret.face,
            "face_material": mat,
            "range_true": ret.r_true,
            "range_measured": ret.r_meas,
            "origin_base": origin_base,
            "dir_base": dir_base,
            "cos_incidence": cos_inc,
            "T_world_base": T_world_base_ft,
        }
        logger.debug(
            "lidar frame %.6f: %d rays, %d returns",
            frame_time,
            len(dt),
            len(ret.idx),
        )
        return cloud, truth

    def _merged(self, p_base: F64, which: NDArray[np.int64]) -> F64:
        """The points as a merge with an imperfect calibration places them: sensor s's
        points moved by its ``merge_errors`` transform (the ground truth stays exact)."""
        if not self.merge_errors:
            return p_base
        out = p_base.copy()
        for k, s in enumerate(self.sensors):
            E = self.merge_errors.get(s.sensor_index)
            if E is None:
                continue
            sel = which == k
            out[sel] = p_base[sel] @ E[:3, :3].T + E[:3, 3]
        return out

    def _emit(self, frame_time: float) -> tuple[F64, NDArray[np.int64], F64]:
        """Rays of every sensor in its own frame: emission times relative to frame_time
        (n,), the emitting sensor's position in ``self.sensors`` (n,), directions (n, 3)."""
        dirs_s, dts, sidx = [], [], []
        for k, s in enumerate(self.sensors):
            pat = s.pattern.rays(frame_time, self.density)
            dirs_s.append(pat.dirs_sensor)
            dts.append(pat.dt)
            sidx.append(np.full(len(pat.dt), k, dtype=np.int64))
        return np.concatenate(dts), np.concatenate(sidx), np.concatenate(dirs_s)

    def _true_poses(
        self, frame_time: float, dt: F64, pose_at: PoseFn
    ) -> tuple[F64, NDArray[np.intp], F64]:
        """True T_world_base at the unique emission times (u, 4, 4), each ray's index into
        them (n,), and the pose at frame_time (4, 4)."""
        t_unique, inv = np.unique(dt, return_inverse=True)
        T_world_base_u = np.asarray(pose_at(frame_time + t_unique), dtype=np.float64)
        if T_world_base_u.shape != (len(t_unique), 4, 4):
            raise ValueError(
                f"pose_at must return ({len(t_unique)}, 4, 4), got {T_world_base_u.shape}"
            )
        T_world_base_ft = np.asarray(pose_at(np.array([frame_time])), dtype=np.float64)
        T_world_base_ft = T_world_base_ft.reshape(4, 4)
        dist0 = np.linalg.norm(T_world_base_ft[:3, 3] - self.origin)
        if dist0 > _FAR_FROM_ORIGIN_M:
            logger.warning(
                "scan %.1f km from the float32 origin: pass a nearer origin", dist0 / 1e3
            )
        return T_world_base_u, inv, T_world_base_ft

    def _world_rays(
        self, which: NDArray[np.int64], d_sensor: F64, T_world_base_u: F64, inv: NDArray[np.intp]
    ) -> tuple[F64, F64]:
        """Ray origins (relative to ``self.origin``) and directions in the world (n, 3)."""
        R_bs = np.stack([s.T_base_sensor[:3, :3] for s in self.sensors])  # (k, 3, 3)
        t_bs = np.stack([s.T_base_sensor[:3, 3] for s in self.sensors])  # (k, 3)
        d_base = np.einsum("nij,nj->ni", R_bs[which], d_sensor)
        o_base = t_bs[which]
        R_wb = T_world_base_u[inv, :3, :3]
        t_wb = T_world_base_u[inv, :3, 3]
        d_world = np.einsum("nij,nj->ni", R_wb, d_base)
        o_rel = np.einsum("nij,nj->ni", R_wb, o_base) + (t_wb - self.origin)
        return o_rel, d_world

    def _cast(self, o_rel: F64, d_world: F64, which: NDArray[np.int64]) -> _Returns:
        """The rays that hit the scene (no measurement model yet: r_meas = r_true)."""
        rays = np.empty((len(o_rel), 6), dtype=np.float32)
        rays[:, :3] = o_rel
        rays[:, 3:] = d_world
        ans = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=self.nthreads)
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        idx = np.flatnonzero(np.isfinite(t_hit))
        return _Returns(
            idx=idx,
            face=ans["primitive_ids"].numpy()[idx].astype(np.int64),
            normal=ans["primitive_normals"].numpy()[idx].astype(np.float64),
            r_true=t_hit[idx],
            r_meas=t_hit[idx],
            which=which[idx],
            u_int=np.zeros(len(idx)),
        )

    def _measure(self, rng: np.random.Generator, hits: _Returns) -> _Returns:
        """Range noise, range limits and dropouts; the intensity noise draw of each kept
        return. Draws for every hit, so the random streams do not depend on what is kept."""
        which_h = hits.which
        n = len(hits.idx)
        sigma = np.array([s.range_sigma for s in self.sensors])[which_h]
        noise = np.clip(rng.standard_normal(n), -NOISE_TRUNCATION, NOISE_TRUNCATION)
        r_meas = hits.r_true + sigma * noise
        max_r = np.array([s.max_range for s in self.sensors])[which_h]
        min_r = np.array([s.min_range for s in self.sensors])[which_h]
        drop_p = np.array([s.dropout for s in self.sensors])[which_h]
        keep = (r_meas <= max_r) & (r_meas >= min_r) & (hits.r_true <= max_r)
        keep &= rng.random(n) >= drop_p
        u_int = rng.standard_normal(n)  # drawn for all hits: stable streams
        sel = np.flatnonzero(keep)
        return _Returns(
            idx=hits.idx[sel],
            face=hits.face[sel],
            normal=hits.normal[sel],
            r_true=hits.r_true[sel],
            r_meas=r_meas[sel],
            which=which_h[sel],
            u_int=u_int[sel],
        )

    def _intensity(self, ret: _Returns, d_w: F64) -> tuple[F64, F64, NDArray[np.int64]]:
        """Intensity (n,), |cos| of the incidence angle (n,), material of the hit face (n,)."""
        which_h = ret.which
        cos_inc = np.abs(np.einsum("ni,ni->n", ret.normal, d_w))
        mat = self._face_material[ret.face]
        rho = self._reflectivity[mat]
        half = np.array([s.intensity_half_range for s in self.sensors])[which_h]
        rel_n = np.array([s.intensity_noise for s in self.sensors])[which_h]
        scale = np.array([s.intensity_scale for s in self.sensors])[which_h]
        as_int = np.array([s.intensity_integer for s in self.sensors])[which_h]
        val = rho * cos_inc / (1.0 + (ret.r_true / half) ** 2) * (1.0 + rel_n * ret.u_int)
        intensity = scale * np.clip(val, 0.0, 1.0)
        intensity = np.where(as_int, np.round(intensity), intensity)
        return intensity, cos_inc, mat


def cloud_points(cloud: dict[str, np.ndarray]) -> F64:
    """(n, 3) float64 base-frame points of a cloud dict."""
    return np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=-1).astype(np.float64)
