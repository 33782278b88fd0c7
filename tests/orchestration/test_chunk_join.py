"""The join of a job's chunks in our database (worker/orchestration/chunk_join.py), on
SQLite and PostgreSQL rows: a chunk counted once however often it is delivered, the
``finish`` sent exactly once by the chunk that completes the last one (also when chunks
race), a stale ``finish`` refused, and the reaper sending a lost ``finish`` again.

The chunk task runs for real (worker/orchestration/tasks.py) on an in-memory broker; only
the chunk's rendering (``runner.augment_chunk``'s work) is replaced by its record."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select, update

from osdar_platform.db import session_scope
from osdar_platform.migrate import upgrade
from osdar_platform.models import ApiKey, Job, JobEvent, JobLease, JobState, utcnow
from osdar_platform.settings import Settings
from tests.conftest_service import make_pg_schema, memory_celery, sent_tasks
from worker.orchestration import chunk_join, lease, runner, state, tasks
from worker.orchestration.queue import TASK_AUGMENT_CHUNK, TASK_FINISH
from worker.orchestration.reaper import reap


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    values: dict[str, Any] = {"lease_ttl_s": 9, "lease_renew_s": 3, "reaper_orphan_grace_s": 5}
    if request.param == "sqlite":
        s = Settings(data_dir=tmp_path, **values)
        upgrade(database_url=str(s.database_url))
        yield s
        return
    for pg in make_pg_schema("osdar_join"):
        yield Settings(data_dir=tmp_path, database_url=pg.url, **values)


def _running_job(settings: Settings, chunks: int) -> tuple[str, int]:
    """A job started (attempt 1) with ``chunks`` chunks planned."""
    with session_scope(settings) as s:
        key = ApiKey(name="k", key_hash=utcnow().isoformat().ljust(64, "j")[:64], prefix="p")
        s.add(key)
        s.flush()
        job = Job(owner_id=key.id, spec={}, state=JobState.QUEUED)
        s.add(job)
        s.flush()
        job_id = job.id
    attempt = state.mark_running(job_id, settings=settings)
    chunk_join.plan(job_id, attempt, chunks, settings=settings)
    return job_id, attempt


def _record(index: int) -> dict[str, Any]:
    return {"index": index, "frames": [index], "files": f"f{index}", "records": f"r{index}"}


def _row(settings: Settings, job_id: str) -> Job:
    with session_scope(settings) as s:
        job = s.get(Job, job_id)
        assert job is not None
        s.expunge(job)
        return job


def _finishes() -> list[dict[str, Any]]:
    return [t for t in sent_tasks() if t["task"] == TASK_FINISH]


def test_each_chunk_counts_once_and_one_claim_gets_the_finish(settings: Settings) -> None:
    job_id, attempt = _running_job(settings, 2)
    kw: dict[str, Any] = {"settings": settings}
    assert chunk_join.complete_chunk(job_id, attempt, 1, _record(1), **kw)
    assert not chunk_join.complete_chunk(job_id, attempt, 1, _record(1), **kw)  # again
    assert chunk_join.claim_finish(job_id, attempt, **kw) is None  # chunk 0 not done
    assert chunk_join.chunk_result(job_id, attempt, 1, **kw) == _record(1)
    assert chunk_join.chunk_result(job_id, attempt, 0, **kw) is None
    assert chunk_join.complete_chunk(job_id, attempt, 0, _record(0), **kw)
    token = chunk_join.claim_finish(job_id, attempt, **kw)
    assert token is not None and len(token) == 32
    assert chunk_join.claim_finish(job_id, attempt, **kw) is None  # sent already
    assert chunk_join.chunk_results(job_id, attempt, **kw) == [_record(0), _record(1)]
    # an older attempt's chunk changes nothing and claims nothing
    assert not chunk_join.complete_chunk(job_id, attempt - 1, 2, _record(2), **kw)
    assert chunk_join.claim_finish(job_id, attempt - 1, **kw) is None
    # the finish carrying the token is admitted (again when delivered again), no other
    assert not chunk_join.finish_token_current(job_id, attempt, "0" * 32, **kw)
    assert not chunk_join.admit_finish(job_id, attempt, "0" * 32, **kw)
    assert chunk_join.admit_finish(job_id, attempt, token, **kw)
    assert chunk_join.admit_finish(job_id, attempt, token, **kw)
    assert chunk_join.claim_finish(job_id, attempt, resend=True, **kw) is None  # started
    # a new attempt starts with an empty join
    _set(settings, job_id, state=JobState.QUEUED)
    again = state.mark_running(job_id, settings=settings)
    row = _row(settings, job_id)
    assert again == attempt + 1 and row.chunks_total == 0 and row.chunks_done is None
    assert row.finish_token is None and row.finish_started_at is None
    assert chunk_join.claim_finish(job_id, again, **kw) is None


def _set(settings: Settings, job_id: str, **values: Any) -> None:
    with session_scope(settings) as s:
        s.execute(update(Job).where(Job.id == job_id).values(**values))


def test_chunks_completing_at_once_send_one_finish(settings: Settings) -> None:
    """Four chunks recorded and claimed by four threads at once, twice each (a
    redelivery): every chunk counted once, exactly one token handed out."""
    job_id, attempt = _running_job(settings, 4)
    tokens: list[str | None] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(8)

    def chunk(index: int) -> None:
        try:
            barrier.wait(10)
            chunk_join.complete_chunk(job_id, attempt, index, _record(index), settings=settings)
            tokens.append(chunk_join.claim_finish(job_id, attempt, settings=settings))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=chunk, args=(i % 4,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == []
    assert len([t for t in tokens if t is not None]) == 1
    assert chunk_join.chunk_results(job_id, attempt, settings=settings) == [
        _record(i) for i in range(4)
    ]


@pytest.fixture
def chunk_task(monkeypatch: pytest.MonkeyPatch, settings: Settings) -> Iterator[Any]:
    """The real ``osdar_ar.augment_chunk`` task on an in-memory broker, its chunk's
    rendering replaced by the chunk's record (runner.augment_chunk records it the same
    way at the end of its stage); yields (task, calls of the rendering)."""
    app = memory_celery()
    rendered: list[int] = []

    def augment(job_id: str, index: int, frames: list[int], *, attempt: int) -> Any:
        done = chunk_join.chunk_result(job_id, attempt, index, settings=settings)
        if done is not None:  # as the runner: a chunk done already is not redone
            return done
        rendered.append(index)
        record = _record(index)
        chunk_join.complete_chunk(job_id, attempt, index, record, settings=settings)
        return record

    monkeypatch.setattr(runner, "augment_chunk", augment)
    monkeypatch.setattr(tasks, "get_settings", lambda: settings)
    sent_tasks()
    yield app.tasks[TASK_AUGMENT_CHUNK], rendered
    sent_tasks()


def test_two_chunk_tasks_enqueue_finish_once(settings: Settings, chunk_task: Any) -> None:
    task, rendered = chunk_task
    job_id, attempt = _running_job(settings, 2)
    task.run(job_id, attempt, 0, [0])
    assert _finishes() == []  # chunk 1 not done yet
    task.run(job_id, attempt, 0, [0])  # chunk 0 delivered again: not counted twice
    assert _finishes() == [] and rendered == [0]
    assert len(_row(settings, job_id).chunks_done or {}) == 1
    task.run(job_id, attempt, 1, [1])
    (sent,) = _finishes()
    token = _row(settings, job_id).finish_token
    assert sent["args"] == [job_id, attempt, token]
    task.run(job_id, attempt, 1, [1])  # the last chunk delivered again: no second finish
    assert _finishes() == [] and rendered == [0, 1]


def test_a_stale_finish_stops_before_its_stage(settings: Settings) -> None:
    job_id, attempt = _running_job(settings, 1)
    chunk_join.complete_chunk(job_id, attempt, 0, _record(0), settings=settings)
    token = chunk_join.claim_finish(job_id, attempt, settings=settings)
    assert token is not None
    with pytest.raises(state.JobSuperseded):
        runner.finish_job(job_id, token="f" * 32, attempt=attempt, settings=settings)
    with session_scope(settings) as s:
        kinds = list(s.scalars(select(JobEvent.kind).where(JobEvent.job_id == job_id)))
        assert list(s.scalars(select(JobLease))) == []
    assert "stage_delivered" not in kinds  # no lease taken, no delivery counted
    assert _row(settings, job_id).finish_started_at is None


def _age(settings: Settings, job_id: str, seconds: float) -> None:
    _set(settings, job_id, updated_at=utcnow() - timedelta(seconds=seconds))


def test_the_reaper_sends_a_lost_finish_again(settings: Settings) -> None:
    app = memory_celery()
    sent_tasks()
    # the last chunk's process died after its record, before its claim
    unclaimed, a1 = _running_job(settings, 2)
    for i in range(2):
        chunk_join.complete_chunk(unclaimed, a1, i, _record(i), settings=settings)
    # ... after its claim, before its send reached the broker
    claimed, a2 = _running_job(settings, 1)
    chunk_join.complete_chunk(claimed, a2, 0, _record(0), settings=settings)
    lost = chunk_join.claim_finish(claimed, a2, settings=settings)
    # not lost: a chunk still to come, a finish running, a live lease, a recent update
    waiting, a3 = _running_job(settings, 2)
    chunk_join.complete_chunk(waiting, a3, 0, _record(0), settings=settings)
    started, a4 = _running_job(settings, 1)
    chunk_join.complete_chunk(started, a4, 0, _record(0), settings=settings)
    running = chunk_join.claim_finish(started, a4, settings=settings)
    assert running is not None and chunk_join.admit_finish(started, a4, running,
                                                           settings=settings)  # fmt: skip
    held, a5 = _running_job(settings, 1)
    chunk_join.complete_chunk(held, a5, 0, _record(0), settings=settings)
    lease.take(held, a5, "augment[0]", settings=settings)
    recent, a6 = _running_job(settings, 1)
    chunk_join.complete_chunk(recent, a6, 0, _record(0), settings=settings)
    for job_id in (unclaimed, claimed, waiting, started, held):
        _age(settings, job_id, 10)

    report = reap(settings, app)
    assert sorted(report.finish_resent) == sorted([unclaimed, claimed])
    assert report.requeued == []
    sent = {t["args"][0]: t["args"] for t in _finishes()}
    assert sorted(sent) == sorted([unclaimed, claimed])
    for job_id, attempt in ((unclaimed, a1), (claimed, a2)):
        token = _row(settings, job_id).finish_token
        assert sent[job_id] == [job_id, attempt, token]
    assert sent[claimed][2] != lost  # the lost message, if it comes, is refused
    assert not chunk_join.admit_finish(claimed, a2, str(lost), settings=settings)
    assert chunk_join.admit_finish(claimed, a2, sent[claimed][2], settings=settings)
    with session_scope(settings) as s:
        events = s.scalars(select(JobEvent.job_id).where(JobEvent.kind == "finish_resent"))
        assert sorted(events) == sorted([unclaimed, claimed])
    # the next sweep: the row moved with the send, nothing sent again
    assert reap(settings, app).finish_resent == [] and _finishes() == []
