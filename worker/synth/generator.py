"""The synthetic OSDaR23 sequence generator (the project's digital twin).

A procedural railway scene is driven through by a train carrying the real OSDaR23 sensor
set-up (calibration from the shared real labels file); every frame it writes both front
cameras (moderngl, real lens distortion), the merged lidar cloud of the six lidars
(open3d ray casting), and the three NovAtel INS CSVs with a configurable error model, in
the OSDaR23 layout. ``ground_truth/`` holds what the pipeline must never read while it
runs: true poses, the true INS misalignment, lidar mounting poses, centrelines, and
landmarks with their true pixel positions per frame.

Recipe, per frame: true pose at each sensor's timestamp -> render cameras -> cast lidar
-> write files; then INS, labels and ground truth for the whole sequence.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from geometry.camera import CameraModel, load_cameras
from geometry.poses import PoseTrack
from geometry.transforms import T_to_pose, transform_points
from osdar_platform.shared_data import real_labels_path
from worker.osdar.labels import frame_intervals
from worker.osdar.pcd import PointCloud, header_for_fields
from worker.osdar.writer import SequenceWriter
from worker.synth.camera_sim import CameraSimulator
from worker.synth.ins_sim import HAMBURG, InsErrorModel, SimulatedIns, simulate_ins
from worker.synth.lidar_sim import (
    LidarSensor,
    LidarSimulator,
    default_sensors,
    sensors_to_json,
)
from worker.synth.scene import Scene
from worker.synth.scenes import build_scene

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

DEFAULT_CAMERAS = ("rgb_center", "rgb_highres_center")
FRAME_PERIOD_NS = 100_000_000  # 10 Hz
# Offsets of each stream's timestamp from the frame's nominal time (ns), of the size seen
# in OSDaR23 (lidar 0.5 ms early, cameras a few ms apart): hard case 12 of BENCHMARK.md.
STREAM_OFFSET_NS = {"lidar": -496_000, "rgb_center": 0, "rgb_highres_center": 2_100_030}
DEFAULT_START_NS = 1_631_441_453_300_000_000  # the real sequence 1_calibration_1.1's first frame
# Landmarks hidden by the scene closer than this to themselves (m) count as occluded.
OCCLUSION_EPS_M = 0.15
# A UTM-like offset for the far-origin hard case (m).
FAR_ORIGIN_OFFSET = np.array([566_000.0, 5_933_000.0, 30.0])


def default_calibration_path() -> Path:
    """The real OSDaR23 labels file with the real calibration (``osdar_platform.shared_data``)."""
    return real_labels_path()


@dataclass
class SynthConfig:
    """What to generate. Defaults make the paper-like 100-frame sequence at scale 0.25."""

    scene: str = "fire_site"
    frames: int = 100
    scale: float = 0.25
    seed: int = 0
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    lidar_density: float = 1.0
    ins_profile: str = "paper"
    #: Per-lidar error of the calibration the merged clouds are made with: (rotation deg,
    #: translation m) standard deviations per axis; None: the INS profile's default
    #: (:data:`MERGE_ERROR_BY_PROFILE`: "osdar23" has it, as real merged clouds do).
    lidar_merge_error: tuple[float, float] | None = None
    #: Returns less than this far ahead of the base origin (base x, m) are not reported:
    #: lidars on a train's roof that do not see the track right in front of it (the first
    #: metres of the sequence's track are then never seen). 0: they see everything.
    lidar_blind_ahead_m: float = 0.0
    #: The train body on two bogies: (overhang m, the base origin ahead of the front
    #: bogie's centre; spacing m between the bogie centres), e.g. (3.0, 19.0); None: the
    #: base frame runs on the centreline with the track's tangent.
    bogies: tuple[float, float] | None = None
    ins_overrides: dict[str, Any] = field(default_factory=dict)
    speed_mps: float | None = None  # None: the scene's own speed
    stationary: bool = False
    far_origin: bool = False
    first_counter: int = 0
    start_ns: int = DEFAULT_START_NS
    dropped_frames: tuple[int, ...] = ()  # frame counters left out (a dropped frame)
    pcd_data: str = "binary"
    png_compression: int = 1
    calibration: Path | None = None
    scene_params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError("frames must be >= 1")
        if not 0.01 <= self.scale <= 1.0:
            raise ValueError("scale must be in [0.01, 1]")
        if self.bogies is not None and not (
            self.bogies[0] >= 0 and 0 < self.bogies[1] and sum(self.bogies) < 25.0
        ):
            raise ValueError(
                f"bogies must be (overhang >= 0, spacing > 0) m within 25 m, got {self.bogies}"
            )
        if self.lidar_blind_ahead_m < 0:
            raise ValueError(f"lidar_blind_ahead_m must be >= 0, got {self.lidar_blind_ahead_m}")
        if not 0.0 < self.lidar_density <= 1.0:
            raise ValueError("lidar_density must be in (0, 1]")
        if self.pcd_data not in ("ascii", "binary", "binary_compressed"):
            raise ValueError("pcd_data must be ascii, binary or binary_compressed")


@dataclass
class FrameTimes:
    """Integer-nanosecond timestamps of one frame per stream (exact strings for file names)."""

    counter: int
    ns: dict[str, int]

    def seconds(self, stream: str) -> float:
        return self.ns[stream] / 1e9

    def string(self, stream: str) -> str:
        return ns_to_string(self.ns[stream])


def ns_to_string(t_ns: int) -> str:
    """UNIX nanoseconds -> the OSDaR23 timestamp string with 9 decimals."""
    return f"{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d}"


def frame_schedule(cfg: SynthConfig, streams: list[str]) -> list[FrameTimes]:
    """Counters and per-stream timestamps of the frames written (dropped frames skipped)."""
    rng = np.random.default_rng(cfg.seed + 17)
    out = []
    for i in range(cfg.frames):
        counter = cfg.first_counter + i
        if counter in cfg.dropped_frames:
            continue
        base = cfg.start_ns + i * FRAME_PERIOD_NS
        jitter = int(rng.integers(-200, 200))  # sub-microsecond trigger jitter
        ns = {s: base + STREAM_OFFSET_NS.get(s, 1_000) + jitter for s in streams}
        out.append(FrameTimes(counter, ns))
    return out


class Trajectory:
    """The train's true motion along the ego track: T_S_base(t) in the scene frame.

    Arc length s(t) = s0 + v t + a t^2 / 2 (gentle acceleration), plus small body motion of
    the vehicle on its suspension (sway, bounce, pitch and roll oscillations of mm and
    hundredths of a degree), which no rail-only model can follow.
    """

    def __init__(
        self,
        track: Any,
        t0: float,
        speed: float,
        accel: float,
        s0: float,
        seed: int,
        body_motion: bool = True,
        bogies: tuple[float, float] | None = None,
    ) -> None:
        self.track = track
        self.t0, self.speed, self.accel, self.s0 = t0, speed, accel, s0
        self.bogies = bogies
        rng = np.random.default_rng(seed + 101)
        self.phase = rng.uniform(0, 2 * np.pi, 5)
        self.body = body_motion and speed > 0.0

    def arclength(self, t: F64) -> F64:
        dt = np.asarray(t, dtype=np.float64) - self.t0
        return self.s0 + self.speed * dt + 0.5 * self.accel * dt * dt

    def __call__(self, t: F64) -> F64:
        """(m,) UNIX seconds -> (m, 4, 4) T_S_base."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        s = self.arclength(t)
        T = self.track.frame_at(s) if self.bogies is None else self._on_bogies(s)
        if not self.body:
            return T
        dt = t - self.t0
        ph = self.phase
        sway = 0.006 * np.sin(2 * np.pi * 0.7 * dt + ph[0])  # m, lateral
        bounce = 0.004 * np.sin(2 * np.pi * 1.3 * dt + ph[1])  # m, vertical
        pitch = np.deg2rad(0.03) * np.sin(2 * np.pi * 1.1 * dt + ph[2])
        roll = np.deg2rad(0.04) * np.sin(2 * np.pi * 0.9 * dt + ph[3])
        yaw = np.deg2rad(0.01) * np.sin(2 * np.pi * 0.5 * dt + ph[4])

        R_body = Rotation.from_euler("xyz", np.stack([roll, pitch, yaw], 1)).as_matrix()
        T_body = np.tile(np.eye(4), (len(t), 1, 1))
        T_body[:, :3, :3] = R_body
        T_body[:, 1, 3] = sway
        T_body[:, 2, 3] = bounce
        return T @ T_body

    def _on_bogies(self, s: F64) -> F64:
        """(m, 4, 4) T_S_base of a body whose two bogie centres run on the centreline at
        ``s - overhang`` and ``s - overhang - spacing``: the base is ``overhang`` ahead of
        the front bogie on the body's axis, so in a curve it lies outside the centreline
        (overhang (overhang + spacing) / 2R) and the body's heading is the chord's, not
        the tangent's at the base. Up: the mean of the two bogies' rail-plane normals
        (their cant), square to the axis."""
        overhang, spacing = self.bogies  # type: ignore[misc]
        front = self.track.frame_at(s - overhang)
        rear = self.track.frame_at(s - overhang - spacing)
        x = front[:, :3, 3] - rear[:, :3, 3]
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        z = front[:, :3, 2] + rear[:, :3, 2]
        z -= np.sum(z * x, axis=1, keepdims=True) * x
        z /= np.linalg.norm(z, axis=1, keepdims=True)
        T = np.tile(np.eye(4), (len(s), 1, 1))
        T[:, :3, :3] = np.stack([x, np.cross(z, x), z], axis=2)
        T[:, :3, 3] = front[:, :3, 3] + overhang * x
        return T


