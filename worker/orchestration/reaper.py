"""The reaper: jobs that no worker will ever finish are re-queued (or FAILED), never lost.

It decides from the database alone (a lease per running stage, ``lease.py``) and from a
sentinel key of its own in the broker's Redis database, never from the broker's internal
layout (kombu's queue lists and unacked hash). Celery's at-least-once delivery covers a pool
process that dies mid-task while its worker lives (``task_reject_on_worker_lost`` puts the
message back at once, the stage runs again and takes its lease over). Four cases are left,
and each leaves a job active with nothing working on it. An active job is in one of two
places: **held** (worker processes run its stages and renew their leases) or **in the
broker** (QUEUED, or RUNNING between two stages: no lease of its attempt; when it was last
handed to the broker is ``jobs.broker_seen_at``).

- **lease expired**: a RUNNING job with an expired lease of its current attempt. Its
  holder stopped renewing while it held the stage's message: the worker was killed with
  its children (an OOM kill of a container), its host died, its database connection did
  not come back within ``lease_ttl_s``, or the stage ended while the database was away
  (its release failed). The message may come back after the broker's visibility timeout
  (hours by default): the re-queue does not wait for it. A new attempt starts; sibling
  chunks still running stop at their next check, and late deliveries of the old attempt
  are refused by the attempt check.
- **broker lost its data**: Redis restarted without persistence (or flushed, or failed
  over to an empty replica) loses every queued and unacknowledged message. The reaper
  keeps a sentinel key in the broker's database (``osdar_ar:broker_epoch``: a random token
  and the time it was written, ``SET NX`` so all reapers agree). Whatever removes the
  messages removes the sentinel too: a reaper that finds it gone writes a new one, and
  the broker's data is known intact only since then. A job in the broker whose message
  was handed to it (QUEUED: ``updated_at``; RUNNING: ``broker_seen_at``) before the
  sentinel was written, plus ``broker_restart_margin_s`` for the hosts' clocks and the
  time between a send and its timestamp, is re-queued, unless the reaper itself sent it
  under this sentinel (``jobs.broker_run_id`` holds its token; that stamp stops a job
  re-sent just after the loss from being re-sent again). A persistent Redis keeps the
  sentinel with the messages: nothing is re-sent. Running stages are cancelled by Celery
  when the connection drops (``worker_cancel_long_running_tasks_on_connection_loss``) and
  release their leases without a hand-off, so their jobs fall under this rule at once.
  Other brokers are not checked (the SQLite broker of the embedded mode never loses a
  message).
- **stale RUNNING** (brokers other than Redis): no row update (``updated_at``: every
  stage, sub-stage and frame writes it) for longer than the hard time limit plus a margin
  and no lease. The SQLite broker of the embedded mode never gives a message back: a
  worker that died holding one it had not started (no lease yet) leaves the job there.
  With Redis the rule does not apply: such a message comes back after the visibility
  timeout, and a RUNNING job between stages may wait behind a backlog as long as it must
  (the rule re-queued those on a loaded machine). A task stopped at the hard time limit
  is not a case of its own any more: its process is killed and its lease expires.
- **PENDING**: the API committed the row but could not send the message
  (``worker.orchestration.queue.requeue_pending``).
- **finish lost**: a RUNNING job whose attempt's chunks are all done (``chunk_join.py``)
  but whose ``finish`` has not started, with no lease and no row update for
  ``reaper_orphan_grace_s``: the chunk that completed the last one died before it claimed
  the finish or before its send reached the broker. No new attempt: a new finish token is
  claimed (one conditional update, the row as read) and ``finish`` is sent again; the
  first message, if it still comes, carries the old token and is refused.

Campaigns: a campaign's variants are jobs like any other, re-queued by the rules above;
a re-queued variant's new attempt ends in its publish (or failure), which finalizes the
campaign once every variant has finished. What no job rule covers is a lost campaign
message or trigger: an expansion whose worker died, a finalize never sent (the variant's
worker killed between its publish and the finalize, a variant FAILED here as poison, a
finalize that raised). Every sweep gives each campaign not ended
:func:`~worker.orchestration.queue.nudge_campaign` (what an API read of the campaign
does), so a campaign nobody reads still ends.

A stage that cannot reach the database does not fail the job: its message goes back to
the broker (``tasks.py``), and its lease, if it had one, expires or is taken over by the
stage's next delivery. A reaper whose own sweep failed (the database away) does not
expire leases for ``lease_ttl_s`` after it is back: the holders need one renewal to show
they lived through the outage.

Re-queueing is one conditional row update (``state`` and ``updated_at`` as read, and for
the lease rule an expired lease still there to delete, in one transaction), then the
send: of several reapers (one per worker) exactly one wins a given job; a stage that
started (it moves ``updated_at``) or a lease renewed in the meantime makes the claim roll
back. A send that fails moves the job back to PENDING
(``requeue_pending`` sends it later). The new delivery starts a new attempt through
``state.mark_running``, which counts deliveries: a job already delivered
``max_deliveries`` times is FAILED here with the reason instead. Duplicate messages (a
job handed to the broker between the loss and the new sentinel is sent again) are
harmless: the attempt check stops the older attempt, store keys are attempt-scoped, one conditional
update publishes, and the winner removes every other attempt's objects.

Every worker runs :func:`reap` when it is ready and then every ``reaper_interval_s``
(a daemon thread of the worker's main process, ``lifecycle.py``). The thread opens its own
engine per sweep and disposes it, so no pooled connection is ever inherited by a prefork
child forked later.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, delete, or_, select, update

from osdar_platform.db import make_engine, make_sessionmaker, updated_rows
from osdar_platform.models import (
    TERMINAL_STATES,
    Campaign,
    CampaignState,
    Job,
    JobEvent,
    JobLease,
    JobState,
    utcnow,
)
from osdar_platform.settings import Settings
from worker.orchestration import chunk_join
from worker.orchestration.broker_sentinel import (
    SENTINEL_KEY,
    BrokerEpoch,
    is_redis_url,
    sentinel_epoch,
)
from worker.orchestration.celery_app import make_celery
from worker.orchestration.queue import (
    TASK_EXPAND_CAMPAIGN,
    TASK_FINALIZE_CAMPAIGN,
    TASK_RUN_JOB,
    nudge_campaign,
    requeue_pending,
)
from worker.orchestration.state import POISON_REASON

log = logging.getLogger(__name__)

#: The campaigns a sweep looks at: those a lost message or trigger can leave stuck.
ACTIVE_CAMPAIGN_STATES = [CampaignState.PENDING, CampaignState.EXPANDING, CampaignState.RUNNING]

STALE_REASON = "worker lost: no progress for {s:.0f}s (time limit or killed worker)"
LEASE_REASON = "lease expired: {stage} held by {holder}, {ago:.0f}s ago (worker lost)"
BROKER_REASON = (
    "broker lost its data: its sentinel {token} written at {since}, the job's message "
    "handed to it at {sent}"
)
#: The reaper's own key in the broker's Redis database (module docstring).


@dataclass
class ReapReport:
    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    pending_sent: list[str] = field(default_factory=list)
    #: jobs whose lost ``finish`` was sent again (chunk_join.py)
    finish_resent: list[str] = field(default_factory=list)
    #: campaigns whose expansion or finalize was sent again (nudge_campaign)
    campaigns_nudged: list[str] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)
    broker: BrokerEpoch | None = None


def stale_after_s(settings: Settings) -> float:
    if settings.reaper_stale_after_s is not None:
        return float(settings.reaper_stale_after_s)
    return float(settings.task_time_limit_s + settings.visibility_margin_s)


# ---------------------------------------------------------------------------- broker
def _is_redis(settings: Settings) -> bool:
    return is_redis_url(str(settings.broker_url))


def broker_epoch(settings: Settings) -> BrokerEpoch | None:
    """The sentinel of the Redis broker (written now if it is gone); None for other
    brokers. Raises if Redis is not reachable or the sentinel is not ours."""
    return sentinel_epoch(str(settings.broker_url))


# ---------------------------------------------------------------------------- decide
@dataclass(frozen=True)
class LeaseView:
    stage: str
    holder: str
    renewed_at: datetime
    expires_at: datetime


@dataclass(frozen=True)
class JobView:
    """What the reaper reads of one active job (its current attempt's leases)."""

    id: str
    state: JobState
    updated_at: datetime
    broker_seen_at: datetime | None = None
    broker_run_id: str | None = None
    leases: tuple[LeaseView, ...] = ()
    attempt: int = 0
    #: every chunk of the attempt done and its finish not started (chunk_join.py)
    joined: bool = False


def decide(
    job: JobView,
    now: datetime,
    epoch: BrokerEpoch | None,
    settings: Settings,
    *,
    expire_leases: bool = True,
    stale_rule: bool = False,
) -> str | None:
    """Why ``job`` must be re-queued (module docstring), or None to leave it alone.

    ``expire_leases``: False right after the reaper's own database outage;
    ``stale_rule``: the broker is not Redis (see the module docstring).
    """
    running = job.state == JobState.RUNNING
    expired = [lease for lease in job.leases if lease.expires_at <= now]
    if running and expired:  # a holder died with the stage's message in its hands
        if not expire_leases:
            return None
        last = max(expired, key=lambda lease: lease.expires_at)
        ago = (now - last.expires_at).total_seconds()
        return LEASE_REASON.format(stage=last.stage, holder=last.holder, ago=ago)
    if running and job.leases:
        return None  # held: its holders renew their leases
    # in the broker (a QUEUED job's message is there, whatever a stale delivery holds)
    seen = job.broker_seen_at
    if epoch is not None and job.broker_run_id != epoch.token:
        sent = job.updated_at if not running else (seen or job.updated_at)
        margin = timedelta(seconds=settings.broker_restart_margin_s)
        if sent < epoch.since + margin:
            return BROKER_REASON.format(
                token=epoch.token[:8],
                since=epoch.since.isoformat(timespec="seconds"),
                sent=sent.isoformat(timespec="seconds"),
            )
    stale_cut = now - timedelta(seconds=stale_after_s(settings))
    if stale_rule and running and job.updated_at < stale_cut:
        return STALE_REASON.format(s=stale_after_s(settings))
    return None


def finish_lost(job: JobView, now: datetime, settings: Settings) -> bool:
    """Whether ``job`` waits for a ``finish`` that nobody will run (module docstring)."""
    quiet = now - timedelta(seconds=settings.reaper_orphan_grace_s)
    running = job.state == JobState.RUNNING
    return running and job.joined and not job.leases and job.updated_at < quiet


# ---------------------------------------------------------------------------- reap
def _claim(
    s: Any,
    job_id: str,
    seen_state: JobState,
    seen_updated: Any,
    now: datetime,
    expected_expired: bool,
) -> Any:
    """Lock the job for a re-queue: its row as read, its expired leases deleted (at least
    one if ``expected_expired``: the lease rule).

    Returns ``(deliveries, attempt)`` or None if the job moved (progress, a stage started,
    a renewal, or another reaper), in which case the caller's transaction must be rolled
    back.
    """
    claim = [Job.id == job_id, Job.state == seen_state, Job.updated_at == seen_updated]
    # touch the row first: on PostgreSQL this locks it, so that two reapers serialize here
    locked = updated_rows(s, update(Job).where(*claim).values(updated_at=seen_updated))
    if not locked:
        return None
    gone = s.execute(delete(JobLease).where(JobLease.job_id == job_id, JobLease.expires_at <= now))
    if expected_expired and not gone.rowcount:
        return None  # renewed meanwhile: its holder lives (a stage start moves updated_at)
    return s.execute(select(Job.deliveries, Job.attempt).where(Job.id == job_id)).one()


def _requeue(
    sessions: Any,
    app: Any,
    settings: Settings,
    job: JobView,
    why: str,
    epoch: BrokerEpoch | None,
) -> str | None:
    """Claim the job (conditional update) and send it again; 'requeued'/'failed'/None."""

    now = utcnow()
    job_id = job.id
    with sessions() as s, s.begin():
        lease_rule = job.state == JobState.RUNNING and bool(job.leases)
        row = _claim(s, job_id, job.state, job.updated_at, now, lease_rule)
        if row is None:
            s.rollback()
            return None
        if row.deliveries >= settings.max_deliveries:
            reason = f"{POISON_REASON}: {why}"
            s.execute(
                update(Job)
                .where(Job.id == job_id)
                .values(state=JobState.FAILED, error=reason, finished_at=now, updated_at=now)
            )
            data = {"by": "reaper", "deliveries": row.deliveries}
            s.add(JobEvent(job_id=job_id, kind="failed", attempt=row.attempt, message=reason,
                           data=data))  # fmt: skip
            return "failed"
        s.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(state=JobState.QUEUED, stage="requeued", updated_at=now, broker_run_id=None)
        )
        data = {"by": "reaper", "deliveries": row.deliveries}
        s.add(JobEvent(job_id=job_id, kind="requeued", attempt=row.attempt, message=why,
                       data=data))  # fmt: skip
    try:
        app.send_task(TASK_RUN_JOB, args=[job_id], task_id=job_id)
    except Exception as exc:  # PENDING again: requeue_pending sends it once the broker is back
        log.warning("reaper: re-queue of job %s could not be sent: %s", job_id, exc)
        with sessions.begin() as s:
            back = updated_rows(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state == JobState.QUEUED, Job.updated_at == now)
                .values(state=JobState.PENDING),
            )
            if back:
                s.add(JobEvent(job_id=job_id, kind="enqueue_failed", message=str(exc)[:2000]))
        return None
    if epoch is not None:  # sent under this sentinel: not "sent before it" next sweep
        with sessions.begin() as s:
            s.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == JobState.QUEUED, Job.updated_at == now)
                .values(broker_run_id=epoch.token, updated_at=now)
            )
    log.warning("reaper: job %s re-queued (%s)", job_id, why)
    return "requeued"


