"""What the dashboard pages show: plain dicts and rows made from the tables' rows.

No HTML here (the templates in ``service/dashboard/templates`` lay these out) and no
pipeline import: a job's metrics JSON and preview keys are read as data. Ownership is
checked by the resource services (``service/services/jobs.py`` and friends); these
functions only shape what they return.
"""

from __future__ import annotations

import math
import re
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from osdar_platform.models import ApiKey, Job, JobState, Sequence
from service.schemas import spec_objects

#: At most this many jobs in one progress poll.
MAX_POLL_IDS = 100
#: Preview file names written by ``worker/packaging.py`` and ``worker/evaluation/evaluate.py``.
_FRAME_PREVIEW = re.compile(r"^(?P<name>[A-Za-z0-9_]+?)_(?P<frame>\d+)\.(?:png|jpe?g)$")
_LIDAR_BEV = "lidar_bev"
_PLOT_NAME = "rpe_jitter.png"
_POSITIONS = ("first", "middle", "last")


# ---------------------------------------------------------------------------- progress
def percent(job: Job) -> float:
    """Progress in percent (0..100); a succeeded job is 100 whatever its counters say."""
    if job.state == JobState.SUCCEEDED:
        return 100.0
    if job.progress_total <= 0:
        return 0.0
    return max(0.0, min(100.0, 100.0 * job.progress_done / job.progress_total))


def job_status(job: Job) -> dict[str, Any]:
    """The live part of a job (what the pages' poller reads)."""
    return {
        "id": job.id,
        "state": job.state.value,
        "terminal": job.state.terminal,
        "stage": job.stage,
        "done": job.progress_done,
        "total": job.progress_total,
        "percent": round(percent(job), 1),
        "error": job.error,
        "has_result": job.state.value == "SUCCEEDED" and job.result_key is not None,
        "updated_at": _iso(job.updated_at),
    }


def jobs_status(
    *, session: Session, owner: ApiKey, ids: list[str], everyone: bool = False
) -> list[dict[str, Any]]:
    """:func:`job_status` of those of ``ids`` that belong to ``owner`` (others are left out,
    unless ``everyone``: an operator)."""
    wanted = list(dict.fromkeys(i for i in ids if i))[:MAX_POLL_IDS]
    if not wanted:
        return []
    mine = [] if everyone else [Job.owner_id == owner.id]
    rows = session.scalars(select(Job).where(*mine, Job.id.in_(wanted)))
    by_id = {j.id: j for j in rows}
    return [job_status(by_id[i]) for i in wanted if i in by_id]


def sequence_names(
    *, session: Session, owner: ApiKey, ids: set[str | None], everyone: bool = False
) -> dict[str, str]:
    """Sequence id -> name, for the owner's sequences among ``ids`` (all: ``everyone``)."""
    wanted = sorted(i for i in ids if i)
    if not wanted:
        return {}
    mine = [] if everyone else [Sequence.owner_id == owner.id]
    rows = session.execute(select(Sequence.id, Sequence.name).where(*mine, Sequence.id.in_(wanted)))
    return {sid: name for sid, name in rows}


def key_names(*, session: Session, ids: set[int]) -> dict[int, str]:
    """API key id -> name (an operator's pages say whose a job is)."""
    if not ids:
        return {}
    rows = session.execute(select(ApiKey.id, ApiKey.name).where(ApiKey.id.in_(sorted(ids))))
    return {kid: name for kid, name in rows}


# ---------------------------------------------------------------------------- spec
def object_label(spec: dict[str, Any]) -> str:
    """The job's objects: ``cow``, ``rock ×2``, ``person (moving) + asset a81b``."""
    labels = []
    for _, entry in spec_objects(spec):
        obj = entry.get("object") or {}
        what = obj.get("builtin") or (f"asset {obj['asset_id']}" if obj.get("asset_id") else "?")
        scale = obj.get("scale")
        what = what if scale in (None, 1, 1.0) else f"{what} ×{scale:g}"
        labels.append(what + (" (moving)" if entry.get("motion") else ""))
    return " + ".join(labels)


def placement_label(spec: dict[str, Any]) -> str:
    """Where the job's objects stand (or how they move), ``; ``-separated."""
    out = []
    for _, entry in spec_objects(spec):
        m = entry.get("motion")
        if m:
            a = ", ".join(_num(v) for v in (m.get("path") or [[]])[0])
            out.append(
                f"moving ({m.get('mode', 'track')}) from ({a}) at {_num(m.get('speed_mps'))} m/s"
            )
        else:
            out.append(_one_placement(entry.get("placement") or {}))
    return "; ".join(out)