def _load_calibration(cfg: SynthConfig) -> dict[str, Any]:
    path = Path(cfg.calibration) if cfg.calibration else default_calibration_path()
    if not path.is_file():
        raise FileNotFoundError(
            f"real OSDaR23 calibration not found at {path}: pass --calibration with an "
            "OSDaR23 labels file (e.g. shared/data/osdar23/1_calibration_1.1_labels.json)"
        )
    return json.loads(path.read_text())


def _labels_skeleton(real: dict[str, Any], name: str, cams: dict[str, CameraModel]) -> dict:
    """OpenLABEL dict with the real calibration, scaled intrinsics for written cameras."""
    ol = real["openlabel"]
    meta = dict(ol["metadata"])
    meta["name"] = f"synthetic sequence {name}"
    meta["tagged_file"] = name
    meta["comment"] = (
        "Synthetic OSDaR23-layout sequence made by osdar-ar's generator with the real "
        "OSDaR23 calibration. " + str(meta.get("comment", ""))
    )
    streams = json.loads(json.dumps(ol["streams"]))
    for cname, cam in cams.items():
        intr = streams[cname]["stream_properties"]["intrinsics_pinhole"]
        K = cam.K
        intr["camera_matrix"] = [
            K[0, 0],
            K[0, 1],
            K[0, 2],
            0.0,
            K[1, 0],
            K[1, 1],
            K[1, 2],
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
        ]
        intr["width_px"] = cam.width
        intr["height_px"] = cam.height
    return {
        "openlabel": {
            "metadata": meta,
            "coordinate_systems": json.loads(json.dumps(ol["coordinate_systems"])),
            "streams": streams,
            "objects": {},
            "frames": {},
            "frame_intervals": [],
        }
    }


