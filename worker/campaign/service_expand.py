"""A service campaign's expansion stage: prepare, expand, write the variants and their jobs.

The API records a campaign (PENDING) and sends ``osdar_ar.campaign_expand`` with its id;
the task (worker/orchestration/tasks.py) calls :func:`expand_campaign_stage`::

    start          count the delivery (a campaign that keeps killing its workers FAILS),
                   PENDING -> EXPANDING
    prepare        ONE preparation per sequence (the prepared cache and its lock: the
                   variant jobs on that sequence then reuse it; their metrics say
                   ``preparation.reused``); the expansion always runs on the cached copy
                   (a dry run and the real run then agree byte for byte)
    expand         worker.campaign.expand on the prepared sequences (deterministic)
    commit         in ONE transaction: the campaign EXPANDING -> RUNNING (conditional:
                   not cancelled, not done by another delivery), every variant row and
                   its job (PENDING); a dry run writes the variants only (EXPANDED)
    enqueue        each job is sent (a failed send stays PENDING: the reaper sends it)

The commit is keyed by (campaign, variant index) and conditional on the campaign's state,
so a redelivered expansion (its worker killed) makes every variant exactly once: a second
delivery after the commit only sends the jobs still PENDING.

An expansion that finds errors (an impossible rule, an unreadable sequence) FAILS the
campaign with every issue (``issues``), and no job is made.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import trimesh
from sqlalchemy import select, update

from osdar_platform.db import session_scope, updated_rows
from osdar_platform.models import (
    Asset,
    Campaign,
    CampaignState,
    CampaignVariant,
    Job,
    JobEvent,
    JobState,
    Sequence,
    utcnow,
)
from osdar_platform.retry import RetryingStore
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectStore, store_from_url
from worker.campaign.expand import expand_with_issues
from worker.campaign.placement import Footprint
from worker.campaign.run import prepare_config
from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import Issue, Variant
from worker.orchestration.queue import enqueue_job
from worker.orchestration.runner import sequence_folder
from worker.osdar.errors import SequenceError
from worker.preparation.artifact import PreparedSequence
from worker.preparation.prepare import PreparationError, prepare

log = logging.getLogger(__name__)

POISON_REASON = "the expansion killed its worker repeatedly (poison input?)"


class CampaignStop(Exception):
    """The expansion must stop: the campaign is done, cancelled or failed (its row says)."""


@dataclass
class ExpandOutcome:
    """What one delivery did: the campaign's state after it, the jobs it sent."""

    state: CampaignState
    sent: list[str]
    created: int = 0


def campaign_store(settings: Settings) -> ObjectStore:
    """The object store, every call retried with backoff (as a job's)."""
    s = settings
    return RetryingStore(
        store_from_url(str(s.store_url), s), retries=s.store_retries, base=s.store_retry_base_s,
        cap=s.store_retry_max_s, budget_s=s.store_retry_budget_s,
    )  # fmt: skip


def _fail(campaign_id: str, message: str, issues: list[Issue], settings: Settings) -> None:
    now = utcnow()
    with session_scope(settings) as s:
        s.execute(
            update(Campaign)
            .where(Campaign.id == campaign_id, Campaign.state.in_(_EXPANDABLE))
            .values(state=CampaignState.FAILED, error=message[:4000], stage=None,
                    issues=[i.to_json() for i in issues], finished_at=now, updated_at=now)
        )  # fmt: skip


_EXPANDABLE = [CampaignState.PENDING, CampaignState.EXPANDING]


def start_expansion(campaign_id: str, settings: Settings) -> Campaign | None:
    """Count this delivery; PENDING -> EXPANDING. Returns a detached copy of the row, or
    None when the campaign is gone. A campaign delivered more than ``max_deliveries``
    times is FAILED (:data:`POISON_REASON`) and :class:`CampaignStop` is raised."""
    now = utcnow()
    stop: str | None = None
    with session_scope(settings) as s:
        row = s.get(Campaign, campaign_id)
        if row is None:
            return None
        if row.state not in _EXPANDABLE:
            s.expunge(row)
            return row
        if row.deliveries >= settings.max_deliveries:
            row.state, row.error, row.finished_at = CampaignState.FAILED, POISON_REASON, now
            stop = POISON_REASON
        elif row.cancel_requested:
            row.state, row.finished_at = CampaignState.CANCELLED, now
            stop = "cancelled"
        else:
            row.deliveries += 1
            row.state, row.stage, row.updated_at = CampaignState.EXPANDING, "start", now
        s.flush()
        s.expunge(row)
    if stop is not None:
        raise CampaignStop(stop)
    return row


def _stage(campaign_id: str, stage: str, settings: Settings) -> None:
    """Show the stage (and beat the heart: ``updated_at``); stop when cancelled."""
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Campaign)
            .where(Campaign.id == campaign_id, Campaign.state == CampaignState.EXPANDING,
                   Campaign.cancel_requested.is_(False))
            .values(stage=stage[:64], updated_at=utcnow()),
        )  # fmt: skip
    if not moved:
        raise CampaignStop(f"campaign {campaign_id} is no longer expanding")


