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

from worker.augmentation.annotations import add_object, builtin_provenance
from worker.augmentation.frame import STAGE_KEYS, ChunkResult, FrameRecord
from worker.augmentation.plan import Plan, PlannedObject
from worker.evaluation.object_error import evaluate_object, wants_object_errors
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
        labels, oids, n_annotated = _labels_with_object(plan, records, seq_root)
        t_labels = time.perf_counter() - tic

        metrics = _metrics(plan, chunks, records, out_folder, oids, n_annotated)
        metrics["timings_s"].update(
            {
                "assemble": t_move,
                "labels": t_labels,
                "linked_files": n_linked,
                **(extra_timings or {}),
            }
        )
        if evaluate and (seq_root / "ground_truth").is_dir():
            if wants_object_errors(plan):
                _evaluate_object(metrics, plan, chunks, records)
            else:  # the reference render knows one static object, unoccluded by others
                metrics["object_errors"] = {
                    "skipped": "the object errors are measured for one static object only"
                }
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
) -> tuple[dict[str, Any], list[str | None], list[int]]:
    """The input labels with the objects added (each where visible): labels, per object
    its UUID (None: visible nowhere, a warning in the plan) and the frames annotated."""
    labels = copy.deepcopy(load_labels(seq_root / plan.labels_name).raw)
    oids: list[str | None] = []
    counts: list[int] = []
    for k, obj in enumerate(plan.objects):
        anns = [r.objects[k].annotation for r in records]
        anns_present = [a for a in anns if a is not None]
        oid = None
        if anns_present:
            oid = add_object(labels, obj_class=obj.obj_class, frames=anns_present, seed=obj.seed,
                             attributes=_provenance(obj))  # fmt: skip
        else:
            what = "the object" if len(plan.objects) == 1 else f"object {k} ({obj.obj_class})"
            plan.warnings.append(f"{what} is visible in no frame: no annotation added")
        oids.append(oid)
        counts.append(len(anns_present))
    return labels, oids, counts


def _provenance(obj: PlannedObject) -> dict[str, str]:
    """A built-in obstacle's seed, pose and variant for its labels; nothing for an
    uploaded mesh (its meta has no seed)."""
    meta = obj.obj_full.meta
    return builtin_provenance(meta) if "seed" in meta else {}


def _metrics(
    plan: Plan,
    chunks: list[ChunkResult],
    records: list[FrameRecord],
    out_folder: Path,
    oids: list[str | None],
    n_annotated: list[int],
) -> dict[str, Any]:
    """metrics.json without the finishing's own timings and the evaluation. ``object``,
    ``placement``, ``T_world_obj``, ``cameras``, ``lidar``, ``placement_bound_px`` and
    ``gauge`` are the first object's; ``objects`` has them for every object."""
    stages = _stage_totals(chunks)
    per_object = [
        _object_metrics(plan, k, records, oids[k], n_annotated[k]) for k in range(len(plan.objects))
    ]
    first = per_object[0]
    return {
        "sequence": Path(plan.seq_folder).name,
        "output": str(out_folder),
        "object": {
            "class": plan.obj_class,
            "uuid": oids[0],
            **plan.info,
        },
        "placement": first["placement"],
        "T_world_obj": plan.T_world_obj.tolist(),
        "objects": per_object,
        "frames": {
            "total": len(plan.all_frames),
            "augmented_range": len(plan.frames),
            "annotated": sum(any(o.annotation is not None for o in r.objects) for r in records),
        },
        "cameras": first["cameras"],
        "lidar": _lidar_counts(plan, records, None),
        "placement_bound_px": first["placement_bound_px"],
        "gauge": first["gauge"],
        "timings_s": {
            **{f"plan_{k}": v for k, v in plan.timings.items()},
            **{f"frames_{k}": v for k, v in stages.items()},
            "frames_wall": sum(ch.seconds for ch in chunks),
        },
        "warnings": list(plan.warnings),
    }


def _object_metrics(
    plan: Plan, k: int, records: list[FrameRecord], oid: str | None, n_annotated: int
) -> dict[str, Any]:
    """One object's part of metrics.json."""
    obj = plan.objects[k]
    return {
        "index": k,
        "class": obj.obj_class,
        "uuid": oid,
        "moving": obj.moving,
        "size_m": obj.obj_full.size.tolist(),
        "placement": jsonable(obj.placement),
        "T_world_obj": obj.T_world_obj.tolist(),
        "annotated_frames": n_annotated,
        "cameras": _camera_counts(plan, records, k),
        "lidar": _lidar_counts(plan, records, k),
        "placement_bound_px": _bound_summary(plan, records, k),
        "gauge": _gauge_summary(plan, records, k),
    }


