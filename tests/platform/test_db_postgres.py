"""The database layer on a real PostgreSQL (and the SQLite default): migrations match the
models, constraints hold under concurrency, the queue's state changes are conditional."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, inspect, select, text, update
from sqlalchemy.exc import IntegrityError

from osdar_platform.db import make_engine, make_sessionmaker
from osdar_platform.keys import create_api_key, find_api_key, hash_secret
from osdar_platform.models import ApiKey, Job, JobEvent, JobState, Sequence, utcnow
from tests.conftest_service import PgSchema, make_pg_schema, memory_celery, sent_tasks
from worker.orchestration.queue import TASK_RUN_JOB, enqueue_job, request_cancel, requeue_pending

TABLES = {
    *("alembic_version", "api_keys", "sequences", "assets", "jobs", "job_events"),
    *("campaigns", "campaign_variants", "job_leases"),
}


@pytest.fixture(scope="module")
def pg() -> Iterator[PgSchema]:
    yield from make_pg_schema("osdar_dbtest")


@pytest.fixture(scope="module")
def sessions(pg: PgSchema) -> Iterator[Any]:
    engine = make_engine(pg.url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _owner(sessions: Any, name: str = "k") -> ApiKey:
    with sessions.begin() as s:
        key, _ = create_api_key(session=s, name=name, pepper="p")
    return key


def _sequence(sessions: Any, owner: ApiKey) -> Sequence:
    seq = Sequence(
        owner_id=owner.id,
        name="s",
        source="path",
        path="/x",
        frames=3,
        cameras=["rgb_center"],
        time_span_s=0.2,
        validation={"first_frame": 0, "last_frame": 2, "frame_indices": [0, 1, 2]},
    )
    with sessions.begin() as s:
        s.add(seq)
    return seq


def _job(sessions: Any, owner: ApiKey, seq: Sequence | None = None, **kw: Any) -> Job:
    job = Job(owner_id=owner.id, sequence_id=seq.id if seq else None, spec={"a": 1}, **kw)
    with sessions.begin() as s:
        s.add(job)
    return job


def test_migrations_create_exactly_the_models(pg: PgSchema) -> None:
    from alembic import command

    from osdar_platform.migrate import alembic_config, current_head

    engine = make_engine(pg.url)
    try:
        with engine.connect() as conn:
            assert set(inspect(conn).get_table_names()) == TABLES
            assert conn.scalar(text("SELECT version_num FROM alembic_version")) == current_head()
            command.check(alembic_config(connection=conn))  # raises on any drift
    finally:
        engine.dispose()


def test_downgrade_and_upgrade_again() -> None:
    from osdar_platform.migrate import downgrade, upgrade

    for schema in make_pg_schema("osdar_dbdown"):
        downgrade(database_url=schema.url)
        engine = make_engine(schema.url)
        with engine.connect() as conn:
            assert set(inspect(conn).get_table_names()) == {"alembic_version"}
        upgrade(database_url=schema.url)
        with engine.connect() as conn:
            assert set(inspect(conn).get_table_names()) == TABLES
        engine.dispose()


def test_sqlite_default_runs_the_same_migrations(tmp_path: Path) -> None:
    from alembic import command

    from osdar_platform.migrate import alembic_config, upgrade

    url = f"sqlite:///{tmp_path}/db/osdar-ar.db"
    upgrade(database_url=url)
    engine = make_engine(url)
    with engine.connect() as conn:
        assert conn.scalar(text("PRAGMA journal_mode")) == "wal"
        assert conn.scalar(text("PRAGMA foreign_keys")) == 1
        assert conn.scalar(text("PRAGMA busy_timeout")) == 30000
        command.check(alembic_config(connection=conn))
    engine.dispose()


def test_keys_are_stored_hashed(sessions: Any) -> None:
    with sessions.begin() as s:
        row, secret = create_api_key(session=s, name="hashed", pepper="pepper")
    with sessions() as s:
        stored = s.get(ApiKey, row.id)
        assert stored.key_hash == hash_secret(secret, "pepper") and secret not in stored.key_hash
        assert secret.startswith(stored.prefix)
        assert find_api_key(session=s, secret=secret, pepper="pepper").id == row.id
        assert find_api_key(session=s, secret=secret, pepper="other") is None
        assert find_api_key(session=s, secret=secret + "x", pepper="pepper") is None


def test_idempotency_key_is_unique_per_owner(sessions: Any) -> None:
    a, b = _owner(sessions, "a"), _owner(sessions, "b")
    _job(sessions, a, idempotency_key="k1")
    _job(sessions, b, idempotency_key="k1")  # another owner: fine
    _job(sessions, a)
    _job(sessions, a)  # NULL keys never collide
    with pytest.raises(IntegrityError):
        _job(sessions, a, idempotency_key="k1")


def test_20_concurrent_idempotent_submissions_make_one_row(sessions: Any) -> None:
    from osdar_platform.settings import Settings
    from service.schemas import JobCreate
    from service.services.jobs import create_job

    owner = _owner(sessions, "racer")
    seq = _sequence(sessions, owner)
    spec = JobCreate.model_validate(
        {
            "sequence_id": seq.id,
            "cameras": ["rgb_center"],
            "lidar": False,
            "object": {"builtin": "rock"},
            "placement": {"mode": "track", "s": 10},
        }
    )
    settings = Settings(max_concurrent_jobs_per_key=100)
    barrier = threading.Barrier(20)
    results: list[tuple[str, bool]] = []

    def submit() -> None:
        with sessions() as s:
            barrier.wait()
            job, created = create_job(
                session=s, spec=spec, owner=owner, idempotency_key="same", settings=settings
            )
            results.append((job.id, created))

    threads = [threading.Thread(target=submit) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 20
    assert len({job_id for job_id, _ in results}) == 1
    assert sum(created for _, created in results) == 1
    with sessions() as s:
        count = s.scalar(select(func.count()).select_from(Job).where(Job.owner_id == owner.id))
    assert count == 1


def test_deleting_a_sequence_keeps_its_jobs(sessions: Any) -> None:
    owner = _owner(sessions)
    seq = _sequence(sessions, owner)
    job = _job(sessions, owner, seq)
    with sessions.begin() as s:
        s.add(JobEvent(job_id=job.id, kind="created"))
    with sessions.begin() as s:
        s.delete(s.get(Sequence, seq.id))
    with sessions.begin() as s:
        row = s.get(Job, job.id)
        assert row.sequence_id is None and row.state == JobState.PENDING
        assert row.created_at.tzinfo is not None
        s.delete(row)
    with sessions() as s:  # events go with their job
        n = s.scalar(select(func.count()).select_from(JobEvent).where(JobEvent.job_id == job.id))
        assert n == 0


def test_enqueue_moves_pending_to_queued_only(sessions: Any) -> None:
    owner = _owner(sessions)
    app = memory_celery()
    sent_tasks()
    fresh = _job(sessions, owner)
    enqueue_job(fresh.id, sessions=sessions, app=app)
    running = _job(sessions, owner, state=JobState.RUNNING)  # a worker was faster
    enqueue_job(running.id, sessions=sessions, app=app)
    with sessions() as s:
        assert s.get(Job, fresh.id).state == JobState.QUEUED
        assert s.get(Job, running.id).state == JobState.RUNNING
    sent = sent_tasks()
    assert [(m["task"], m["id"]) for m in sent] == [
        (TASK_RUN_JOB, fresh.id),
        (TASK_RUN_JOB, running.id),
    ]


def test_requeue_pending_sends_the_stragglers(sessions: Any) -> None:
    owner = _owner(sessions)
    old = _job(sessions, owner, created_at=utcnow() - timedelta(minutes=5))
    young = _job(sessions, owner)
    sent_tasks()
    ids = requeue_pending(older_than_s=60, sessions=sessions, app=memory_celery())
    assert old.id in ids and young.id not in ids
    assert old.id in [m["id"] for m in sent_tasks()]


def test_request_cancel_by_state(sessions: Any) -> None:
    owner = _owner(sessions)
    app = memory_celery()
    queued = _job(sessions, owner, state=JobState.QUEUED)
    running = _job(sessions, owner, state=JobState.RUNNING)
    done = _job(sessions, owner, state=JobState.SUCCEEDED)
    assert request_cancel(queued.id, sessions=sessions, app=app) == JobState.CANCELLED
    assert request_cancel(running.id, sessions=sessions, app=app) == JobState.RUNNING
    assert request_cancel(done.id, sessions=sessions, app=app) == JobState.SUCCEEDED
    assert request_cancel("nope", sessions=sessions, app=app) is None
    with sessions() as s:
        assert s.get(Job, running.id).cancel_requested is True
        assert s.get(Job, done.id).cancel_requested is False
        assert s.get(Job, queued.id).finished_at is not None
    with sessions.begin() as s:
        s.execute(update(Job).where(Job.id == running.id).values(state=JobState.CANCELLED))
