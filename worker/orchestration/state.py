"""Job state transitions written by the workers, each in one short transaction.

Every change is a conditional ``UPDATE ... WHERE`` on the row, so that two deliveries of
the same job (Celery delivers at least once) can never undo each other's work:

- :func:`mark_running` starts an *attempt*: it counts the delivery, refuses a job that
  has crashed its workers too often (poison input), and moves QUEUED -> RUNNING with
  ``attempt + 1``. The attempt number scopes everything an attempt writes. The leases of
  earlier attempts are dropped (``lease.py``: liveness per running stage).
- :func:`check_attempt` is the checkpoint between stages and chunks: a job that was
  cancelled raises :class:`JobCancelled`; one that finished, failed or was taken over by a
  newer attempt raises :class:`JobSuperseded` (the stale attempt just stops).
- :func:`publish_result` is the single atomic step that makes a result visible:
  ``UPDATE jobs SET result_key=... WHERE id=... AND result_key IS NULL AND state=RUNNING``.

No session is held across compute: callers pass ids, these functions open and close.
"""

from __future__ import annotations

import logging
from typing import Any

from sqlalchemy import case, delete, func, select, update

from osdar_platform.db import session_scope, updated_rows
from osdar_platform.models import TERMINAL_STATES, Job, JobEvent, JobLease, JobState, utcnow
from osdar_platform.settings import Settings

log = logging.getLogger(__name__)

#: Reason written when a job keeps killing the worker that runs it.
POISON_REASON = "worker died repeatedly (poison input?)"
_MAX_ERROR_CHARS = 4000


class JobStop(Exception):
    """The attempt must stop now (the job's state already says why)."""


class JobSuperseded(JobStop):
    """The job is gone, terminal, or run by a newer attempt: stop without writing."""


class JobCancelled(JobStop):
    """The job's ``cancel_requested`` flag is set: clean up and mark it CANCELLED."""


class JobFailed(JobStop):
    """The attempt failed; the job is FAILED with the reason (``str(exc)``)."""


def _not_terminal() -> Any:
    return Job.state.not_in(list(TERMINAL_STATES))


def _event(session: Any, job_id: str, kind: str, attempt: int, message: str | None = None,
           data: dict[str, Any] | None = None) -> None:  # fmt: skip
    session.add(JobEvent(job_id=job_id, kind=kind, attempt=attempt, message=message, data=data))


def record_event(job_id: str, kind: str, attempt: int, message: str | None = None,
                 data: dict[str, Any] | None = None, *, settings: Settings) -> None:  # fmt: skip
    """Append one event to the job's log (store retries, reaper actions)."""
    with session_scope(settings) as s:
        _event(s, job_id, kind, attempt, message=message, data=data)


def mark_running(job_id: str, *, settings: Settings, max_deliveries: int | None = None) -> int:
    """Count this delivery of ``job_id`` and start a new attempt; returns its number.

    Raises
    ------
    JobSuperseded
        No such job, or it is terminal already (a late re-delivery), or it has now been
        delivered more than ``max_deliveries`` times and was marked FAILED (poison).
    JobCancelled
        Cancel was requested before the attempt started (the job is marked CANCELLED).
    """
    limit = max_deliveries if max_deliveries is not None else settings.max_deliveries
    now = utcnow()
    with session_scope(settings) as s:
        counted = updated_rows(
            s,
            update(Job)
            .where(Job.id == job_id, _not_terminal())
            .values(deliveries=Job.deliveries + 1, updated_at=now),
        )
        if not counted:
            raise JobSuperseded(f"job {job_id} is gone or finished")
        job = s.execute(
            select(Job.deliveries, Job.attempt, Job.cancel_requested).where(Job.id == job_id)
        ).one()
    if job.deliveries > limit:
        mark_failed(job_id, POISON_REASON, settings=settings, data={"deliveries": job.deliveries})
        raise JobSuperseded(POISON_REASON)
    if job.cancel_requested:
        mark_cancelled(job_id, settings=settings, attempt=job.attempt)
        raise JobCancelled(job_id)
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Job)
            .where(
                Job.id == job_id,
                Job.state.in_([JobState.PENDING, JobState.QUEUED, JobState.RUNNING]),
                Job.attempt == job.attempt,  # two deliveries racing: one wins
            )
            .values(
                state=JobState.RUNNING,
                attempt=Job.attempt + 1,
                stage="starting",
                progress_done=0,
                error=None,
                started_at=func.coalesce(Job.started_at, now),
                updated_at=now,
                broker_seen_at=now,  # its message was delivered just now
                # the join of the new attempt's chunks starts empty (chunk_join.py)
                chunks_total=0,
                chunks_done=None,
                finish_token=None,
                finish_sent_at=None,
                finish_started_at=None,
            ),
        )
        if not moved:
            raise JobSuperseded(f"job {job_id} was taken by another delivery")
        attempt: int = job.attempt + 1
        # the leases of earlier attempts mean nothing now (lease.py)
        s.execute(delete(JobLease).where(JobLease.job_id == job_id, JobLease.attempt < attempt))
        _event(s, job_id, "attempt_started", attempt, data={"deliveries": job.deliveries})
    return attempt


