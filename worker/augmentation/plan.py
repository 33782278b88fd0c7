"""Planning an augmentation: everything frame-independent, done once per job.

The objects' meshes and their levels of detail, their placements (a moving object's pose
at every sensor timestamp), the proxies, the lighting per camera and the vehicle pose at
every sensor timestamp, collected in a :class:`Plan`; each object in a
:class:`PlannedObject`.
"""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel, load_cameras
from geometry.transforms import transform_points
from renderer.assets import MeshError, build_obstacle, choose_detail, load_user_mesh, simplify
from renderer.assets.lod import FACES_PER_PX
from renderer.assets.walk_cycle import WALKERS, gait_phase_of, gait_pose
from renderer.lidar_cast import LidarNoise, origins_from_json
from renderer.lighting import Lighting, estimate_lighting, sun_dir_enu
from renderer.mesh import ObjectMesh, ProxyMesh
from worker.augmentation.confidence import placement_bounds
from worker.augmentation.gauge import GaugeLabel, gauge_labels, gauge_labels_moving
from worker.augmentation.lidar_noise import measure_key_noise, noise_key_spheres
from worker.augmentation.motion import MovingPoses, moving_poses
from worker.augmentation.placement import (
    RAIL_HEIGHT_ABOVE_BED,
    ResolvedPlacement,
    resolve_placement,
)
from worker.augmentation.proxies import build_proxies
from worker.augmentation.spec import AugmentSpec, ObjectSource, SceneObject
from worker.osdar.sequence import Sequence

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Near plane of the cameras' renders (m): nearer geometry is clipped.
NEAR_PLANE_M = 0.05

#: The camera images the plan decoded for the lighting (path -> (H, W, 3) uint8 in OpenCV's
#: BGR order), for this process's frames stage to take instead of decoding them again
#: (:func:`take_decoded`); emptied by each plan and by :func:`drop_decoded`.
_DECODED: dict[str, NDArray[np.uint8]] = {}


def take_decoded(path: str | Path) -> NDArray[np.uint8] | None:
    """The (H, W, 3) uint8 BGR image of ``path`` the plan decoded in this process, handed
    out once (None: decode the file)."""
    return _DECODED.pop(str(Path(path).resolve()), None)


def drop_decoded() -> None:
    """Forget the images the plan decoded (the frames stage is over)."""
    _DECODED.clear()


class AugmentError(ValueError):
    """A spec the sequence cannot honour (unknown object, camera missing, placement...)."""


# ---------------------------------------------------------------------------- the plan
@dataclass
class PlannedObject:
    """One object of a plan (stored in the plan's record: records.py).

    index : its place in the spec's objects; obj_class : the class annotated;
    seed : what its annotation UUIDs are derived from (the same job, the same UUIDs).
    obj_full / obj_render : the mesh (lidar, cuboid) and its level of detail for the
    cameras, in the rest pose (a walking person is posed per frame: :meth:`mesh`).
    T_world_obj : (4, 4) its pose at the first frame of the range (lidar clock); a
    static object's only pose.
    poses : a moving object's stream -> frame -> (4, 4) pose at that stream's timestamp
    of the frame; None: static.
    phases : stream -> frame -> walk-cycle phase (rad) of a walking person or animal
    (renderer/assets/walk_cycle.py); None: rigid.
    velocity_world : frame -> (3,) m/s over the ground at the lidar timestamp (a moving
    object's; empty: static).
    gauge : frame -> the object against the train's clearance envelope (gauge.py).
    placement_bounds : frame -> camera -> 90 % bound (px) on the placement error.
    """

    index: int
    obj_class: str
    seed: str
    obj_full: ObjectMesh
    obj_render: ObjectMesh
    T_world_obj: F64
    placement: dict[str, Any]
    poses: dict[str, dict[int, F64]] | None = None
    phases: dict[str, dict[int, float]] | None = None
    velocity_world: dict[int, F64] = field(default_factory=dict)
    gauge: dict[int, GaugeLabel] = field(default_factory=dict)
    placement_bounds: dict[int, dict[str, float]] = field(default_factory=dict)

    @property
    def moving(self) -> bool:
        return self.poses is not None

    def pose(self, stream: str, frame: int) -> F64:
        """(4, 4) T_world_obj at ``stream``'s timestamp of ``frame``."""
        if self.poses is None:
            return self.T_world_obj
        return self.poses[stream][frame]

    def mesh(self, stream: str, frame: int, *, full: bool) -> ObjectMesh:
        """The mesh (full or the cameras' level of detail) as it is at ``stream``'s
        timestamp of ``frame`` (a walking person posed, else the rest mesh)."""
        base = self.obj_full if full else self.obj_render
        if self.phases is None:
            return base
        return gait_pose(base, self.phases[stream][frame])

    def velocity(self, frame: int) -> F64:
        """(3,) world velocity (m/s) at the lidar timestamp of ``frame``."""
        v = self.velocity_world.get(frame)
        return np.zeros(3) if v is None else np.asarray(v, dtype=np.float64)


