"""Handing jobs to the workers, and asking them to stop.

The contract with the Celery side (``worker/orchestration/celery_app.py``, ``tasks.py``): the API
commits the new job row (PENDING), then calls :func:`enqueue_job`, which sends task
``TASK_RUN_JOB`` with the job id (the task id is the job id, so it can be revoked) and
moves the row PENDING -> QUEUED. The state change is conditional: a worker that already
picked the job up (RUNNING) is never set back to QUEUED. A job whose send failed stays
PENDING with an event saying why; :func:`requeue_pending` sends those again.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, Any

from sqlalchemy import func, or_, select, update

from osdar_platform.db import get_sessionmaker, updated_rows
from osdar_platform.models import (
    TERMINAL_STATES,
    Campaign,
    CampaignState,
    Job,
    JobEvent,
    JobState,
    utcnow,
)
from worker.orchestration.broker_sentinel import sentinel_epoch

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from osdar_platform.settings import Settings

log = logging.getLogger(__name__)

#: The Celery task that runs a job (a plain function in worker/orchestration/runner.py).
TASK_RUN_JOB = "osdar_ar.run_job"
#: The campaign tasks (plain functions in worker/campaign/service_expand.py and
#: service_finalize.py): the expansion into variant jobs, and the manifest at the end.
TASK_EXPAND_CAMPAIGN = "osdar_ar.campaign_expand"
TASK_FINALIZE_CAMPAIGN = "osdar_ar.campaign_finalize"
#: The stages of a job after ``run_job`` (worker/orchestration/tasks.py).
TASK_FETCH = "osdar_ar.fetch"
TASK_PREPARE = "osdar_ar.prepare"
TASK_AUGMENT_CHUNK = "osdar_ar.augment_chunk"
TASK_FINISH = "osdar_ar.finish"
TASK_EVALUATE = "osdar_ar.evaluate"
TASK_PACKAGE = "osdar_ar.package"
TASK_PUBLISH = "osdar_ar.publish"
#: A campaign finalize asked for and not done within this long is asked for again.
FINALIZE_RETRY_S = 30.0
#: Broker priorities of a job's first message (``run_job``). On Redis a lower number is
#: served first, and every later stage of a job (and a job the reaper re-queues) is sent
#: with the default, 0: a worker finishes the jobs it started before it starts new ones.
#: Without this a campaign's 24 variants ran stage by stage in lockstep (every run_job,
#: then every fetch, ...), each variant taking the whole campaign's time and all of them
#: holding their scratch files at once (scripts/bench_campaign_throughput.py). A direct
#: job starts before campaign variants queued earlier. Kombu's Redis transport serves the
#: steps 0, 3, 6 and 9; other brokers ignore priorities (first in, first out).
PRIORITY_JOB = 3
PRIORITY_CAMPAIGN_VARIANT = 6


def _celery_app(app: Any) -> Any:
    if app is not None:
        return app
    # Celery is the workers' side: the API imports this module at start, and Celery there
    # cost +45 ms and +6.8 MiB max RSS over `import service.app` (0.65 s, 90 MiB), median of 7.
    from worker.orchestration.celery_app import celery_app  # lazy: Celery, +45 ms +6.8 MiB

    return celery_app


def _sessions(
    settings: Settings | None, sessions: sessionmaker[Session] | None
) -> sessionmaker[Session]:
    if sessions is not None:
        return sessions

    return get_sessionmaker(settings)


def enqueue_job(
    job_id: str,
    *,
    settings: Settings | None = None,
    sessions: sessionmaker[Session] | None = None,
    app: Any = None,
) -> None:
    """Send the job to the workers and mark it QUEUED (call after the row's commit).

    Raises whatever the broker raised when the message could not be sent; the job then
    stays PENDING with an ``enqueue_failed`` event.
    """
    make_session = _sessions(settings, sessions)
    celery = _celery_app(app)
    conf = getattr(celery, "conf", None)  # a dispatcher's stand-in may have none
    token = _sentinel_token(str(getattr(conf, "broker_url", None) or ""))
    with make_session() as session:
        variant = session.scalar(select(Job.campaign_id).where(Job.id == job_id)) is not None
    priority = PRIORITY_CAMPAIGN_VARIANT if variant else PRIORITY_JOB
    try:
        celery.send_task(TASK_RUN_JOB, args=[job_id], task_id=job_id, priority=priority)
    except Exception as exc:
        log.warning("job %s: enqueue failed: %s", job_id, exc)
        with make_session.begin() as session:
            session.add(JobEvent(job_id=job_id, kind="enqueue_failed", message=str(exc)[:2000]))
        raise
    with make_session.begin() as session:
        moved = updated_rows(
            session,
            update(Job)
            .where(Job.id == job_id, Job.state == JobState.PENDING)
            .values(state=JobState.QUEUED, updated_at=utcnow(), broker_run_id=token),
        )
        session.add(JobEvent(job_id=job_id, kind="queued" if moved else "sent"))


def _sentinel_token(broker_url: str) -> str | None:
    """The Redis broker's sentinel token the message is handed under (written if it is
    gone: a first run), so that the reaper re-sends it only if that sentinel vanishes
    (:mod:`worker.orchestration.broker_sentinel`); None for other brokers or when it
    cannot be read (the reaper's time rule then applies)."""
    try:
        epoch = sentinel_epoch(broker_url)
    except Exception as exc:  # the send below says whether the broker is there
        log.debug("broker sentinel not read before a send: %s", exc)
        return None
    return None if epoch is None else epoch.token


def request_cancel(
    job_id: str,
    *,
    settings: Settings | None = None,
    sessions: sessionmaker[Session] | None = None,
    app: Any = None,
    revoke: bool = True,
) -> JobState | None:
    """Ask a job to stop; returns its state afterwards (None if there is no such job).

    PENDING/QUEUED jobs become CANCELLED at once (conditionally: a worker that starts it
    meanwhile sees ``cancel_requested`` and stops at its next check). RUNNING jobs get
    ``cancel_requested``; the worker stops at its next stage or frame and writes
    CANCELLED. The broker message is revoked too (best effort).
    """
    make_session = _sessions(settings, sessions)
    now = utcnow()
    with make_session.begin() as session:
        job = session.get(Job, job_id)
        if job is None:
            return None
        if job.state.terminal:
            return job.state
        session.execute(
            update(Job).where(Job.id == job_id).values(cancel_requested=True, updated_at=now)
        )
        moved = updated_rows(
            session,
            update(Job)
            .where(Job.id == job_id, Job.state.in_([JobState.PENDING, JobState.QUEUED]))
            .values(state=JobState.CANCELLED, finished_at=now, updated_at=now),
        )
        session.add(
            JobEvent(
                job_id=job_id,
                kind="cancelled" if moved else "cancel_requested",
                attempt=job.attempt,
            )
        )
    if revoke:
        try:
            _celery_app(app).control.revoke(job_id)
        except Exception as exc:  # the DB flag is what the worker obeys
            log.warning("job %s: revoke failed (the cancel flag stands): %s", job_id, exc)
    with make_session() as session:
        state = session.scalar(select(Job.state).where(Job.id == job_id))
    return state


def send_task(name: str, args: list[Any], *, task_id: str | None = None, app: Any = None) -> None:
    """Send one task by name (the campaign tasks; raises what the broker raised)."""
    _celery_app(app).send_task(name, args=args, task_id=task_id)


def broker_overview(*, app: Any = None, timeout_s: float = 1.0) -> dict[str, Any]:
    """What an operator sees of the workers: the names of those answering a ping within
    ``timeout_s`` (None: the broker could not be asked) and the messages waiting in the
    job queue (None: unknown); ``error`` says what could not be read."""
    celery = _celery_app(app)
    out: dict[str, Any] = {"workers": None, "queue_messages": None, "error": None}
    try:
        replies = celery.control.ping(timeout=timeout_s) or []
        out["workers"] = sorted(str(name) for reply in replies for name in reply)
    except Exception as exc:  # a broker without remote control, or down
        out["error"] = f"ping: {exc}"[:300]
    try:
        with celery.connection_for_read() as conn:
            q = conn.default_channel.queue_declare(
                queue=celery.conf.task_default_queue, passive=True
            )
            out["queue_messages"] = int(q.message_count)
    except Exception as exc:
        out["error"] = (out["error"] or "") + f" queue: {exc}"[:300]
    return out


def requeue_pending(
    *,
    older_than_s: float = 60.0,
    settings: Settings | None = None,
    sessions: sessionmaker[Session] | None = None,
    app: Any = None,
) -> list[str]:
    """Send again the jobs left PENDING (their first send failed); returns their ids."""
    make_session = _sessions(settings, sessions)
    cutoff = utcnow() - timedelta(seconds=older_than_s)
    with make_session() as session:
        ids = list(
            session.scalars(
                select(Job.id).where(Job.state == JobState.PENDING, Job.created_at < cutoff)
            )
        )
    sent = []
    for job_id in ids:
        try:
            enqueue_job(job_id, sessions=make_session, app=app)
            sent.append(job_id)
        except Exception as exc:
            log.warning("requeue of %s failed: %s", job_id, exc)
    return sent


def _claim_resend(
    session: Session, campaign_id: str, state: CampaignState, cut: datetime, now: datetime
) -> bool:
    """Claim the re-send of a campaign left in ``state`` since before ``cut``: one
    conditional row update (its ``updated_at`` to ``now``), committed; True for the one
    caller that made it."""
    if updated_rows(session, update(Campaign).where(
            Campaign.id == campaign_id, Campaign.state == state,
            Campaign.updated_at < cut).values(updated_at=now)):  # fmt: skip
        session.commit()
        return True
    return False


def nudge_campaign(
    *,
    session: Session,
    campaign: Campaign,
    settings: Settings,
    send_expand: Callable[[str], None],
    send_finalize: Callable[[str], None],
) -> None:
    """Send again what a lost message or a missed trigger left undone for one campaign:
    its expansion when it was left PENDING past ``reaper_orphan_grace_s`` or EXPANDING
    without a heartbeat for longer than a task may run (its worker died with the message
    unacknowledged), its finalize when every variant job has finished but the campaign is
    still RUNNING (the variant's own trigger lost: its worker killed after the publish, a
    variant FAILED by the reaper, a finalize that raised), again after
    :data:`FINALIZE_RETRY_S` if that one is lost too. Each send is claimed by one
    conditional row update, so concurrent callers (API reads, reapers) send once.

    Called on every API read of the campaign (service/services/campaigns.py) and by every
    reaper sweep (reaper.py) for every campaign not ended."""
    now = utcnow()
    c = campaign
    try:
        if c.state == CampaignState.PENDING:
            cut = now - timedelta(seconds=settings.reaper_orphan_grace_s)
            if _claim_resend(session, c.id, CampaignState.PENDING, cut, now):
                send_expand(c.id)
        elif c.state == CampaignState.EXPANDING:
            # the expansion beats its heart (stage, updated_at) as it prepares; silent for
            # longer than any task may run, its worker died with the message unacknowledged
            stale = settings.reaper_stale_after_s or (
                settings.task_time_limit_s + settings.visibility_margin_s
            )
            cut = now - timedelta(seconds=stale)
            if _claim_resend(session, c.id, CampaignState.EXPANDING, cut, now):
                send_expand(c.id)
        elif c.state == CampaignState.RUNNING:
            unfinished = session.scalar(
                select(func.count()).select_from(Job).where(
                    Job.campaign_id == c.id, Job.state.not_in(list(TERMINAL_STATES)))
            )  # fmt: skip
            if unfinished:
                return
            cut = now - timedelta(seconds=FINALIZE_RETRY_S)
            claim = update(Campaign).where(
                Campaign.id == c.id, Campaign.state == CampaignState.RUNNING,
                or_(Campaign.stage.is_(None), Campaign.stage != "finalize",
                    Campaign.updated_at < cut),
            ).values(stage="finalize", updated_at=now)  # fmt: skip
            if updated_rows(session, claim):
                session.commit()
                send_finalize(c.id)
    except Exception as exc:  # the next read tries again
        session.rollback()
        log.warning("campaign %s: nudge failed: %s", c.id, exc)
    session.refresh(c)


__all__ = [
    "FINALIZE_RETRY_S",
    "PRIORITY_CAMPAIGN_VARIANT",
    "PRIORITY_JOB",
    "TASK_AUGMENT_CHUNK",
    "TASK_EVALUATE",
    "TASK_EXPAND_CAMPAIGN",
    "TASK_FETCH",
    "TASK_FINALIZE_CAMPAIGN",
    "TASK_FINISH",
    "TASK_PACKAGE",
    "TASK_PREPARE",
    "TASK_PUBLISH",
    "TASK_RUN_JOB",
    "broker_overview",
    "enqueue_job",
    "nudge_campaign",
    "request_cancel",
    "requeue_pending",
    "send_task",
]