def prepare_sequences(
    spec: CampaignSpec,
    campaign_id: str,
    sequences: dict[str, dict[str, Any]],
    settings: Settings,
    store: Callable[[], ObjectStore],
) -> tuple[dict[str, PreparedSequence], list[Issue]]:
    """ONE preparation per sequence entry (the prepared cache), keyed by sequence id."""
    config = prepare_config(spec)
    prepared: dict[str, PreparedSequence] = {}
    issues: list[Issue] = []
    for i, entry in enumerate(spec.sequences):
        where = f"sequences[{i}] ({entry.label})"

        def progress(sub: str, done: int, total: int, label: str = entry.label) -> None:
            _stage(campaign_id, f"prepare {label}: {sub}", settings)

        _stage(campaign_id, f"prepare {entry.label}", settings)
        seq = sequences.get(str(entry.id))
        if seq is None:
            issues.append(Issue("error", where, f"sequence {entry.id} was deleted"))
            continue
        try:
            folder = sequence_folder(seq, settings, store)
            cache = settings.prepared_cache_dir
            done = prepare(folder, config, cache_dir=cache, progress=progress)
            if not done.summary.get("reused"):
                # Expand on the artifact as the cache gives it back, always: an expansion
                # on the freshly computed one differs from one on the cached copy by a
                # rounding step now and then (measured: 14 of 40 sequence keys on the
                # tiny fire_site, 1 mm in xyz_world, sometimes another draw), so a dry
                # run and the real run would disagree.
                done = prepare(folder, config, cache_dir=cache)
            prepared[str(entry.id)] = done
        except (SequenceError, PreparationError, OSError, ValueError) as exc:
            issues.append(Issue("error", where, f"cannot prepare: {exc}"))
    return prepared, issues


def asset_footprints(
    spec: CampaignSpec, settings: Settings, store: Callable[[], ObjectStore]
) -> dict[str, Footprint]:
    """Each uploaded asset's footprint (its mesh's bounds at scale 1)."""
    out: dict[str, Footprint] = {}
    ids = sorted({str(o.asset_id) for o in spec.obstacles if o.asset_id is not None})
    for asset_id in ids:
        with session_scope(settings) as s:
            asset = s.get(Asset, asset_id)
            where = None if asset is None else (asset.store_key, asset.file_type)
        if where is None:
            continue  # the expansion reports the footprint as unknown
        data = b"".join(store().open_read(where[0]))
        mesh = trimesh.load(io.BytesIO(data), file_type=where[1], force="mesh", process=False)
        out[asset_id] = Footprint.from_bounds(mesh.bounds)
    return out


def _frames_in(job: dict[str, Any], validation: dict[str, Any], frames: int) -> int:
    indices = validation.get("frame_indices") or []
    rng = job.get("frame_range")
    if rng is None:
        return len(indices) or frames
    return sum(1 for i in indices if rng[0] <= i <= rng[1])


def commit_variants(
    campaign_id: str,
    owner_id: int,
    variants: list[Variant],
    issues: list[Issue],
    sequences: dict[str, dict[str, Any]],
    *,
    dry_run: bool,
    settings: Settings,
) -> list[str] | None:
    """The variants (and, unless a dry run, their PENDING jobs) in ONE transaction with
    the campaign's EXPANDING -> RUNNING (EXPANDED for a dry run). Returns the new job
    ids, or None when the campaign was no longer expanding (cancelled, or another
    delivery committed first): then nothing is written."""
    now = utcnow()
    target = CampaignState.EXPANDED if dry_run else CampaignState.RUNNING
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Campaign)
            .where(Campaign.id == campaign_id, Campaign.state == CampaignState.EXPANDING,
                   Campaign.cancel_requested.is_(False))
            .values(state=target, stage=None, variants_total=len(variants),
                    issues=[i.to_json() for i in issues], expanded_at=now, updated_at=now,
                    finished_at=now if dry_run else None),
        )  # fmt: skip
        if not moved:
            s.rollback()
            return None
        job_ids: list[str] = []
        for v in variants:
            job_id = None
            if not dry_run:
                seq = sequences[v.sequence]
                job = Job(
                    owner_id=owner_id,
                    sequence_id=v.sequence,
                    campaign_id=campaign_id,
                    spec=v.job_spec(v.sequence),
                    state=JobState.PENDING,
                    progress_total=_frames_in(v.job, seq["validation"], seq["frames"]),
                )
                job.events.append(
                    JobEvent(kind="created", message=f"campaign {campaign_id} variant {v.id}")
                )
                s.add(job)
                s.flush()
                job_id = job.id
                job_ids.append(job.id)
            s.add(
                CampaignVariant(
                    campaign_id=campaign_id, index=v.index, variant_id=v.id, key=v.key,
                    sequence_id=v.sequence, sequence_label=v.sequence_label,
                    classes=[o.class_name for o in v.objects],
                    variant=v.model_dump(mode="json"), job_id=job_id,
                )
            )  # fmt: skip
    return job_ids


