"""The campaign manifest: one row per variant, as ``manifest.json`` and ``manifest.csv``.

A row (JSON)::

    variant, key, sequence, sequence_label, state ("done" | "failed" | "pending"), error,
    objects: [{class, seed, position: {zone, s_m, s_job_m, offset_m, yaw_deg,
               heading_deg, xyz_world, distance_first_view_m, first_view_frame},
               speed_mps (None: static), motion (the job's path; None: static),
               gauge (this object's, as below)}],
    gauge: {intrudes, intrusion_frames, annotated_frames, lateral_distance_m,
            track_distance_min_m, track_distance_max_m}        (None before it ran)
    quality: {camera: {rpe_px_mean, jitter_px_mean, bound_px_median}},
    strategy, annotated_frames, seconds, archive, archive_bytes, thumb

``gauge`` is the object (all objects of a several-object variant: intrudes when any does)
against the train's clearance envelope over its annotated frames
(worker/augmentation/gauge.py): ``intrudes`` when it is inside the envelope in any of them,
the lateral distance to the envelope's side (m, negative inside) and the distance along
the track from the train (m, first and last annotated frame's range). ``quality`` is the
paper's RPE / jitter (px, chosen strategy; worker/evaluation/evaluate.py) and the median
of the per-frame 90 % placement bound (px; worker/augmentation/confidence.py).

The CSV has the same rows flattened (:func:`flatten_row`): the objects' fields joined by
``;`` (one value per object), ``gauge_*`` and ``<camera>_<measure>`` columns; empty cells
for None. The JSON also holds the campaign's name, seed and a summary.
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import Variant
from worker.json_values import jsonable

if TYPE_CHECKING:  # the record's type only; run.py imports this module
    from worker.campaign.run import VariantRecord

MANIFEST_JSON = "manifest.json"
MANIFEST_CSV = "manifest.csv"

#: The per-camera measures of the quality columns.
QUALITY_MEASURES = ("rpe_px_mean", "jitter_px_mean", "bound_px_median")
#: The objects' fields of the CSV (one value per object, joined by ";").
OBJECT_FIELDS = (
    "class",
    "seed",
    "zone",
    "s_m",
    "offset_m",
    "yaw_deg",
    "distance_first_view_m",
    "speed_mps",
    "intrudes",
)
GAUGE_FIELDS = (
    "intrudes",
    "intrusion_frames",
    "annotated_frames",
    "lateral_distance_m",
    "track_distance_min_m",
    "track_distance_max_m",
)


def write_atomic(path: Path, data: bytes) -> Path:
    """``data`` under a temporary name beside ``path``, then renamed into place: a reader
    (or a resumed run) never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _gauge(g: Mapping[str, Any] | None) -> dict[str, Any] | None:
    if g is None:
        return None
    dist = g.get("track_distance_m") or [None, None]
    return {
        "intrudes": int(g.get("intrusion_frames") or 0) > 0,
        "intrusion_frames": int(g.get("intrusion_frames") or 0),
        "annotated_frames": int(g.get("annotated_frames") or 0),
        "lateral_distance_m": _f(g.get("lateral_distance_m")),
        "track_distance_min_m": _f(dist[0]),
        "track_distance_max_m": _f(dist[1]),
    }


def _f(x: Any) -> float | None:
    return None if x is None else round(float(x), 3)


def manifest_row(variant: Variant, record: VariantRecord | None) -> dict[str, Any]:
    """One variant's row (module docstring); ``record`` None: not run (pending)."""
    objects = [
        {
            "class": o.class_name,
            "seed": o.variation_seed,
            "position": o.resolved.model_dump(
                mode="json",
                include={
                    "zone",
                    "s_m",
                    "s_job_m",
                    "offset_m",
                    "yaw_deg",
                    "heading_deg",
                    "xyz_world",
                    "distance_first_view_m",
                    "first_view_frame",
                },
            ),
        }
        for o in variant.objects
    ]
    r = record
    gauges = [] if r is None else list(r.object_gauges)
    for k, (row, o) in enumerate(zip(objects, variant.objects, strict=True)):
        row["speed_mps"] = None if o.motion is None else o.motion.get("speed_mps")
        row["motion"] = o.motion
        row["gauge"] = _gauge(gauges[k]) if k < len(gauges) else None
    return {
        "variant": variant.id,
        "key": variant.key,
        "sequence": variant.sequence,
        "sequence_label": variant.sequence_label,
        "objects": objects,
        "state": "pending" if r is None else r.state,
        "error": None if r is None else r.error,
        "gauge": None if r is None else _gauge(r.gauge),
        "quality": {} if r is None else jsonable(r.quality),
        "strategy": None if r is None else r.strategy,
        "annotated_frames": None if r is None else r.annotated_frames,
        "seconds": None if r is None or r.seconds is None else round(r.seconds, 3),
        "archive": None if r is None else r.archive,
        "archive_bytes": None if r is None else r.archive_bytes,
        "thumb": None if r is None or r.contact is None else r.contact.get("thumb"),
    }