@dataclass
class Plan:
    """Everything frame-independent of one augmentation (stored as a record: records.py).

    frames : the frame indices to augment (the spec's range); all_frames : every frame.
    uris : frame -> stream -> uri (relative to the sequence folder).
    T_world_base : stream -> frame -> (4, 4) vehicle pose at that stream's timestamp.
    objects : the objects (:class:`PlannedObject`, at least one); proxies : world frame.
    lights, pixel_offsets : per camera; speed_mps : frame -> vehicle speed.
    lidar_origins : {sensor_index: (3,)} or (3,) base-frame ray origins, None: no lidar.
    lidar_noise_keys : frame -> the key frame whose lidar noise it uses; lidar_noise : key
    frame -> {sensor_index: LidarNoise} (both empty when the spec's render.lidar_noise is
    off or there is no lidar: :mod:`.lidar_noise`); lidar_noise_spheres : key frame ->
    (k, 4) the objects' bounding spheres (centre, radius; base frame) its estimate is
    measured around, for the keys measured after the plan (:func:`.lidar_noise.key_noise`:
    the plan is then made with ``measure_noise=False``); lidar_noise_dir : a folder where
    those estimates are shared between processes ("" for none).

    ``T_world_obj``, ``obj_full``, ``obj_render``, ``obj_class``, ``placement``,
    ``gauge`` and ``placement_bounds`` are the first object's (single-object readers).
    """

    seq_folder: str
    spec: AugmentSpec
    frames: list[int]
    all_frames: list[int]
    cameras: dict[str, CameraModel]
    lidar_stream: str | None
    uris: dict[int, dict[str, str]]
    T_world_base: dict[str, dict[int, F64]]
    objects: list[PlannedObject]
    proxies: ProxyMesh
    lights: dict[str, Lighting]
    pixel_offsets: dict[str, tuple[float, float]]
    speed_mps: dict[int, float]
    lidar_origins: dict[int, F64] | F64 | None
    labels_name: str
    lidar_noise_keys: dict[int, int] = field(default_factory=dict)
    lidar_noise: dict[int, dict[int, LidarNoise]] = field(default_factory=dict)
    lidar_noise_spheres: dict[int, F64] = field(default_factory=dict)
    lidar_noise_dir: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def T_world_obj(self) -> F64:
        return self.objects[0].T_world_obj

    @property
    def obj_full(self) -> ObjectMesh:
        return self.objects[0].obj_full

    @property
    def obj_render(self) -> ObjectMesh:
        return self.objects[0].obj_render

    @property
    def obj_class(self) -> str:
        return self.objects[0].obj_class

    @property
    def placement(self) -> dict[str, Any]:
        return self.objects[0].placement

    @property
    def gauge(self) -> dict[int, GaugeLabel]:
        return self.objects[0].gauge

    @property
    def placement_bounds(self) -> dict[int, dict[str, float]]:
        return self.objects[0].placement_bounds

    @property
    def annotation_stream(self) -> str:
        """The stream whose timestamps the annotations (cuboids, gauge) use: the lidar,
        else the first camera."""
        return self.lidar_stream or next(iter(self.cameras))