def _resend_finish(sessions: Any, app: Any, job: JobView) -> bool:
    """Claim a new finish token for ``job`` (its row as read) and send ``finish``."""
    with sessions() as s, s.begin():
        token = chunk_join.claim_in(s, job.id, job.attempt, resend=True,
                                    seen_updated=job.updated_at)  # fmt: skip
    if token is None:
        return False
    try:
        chunk_join.send_finish(app, job.id, job.attempt, token)
    except Exception as exc:  # the row moved: the next sweep after the grace tries again
        log.warning("reaper: finish of job %s could not be sent: %s", job.id, exc)
        return False
    log.warning("reaper: job %s: its chunks were done, finish sent again", job.id)
    return True


def _stamp(sessions: Any, ids: list[str], epoch: BrokerEpoch) -> None:
    """Jobs just sent (QUEUED) were sent under this sentinel: not "before it" next sweep."""
    with sessions.begin() as s:
        s.execute(
            update(Job)
            .where(Job.id.in_(ids), Job.state == JobState.QUEUED, Job.broker_run_id.is_(None))
            .values(broker_run_id=epoch.token, updated_at=Job.updated_at)
        )


def _active_jobs(s: Any, now: datetime, epoch: BrokerEpoch | None, settings: Settings) -> Any:
    """The jobs a rule could apply to: every RUNNING one; QUEUED ones only when handed to
    the broker before its sentinel was written (and not re-sent under it by a reaper)."""
    where = [Job.state == JobState.RUNNING]
    if epoch is not None:
        cut = epoch.since + timedelta(seconds=settings.broker_restart_margin_s)
        not_ours = or_(Job.broker_run_id.is_(None), Job.broker_run_id != epoch.token)
        where.append(and_(Job.state == JobState.QUEUED, Job.updated_at < cut, not_ours))
    rows = s.execute(
        select(
            Job.id, Job.state, Job.attempt, Job.updated_at, Job.broker_seen_at, Job.broker_run_id,
            Job.chunks_total, Job.chunks_done, Job.finish_started_at,
        ).where(or_(*where))
    ).all()  # fmt: skip
    leases: dict[str, list[LeaseView]] = {}
    attempts = {r.id: r.attempt for r in rows}
    if attempts:
        for lease in s.scalars(select(JobLease).where(JobLease.job_id.in_(list(attempts)))):
            if lease.attempt == attempts[lease.job_id]:
                view = LeaseView(lease.stage, lease.holder, lease.renewed_at, lease.expires_at)
                leases.setdefault(lease.job_id, []).append(view)
    return [
        JobView(
            r.id,
            JobState(r.state),
            r.updated_at,
            r.broker_seen_at,
            r.broker_run_id,
            tuple(leases.get(r.id, ())),
            r.attempt,
            r.finish_started_at is None and chunk_join.joined_at(r.chunks_total, r.chunks_done),
        )
        for r in rows
    ]


