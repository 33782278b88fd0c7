"""The virtual object added to the OpenLABEL file the way OSDaR23 annotates objects.

Per frame: a ``cuboid`` in the lidar frame and a ``vec`` of the lidar point indices on
the object; per camera where the object is visible: a ``bbox`` [x_center, y_center, width,
height] and a closed ``poly2d`` outline of the visible mask. Names follow OSDaR23:
``<sensor>__<kind>__<class>``. Attributes: ``occlusion`` (OSDaR23's buckets), truncation
flags, and provenance (``isSynthetic`` true, ``generator`` osdar-ar, ``osdarArClass``, the
exact obstacle; for a built-in obstacle also the text attributes ``osdarArSeed`` (the seed
its shape and colours were drawn from), ``osdarArPose`` and ``osdarArVariant``: with the
class they rebuild the same mesh). OSDaR23 has no class for rocks or fallen trees: they are typed
``obstacle`` (animals ``animal``, people ``person``), the exact class in ``osdarArClass``.

Gauge labels (:mod:`~worker.augmentation.gauge`), on every element of the frame when the
plan has them: boolean ``gaugeIntrusion`` (inside the train's clearance envelope ahead),
num ``gaugeLateralDistanceM`` (to the envelope's side, negative inside) and
``trackDistanceM`` (along the ego track from the train, negative behind); on a camera's
``bbox`` and ``poly2d`` also num ``visiblePixels`` (the object's visible mask in that
camera). A dataset user filters by them.

Motion, on the cuboid (and the lidar ``vec``) of every frame: the ``vec`` attribute
``velocity`` [vx, vy, vz] (m/s, the object's own velocity over the ground, expressed in
the lidar frame's axes at that frame's lidar timestamp; a static object's is [0, 0, 0])
and the num ``speedMps`` (its length). A moving object's cuboid is its pose at the
lidar timestamp, so cuboid centres move at that velocity plus the train's own motion.

Several objects in one sequence: each is its own OpenLABEL object (its own uid and
``<class>_synthetic_<n>`` name), its masks cut where another object hides it.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry.transforms import invert_T, matrix_to_quat, transform_points
from renderer.mesh import ObjectMesh
from worker.augmentation.gauge import GaugeLabel
from worker.osdar.labels import frame_intervals

F64 = NDArray[np.float64]

OSDAR_TYPE = {
    "person": "person",
    "cow": "animal",
    "horse": "animal",
    "elephant": "animal",
    "rock": "obstacle",
    "fallen_tree": "obstacle",
}
# Fixed namespace so that the same job gives the same object UUIDs.
_NAMESPACE = uuid.UUID("6f1c3a52-3c55-4f0e-9a0c-0d5a1e0f2b11")


def osdar_type(obj_class: str) -> str:
    return OSDAR_TYPE.get(obj_class, "obstacle")


def occlusion_bucket(visible_fraction: float) -> str:
    """OSDaR23's occlusion text from the visible fraction of the object's pixels."""
    occ = 1.0 - float(np.clip(visible_fraction, 0.0, 1.0))
    if occ < 0.25:
        return "0-25 %"
    if occ < 0.50:
        return "25-50 %"
    if occ < 0.75:
        return "50-75 %"
    if occ < 0.999:
        return "75-99 %"
    return "100 %"


#: Name of the per-frame ``num`` attribute of a camera's bbox: the 90 % bound (px) on the
#: object's placement error in that camera (OSDaR23 attributes are camelCase).
PLACEMENT_BOUND_ATTRIBUTE = "arPlacementBoundPx"
#: Gauge labels (module docstring): boolean, num (m), num (m), and num (px) per camera.
GAUGE_INTRUSION_ATTRIBUTE = "gaugeIntrusion"
GAUGE_LATERAL_ATTRIBUTE = "gaugeLateralDistanceM"
TRACK_DISTANCE_ATTRIBUTE = "trackDistanceM"
VISIBLE_PIXELS_ATTRIBUTE = "visiblePixels"
#: Motion: vec (m/s, lidar frame axes) and num (m/s) on the cuboid and the lidar vec.
VELOCITY_ATTRIBUTE = "velocity"
SPEED_ATTRIBUTE = "speedMps"

# Provenance of a built-in obstacle (text attributes): the ``mesh.meta`` keys they carry.
BUILTIN_PROVENANCE = {"seed": "osdarArSeed", "pose": "osdarArPose", "variant": "osdarArVariant"}


def builtin_provenance(meta: dict[str, Any]) -> dict[str, str]:
    """The provenance text attributes of a built-in obstacle from its ``mesh.meta``
    (``renderer.assets.obstacles``: ``seed``, ``pose``, ``variant``); keys the mesh does
    not have, or that are not a plain value (an uploaded mesh's pose dict), are left out."""
    out = {}
    for key, name in BUILTIN_PROVENANCE.items():
        v = meta.get(key)
        if isinstance(v, (str, int)) and not isinstance(v, bool):
            out[name] = str(v)
    return out


@dataclass
class CameraView:
    """What one camera sees of the object in one frame (full-image pixel coordinates)."""

    bbox: tuple[float, float, float, float]  # x_center, y_center, width, height
    outline: list[float]  # flat [x0, y0, x1, y1, ...], closed
    visible_fraction: float
    truncated: bool
    #: 90 % bound (px) on the object's placement error in this camera
    #: (:mod:`~worker.augmentation.confidence`); None: not known
    placement_bound_px: float | None = None
    #: pixels of the object's visible mask (alpha > 0.5); None: not known
    visible_pixels: int | None = None


@dataclass
class FrameAnnotation:
    """The object in one frame: cuboid in the lidar frame, camera views, lidar indices."""

    frame_idx: int
    cuboid: list[float]  # [x, y, z, qx, qy, qz, qw, sx, sy, sz]
    views: dict[str, CameraView] = field(default_factory=dict)
    lidar_indices: list[int] | None = None
    #: the object against the train's clearance envelope in this frame (None: not known)
    gauge: GaugeLabel | None = None
    #: [vx, vy, vz] m/s over the ground in the lidar frame's axes (None: not known)
    velocity: list[float] | None = None


def gauge_attributes(g: GaugeLabel | None) -> tuple[dict[str, bool], dict[str, float]]:
    """The boolean and num attributes of a gauge label (empty without one)."""
    if g is None:
        return {}, {}
    return {GAUGE_INTRUSION_ATTRIBUTE: bool(g.intrusion)}, {
        GAUGE_LATERAL_ATTRIBUTE: round(g.lateral_distance_m, 3),
        TRACK_DISTANCE_ATTRIBUTE: round(g.track_distance_m, 3),
    }


def cuboid_in_lidar(obj: ObjectMesh, T_world_obj: F64, T_world_base: F64) -> list[float]:
    """OpenLABEL cuboid [x, y, z, qx, qy, qz, qw, sx, sy, sz] of the object's bounding box
    in the lidar (base) frame at a frame's pose."""
    b = obj.bounds
    centre_obj = 0.5 * (b[0] + b[1])
    T_base_obj = invert_T(T_world_base) @ T_world_obj
    c = transform_points(T_base_obj, centre_obj[None])[0]
    q = matrix_to_quat(T_base_obj[:3, :3])
    return [*map(float, c), *map(float, q), *map(float, obj.size)]


def mask_outline(
    alpha: NDArray,
    offset_uv: tuple[int, int],
    threshold: float = 0.5,
    epsilon_px: float = 0.0,
) -> list[float]:
    """Closed outline (flat list, full-image pixels) of the largest blob of a mask.

    alpha : (h, w) coverage of a region of interest whose top-left pixel is ``offset_uv``.
    epsilon_px : Douglas-Peucker tolerance; 0 keeps the exact boundary-pixel polygon
        (straight runs compressed), which ``cv2.fillPoly`` turns back into the blob.
        Small objects lose most to any simplification (a 16 px wide person: IoU 0.86
        at 0.5 px), so the default is exact.
    """
    m = (np.asarray(alpha) >= threshold).astype(np.uint8)
    if not m.any():
        return []
    contours, hier = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    outer = [i for i in range(len(contours)) if hier[0, i, 3] < 0]
    k = max(outer, key=lambda i: cv2.contourArea(contours[i]))
    c = contours[k]
    if epsilon_px > 0:
        c = cv2.approxPolyDP(c, epsilon_px, True)
    c = c.reshape(-1, 2).astype(np.float64)
    # Holes (e.g. between legs) are spliced in through zero-width bridges (a keyhole
    # polygon): one closed poly2d that fills back to the blob without its holes.
    for j in range(len(contours)):
        if hier[0, j, 3] == k and len(contours[j]) >= 3:
            c = _splice_hole(c, contours[j].reshape(-1, 2).astype(np.float64))
    c += np.asarray(offset_uv, dtype=np.float64)
    return [float(v) for v in c.ravel()]


def _splice_hole(outer: F64, hole: F64) -> F64:
    """Keyhole: ``outer`` (n, 2) -> to the nearest ``hole`` (m, 2) vertex, round the hole,
    back. OpenCV returns holes with the opposite orientation to their outer contour."""
    d = np.linalg.norm(outer[:, None, :] - hole[None, :, :], axis=2)
    i, j = np.unravel_index(int(np.argmin(d)), d.shape)
    ring = np.concatenate([hole[j:], hole[: j + 1]])
    return np.concatenate([outer[: i + 1], ring, outer[i:]])


def _entry(
    name: str,
    kind: str,
    cs: str,
    val: Any,
    uid: str,
    text: dict[str, str],
    booleans: dict[str, bool],
    extra: dict[str, Any] | None = None,
    numbers: dict[str, float] | None = None,
    vectors: dict[str, list[float]] | None = None,
) -> dict[str, Any]:
    e: dict[str, Any] = {"name": name, "val": val}
    if extra:
        e.update(extra)
    e.update(
        {
            "coordinate_system": cs,
            "uid": uid,
            "attributes": {
                "boolean": [{"name": k, "val": v} for k, v in booleans.items()],
                "num": [{"name": k, "val": float(v)} for k, v in (numbers or {}).items()],
                "text": [{"name": k, "val": v} for k, v in text.items()],
                "vec": [{"name": k, "val": list(v)} for k, v in (vectors or {}).items()],
            },
        }
    )
    return e


class _Pointers:
    """The object's ``object_data_pointers``: per element name, its type, the kinds of its
    attributes (from its first occurrence) and the frames it occurs in."""

    def __init__(self) -> None:
        self.by_name: dict[str, dict[str, Any]] = {}

    def point(
        self,
        name: str,
        kind: str,
        frame: int,
        text: dict[str, str],
        booleans: dict[str, bool],
        numbers: dict[str, float] | None = None,
        vectors: dict[str, list[float]] | None = None,
    ) -> None:
        p = self.by_name.setdefault(
            name,
            {
                "attribute_pointers": {},
                "frame_intervals": [],
                "type": kind,
                "_frames": [],
            },
        )
        kinds = {**{k: "text" for k in text}, **{k: "boolean" for k in booleans}}
        kinds.update({k: "num" for k in numbers or {}})
        kinds.update({k: "vec" for k in vectors or {}})
        p["attribute_pointers"].update(kinds)
        p["_frames"].append(frame)

    def finish(self) -> dict[str, dict[str, Any]]:
        for p in self.by_name.values():
            p["frame_intervals"] = frame_intervals(p.pop("_frames"))
        return self.by_name


@dataclass
class _FrameData:
    """One frame's ``object_data`` of the object, its pointers kept up to date."""

    frame_idx: int
    seed: str
    pointers: _Pointers
    data: dict[str, list[dict[str, Any]]] = field(default_factory=dict)

    def add(
        self,
        kind: str,
        name: str,
        cs: str,
        val: Any,
        uid_key: str,
        text: dict[str, str],
        booleans: dict[str, bool],
        extra: dict[str, Any] | None = None,
        numbers: dict[str, float] | None = None,
        vectors: dict[str, list[float]] | None = None,
    ) -> None:
        uid = str(uuid.uuid5(_NAMESPACE, f"{self.seed}/{self.frame_idx}/{uid_key}"))
        entry = _entry(name, kind, cs, val, uid, text, booleans, extra=extra, numbers=numbers,
                       vectors=vectors)  # fmt: skip
        self.data.setdefault(kind, []).append(entry)
        self.pointers.point(name, kind, self.frame_idx, text, booleans, numbers, vectors)


def _add_lidar_elements(
    fd: _FrameData, fa: FrameAnnotation, otype: str, lidar_cs: str, provenance: dict[str, str]
) -> None:
    """The cuboid and, when known, the vector of the lidar points on the object."""
    any_occl = min((v.visible_fraction for v in fa.views.values()), default=1.0)
    base_text = {"occlusion": occlusion_bucket(any_occl), **provenance}
    g_bool, g_num = gauge_attributes(fa.gauge)
    booleans = {"isSynthetic": True, **g_bool}
    nums = dict(g_num)
    vecs = None
    if fa.velocity is not None:
        vel = [round(float(v), 4) for v in fa.velocity]
        vecs = {VELOCITY_ATTRIBUTE: vel}
        nums[SPEED_ATTRIBUTE] = round(float(np.linalg.norm(vel)), 4)
    cub_name = f"{lidar_cs}__cuboid__{otype}"
    fd.add("cuboid", cub_name, lidar_cs, fa.cuboid, "cuboid", base_text, booleans,
           numbers=nums or None, vectors=vecs)  # fmt: skip
    if fa.lidar_indices is not None:
        indices = [int(i) for i in fa.lidar_indices]
        fd.add("vec", f"{lidar_cs}__vec__{otype}", lidar_cs, indices, "vec", base_text, booleans,
               numbers=nums or None, vectors=vecs)  # fmt: skip


def _add_camera_elements(
    fd: _FrameData,
    cam: str,
    view: CameraView,
    otype: str,
    provenance: dict[str, str],
    gauge: GaugeLabel | None = None,
) -> None:
    """The bounding box and, for outlines of at least 3 points, the poly2d in one camera."""
    text = {"occlusion": occlusion_bucket(view.visible_fraction), **provenance}
    g_bool, g_num = gauge_attributes(gauge)
    b = {"isSynthetic": True, "isTruncated": bool(view.truncated), **g_bool}
    bbox = [float(v) for v in view.bbox]
    shape_nums = dict(g_num)
    if view.visible_pixels is not None:
        shape_nums[VISIBLE_PIXELS_ATTRIBUTE] = float(view.visible_pixels)
    nums = dict(shape_nums)
    if view.placement_bound_px is not None:
        nums[PLACEMENT_BOUND_ATTRIBUTE] = round(view.placement_bound_px, 3)
    fd.add("bbox", f"{cam}__bbox__{otype}", cam, bbox, f"{cam}/bbox", text, b, numbers=nums or None)
    if len(view.outline) >= 6:
        fd.add(
            "poly2d",
            f"{cam}__poly2d__{otype}",
            cam,
            view.outline,
            f"{cam}/poly2d",
            text,
            b,
            extra={"closed": True, "mode": "MODE_POLY2D_ABSOLUTE"},
            numbers=shape_nums or None,
        )


def add_object(
    labels_raw: dict[str, Any],
    *,
    obj_class: str,
    frames: list[FrameAnnotation],
    seed: str = "osdar-ar",
    lidar_cs: str = "lidar",
    attributes: dict[str, str] | None = None,
) -> str:
    """Add the object to an OpenLABEL dict in place; returns its UUID.

    Frames of ``frames`` must exist in the labels. The object's name is
    ``<class>_synthetic_<n>`` with n counting synthetic objects already present.
    ``attributes`` : more provenance text attributes on every element (e.g.
    :func:`builtin_provenance`).
    """
    ol = labels_raw["openlabel"]
    otype = osdar_type(obj_class)
    oid = str(uuid.uuid5(_NAMESPACE, f"{seed}/object"))
    n_existing = sum(1 for o in ol.get("objects", {}).values() if "_synthetic_" in o["name"])
    provenance = {"generator": "osdar-ar", "osdarArClass": obj_class, **(attributes or {})}
    pointers = _Pointers()
    for fa in frames:
        fkey = str(fa.frame_idx)
        if fkey not in ol["frames"]:
            raise KeyError(f"frame {fa.frame_idx} is not in the labels")
        fd = _FrameData(fa.frame_idx, seed, pointers)
        _add_lidar_elements(fd, fa, otype, lidar_cs, provenance)
        for cam, view in sorted(fa.views.items()):
            _add_camera_elements(fd, cam, view, otype, provenance, fa.gauge)
        ol["frames"][fkey].setdefault("objects", {})[oid] = {"object_data": fd.data}
    ol.setdefault("objects", {})[oid] = {
        "name": f"{obj_class}_synthetic_{n_existing + 1:04d}",
        "type": otype,
        "frame_intervals": frame_intervals([fa.frame_idx for fa in frames]),
        "object_data_pointers": pointers.finish(),
    }
    return oid
