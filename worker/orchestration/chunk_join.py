"""The join of a job's chunks before ``finish``, in our database (no Celery chord).

A job's frames are augmented in chunks that may run on several workers at once; its
``finish`` needs every chunk's result. A Celery chord on the database result backend is
finished by ``celery.chord_unlock`` polling once a second: about a second of every
job's latency and a worker busy polling (scripts/bench_campaign_throughput.py). Here the
join lives on the job's row, in the columns ``chunks_total``, ``chunks_done``,
``finish_token``, ``finish_sent_at`` and ``finish_started_at``, all reset when an attempt
starts (``state.mark_running``), every change scoped to the attempt:

- :func:`plan` (``run_job``, before the stages are sent) records how many chunks the
  attempt has;
- :func:`complete_chunk` (at the end of a chunk's stage, inside its lease) records the
  chunk's result (store keys) under its index: a chunk delivered again finds its index
  there and changes nothing, so no chunk is counted twice; :func:`chunk_result` lets such a
  delivery skip the work it already did;
- :func:`claim_finish` (the chunk task, after its stage) hands out the token of the one
  ``finish`` once every chunk is done: of the chunks racing there, exactly one gets it, and
  only that one sends ``finish`` (:func:`send_finish`). The token travels in the message;
- :func:`admit_finish` (``finish``, inside its lease) lets only the message carrying the
  current token start, and marks the finish started.

Each read-modify-write first touches the row (``UPDATE ... SET updated_at=updated_at``):
on PostgreSQL that locks the row until the commit, on SQLite it takes the database's
write lock, so the read that follows sees the last committed state and no other writer
can interleave (SQLite's driver starts its transaction at the first write, not at a read).

A process that dies between its chunk's record and the send of ``finish`` (or a send the
broker lost) leaves a job RUNNING with every chunk done, no lease and no ``finish``
started. The reaper (``reaper.py``) claims a new token for it with
``claim_finish(resend=True)`` once the row has been still for ``reaper_orphan_grace_s``
and sends ``finish`` again; a late delivery of the first message carries the old token
and is refused by :func:`admit_finish`.
"""

from __future__ import annotations

import uuid
from typing import Any

from celery import chain
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from osdar_platform.db import session_scope, updated_rows
from osdar_platform.models import Job, JobEvent, JobState, utcnow
from osdar_platform.settings import Settings
from worker.orchestration.queue import TASK_EVALUATE, TASK_FINISH, TASK_PACKAGE, TASK_PUBLISH


def _lock(s: Session, job_id: str, attempt: int, *extra: Any) -> bool:
    """Touch the attempt's RUNNING row (and ``extra`` conditions) to lock it for the rest
    of the transaction (module docstring); False if there is no such row."""
    touch = update(Job).where(
        Job.id == job_id, Job.attempt == attempt, Job.state == JobState.RUNNING, *extra
    )
    return bool(updated_rows(s, touch.values(updated_at=Job.updated_at)))


def plan(job_id: str, attempt: int, total: int, *, settings: Settings) -> None:
    """The attempt has ``total`` chunks (``total`` >= 1)."""
    with session_scope(settings) as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id, Job.attempt == attempt, Job.state == JobState.RUNNING)
            .values(chunks_total=total, updated_at=utcnow())
        )


def chunk_result(job_id: str, attempt: int, index: int, *, settings: Settings) -> Any:
    """The recorded result of chunk ``index`` of the attempt (None: not done)."""
    with session_scope(settings) as s:
        row = s.execute(select(Job.attempt, Job.chunks_done).where(Job.id == job_id)).one_or_none()
    if row is None or row.attempt != attempt:
        return None
    return (row.chunks_done or {}).get(str(index))


def complete_chunk(
    job_id: str, attempt: int, index: int, result: dict[str, Any], *, settings: Settings
) -> bool:
    """Record chunk ``index`` of the attempt as done with ``result`` (JSON); True if this
    call counted it (False: it was already, or the attempt is no longer current)."""
    with session_scope(settings) as s:
        if not _lock(s, job_id, attempt):
            return False
        done = dict(s.scalar(select(Job.chunks_done).where(Job.id == job_id)) or {})
        if str(index) in done:
            return False
        done[str(index)] = result
        s.execute(update(Job).where(Job.id == job_id).values(chunks_done=done))
    return True