def _frame_entry(ft: FrameTimes, cameras: tuple[str, ...]) -> dict[str, Any]:
    streams = {}
    for cam in cameras:
        streams[cam] = {
            "stream_properties": {"sync": {"timestamp": ft.string(cam)}},
            "uri": f"/{cam}/{ft.counter:03d}_{ft.string(cam)}.png",
        }
    streams["lidar"] = {
        "stream_properties": {"sync": {"timestamp": ft.string("lidar")}},
        "uri": f"/lidar/{ft.counter:03d}_{ft.string('lidar')}.pcd",
    }
    return {
        "frame_properties": {
            "timestamp": ft.string("lidar"),
            "streams": streams,
            "frame_data": {"num": []},
        },
        "objects": {},
    }


class LandmarkVisibility:
    """Occlusion test of landmarks from a camera centre by ray casting the scene mesh."""

    def __init__(self, mesh: Any, origin: F64) -> None:

        self.origin = origin
        scene = o3d.t.geometry.RaycastingScene()
        v = (mesh.vertices - origin).astype(np.float32)
        scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        self.scene = scene

    def visible(self, c_S: F64, p_S: F64) -> NDArray[np.bool_]:
        """Camera centre (3,) and points (n, 3) in the scene frame -> (n,) unoccluded."""

        d = p_S - c_S
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate(
            [np.broadcast_to(c_S - self.origin, d.shape), d / dist[:, None]], axis=1
        ).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return hit >= dist - OCCLUSION_EPS_M


