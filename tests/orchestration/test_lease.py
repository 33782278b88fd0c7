"""Leases of running stages (worker/orchestration/lease.py) on real PostgreSQL and SQLite:
taken, renewed by the heartbeat, released with or without a hand-off, lost to the reaper."""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import delete, select
from sqlalchemy.exc import OperationalError

from osdar_platform.db import session_scope
from osdar_platform.migrate import upgrade
from osdar_platform.models import ApiKey, Job, JobLease, JobState, utcnow
from osdar_platform.settings import Settings
from tests.conftest_service import make_pg_schema
from worker.orchestration import lease


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    # a TTL of 1.2 s renewed every 0.3 s: the heartbeat's work in a second or two
    kw: dict[str, Any] = {"lease_ttl_s": 1.2, "lease_renew_s": 0.3}
    if request.param == "sqlite":
        s = Settings(data_dir=tmp_path, **kw)
        upgrade(database_url=str(s.database_url))
        yield s
        return
    for pg in make_pg_schema("osdar_lease"):
        yield Settings(data_dir=tmp_path, database_url=pg.url, **kw)


def running_job(settings: Settings, attempt: int = 1) -> str:
    with session_scope(settings) as s:
        key = ApiKey(name="k", key_hash=utcnow().isoformat().ljust(64, "x")[:64], prefix="p")
        s.add(key)
        s.flush()
        job = Job(owner_id=key.id, spec={}, state=JobState.RUNNING, attempt=attempt)
        s.add(job)
        s.flush()
        return job.id


def leases(settings: Settings, job_id: str) -> list[JobLease]:
    with session_scope(settings) as s:
        rows = list(s.scalars(select(JobLease).where(JobLease.job_id == job_id)))
        s.expunge_all()
        return rows


def seen_at(settings: Settings, job_id: str) -> Any:
    with session_scope(settings) as s:
        return s.scalar(select(Job.broker_seen_at).where(Job.id == job_id))


def test_take_renew_release(settings: Settings) -> None:
    job_id = running_job(settings)
    t0 = utcnow()
    a = lease.take(job_id, 1, "fetch", settings=settings)
    (row,) = leases(settings, job_id)
    assert row.holder == lease.holder_name() and row.stage == "fetch" and row.attempt == 1
    ttl = timedelta(seconds=settings.lease_ttl_s)
    assert t0 + ttl <= row.expires_at <= utcnow() + ttl
    assert t0 <= seen_at(settings, job_id) <= utcnow()  # its message was just delivered

    # the same stage delivered again replaces the row: its previous holder is gone
    b = lease.take(job_id, 1, "fetch", settings=settings)
    (again,) = leases(settings, job_id)
    assert again.id == b.id and again.taken_at > row.taken_at and a.stage == b.stage

    time.sleep(0.2)
    assert lease.renew(b, settings=settings)
    (renewed,) = leases(settings, job_id)
    assert renewed.expires_at > row.expires_at + timedelta(seconds=0.15)
    assert renewed.renewed_at > row.renewed_at

    # chunks in parallel: each completed one releases its own row and records the hand-off
    c = lease.take(job_id, 1, "augment[1]", settings=settings)
    before = seen_at(settings, job_id)
    lease.release(b, settings=settings, handed_off=True)
    assert [r.id for r in leases(settings, job_id)] == [c.id]
    assert seen_at(settings, job_id) > before
    # one that did not complete leaves the hand-off time alone
    handed = seen_at(settings, job_id)
    lease.release(c, settings=settings, handed_off=False)
    assert leases(settings, job_id) == [] and seen_at(settings, job_id) == handed
    assert not lease.renew(c, settings=settings)  # gone: nothing to renew


@pytest.mark.parametrize(  # 3.6 s of sleep each: PostgreSQL's run only in make test
    "settings", ["sqlite", pytest.param("postgresql", marks=pytest.mark.slow)], indirect=True
)
def test_the_heartbeat_keeps_a_lease_alive_and_the_end_releases_it(settings: Settings) -> None:
    job_id = running_job(settings)
    with lease.held(job_id, 1, "prepare", settings=settings):
        time.sleep(3 * settings.lease_ttl_s)  # three TTLs: alive only if renewed
        (row,) = leases(settings, job_id)
        assert row.expires_at > utcnow()
        assert row.renewed_at > row.taken_at + timedelta(seconds=2 * settings.lease_ttl_s)
    assert leases(settings, job_id) == []
    # a stage that raised released its lease without handing the job off
    handed = seen_at(settings, job_id)
    with pytest.raises(RuntimeError), lease.held(job_id, 1, "evaluate", settings=settings):
        taken = seen_at(settings, job_id)
        raise RuntimeError("stage failed")
    assert leases(settings, job_id) == [] and seen_at(settings, job_id) == taken > handed


def test_a_lease_taken_away_stops_the_heartbeat(settings: Settings) -> None:
    job_id = running_job(settings)
    taken = lease.take(job_id, 1, "package", settings=settings)
    beat = lease.Heartbeat(taken, settings)
    beat.start()
    time.sleep(settings.lease_renew_s * 2.5)
    with session_scope(settings) as s:  # what the reaper's claim does
        s.execute(delete(JobLease).where(JobLease.id == taken.id))
    beat.join(settings.lease_renew_s * 4)
    assert not beat.is_alive() and beat.lost and beat.renewals >= 1
    assert leases(settings, job_id) == []  # a renewal never brings a row back


def test_an_unreachable_database_is_told_apart(tmp_path: Path) -> None:
    down = Settings(data_dir=tmp_path, database_url="postgresql+psycopg://x@127.0.0.1:9/none")
    with pytest.raises(lease.LeaseUnavailable, match="database unreachable") as exc:
        lease.take("j", 1, "fetch", settings=down)
    assert isinstance(exc.value.__cause__, OperationalError)
    assert lease.database_unreachable(exc.value)
    try:
        raise RuntimeError("wrapped") from exc.value
    except RuntimeError as wrapped:
        assert lease.database_unreachable(wrapped)
    assert not lease.database_unreachable(ValueError("a job's own error"))


def test_lease_settings_leave_room_for_missed_renewals(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="at most a third"):
        Settings(data_dir=tmp_path, lease_ttl_s=10, lease_renew_s=4)
    s = Settings(data_dir=tmp_path)
    assert s.lease_renew_s * 3 <= s.lease_ttl_s
