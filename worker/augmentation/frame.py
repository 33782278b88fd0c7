"""One frame of an augmentation (the recipe of :mod:`worker.augmentation.augment`).

Per camera: poses at its timestamp -> render each object -> (none visible: link the
file) -> decode -> composite (ROI only, far objects first) -> encode -> write. Lidar:
poses at the lidar timestamp -> read -> cast rays near the objects -> (no hit: link the
file) -> write (the input's DATA type). Annotation per object: cuboid in the lidar frame,
bbox + poly2d per camera, lidar indices, velocity.

Several objects hide each other with one depth test: each object is rendered with the
scene proxies AND the other objects (posed at the same camera timestamp) as occluders in
its depth buffer, so its coverage, mask and outline are cut wherever another object is
nearer, and its shadow falls on the other objects too. In the lidar all objects are one
ray-casting scene (in the base frame of the frame), so a ray stops at the nearest object
surface; each moved point is then given to the object it lies on.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from geometry.camera import CameraModel
from geometry.transforms import invert_T, transform_points
from renderer.composite import composite, composite_into
from renderer.lidar_cast import (
    LidarCastResult,
    LidarNoise,
    cast_object,
    point_origins,
)
from renderer.mesh import ObjectMesh, ProxyMesh
from renderer.object_render import ObjectRenderer
from worker.augmentation.annotations import (
    CameraView,
    FrameAnnotation,
    cuboid_in_lidar,
    mask_outline,
)
from worker.augmentation.lidar_noise import bounding_sphere, key_noise
from worker.augmentation.plan import (
    NEAR_PLANE_M,
    Plan,
    PlannedObject,
    drop_decoded,
    take_decoded,
)
from worker.osdar.errors import atomic_write_bytes
from worker.osdar.images import read_png, write_png
from worker.osdar.pcd import PointCloud, read_pcd, write_pcd
from worker.osdar.png_splice import DecodedRows, decode_rows, splice_decoded, splice_png
from worker.osdar.sequence import uri_to_path

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# One renderer per camera and antialiasing mode in each process.
_RENDERERS: dict[tuple, Any] = {}


# The motion blur cap (px).
MAX_MOTION_BLUR_PX = 32.0


# Composite window around the ROI (px): wider than composite's LAB ring (<= 48 px).
COMPOSITE_MARGIN_PX = 64


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
class ObjectFrame:
    """One object in one frame: its annotation (None: the object is nowhere), per-camera
    records and its lidar point count."""

    annotation: FrameAnnotation | None
    cameras: dict[str, CameraRecord]
    lidar_points: int = 0


@dataclass
class FrameRecord:
    """One frame's result: per object (the plan's order) an :class:`ObjectFrame`, the
    lidar rays cast, per-stage seconds and the lidar noise the object points got
    (its key frame's, :mod:`.lidar_noise`: {sensor_index: {range_sigma_m, dropout, points,
    rings}}).
    ``annotation``, ``cameras`` and ``lidar_points`` are the first object's
    (single-object readers)."""

    frame_idx: int
    objects: list[ObjectFrame]
    lidar_candidates: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    lidar_noise: dict[int, dict[str, float]] = field(default_factory=dict)

    @property
    def annotation(self) -> FrameAnnotation | None:
        return self.objects[0].annotation

    @property
    def cameras(self) -> dict[str, CameraRecord]:
        return self.objects[0].cameras

    @property
    def lidar_points(self) -> int:
        return self.objects[0].lidar_points


@dataclass
class ChunkResult:
    """What :func:`augment_frames` wrote under ``root`` (relative paths) and found."""

    root: str
    files: list[str]
    frames: list[FrameRecord]
    seconds: float = 0.0
    #: the object's errors against the true poses, measured where the frames were
    #: augmented (sequences with ground truth): {frame: {camera: {anchor_px, iou}}}
    #: (worker/evaluation/object_error.py; frames not here are measured by the finish)
    object_errors: dict[int, dict[str, dict[str, float | None]]] = field(default_factory=dict)


def camera_renderer(cam: CameraModel, antialias: str) -> Any:
    """The process's ObjectRenderer of a camera (one GL context per process)."""

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
    return dataclasses.replace(view, bbox=bb, outline=out)


def _truncated(cam: CameraModel, obj: ObjectMesh, T_world_obj: F64, T_world_base: F64) -> bool:
    """Whether part of the (unoccluded) object falls outside the image or the lens model."""
    p = transform_points(T_world_obj, obj.vertices)
    uv, ok = cam.project_world(p, T_world_base)
    return bool(not np.all(ok) or not np.all(cam.in_image(uv[ok])))


