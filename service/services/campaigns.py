"""Campaigns: submission (checked against the key's sequences, idempotent), status with
aggregate progress and per-variant states, listing, cancel, the manifest.

The expansion needs the prepared sequences' geometry, which the API never imports: a
worker runs it (``osdar_ar.campaign_expand``: worker/campaign/service_expand.py) and
writes the variants and their jobs; the manifest is written by the worker when every
variant has finished (worker/campaign/service_finalize.py). The API sends those tasks
(:class:`~service.deps.Dispatcher`) and, when it sees a campaign whose message got lost
(PENDING past the grace, or EXPANDING without a heartbeat for longer than a task may run)
or whose variants are all finished without a manifest, sends them again (:func:`nudge`,
on every GET of the campaign; the workers' reaper does the same for every campaign):
both tasks are idempotent.
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable
from typing import Any

from sqlalchemy import case, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from osdar_platform.models import (
    TERMINAL_STATES,
    ApiKey,
    Asset,
    Campaign,
    CampaignState,
    CampaignVariant,
    Job,
    JobState,
    Sequence,
    utcnow,
)
from service.campaign_schemas import (
    CampaignDetail,
    CampaignIssue,
    CampaignLinks,
    CampaignProgress,
    CampaignPublic,
    CampaignVariantPublic,
    VariantLinks,
)
from service.errors import Conflict, Invalid
from service.schemas import ID_PATTERN, Progress
from service.services.ownership import owned_or_404
from worker.campaign.spec import CampaignSpec
from worker.orchestration.queue import nudge_campaign as nudge

log = logging.getLogger(__name__)

Loc = tuple[str | int, ...]


# ---------------------------------------------------------------------------- checks
def check_campaign(*, session: Session, spec: CampaignSpec, owner: ApiKey) -> list[tuple[Loc, str]]:
    """What makes the spec impossible on the key's sequences and assets, by field."""
    errors: list[tuple[Loc, str]] = []
    cameras = list(spec.job.cameras)
    for i, entry in enumerate(spec.sequences):
        loc: Loc = ("body", "sequences", i)
        if entry.path is not None:
            errors.append((
                (*loc, "path"),
                "a service campaign names registered or uploaded sequences by 'id' "
                "(POST /v1/sequences); 'path' is for `osdar-ar campaign run`",
            ))  # fmt: skip
            continue
        if not re.fullmatch(ID_PATTERN, str(entry.id)):
            errors.append(((*loc, "id"), f"not an id (ids match {ID_PATTERN})"))
            continue
        seq = session.get(Sequence, entry.id)
        if seq is None or seq.owner_id != owner.id:
            errors.append(((*loc, "id"), f"sequence {entry.id} not found for this key"))
            continue
        have = list(seq.cameras or [])
        for k, cam in enumerate(cameras):
            if cam not in have:
                errors.append((
                    ("body", "job", "cameras", k),
                    f"camera {cam!r} not in sequence {entry.label} (it has {have})",
                ))  # fmt: skip
        v = seq.validation or {}
        first, last = v.get("first_frame"), v.get("last_frame")
        if first is None or last is None:
            errors.append(((*loc, "id"), f"sequence {entry.label} has no frames"))
        elif entry.frame_range is not None:
            for k, f in enumerate(entry.frame_range):
                if not first <= f <= last:
                    errors.append((
                        (*loc, "frame_range", k),
                        f"frame {f} outside the sequence's frames [{first}, {last}]",
                    ))  # fmt: skip
        if spec.job.lidar and not v.get("lidar"):
            errors.append((("body", "job", "lidar"), f"sequence {entry.label} has no lidar"))
    for i, ob in enumerate(spec.obstacles):
        if ob.asset_id is not None:
            if not re.fullmatch(ID_PATTERN, str(ob.asset_id)):
                errors.append((("body", "obstacles", i, "asset_id"), "not an id"))
                continue
            asset = session.get(Asset, ob.asset_id)
            if asset is None or asset.owner_id != owner.id:
                errors.append(
                    (("body", "obstacles", i, "asset_id"), f"asset {ob.asset_id} not found")
                )
    return errors


def _canonical(spec: dict[str, Any], dry_run: bool) -> str:
    return json.dumps({"spec": spec, "dry_run": dry_run}, sort_keys=True, separators=(",", ":"))


def _replay(c: Campaign, spec_json: dict[str, Any], dry_run: bool) -> Campaign:
    if _canonical(c.spec, c.dry_run) != _canonical(spec_json, dry_run):
        raise Conflict("Idempotency-Key already used for a different campaign (spec or dry_run)")
    return c


def _existing(session: Session, owner: ApiKey, idempotency_key: str) -> Campaign | None:
    return session.scalar(
        select(Campaign).where(
            Campaign.owner_id == owner.id, Campaign.idempotency_key == idempotency_key
        )
    )


