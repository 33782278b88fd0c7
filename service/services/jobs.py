"""Jobs: submission (checked against the sequence, idempotent), status, cancel, results.

The workers never call these: they write job state through ``worker/orchestration/state.py``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from osdar_platform.models import (
    ACTIVE_STATES,
    ApiKey,
    Asset,
    Job,
    JobEvent,
    JobState,
    Sequence,
    new_id,
)
from osdar_platform.settings import Settings
from service.errors import Conflict, Invalid, NotFound, TooManyRequests
from service.schemas import JobCreate, Loc, PointPlacement
from service.services.ownership import owned_or_404

log = logging.getLogger(__name__)


def check_spec(*, spec: JobCreate, sequence: Sequence) -> list[tuple[Loc, str]]:
    """What makes ``spec`` impossible on ``sequence``: (location, message) pairs."""
    errors: list[tuple[Loc, str]] = []
    have = list(sequence.cameras or [])
    for i, cam in enumerate(spec.cameras):
        if cam not in have:
            errors.append(
                (("body", "cameras", i), f"camera {cam!r} not in the sequence (it has {have})")
            )
    v = sequence.validation or {}
    indices = v.get("frame_indices") or []
    first, last = v.get("first_frame"), v.get("last_frame")
    if first is None or last is None:
        errors.append((("body", "sequence_id"), "the sequence has no frames"))
        return errors
    span = f"[{first}, {last}]"
    if spec.frame_range is not None:
        lo, hi = spec.frame_range
        for k, f in ((0, lo), (1, hi)):
            if not first <= f <= last:
                errors.append(
                    (("body", "frame_range", k), f"frame {f} outside the sequence's frames {span}")
                )
        if first <= lo <= hi <= last and indices and not any(lo <= i <= hi for i in indices):
            errors.append((("body", "frame_range"), f"no frame of the sequence in [{lo}, {hi}]"))
    for where, obj in spec.scene_objects():
        p = obj.placement
        if isinstance(p, PointPlacement) and p.mode == "lidar_frame" and p.frame_idx is not None:
            if indices and p.frame_idx not in indices:
                errors.append(
                    (
                        (*where, "placement", "frame_idx"),
                        f"frame {p.frame_idx} is not a frame of the sequence {span}",
                    )
                )
    if spec.lidar and not v.get("lidar"):
        errors.append((("body", "lidar"), "the sequence has no lidar stream"))
    for cam, per_frame in (spec.clicks or {}).items():
        if cam not in have:
            errors.append((("body", "clicks", cam), f"camera {cam!r} not in the sequence"))
            continue
        for frame in per_frame:
            if indices and int(frame) not in indices:
                errors.append(
                    (("body", "clicks", cam, frame), f"frame {frame} not in the sequence {span}")
                )
    return errors


def _frames_in(spec: JobCreate, sequence: Sequence) -> int:
    v = sequence.validation or {}
    indices = v.get("frame_indices") or []
    if spec.frame_range is None:
        return len(indices) or sequence.frames
    lo, hi = spec.frame_range
    return sum(1 for i in indices if lo <= i <= hi)


def _canonical(spec: dict[str, Any]) -> str:
    return json.dumps(spec, sort_keys=True, separators=(",", ":"))


def _existing(session: Session, owner: ApiKey, idempotency_key: str) -> Job | None:
    return session.scalar(
        select(Job).where(Job.owner_id == owner.id, Job.idempotency_key == idempotency_key)
    )


def _replay(job: Job, spec_json: dict[str, Any]) -> Job:
    if _canonical(job.spec) != _canonical(spec_json):
        raise Conflict("Idempotency-Key already used for a different job spec")
    return job


def create_job(
    *,
    session: Session,
    spec: JobCreate,
    owner: ApiKey,
    idempotency_key: str | None,
    settings: Settings,
) -> tuple[Job, bool]:
    """Check and record a job (PENDING, committed). Returns (job, created).

    With an ``idempotency_key`` already used by this key, the job recorded then is
    returned (created False) if the spec is the same, 409 otherwise; concurrent requests
    with one key race on the unique constraint and all but one read the winner's row.
    """
    spec_json = spec.model_dump(mode="json")
    if idempotency_key is not None:
        prior = _existing(session, owner, idempotency_key)
        if prior is not None:
            return _replay(prior, spec_json), False
    sequence = session.get(Sequence, spec.sequence_id)
    if sequence is None or sequence.owner_id != owner.id:
        raise NotFound(f"sequence {spec.sequence_id} not found (body.sequence_id)")
    for where, obj in spec.scene_objects():
        asset_id = obj.object.asset_id
        if asset_id is not None:
            asset = session.get(Asset, asset_id)
            if asset is None or asset.owner_id != owner.id:
                at = ".".join(str(x) for x in (*where, "object", "asset_id"))
                raise NotFound(f"asset {asset_id} not found ({at})")
    errors = check_spec(spec=spec, sequence=sequence)
    if errors:
        raise Invalid.many(errors)
    active = session.scalar(
        select(func.count())
        .select_from(Job)
        .where(
            Job.owner_id == owner.id,
            Job.state.in_(ACTIVE_STATES),
            Job.campaign_id.is_(None),  # a campaign's variants queue behind each other
        )
    )
    if active is not None and active >= settings.max_concurrent_jobs_per_key:
        raise TooManyRequests(
            f"{active} active jobs: at most {settings.max_concurrent_jobs_per_key} per API key",
            retry_after_s=30,
        )
    job = Job(
        id=new_id(),
        owner_id=owner.id,
        sequence_id=sequence.id,
        idempotency_key=idempotency_key,
        spec=spec_json,
        state=JobState.PENDING,
        progress_total=_frames_in(spec, sequence),
    )
    job.events.append(JobEvent(kind="created"))
    session.add(job)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        if idempotency_key is None:
            raise
        prior = _existing(session, owner, idempotency_key)
        if prior is None:
            raise
        return _replay(prior, spec_json), False
    return job, True


def submit_job(
    *,
    session: Session,
    spec: JobCreate,
    owner: ApiKey,
    idempotency_key: str | None,
    settings: Settings,
    enqueue: Callable[[str], None],
) -> tuple[Job, bool]:
    """:func:`create_job`, then hand a new job to the workers (after the commit).

    A failed send leaves the job PENDING (``worker.orchestration.queue.requeue_pending`` retries);
    the client still gets the job.
    """
    job, created = create_job(
        session=session,
        spec=spec,
        owner=owner,
        idempotency_key=idempotency_key,
        settings=settings,
    )
    if created:
        try:
            enqueue(job.id)
        except Exception as exc:
            log.warning("job %s stays PENDING: %s", job.id, exc)
        session.refresh(job)
    return job, created


def get_job(*, session: Session, owner: ApiKey, job_id: str, everyone: bool = False) -> Job:
    """The key's job (404 for another key's, unless ``everyone``: an operator's dashboard)."""
    return owned_or_404(session, Job, job_id, owner=owner, what="job", everyone=everyone)


