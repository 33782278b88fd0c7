"""Pipeline steps 3-7: a virtual object in every frame of a sequence, cameras and lidar.

The recipe, per frame (:func:`augment_frame`)::

    for each camera: pose at its timestamp -> render -> (not visible: link the file)
                     -> decode -> composite (ROI only) -> encode -> write
    lidar:           pose at the lidar timestamp -> read -> cast rays near the object
                     -> (no hit: link the file) -> write (the input's DATA type)
    annotation:      cuboid in the lidar frame, bbox + poly2d per camera, lidar indices

Everything frame-independent is done once by :func:`plan_augmentation` (object mesh and
its level of detail, placement, proxies, lighting per camera, poses at every sensor
timestamp) into a picklable :class:`Plan`. The chunk API is what a Celery chord uses:
``plan_augmentation`` once, :func:`augment_frames` per chunk of frames (any process or
machine that sees the sequence and a scratch folder), :func:`finish_augmentation` once
(moves the chunks' files into the output, copies every other input file byte-identically,
adds the annotations to the labels, writes ``metrics.json``, renames into place).
:func:`augment` runs all three here, the frames in a process pool (``workers``).

Files not touched are hard links (or byte copies) of the input: frames where the object
is not visible in a camera cost no PNG decode or encode, which is what keeps a job close
to its I/O floor (BENCHMARK.md). The process pool uses the ``forkserver`` start method:
each worker gets its own EGL context, none is ever inherited through ``fork``.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import multiprocessing as mp
import os
import pickle
import shutil
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel, load_cameras
from geometry.transforms import invert_T, transform_points
from renderer.lighting import Lighting, estimate_lighting, sun_dir_enu
from renderer.mesh import ObjectMesh, ProxyMesh
from worker.augmentation.annotations import (
    CameraView,
    FrameAnnotation,
    add_object,
    cuboid_in_lidar,
    mask_outline,
)
from worker.augmentation.placement import (
    RAIL_HEIGHT_ABOVE_BED,
    PlacementError,
    ResolvedPlacement,
    resolve_placement,
)
from worker.augmentation.proxies import build_proxies
from worker.augmentation.spec import AugmentSpec

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: ``progress(done, total)`` in frames.
Progress = Callable[[int, int], None]

METRICS_FILE = "metrics.json"
NEAR_PLANE_M = 0.05
# A frame's lidar cast only sees points whose ray passes within the object's bounding
# sphere grown by this (m): the rest are never handed to the ray caster.
LIDAR_SPHERE_MARGIN_M = 0.05
# Exposure of the front cameras (s, composite's default) and the motion blur cap (px).
EXPOSURE_S = 0.005
MAX_MOTION_BLUR_PX = 32.0
# Composite window around the ROI (px): wider than composite's LAB ring (<= 48 px).
COMPOSITE_MARGIN_PX = 64


class AugmentError(ValueError):
    """A spec the sequence cannot honour (unknown object, camera missing, placement...)."""


# ---------------------------------------------------------------------------- the plan
@dataclass
class Plan:
    """Everything frame-independent of one augmentation (picklable).

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


@dataclass
class CameraRecord:
    """One camera in one frame: what the render said (full-image pixels).

    mask : (u0, v0, u1, v1) and the packed bits (np.packbits) of alpha > 0.5 in it, for
    the evaluation; None where nothing of the object is visible.
    """

    visible: bool
    anchor_uv: tuple[float, float]
    distance_m: float
    bbox: tuple[float, float, float, float] | None = None  # u0, v0, u1, v1 pixel edges
    visible_fraction: float = 0.0
    augmented: bool = False
    mask_roi: tuple[int, int, int, int] | None = None
    mask_bits: bytes | None = None

    def mask(self, shape: tuple[int, int]) -> NDArray[np.bool_]:
        """The visible mask (alpha > 0.5) as a full (H, W) bool image."""
        out = np.zeros(shape, dtype=bool)
        if self.mask_roi is None or self.mask_bits is None:
            return out
        u0, v0, u1, v1 = self.mask_roi
        n = (v1 - v0) * (u1 - u0)
        bits = np.unpackbits(np.frombuffer(self.mask_bits, np.uint8), count=n)
        out[v0:v1, u0:u1] = bits.reshape(v1 - v0, u1 - u0).astype(bool)
        return out


@dataclass
class FrameRecord:
    """One frame's result: its annotation (None: the object is nowhere), per-camera
    records, lidar counts and per-stage seconds."""

    frame_idx: int
    annotation: FrameAnnotation | None
    cameras: dict[str, CameraRecord]
    lidar_points: int = 0
    lidar_candidates: int = 0
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class ChunkResult:
    """What :func:`augment_frames` wrote under ``root`` (relative paths) and found."""

    root: str
    files: list[str]
    frames: list[FrameRecord]
    seconds: float = 0.0


# ---------------------------------------------------------------------------- planning
def _sequence(seq_folder: str | Path) -> Any:
    from worker.osdar.sequence import Sequence

    return Sequence.open(seq_folder)


def _frame_times(seq: Any, stream: str) -> dict[int, float]:
    ts = seq.timestamps(stream)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


