"""Planning an augmentation: everything frame-independent, done once per job.

The object mesh and its level of detail, the placement, the proxies, the lighting per
camera and the vehicle pose at every sensor timestamp, collected in a :class:`Plan`.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel, load_cameras
from geometry.transforms import transform_points
from renderer.assets import MeshError, build_obstacle, choose_detail, load_user_mesh, simplify
from renderer.assets.lod import FACES_PER_PX
from renderer.lidar_cast import origins_from_json
from renderer.lighting import Lighting, estimate_lighting, sun_dir_enu
from renderer.mesh import ObjectMesh, ProxyMesh
from worker.augmentation.confidence import placement_bounds
from worker.augmentation.gauge import GaugeLabel, gauge_labels
from worker.augmentation.placement import (
    RAIL_HEIGHT_ABOVE_BED,
    ResolvedPlacement,
    resolve_placement,
)
from worker.augmentation.proxies import build_proxies
from worker.augmentation.spec import AugmentSpec
from worker.osdar.sequence import Sequence

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Near plane of the cameras' renders (m): nearer geometry is clipped.
NEAR_PLANE_M = 0.05


class AugmentError(ValueError):
    """A spec the sequence cannot honour (unknown object, camera missing, placement...)."""


# ---------------------------------------------------------------------------- the plan
@dataclass
class Plan:
    """Everything frame-independent of one augmentation (stored as a record: records.py).

    frames : the frame indices to augment (the spec's range); all_frames : every frame.
    uris : frame -> stream -> uri (relative to the sequence folder).
    T_world_base : stream -> frame -> (4, 4) vehicle pose at that stream's timestamp.
    T_world_obj : (4, 4) the object's pose; obj_full / obj_render : the mesh (lidar,
    cuboid) and its level of detail for the cameras; proxies : world frame.
    lights, pixel_offsets : per camera; speed_mps : frame -> vehicle speed.
    lidar_origins : {sensor_index: (3,)} or (3,) base-frame ray origins, None: no lidar.
    """

    seq_folder: str
    spec: AugmentSpec
    frames: list[int]
    all_frames: list[int]
    cameras: dict[str, CameraModel]
    lidar_stream: str | None
    uris: dict[int, dict[str, str]]
    T_world_base: dict[str, dict[int, F64]]
    T_world_obj: F64
    placement: dict[str, Any]
    obj_full: ObjectMesh
    obj_render: ObjectMesh
    obj_class: str
    proxies: ProxyMesh
    lights: dict[str, Lighting]
    pixel_offsets: dict[str, tuple[float, float]]
    speed_mps: dict[int, float]
    lidar_origins: dict[int, F64] | F64 | None
    labels_name: str
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    #: frame -> camera -> 90 % bound (px) on the placement error (confidence.py)
    placement_bounds: dict[int, dict[str, float]] = field(default_factory=dict)
    #: frame -> the object against the train's clearance envelope (gauge.py; {}: no ego)
    gauge: dict[int, GaugeLabel] = field(default_factory=dict)


# ---------------------------------------------------------------------------- planning
def sequence(seq_folder: str | Path) -> Any:

    return Sequence.open(seq_folder)


def _frame_times(seq: Any, stream: str) -> dict[int, float]:
    ts = seq.timestamps(stream)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


def load_object(spec: AugmentSpec) -> ObjectMesh:
    """The spec's object mesh at full detail. Raises AugmentError (unknown name, bad
    mesh file)."""

    o = spec.object
    try:
        if o.builtin is not None:
            mesh = build_obstacle(o.builtin, seed=o.seed, detail=o.detail, scale=o.scale)
        else:
            if o.mesh_path is not None:
                path = Path(o.mesh_path)
                if not path.is_file():
                    raise AugmentError(f"mesh file {path} not found")
                data, ftype = path.read_bytes(), o.file_type or path.suffix.lstrip(".")
            else:
                data, ftype = o.mesh_bytes or b"", o.file_type or ""
            mesh = load_user_mesh(data, ftype, scale=o.mesh_scale, up=o.up, name=o.class_name)
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
    return _Opened(cam_names, cams, lidar_stream, all_frames, frames, uris, lidar_times, poses)


def _place(
    spec: AugmentSpec, prepared: Any, obj: ObjectMesh, view: _Opened
) -> tuple[ResolvedPlacement, ProxyMesh]:
    """Placement: nominal point -> proxies around it -> snapped onto them, poles checked."""
    kw = {
        "ego": prepared.ego,
        "track": prepared.track,
        "frame_times": view.lidar_times,
        "poles": [],
        "obj": obj,
    }
    nominal = resolve_placement(spec.placement.to_spec(), proxies=None, **kw)
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
    p0 = nominal.T_world_obj[:3, 3]
    ground_z = p0[2] - (0.0 if nominal.surface == "nominal" and abs(spec.placement.offset) < 1
                        else RAIL_HEIGHT_ABOVE_BED)  # fmt: skip
    proxies = build_proxies(prepared, p0, cam_xyz, ground_z=ground_z)
    kw["poles"] = list(prepared.poles)
    placed: ResolvedPlacement = resolve_placement(spec.placement.to_spec(), proxies=proxies, **kw)
    return placed, proxies


def _level_of_detail(obj: ObjectMesh, view: _Opened, T_world_obj: F64) -> tuple[ObjectMesh, float]:
    """The mesh the cameras render, simplified for the largest projected height (px) over
    the frames, and that height."""
    in_range = {
        c: {f: view.poses[c][f] for f in view.frames if f in view.poses[c]} for c in view.cam_names
    }
    h_px = _projected_height_px(
        view.cams,
        in_range,
        T_world_obj[:3, 3] + np.array([0.0, 0.0, 0.5 * obj.size[2]]),
        float(obj.size[2]),
    )
    budget = choose_detail(h_px, float(obj.meta.get("lod_faces_per_px", FACES_PER_PX)))
    obj_render = simplify(obj, budget) if budget < len(obj.faces) else obj
    return obj_render, h_px


def _lights(
    spec: AugmentSpec, prepared: Any, seq: Any, view: _Opened, warnings: list[str]
) -> dict[str, Lighting]:
    """Lighting per camera from its first frame of the range (sun by ephemeris if asked)."""
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


def plan_augmentation(seq_folder: str | Path, spec: AugmentSpec, prepared: Any) -> Plan:
    """Everything frame-independent (module docstring). Raises AugmentError /
    PlacementError with a message saying what and where."""

    timings: dict[str, float] = {}
    warnings: list[str] = []
    tic = time.perf_counter()
    seq = sequence(seq_folder)
    view = _open(seq, spec, prepared.track, warnings)
    timings["open"] = time.perf_counter() - tic

    tic = time.perf_counter()
    obj = load_object(spec)
    timings["object"] = time.perf_counter() - tic

    tic = time.perf_counter()
    placed, proxies = _place(spec, prepared, obj, view)
    T_world_obj = placed.T_world_obj
    timings["placement"] = time.perf_counter() - tic

    tic = time.perf_counter()
    obj_render, h_px = _level_of_detail(obj, view, T_world_obj)
    timings["lod"] = time.perf_counter() - tic

    tic = time.perf_counter()
    lights = _lights(spec, prepared, seq, view, warnings)
    timings["lighting"] = time.perf_counter() - tic

    offsets = _render_offsets(spec, prepared, view.cams, warnings)
    origins = _lidar_origins(spec) if view.lidar_stream is not None else None
    log.info(
        "plan: %s at %s (%s), %d/%d faces (%.0f px high at most), %d proxy faces",
        obj.name, np.round(T_world_obj[:3, 3], 2).tolist(), placed.surface,
        len(obj_render.faces), len(obj.faces), h_px, len(proxies.faces),
    )  # fmt: skip
    return Plan(
        seq_folder=str(Path(seq_folder)),
        spec=spec,
        frames=view.frames,
        all_frames=view.all_frames,
        cameras=view.cams,
        lidar_stream=view.lidar_stream,
        uris=view.uris,
        T_world_base=view.poses,
        T_world_obj=T_world_obj,
        placement={
            "surface": placed.surface,
            "s": placed.s,
            "lateral": placed.lateral,
            **placed.info,
            "spec": spec.placement.model_dump(mode="json"),
        },
        obj_full=obj,
        obj_render=obj_render,
        obj_class=spec.object.class_name,
        proxies=proxies,
        lights=lights,
        pixel_offsets=offsets,
        speed_mps=_speeds(prepared.track, view.lidar_times),
        lidar_origins=origins,
        labels_name=seq.labels_path.name,
        timings=timings,
        warnings=warnings,
        info={
            "object_faces": len(obj.faces),
            "render_faces": len(obj_render.faces),
            "projected_height_px_max": h_px,
            "object_size_m": obj.size.tolist(),
            "proxy_faces": len(proxies.faces),
            "strategy": getattr(prepared, "strategy", ""),
            "world": prepared.world.to_json(),
        },
        placement_bounds=placement_bounds(
            prepared.track, getattr(prepared, "information", None), view.cams, view.poses,
            T_world_obj, view.frames,
        ),
        gauge=_gauge(spec, prepared, obj, T_world_obj, view),
    )  # fmt: skip


def _gauge(
    spec: AugmentSpec, prepared: Any, obj: ObjectMesh, T_world_obj: F64, view: _Opened
) -> dict[int, GaugeLabel]:
    """The gauge label per frame of the range, at the poses the annotations use (the
    lidar's, else the first camera's)."""
    stream = view.lidar_stream or view.cam_names[0]
    poses = {f: view.poses[stream][f] for f in view.frames if f in view.poses[stream]}
    p_world = transform_points(T_world_obj, obj.vertices)
    return gauge_labels(prepared.ego, p_world, poses, spec.gauge)