def reap(
    settings: Settings,
    app: Any = None,
    *,
    sessions: Any = None,
    expire_leases: bool = True,
) -> ReapReport:
    """One sweep (module docstring); safe to run in many processes at once."""

    if app is None:
        app = make_celery(settings)
    report = ReapReport()
    try:
        report.broker = broker_epoch(settings)
    except Exception as exc:  # broker down: the lease rule still applies
        log.warning("reaper: broker sentinel not readable: %s", exc)
    engine = None
    if sessions is None:
        kw = {} if settings.is_sqlite else {"pool_size": 1, "max_overflow": 2}
        engine = make_engine(str(settings.database_url), **kw)
        sessions = make_sessionmaker(engine)
    try:
        now = utcnow()
        with sessions.begin() as s:
            terminal = select(Job.id).where(Job.state.in_(list(TERMINAL_STATES)))
            s.execute(delete(JobLease).where(JobLease.job_id.in_(terminal)))
            jobs = _active_jobs(s, now, report.broker, settings)
        stale_rule = not _is_redis(settings)
        for job in jobs:
            why = decide(job, now, report.broker, settings, expire_leases=expire_leases,
                         stale_rule=stale_rule)  # fmt: skip
            if why is None:
                if finish_lost(job, now, settings) and _resend_finish(sessions, app, job):
                    report.finish_resent.append(job.id)
                continue
            out = _requeue(sessions, app, settings, job, why, report.broker)
            if out:
                getattr(report, out).append(job.id)
                report.reasons[job.id] = why
        report.pending_sent = requeue_pending(
            older_than_s=settings.reaper_orphan_grace_s, sessions=sessions, app=app
        )
        if report.pending_sent and report.broker is not None:
            _stamp(sessions, report.pending_sent, report.broker)
        report.campaigns_nudged = _nudge_campaigns(sessions, app, settings)
    finally:
        if engine is not None:
            engine.dispose()
    acted = report.requeued or report.failed or report.pending_sent or report.finish_resent
    if acted or report.campaigns_nudged:
        log.warning("reaper: %s", report)
    return report