def composite_file(
    src: Path,
    dest: Path,
    layers: list[tuple[Any, dict[str, Any]]],
    compression: int,
    t: dict[str, float],
) -> bool:
    """Decode ``src``, composite each ``(render, options)`` of ``layers`` in turn (far
    objects first) into its ROI, encode once to ``dest`` (only the band of rows that
    changed is compressed anew: :func:`_encode_changed`; ``src`` is linked when no pixel
    changes); returns whether pixels changed.

    The PNG is decoded straight into OpenCV's BGR order, down to the lowest window's
    rows only (:func:`~worker.osdar.png_splice.decode_rows`; or taken whole from the
    plan, which decoded the first frame for the lighting: :func:`.plan.take_decoded`),
    and encoded from it: only a window around each ROI (``COMPOSITE_MARGIN_PX`` wider than the
    LAB-matching ring, so the result equals a full-frame composite) is composited, in
    place through the image's RGB view. Images that are not 8-bit 3-channel take the general
    :func:`read_png` path.
    """

    tic = time.perf_counter()
    src_bytes = src.read_bytes()
    m = COMPOSITE_MARGIN_PX
    decoded = None
    img = take_decoded(src)
    if img is None and not layers:
        t["decode"] += time.perf_counter() - tic
        _link(src, dest)
        return False
    if img is None:  # the rows down to the lowest window (and the one below it) only
        decoded = decode_rows(src_bytes, max(r.roi[3] for r, _ in layers) + m + 1)
        img = None if decoded is None else decoded.img_bgr
    if img is None:
        img = cv2.imdecode(np.frombuffer(src_bytes, np.uint8), cv2.IMREAD_UNCHANGED)
    t["decode"] += time.perf_counter() - tic
    if img is None or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        tic = time.perf_counter()
        rgb = read_png(src)
        out = rgb
        for render, options in layers:
            out = composite(out, render, **options)
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
    H = img.shape[0] if decoded is None else decoded.height
    W = img.shape[1]
    rows = (H, 0)  # the band of rows that changed: [rows[0], rows[1])
    for render, options in layers:
        u0, v0, u1, v1 = render.roi
        a0, b0, a1, b1 = max(u0 - m, 0), max(v0 - m, 0), min(u1 + m, W), min(v1 + m, H)
        shifted = dataclasses.replace(render, roi=(u0 - a0, v0 - b0, u1 - a0, v1 - b0))
        # blended into the decoded image itself, through its RGB view
        if composite_into(img[b0:b1, a0:a1, ::-1], shifted, **options):
            rows = (min(rows[0], b0), max(rows[1], b1))
    changed = rows[0] < rows[1]
    t["composite"] += time.perf_counter() - tic
    tic = time.perf_counter()
    if changed:
        data = _encode_changed(src_bytes, img, rows, compression, dest, decoded)
        atomic_write_bytes(dest, data)
        t["encode"] += time.perf_counter() - tic
    else:
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
    return changed


def _encode_changed(
    src_bytes: bytes,
    img: NDArray[np.uint8],
    rows: tuple[int, int],
    level: int,
    dest: Path,
    decoded: DecodedRows | None = None,
) -> bytes:
    """PNG bytes of ``img`` whose pixel rows [rows[0], rows[1]) differ from the PNG
    ``src_bytes``: (H, W, 3) BGR, or its first rows as :func:`decode_rows` gave them
    (``decoded``). The source's compressed rows outside the band are kept
    (:func:`~worker.osdar.png_splice.splice_png`: a 4112 x 2504 frame with a 300-row band
    in 0.32 s against 1.2 s for OpenCV's whole encode), or the whole image is encoded when
    the source cannot be spliced (not 8-bit RGB, interlaced)."""
    if decoded is not None:
        result = splice_decoded(decoded, img, rows, int(level))
        if result is not None:
            return result.png
        full = cv2.imdecode(np.frombuffer(src_bytes, np.uint8), cv2.IMREAD_UNCHANGED)
        if full is None or full.shape[1:] != img.shape[1:] or full.dtype != img.dtype:
            raise ValueError(f"{dest}: cannot decode the source PNG again")
        full[: img.shape[0]] = img
        img = full
    spliced = splice_png(src_bytes, img, rows, int(level))
    if spliced is not None:
        return spliced
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, int(level)])
    if not ok:
        raise ValueError(f"{dest}: OpenCV failed to encode the PNG")
    return bytes(buf.tobytes())