def _pending_jobs(campaign_id: str, settings: Settings) -> list[str]:
    with session_scope(settings) as s:
        return list(
            s.scalars(
                select(Job.id)
                .where(Job.campaign_id == campaign_id, Job.state == JobState.PENDING)
                .order_by(Job.created_at, Job.id)
            )
        )


def _send(job_ids: list[str], settings: Settings, app: Any) -> list[str]:
    sent = []
    for job_id in job_ids:
        try:
            enqueue_job(job_id, settings=settings, app=app)
            sent.append(job_id)
        except Exception as exc:  # stays PENDING: the reaper sends it again
            log.warning("campaign job %s stays PENDING: %s", job_id, exc)
    return sent


def _sequence_rows(spec: CampaignSpec, owner_id: int, settings: Settings) -> dict[str, Any]:
    ids = [str(e.id) for e in spec.sequences if e.id is not None]
    with session_scope(settings) as s:
        rows = s.scalars(
            select(Sequence).where(Sequence.id.in_(ids), Sequence.owner_id == owner_id)
        )
        return {
            r.id: {
                "id": r.id,
                "path": r.path,
                "content_key": r.content_key,
                "validation": dict(r.validation or {}),
                "frames": r.frames,
            }
            for r in rows
        }


def expand_campaign_stage(
    campaign_id: str, *, settings: Settings, app: Any = None
) -> ExpandOutcome | None:
    """One delivery of the expansion (module docstring); None when the campaign is gone.

    ``app``: the Celery app the variant jobs are sent with (None: the workers' own).
    """
    try:
        row = start_expansion(campaign_id, settings)
    except CampaignStop as stop:
        log.warning("campaign %s: %s", campaign_id, stop)
        return ExpandOutcome(_state(campaign_id, settings), [])
    if row is None:
        return None
    if row.state != CampaignState.EXPANDING:  # committed by an earlier delivery
        sent = [] if row.state.terminal else _send(_pending_jobs(campaign_id, settings),
                                                   settings, app)  # fmt: skip
        return ExpandOutcome(row.state, sent)
    spec = CampaignSpec.model_validate(row.spec)
    store_cache: list[ObjectStore] = []

    def store() -> ObjectStore:
        if not store_cache:
            store_cache.append(campaign_store(settings))
        return store_cache[0]

    try:
        sequences = _sequence_rows(spec, row.owner_id, settings)
        prepared, issues = prepare_sequences(spec, campaign_id, sequences, settings, store)
        if not issues:
            _stage(campaign_id, "expand", settings)
            footprints = asset_footprints(spec, settings, store)
            variants, issues = expand_with_issues(spec, prepared, footprints=footprints)
        errors = [i for i in issues if i.level == "error"]
        if errors:
            msg = f"{len(errors)} error(s) in the campaign: " + "; ".join(map(str, errors))
            _fail(campaign_id, msg, issues, settings)
            return ExpandOutcome(CampaignState.FAILED, [])
        _stage(campaign_id, "commit", settings)
        job_ids = commit_variants(campaign_id, row.owner_id, variants, issues, sequences,
                                  dry_run=row.dry_run, settings=settings)  # fmt: skip
    except CampaignStop as stop:
        log.info("campaign %s: %s", campaign_id, stop)
        _cancel_if_requested(campaign_id, settings)
        return ExpandOutcome(_state(campaign_id, settings), [])
    if job_ids is None:
        _cancel_if_requested(campaign_id, settings)
        state = _state(campaign_id, settings)
        sent = _send(_pending_jobs(campaign_id, settings), settings, app) if (
            state == CampaignState.RUNNING) else []  # fmt: skip
        return ExpandOutcome(state, sent)
    log.info("campaign %s: %d variants%s", campaign_id, len(variants),
             " (dry run)" if row.dry_run else "")  # fmt: skip
    return ExpandOutcome(_state(campaign_id, settings), _send(job_ids, settings, app),
                         created=len(variants))  # fmt: skip


def _cancel_if_requested(campaign_id: str, settings: Settings) -> None:
    now = utcnow()
    with session_scope(settings) as s:
        s.execute(
            update(Campaign)
            .where(Campaign.id == campaign_id, Campaign.state.in_(_EXPANDABLE),
                   Campaign.cancel_requested.is_(True))
            .values(state=CampaignState.CANCELLED, stage=None, finished_at=now, updated_at=now)
        )  # fmt: skip


def _state(campaign_id: str, settings: Settings) -> CampaignState:
    with session_scope(settings) as s:
        st = s.scalar(select(Campaign.state).where(Campaign.id == campaign_id))
    return CampaignState(st) if st is not None else CampaignState.FAILED


__all__ = [
    "POISON_REASON",
    "CampaignStop",
    "ExpandOutcome",
    "asset_footprints",
    "campaign_store",
    "commit_variants",
    "expand_campaign_stage",
    "prepare_sequences",
    "start_expansion",
]
