"""The reaper's decisions (worker/orchestration/reaper.py): the rules on their own, then
sweeps over real PostgreSQL and SQLite rows, with the broker's identity read from this
machine's Redis (``INFO server``), and several reapers racing for the same jobs."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from dataclasses import replace
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select, update

from osdar_platform.db import get_sessionmaker, session_scope
from osdar_platform.migrate import upgrade
from osdar_platform.models import ApiKey, Job, JobEvent, JobLease, JobState, utcnow
from osdar_platform.settings import Settings
from scripts.reliability import common
from tests.conftest_service import make_pg_schema, memory_celery, sent_tasks
from worker.orchestration import lease
from worker.orchestration.reaper import (
    SENTINEL_KEY,
    BrokerEpoch,
    JobView,
    LeaseView,
    _requeue,
    broker_epoch,
    decide,
    reap,
)

NOW = datetime(2026, 11, 25, 12, 0, 0).astimezone()
S = timedelta(seconds=1)


def _settings(tmp_path: Path, **kw: Any) -> Settings:
    values: dict[str, Any] = {"lease_ttl_s": 9, "lease_renew_s": 3, "broker_restart_margin_s": 2}
    values.update(kw)
    return Settings(data_dir=tmp_path, **values)


# ---------------------------------------------------------------------------- rules
def _lease(renewed: datetime, ttl: float = 9) -> LeaseView:
    return LeaseView("augment[0]", "host:42", renewed, renewed + ttl * S)


def test_decide_lease_rules(tmp_path: Path) -> None:
    st = _settings(tmp_path)
    seen = NOW - 60 * S
    running = JobView("j", JobState.RUNNING, NOW - 5 * S, broker_seen_at=seen)
    # live leases: held, whatever the broker says
    live = replace(running, leases=(_lease(NOW - 2 * S), _lease(NOW)))
    assert decide(live, NOW, BrokerEpoch("r", NOW), st) is None
    # a lease expired: its holder died holding the stage's message
    dead = replace(running, leases=(_lease(NOW - 12 * S),))
    why = decide(dead, NOW, None, st)
    assert why is not None and why.startswith("lease expired: augment[0] held by host:42, 3s ago")
    # ... even beside a sibling chunk still running (its message would wait for the
    # visibility timeout otherwise), and even if a sibling handed the job off since
    assert decide(replace(dead, leases=(_lease(NOW - 12 * S), _lease(NOW))), NOW, None, st)
    assert decide(replace(dead, broker_seen_at=NOW - S), NOW, None, st) is not None
    # ... but not while the reaper itself just came back from a database outage
    assert decide(dead, NOW, None, st, expire_leases=False) is None
    # a QUEUED job's message is in the broker: a stale delivery's lease is not a holder
    queued = JobView("q", JobState.QUEUED, NOW - 5 * S, leases=(_lease(NOW - 12 * S),))
    assert decide(queued, NOW, None, st) is None
    assert decide(replace(queued, updated_at=NOW - 40 * S), NOW, BrokerEpoch("r", NOW - 30 * S),
                  st) is not None  # fmt: skip


def test_decide_broker_restart_rules(tmp_path: Path) -> None:
    st = _settings(tmp_path)
    epoch = BrokerEpoch("run-2", NOW - 30 * S)  # Redis started 30 s ago
    queued_before = JobView("q", JobState.QUEUED, NOW - 31 * S)
    why = decide(queued_before, NOW, epoch, st)
    assert why is not None and why.startswith("broker lost its data: its sentinel run-2")
    # within the margin after the start: it may have been sent to the old Redis
    assert decide(JobView("q", JobState.QUEUED, NOW - 29 * S), NOW, epoch, st) is not None
    assert decide(JobView("q", JobState.QUEUED, NOW - 27 * S), NOW, epoch, st) is None
    # the reaper sent it to this Redis itself (stamp): never sent again for this run_id
    stamped = JobView("q", JobState.QUEUED, NOW - 29 * S, broker_run_id="run-2")
    assert decide(stamped, NOW, epoch, st) is None
    assert decide(stamped, NOW, BrokerEpoch("run-3", NOW - S), st) is not None
    # a RUNNING job between stages counts from its hand-off, not its row update
    between = JobView("r", JobState.RUNNING, NOW - S, broker_seen_at=NOW - 40 * S)
    assert decide(between, NOW, epoch, st) is not None
    assert decide(between, NOW, None, st) is None  # no identity (SQLite broker): not checked
    # a RUNNING job held by a live lease is never the broker's (Celery cancels running
    # stages when Redis goes: their leases are released, the rule above applies then)
    held = JobView("r", JobState.RUNNING, NOW - S, NOW - 40 * S, leases=(_lease(NOW),))
    assert decide(held, NOW, epoch, st) is None


def test_decide_stale_backstop(tmp_path: Path) -> None:
    st = _settings(tmp_path, task_time_limit_s=60, task_soft_time_limit_s=50,
                   visibility_margin_s=10, visibility_timeout_s=70)  # fmt: skip
    stale = JobView("r", JobState.RUNNING, NOW - 71 * S, broker_seen_at=NOW - 71 * S)
    why = decide(stale, NOW, None, st, stale_rule=True)
    assert why is not None and "no progress for 70s" in why
    recent = JobView("r", JobState.RUNNING, NOW - 69 * S, NOW - 69 * S)
    assert decide(recent, NOW, None, st, stale_rule=True) is None
    # with Redis a RUNNING job between stages waits in a backlog as long as it must
    assert decide(stale, NOW, BrokerEpoch("t", NOW - 100 * S), st) is None
    # a QUEUED job is never stale
    queued = JobView("q", JobState.QUEUED, NOW - 10_000 * S)
    assert decide(queued, NOW, None, st, stale_rule=True) is None


# ---------------------------------------------------------------------------- sweeps
@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    if request.param == "sqlite":
        s = _settings(tmp_path)
        upgrade(database_url=str(s.database_url))
        yield s
        return
    for pg in make_pg_schema("osdar_reaper"):
        yield _settings(tmp_path, database_url=pg.url)


def _jobs(settings: Settings, n: int, **kw: Any) -> list[str]:
    with session_scope(settings) as s:
        key = ApiKey(name="k", key_hash=utcnow().isoformat().ljust(64, "y")[:64], prefix="p")
        s.add(key)
        s.flush()
        jobs = [Job(owner_id=key.id, spec={}, **kw) for _ in range(n)]
        s.add_all(jobs)
        s.flush()
        return [j.id for j in jobs]


def _set(settings: Settings, job_id: str, **values: Any) -> None:
    with session_scope(settings) as s:
        s.execute(update(Job).where(Job.id == job_id).values(**values))


def _expire(settings: Settings, job_id: str, ago_s: float) -> None:
    """Age every lease of the job: renewed ``ago_s + ttl`` ago, expired ``ago_s`` ago."""
    at = utcnow() - timedelta(seconds=ago_s)
    ttl = timedelta(seconds=settings.lease_ttl_s)
    with session_scope(settings) as s:
        s.execute(
            update(JobLease)
            .where(JobLease.job_id == job_id)
            .values(taken_at=at - ttl, renewed_at=at - ttl, expires_at=at)
        )
        s.execute(update(Job).where(Job.id == job_id).values(broker_seen_at=at - ttl))


def _row(settings: Settings, job_id: str) -> Job:
    with session_scope(settings) as s:
        job = s.get(Job, job_id)
        assert job is not None
        s.expunge(job)
        return job


def test_a_sweep_requeues_only_the_jobs_whose_holder_died(settings: Settings) -> None:
    dead, alive, handed, queued, poison = _jobs(
        settings, 5, state=JobState.RUNNING, attempt=1, deliveries=1
    )
    _set(settings, poison, deliveries=settings.max_deliveries)
    _set(settings, queued, state=JobState.QUEUED)
    taken = {j: lease.take(j, 1, "augment[0]", settings=settings) for j in (dead, handed, poison)}
    lease.take(alive, 0, "fetch", settings=settings)  # an older attempt's lease: ignored
    _expire(settings, alive, ago_s=1)
    lease.take(alive, 1, "augment[0]", settings=settings)  # ... and a live one of attempt 1
    _expire(settings, dead, ago_s=1)
    _expire(settings, poison, ago_s=1)
    # completed: handed to the broker, no lease left
    lease.release(taken[handed], settings=settings, handed_off=True)
    app = memory_celery()
    sent_tasks()

    report = reap(settings, app)  # SQLite broker: no identity, the lease rules only
    assert report.broker is None
    assert report.requeued == [dead] and report.failed == [poison]
    assert report.reasons[dead].startswith("lease expired: augment[0]")
    assert [t["id"] for t in sent_tasks()] == [dead]
    row = _row(settings, dead)
    assert row.state == JobState.QUEUED and row.stage == "requeued"
    assert _row(settings, poison).state == JobState.FAILED
    assert "poison" in (_row(settings, poison).error or "")
    for job_id, state in ((alive, JobState.RUNNING), (handed, JobState.RUNNING),
                          (queued, JobState.QUEUED)):  # fmt: skip
        assert _row(settings, job_id).state == state
    with session_scope(settings) as s:
        holders = {r.job_id for r in s.scalars(select(JobLease))}
        kinds = [e.kind for e in s.scalars(select(JobEvent).where(JobEvent.job_id == dead))]
    assert holders == {alive}  # the dead job's leases went with its claim
    assert kinds == ["requeued"]
    # another worker's reaper right after: nothing left to do
    assert reap(settings, app).requeued == [] and sent_tasks() == []


def test_a_renewal_between_read_and_claim_wins(settings: Settings) -> None:
    (job_id,) = _jobs(settings, 1, state=JobState.RUNNING, attempt=1)
    taken = lease.take(job_id, 1, "evaluate", settings=settings)
    _expire(settings, job_id, ago_s=1)
    row = _row(settings, job_id)
    view = JobView(job_id, row.state, row.updated_at, row.broker_seen_at, None,
                   (LeaseView("evaluate", taken.holder, utcnow(), utcnow()),))  # fmt: skip
    assert lease.renew(taken, settings=settings)  # the holder was only slow
    out = _requeue(get_sessionmaker(settings), memory_celery(), settings, view, "test", None)
    assert out is None and _row(settings, job_id).state == JobState.RUNNING
    assert sent_tasks() == []


def test_reapers_racing_requeue_each_job_once(settings: Settings) -> None:
    ids = _jobs(settings, 6, state=JobState.RUNNING, attempt=1, deliveries=1)
    for job_id in ids:
        lease.take(job_id, 1, "package", settings=settings)
        _expire(settings, job_id, ago_s=1)
    app = memory_celery()
    sent_tasks()
    reports: list[Any] = []
    errors: list[BaseException] = []

    def sweep() -> None:
        try:
            reports.append(reap(settings, app))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=sweep) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == []
    won = sorted(j for r in reports for j in r.requeued)
    assert won == sorted(ids)  # each job re-queued by exactly one of the four
    assert sorted(t["id"] for t in sent_tasks()) == sorted(ids)
    with session_scope(settings) as s:
        requeues = s.scalars(select(JobEvent.job_id).where(JobEvent.kind == "requeued")).all()
    assert sorted(requeues) == sorted(ids)


def test_a_lost_broker_is_seen_from_the_sentinel(settings: Settings) -> None:
    """Redis restarted without persistence or flushed: both take the sentinel with the
    messages. Shown by deleting the sentinel of a Redis database of this test's own."""
    if not common.redis_up():
        pytest.skip("Redis not reachable")
    url = common.REDIS_URL.rsplit("/", 1)[0] + "/14"  # not the scenarios' database
    client = common.redis_client(url)
    client.delete(SENTINEL_KEY)
    redis_settings = settings.model_copy(update={"broker_url": url})
    epoch = broker_epoch(redis_settings)
    assert epoch is not None and epoch.written and len(epoch.token) == 32
    assert utcnow() - timedelta(seconds=5) < epoch.since <= utcnow()
    assert broker_epoch(redis_settings) == replace(epoch, written=False)  # read, not rewritten
    assert broker_epoch(settings) is None  # the SQLite broker is not checked
    client.set(SENTINEL_KEY, b"not ours")
    with pytest.raises(ValueError, match="unreadable"):
        broker_epoch(redis_settings)
    # a sentinel written a minute ago (the broker lost its data then)
    minute_ago = {"token": "t" * 32, "since": (utcnow() - timedelta(seconds=60)).isoformat()}
    client.set(SENTINEL_KEY, json.dumps(minute_ago))
    epoch = broker_epoch(redis_settings)
    assert epoch is not None and not epoch.written and epoch.token == "t" * 32

    before, after, running = _jobs(settings, 3, state=JobState.QUEUED)
    sent_before = epoch.since - timedelta(seconds=5)  # handed to the broker before the loss
    _set(settings, before, updated_at=sent_before)
    _set(settings, running, state=JobState.RUNNING, attempt=1, broker_seen_at=sent_before,
         updated_at=utcnow())  # fmt: skip
    _set(settings, after, updated_at=epoch.since + timedelta(seconds=30))  # after: it is there
    # the API could not send this one (broker down): sent by the sweep, under the sentinel
    (pending,) = _jobs(settings, 1, state=JobState.PENDING)
    _set(settings, pending, created_at=utcnow() - timedelta(seconds=200))
    app = memory_celery()
    sent_tasks()
    report = reap(redis_settings, app)
    assert report.broker is not None and report.broker.token == epoch.token
    assert sorted(report.requeued) == sorted([before, running])
    why = f"broker lost its data: its sentinel {epoch.token[:8]}"
    assert report.reasons[before].startswith(why)
    assert report.pending_sent == [pending]
    assert sorted(t["id"] for t in sent_tasks()) == sorted([before, running, pending])
    assert _row(settings, before).broker_run_id == epoch.token  # sent under this sentinel
    assert _row(settings, pending).broker_run_id == epoch.token
    assert _row(settings, after).state == JobState.QUEUED and _row(settings, after).stage is None
    # the next sweep finds the re-sent jobs covered, though within the margin of the loss
    assert reap(redis_settings, app).requeued == [] and sent_tasks() == []
    # the broker flushed again: everything handed to it before is sent again, once
    client.delete(SENTINEL_KEY)
    report = reap(redis_settings, app)
    assert report.broker is not None and report.broker.written
    assert sorted(report.requeued) == sorted([before, running, after, pending])
    assert reap(redis_settings, app).requeued == []
    client.delete(SENTINEL_KEY)