def occluders(proxies: ProxyMesh, others: list[tuple[ObjectMesh, F64]]) -> ProxyMesh:
    """The scene proxies and the other objects (mesh, (4, 4) T_world_obj) as one depth-only
    occluder mesh in the world frame."""
    if not others:
        return proxies
    parts = [proxies] + [ProxyMesh(transform_points(T, m.vertices), m.faces) for m, T in others]
    return ProxyMesh.concatenate(parts)


def _bounded_motion(render: Any, speed_mps: float, exposure_s: float) -> Any:
    """The render with its image motion per metre limited so that the motion blur stays
    under ``MAX_MOTION_BLUR_PX``: the renderer's finite difference is a linearisation that
    explodes for an anchor at or behind the camera plane (an object passing the camera)."""
    m = np.asarray(render.motion_uv_per_m, dtype=np.float64)
    blur = float(np.linalg.norm(m)) * abs(speed_mps) * exposure_s
    if np.all(np.isfinite(m)) and blur <= MAX_MOTION_BLUR_PX:
        return render
    if not np.all(np.isfinite(m)) or blur == 0.0:
        return dataclasses.replace(render, motion_uv_per_m=np.zeros(2))
    return dataclasses.replace(render, motion_uv_per_m=m * (MAX_MOTION_BLUR_PX / blur))


def _camera_frame(
    plan: Plan, frame: int, name: str, src: Path, dest: Path, t: dict[str, float]
) -> tuple[list[CameraRecord], list[CameraView | None], bool]:
    """poses -> render each object -> composite -> write for one camera; returns per
    object (record, view) and whether pixels changed."""
    cam, r = plan.cameras[name], plan.spec.render
    T_world_base = plan.T_world_base[name][frame]
    objs = plan.objects
    meshes = [o.mesh(name, frame, full=False) for o in objs]
    poses = [o.pose(name, frame) for o in objs]
    renderer = camera_renderer(cam, r.antialias)
    tic = time.perf_counter()
    renders = []
    for i in range(len(objs)):
        others = [(meshes[j], poses[j]) for j in range(len(objs)) if j != i]
        renders.append(renderer.render(
            meshes[i], poses[i], T_world_base, occluders(plan.proxies, others),
            plan.lights[name], near=NEAR_PLANE_M,
        ))  # fmt: skip
    t["render"] += time.perf_counter() - tic
    speed = plan.speed_mps.get(frame, 0.0)
    offset = plan.pixel_offsets.get(name, (0.0, 0.0))
    options = {
        "speed_mps": speed,
        "exposure_s": r.exposure_ms / 1000.0,
        "aperture_m": r.aperture_mm / 1000.0,
        "lab_match": r.lab_match,
        "blur": r.blur,
        "shadow_strength": r.shadow_strength,
        "pixel_offset": offset,
    }
    shown = [i for i, rd in enumerate(renders) if rd.roi is not None]
    if not shown:
        tic = time.perf_counter()
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
        return [_camera_record(rd) for rd in renders], [None] * len(renders), False
    shown.sort(key=lambda i: -renders[i].distance_m)  # far objects first
    for i in shown:
        renders[i] = _bounded_motion(renders[i], speed, r.exposure_ms / 1000.0)
    changed = composite_file(
        src, dest, [(renders[i], options) for i in shown], r.png_compression, t
    )
    records, views = [], []
    for i, rd in enumerate(renders):
        rec, view = _object_view(plan, objs[i], meshes[i], poses[i], frame, name, rd, T_world_base,
                                 offset, changed, t)  # fmt: skip
        records.append(rec)
        views.append(view)
    return records, views, changed


def _camera_record(render: Any) -> CameraRecord:
    anchor = (float(render.anchor_uv[0]), float(render.anchor_uv[1]))
    return CameraRecord(False, anchor, float(render.distance_m))