def list_jobs(
    *,
    session: Session,
    owner: ApiKey,
    limit: int,
    offset: int,
    state: list[JobState] | None = None,
    sequence_id: str | None = None,
    campaign_id: str | None = None,
    everyone: bool = False,
) -> tuple[list[Job], int]:
    conds: list[Any] = [] if everyone else [Job.owner_id == owner.id]
    if campaign_id is not None:
        conds.append(Job.campaign_id == campaign_id)
    if state:
        conds.append(Job.state.in_(state))
    if sequence_id is not None:
        conds.append(Job.sequence_id == sequence_id)
    total = session.scalar(select(func.count()).select_from(Job).where(*conds)) or 0
    rows = session.scalars(
        select(Job)
        .where(*conds)
        .order_by(Job.created_at.desc(), Job.id)
        .limit(limit)
        .offset(offset)
    )
    return list(rows), total


def cancel_job(
    *, session: Session, owner: ApiKey, job_id: str, cancel: Callable[[str], Any]
) -> Job:
    """Cancel: QUEUED/PENDING at once, RUNNING at the worker's next check; 409 if done."""
    job = get_job(session=session, owner=owner, job_id=job_id)
    if job.state in (JobState.SUCCEEDED, JobState.FAILED):
        raise Conflict(f"job {job_id} is {job.state.value}: nothing to cancel")
    if job.state != JobState.CANCELLED:
        cancel(job_id)
        session.refresh(job)
    return job


def list_events(
    *, session: Session, owner: ApiKey, job_id: str, everyone: bool = False
) -> list[JobEvent]:
    job = get_job(session=session, owner=owner, job_id=job_id, everyone=everyone)
    return list(
        session.scalars(select(JobEvent).where(JobEvent.job_id == job.id).order_by(JobEvent.id))
    )


def finished_job(*, session: Session, owner: ApiKey, job_id: str, everyone: bool = False) -> Job:
    """The job if its results may be served: every result endpoint (archive, metrics,
    previews) asks here, and only a SUCCEEDED job has results; 409 otherwise (404 for
    another key's job). SUCCEEDED is set in the same row update that publishes the
    archive (worker/orchestration/state.publish_result), so a job seen SUCCEEDED has one."""
    job = get_job(session=session, owner=owner, job_id=job_id, everyone=everyone)
    if job.state != JobState.SUCCEEDED or job.result_key is None:
        raise Conflict(
            f"job {job_id} is {job.state.value}: its results are served once it SUCCEEDED"
        )
    return job


def archive_key(*, session: Session, owner: ApiKey, job_id: str, everyone: bool = False) -> str:
    """Store key of the published archive (409 unless SUCCEEDED)."""
    job = finished_job(session=session, owner=owner, job_id=job_id, everyone=everyone)
    assert job.result_key is not None  # finished_job checked it
    return job.result_key


def job_metrics(*, session: Session, owner: ApiKey, job_id: str) -> dict[str, Any]:
    """metrics.json of a SUCCEEDED job (409 otherwise)."""
    job = finished_job(session=session, owner=owner, job_id=job_id)
    return job.metrics or {}


def preview_keys(
    *, session: Session, owner: ApiKey, job_id: str, everyone: bool = False
) -> list[str]:
    """Store keys of a SUCCEEDED job's preview images (409 otherwise)."""
    job = finished_job(session=session, owner=owner, job_id=job_id, everyone=everyone)
    return [str(k) for k in (job.previews or [])]


def preview_key(
    *, session: Session, owner: ApiKey, job_id: str, index: int, everyone: bool = False
) -> str:
    keys = preview_keys(session=session, owner=owner, job_id=job_id, everyone=everyone)
    if not 0 <= index < len(keys):
        raise NotFound(f"job {job_id} has no preview {index}")
    return keys[index]