def current_attempt(job_id: str, *, settings: Settings) -> int:
    with session_scope(settings) as s:
        attempt = s.scalar(select(Job.attempt).where(Job.id == job_id))
    if attempt is None:
        raise JobSuperseded(f"job {job_id} does not exist")
    return int(attempt)


def check_attempt(job_id: str, attempt: int, *, settings: Settings) -> None:
    """The checkpoint between stages and chunks (see the module docstring)."""
    with session_scope(settings) as s:
        row = s.execute(
            select(Job.state, Job.attempt, Job.cancel_requested).where(Job.id == job_id)
        ).one_or_none()
    if row is None or row.state in TERMINAL_STATES or row.attempt != attempt:
        raise JobSuperseded(f"job {job_id} attempt {attempt} is no longer current")
    if row.cancel_requested:
        raise JobCancelled(job_id)


def count_stage_delivery(job_id: str, attempt: int, stage: str, *, settings: Settings) -> int:
    """Record that ``stage`` was delivered; returns how many times it was, in all attempts.

    A stage task whose worker died is delivered again (``task_reject_on_worker_lost``);
    the count lets the stage refuse a poison input the way :func:`mark_running` does.
    It spans the job's attempts: when the reaper re-queues a job whose stage killed its
    worker (an expired lease), the new attempt's deliveries of that stage add to the
    earlier ones, so a poison input kills at most ``max_deliveries`` workers per stage.
    """
    with session_scope(settings) as s:
        _event(s, job_id, "stage_delivered", attempt, message=stage)
        s.flush()
        return int(
            s.scalar(
                select(func.count())
                .select_from(JobEvent)
                .where(
                    JobEvent.job_id == job_id,
                    JobEvent.kind == "stage_delivered",
                    JobEvent.message == stage,
                )
            )
            or 0
        )


def set_stage(
    job_id: str,
    attempt: int,
    stage: str,
    *,
    settings: Settings,
    done: int | None = None,
    total: int | None = None,
) -> bool:
    """Show ``stage`` (and optionally frames done/total) on a RUNNING job of this attempt."""
    values: dict[str, Any] = {"stage": stage, "updated_at": utcnow()}
    if done is not None:
        values["progress_done"] = done
    if total is not None:
        values["progress_total"] = total
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Job)
            .where(Job.id == job_id, Job.attempt == attempt, Job.state == JobState.RUNNING)
            .values(**values),
        )
    return bool(moved)


def set_progress(job_id: str, attempt: int, done: int, *, settings: Settings) -> None:
    """Frames done so far (capped by the total)."""
    capped = case((Job.progress_total < done, Job.progress_total), else_=done)
    with session_scope(settings) as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id, Job.attempt == attempt, Job.state == JobState.RUNNING)
            .values(progress_done=capped, updated_at=utcnow())
        )


def add_progress(job_id: str, attempt: int, frames: int, *, settings: Settings) -> None:
    """Add ``frames`` done (parallel chunks add theirs atomically; capped by the total)."""
    new = Job.progress_done + frames
    capped = case((new > Job.progress_total, Job.progress_total), else_=new)
    with session_scope(settings) as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id, Job.attempt == attempt, Job.state == JobState.RUNNING)
            .values(progress_done=capped, updated_at=utcnow())
        )


def _lock_attempt(s: Any, job_id: str, attempt: int) -> bool:
    """Touch the attempt's row to lock it for the rest of the transaction: a row lock on
    PostgreSQL, the write lock on SQLite (whose driver starts a transaction at the first
    write, so a read before it would not be protected); False if the attempt is gone."""
    touch = update(Job).where(Job.id == job_id, Job.attempt == attempt)
    return bool(updated_rows(s, touch.values(updated_at=Job.updated_at)))