def _object_view(
    plan: Plan,
    obj: PlannedObject,
    mesh: ObjectMesh,
    T_world_obj: F64,
    frame: int,
    name: str,
    render: Any,
    T_world_base: F64,
    offset: tuple[float, float],
    changed: bool,
    t: dict[str, float],
) -> tuple[CameraRecord, CameraView | None]:
    """One object's record and annotation view in one camera from its render."""
    rec = _camera_record(render)
    anchor = rec.anchor_uv
    visible = (
        render.roi is not None
        and render.alpha.size > 0
        and bool(np.any(render.alpha > 0))
        and np.all(np.isfinite(render.bbox))
    )
    if not visible:
        rec.augmented = changed and render.roi is not None
        return rec, None
    tic = time.perf_counter()
    u0, v0, u1, v1 = render.bbox
    outline = mask_outline(render.alpha, (render.roi[0], render.roi[1]))
    trunc = _truncated(plan.cameras[name], mesh, T_world_obj, T_world_base)
    view = _shift_view(
        CameraView(
            ((u0 + u1) / 2, (v0 + v1) / 2, u1 - u0, v1 - v0),
            outline,
            float(render.visible_fraction),
            trunc,
            obj.placement_bounds.get(frame, {}).get(name),
            int(np.count_nonzero(render.alpha > 0.5)),
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
    return rec, view


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


def _noise_arguments(
    fields: dict[str, NDArray], noise: dict[int, LidarNoise] | None
) -> dict[str, Any]:
    """``range_sigma`` and ``dropout`` for :func:`cast_object` from an estimate: per
    sensor_index (finite range noise only), or the one value of a cloud without it."""
    if not noise:
        return {}
    sigma = {s: n.range_sigma_m for s, n in noise.items() if np.isfinite(n.range_sigma_m)}
    dropout = {s: n.dropout for s, n in noise.items()}
    if "sensor_index" not in fields:
        return {"range_sigma": sigma.get(0, 0.0), "dropout": dropout.get(0, 0.0)}
    return {"range_sigma": sigma, "dropout": dropout}


def _merge_cast(
    fields: dict[str, NDArray], cand: NDArray[np.int64], res: LidarCastResult
) -> tuple[dict[str, NDArray], NDArray[np.int64]]:
    """The cast of the candidate points ``cand`` written back into the whole cloud.

    Returns the new fields (without the object rays that returned nothing, when the cast
    dropped some) and the sorted indices of the object points in them.
    """
    src = res.object_indices if res.kept is None else res.kept[res.object_indices]
    idx = cand[src]  # object points, input indices (cand, kept, object_indices sorted)
    out = dict(fields)
    for k in fields:
        col = np.array(fields[k], copy=True)
        col[idx] = res.fields[k][res.object_indices]
        out[k] = col
    if len(res.dropped) == 0:
        return out, idx
    keep = np.ones(len(fields["x"]), dtype=bool)
    keep[cand[res.dropped]] = False
    new_pos = np.cumsum(keep) - 1
    return {k: v[keep] for k, v in out.items()}, new_pos[idx].astype(np.int64)


def cast_frame_lidar(
    fields: dict[str, NDArray],
    mesh: ObjectMesh,
    T_base_obj: F64,
    origins: dict | F64,
    *,
    noise: dict[int, LidarNoise] | None = None,
    seed: int = 0,
) -> tuple[dict[str, NDArray] | None, NDArray[np.int64], int]:
    """The object cast into one cloud, only over the points near it.

    noise : per sensor_index the range noise and dropout the object points get (e.g.
    :func:`.lidar_noise.lidar_noise_near`); None: exactly on the surface, none dropped.
    seed : the noise's draw (the same seed, the same cloud).

    Returns (new fields or None when no point moved, sorted object point indices in the
    new fields, number of candidate rays).
    """

    centre, radius = bounding_sphere(mesh, T_base_obj)
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
        fields, sub), seed=seed, **_noise_arguments(fields, noise))  # fmt: skip
    if res.moved == 0 and len(res.dropped) == 0:
        return None, np.zeros(0, np.int64), len(cand)
    out, idx = _merge_cast(fields, cand, res)
    return out, idx, len(cand)


def _intensity_scale_for(full: dict[str, NDArray], sub: dict[str, NDArray]) -> Any:
    s = _intensity_scale(full)
    if isinstance(s, dict) and "sensor_index" in sub:
        present = {int(k) for k in np.unique(np.asarray(sub["sensor_index"]))}
        return {k: v for k, v in s.items() if k in present}
    return s


