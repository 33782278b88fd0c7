"""The reaper: jobs that no worker will ever finish are re-queued (or FAILED), never lost.

Celery's at-least-once delivery covers a worker process that dies mid-task (the message
goes back: ``task_reject_on_worker_lost``, or the Redis visibility timeout). Three cases
are left, and each leaves a job row active with nothing working on it:

- **stale RUNNING**: a task stopped at the hard time limit is acknowledged as failed
  (no redelivery), and a worker whose parent was killed with its children may leave a
  stage whose chain never continues. A RUNNING job whose row has not changed (the
  heartbeat: every stage, sub-stage and frame updates ``updated_at``) for longer than the
  hard limit plus a margin has no live task: no stage runs longer than the hard limit.
- **orphaned QUEUED/RUNNING**: Redis restarted without persistence loses every queued and
  unacknowledged message. With a Redis broker the reaper reads the queue and the unacked
  hash; an active job older than ``reaper_orphan_grace_s`` that no message names (its id
  is the run_job task id and the first argument of every stage) is re-queued. The check
  is made twice, a second apart, so that a message moving from the queue to the unacked
  hash is not missed. Other brokers are not inspected (the SQLite broker of the embedded
  mode never loses a message, but has no redelivery after a crash either: a job whose
  worker died stays RUNNING until the stale rule applies).
- **PENDING**: the API committed the row but could not send the message
  (``worker.orchestration.queue.requeue_pending``).

Re-queueing is one conditional row update (``state`` and ``updated_at`` as read), then the
send: of several reapers (one per worker) exactly one wins a given job. The new delivery
starts a new attempt through ``state.mark_running``, which counts deliveries: a job that
has already been delivered ``max_deliveries`` times is FAILED here with the reason instead.

Every worker runs :func:`reap` when it is ready and then every ``reaper_interval_s``
(a daemon thread of the worker's main process, ``worker/orchestration/celery_app.py``). The thread
opens its own engine per sweep and disposes it, so no pooled connection is ever inherited
by a prefork child forked later.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

import redis
from sqlalchemy import select, update

from osdar_platform.db import make_engine, make_sessionmaker, updated_rows
from osdar_platform.models import Job, JobEvent, JobState, utcnow
from osdar_platform.settings import Settings
from worker.orchestration.celery_app import QUEUE, make_celery
from worker.orchestration.queue import TASK_RUN_JOB, requeue_pending
from worker.orchestration.state import POISON_REASON

log = logging.getLogger(__name__)

STALE_REASON = "worker lost: no progress for {s:.0f}s (time limit or killed worker)"
#: Most messages read from one Redis key per sweep (bounded work on a huge backlog).
MAX_SCAN = 100_000


@dataclass
class ReapReport:
    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    pending_sent: list[str] = field(default_factory=list)
    broker_checked: bool = False


def stale_after_s(settings: Settings) -> float:
    if settings.reaper_stale_after_s is not None:
        return float(settings.reaper_stale_after_s)
    return float(settings.task_time_limit_s + settings.visibility_margin_s)


# ---------------------------------------------------------------------------- broker
def _message_text(raw: bytes | str) -> str:
    """A kombu Redis message (or unacked [message, exchange, key]) as searchable text."""
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else raw
    parts = [text]
    try:
        obj = json.loads(text)
        msg = obj[0] if isinstance(obj, list) and obj else obj
        body = msg.get("body") if isinstance(msg, dict) else None
        if isinstance(body, str) and msg.get("properties", {}).get("body_encoding") == "base64":
            parts.append(base64.b64decode(body).decode("utf-8", "replace"))
    except (ValueError, TypeError, AttributeError):
        pass
    return "\n".join(parts)


def broker_messages_text(settings: Settings) -> str | None:
    """Every message of our queue and of the unacked hash as one text; None if unknown.

    Only the Redis transport is read (kombu's layout: the queue is a list named after
    it, priority sub-queues ``<queue>\\x06\\x16<n>``, unacked messages in hash ``unacked``).
    """
    url = str(settings.broker_url)
    if not url.startswith(("redis://", "rediss://")):
        return None

    client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5)
    try:
        chunks: list[str] = []
        keys = [QUEUE, *(k.decode() for k in client.scan_iter(match=f"{QUEUE}\x06\x16*"))]
        for key in keys:
            if client.type(key) == b"list":
                chunks.extend(_message_text(m) for m in client.lrange(key, 0, MAX_SCAN - 1))
        for _, raw in client.hscan_iter("unacked", count=1000):
            chunks.append(_message_text(raw))
        return "\n".join(chunks)
    finally:
        client.close()


# ---------------------------------------------------------------------------- reap
def _requeue(
    sessions: Any,
    app: Any,
    settings: Settings,
    job_id: str,
    seen_state: JobState,
    seen_updated: Any,
    why: str,
) -> str | None:
    """Claim the job (conditional update) and send it again; 'requeued'/'failed'/None."""

    now = utcnow()
    claim = [Job.id == job_id, Job.state == seen_state, Job.updated_at == seen_updated]
    with sessions.begin() as s:
        job = s.execute(select(Job.deliveries, Job.attempt).where(*claim)).one_or_none()
        if job is None:
            return None  # moved meanwhile (progress, or another reaper)
        if job.deliveries >= settings.max_deliveries:
            reason = f"{POISON_REASON}: {why}"
            moved = updated_rows(
                s,
                update(Job)
                .where(*claim)
                .values(state=JobState.FAILED, error=reason, finished_at=now, updated_at=now),
            )
            if moved:
                s.add(
                    JobEvent(
                        job_id=job_id,
                        kind="failed",
                        attempt=job.attempt,
                        message=reason,
                        data={"by": "reaper", "deliveries": job.deliveries},
                    )
                )
                return "failed"
            return None
        requeue = {"state": JobState.QUEUED, "stage": "requeued", "updated_at": now}
        moved = updated_rows(s, update(Job).where(*claim).values(**requeue))
        if not moved:
            return None
        s.add(
            JobEvent(
                job_id=job_id,
                kind="requeued",
                attempt=job.attempt,
                message=why,
                data={"by": "reaper", "deliveries": job.deliveries},
            )
        )
    try:
        app.send_task(TASK_RUN_JOB, args=[job_id], task_id=job_id)
    except Exception as exc:  # the row is QUEUED without a message: the next sweep sees it
        log.warning("reaper: re-queue of job %s could not be sent: %s", job_id, exc)
        return None
    log.warning("reaper: job %s re-queued (%s)", job_id, why)
    return "requeued"


def reap(settings: Settings, app: Any = None, *, sessions: Any = None) -> ReapReport:
    """One sweep (module docstring); safe to run in many processes at once."""

    if app is None:
        app = make_celery(settings)
    report = ReapReport()
    engine = None
    if sessions is None:
        kw = {} if settings.is_sqlite else {"pool_size": 1, "max_overflow": 2}
        engine = make_engine(str(settings.database_url), **kw)
        sessions = make_sessionmaker(engine)
    try:
        now = utcnow()
        stale_cut = now - timedelta(seconds=stale_after_s(settings))
        grace_cut = now - timedelta(seconds=settings.reaper_orphan_grace_s)
        with sessions() as s:
            rows = s.execute(
                select(Job.id, Job.state, Job.updated_at).where(
                    Job.state.in_([JobState.QUEUED, JobState.RUNNING]),
                    Job.updated_at < max(stale_cut, grace_cut),
                )
            ).all()
        texts: list[str] = []
        if rows:
            try:
                first = broker_messages_text(settings)
                if first is not None:
                    time.sleep(1.0)  # a message between the queue and the unacked hash
                    texts = [first, broker_messages_text(settings) or ""]
                    report.broker_checked = True
            except Exception as exc:  # broker down: only the stale rule decides now
                log.warning("reaper: broker not readable: %s", exc)
        for row in rows:
            stale = row.state == JobState.RUNNING and row.updated_at < stale_cut
            if report.broker_checked:
                if any(row.id in t for t in texts):
                    continue  # queued, or held by a worker (redelivered if that one died)
                why = "no broker message names the job (broker restarted, or task killed)"
            elif stale:
                why = STALE_REASON.format(s=stale_after_s(settings))
            else:
                continue
            out = _requeue(sessions, app, settings, row.id, row.state, row.updated_at, why)
            if out:
                getattr(report, out).append(row.id)
        report.pending_sent = requeue_pending(
            older_than_s=settings.reaper_orphan_grace_s, sessions=sessions, app=app
        )
    finally:
        if engine is not None:
            engine.dispose()
    if report.requeued or report.failed or report.pending_sent:
        log.warning("reaper: %s", report)
    return report


# ---------------------------------------------------------------------------- thread
class ReaperThread(threading.Thread):
    """Runs :func:`reap` now and every ``interval_s`` until :meth:`stop`."""

    def __init__(self, settings: Settings, app: Any, interval_s: float) -> None:
        super().__init__(name="osdar-ar-reaper", daemon=True)
        self.settings = settings
        self.app = app
        self.interval_s = interval_s
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                reap(self.settings, self.app)
            except Exception:
                log.exception("reaper sweep failed (next in %.0fs)", self.interval_s)
            self._halt.wait(self.interval_s)

    def stop(self) -> None:
        self._halt.set()


_thread: ReaperThread | None = None


def start_reaper(settings: Settings, app: Any) -> ReaperThread | None:
    """Start this process's reaper thread (once); None when disabled."""
    global _thread
    if settings.reaper_interval_s <= 0:
        return None
    if _thread is None or not _thread.is_alive():
        _thread = ReaperThread(settings, app, settings.reaper_interval_s)
        _thread.start()
    return _thread


def stop_reaper() -> None:
    global _thread
    if _thread is not None:
        _thread.stop()
        with contextlib.suppress(RuntimeError):
            _thread.join(5)
        _thread = None


__all__ = [
    "ReapReport",
    "ReaperThread",
    "broker_messages_text",
    "reap",
    "stale_after_s",
    "start_reaper",
    "stop_reaper",
]