def _nudge_campaigns(sessions: Any, app: Any, settings: Settings) -> list[str]:
    """Every campaign not ended gets :func:`nudge_campaign`: a RUNNING one whose variant
    jobs have all finished is finalized even when no variant's own trigger did it (a
    variant FAILED by this sweep, a worker killed between a publish and its finalize) and
    nobody reads the campaign. Returns the campaigns a task was sent for."""
    sent: list[str] = []

    def sender(task: str) -> Any:
        def send(campaign_id: str) -> None:
            app.send_task(task, args=[campaign_id])
            sent.append(campaign_id)

        return send

    with sessions() as s:
        active = s.scalars(select(Campaign).where(Campaign.state.in_(ACTIVE_CAMPAIGN_STATES)))
        for c in list(active):
            nudge_campaign(session=s, campaign=c, settings=settings,
                           send_expand=sender(TASK_EXPAND_CAMPAIGN),
                           send_finalize=sender(TASK_FINALIZE_CAMPAIGN))  # fmt: skip
    return sent


# ---------------------------------------------------------------------------- thread
class ReaperThread(threading.Thread):
    """Runs :func:`reap` now and every ``interval_s`` until :meth:`stop`.

    After a sweep that failed (the database away), leases are not expired for
    ``lease_ttl_s``: their holders renew them once the database is back.
    """

    def __init__(self, settings: Settings, app: Any, interval_s: float) -> None:
        super().__init__(name="osdar-ar-reaper", daemon=True)
        self.settings = settings
        self.app = app
        self.interval_s = interval_s
        self._halt = threading.Event()
        self._expire_from = 0.0  # time.monotonic() from which leases may be expired

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                expire = time.monotonic() >= self._expire_from
                report = reap(self.settings, self.app, expire_leases=expire)
                if report.broker is not None and report.broker.written:
                    log.warning(
                        "reaper: the broker's sentinel was gone (Redis restarted without "
                        "persistence, flushed or evicted, or first run): jobs handed to it "
                        "before %s are sent again", report.broker.since.isoformat(),
                    )  # fmt: skip
            except Exception:
                self._expire_from = time.monotonic() + self.settings.lease_ttl_s
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
    "SENTINEL_KEY",
    "BrokerEpoch",
    "JobView",
    "LeaseView",
    "ReapReport",
    "ReaperThread",
    "broker_epoch",
    "decide",
    "finish_lost",
    "reap",
    "stale_after_s",
    "start_reaper",
    "stop_reaper",
]