# ---------------------------------------------------------------------------- planning
def sequence(seq_folder: str | Path) -> Any:

    return Sequence.open(seq_folder)


def _frame_times(seq: Any, stream: str) -> dict[int, float]:
    ts = seq.timestamps(stream)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


def load_object(source: ObjectSource | AugmentSpec) -> ObjectMesh:
    """An object's mesh at full detail (an AugmentSpec: its first object's). Raises
    AugmentError (unknown name, bad mesh file)."""

    o = source if isinstance(source, ObjectSource) else source.scene_objects[0].object
    try:
        if o.builtin is not None:
            mesh = build_obstacle(o.builtin, seed=o.seed, detail=o.detail, scale=o.scale,
                                  pose=o.pose)  # fmt: skip
        else:
            if o.mesh_path is not None:
                path = Path(o.mesh_path)
                if not path.is_file():
                    raise AugmentError(f"mesh file {path} not found")
                data, ftype = path.read_bytes(), o.file_type or path.suffix.lstrip(".")
            else:
                data, ftype = o.mesh_bytes or b"", o.file_type or ""
            mesh = load_user_mesh(data, ftype, scale=o.mesh_scale, up=o.up, name=o.class_name,
                                  animation_time_s=o.animation_time_s)  # fmt: skip
            if o.scale != 1.0:
                mesh.vertices = mesh.vertices * o.scale
    except (MeshError, ValueError) as exc:
        if isinstance(exc, AugmentError):
            raise
        raise AugmentError(f"object: {exc}") from exc
    mesh.name = o.class_name
    return mesh