def load_object(spec: AugmentSpec) -> ObjectMesh:
    """The spec's object mesh at full detail. Raises AugmentError (unknown name, bad
    mesh file)."""
    from renderer.assets import MeshError, build_obstacle, load_user_mesh

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
    from renderer.lidar_cast import origins_from_json

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


def plan_augmentation(seq_folder: str | Path, spec: AugmentSpec, prepared: Any) -> Plan:
    """Everything frame-independent (module docstring). Raises AugmentError /
    PlacementError with a message saying what and where."""
    from renderer.assets import choose_detail, simplify
    from renderer.assets.lod import FACES_PER_PX

    timings: dict[str, float] = {}
    warnings: list[str] = []
    tic = time.perf_counter()
    seq = _sequence(seq_folder)
    try:
        cam_names = spec.camera_names(seq.cameras)
        cams = load_cameras(seq.labels.raw, cam_names)
    except ValueError as exc:
        raise AugmentError(f"{seq.folder}: {exc}") from exc
    lidar_stream = seq.lidar_stream if spec.lidar else None
    if spec.lidar and lidar_stream is None:
        warnings.append("the sequence has no lidar files: lidar not augmented")
    all_frames = seq.frame_indices
    frames = all_frames
    if spec.frame_range is not None:
        a, b = spec.frame_range
        frames = [f for f in all_frames if a <= f <= b]
        if not frames:
            raise AugmentError(
                f"frame_range [{a}, {b}] holds no frame of the sequence "
                f"({all_frames[0]}..{all_frames[-1]})"
            )
    uris = {fr.index: {name: fs.uri for name, fs in fr.streams.items()} for fr in seq.labels.frames}
    track = prepared.track
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
    timings["open"] = time.perf_counter() - tic

    tic = time.perf_counter()
    obj = load_object(spec)
    timings["object"] = time.perf_counter() - tic

    # Placement: nominal point -> proxies around it -> snapped onto them, poles checked.
    tic = time.perf_counter()
    ego = prepared.ego
    kw = {"ego": ego, "track": track, "frame_times": lidar_times, "poles": [], "obj": obj}
    nominal = resolve_placement(spec.placement.to_spec(), proxies=None, **kw)
    cam_xyz = np.concatenate(
        [
            np.stack([(T @ cams[c].T_base_opt)[:3, 3] for f, T in poses[c].items() if f in frames])
            for c in cam_names
        ]
    )
    p0 = nominal.T_world_obj[:3, 3]
    ground_z = p0[2] - (0.0 if nominal.surface == "nominal" and abs(spec.placement.offset) < 1
                        else RAIL_HEIGHT_ABOVE_BED)  # fmt: skip
    proxies = build_proxies(prepared, p0, cam_xyz, ground_z=ground_z)
    kw["poles"] = list(prepared.poles)
    placed: ResolvedPlacement = resolve_placement(spec.placement.to_spec(), proxies=proxies, **kw)
    T_world_obj = placed.T_world_obj
    timings["placement"] = time.perf_counter() - tic

    # Level of detail from the largest projected height over the sequence.
    tic = time.perf_counter()
    h_px = _projected_height_px(
        cams, {c: {f: poses[c][f] for f in frames if f in poses[c]} for c in cam_names},
        T_world_obj[:3, 3] + np.array([0.0, 0.0, 0.5 * obj.size[2]]), float(obj.size[2]),
    )  # fmt: skip
    budget = choose_detail(h_px, float(obj.meta.get("lod_faces_per_px", FACES_PER_PX)))
    obj_render = simplify(obj, budget) if budget < len(obj.faces) else obj
    timings["lod"] = time.perf_counter() - tic

    # Lighting per camera from its first frame of the range.
    tic = time.perf_counter()
    sun = None
    if spec.render.sun == "ephemeris":
        w = prepared.world
        sun = sun_dir_enu(w.latitude_deg, w.longitude_deg, lidar_times[frames[0]])
        if sun[2] < 0.02:
            warnings.append("the sun is below the horizon at the sequence's time: no shadow")
    lights = {}
    for c in cam_names:
        f0 = next(f for f in frames if f in poses[c])
        img = seq.image(f0, c)
        if img.ndim == 2:
            raise AugmentError(f"camera {c} has grey images: only colour cameras are augmented")
        lights[c] = estimate_lighting(img, cams[c], poses[c][f0], sun_dir_world=sun)
    timings["lighting"] = time.perf_counter() - tic

    offsets = _pixel_offsets(prepared, cams) if spec.render.pixel_offset else {}
    if spec.render.pixel_offset and not any(any(v) for v in offsets.values()):
        warnings.append("pixel_offset asked but the preparation has no clicked calibration")
    if spec.render.scale != 1.0:
        warnings.append(
            f"render.scale {spec.render.scale} ignored: the output keeps the input resolution"
        )
    origins = _lidar_origins(spec) if lidar_stream is not None else None
    labels_name = seq.labels_path.name
    log.info(
        "plan: %s at %s (%s), %d/%d faces (%.0f px high at most), %d proxy faces",
        obj.name, np.round(T_world_obj[:3, 3], 2).tolist(), placed.surface,
        len(obj_render.faces), len(obj.faces), h_px, len(proxies.faces),
    )  # fmt: skip
    return Plan(
        seq_folder=str(Path(seq_folder)),
        spec=spec,
        frames=frames,
        all_frames=all_frames,
        cameras=cams,
        lidar_stream=lidar_stream,
        uris=uris,
        T_world_base=poses,
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
        speed_mps=_speeds(track, lidar_times),
        lidar_origins=origins,
        labels_name=labels_name,
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
    )