def record_timing(job_id: str, attempt: int, stage: str, seconds: float, *,
                  settings: Settings) -> None:  # fmt: skip
    """Add ``stage: seconds`` to the job's timings (chunks of one job running at once
    add theirs under the row's lock: neither is lost)."""
    with session_scope(settings) as s:
        if not _lock_attempt(s, job_id, attempt):
            return
        timings = s.scalar(select(Job.timings).where(Job.id == job_id)) or {}
        timings = {**timings, stage: round(float(seconds), 3)}
        s.execute(update(Job).where(Job.id == job_id).values(timings=timings))


def merge_metrics(job_id: str, attempt: int, metrics: dict[str, Any], *,
                  settings: Settings) -> None:  # fmt: skip
    """Merge top-level keys into the job's metrics (evaluate, augmentation)."""
    with session_scope(settings) as s:
        if not _lock_attempt(s, job_id, attempt):
            return
        merged = {**(s.scalar(select(Job.metrics).where(Job.id == job_id)) or {}), **metrics}
        s.execute(update(Job).where(Job.id == job_id).values(metrics=merged))


def get_metrics(job_id: str, *, settings: Settings) -> dict[str, Any]:
    with session_scope(settings) as s:
        return dict(s.scalar(select(Job.metrics).where(Job.id == job_id)) or {})


def publish_result(
    job_id: str,
    attempt: int,
    result_key: str,
    *,
    settings: Settings,
    previews: list[str] | None = None,
) -> bool:
    """Make ``result_key`` the job's result and the job SUCCEEDED: True if this call won.

    One conditional row update: a re-delivered publish, or a stale attempt racing a newer
    one, finds ``result_key`` set (or the job no longer RUNNING) and changes nothing.
    """
    now = utcnow()
    with session_scope(settings) as s:
        won = updated_rows(
            s,
            update(Job)
            .where(Job.id == job_id, Job.result_key.is_(None), Job.state == JobState.RUNNING)
            .values(
                result_key=result_key,
                previews=previews or [],
                state=JobState.SUCCEEDED,
                stage="done",
                progress_done=Job.progress_total,
                finished_at=now,
                updated_at=now,
            ),
        )
        if won:
            _event(s, job_id, "succeeded", attempt, data={"result_key": result_key})
        else:
            _event(s, job_id, "publish_lost", attempt, data={"result_key": result_key})
    return bool(won)


def mark_failed(
    job_id: str,
    reason: str,
    *,
    settings: Settings,
    attempt: int | None = None,
    data: dict[str, Any] | None = None,
) -> bool:
    """FAILED with ``reason`` unless already terminal (or, given ``attempt``, superseded)."""
    now = utcnow()
    conds = [Job.id == job_id, _not_terminal()]
    if attempt is not None:
        conds.append(Job.attempt == attempt)
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Job)
            .where(*conds)
            .values(
                state=JobState.FAILED,
                error=reason[:_MAX_ERROR_CHARS],
                finished_at=now,
                updated_at=now,
            ),
        )
        if moved:
            at = attempt if attempt is not None else s.scalar(
                select(Job.attempt).where(Job.id == job_id)
            )  # fmt: skip
            _event(s, job_id, "failed", int(at or 0), message=reason[:_MAX_ERROR_CHARS], data=data)
    if moved:
        log.warning("job %s FAILED: %s", job_id, reason)
    return bool(moved)


def mark_cancelled(job_id: str, *, settings: Settings, attempt: int | None = None) -> bool:
    """CANCELLED unless already terminal."""
    now = utcnow()
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(Job)
            .where(Job.id == job_id, _not_terminal())
            .values(state=JobState.CANCELLED, stage="cancelled", finished_at=now, updated_at=now),
        )
        if moved:
            _event(s, job_id, "cancelled", attempt or 0)
    return bool(moved)


__all__ = [
    "POISON_REASON",
    "JobCancelled",
    "JobFailed",
    "JobStop",
    "JobSuperseded",
    "add_progress",
    "check_attempt",
    "count_stage_delivery",
    "current_attempt",
    "get_metrics",
    "mark_cancelled",
    "mark_failed",
    "mark_running",
    "merge_metrics",
    "publish_result",
    "record_event",
    "record_timing",
    "set_progress",
    "set_stage",
]