def _one_placement(p: dict[str, Any]) -> str:
    mode = p.get("mode")
    if mode == "track":
        return (
            f"track: s = {_num(p.get('s'))} m, offset {_num(p.get('offset'))} m, "
            f"yaw {_num(p.get('yaw_deg'))}°"
        )
    xyz = p.get("xyz") or []
    where = ", ".join(_num(v) for v in xyz)
    frame = f" (frame {p['frame_idx']})" if p.get("frame_idx") is not None else ""
    return f"{mode}: ({where}){frame}"


def spec_summary(spec: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, value) rows of a job spec, in reading order."""
    rng = spec.get("frame_range")
    rows = [
        ("Cameras", ", ".join(spec.get("cameras") or []) or "-"),
        ("Lidar", "yes" if spec.get("lidar") else "no"),
        ("Object", object_label(spec)),
        ("Placement", placement_label(spec)),
        ("Strategy", str(spec.get("strategy") or "auto")),
        ("Frames", "all" if not rng else f"{rng[0]} – {rng[1]}"),
    ]
    if spec.get("clicks"):
        rows.append(("Clicks", ", ".join(sorted(spec["clicks"]))))
    return rows


def timings_rows(timings: dict[str, Any] | None) -> list[tuple[str, str]]:
    """(stage, seconds) in the order the stages ran, and the total."""
    rows: list[tuple[str, str]] = []
    total = 0.0
    for stage, seconds in (timings or {}).items():
        if isinstance(seconds, int | float) and math.isfinite(seconds):
            rows.append((stage, f"{seconds:.2f}"))
            total += float(seconds)
    if rows:
        rows.append(("total", f"{total:.2f}"))
    return rows


# ---------------------------------------------------------------------------- metrics
def _num(value: Any, digits: int = 2) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return "-"
    if not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}"


def _stats(m: dict[str, Any] | None) -> dict[str, str]:
    """``{"mean", "std", "max", "n"}`` statistics as text."""
    m = m or {}
    mean, std = m.get("mean"), m.get("std")
    text = "-" if mean is None else _num(mean) + ("" if std is None else f" ± {_num(std)}")
    return {"mean_std": text, "max": _num(m.get("max")), "n": str(m.get("n", "-"))}


def rpe_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """RPE and jitter per camera and strategy (true landmarks), then the clicked landmark."""
    ev = metrics.get("evaluation") or {}
    chosen = ev.get("strategy")
    rows = []
    landmark = (ev.get("ground_truth") or {}).get("landmark_rpe") or {}
    for cam in sorted(landmark):
        for strategy in sorted(landmark[cam] or {}):
            m = landmark[cam][strategy] or {}
            rows.append(
                {
                    "camera": cam,
                    "strategy": strategy,
                    "source": "true landmarks",
                    "chosen": strategy == chosen,
                    "rpe": _stats(m.get("rpe_px")),
                    "jitter": _stats(m.get("jitter_px")),
                }
            )
    for cam, m in sorted((ev.get("rpe") or {}).items()):
        rows.append(
            {
                "camera": cam,
                "strategy": chosen or "-",
                "source": "clicked landmark",
                "chosen": True,
                "rpe": _stats((m or {}).get("rpe_px")),
                "jitter": _stats((m or {}).get("jitter_px")),
            }
        )
    return rows


def pose_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """True pose error per strategy (synthetic sequences only)."""
    ev = metrics.get("evaluation") or {}
    pose = (ev.get("ground_truth") or {}).get("pose_error") or {}
    return [
        {
            "strategy": name,
            "chosen": name == ev.get("strategy"),
            "t_mean": _num(m.get("translation_m_mean"), 3),
            "t_max": _num(m.get("translation_m_max"), 3),
            "r_mean": _num(m.get("rotation_deg_mean"), 3),
            "r_max": _num(m.get("rotation_deg_max"), 3),
        }
        for name, m in sorted(pose.items())
        if isinstance(m, dict)
    ]


def object_error_rows(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """The placed object's errors per camera (anchor pixels, mask IoU) against the truth."""
    errors = (metrics.get("augmentation") or {}).get("object_errors") or {}
    return [
        {
            "camera": cam,
            "frames": str(m.get("frames", "-")),
            "anchor_mean": _num(m.get("anchor_px_mean")),
            "anchor_max": _num(m.get("anchor_px_max")),
            "iou_mean": _num(m.get("mask_iou_mean"), 3),
            "iou_min": _num(m.get("mask_iou_min"), 3),
        }
        for cam, m in sorted((errors.get("cameras") or {}).items())
        if isinstance(m, dict)
    ]