def create_campaign(
    *,
    session: Session,
    spec: CampaignSpec,
    owner: ApiKey,
    dry_run: bool,
    idempotency_key: str | None,
) -> tuple[Campaign, bool]:
    """Check and record a campaign (PENDING, committed). Returns (campaign, created);
    an ``idempotency_key`` already used returns that campaign (same spec) or 409."""
    spec_json = spec.model_dump(mode="json")
    if idempotency_key is not None:
        prior = _existing(session, owner, idempotency_key)
        if prior is not None:
            return _replay(prior, spec_json, dry_run), False
    errors = check_campaign(session=session, spec=spec, owner=owner)
    if errors:
        raise Invalid.many(errors)
    row = Campaign(
        owner_id=owner.id,
        name=spec.name,
        idempotency_key=idempotency_key,
        spec=spec_json,
        dry_run=dry_run,
        state=CampaignState.PENDING,
    )
    session.add(row)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        if idempotency_key is None:
            raise
        prior = _existing(session, owner, idempotency_key)
        if prior is None:
            raise
        return _replay(prior, spec_json, dry_run), False
    return row, True


def submit_campaign(
    *,
    session: Session,
    spec: CampaignSpec,
    owner: ApiKey,
    dry_run: bool,
    idempotency_key: str | None,
    send_expand: Callable[[str], None],
) -> tuple[Campaign, bool]:
    """:func:`create_campaign`, then the expansion sent to the workers (a failed send
    leaves it PENDING: :func:`nudge` sends it again)."""
    row, created = create_campaign(session=session, spec=spec, owner=owner, dry_run=dry_run,
                                   idempotency_key=idempotency_key)  # fmt: skip
    if created:
        try:
            send_expand(row.id)
        except Exception as exc:
            log.warning("campaign %s stays PENDING: %s", row.id, exc)
    return row, created


def wait_expanded(*, session: Session, campaign_id: str, timeout_s: float) -> Campaign:
    """Poll the row until the expansion is done (or failed) or ``timeout_s`` passed."""
    deadline = time.monotonic() + timeout_s
    while True:
        row = session.get(Campaign, campaign_id)
        assert row is not None
        session.refresh(row)
        if row.state not in (CampaignState.PENDING, CampaignState.EXPANDING):
            return row
        if time.monotonic() >= deadline:
            return row
        time.sleep(min(0.25, max(0.0, deadline - time.monotonic())))


# ---------------------------------------------------------------------------- reading
def get_campaign(
    *, session: Session, owner: ApiKey, campaign_id: str, everyone: bool = False
) -> Campaign:
    """The campaign (404 for another key's, unless ``everyone``: an operator's dashboard)."""
    return owned_or_404(
        session, Campaign, campaign_id, owner=owner, what="campaign", everyone=everyone
    )


def list_campaigns(
    *,
    session: Session,
    owner: ApiKey,
    limit: int,
    offset: int,
    state: list[CampaignState] | None = None,
    everyone: bool = False,
) -> tuple[list[Campaign], int]:
    conds: list[Any] = [] if everyone else [Campaign.owner_id == owner.id]
    if state:
        conds.append(Campaign.state.in_(state))
    total = session.scalar(select(func.count()).select_from(Campaign).where(*conds)) or 0
    rows = session.scalars(
        select(Campaign)
        .where(*conds)
        .order_by(Campaign.created_at.desc(), Campaign.id)
        .limit(limit)
        .offset(offset)
    )
    return list(rows), total


def progress_of(session: Session, campaign_ids: list[str]) -> dict[str, CampaignProgress]:
    """Aggregate progress of each campaign from its jobs (one query)."""

    def count(*states: JobState) -> Any:
        return func.sum(case((Job.state.in_(states), 1), else_=0))

    rows = session.execute(
        select(
            Job.campaign_id,
            func.count(),
            count(JobState.PENDING, JobState.QUEUED),
            count(JobState.RUNNING),
            count(JobState.SUCCEEDED),
            count(JobState.FAILED),
            count(JobState.CANCELLED),
            func.sum(Job.progress_done),
            func.sum(Job.progress_total),
        )
        .where(Job.campaign_id.in_(campaign_ids))
        .group_by(Job.campaign_id)
    ).all()
    out: dict[str, CampaignProgress] = {}
    for cid, n, pending, running, ok, failed, cancelled, done, total in rows:
        done, total = int(done or 0), int(total or 0)
        out[str(cid)] = CampaignProgress(
            variants=int(n), pending=int(pending or 0), running=int(running or 0),
            succeeded=int(ok or 0), failed=int(failed or 0), cancelled=int(cancelled or 0),
            frames_done=done, frames_total=total,
            fraction=round(done / total, 4) if total else 0.0,
        )  # fmt: skip
    return out


def _empty_progress(c: Campaign) -> CampaignProgress:
    return CampaignProgress(
        variants=c.variants_total, pending=0, running=0, succeeded=0, failed=0, cancelled=0,
        frames_done=0, frames_total=0, fraction=0.0,
    )  # fmt: skip