def claim_finish(
    job_id: str, attempt: int, *, settings: Settings, resend: bool = False
) -> str | None:
    """The token of the attempt's ``finish`` if the caller must send it, else None.

    Once every chunk is done the first call gets a new token; later calls get None (the
    finish is sent already). ``resend``: the reaper's claim for a finish that never
    started (module docstring; :func:`claim_in`).
    """
    with session_scope(settings) as s:
        return claim_in(s, job_id, attempt, resend=resend)


def claim_in(
    s: Session, job_id: str, attempt: int, *, resend: bool = False, seen_updated: Any = None
) -> str | None:
    """:func:`claim_finish` in the caller's transaction (the reaper's own sessions);
    ``seen_updated``: the row's ``updated_at`` as the caller read it (a row that moved
    since is not claimed). ``resend`` hands out a new token even if one was."""
    extra = [Job.finish_started_at.is_(None)]
    if seen_updated is not None:
        extra.append(Job.updated_at == seen_updated)
    if not _lock(s, job_id, attempt, *extra):
        return None
    row = s.execute(
        select(Job.chunks_total, Job.chunks_done, Job.finish_token).where(Job.id == job_id)
    ).one()
    if not joined_at(row.chunks_total, row.chunks_done):
        return None
    if row.finish_token is not None and not resend:
        return None
    token = uuid.uuid4().hex
    now = utcnow()
    s.execute(
        update(Job)
        .where(Job.id == job_id)
        .values(finish_token=token, finish_sent_at=now, updated_at=now)
    )
    if resend:
        data = {"by": "reaper", "previous_token": row.finish_token}
        s.add(JobEvent(job_id=job_id, kind="finish_resent", attempt=attempt, data=data))
    return token


def finish_token_current(job_id: str, attempt: int, token: str, *, settings: Settings) -> bool:
    """Whether ``token`` is the attempt's finish token (a cheap check before the lease)."""
    with session_scope(settings) as s:
        row = s.execute(select(Job.attempt, Job.finish_token).where(Job.id == job_id)).one_or_none()
    return row is not None and row.attempt == attempt and row.finish_token == token


def admit_finish(job_id: str, attempt: int, token: str, *, settings: Settings) -> bool:
    """Let the ``finish`` carrying ``token`` start (again, if it was delivered again) and
    mark the attempt's finish started; False for a stale token or attempt."""
    now = utcnow()
    with session_scope(settings) as s:
        return bool(
            updated_rows(
                s,
                update(Job)
                .where(
                    Job.id == job_id,
                    Job.attempt == attempt,
                    Job.state == JobState.RUNNING,
                    Job.finish_token == token,
                )
                .values(finish_started_at=now, updated_at=now),
            )
        )


def chunk_results(job_id: str, attempt: int, *, settings: Settings) -> list[dict[str, Any]]:
    """Every recorded chunk result of the attempt, in chunk order."""
    with session_scope(settings) as s:
        row = s.execute(select(Job.attempt, Job.chunks_done).where(Job.id == job_id)).one_or_none()
    if row is None or row.attempt != attempt:
        return []
    done: dict[str, Any] = row.chunks_done or {}
    return [done[k] for k in sorted(done, key=int)]


def joined_at(chunks_total: int, chunks_done: dict[str, Any] | None) -> bool:
    """Whether a row's chunks are all done (the reaper reads the columns itself)."""
    return chunks_total > 0 and len(chunks_done or {}) >= chunks_total


def send_finish(app: Any, job_id: str, attempt: int, token: str) -> None:
    """Send ``finish`` (with ``token``) and the stages after it: evaluate, package,
    publish, each sent by the one before when it completes."""

    def step(name: str, *args: Any, immutable: bool = True) -> Any:
        return app.signature(name, args=args, immutable=immutable)

    chain(
        step(TASK_FINISH, job_id, attempt, token),
        step(TASK_EVALUATE, job_id, attempt),
        step(TASK_PACKAGE, job_id, attempt),
        step(TASK_PUBLISH, job_id, attempt, immutable=False),  # gets the archive path
    ).apply_async()


__all__ = [
    "admit_finish",
    "chunk_result",
    "chunk_results",
    "claim_finish",
    "claim_in",
    "complete_chunk",
    "finish_token_current",
    "joined_at",
    "plan",
    "send_finish",
]