def cast_frame_lidar_objects(
    fields: dict[str, NDArray],
    meshes: list[ObjectMesh],
    T_base_objs: list[F64],
    origins: dict | F64,
    *,
    noise: dict[int, LidarNoise] | None = None,
    seed: int = 0,
) -> tuple[dict[str, NDArray] | None, list[NDArray[np.int64]], int]:
    """Several objects cast into one cloud as ONE scene: a ray stops at the nearest object
    surface (module docstring). Only rays near some object are cast. ``noise`` and
    ``seed`` as in :func:`cast_frame_lidar`.

    Returns (new fields or None when no point moved, per object its sorted point
    indices in the new fields, number of candidate rays).
    """
    n = len(meshes)
    empty = [np.zeros(0, np.int64) for _ in range(n)]
    xyz = np.stack([np.asarray(fields[k]) for k in "xyz"], axis=1)
    o = point_origins(fields, origins) if isinstance(origins, dict) else np.asarray(origins, float)
    cand_parts = []
    for m, T in zip(meshes, T_base_objs, strict=True):
        centre, radius = bounding_sphere(m, T)
        cand_parts.append(lidar_candidates(xyz, o, centre, radius))
    cand = np.unique(np.concatenate(cand_parts)) if cand_parts else np.zeros(0, np.int64)
    if len(cand) == 0:
        return None, empty, 0
    placed = [transform_points(T, m.vertices) for m, T in zip(meshes, T_base_objs, strict=True)]
    offsets = np.cumsum([0] + [len(v) for v in placed[:-1]])
    scene_mesh = ObjectMesh(
        np.concatenate(placed),
        np.concatenate([m.faces + k for m, k in zip(meshes, offsets, strict=True)]),
        np.concatenate([m.colors for m in meshes]),
        np.concatenate([m.reflectivity for m in meshes]),
        name="objects",
    )
    sub = {k: np.asarray(v)[cand] for k, v in fields.items()}
    res = cast_object(sub, scene_mesh, np.eye(4), origins,
                      intensity_scale=_intensity_scale_for(fields, sub), seed=seed,
                      **_noise_arguments(fields, noise))  # fmt: skip
    if res.moved == 0 and len(res.dropped) == 0:
        return None, empty, len(cand)
    out, idx = _merge_cast(fields, cand, res)
    owner = _owners(placed, meshes, np.stack([out[k][idx] for k in "xyz"], 1).astype(np.float64))
    return out, [np.sort(idx[owner == k]) for k in range(n)], len(cand)


def _owners(placed: list[F64], meshes: list[ObjectMesh], q: F64) -> NDArray[np.int64]:
    """(k,) index of the object whose surface (vertices ``placed``, base frame) each point
    of ``q`` (k, 3) lies on: the nearest one."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = [
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                            o3d.core.Tensor(m.faces.astype(np.uint32)))
        for v, m in zip(placed, meshes, strict=True)
    ]  # fmt: skip
    got = scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
    gid = got["geometry_ids"].numpy().astype(np.int64)
    lookup = {int(g): k for k, g in enumerate(ids)}
    return np.array([lookup.get(int(g), -1) for g in gid], dtype=np.int64)


def _lidar_frame(
    plan: Plan,
    frame: int,
    src: Path,
    dest: Path,
    t: dict[str, float],
    noise_out: dict[int, dict[str, float]],
) -> tuple[list[list[int]] | None, int, bool]:
    """read -> cast with the key frame's noise -> write for one cloud; returns (per
    object its point indices, None when no point moved; candidates; written). The
    noise used (the plan's estimate at the frame's key frame, :mod:`.lidar_noise`) goes
    into ``noise_out`` ({sensor_index: LidarNoise as a dict}; none when the spec's
    ``render.lidar_noise`` is off); the noise's draw is seeded with the frame number (the
    same job, the same clouds)."""

    assert plan.lidar_origins is not None and plan.lidar_stream is not None
    stream = plan.lidar_stream
    tic = time.perf_counter()
    cloud = read_pcd(src)
    t["lidar_read"] += time.perf_counter() - tic
    tic = time.perf_counter()
    T_base_world = invert_T(plan.T_world_base[stream][frame])
    meshes = [o.mesh(stream, frame, full=True) for o in plan.objects]
    T_base_objs = [T_base_world @ o.pose(stream, frame) for o in plan.objects]
    key = plan.lidar_noise_keys.get(frame)
    noise = key_noise(plan, key) if key is not None else None
    noise_out.update({s: dataclasses.asdict(v) for s, v in (noise or {}).items()})
    if len(meshes) == 1:
        new, idx, n_cand = cast_frame_lidar(
            cloud.fields, meshes[0], T_base_objs[0], plan.lidar_origins, noise=noise, seed=frame
        )
        per = [idx]
    else:
        new, per, n_cand = cast_frame_lidar_objects(
            cloud.fields, meshes, T_base_objs, plan.lidar_origins, noise=noise, seed=frame
        )
    t["lidar_cast"] += time.perf_counter() - tic
    tic = time.perf_counter()
    if new is None:
        _link(src, dest)
        t["copy"] += time.perf_counter() - tic
        return None, n_cand, False
    write_pcd(dest, PointCloud(fields=new, header=cloud.header))
    t["lidar_write"] += time.perf_counter() - tic
    return [[int(i) for i in idx] for idx in per], n_cand, True


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


def _annotation_pose(plan: Plan, frame: int) -> tuple[str, F64]:
    """The stream and vehicle pose the frame's cuboids use: the lidar's, else the first
    camera's."""
    lidar = plan.lidar_stream
    if lidar is not None and frame in plan.T_world_base.get(lidar, {}):
        return lidar, plan.T_world_base[lidar][frame]
    cam = next(c for c in plan.cameras if frame in plan.T_world_base[c])
    return cam, plan.T_world_base[cam][frame]


