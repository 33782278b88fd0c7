"""A service campaign's end: once every variant's job is finished, the manifest and the
campaign's final state.

:func:`finalize_campaign` is called after a campaign job ends (the job's last task, or the
stage that failed or cancelled it: worker/orchestration/tasks.py) and by the
``osdar_ar.campaign_finalize`` task the API sends when it sees every variant finished. It
returns at once while a variant is unfinished; otherwise it

1. builds each variant's record from its job (state, error, the augmentation's gauge
   summary, the paper's RPE / jitter and the placement bound: the embedded run's
   :func:`~worker.campaign.run.quality_of`) and the manifest rows
   (:mod:`worker.campaign.manifest`, the same rows and CSV as ``campaign run``), with the
   variant's ``job_id``; a cancelled variant's row says ``cancelled``;
2. uploads ``campaigns/<id>/manifest.json`` and ``manifest.csv`` to the store;
3. in one conditional row update (RUNNING -> the final state), records the manifest's keys,
   the summary and each variant's row. Two finalizers racing write the same bytes; one
   row update wins.

Final states: SUCCEEDED (every variant SUCCEEDED), PARTIAL (some did, the others FAILED
or were CANCELLED: each failed variant's row carries its own reason), CANCELLED (cancelled,
none SUCCEEDED), FAILED (none SUCCEEDED).
"""

from __future__ import annotations

import logging
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from osdar_platform.db import session_scope, updated_rows
from osdar_platform.models import (
    TERMINAL_STATES,
    Campaign,
    CampaignState,
    CampaignVariant,
    Job,
    JobState,
    utcnow,
)
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectNotFound, ObjectStore, StoreError
from worker.campaign.manifest import MANIFEST_CSV, MANIFEST_JSON, manifest_row, write_manifest
from worker.campaign.run import VariantRecord, archive_name, quality_of
from worker.campaign.service_expand import campaign_store
from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import Variant

log = logging.getLogger(__name__)


def manifest_keys(campaign_id: str) -> tuple[str, str]:
    """Store keys of a campaign's manifest (JSON, CSV)."""
    return f"campaigns/{campaign_id}/{MANIFEST_JSON}", f"campaigns/{campaign_id}/{MANIFEST_CSV}"


def record_of(variant: Variant, job: dict[str, Any], cameras: list[str],
              store: ObjectStore) -> VariantRecord:  # fmt: skip
    """A variant's record from its finished job (module docstring)."""
    state = JobState(job["state"])
    metrics = job["metrics"] or {}
    seconds = None
    if job["started_at"] is not None and job["finished_at"] is not None:
        seconds = (job["finished_at"] - job["started_at"]).total_seconds()
    if state != JobState.SUCCEEDED:
        reason = job["error"] or ("cancelled" if state == JobState.CANCELLED else "failed")
        return VariantRecord(variant=variant.id, key=variant.key, state="failed",
                             error=reason, seconds=seconds)  # fmt: skip
    aug = metrics.get("augmentation") or {}
    evaluation = metrics.get("evaluation") or {}
    size = None
    try:
        size = store.size(str(job["result_key"]))
    except (ObjectNotFound, StoreError) as exc:
        log.warning("variant %s: archive size unknown: %s", variant.id, exc)
    cams = aug.get("cameras") or {}
    return VariantRecord(
        variant=variant.id,
        key=variant.key,
        state="done",
        archive=archive_name(variant),
        archive_bytes=size,
        seconds=seconds,
        strategy=evaluation.get("strategy") or (metrics.get("preparation") or {}).get("strategy"),
        annotated_frames=(aug.get("frames") or {}).get("annotated"),
        visible_frames={c: int(v.get("visible_frames") or 0) for c, v in cams.items()},
        gauge=aug.get("gauge"),
        quality=quality_of(evaluation, aug, cameras),
    )


def final_state(states: list[JobState], cancel_requested: bool) -> CampaignState:
    """The campaign's state from its variants' (module docstring)."""
    ok = sum(s == JobState.SUCCEEDED for s in states)
    if ok == len(states):
        return CampaignState.SUCCEEDED
    if ok > 0:
        return CampaignState.PARTIAL
    return CampaignState.CANCELLED if cancel_requested else CampaignState.FAILED