@dataclass
class SynthResult:
    folder: Path
    frames: int
    seconds: float
    stage_seconds: dict[str, float]


@dataclass
class _Rig:
    """The simulated train: its trajectory in the scene frame S and its sensors."""

    scene: Scene
    traj: Trajectory
    T_ref_S: F64  # the scene frame in the true reference frame (HAMBURG ENU)
    cams_full: dict[str, CameraModel]  # full resolution (landmark pixels)
    camsim: CameraSimulator
    sensors: list[LidarSensor]
    lidar: LidarSimulator
    vis: LandmarkVisibility


def _build_scene(cfg: SynthConfig, duration: float) -> tuple[Scene, float, float, F64]:
    """The scene, long enough for the drive: (scene, speed m/s, start arc length s0 m,
    origin offset (3,))."""
    offset = FAR_ORIGIN_OFFSET if cfg.far_origin else np.zeros(3)
    scene_probe = build_scene(cfg.scene, seed=cfg.seed, length_m=10.0, **cfg.scene_params)
    speed = (
        0.0
        if cfg.stationary
        else (cfg.speed_mps if cfg.speed_mps is not None else scene_probe.speed_mps)
    )
    s0 = 30.0
    driven = s0 + speed * duration * 1.1 + 1.0
    scene = build_scene(
        cfg.scene, seed=cfg.seed, length_m=driven, origin_offset=offset, **cfg.scene_params
    )
    return scene, speed, s0, offset


#: Default per-lidar merge error (deg, m) by INS profile: real OSDaR23 clouds are merged
#: from six lidars whose extrinsics are good to a few hundredths of a degree and a
#: centimetre or two.
MERGE_ERROR_BY_PROFILE = {"osdar23": (0.03, 0.015)}


def merge_errors(cfg: SynthConfig, sensor_indices: list[int]) -> dict[int, F64]:
    """sensor_index -> (4, 4) merge error transform (deterministic in the seed)."""
    sig = cfg.lidar_merge_error
    if sig is None:
        sig = MERGE_ERROR_BY_PROFILE.get(cfg.ins_profile, (0.0, 0.0))
    rot_deg, trans_m = sig
    if rot_deg <= 0 and trans_m <= 0:
        return {}
    rng = np.random.default_rng([cfg.seed, 0x6D65726765])  # "merge"
    out = {}
    for s in sensor_indices:
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(np.radians(rot_deg) * rng.standard_normal(3)).as_matrix()
        E[:3, 3] = trans_m * rng.standard_normal(3)
        out[int(s)] = E
    return out


def _make_rig(
    cfg: SynthConfig,
    scene: Scene,
    traj: Trajectory,
    offset: F64,
    cams_full: dict[str, CameraModel],
    cams: dict[str, CameraModel],
    t0: float,
) -> _Rig:
    T_ref_S = np.eye(4)
    T_ref_S[:3, 3] = -offset
    camsim = CameraSimulator(scene, cams, seed=cfg.seed)
    sensors = default_sensors()
    lidar = LidarSimulator(
        scene.mesh,
        sensors,
        origin=traj(np.array([t0]))[0, :3, 3],
        seed=cfg.seed,
        density=cfg.lidar_density,
        merge_errors=merge_errors(cfg, [s.sensor_index for s in sensors]),
    )
    vis = LandmarkVisibility(scene.mesh, origin=traj(np.array([t0]))[0, :3, 3])
    return _Rig(scene, traj, T_ref_S, cams_full, camsim, sensors, lidar, vis)


