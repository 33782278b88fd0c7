"""AR quality of the augmented object on a sequence with ground truth (synthetic data).

Runs after the augmentation, like an evaluation: the augmentation itself never reads
``ground_truth/``. The object is placed twice, by the same placement spec:

- *estimated*: on the prepared sequence (the strategy's poses and extracted tracks), and
  rendered with the estimated poses: what the augmentation wrote;
- *true*: on a prepared sequence made of the ground truth (:func:`truth_prepared`: the
  dense true poses, the true centrelines, the true world frame), and rendered with the
  true poses at each camera's timestamp: where the object should have appeared.

Per camera: the anchor pixel error (the object origin's pixel, estimated vs true) and
the IoU of the visible masks (alpha > 0.5), mean and max / min over the frames where
either render shows the object. Pixels are at the images' resolution and, for
comparison with the paper's table, also at the sensors' full resolution.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry.geodesy import WorldFrame
from geometry.poses import PoseTrack
from geometry.transforms import transform_points
from worker.augmentation.frame import camera_renderer
from worker.augmentation.placement import resolve_placement
from worker.augmentation.plan import NEAR_PLANE_M
from worker.augmentation.proxies import build_proxies
from worker.osdar.sequence import Sequence
from worker.preparation.artifact import PreparedSequence
from worker.preparation.centreline import Centreline

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def truth_prepared(seq_folder: str | Path) -> Any:
    """A PreparedSequence made of ``ground_truth/`` (dense true poses, true centrelines,
    true world frame; no planes, poles or calibration point)."""

    gt = Path(seq_folder) / "ground_truth"
    dense = gt / "poses_dense.csv"
    track = PoseTrack.from_csv(dense if dense.is_file() else gt / "poses.csv")
    cls = [Centreline.from_json(d) for d in json.loads((gt / "centrelines.json").read_text())]
    cls.sort(key=lambda c: not c.ego)
    return PreparedSequence(
        key="ground_truth",
        world=WorldFrame.from_json(json.loads((gt / "world.json").read_text())),
        track=track,
        centrelines=cls,
        planes=[],
        poles=[],
        calibration=None,
        summary={"strategy": "ground_truth"},
    )


def true_object_pose(plan: Any, truth: Any, seq: Sequence | None = None) -> F64:
    """T_world_obj (4, 4) in the TRUE world frame for the plan's placement spec."""

    spec = plan.spec.placement.to_spec()
    if spec.mode == "world":  # the spec's point is in the estimated world frame
        est_world = WorldFrame.from_json(plan.info["world"])
        T = truth.world.T_world_other(est_world)
        assert spec.xyz is not None
        z = spec.xyz[2] if spec.xyz[2] is not None else plan.T_world_obj[2, 3]
        p = transform_points(T, np.array([[spec.xyz[0], spec.xyz[1], z]]))[0]
        spec = type(spec)("world", yaw_deg=spec.yaw_deg, xyz=(p[0], p[1], p[2]))
    lidar = plan.lidar_stream or next(iter(plan.cameras))
    frame_times = _times(seq or Sequence.open(plan.seq_folder), lidar)
    kw = {"ego": truth.ego, "track": truth.track, "frame_times": frame_times, "poles": []}
    nominal = resolve_placement(spec, proxies=None, obj=plan.obj_full, **kw)
    p0 = nominal.T_world_obj[:3, 3]
    proxies = build_proxies(truth, p0, p0[None], ground_z=None)
    return resolve_placement(spec, proxies=proxies, obj=plan.obj_full, **kw).T_world_obj


def _times(seq: Sequence, stream: str) -> dict[int, float]:
    ts = seq.timestamps(stream)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


@dataclass
class ObjectTruth:
    """What the reference render needs, made once per plan and process: the ground
    truth, the object's true pose, the proxies that occlude it, each camera's frame times.
    """

    truth: Any  # PreparedSequence of the ground truth
    T_world_obj: F64  # (4, 4) in the true world frame
    proxies: Any
    times: dict[str, dict[int, float]]