def augmentation_rows(metrics: dict[str, Any]) -> list[tuple[str, str]]:
    """A few facts of the augmentation: object, frames annotated, lidar points."""
    aug = metrics.get("augmentation") or {}
    if not aug:
        return []
    obj = aug.get("object") or {}
    frames = aug.get("frames") or {}
    lidar = aug.get("lidar") or {}
    rows = [
        ("Object class", str(obj.get("class", "-"))),
        (
            "Frames annotated",
            f"{frames.get('annotated', '-')} of {frames.get('augmented_range', '-')}",
        ),
    ]
    for cam, c in sorted((aug.get("cameras") or {}).items()):
        rows.append((f"Visible in {cam}", f"{c.get('visible_frames', '-')} frames"))
    if lidar:
        rows.append(("Lidar object points", str(lidar.get("object_points_total", "-"))))
    return rows


def metrics_view(metrics: dict[str, Any] | None) -> dict[str, Any] | None:
    """Everything the metrics section of a job page shows, or None before there is any."""
    if not metrics:
        return None
    ev = metrics.get("evaluation") or {}
    warnings = [str(w) for w in ev.get("warnings") or []]
    warnings += [str(w) for w in (metrics.get("augmentation") or {}).get("warnings") or []]
    return {
        "strategy": ev.get("strategy"),
        "requested_strategy": ev.get("requested_strategy"),
        "rpe": rpe_rows(metrics),
        "pose": pose_rows(metrics),
        "objects": object_error_rows(metrics),
        "augmentation": augmentation_rows(metrics),
        "warnings": warnings,
    }


# ---------------------------------------------------------------------------- previews
def preview_groups(keys: list[str], cameras: list[str]) -> dict[str, Any]:
    """Preview store keys sorted into what the job page shows, with their indices.

    ``{"cameras": [{"camera", "frames": [{"position", "frame", "index"}]}],
    "lidar": [{"frame", "index"}], "plot": index | None, "other": [{"name", "index"}]}``:
    per camera the first, middle and last frames (``<camera>_<frame>.png``), the lidar
    bird's-eye views (``lidar_bev_<frame>.png``), the RPE/jitter plot.
    """
    per_camera: dict[str, list[tuple[int, int]]] = {}
    lidar, other = [], []
    plot = None
    for index, key in enumerate(keys):
        name = str(key).rsplit("/", 1)[-1]
        if name == _PLOT_NAME:
            plot = index
            continue
        m = _FRAME_PREVIEW.match(name)
        if m is None:
            other.append({"name": name, "index": index})
        elif m["name"] == _LIDAR_BEV:
            lidar.append({"frame": int(m["frame"]), "index": index})
        else:
            per_camera.setdefault(m["name"], []).append((int(m["frame"]), index))
    order = [c for c in cameras if c in per_camera] + sorted(set(per_camera) - set(cameras))
    groups = []
    for cam in order:
        shots = sorted(per_camera[cam])
        if len(shots) == 3:
            labels = list(_POSITIONS)
        elif len(shots) == 2:
            labels = ["first", "last"]
        else:
            labels = ["frame"] * len(shots)
        groups.append(
            {
                "camera": cam,
                "frames": [
                    {"position": pos, "frame": f, "index": i}
                    for pos, (f, i) in zip(labels, shots, strict=True)
                ],
            }
        )
    return {"cameras": groups, "lidar": lidar, "plot": plot, "other": other}


# ---------------------------------------------------------------------------- format
def _iso(value: datetime | None) -> str | None:
    return None if value is None else value.isoformat()


def when(value: datetime | None) -> str:
    """A timestamp as the pages show it (UTC, seconds)."""
    return "-" if value is None else value.strftime("%Y-%m-%d %H:%M:%S UTC")


def duration(start: datetime | None, end: datetime | None) -> str:
    if start is None or end is None:
        return "-"
    s = max(0.0, (end - start).total_seconds())
    return f"{s:.1f} s" if s < 120 else f"{s / 60:.1f} min"


def size(n: int | None) -> str:
    if n is None:
        return "-"
    value = float(n)
    for unit in ("B", "KB", "MB", "GB"):
        if value < 1000 or unit == "GB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1000
    return f"{n} B"  # pragma: no cover


__all__ = [
    "MAX_POLL_IDS",
    "duration",
    "job_status",
    "jobs_status",
    "metrics_view",
    "percent",
    "preview_groups",
    "sequence_names",
    "size",
    "spec_summary",
    "timings_rows",
    "when",
]