def _write_frame(
    writer: SequenceWriter,
    cfg: SynthConfig,
    rig: _Rig,
    ft: FrameTimes,
    lm_xyz_S: F64,
    lm_pixels: dict[str, dict[str, dict[str, Any]]],
    stages: dict[str, float],
) -> None:
    """One frame: every camera's image and landmark pixels, the lidar cloud. Adds the
    seconds spent to ``stages`` (render, write, landmarks, lidar)."""
    for cname in cfg.cameras:
        T_S_base = rig.traj(np.array([ft.seconds(cname)]))[0]
        tic = time.perf_counter()
        img = rig.camsim.render(cname, T_S_base)
        stages["render"] += time.perf_counter() - tic
        tic = time.perf_counter()
        writer.write_image(
            f"/{cname}/{ft.counter:03d}_{ft.string(cname)}.png",
            img,
            compression=cfg.png_compression,
        )
        stages["write"] += time.perf_counter() - tic
        tic = time.perf_counter()
        _landmark_pixels(
            lm_pixels,
            rig.scene.landmarks,
            lm_xyz_S,
            rig.cams_full[cname],
            T_S_base,
            rig.vis,
            ft.counter,
        )
        stages["landmarks"] += time.perf_counter() - tic
    tic = time.perf_counter()
    scan = rig.lidar.scan(ft.seconds("lidar"), rig.traj)
    if cfg.lidar_blind_ahead_m > 0:
        keep = scan["x"] >= cfg.lidar_blind_ahead_m
        scan = {k: v[keep] for k, v in scan.items()}
    stages["lidar"] += time.perf_counter() - tic
    tic = time.perf_counter()
    cloud = _cloud_from_scan(scan, cfg.pcd_data)
    writer.write_pcd(f"/lidar/{ft.counter:03d}_{ft.string('lidar')}.pcd", cloud)
    stages["write"] += time.perf_counter() - tic


def _simulate_ins(cfg: SynthConfig, rig: _Rig, schedule: list[FrameTimes]) -> SimulatedIns:
    """INS for the whole sequence, at the lidar timestamps (the frame's clock)."""
    model = InsErrorModel.profile(cfg.ins_profile, seed=cfg.seed, **cfg.ins_overrides)
    t_lidar = np.array([ft.seconds("lidar") for ft in schedule])
    counters = np.array([ft.counter for ft in schedule])

    def true_ref(t: F64) -> F64:
        return rig.T_ref_S @ rig.traj(t)

    return simulate_ins(true_ref, t_lidar, counters, model, true_world=HAMBURG)