#: The process's ObjectTruth of the last plans evaluated (a chunk's frames come one at a
#: time; the truth, the placement and the proxies are the same for all of them).
_TRUTHS: dict[tuple[str, str], ObjectTruth] = {}


def object_truth(plan: Any, truth: Any = None) -> ObjectTruth:
    """The reference of ``plan`` (``truth``: a PreparedSequence of the ground truth,
    default :func:`truth_prepared`); cached per sequence and spec unless ``truth`` is
    given."""

    # the true pose of a world-frame placement depends on the estimated world frame too
    world = json.dumps(plan.info.get("world"), sort_keys=True, default=str)
    key = (str(plan.seq_folder), plan.spec.model_dump_json() + world)
    if truth is None and key in _TRUTHS:
        return _TRUTHS[key]
    given = truth is not None
    truth = truth if given else truth_prepared(plan.seq_folder)
    seq = Sequence.open(plan.seq_folder)
    T_world_obj = true_object_pose(plan, truth, seq)
    cam_xyz = np.stack([truth.track.T[:, :3, 3]]).reshape(-1, 3)
    proxies = build_proxies(truth, T_world_obj[:3, 3], cam_xyz[:: max(1, len(cam_xyz) // 200)])
    out = ObjectTruth(truth, T_world_obj, proxies, {n: _times(seq, n) for n in plan.cameras})
    if not given:
        _TRUTHS.clear()  # one plan at a time is what a worker process evaluates
        _TRUTHS[key] = out
    return out


def wants_object_errors(plan: Any) -> bool:
    """Whether ``plan``'s object errors can be measured: the sequence has ground truth
    and the plan one static object (the reference render knows one, unoccluded by
    others)."""

    return (Path(plan.seq_folder) / "ground_truth").is_dir() and (
        len(plan.objects) == 1 and not plan.objects[0].moving
    )


def frame_object_errors(
    plan: Any, records: list[Any], ref: ObjectTruth | None = None
) -> dict[int, dict[str, dict[str, float | None]]]:
    """Per frame and camera, the anchor pixel error (None: not counted) and the mask IoU
    (None: the object shows in neither render) of the augmentation's ``records`` against
    a render with the true poses; frames a camera has no timestamp for are left out."""

    ref = ref if ref is not None else object_truth(plan)
    out: dict[int, dict[str, dict[str, float | None]]] = {}
    for name, cam in plan.cameras.items():
        times = ref.times[name]
        renderer = camera_renderer(cam, plan.spec.render.antialias)
        for rec in records:
            est = rec.cameras.get(name)
            if est is None or rec.frame_idx not in times:
                continue
            T_true = ref.truth.track.interpolate(np.array([times[rec.frame_idx]]))[0]
            r = renderer.render(
                plan.obj_render, ref.T_world_obj, T_true, ref.proxies, plan.lights[name],
                near=NEAR_PLANE_M,
            )  # fmt: skip
            true_vis = r.roi is not None and bool(np.any(r.alpha > 0.5))
            a_est = np.asarray(est.anchor_uv, dtype=np.float64)
            err = None
            if np.all(np.isfinite(a_est)) and np.all(np.isfinite(r.anchor_uv)):
                if est.visible or true_vis:
                    err = float(np.linalg.norm(a_est - r.anchor_uv))
            iou = _iou(est, r) if (est.visible or true_vis) else None
            out.setdefault(int(rec.frame_idx), {})[name] = {"anchor_px": err, "iou": iou}
    return out


def measure_chunk(plan: Any, chunk: Any) -> None:
    """Where ``plan``'s object errors can be measured (:func:`wants_object_errors`), add
    the chunk's frames' values to ``chunk.object_errors``: in the process that augmented
    them, in parallel with the other chunks, so that the finish only sums them up. A
    failure is logged and left to the finish, which measures what a chunk lacks and
    records why it could not."""

    if not wants_object_errors(plan):
        return
    try:
        chunk.object_errors.update(frame_object_errors(plan, chunk.frames))
    except (ValueError, OSError, KeyError) as exc:
        log.warning("object errors of frames %s not measured here: %s",
                    [r.frame_idx for r in chunk.frames][:5], exc)  # fmt: skip


def summarize_object_errors(
    plan: Any, T_world_obj: F64, per_frame: dict[int, dict[str, dict[str, float | None]]]
) -> dict[str, Any]:
    """The metrics' ``object_errors`` from :func:`frame_object_errors`' values."""

    out: dict[str, Any] = {
        "reference": "ground_truth/poses_dense.csv + centrelines.json",
        "true_object_xyz": np.asarray(T_world_obj)[:3, 3].tolist(),
        "cameras": {},
    }
    for name, cam in plan.cameras.items():
        vals = [per_frame[f][name] for f in sorted(per_frame) if name in per_frame[f]]
        anchor_err = [v["anchor_px"] for v in vals if v["anchor_px"] is not None]
        ious = [v["iou"] for v in vals if v["iou"] is not None]
        scale = 1.0 / cam.scale if cam.scale > 0 else 1.0
        out["cameras"][name] = {
            "frames": len(ious),
            "anchor_px_mean": _stat(anchor_err, np.mean),
            "anchor_px_max": _stat(anchor_err, np.max),
            "anchor_px_full_res_mean": _stat([e * scale for e in anchor_err], np.mean),
            "mask_iou_mean": _stat(ious, np.mean),
            "mask_iou_min": _stat(ious, np.min),
        }
    return out


def evaluate_object(
    plan: Any,
    records: list[Any],
    truth: Any = None,
    measured: dict[int, dict[str, dict[str, float | None]]] | None = None,
) -> dict[str, Any]:
    """Anchor pixel error and mask IoU per camera (module docstring).

    records : the augmentation's FrameRecords (estimated anchors and masks).
    truth : a PreparedSequence of the ground truth (default :func:`truth_prepared`).
    measured : per-frame values already measured (the chunks'); only the other frames
        are rendered here.
    """

    ref = object_truth(plan, truth)
    per_frame = dict(measured or {})
    todo = [r for r in records if int(r.frame_idx) not in per_frame]
    if todo:
        per_frame.update(frame_object_errors(plan, todo, ref))
    return summarize_object_errors(plan, ref.T_world_obj, per_frame)


def _stat(values: list[float], fn: Any) -> float | None:
    return float(fn(values)) if values else None


def _iou(est: Any, r: Any) -> float:
    """IoU of the estimated record's mask and a render's alpha > 0.5 (on their union box)."""
    boxes = []
    if est.mask_roi is not None:
        boxes.append(est.mask_roi)
    if r.roi is not None:
        boxes.append(r.roi)
    if not boxes:
        return 0.0
    u0 = min(b[0] for b in boxes)
    v0 = min(b[1] for b in boxes)
    u1 = max(b[2] for b in boxes)
    v1 = max(b[3] for b in boxes)
    a = np.zeros((v1 - v0, u1 - u0), bool)
    if est.mask_roi is not None and est.mask_bits is not None:
        eu0, ev0, eu1, ev1 = est.mask_roi
        n = (ev1 - ev0) * (eu1 - eu0)
        bits = np.unpackbits(np.frombuffer(est.mask_bits, np.uint8), count=n)
        a[ev0 - v0 : ev1 - v0, eu0 - u0 : eu1 - u0] = bits.reshape(ev1 - ev0, eu1 - eu0) > 0
    b = np.zeros_like(a)
    if r.roi is not None:
        ru0, rv0, ru1, rv1 = r.roi
        b[rv0 - v0 : rv1 - v0, ru0 - u0 : ru1 - u0] = r.alpha > 0.5
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