def _lidar_origins(spec: AugmentSpec) -> dict[int, F64] | F64:

    v = spec.origins_value()
    if v == "single":
        return np.zeros(3)
    if isinstance(v, tuple):
        return np.asarray(v, dtype=np.float64)
    path = Path(v)
    try:
        return origins_from_json(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise AugmentError(f"lidar origins {path}: {exc}") from exc


def _projected_height_px(
    cams: dict[str, CameraModel], poses: dict[str, dict[int, F64]], p_world: F64, height: float
) -> float:
    """Largest image height (px) of an object ``height`` m tall at ``p_world`` (3,) over
    all frames and cameras where it is in front (the level-of-detail driver)."""
    best = 0.0
    for name, cam in cams.items():
        T = np.stack(list(poses[name].values()))
        c = (T @ cam.T_base_opt)[:, :3, 3]
        z_axis = (T @ cam.T_base_opt)[:, :3, 2]
        depth = np.einsum("ij,ij->i", p_world[None] - c, z_axis)
        front = depth > NEAR_PLANE_M
        if np.any(front):
            best = max(best, float(cam.fx * height / max(depth[front].min(), 0.5)))
    return best


def _pixel_offsets(prepared: Any, cams: dict[str, CameraModel]) -> dict[str, tuple[float, float]]:
    """Mean (click - projection) of the calibration point per camera, at image scale."""
    out = {c: (0.0, 0.0) for c in cams}
    cal = getattr(prepared, "calibration", None)
    if cal is None or cal.mode != "clicks":
        return out
    for name, cam in cams.items():
        d = [
            np.subtract(o["click"], o["projected"])
            for o in cal.observations
            if o.get("camera") == name and o.get("inlier") and o.get("projected") is not None
        ]
        if d:
            res = cal.resolution.get(name)
            s = cam.width / res[0] if res else cam.scale
            m = np.mean(d, axis=0) * s
            out[name] = (float(m[0]), float(m[1]))
    return out


def _speeds(track: Any, times: dict[int, float]) -> dict[int, float]:
    """Vehicle speed (m/s) per frame from the pose track (central difference, 50 ms)."""
    out = {}
    for f, t in times.items():
        try:
            T = track.interpolate(np.array([t - 0.05, t + 0.05]), max_extrapolation_s=0.2)
        except ValueError:
            out[f] = 0.0
            continue
        out[f] = float(np.linalg.norm(T[1, :3, 3] - T[0, :3, 3]) / 0.1)
    return out


@dataclass
class _Opened:
    """The opened sequence as the plan needs it: cameras, frames and the vehicle's poses."""

    cam_names: list[str]
    cams: dict[str, CameraModel]
    lidar_stream: str | None
    all_frames: list[int]
    frames: list[int]
    uris: dict[int, dict[str, str]]
    lidar_times: dict[int, float]  # the frames' clock (the first camera's without lidar)
    poses: dict[str, dict[int, F64]]
    times: dict[str, dict[int, float]]  # stream -> frame -> timestamp (s)


def _frames_in_range(spec: AugmentSpec, all_frames: list[int]) -> list[int]:
    if spec.frame_range is None:
        return all_frames
    a, b = spec.frame_range
    frames = [f for f in all_frames if a <= f <= b]
    if not frames:
        raise AugmentError(
            f"frame_range [{a}, {b}] holds no frame of the sequence "
            f"({all_frames[0]}..{all_frames[-1]})"
        )
    return frames


def _open(seq: Any, spec: AugmentSpec, track: Any, warnings: list[str]) -> _Opened:
    """Cameras, frames, uris and the vehicle pose at every stream's timestamps."""
    try:
        cam_names = spec.camera_names(seq.cameras)
        cams = load_cameras(seq.labels.raw, cam_names)
    except ValueError as exc:
        raise AugmentError(f"{seq.folder}: {exc}") from exc
    lidar_stream = seq.lidar_stream if spec.lidar else None
    if spec.lidar and lidar_stream is None:
        warnings.append("the sequence has no lidar files: lidar not augmented")
    all_frames = seq.frame_indices
    frames = _frames_in_range(spec, all_frames)
    uris = {fr.index: {name: fs.uri for name, fs in fr.streams.items()} for fr in seq.labels.frames}
    lidar_times = _frame_times(seq, seq.lidar_stream) if seq.lidar_stream else {}
    if not lidar_times:  # no lidar: the first camera's clock numbers the frames
        lidar_times = _frame_times(seq, cam_names[0])
    streams = {c: _frame_times(seq, c) for c in cam_names}
    if lidar_stream is not None:
        streams[lidar_stream] = lidar_times
    try:
        poses = {
            s: dict(zip(ft, track.interpolate(np.array(list(ft.values()))), strict=True))
            for s, ft in streams.items()
        }
    except ValueError as exc:
        raise AugmentError(f"the prepared poses do not cover the frames: {exc}") from exc
    return _Opened(
        cam_names, cams, lidar_stream, all_frames, frames, uris, lidar_times, poses, streams
    )


@dataclass
class _Placed:
    """One object placed: static (``resolved``) or moving (``moving``: the poses at
    ``stream_frames``, stream by stream in the order of ``view.times``)."""

    resolved: ResolvedPlacement | None
    moving: MovingPoses | None = None
    stream_frames: list[tuple[str, int]] = field(default_factory=list)

    @property
    def T_first(self) -> F64:
        """The pose at the first frame of the range (the first row is the lidar clock's)."""
        if self.moving is not None:
            return self.moving.T_world_obj[0]
        assert self.resolved is not None
        return self.resolved.T_world_obj


def _stream_times(view: _Opened) -> tuple[list[tuple[str, int]], F64]:
    """Every (stream, frame) of the range with its timestamp; the lidar clock's first
    frame first (the reference pose of a moving object)."""
    clock = view.lidar_stream if view.lidar_stream is not None else view.cam_names[0]
    order = [clock] + [st for st in view.times if st != clock]
    pairs = [(st, f) for st in order for f in view.frames if f in view.times[st]]
    return pairs, np.array([view.times[st][f] for st, f in pairs])


def _place_one(
    so: SceneObject,
    obj: ObjectMesh,
    prepared: Any,
    view: _Opened,
    proxies: ProxyMesh | None,
    poles: list[Any],
) -> _Placed:
    """An object's pose(s): snapped onto ``proxies`` (None: nominal) and clear of poles."""
    t_first = view.lidar_times[view.frames[0]]
    if so.motion is not None:
        pairs, times = _stream_times(view)
        got = moving_poses(so.motion, obj, ego=prepared.ego, track=prepared.track,
                           t_first=t_first, times=times, proxies=proxies, poles=poles)  # fmt: skip
        return _Placed(None, got, pairs)
    kw = {"ego": prepared.ego, "track": prepared.track, "frame_times": view.lidar_times,
          "poles": poles, "obj": obj}  # fmt: skip
    return _Placed(resolve_placement(so.placement.to_spec(), proxies=proxies, **kw))


def _place(
    spec: AugmentSpec, prepared: Any, objs: list[ObjectMesh], view: _Opened
) -> tuple[list[_Placed], ProxyMesh]:
    """Placement: nominal points -> proxies around all of them -> snapped onto the
    proxies, poles checked, object by object."""
    scene = spec.scene_objects
    pairs = list(zip(scene, objs, strict=True))
    nominal = [_place_one(so, o, prepared, view, None, []) for so, o in pairs]
    cam_xyz = np.concatenate(
        [
            np.stack(
                [
                    (T @ view.cams[c].T_base_opt)[:3, 3]
                    for f, T in view.poses[c].items()
                    if f in view.frames
                ]
            )
            for c in view.cam_names
        ]
    )
    extra = [n.moving.T_world_obj[:, :3, 3] for n in nominal if n.moving is not None]
    extra += [n.T_first[None, :3, 3] for n in nominal[1:]]
    first, so0 = nominal[0], scene[0]
    p0 = first.T_first[:3, 3]
    nominal_surface = first.resolved.surface if first.resolved is not None else "nominal"
    offset0 = so0.placement.offset if so0.motion is None else float(so0.motion.path[0][1])
    on_bed = so0.placement.mode == "track" if so0.motion is None else so0.motion.mode == "track"
    ground_z = p0[2] - (0.0 if nominal_surface == "nominal" and on_bed and abs(offset0) < 1
                        else RAIL_HEIGHT_ABOVE_BED)  # fmt: skip
    proxies = build_proxies(prepared, p0, np.concatenate([cam_xyz, *extra]), ground_z=ground_z)
    poles = list(prepared.poles)
    placed = [_place_one(so, o, prepared, view, proxies, poles) for so, o in pairs]
    return placed, proxies


def _footprints_overlap(objs: list[ObjectMesh], placed: list[_Placed]) -> list[str]:
    """Warnings for pairs of objects whose bounding boxes overlap at the first frame."""
    out = []
    boxes = []
    for o, pl in zip(objs, placed, strict=True):
        q = transform_points(pl.T_first, o.vertices[:: max(1, len(o.vertices) // 2000)])
        boxes.append((q.min(axis=0), q.max(axis=0)))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            lo = np.maximum(boxes[i][0], boxes[j][0])
            hi = np.minimum(boxes[i][1], boxes[j][1])
            if np.all(hi > lo):
                out.append(f"objects {i} and {j} overlap at the first frame: they intersect")
    return out


def _level_of_detail(obj: ObjectMesh, view: _Opened, positions: F64) -> tuple[ObjectMesh, float]:
    """The mesh the cameras render, simplified for the largest projected height (px) over
    the frames (and, for a moving object, over its ``positions`` (k, 3)), and that
    height."""
    in_range = {
        c: {f: view.poses[c][f] for f in view.frames if f in view.poses[c]} for c in view.cam_names
    }
    up = np.array([0.0, 0.0, 0.5 * obj.size[2]])
    h_px = max(
        _projected_height_px(view.cams, in_range, p + up, float(obj.size[2])) for p in positions
    )
    budget = choose_detail(h_px, float(obj.meta.get("lod_faces_per_px", FACES_PER_PX)))
    obj_render = simplify(obj, budget) if budget < len(obj.faces) else obj
    return obj_render, h_px


def _lights(
    spec: AugmentSpec, prepared: Any, seq: Any, view: _Opened, warnings: list[str]
) -> dict[str, Lighting]:
    """Lighting per camera from its first frame of the range (sun by ephemeris if asked);
    the images are kept for the frames stage (:func:`take_decoded`)."""
    sun = None
    if spec.render.sun == "ephemeris":
        w = prepared.world
        sun = sun_dir_enu(w.latitude_deg, w.longitude_deg, view.lidar_times[view.frames[0]])
        if sun[2] < 0.02:
            warnings.append("the sun is below the horizon at the sequence's time: no shadow")
    lights = {}
    for c in view.cam_names:
        f0 = next(f for f in view.frames if f in view.poses[c])
        img = seq.image(f0, c)
        if img.ndim == 2:
            raise AugmentError(f"camera {c} has grey images: only colour cameras are augmented")
        _DECODED[str(seq.image_path(f0, c).resolve())] = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        lights[c] = estimate_lighting(img, view.cams[c], view.poses[c][f0], sun_dir_world=sun)
    return lights


def _render_offsets(
    spec: AugmentSpec, prepared: Any, cams: dict[str, CameraModel], warnings: list[str]
) -> dict[str, tuple[float, float]]:
    """The calibration's pixel offsets if asked; warnings for what the render ignores."""
    offsets = _pixel_offsets(prepared, cams) if spec.render.pixel_offset else {}
    if spec.render.pixel_offset and not any(any(v) for v in offsets.values()):
        warnings.append("pixel_offset asked but the preparation has no clicked calibration")
    if spec.render.scale != 1.0:
        warnings.append(
            f"render.scale {spec.render.scale} ignored: the output keeps the input resolution"
        )
    return offsets


class _Parts(NamedTuple):
    """What :func:`_plan_objects` gives the plan."""

    planned: list[PlannedObject]
    proxies: ProxyMesh
    origins: dict[int, F64] | F64 | None
    offsets: dict[str, tuple[float, float]]
    noise_keys: dict[int, int]
    noise: dict[int, dict[int, LidarNoise]]
    noise_spheres: dict[int, F64]


def _timed_lights(
    spec: AugmentSpec, prepared: Any, seq: Any, view: _Opened, warnings: list[str]
) -> tuple[dict[str, Lighting], float]:
    tic = time.perf_counter()
    return _lights(spec, prepared, seq, view, warnings), time.perf_counter() - tic


def _plan_objects(
    seq_folder: str | Path,
    spec: AugmentSpec,
    prepared: Any,
    view: _Opened,
    warnings: list[str],
    timings: dict[str, float],
    measure_noise: bool = True,
) -> _Parts:
    """The objects loaded, placed and planned, the proxies, the lidar origins, the render
    offsets and the lidar noise at key frames (the plan's parts that need the objects;
    without ``measure_noise`` the key frames and their spheres only)."""
    tic = time.perf_counter()
    objs = []
    for i, so in enumerate(spec.scene_objects):
        try:
            objs.append(load_object(so.object))
        except AugmentError as exc:
            raise AugmentError(f"objects[{i}]: {exc}" if len(spec.scene_objects) > 1
                               else str(exc)) from exc  # fmt: skip
    timings["object"] = time.perf_counter() - tic

    tic = time.perf_counter()
    placed, proxies = _place(spec, prepared, objs, view)
    warnings += _footprints_overlap(objs, placed)
    timings["placement"] = time.perf_counter() - tic

    offsets = _render_offsets(spec, prepared, view.cams, warnings)
    origins = _lidar_origins(spec) if view.lidar_stream is not None else None
    tic = time.perf_counter()
    planned = [
        _planned_object(i, so, obj, pl, spec, prepared, view, Path(seq_folder).name)
        for i, (so, obj, pl) in enumerate(zip(spec.scene_objects, objs, placed, strict=True))
    ]
    timings["objects"] = time.perf_counter() - tic
    tic = time.perf_counter()
    noise_keys: dict[int, int] = {}
    noise: dict[int, dict[int, LidarNoise]] = {}
    spheres: dict[int, F64] = {}
    if origins is not None and view.lidar_stream is not None and spec.render.lidar_noise:
        noise_keys, spheres = noise_key_spheres(
            view.uris, view.lidar_stream, view.frames, planned, view.poses[view.lidar_stream]
        )
        if measure_noise:
            noise = {
                k: measure_key_noise(seq_folder, view.uris[k][view.lidar_stream], origins, sp)
                for k, sp in spheres.items()
            }
            spheres = {}
    timings["lidar_noise"] = time.perf_counter() - tic
    return _Parts(planned, proxies, origins, offsets, noise_keys, noise, spheres)


def plan_augmentation(
    seq_folder: str | Path, spec: AugmentSpec, prepared: Any, *, measure_noise: bool = True
) -> Plan:
    """Everything frame-independent (module docstring). Raises AugmentError /
    PlacementError with a message saying what and where. ``measure_noise=False`` leaves
    the lidar noise's key frames to be measured later (:func:`.lidar_noise.key_noise`:
    by a pool's parent while its children start on the first frames)."""

    timings: dict[str, float] = {}
    warnings: list[str] = []
    drop_decoded()
    tic = time.perf_counter()
    seq = sequence(seq_folder)
    view = _open(seq, spec, prepared.track, warnings)
    timings["open"] = time.perf_counter() - tic

    # the lighting (decoding each camera's first image) in a thread beside the objects,
    # the placement and the lidar noise: the plan is the job's serial part
    light_warnings: list[str] = []
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="plan-lighting") as ex:
        lighting = ex.submit(_timed_lights, spec, prepared, seq, view, light_warnings)
        planned, proxies, origins, offsets, noise_keys, noise, spheres = _plan_objects(
            seq_folder, spec, prepared, view, warnings, timings, measure_noise
        )
        lights, timings["lighting"] = lighting.result()
    warnings += light_warnings

    for po in planned:
        log.info(
            "plan: %s at %s (%s), %d/%d faces (%.0f px high at most)%s",
            po.obj_class, np.round(po.T_world_obj[:3, 3], 2).tolist(),
            po.placement.get("surface"), len(po.obj_render.faces), len(po.obj_full.faces),
            po.placement.get("projected_height_px_max", 0.0), ", moving" if po.moving else "",
        )  # fmt: skip
    first = planned[0]
    return Plan(
        seq_folder=str(Path(seq_folder)),
        spec=spec,
        frames=view.frames,
        all_frames=view.all_frames,
        cameras=view.cams,
        lidar_stream=view.lidar_stream,
        uris=view.uris,
        T_world_base=view.poses,
        objects=planned,
        proxies=proxies,
        lights=lights,
        pixel_offsets=offsets,
        speed_mps=_speeds(prepared.track, view.lidar_times),
        lidar_origins=origins,
        labels_name=seq.labels_path.name,
        lidar_noise_keys=noise_keys,
        lidar_noise=noise,
        lidar_noise_spheres=spheres,
        timings=timings,
        warnings=warnings,
        info={
            "object_faces": len(first.obj_full.faces),
            "render_faces": len(first.obj_render.faces),
            "projected_height_px_max": first.placement.get("projected_height_px_max"),
            "object_size_m": first.obj_full.size.tolist(),
            "objects": len(planned),
            "proxy_faces": len(proxies.faces),
            "strategy": getattr(prepared, "strategy", ""),
            "world": prepared.world.to_json(),
        },
    )


def _planned_object(
    index: int,
    so: SceneObject,
    obj: ObjectMesh,
    pl: _Placed,
    spec: AugmentSpec,
    prepared: Any,
    view: _Opened,
    seq_name: str,
) -> PlannedObject:
    """One object's plan: its poses per stream, level of detail, walk-cycle phases,
    velocities, gauge labels and placement bounds."""
    clock = view.lidar_stream or view.cam_names[0]
    poses: dict[str, dict[int, F64]] | None = None
    phases: dict[str, dict[int, float]] | None = None
    velocity: dict[int, F64] = {}
    if pl.moving is not None:
        assert so.motion is not None
        mv = pl.moving
        poses, walked = {}, {}
        for k, (st, f) in enumerate(pl.stream_frames):
            poses.setdefault(st, {})[f] = mv.T_world_obj[k]
            walked.setdefault(st, {})[f] = float(mv.walked_m[k])
            if st == clock:
                velocity[f] = mv.velocity_world[k]
        # a built-in person standing or walking, or a built-in animal, walks
        walks = obj.meta.get("class") in WALKERS and obj.meta.get("pose", "standing") in (
            "standing",
            "walking",
        )
        if so.motion.gait and so.object.builtin is not None and walks:
            phases = {
                st: {f: gait_phase_of(obj, d) for f, d in per.items()} for st, per in walked.items()
            }
        positions = mv.T_world_obj[:: max(1, len(mv.T_world_obj) // 8), :3, 3]
        surface = "proxy"
        placement: dict[str, Any] = {
            "surface": surface,
            "s": None if mv.s_offset is None else float(mv.s_offset[0, 0]),
            "lateral": None if mv.s_offset is None else float(mv.s_offset[0, 1]),
            "xyz": mv.T_world_obj[0, :3, 3].tolist(),
            "motion": so.motion.model_dump(mode="json"),
        }
    else:
        assert pl.resolved is not None
        r = pl.resolved
        positions = r.T_world_obj[None, :3, 3]
        placement = {"surface": r.surface, "s": r.s, "lateral": r.lateral, **r.info}
    placement["spec"] = so.placement.model_dump(mode="json")
    obj_render, h_px = _level_of_detail(obj, view, positions)
    placement["projected_height_px_max"] = h_px
    T0 = pl.T_first
    seed = (
        f"osdar-ar/{seq_name}/{so.object.class_name}/"
        + ",".join(f"{v:.3f}" for v in T0[:3, 3])
        + (f"#{index}" if index else "")
    )
    po = PlannedObject(
        index=index, obj_class=so.object.class_name, seed=seed, obj_full=obj,
        obj_render=obj_render, T_world_obj=T0, placement=placement, poses=poses,
        phases=phases, velocity_world=velocity,
    )  # fmt: skip
    po.gauge = _gauge(spec, prepared, po, view)
    po.placement_bounds = _bounds(prepared, po, view)
    return po


def _gauge(
    spec: AugmentSpec, prepared: Any, po: PlannedObject, view: _Opened
) -> dict[int, GaugeLabel]:
    """The gauge label per frame of the range, at the poses the annotations use (the
    lidar's, else the first camera's); a moving object measured in every frame."""
    stream = view.lidar_stream or view.cam_names[0]
    poses = {f: view.poses[stream][f] for f in view.frames if f in view.poses[stream]}
    if not po.moving:
        p_world = transform_points(po.T_world_obj, po.obj_full.vertices)
        return gauge_labels(prepared.ego, p_world, poses, spec.gauge)
    pts = {
        f: transform_points(po.pose(stream, f), po.mesh(stream, f, full=True).vertices)
        for f in poses
    }
    return gauge_labels_moving(prepared.ego, pts, poses, spec.gauge)


def _bounds(prepared: Any, po: PlannedObject, view: _Opened) -> dict[int, dict[str, float]]:
    """The per-frame 90 % placement bounds (confidence.py) at the object's position in
    each frame (a moving object's moves)."""
    info = getattr(prepared, "information", None)
    if not po.moving:
        return placement_bounds(prepared.track, info, view.cams, view.poses, po.T_world_obj,
                                view.frames)  # fmt: skip
    stream = view.lidar_stream or view.cam_names[0]
    out: dict[int, dict[str, float]] = {}
    for f in view.frames:
        if f in view.poses[stream]:
            out.update(placement_bounds(prepared.track, info, view.cams, view.poses,
                                        po.pose(stream, f), [f]))  # fmt: skip
    return out