def generate(
    out: Path, cfg: SynthConfig, progress: Callable[[int, int], None] | None = None
) -> SynthResult:
    """Write a synthetic OSDaR23 sequence to ``out`` (its name is the sequence name).

    Nothing half-written is ever visible: everything goes to ``out.partial`` and is renamed
    into place at the end.
    """

    t_start = time.perf_counter()
    stages: dict[str, float] = {}
    out = Path(out)
    name = out.name
    real = _load_calibration(cfg)
    cams_full = load_cameras(real, list(cfg.cameras))
    cams = {n: c.scaled(cfg.scale) for n, c in cams_full.items()}

    schedule = frame_schedule(cfg, ["lidar", *cfg.cameras])
    t0 = cfg.start_ns / 1e9
    duration = cfg.frames * FRAME_PERIOD_NS / 1e9

    tic = time.perf_counter()
    scene, speed, s0, offset = _build_scene(cfg, duration)
    stages["scene"] = time.perf_counter() - tic
    traj = Trajectory(scene.ego, t0, speed, 0.0, s0, cfg.seed, bogies=cfg.bogies)
    tic = time.perf_counter()
    rig = _make_rig(cfg, scene, traj, offset, cams_full, cams, t0)
    stages["setup"] = time.perf_counter() - tic

    labels = _labels_skeleton(real, name, cams)
    ol = labels["openlabel"]
    lm_xyz_S = np.array([lm.xyz for lm in scene.landmarks]).reshape(-1, 3)
    lm_pixels: dict[str, dict[str, dict[str, Any]]] = {
        lm.id: {c: {} for c in cfg.cameras} for lm in scene.landmarks
    }
    stages.update({"render": 0.0, "lidar": 0.0, "write": 0.0, "landmarks": 0.0})
    writer = SequenceWriter(out, name=name)
    with writer:
        for k, ft in enumerate(schedule):
            _write_frame(writer, cfg, rig, ft, lm_xyz_S, lm_pixels, stages)
            ol["frames"][str(ft.counter)] = _frame_entry(ft, cfg.cameras)
            if progress is not None:
                progress(k + 1, len(schedule))
        ol["frame_intervals"] = frame_intervals([ft.counter for ft in schedule])

        tic = time.perf_counter()
        sim = _simulate_ins(cfg, rig, schedule)
        _write_ins(writer, sim, schedule)
        stages["ins"] = time.perf_counter() - tic

        tic = time.perf_counter()
        T_W_S = sim.world.T_world_other(HAMBURG) @ rig.T_ref_S
        _write_ground_truth(
            writer.root / "ground_truth",
            cfg,
            scene,
            traj,
            schedule,
            T_W_S,
            sim,
            rig.sensors,
            sensors_to_json,
            lm_pixels,
            cams_full,
        )
        stages["ground_truth"] = time.perf_counter() - tic
        writer.finish(labels)
    total = time.perf_counter() - t_start
    log.info(
        "synthetic sequence %s: %d frames in %.1f s (%s)",
        out,
        len(schedule),
        total,
        ", ".join(f"{k} {v:.1f}s" for k, v in stages.items()),
    )
    return SynthResult(out, len(schedule), total, stages)


def _landmark_pixels(
    store: dict,
    landmarks: list,
    xyz_S: F64,
    cam_full: CameraModel,
    T_S_base: F64,
    vis: LandmarkVisibility,
    counter: int,
) -> None:
    if len(xyz_S) == 0:
        return
    uv, ok = cam_full.project_world(xyz_S, T_S_base)
    ok &= cam_full.in_image(uv)
    if np.any(ok):
        c_S = (T_S_base @ cam_full.T_base_opt)[:3, 3]
        idx = np.flatnonzero(ok)
        ok[idx] = vis.visible(c_S, xyz_S[idx])
    for i, lm in enumerate(landmarks):
        store[lm.id][cam_full.name][str(counter)] = (
            [float(uv[i, 0]), float(uv[i, 1])] if ok[i] else None
        )


def _cloud_from_scan(scan: dict[str, np.ndarray], data: str) -> PointCloud:
    fields = {
        "x": scan["x"].astype(np.float32),
        "y": scan["y"].astype(np.float32),
        "z": scan["z"].astype(np.float32),
        "intensity": scan["intensity"].astype(np.float32),
        "timestamp": scan["timestamp"].astype(np.float64),
        "sensor_index": scan["sensor_index"].astype(np.uint8),
    }
    return PointCloud(fields=fields, header=header_for_fields(fields, data=data))


def _write_ins(writer: SequenceWriter, sim: Any, schedule: list[FrameTimes]) -> None:
    by_counter = {ft.counter: ft for ft in schedule}
    for folder, table in (
        ("novatel_oem7_inspva", sim.inspva),
        ("novatel_oem7_insstdev", sim.insstdev),
        ("novatel_oem7_corrimu", sim.corrimu),
    ):
        names = [f"{int(c):03d}_{by_counter[int(c)].string('lidar')}.csv" for c in table.frame_idx]
        writer.write_ins(folder, table, names)


