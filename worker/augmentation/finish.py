"""Finishing an augmentation: the chunks' files moved into the output sequence, every
other input file linked byte-identically, the object added to the labels, the metrics
written; all or nothing (:class:`~worker.osdar.writer.SequenceWriter`).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from worker.augmentation.annotations import (
    add_object,
)
from worker.augmentation.frame import STAGE_KEYS, ChunkResult, FrameRecord
from worker.augmentation.plan import Plan
from worker.evaluation.object_error import evaluate_object
from worker.json_values import jsonable
from worker.osdar.labels import load_labels
from worker.osdar.writer import SequenceWriter

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


METRICS_FILE = "metrics.json"


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
        n_linked = _assemble(writer, plan, chunks, seq_root)
        t_move = time.perf_counter() - tic

        tic = time.perf_counter()
        labels, oid, n_annotated = _labels_with_object(plan, records, seq_root)
        t_labels = time.perf_counter() - tic

        metrics = _metrics(plan, chunks, records, out_folder, oid, n_annotated)
        metrics["timings_s"].update(
            {
                "assemble": t_move,
                "labels": t_labels,
                "linked_files": n_linked,
                **(extra_timings or {}),
            }
        )
        if evaluate and (seq_root / "ground_truth").is_dir():
            _evaluate_object(metrics, plan, records)
        if plan.spec.clicks is not None or plan.info.get("calibration"):
            metrics["calibration"] = plan.info.get("calibration")
        metrics["timings_s"]["finish"] = time.perf_counter() - t_finish
        writer.write_bytes("/" + METRICS_FILE, json.dumps(jsonable(metrics), indent=1).encode())
        writer.finish(labels)
    except BaseException:
        writer.abort()
        raise
    return metrics


def _assemble(writer: SequenceWriter, plan: Plan, chunks: list[ChunkResult], seq_root: Path) -> int:
    """Move the chunks' files into the output, link every other input file but the labels
    unchanged; the number of files linked."""
    done: set[str] = set()
    for ch in chunks:
        root = Path(ch.root)
        for rel in ch.files:
            dest = writer.root / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(root / rel, dest)
            done.add(rel)
    n_linked = 0
    for rel in _input_files(seq_root):
        if rel in done or rel == plan.labels_name:
            continue
        writer.copy_unchanged(seq_root / rel, "/" + rel)
        n_linked += 1
    return n_linked


def _labels_with_object(
    plan: Plan, records: list[FrameRecord], seq_root: Path
) -> tuple[dict[str, Any], str | None, int]:
    """The input labels with the object added (where visible): labels, the object's
    UUID (None: visible nowhere, a warning in the plan), the frames annotated."""
    labels = copy.deepcopy(load_labels(seq_root / plan.labels_name).raw)
    anns = [r.annotation for r in records if r.annotation is not None]
    oid = None
    if anns:
        oid = add_object(labels, obj_class=plan.obj_class, frames=anns, seed=_object_seed(plan))
    else:
        plan.warnings.append("the object is visible in no frame: no annotation added")
    return labels, oid, len(anns)


def _metrics(
    plan: Plan,
    chunks: list[ChunkResult],
    records: list[FrameRecord],
    out_folder: Path,
    oid: str | None,
    n_annotated: int,
) -> dict[str, Any]:
    """metrics.json without the finishing's own timings and the evaluation."""
    stages = _stage_totals(chunks)
    return {
        "sequence": Path(plan.seq_folder).name,
        "output": str(out_folder),
        "object": {
            "class": plan.obj_class,
            "uuid": oid,
            **plan.info,
        },
        "placement": jsonable(plan.placement),
        "T_world_obj": plan.T_world_obj.tolist(),
        "frames": {
            "total": len(plan.all_frames),
            "augmented_range": len(plan.frames),
            "annotated": n_annotated,
        },
        "cameras": _camera_counts(plan, records),
        "lidar": _lidar_counts(plan, records),
        "placement_bound_px": _bound_summary(plan, records),
        "gauge": _gauge_summary(plan, records),
        "timings_s": {
            **{f"plan_{k}": v for k, v in plan.timings.items()},
            **{f"frames_{k}": v for k, v in stages.items()},
            "frames_wall": sum(ch.seconds for ch in chunks),
        },
        "warnings": list(plan.warnings),
    }


def _evaluate_object(metrics: dict[str, Any], plan: Plan, records: list[FrameRecord]) -> None:
    """The object's errors against a render with the true poses (sequences with ground
    truth); a failure is recorded, never raised."""
    tic = time.perf_counter()
    try:
        metrics["object_errors"] = evaluate_object(plan, records)
    except (ValueError, OSError, KeyError) as exc:
        log.warning("object evaluation failed: %s", exc)
        metrics["object_errors"] = {"error": str(exc)}
    metrics["timings_s"]["evaluate"] = time.perf_counter() - tic


def _object_seed(plan: Plan) -> str:
    return f"osdar-ar/{Path(plan.seq_folder).name}/{plan.obj_class}/" + ",".join(
        f"{v:.3f}" for v in plan.T_world_obj[:3, 3]
    )


def _bound_summary(plan: Plan, records: list[FrameRecord]) -> dict[str, Any]:
    """Per camera, the 90 % placement bound (px) over the frames the object is visible in:
    median, p90, max (confidence.py; the labels carry it per frame)."""
    out: dict[str, Any] = {}
    for c in plan.cameras:
        b = [
            plan.placement_bounds[r.frame_idx][c]
            for r in records
            if c in r.cameras and r.cameras[c].visible
            and c in plan.placement_bounds.get(r.frame_idx, {})
        ]  # fmt: skip
        out[c] = (
            {"median": float(np.median(b)), "p90": float(np.percentile(b, 90)),
             "max": float(np.max(b)), "frames": len(b)}
            if b else None
        )  # fmt: skip
    return out


def _gauge_summary(plan: Plan, records: list[FrameRecord]) -> dict[str, Any] | None:
    """The object against the clearance envelope over the annotated frames (the labels
    carry it per frame); None without an ego track."""
    if not plan.gauge:
        return None
    g = [plan.gauge[r.frame_idx] for r in records
         if r.annotation is not None and r.frame_idx in plan.gauge]  # fmt: skip
    dist = [x.track_distance_m for x in g]
    return {
        "lateral_distance_m": next(iter(plan.gauge.values())).lateral_distance_m,
        "intrusion_frames": sum(x.intrusion for x in g),
        "annotated_frames": len(g),
        "track_distance_m": [min(dist), max(dist)] if dist else None,
        "outline": plan.spec.gauge.model_dump(),
    }


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