def _annotation(
    plan: Plan,
    obj: PlannedObject,
    frame: int,
    views: dict[str, CameraView],
    lidar_idx: list[int] | None,
) -> FrameAnnotation | None:
    """One object's annotation of the frame (None: it shows nowhere)."""
    if not views and not lidar_idx:
        return None
    stream, T_lidar = _annotation_pose(plan, frame)
    mesh = obj.mesh(stream, frame, full=True)
    ann = FrameAnnotation(
        frame,
        cuboid_in_lidar(mesh, obj.pose(stream, frame), T_lidar),
        views,
        lidar_idx if plan.lidar_stream is not None else None,
        obj.gauge.get(frame),
        velocity=[float(v) for v in T_lidar[:3, :3].T @ obj.velocity(frame)],
    )
    if ann.lidar_indices is None and plan.lidar_stream is not None:
        ann.lidar_indices = []
    return ann


def augment_frame(plan: Plan, frame: int, out_root: Path) -> tuple[FrameRecord, list[str]]:
    """One frame (module docstring's recipe); files go under ``out_root`` at their uris."""

    t = dict.fromkeys(STAGE_KEYS, 0.0)
    seq_root = Path(plan.seq_folder)
    uris = plan.uris[frame]
    n = len(plan.objects)
    written: list[str] = []
    views: list[dict[str, CameraView]] = [{} for _ in range(n)]
    records: list[dict[str, CameraRecord]] = [{} for _ in range(n)]
    for name in plan.cameras:
        if name not in uris:
            continue
        uri = uris[name]
        recs, vws, _ = _camera_frame(
            plan, frame, name, uri_to_path(seq_root, uri), uri_to_path(out_root, uri), t
        )
        written.append(uri.lstrip("/"))
        for k in range(n):
            records[k][name] = recs[k]
            if vws[k] is not None:
                views[k][name] = vws[k]  # type: ignore[assignment]
    lidar_idx: list[list[int]] | None = None
    n_cand = 0
    noise: dict[int, dict[str, float]] = {}
    if plan.lidar_stream is not None and plan.lidar_stream in uris:
        uri = uris[plan.lidar_stream]
        lidar_idx, n_cand, _ = _lidar_frame(
            plan, frame, uri_to_path(seq_root, uri), uri_to_path(out_root, uri), t, noise
        )
        written.append(uri.lstrip("/"))
    objects = []
    for k, obj in enumerate(plan.objects):
        idx = None if lidar_idx is None else lidar_idx[k]
        ann = _annotation(plan, obj, frame, views[k], idx)
        objects.append(ObjectFrame(ann, records[k], len(idx or [])))
    return FrameRecord(frame, objects, n_cand, t, noise), written


def augment_frames(plan: Plan, frames: Iterable[int], out_root: str | Path) -> ChunkResult:
    """Augment a chunk of frames: writes their augmented or linked camera and lidar files
    under ``out_root`` (same relative paths as the input); returns the records. The
    images the plan decoded in this process are used where they fit and then dropped
    (:func:`.plan.take_decoded`: a process's first chunk after its plan starts with the
    first frame)."""
    tic = time.perf_counter()
    out_root = Path(out_root)
    records, files = [], []
    try:
        for f in frames:
            rec, written = augment_frame(plan, int(f), out_root)
            records.append(rec)
            files += written
    finally:
        drop_decoded()
    return ChunkResult(str(out_root), files, records, time.perf_counter() - tic)