def _write_ground_truth(
    gt: Path,
    cfg: SynthConfig,
    scene: Any,
    traj: Trajectory,
    schedule: list[FrameTimes],
    T_W_S: F64,
    sim: Any,
    sensors: list,
    sensors_to_json: Callable,
    lm_pixels: dict,
    cams_full: dict[str, CameraModel],
) -> None:
    gt.mkdir(parents=True, exist_ok=True)
    counters = np.array([ft.counter for ft in schedule])
    t_lidar = np.array([ft.seconds("lidar") for ft in schedule])
    T_W_base = T_W_S @ traj(t_lidar)
    PoseTrack(t_lidar, T_W_base, frame_idx=counters).to_csv(gt / "poses.csv", counters)
    # Dense truth (every 10 ms) for interpolation at any sensor's timestamp.
    t_dense = np.arange(t_lidar[0] - 0.05, t_lidar[-1] + 0.05, 0.01)
    PoseTrack(t_dense, T_W_S @ traj(t_dense)).to_csv(gt / "poses_dense.csv")
    _dump(gt / "world.json", sim.world.to_json())
    _dump(gt / "ins_to_lidar.json", sim.ins_to_lidar.to_json())
    _dump(gt / "lidar_origins.json", sensors_to_json(sensors))
    errors = merge_errors(cfg, [s.sensor_index for s in sensors])
    _dump(gt / "lidar_merge_errors.json", {str(k): v.tolist() for k, v in errors.items()})
    cl = []
    for tr in scene.tracks:
        s = np.arange(0.0, tr.length, 1.0)
        s = np.append(s, tr.length) if s[-1] < tr.length else s
        pts = transform_points(T_W_S, tr.point(s))
        cl.append(
            {
                "id": str(tr.id),
                "ego": tr is scene.ego,
                "s": s.tolist(),
                "xyz": pts.tolist(),
                "roll_rad": tr.roll(s).tolist(),
            }
        )
    _dump(gt / "centrelines.json", cl)
    lms = []
    for lm in scene.landmarks:
        xyz_W = transform_points(T_W_S, np.asarray(lm.xyz, dtype=np.float64)[None])[0]
        lms.append(
            {"id": lm.id, "kind": lm.kind, "xyz": xyz_W.tolist(), "pixels": lm_pixels[lm.id]}
        )
    _dump(gt / "landmarks.json", lms)
    t_, q_ = T_to_pose(T_W_S)
    _dump(
        gt / "meta.json",
        {
            "generator": "osdar-ar synth",
            "scene": cfg.scene,
            "seed": cfg.seed,
            "frames": len(schedule),
            "scale": cfg.scale,
            "cameras_full_resolution": {n: c.to_json() for n, c in cams_full.items()},
            # the cameras are pinholes rendered at the frame's instant: no defocus, no
            # motion blur (the augmentation's RenderSpec exposure_ms / aperture_mm)
            "camera_optics": {"exposure_s": 0.0, "aperture_m": 0.0},
            "stationary": cfg.stationary,
            "far_origin": cfg.far_origin,
            "dropped_frames": list(cfg.dropped_frames),
            "ins_dropped_frames": [int(x) for x in sim.dropped_frames],
            "ins_profile": cfg.ins_profile,
            "ins_model": json.loads(
                InsErrorModel.profile(
                    cfg.ins_profile, seed=cfg.seed, **cfg.ins_overrides
                ).model_dump_json()
            ),
            "speed_mps": traj.speed,
            "lidar_density": cfg.lidar_density,
            "lidar_merge_error": cfg.lidar_merge_error,
            "lidar_blind_ahead_m": cfg.lidar_blind_ahead_m,
            "bogies": None if cfg.bogies is None else list(cfg.bogies),
            "T_world_scene": {"translation": t_.tolist(), "quaternion": q_.tolist()},
            "pixel_convention": "OpenCV: integer coordinates at pixel centres, full resolution",
        },
    )


def _dump(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=1))


__all__ = [
    "SynthConfig",
    "SynthResult",
    "Trajectory",
    "default_calibration_path",
    "frame_schedule",
    "generate",
    "ns_to_string",
]