def _load(campaign_id: str, settings: Settings) -> tuple[dict[str, Any], list[Any]] | None:
    with session_scope(settings) as s:
        c = s.get(Campaign, campaign_id)
        if c is None or c.state != CampaignState.RUNNING:
            return None
        rows = s.execute(
            select(CampaignVariant, Job)
            .join(Job, Job.id == CampaignVariant.job_id, isouter=True)
            .where(CampaignVariant.campaign_id == campaign_id)
            .order_by(CampaignVariant.index)
        ).all()
        variants = []
        for v, j in rows:
            job = None if j is None else {
                "id": j.id, "state": j.state, "error": j.error, "metrics": j.metrics,
                "result_key": j.result_key, "started_at": j.started_at,
                "finished_at": j.finished_at,
            }  # fmt: skip
            variants.append((Variant.model_validate(v.variant), job))
        return {"spec": c.spec, "cancel_requested": c.cancel_requested}, variants


def finalize_campaign(campaign_id: str, *, settings: Settings) -> CampaignState | None:
    """The campaign's manifest and final state once every variant is finished (module
    docstring); None while a variant is unfinished or when the campaign is not RUNNING."""
    loaded = _load(campaign_id, settings)
    if loaded is None:
        return None
    campaign, variants = loaded
    if any(job is not None and job["state"] not in TERMINAL_STATES for _, job in variants):
        return None
    spec = CampaignSpec.model_validate(campaign["spec"])
    cameras = list(spec.job.cameras)
    store = campaign_store(settings)
    states: list[JobState] = []
    rows: list[dict[str, Any]] = []
    for v, job in variants:
        if job is None:  # its job row was deleted: the variant is lost, say so
            job = {"id": None, "state": JobState.FAILED, "error": "its job was deleted",
                   "metrics": None, "result_key": None, "started_at": None,
                   "finished_at": None}  # fmt: skip
        states.append(JobState(job["state"]))
        row = manifest_row(v, record_of(v, job, cameras, store))
        if job["state"] == JobState.CANCELLED:
            row["state"] = "cancelled"
        row["job_id"] = job["id"]
        rows.append(row)
    state = final_state(states, bool(campaign["cancel_requested"]))
    counts = Counter(r["state"] for r in rows)
    summary = {"variants": len(rows), "done": counts.get("done", 0),
               "failed": counts.get("failed", 0), "cancelled": counts.get("cancelled", 0),
               "state": state.value}  # fmt: skip
    json_key, csv_key = manifest_keys(campaign_id)
    with tempfile.TemporaryDirectory(prefix="osdar-ar-manifest-") as tmp:
        j, c = write_manifest(Path(tmp), spec, rows, summary, cameras=cameras)
        store.put_file(json_key, j)
        store.put_file(csv_key, c)
    now = utcnow()
    with session_scope(settings) as s:
        won = updated_rows(
            s,
            update(Campaign)
            .where(Campaign.id == campaign_id, Campaign.state == CampaignState.RUNNING)
            .values(state=state, stage=None, summary=summary, manifest_json_key=json_key,
                    manifest_csv_key=csv_key, finished_at=now, updated_at=now),
        )  # fmt: skip
        if won:
            for v, row in zip(variants, rows, strict=True):
                s.execute(
                    update(CampaignVariant)
                    .where(CampaignVariant.campaign_id == campaign_id,
                           CampaignVariant.index == v[0].index)
                    .values(row=row)
                )  # fmt: skip
    if won:
        log.info("campaign %s %s: %s", campaign_id, state.value, summary)
    return state if won else None


def campaign_of_job(job_id: str, *, settings: Settings) -> str | None:
    """The campaign a job is a variant of (None: a job of its own)."""
    with session_scope(settings) as s:
        return s.scalar(select(Job.campaign_id).where(Job.id == job_id))


def finalize_after_job(job_id: str, *, settings: Settings) -> CampaignState | None:
    """After a job ended: its campaign's :func:`finalize_campaign` (None otherwise)."""
    campaign_id = campaign_of_job(job_id, settings=settings)
    if campaign_id is None:
        return None
    return finalize_campaign(campaign_id, settings=settings)


__all__ = [
    "campaign_of_job",
    "final_state",
    "finalize_after_job",
    "finalize_campaign",
    "manifest_keys",
    "record_of",
]