def _evaluate_object(
    metrics: dict[str, Any], plan: Plan, chunks: list[ChunkResult], records: list[FrameRecord]
) -> None:
    """The object's errors against a render with the true poses (sequences with ground
    truth): the chunks' per-frame values, the frames they lack measured here; a failure
    is recorded, never raised."""
    tic = time.perf_counter()
    try:
        measured = {f: v for ch in chunks for f, v in ch.object_errors.items()}
        metrics["object_errors"] = evaluate_object(plan, records, measured=measured)
    except (ValueError, OSError, KeyError) as exc:
        log.warning("object evaluation failed: %s", exc)
        metrics["object_errors"] = {"error": str(exc)}
    metrics["timings_s"]["evaluate"] = time.perf_counter() - tic


def _bound_summary(plan: Plan, records: list[FrameRecord], k: int = 0) -> dict[str, Any]:
    """Per camera, object ``k``'s 90 % placement bound (px) over the frames it is visible
    in: median, p90, max (confidence.py; the labels carry it per frame)."""
    bounds = plan.objects[k].placement_bounds
    out: dict[str, Any] = {}
    for c in plan.cameras:
        b = [
            bounds[r.frame_idx][c]
            for r in records
            if c in r.objects[k].cameras and r.objects[k].cameras[c].visible
            and c in bounds.get(r.frame_idx, {})
        ]  # fmt: skip
        out[c] = (
            {"median": float(np.median(b)), "p90": float(np.percentile(b, 90)),
             "max": float(np.max(b)), "frames": len(b)}
            if b else None
        )  # fmt: skip
    return out


def _gauge_summary(plan: Plan, records: list[FrameRecord], k: int = 0) -> dict[str, Any] | None:
    """Object ``k`` against the clearance envelope over its annotated frames (the labels
    carry it per frame); None without an ego track."""
    gauge = plan.objects[k].gauge
    if not gauge:
        return None
    g = [gauge[r.frame_idx] for r in records
         if r.objects[k].annotation is not None and r.frame_idx in gauge]  # fmt: skip
    dist = [x.track_distance_m for x in g]
    lateral = [x.lateral_distance_m for x in g] or [next(iter(gauge.values())).lateral_distance_m]
    return {
        "lateral_distance_m": lateral[0] if not plan.objects[k].moving else min(lateral),
        "lateral_distance_m_range": [min(lateral), max(lateral)],
        "intrusion_frames": sum(x.intrusion for x in g),
        "annotated_frames": len(g),
        "track_distance_m": [min(dist), max(dist)] if dist else None,
        "outline": plan.spec.gauge.model_dump(),
    }


def _camera_counts(plan: Plan, records: list[FrameRecord], k: int = 0) -> dict[str, Any]:
    out = {}
    for c in plan.cameras:
        recs = [r.objects[k].cameras[c] for r in records if c in r.objects[k].cameras]
        out[c] = {
            "visible_frames": sum(x.visible for x in recs),
            "augmented_files": sum(x.augmented for x in recs),
            "linked_files": sum(not x.augmented for x in recs),
        }
    return out


def _lidar_counts(plan: Plan, records: list[FrameRecord], k: int | None) -> dict[str, Any] | None:
    """Lidar counts of object ``k`` (None: all objects together)."""
    if plan.lidar_stream is None:
        return None
    ks = range(len(plan.objects)) if k is None else [k]
    pts = [sum(r.objects[j].lidar_points for j in ks) for r in records]
    out: dict[str, Any] = {
        "origins": plan.spec.lidar_origins,
        "frames_with_points": int(sum(p > 0 for p in pts)),
        "object_points_total": int(sum(pts)),
        "object_points_max": int(max(pts, default=0)),
        "candidate_rays_total": int(sum(r.lidar_candidates for r in records)),
    }
    if k is None:
        out["noise"] = _lidar_noise_summary(records)
    return out


def _lidar_noise_summary(records: list[FrameRecord]) -> dict[str, Any]:
    """Per sensor_index, the range noise (m) and dropout the object points got, over the
    frames where they were measured: median, min, max (the per-frame estimates are in
    the chunk records, ``FrameRecord.lidar_noise``)."""
    out: dict[str, Any] = {}
    for s in sorted({s for r in records for s in r.lidar_noise}):
        est = [r.lidar_noise[s] for r in records if s in r.lidar_noise]
        sig = [e["range_sigma_m"] for e in est if np.isfinite(e["range_sigma_m"])]
        drop = [e["dropout"] for e in est]
        out[str(s)] = {
            "frames": len(est),
            "range_sigma_m": _spread(sig),
            "dropout": _spread(drop),
            "rings_median": float(np.median([e["rings"] for e in est])),
        }
    return out


def _spread(v: list[float]) -> dict[str, float] | None:
    if not v:
        return None
    return {"median": float(np.median(v)), "min": float(np.min(v)), "max": float(np.max(v))}