def public(c: Campaign, progress: CampaignProgress | None) -> CampaignPublic:
    base = f"/v1/campaigns/{c.id}"
    return CampaignPublic(
        id=c.id, name=c.name, state=c.state, stage=c.stage, dry_run=c.dry_run,
        cancel_requested=c.cancel_requested, error=c.error,
        issues=[CampaignIssue(**i) for i in (c.issues or [])],
        spec=c.spec, progress=progress or _empty_progress(c), summary=c.summary,
        created_at=c.created_at, updated_at=c.updated_at, expanded_at=c.expanded_at,
        finished_at=c.finished_at,
        links=CampaignLinks(
            self=base, cancel=f"{base}/cancel",
            manifest_json=f"{base}/manifest.json" if c.manifest_json_key else None,
            manifest_csv=f"{base}/manifest.csv" if c.manifest_csv_key else None,
        ),
    )  # fmt: skip


def variant_rows(
    session: Session, campaign_id: str, *, limit: int, offset: int
) -> list[tuple[CampaignVariant, Job | None]]:
    rows = session.execute(
        select(CampaignVariant, Job)
        .join(Job, Job.id == CampaignVariant.job_id, isouter=True)
        .where(CampaignVariant.campaign_id == campaign_id)
        .order_by(CampaignVariant.index)
        .limit(limit)
        .offset(offset)
    ).all()
    return [(v, j) for v, j in rows]


def variant_public(v: CampaignVariant, job: Job | None) -> CampaignVariantPublic:
    data = v.variant or {}
    ok = job is not None and job.state == JobState.SUCCEEDED and job.result_key is not None
    return CampaignVariantPublic(
        index=v.index, id=v.variant_id, key=v.key, sequence_id=v.sequence_id,
        sequence_label=v.sequence_label, classes=[str(c) for c in v.classes or []],
        objects=list(data.get("objects") or []), warnings=list(data.get("warnings") or []),
        job_id=v.job_id, state=None if job is None else job.state,
        stage=None if job is None else job.stage,
        progress=None if job is None else Progress(done=job.progress_done,
                                                   total=job.progress_total),
        error=None if job is None else job.error, row=v.row,
        links=VariantLinks(
            job=None if v.job_id is None else f"/v1/jobs/{v.job_id}",
            archive=f"/v1/jobs/{v.job_id}/archive" if ok else None,
            previews=f"/v1/jobs/{v.job_id}/previews" if ok and job and job.previews else None,
        ),
    )  # fmt: skip


def detail(session: Session, c: Campaign, *, limit: int, offset: int) -> CampaignDetail:
    progress = progress_of(session, [c.id]).get(c.id)
    rows = variant_rows(session, c.id, limit=limit, offset=offset)
    return CampaignDetail(
        **public(c, progress).model_dump(),
        variants=[variant_public(v, j) for v, j in rows],
        variants_offset=offset,
        variants_limit=limit,
    )


# ---------------------------------------------------------------------------- actions
def cancel_campaign(
    *,
    session: Session,
    owner: ApiKey,
    campaign_id: str,
    cancel_job: Callable[[str], Any],
    send_finalize: Callable[[str], None],
) -> Campaign:
    """Cancel: before the expansion commits, at once (no variant is made); afterwards
    every unfinished variant job is cancelled (queued ones at once, running ones at their
    next check) and the campaign ends when they have. 409 once the campaign has ended."""
    c = get_campaign(session=session, owner=owner, campaign_id=campaign_id)
    if c.state.terminal:
        raise Conflict(f"campaign {campaign_id} is {c.state.value}: nothing to cancel")
    now = utcnow()
    session.execute(
        update(Campaign).where(Campaign.id == c.id).values(cancel_requested=True, updated_at=now)
    )
    session.execute(
        update(Campaign)
        .where(Campaign.id == c.id, Campaign.state.in_([CampaignState.PENDING,
                                                         CampaignState.EXPANDING]))
        .values(state=CampaignState.CANCELLED, stage=None, finished_at=now)
    )  # fmt: skip
    session.commit()
    session.refresh(c)
    if c.state == CampaignState.RUNNING:
        ids = session.scalars(
            select(Job.id).where(Job.campaign_id == c.id, Job.state.not_in(list(TERMINAL_STATES)))
        ).all()
        for job_id in ids:
            cancel_job(job_id)
        try:
            send_finalize(c.id)
        except Exception as exc:  # nudge() sends it again
            log.warning("campaign %s: finalize not sent: %s", c.id, exc)
        session.refresh(c)
    return c


def manifest_key(
    *, session: Session, owner: ApiKey, campaign_id: str, fmt: str, everyone: bool = False
) -> str:
    """Store key of the manifest (``json`` or ``csv``); 409 until the campaign ended."""
    c = get_campaign(session=session, owner=owner, campaign_id=campaign_id, everyone=everyone)
    key = c.manifest_json_key if fmt == "json" else c.manifest_csv_key
    if key is None:
        raise Conflict(
            f"campaign {campaign_id} is {c.state.value}: its manifest is written when every "
            "variant has finished"
        )
    return key


__all__ = [
    "cancel_campaign",
    "check_campaign",
    "create_campaign",
    "detail",
    "get_campaign",
    "list_campaigns",
    "manifest_key",
    "nudge",
    "progress_of",
    "public",
    "submit_campaign",
    "variant_public",
    "variant_rows",
    "wait_expanded",
]