# ---------------------------------------------------------------------------- per frame
_RENDERERS: dict[tuple, Any] = {}


def _renderer(cam: CameraModel, antialias: str) -> Any:
    """The process's ObjectRenderer of a camera (one GL context per process)."""
    from renderer.object_render import ObjectRenderer

    key = (cam.name, cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), antialias)
    r = _RENDERERS.get(key)
    if r is None:
        r = _RENDERERS[key] = ObjectRenderer(cam, antialias=antialias)
    return r


def _link(src: Path, dest: Path) -> None:
    """``dest`` byte-identical to ``src``: hard link, else copy."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.unlink(missing_ok=True)
    try:
        os.link(src, dest)
    except OSError:
        shutil.copyfile(src, dest)


def _shift_view(view: CameraView, d: tuple[float, float]) -> CameraView:
    if d == (0.0, 0.0):
        return view
    bb = (view.bbox[0] + d[0], view.bbox[1] + d[1], view.bbox[2], view.bbox[3])
    out = [v + d[i % 2] for i, v in enumerate(view.outline)]
    return CameraView(bb, out, view.visible_fraction, view.truncated)


def _truncated(cam: CameraModel, obj: ObjectMesh, T_world_obj: F64, T_world_base: F64) -> bool:
    """Whether part of the (unoccluded) object falls outside the image or the lens model."""
    p = transform_points(T_world_obj, obj.vertices)
    uv, ok = cam.project_world(p, T_world_base)
    return bool(not np.all(ok) or not np.all(cam.in_image(uv[ok])))


def composite_file(
    src: Path,
    dest: Path,
    render: Any,
    options: dict[str, Any],
    compression: int,
    t: dict[str, float],
) -> bool:
    """Decode ``src``, composite ``render`` into its ROI, encode once to ``dest`` (or link
    ``src`` when no pixel changes); returns whether pixels changed.

    The PNG is decoded straight into OpenCV's BGR order and encoded from it: only a
    window around the ROI (``COMPOSITE_MARGIN_PX`` wider than the LAB-matching ring, so
    the result equals a full-frame composite) is converted to RGB and composited. Images
    that are not 8-bit 3-channel take the general :func:`read_png` path.
    """
    import cv2

    from renderer.composite import composite
    from worker.osdar.errors import atomic_write_bytes
    from worker.osdar.images import read_png, write_png

    tic = time.perf_counter()
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    t["decode"] += time.perf_counter() - tic
    if img is None or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        tic = time.perf_counter()
        rgb = read_png(src)
        out = composite(rgb, render, **options)
        changed = out is not rgb and not np.array_equal(out, rgb)
        t["composite"] += time.perf_counter() - tic
        tic = time.perf_counter()
        if changed:
            write_png(dest, out, compression=compression)
        else:
            _link(src, dest)
        t["encode"] += time.perf_counter() - tic
        return changed
    tic = time.perf_counter()
    u0, v0, u1, v1 = render.roi
    H, W = img.shape[:2]
    m = COMPOSITE_MARGIN_PX
    a0, b0, a1, b1 = max(u0 - m, 0), max(v0 - m, 0), min(u1 + m, W), min(v1 + m, H)
    sub = np.ascontiguousarray(img[b0:b1, a0:a1, ::-1])
    shifted = dataclasses.replace(render, roi=(u0 - a0, v0 - b0, u1 - a0, v1 - b0))
    out = composite(sub, shifted, **options)
    changed = out is not sub and not np.array_equal(out, sub)
    if changed:
        img[b0:b1, a0:a1] = out[..., ::-1]
    t["composite"] += time.perf_counter() - tic
    tic = time.perf_counter()
    if changed:
        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
        if not ok:
            raise ValueError(f"{dest}: OpenCV failed to encode the PNG")
        atomic_write_bytes(dest, buf.tobytes())
        t["encode"] += time.perf_counter() - tic
    else:
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
    return changed


def _bounded_motion(render: Any, speed_mps: float) -> Any:
    """The render with its image motion per metre limited so that the motion blur stays
    under ``MAX_MOTION_BLUR_PX``: the renderer's finite difference is a linearisation that
    explodes for an anchor at or behind the camera plane (an object passing the camera)."""
    m = np.asarray(render.motion_uv_per_m, dtype=np.float64)
    blur = float(np.linalg.norm(m)) * abs(speed_mps) * EXPOSURE_S
    if np.all(np.isfinite(m)) and blur <= MAX_MOTION_BLUR_PX:
        return render
    if not np.all(np.isfinite(m)) or blur == 0.0:
        return dataclasses.replace(render, motion_uv_per_m=np.zeros(2))
    return dataclasses.replace(render, motion_uv_per_m=m * (MAX_MOTION_BLUR_PX / blur))


def _camera_frame(
    plan: Plan, frame: int, name: str, src: Path, dest: Path, t: dict[str, float]
) -> tuple[CameraRecord, CameraView | None, bool]:
    """pose -> render -> composite -> write for one camera; returns (record, view,
    whether a file was written)."""
    cam, r = plan.cameras[name], plan.spec.render
    T_world_base = plan.T_world_base[name][frame]
    tic = time.perf_counter()
    render = _renderer(cam, r.antialias).render(
        plan.obj_render, plan.T_world_obj, T_world_base, plan.proxies, plan.lights[name],
        near=NEAR_PLANE_M,
    )  # fmt: skip
    t["render"] += time.perf_counter() - tic
    anchor = (float(render.anchor_uv[0]), float(render.anchor_uv[1]))
    rec = CameraRecord(False, anchor, float(render.distance_m))
    if render.roi is None:
        tic = time.perf_counter()
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
        return rec, None, False
    render = _bounded_motion(render, plan.speed_mps.get(frame, 0.0))
    offset = plan.pixel_offsets.get(name, (0.0, 0.0))
    options = {
        "speed_mps": plan.speed_mps.get(frame, 0.0),
        "exposure_s": EXPOSURE_S,
        "lab_match": r.lab_match,
        "blur": r.blur,
        "shadow_strength": r.shadow_strength,
        "pixel_offset": offset,
    }
    changed = composite_file(src, dest, render, options, r.png_compression, t)
    view = None
    visible = (
        render.alpha.size > 0
        and bool(np.any(render.alpha > 0))
        and np.all(np.isfinite(render.bbox))
    )
    if visible:
        tic = time.perf_counter()
        u0, v0, u1, v1 = render.bbox
        outline = mask_outline(render.alpha, (render.roi[0], render.roi[1]))
        trunc = _truncated(cam, plan.obj_render, plan.T_world_obj, T_world_base)
        view = _shift_view(
            CameraView(
                ((u0 + u1) / 2, (v0 + v1) / 2, u1 - u0, v1 - v0),
                outline,
                float(render.visible_fraction),
                trunc,
            ),
            offset,
        )
        m = render.alpha > 0.5
        rec = CameraRecord(
            True,
            (anchor[0] + offset[0], anchor[1] + offset[1]),
            rec.distance_m,
            (u0 + offset[0], v0 + offset[1], u1 + offset[0], v1 + offset[1]),
            float(render.visible_fraction),
            changed,
            tuple(int(v) for v in render.roi),  # type: ignore[arg-type]
            np.packbits(m.ravel()).tobytes(),
        )
        t["annotate"] += time.perf_counter() - tic
    else:
        rec.augmented = changed
    return rec, view, changed


def lidar_candidates(
    xyz: NDArray, origins: NDArray, centre: F64, radius: float
) -> NDArray[np.int64]:
    """Indices of points whose segment origin -> point passes within ``radius`` of
    ``centre`` (base frame): the only rays that can meet the object.

    xyz : (n, 3) points; origins : (n, 3) or (3,) ray origins; centre : (3,).
    A cheap float32 cone test first (angle from the origin to the sphere), then the
    exact float64 segment-sphere distance on the survivors.
    """
    o = np.broadcast_to(np.asarray(origins, dtype=np.float64), xyz.shape)
    c = np.asarray(centre, dtype=np.float64)
    d32 = xyz.astype(np.float32) - o.astype(np.float32)
    oc = (c - o).astype(np.float32)
    # Cone: the point's direction within asin(r / |oc|) of the centre's (or the origin
    # is inside the sphere); done as dot >= |d| * sqrt(|oc|^2 - r^2) with a little slack.
    dot = np.einsum("ij,ij->i", d32, oc)
    dn = np.sqrt(np.einsum("ij,ij->i", d32, d32))
    oc2 = np.einsum("ij,ij->i", oc, oc)
    inside = oc2 <= radius * radius
    cos_lim = np.sqrt(np.maximum(oc2 - radius * radius, 0.0))
    keep = np.flatnonzero(inside | ((dot > 0) & (dot >= dn * cos_lim * (1 - 1e-4) - 1e-3)))
    if len(keep) == 0:
        return keep.astype(np.int64)
    seg = xyz[keep].astype(np.float64) - o[keep]
    L2 = np.einsum("ij,ij->i", seg, seg)
    with np.errstate(invalid="ignore", divide="ignore"):
        tt = np.clip(np.einsum("ij,ij->i", c - o[keep], seg) / L2, 0.0, 1.0)
    dist = np.linalg.norm(o[keep] + tt[:, None] * seg - c, axis=1)
    return keep[np.isfinite(dist) & (dist <= radius)].astype(np.int64)


def _intensity_scale(fields: dict[str, NDArray]) -> dict[int, float] | float:
    """Full-scale intensity per sensor_index: the largest intensity of that sensor in the
    frame (OSDaR23's intensities are sensor-specific: 0-255 for some, 0-1 for others)."""
    if "intensity" not in fields:
        return 1.0
    inten = np.asarray(fields["intensity"], dtype=np.float64)
    if "sensor_index" not in fields:
        return float(np.nanmax(inten)) if len(inten) else 1.0
    sidx = np.asarray(fields["sensor_index"]).astype(np.int64)
    out = {}
    for k in np.unique(sidx):
        v = inten[sidx == k]
        v = v[np.isfinite(v)]
        out[int(k)] = float(v.max()) if len(v) and v.max() > 0 else 1.0
    return out


def cast_frame_lidar(
    fields: dict[str, NDArray], mesh: ObjectMesh, T_base_obj: F64, origins: dict | F64
) -> tuple[dict[str, NDArray] | None, NDArray[np.int64], int]:
    """The object cast into one cloud, only over the points near it.

    Returns (new fields or None when no point moved, sorted object point indices,
    number of candidate rays).
    """
    from renderer.lidar_cast import cast_object, point_origins

    b = mesh.bounds
    centre_obj = 0.5 * (b[0] + b[1])
    centre = transform_points(T_base_obj, centre_obj[None])[0]
    radius = 0.5 * float(np.linalg.norm(b[1] - b[0])) + LIDAR_SPHERE_MARGIN_M
    xyz = np.stack([np.asarray(fields[k]) for k in "xyz"], axis=1)
    if isinstance(origins, dict):
        o = point_origins(fields, origins)
    else:
        o = np.asarray(origins, dtype=np.float64)
    cand = lidar_candidates(xyz, o, centre, radius)
    if len(cand) == 0:
        return None, cand, 0
    sub = {k: np.asarray(v)[cand] for k, v in fields.items()}
    res = cast_object(sub, mesh, T_base_obj, origins, intensity_scale=_intensity_scale_for(
        fields, sub))  # fmt: skip
    if res.moved == 0:
        return None, np.zeros(0, np.int64), len(cand)
    out = dict(fields)
    idx = cand[res.object_indices]
    for k in fields:
        col = np.array(fields[k], copy=True)
        col[idx] = res.fields[k][res.object_indices]
        out[k] = col
    return out, np.sort(idx), len(cand)


def _intensity_scale_for(full: dict[str, NDArray], sub: dict[str, NDArray]) -> Any:
    s = _intensity_scale(full)
    if isinstance(s, dict) and "sensor_index" in sub:
        present = {int(k) for k in np.unique(np.asarray(sub["sensor_index"]))}
        return {k: v for k, v in s.items() if k in present}
    return s


def _lidar_frame(
    plan: Plan, frame: int, src: Path, dest: Path, t: dict[str, float]
) -> tuple[list[int] | None, int, bool]:
    """read -> cast -> write for one cloud; returns (object indices, candidates, written)."""
    from worker.osdar.pcd import PointCloud, read_pcd, write_pcd

    assert plan.lidar_origins is not None
    tic = time.perf_counter()
    cloud = read_pcd(src)
    t["lidar_read"] += time.perf_counter() - tic
    tic = time.perf_counter()
    T_base_obj = invert_T(plan.T_world_base[plan.lidar_stream][frame]) @ plan.T_world_obj
    new, idx, n_cand = cast_frame_lidar(cloud.fields, plan.obj_full, T_base_obj, plan.lidar_origins)
    t["lidar_cast"] += time.perf_counter() - tic
    tic = time.perf_counter()
    if new is None:
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
        return None, n_cand, False
    write_pcd(dest, PointCloud(fields=new, header=cloud.header))
    t["lidar_write"] += time.perf_counter() - tic
    return [int(i) for i in idx], n_cand, True


STAGE_KEYS = (
    "render",
    "decode",
    "composite",
    "encode",
    "annotate",
    "copy",
    "lidar_read",
    "lidar_cast",
    "lidar_write",
)


def augment_frame(plan: Plan, frame: int, out_root: Path) -> tuple[FrameRecord, list[str]]:
    """One frame (module docstring's recipe); files go under ``out_root`` at their uris."""
    from worker.osdar.sequence import uri_to_path

    t = dict.fromkeys(STAGE_KEYS, 0.0)
    seq_root = Path(plan.seq_folder)
    uris = plan.uris[frame]
    written: list[str] = []
    views: dict[str, CameraView] = {}
    records: dict[str, CameraRecord] = {}
    for name in plan.cameras:
        if name not in uris:
            continue
        uri = uris[name]
        rec, view, _ = _camera_frame(
            plan, frame, name, uri_to_path(seq_root, uri), uri_to_path(out_root, uri), t
        )
        written.append(uri.lstrip("/"))
        records[name] = rec
        if view is not None:
            views[name] = view
    lidar_idx, n_cand = None, 0
    if plan.lidar_stream is not None and plan.lidar_stream in uris:
        uri = uris[plan.lidar_stream]
        lidar_idx, n_cand, _ = _lidar_frame(
            plan, frame, uri_to_path(seq_root, uri), uri_to_path(out_root, uri), t
        )
        written.append(uri.lstrip("/"))
    ann = None
    if views or lidar_idx:
        T_lidar = plan.T_world_base.get(plan.lidar_stream or "", {}).get(frame)
        if T_lidar is None:  # no lidar stream: the first camera's pose
            T_lidar = next(plan.T_world_base[c][frame] for c in plan.cameras)
        ann = FrameAnnotation(
            frame,
            cuboid_in_lidar(plan.obj_full, plan.T_world_obj, T_lidar),
            views,
            lidar_idx if plan.lidar_stream is not None else None,
        )
        if ann.lidar_indices is None and plan.lidar_stream is not None:
            ann.lidar_indices = []
    rec = FrameRecord(frame, ann, records, len(lidar_idx or []), n_cand, t)
    return rec, written


def augment_frames(plan: Plan, frames: Iterable[int], out_root: str | Path) -> ChunkResult:
    """Augment a chunk of frames: writes their augmented or linked camera and lidar files
    under ``out_root`` (same relative paths as the input); returns the records."""
    tic = time.perf_counter()
    out_root = Path(out_root)
    records, files = [], []
    for f in frames:
        rec, written = augment_frame(plan, int(f), out_root)
        records.append(rec)
        files += written
    return ChunkResult(str(out_root), files, records, time.perf_counter() - tic)


# ---------------------------------------------------------------------------- finishing
def _stage_totals(chunks: list[ChunkResult]) -> dict[str, float]:
    tot = dict.fromkeys(STAGE_KEYS, 0.0)
    for ch in chunks:
        for r in ch.frames:
            for k, v in r.timings.items():
                tot[k] = tot.get(k, 0.0) + v
    return tot


def _input_files(folder: Path) -> list[str]:
    out = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            out.append((Path(root) / name).relative_to(folder).as_posix())
    return out


def finish_augmentation(
    plan: Plan,
    chunks: list[ChunkResult],
    out_folder: str | Path,
    *,
    overwrite: bool = False,
    evaluate: bool = True,
    extra_timings: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Assemble the output sequence (module docstring); returns the metrics.

    Chunk files are moved (renamed) from their roots into the output; every other input
    file (INS CSVs, other cameras, calibration.txt, ...) is linked byte-identically; the
    labels get the object; ``metrics.json`` holds per-stage seconds, counts and, where
    the sequence has ground truth, the object's errors (:mod:`.evaluate_object`).
    """
    from worker.osdar.labels import load_labels
    from worker.osdar.writer import SequenceWriter

    t_finish = time.perf_counter()
    out_folder = Path(out_folder)
    seq_root = Path(plan.seq_folder)
    records = sorted((r for ch in chunks for r in ch.frames), key=lambda r: r.frame_idx)
    missing = sorted(set(plan.frames) - {r.frame_idx for r in records})
    if missing:
        raise ValueError(f"chunks miss frame(s) {missing[:10]}")
    writer = SequenceWriter(out_folder, name=out_folder.name, overwrite=overwrite)
    try:
        tic = time.perf_counter()
        done: set[str] = set()
        for ch in chunks:
            root = Path(ch.root)
            for rel in ch.files:
                dest = writer.root / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(root / rel, dest)
                done.add(rel)
        labels_rel = plan.labels_name
        n_linked = 0
        for rel in _input_files(seq_root):
            if rel in done or rel == labels_rel:
                continue
            writer.copy_unchanged(seq_root / rel, "/" + rel)
            n_linked += 1
        t_move = time.perf_counter() - tic

        tic = time.perf_counter()
        labels = copy.deepcopy(load_labels(seq_root / labels_rel).raw)
        anns = [r.annotation for r in records if r.annotation is not None]
        oid = None
        if anns:
            oid = add_object(labels, obj_class=plan.obj_class, frames=anns, seed=_object_seed(plan))
        else:
            plan.warnings.append("the object is visible in no frame: no annotation added")
        t_labels = time.perf_counter() - tic

        stages = _stage_totals(chunks)
        metrics: dict[str, Any] = {
            "sequence": seq_root.name,
            "output": str(out_folder),
            "object": {
                "class": plan.obj_class,
                "uuid": oid,
                **plan.info,
            },
            "placement": _jsonable(plan.placement),
            "T_world_obj": plan.T_world_obj.tolist(),
            "frames": {
                "total": len(plan.all_frames),
                "augmented_range": len(plan.frames),
                "annotated": len(anns),
            },
            "cameras": _camera_counts(plan, records),
            "lidar": _lidar_counts(plan, records),
            "timings_s": {
                **{f"plan_{k}": v for k, v in plan.timings.items()},
                **{f"frames_{k}": v for k, v in stages.items()},
                "frames_wall": sum(ch.seconds for ch in chunks),
                "assemble": t_move,
                "labels": t_labels,
                "linked_files": n_linked,
                **(extra_timings or {}),
            },
            "warnings": list(plan.warnings),
        }
        if evaluate and (seq_root / "ground_truth").is_dir():
            from worker.evaluation.object_error import evaluate_object

            tic = time.perf_counter()
            try:
                metrics["object_errors"] = evaluate_object(plan, records)
            except (ValueError, OSError, KeyError) as exc:
                log.warning("object evaluation failed: %s", exc)
                metrics["object_errors"] = {"error": str(exc)}
            metrics["timings_s"]["evaluate"] = time.perf_counter() - tic
        if plan.spec.clicks is not None or plan.info.get("calibration"):
            metrics["calibration"] = plan.info.get("calibration")
        metrics["timings_s"]["finish"] = time.perf_counter() - t_finish
        writer.write_bytes("/" + METRICS_FILE, json.dumps(_jsonable(metrics), indent=1).encode())
        writer.finish(labels)
    except BaseException:
        writer.abort()
        raise
    return metrics


def _object_seed(plan: Plan) -> str:
    return f"osdar-ar/{Path(plan.seq_folder).name}/{plan.obj_class}/" + ",".join(
        f"{v:.3f}" for v in plan.T_world_obj[:3, 3]
    )


def _camera_counts(plan: Plan, records: list[FrameRecord]) -> dict[str, Any]:
    out = {}
    for c in plan.cameras:
        recs = [r.cameras[c] for r in records if c in r.cameras]
        out[c] = {
            "visible_frames": sum(x.visible for x in recs),
            "augmented_files": sum(x.augmented for x in recs),
            "linked_files": sum(not x.augmented for x in recs),
        }
    return out


def _lidar_counts(plan: Plan, records: list[FrameRecord]) -> dict[str, Any] | None:
    if plan.lidar_stream is None:
        return None
    pts = [r.lidar_points for r in records]
    return {
        "origins": plan.spec.lidar_origins,
        "frames_with_points": int(sum(p > 0 for p in pts)),
        "object_points_total": int(sum(pts)),
        "object_points_max": int(max(pts, default=0)),
        "candidate_rays_total": int(sum(r.lidar_candidates for r in records)),
    }


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


# ---------------------------------------------------------------------------- the step
def _pool_context() -> Any:
    """``forkserver`` (a clean server imports the heavy modules once; workers fork from it
    without any GL or open3d state), ``spawn`` where forkserver does not exist."""
    try:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(["worker.augmentation.augment"])
        return ctx
    except ValueError:
        return mp.get_context("spawn")


def default_setup_cache() -> Path:
    """Where camera render setups are cached: ``$OSDAR_AR_CACHE_DIR/../render_setup``
    or ``~/.cache/osdar-ar/render_setup``."""
    env = os.environ.get("OSDAR_AR_CACHE_DIR")
    base = Path(env).parent if env else Path.home() / ".cache/osdar-ar"
    return base / "render_setup"


def load_render_setup(cam: CameraModel, cache_dir: str | Path | None) -> None:
    """Fill the renderer's in-process cache of ``cam``'s render setup (the undistorted
    pinhole and its remap, ~2 s to compute at 12 MP) from a disk cache, computing and
    storing it there on a miss. The remap depends only on the intrinsics, so every job
    on the same cameras shares it.

    Uses geometry.camera's private cache (``_SETUP_CACHE``, ``_camera_key``): the
    renderer has no public hook for a precomputed setup.
    """
    from renderer import camera as cam_mod

    margin = 2.0  # CameraModel.render_setup's default margin_px, as ObjectRenderer uses
    key = cam_mod._camera_key(cam, margin)
    if key in cam_mod._SETUP_CACHE or cache_dir is None:
        return
    import hashlib

    digest = hashlib.sha256(repr((key[0], key[1], key[4])).encode() + key[2] + key[3])
    path = Path(cache_dir) / f"{digest.hexdigest()[:32]}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                cam_mod._SETUP_CACHE[key] = cam_mod.RenderSetup(
                    K=z["K"], width=int(z["size"][0]), height=int(z["size"][1]),
                    map_x=z["map_x"], map_y=z["map_y"],
                )  # fmt: skip
            return
        except (OSError, ValueError, KeyError) as exc:
            log.warning("render setup cache %s unreadable (%s): recomputing", path, exc)
    setup = cam.render_setup(margin)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, K=setup.K, size=np.array([setup.width, setup.height]),
                     map_x=setup.map_x, map_y=setup.map_y)  # fmt: skip
        os.replace(tmp, path)
    except OSError as exc:
        log.debug("render setup not cached: %s", exc)


def _warm_worker(cameras: list[dict[str, Any]], antialias: str, setup_cache: str | None) -> int:
    """Create the worker's GL context, renderers (render setups) and ray caster ahead."""
    import open3d as o3d

    for c in cameras:
        cam = CameraModel.from_json(c)
        load_render_setup(cam, setup_cache)
        _renderer(cam, antialias)
    scene = o3d.t.geometry.RaycastingScene()
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    scene.add_triangles(o3d.core.Tensor(tri), o3d.core.Tensor(np.array([[0, 1, 2]], np.uint32)))
    scene.cast_rays(o3d.core.Tensor(np.array([[0.2, 0.2, 1, 0, 0, -1]], np.float32)))
    return os.getpid()


def start_pool(
    workers: int,
    cameras: list[CameraModel] | None = None,
    antialias: str = "auto",
    setup_cache: str | Path | None = None,
) -> Any:
    """A process pool for :func:`augment`, warmed with the cameras (GL context, render
    setups from ``setup_cache``) while the parent plans."""
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=_pool_context())
    cams = [c.to_json() for c in cameras or []]
    cache = None if setup_cache is None else str(setup_cache)
    for _ in range(workers):
        pool.submit(_warm_worker, cams, antialias, cache)
    return pool


def _spec_cameras(seq_folder: str | Path, spec: AugmentSpec) -> list[CameraModel]:
    """The spec's cameras of a sequence ([] when the spec cannot be honoured: the plan
    reports that)."""
    try:
        seq = _sequence(seq_folder)
        names = spec.camera_names(seq.cameras)
        return list(load_cameras(seq.labels.raw, names).values())
    except (ValueError, OSError):
        return []


def augment(
    seq_folder: str | Path,
    spec: AugmentSpec,
    out_folder: str | Path,
    *,
    prepared: Any = None,
    cache_dir: str | Path | None = None,
    workers: int = 1,
    progress: Progress | None = None,
    overwrite: bool = False,
    evaluate: bool = True,
    setup_cache: str | Path | None = None,
) -> dict[str, Any]:
    """Augment a sequence into ``out_folder`` (OSDaR23 layout + metrics.json).

    Parameters
    ----------
    seq_folder : the input sequence.
    spec : what to add and how.
    out_folder : the output sequence folder (its name is the sequence name).
    prepared : a PreparedSequence; None runs (or reuses from ``cache_dir``) the
        preparation with ``spec.strategy`` and ``spec.clicks``.
    workers : processes for the frames (1: in this process).
    progress : ``progress(done, total)`` in frames.
    setup_cache : folder of cached camera render setups (default
        :func:`default_setup_cache`).

    Returns
    -------
    The metrics (also written to ``out_folder/metrics.json``).

    Raises
    ------
    AugmentError, PlacementError : the spec cannot be honoured (message says why).
    """
    t0 = time.perf_counter()
    out_folder = Path(out_folder)
    if out_folder.exists() and not overwrite:
        raise FileExistsError(f"{out_folder}: output sequence already exists")
    setup_cache = default_setup_cache() if setup_cache is None else Path(setup_cache)
    cams = _spec_cameras(seq_folder, spec)
    pool = None
    if workers > 1:  # this process is one of the workers
        pool = start_pool(workers - 1, cams, spec.render.antialias, setup_cache)
    for cam in cams:
        load_render_setup(cam, setup_cache)
    scratch = out_folder.with_name(out_folder.name + ".chunks")
    extra: dict[str, float] = {}
    try:
        if prepared is None:
            tic = time.perf_counter()
            prepared = _prepare(seq_folder, spec, cache_dir)
            extra["prepare"] = time.perf_counter() - tic
        plan = plan_augmentation(seq_folder, spec, prepared)
        if prepared.calibration is not None:
            plan.info["calibration"] = prepared.calibration.summary()
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
        tic = time.perf_counter()
        chunks = _run_frames(plan, scratch, pool, progress)
        extra["frames_total_wall"] = time.perf_counter() - tic
        extra["job_before_finish"] = time.perf_counter() - t0
        metrics = finish_augmentation(
            plan, chunks, out_folder, overwrite=overwrite, evaluate=evaluate, extra_timings=extra
        )
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(scratch, ignore_errors=True)
    total = time.perf_counter() - t0
    metrics["timings_s"]["total"] = total
    (out_folder / METRICS_FILE).write_text(json.dumps(_jsonable(metrics), indent=1))
    log.info("augmented %s -> %s in %.1f s", seq_folder, out_folder, total)
    return metrics


def _prepare(seq_folder: str | Path, spec: AugmentSpec, cache_dir: str | Path | None) -> Any:
    from worker.preparation.calibration_point import Clicks
    from worker.preparation.config import PrepareConfig
    from worker.preparation.prepare import prepare

    clicks = None if spec.clicks is None else Clicks.from_json(spec.clicks)
    config = PrepareConfig(strategy=spec.strategy)
    return prepare(seq_folder, config, clicks=clicks, cache_dir=cache_dir)


_PLAN_CACHE: dict[str, Plan] = {}


def _augment_frames_from_file(plan_file: str, frames: list[int], out_root: str) -> ChunkResult:
    plan = _PLAN_CACHE.get(plan_file)
    if plan is None:
        _PLAN_CACHE.clear()
        plan = _PLAN_CACHE[plan_file] = pickle.loads(Path(plan_file).read_bytes())
    return augment_frames(plan, frames, out_root)


def _run_frames(
    plan: Plan, scratch: Path, pool: Any, progress: Progress | None
) -> list[ChunkResult]:
    """All frames of the plan, one per task. With a pool of n - 1 processes, this
    process is the n-th worker: it takes frames itself while the others start up and
    between collecting their results (each child keeps two frames queued)."""
    total = len(plan.frames)
    pending = list(reversed(plan.frames))
    chunks: list[ChunkResult] = []

    def report() -> None:
        if progress is not None:
            progress(len(chunks), total)

    if pool is None:
        while pending:
            chunks.append(augment_frames(plan, [pending.pop()], scratch))
            report()
        return chunks
    # The plan goes to the workers once, as a file; each task names it.
    plan_file = scratch / ".plan.pkl"
    plan_file.write_bytes(pickle.dumps(plan, protocol=pickle.HIGHEST_PROTOCOL))
    n_children = pool._max_workers
    futures: set[Future] = set()
    while pending or futures:
        while pending and len(futures) < 2 * n_children:
            f = pending.pop()
            futures.add(pool.submit(_augment_frames_from_file, str(plan_file), [f], str(scratch)))
        if pending:
            chunks.append(augment_frames(plan, [pending.pop()], scratch))
            report()
            timeout = 0.0
        else:
            timeout = None
        done, futures = wait(futures, timeout=timeout, return_when=FIRST_COMPLETED)
        for fut in done:
            chunks.append(fut.result())
            report()
    return chunks


__all__ = [
    "AugmentError",
    "AugmentSpec",
    "ChunkResult",
    "FrameRecord",
    "PlacementError",
    "Plan",
    "augment",
    "augment_frame",
    "augment_frames",
    "cast_frame_lidar",
    "finish_augmentation",
    "lidar_candidates",
    "plan_augmentation",
]