def manifest_rows(
    spec: CampaignSpec, variants: list[Variant], records: Mapping[str, VariantRecord | None]
) -> list[dict[str, Any]]:
    """Every variant's row, in the variants' order."""
    return [manifest_row(v, records.get(v.id)) for v in variants]


def csv_columns(cameras: list[str]) -> list[str]:
    return [
        "variant",
        "key",
        "sequence",
        "sequence_label",
        "state",
        "objects",
        *OBJECT_FIELDS,
        *(f"gauge_{k}" for k in GAUGE_FIELDS),
        *(f"{c}_{m}" for c in cameras for m in QUALITY_MEASURES),
        "strategy",
        "annotated_frames",
        "seconds",
        "archive",
        "archive_bytes",
        "thumb",
        "error",
    ]


def _cell(x: Any) -> str:
    if x is None:
        return ""
    if isinstance(x, bool):
        return "true" if x else "false"
    return str(x)


def flatten_row(row: Mapping[str, Any], cameras: list[str]) -> dict[str, str]:
    """A JSON row as the CSV's cells (module docstring)."""
    obj = row["objects"]
    per_object: dict[str, list[Any]] = {
        "class": [o["class"] for o in obj],
        "seed": [o["seed"] for o in obj],
        **{k: [o["position"].get(k) for o in obj] for k in OBJECT_FIELDS[2:7]},
        "speed_mps": [o.get("speed_mps") for o in obj],
        "intrudes": [(o.get("gauge") or {}).get("intrudes") for o in obj],
    }
    gauge = row.get("gauge") or {}
    quality = row.get("quality") or {}
    out: dict[str, Any] = {
        "variant": row["variant"],
        "key": row["key"],
        "sequence": row["sequence"],
        "sequence_label": row["sequence_label"],
        "state": row["state"],
        "objects": len(obj),
        **{k: ";".join(_cell(x) for x in v) for k, v in per_object.items()},
        **{f"gauge_{k}": gauge.get(k) for k in GAUGE_FIELDS},
        **{f"{c}_{m}": (quality.get(c) or {}).get(m) for c in cameras for m in QUALITY_MEASURES},
        **{
            k: row.get(k)
            for k in (
                "strategy",
                "annotated_frames",
                "seconds",
                "archive",
                "archive_bytes",
                "thumb",
                "error",
            )
        },
    }
    return {k: _cell(out[k]) for k in csv_columns(cameras)}


def manifest_csv_text(rows: list[dict[str, Any]], cameras: list[str]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=csv_columns(cameras), lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow(flatten_row(row, cameras))
    return buf.getvalue()


def write_manifest(
    out_dir: str | Path,
    spec: CampaignSpec,
    rows: list[dict[str, Any]],
    summary: Mapping[str, Any],
    *,
    cameras: list[str],
) -> tuple[Path, Path]:
    """``manifest.json`` and ``manifest.csv`` in ``out_dir`` (each written under a
    temporary name and renamed into place); returns their paths."""
    out_dir = Path(out_dir)
    doc = {
        "campaign": spec.name,
        "seed": spec.seed,
        "cameras": cameras,
        "summary": dict(summary),
        "variants": rows,
    }
    text = json.dumps(jsonable(doc), indent=1, sort_keys=True)
    j = write_atomic(out_dir / MANIFEST_JSON, text.encode())
    c = write_atomic(out_dir / MANIFEST_CSV, manifest_csv_text(rows, cameras).encode())
    return j, c


__all__ = [
    "GAUGE_FIELDS",
    "MANIFEST_CSV",
    "MANIFEST_JSON",
    "OBJECT_FIELDS",
    "QUALITY_MEASURES",
    "csv_columns",
    "flatten_row",
    "manifest_csv_text",
    "manifest_row",
    "manifest_rows",
    "write_atomic",
    "write_manifest",
]
