"""The job runner and the Celery side: inline runs, real workers, re-delivery, poison, cancel.

- run_job_inline end to end on a tiny synthetic sequence (SQLite + local store);
- a real ``celery worker`` subprocess on Redis + PostgreSQL, jobs submitted over the API;
- the embedded mode (SQLite broker, no server) through ``Embedded``;
- publish raced by two attempts: one result, the loser's objects removed;
- a poison job that kills its worker process: FAILED after <= 3 deliveries, the next job
  still succeeds;
- the Celery config (visibility timeout above the time limit plus margin);
- cancel between stages: CANCELLED, no archive, no partial output.
"""

from __future__ import annotations

import contextlib
import os
import tarfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from osdar_platform.db import session_scope
from osdar_platform.models import ApiKey, Job, JobEvent, JobState, Sequence
from osdar_platform.settings import Settings

REDIS_URL = os.environ.get("OSDAR_AR_TEST_REDIS_URL", "redis://127.0.0.1:6379/13")
JOB_TIMEOUT_S = 120.0


# ---------------------------------------------------------------------------- helpers
def _settings(data_dir: Path, **extra: Any) -> Settings:
    from worker.orchestration.embedded import embedded_settings

    values: dict[str, Any] = {
        "environment": "test",
        "frames_per_chunk": 2,
        "rate_limit_per_s": 10_000,
        "rate_limit_burst": 100_000,
        "max_concurrent_jobs_per_key": 10_000,
    }
    values.update(extra)
    return embedded_settings(data_dir, **values)


def _migrated(settings: Settings) -> Settings:
    from osdar_platform.migrate import upgrade

    upgrade(database_url=str(settings.database_url))
    return settings


def _spec(sequence_id: str, **overrides: Any) -> dict[str, Any]:
    from service.schemas import JobCreate

    spec = {
        "sequence_id": sequence_id,
        "cameras": ["rgb_center", "rgb_highres_center"],
        "lidar": True,
        "object": {"builtin": "person", "scale": 1.0},
        "placement": {"mode": "track", "s": 5.0, "offset": 0.0, "yaw_deg": 90.0},
        "strategy": "ins",
    }
    spec.update(overrides)
    return JobCreate.model_validate(spec).model_dump(mode="json")


def _owner_and_sequence(settings: Settings, folder: Path) -> tuple[int, str]:
    from osdar_platform.keys import create_api_key
    from service.services.sequences import register_sequence

    with session_scope(settings) as s:
        key, _ = create_api_key(session=s, name="t", pepper="p")
        owner = s.get(ApiKey, key.id)
        seq = register_sequence(
            session=s, owner=owner, path=str(folder), name=None, settings=settings
        )
        return key.id, seq.id


def _new_job(settings: Settings, owner: int, sequence_id: str, **test: Any) -> str:
    """A QUEUED job row (as the API leaves it); ``test`` goes to the test-only hooks."""
    spec = _spec(sequence_id)
    if test:
        spec["_test"] = test
    with session_scope(settings) as s:
        frames = len(s.get(Sequence, sequence_id).validation["frame_indices"])
        job = Job(
            owner_id=owner,
            sequence_id=sequence_id,
            spec=spec,
            state=JobState.QUEUED,
            progress_total=frames,
        )
        s.add(job)
        s.flush()
        return job.id


def _job(settings: Settings, job_id: str) -> Job:
    with session_scope(settings) as s:
        return s.get(Job, job_id)


def _archive_keys(store: Any, job_id: str) -> list[str]:
    return [k for k in store.list(f"jobs/{job_id}/") if k.endswith("archive.tar.gz")]


def _wait(predicate: Any, timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s}s waiting for {what}")


def _check_archive(store: Any, key: str, tmp: Path, seq_name: str) -> set[str]:
    path = tmp / "got.tar.gz"
    store.get_file(key, path)
    with tarfile.open(path) as tar:
        names = set(tar.getnames())
    assert f"{seq_name}/metrics.json" in names
    assert f"{seq_name}/{seq_name}_labels.json" in names
    assert not any("/ground_truth/" in n for n in names)
    assert any(n.startswith(f"{seq_name}/report/previews/") for n in names)
    return names


@pytest.fixture(scope="module")
def seq_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 4-frame synthetic sequence (2 chunks of 2 frames)."""
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("jobs_seq") / "fire_site_jobs"
    generate(folder, SynthConfig(scene="fire_site", frames=4, scale=0.05, lidar_density=0.05))
    return folder


# ---------------------------------------------------------------------------- (a) inline
def test_run_job_inline_end_to_end(tmp_path: Path, seq_folder: Path) -> None:
    from osdar_platform.store import store_from_url
    from worker.orchestration.runner import run_job_inline

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id)

    assert run_job_inline(job_id, settings=settings) == JobState.SUCCEEDED, _job(
        settings, job_id
    ).error
    job = _job(settings, job_id)
    assert job.attempt == 1 and job.deliveries == 1
    assert job.progress_total == 4 and job.progress_done == job.progress_total
    assert job.result_key == f"jobs/{job_id}/attempt-1/archive.tar.gz"
    ev = job.metrics["evaluation"]
    assert ev["strategy"] == "ins"
    gt = ev["ground_truth"]
    assert gt["pose_error"]["ins"]["translation_m_mean"] >= 0
    assert gt["landmark_rpe"]["rgb_center"]["ins"]["rpe_px"]["n"] > 0
    assert set(job.timings) >= {"fetch", "prepare", "evaluate", "package", "publish"}
    store = store_from_url(str(settings.store_url), settings)
    assert store.list(f"jobs/{job_id}/") == sorted([job.result_key, *job.previews])
    assert any(k.endswith("rpe_jitter.png") for k in job.previews)
    assert any("lidar_bev" in k for k in job.previews)
    names = _check_archive(store, job.result_key, tmp_path, seq_folder.name)
    if "augmentation" in job.metrics:  # the augmentation step is plugged in
        assert set(job.timings) >= {"augment[0]", "augment[1]", "finish"}
        assert job.metrics["augmentation"]["frames"]["augmented_range"] == 4
    else:
        assert sum(n.endswith(".pcd") for n in names) == 4
    assert not (Path(settings.cache_dir) / "jobs" / job_id / "attempt-1").exists()


# ---------------------------------------------------------------------------- (d) publish
def test_publish_twice_keeps_one_result_and_removes_the_losers_object(
    tmp_path: Path, seq_folder: Path
) -> None:
    from osdar_platform.store import store_from_url
    from worker.orchestration import runner, state

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id)
    attempt = runner.start_job(job_id, settings=settings)
    archive = tmp_path / "a.tar.gz"
    archive.write_bytes(b"archive of attempt 1")
    store = store_from_url(str(settings.store_url), settings)

    first = runner.JobRun(job_id, attempt, settings)
    assert runner.upload_and_publish(first, archive) == f"jobs/{job_id}/attempt-1/archive.tar.gz"
    # a re-delivered publish of the same attempt: its object IS the result, nothing changes
    assert runner.upload_and_publish(first, archive) == f"jobs/{job_id}/attempt-1/archive.tar.gz"
    # a second attempt that got as far as publishing (stale delivery racing): loses
    second = runner.JobRun(job_id, attempt + 1, settings)
    # its own archive file (the store may hold the first one's bytes as a link:
    # upload_and_publish takes the file, rewriting it in place is not allowed)
    archive_2 = tmp_path / "b.tar.gz"
    archive_2.write_bytes(b"archive of attempt 2")
    assert runner.upload_and_publish(second, archive_2) is None

    job = _job(settings, job_id)
    assert job.state == JobState.SUCCEEDED
    assert job.result_key == f"jobs/{job_id}/attempt-1/archive.tar.gz"
    assert _archive_keys(store, job_id) == [job.result_key]
    assert b"".join(store.open_read(job.result_key)) == b"archive of attempt 1"
    # the publish task delivered again after success is a no-op (the job is terminal)
    with pytest.raises(state.JobSuperseded):
        runner.publish_job(job_id, archive, attempt=attempt, settings=settings)
    with session_scope(settings) as s:
        kinds = list(s.scalars(select(JobEvent.kind).where(JobEvent.job_id == job_id)))
    assert kinds.count("succeeded") == 1 and "publish_lost" in kinds


# ---------------------------------------------------------------------------- (g) cancel
def test_cancel_a_running_job_between_stages(tmp_path: Path, seq_folder: Path) -> None:
    from osdar_platform.store import store_from_url
    from worker.orchestration.queue import request_cancel
    from worker.orchestration.runner import run_job_inline

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id, sleep_in={"prepare": 1.5})
    result: dict[str, Any] = {}
    t = threading.Thread(
        target=lambda: result.update(state=run_job_inline(job_id, settings=settings))
    )
    t.start()
    _wait(lambda: _job(settings, job_id).stage == "prepare", 30, "stage prepare")
    assert request_cancel(job_id, settings=settings, revoke=False) == JobState.RUNNING
    t.join(60)
    assert result["state"] == JobState.CANCELLED
    job = _job(settings, job_id)
    assert job.state == JobState.CANCELLED and job.result_key is None
    # stopped at the next checkpoint (a sub-stage of prepare, or the next stage)
    assert set(job.timings or {}) <= {"fetch", "prepare"} and job.stage == "cancelled"
    store = store_from_url(str(settings.store_url), settings)
    assert store.list(f"jobs/{job_id}/") == []
    assert not (Path(settings.cache_dir) / "jobs" / job_id / "attempt-1").exists()


def test_a_stage_error_fails_the_job_with_a_readable_reason(
    tmp_path: Path, seq_folder: Path
) -> None:
    from worker.orchestration.runner import run_job_inline

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id, fail_in="prepare")
    assert run_job_inline(job_id, settings=settings) == JobState.FAILED
    job = _job(settings, job_id)
    assert job.error.startswith("prepare: internal error (RuntimeError: test hook")
    # the hooks are ignored outside environment "test"
    dev = settings.model_copy(update={"environment": "dev"})
    job2 = _new_job(dev, owner, seq_id, fail_in="prepare", crash_in="prepare")
    assert run_job_inline(job2, settings=dev) == JobState.SUCCEEDED


def test_a_termination_inside_a_stage_leaves_the_job_to_redelivery(
    tmp_path: Path, seq_folder: Path
) -> None:
    """The pool's SIGTERM surfacing as an ImportError (seen when Redis restarted mid-import):
    the process exits and the job stays RUNNING for redelivery / the reaper, not FAILED."""
    from worker.orchestration.runner import run_job_inline

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id, terminated_in="fetch")
    with pytest.raises(SystemExit):
        run_job_inline(job_id, settings=settings)
    job = _job(settings, job_id)
    assert job.state == JobState.RUNNING and job.error is None


def test_a_chunk_delivered_again_is_counted_once_and_not_redone(
    tmp_path: Path, seq_folder: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The join before finish (chunk_join.py) with the real stages: the plan is made by
    prepare (no chunk plans again); each chunk recorded once; a chunk delivered again
    after its record returns it without a stage; the claim hands out one finish token,
    and finish reads the chunks from the job's row."""
    from worker.orchestration import chunk_join, runner

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id)
    kw: dict[str, Any] = {"attempt": runner.start_job(job_id, settings=settings)}
    kw["settings"] = settings
    runner.fetch_sequence(job_id, **kw)
    runner.prepare_for_job(job_id, **kw)
    run = runner.JobRun(job_id, kw["attempt"], settings)
    assert (run.workdir / "plan.npz").is_file() and run.store.exists(f"{run.prefix}plan.npz")

    def planned_again(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a chunk computed the plan that prepare made")

    monkeypatch.setattr(runner, "plan_augmentation", planned_again)
    plan = runner.plan_chunks(job_id, **kw)
    assert len(plan) == 2 and _job(settings, job_id).chunks_total == 2
    first = runner.augment_chunk(job_id, 0, plan[0], **kw)
    assert chunk_join.claim_finish(job_id, kw["attempt"], settings=settings) is None
    assert runner.augment_chunk(job_id, 0, plan[0], **kw) == first  # delivered again
    second = runner.augment_chunk(job_id, 1, plan[1], **kw)
    # each chunk measured its own frames' object errors (the finish only sums them up)
    for c, frames in ((first, plan[0]), (second, plan[1])):
        record = runner.load_chunk(b"".join(run.store.open_read(c["records"])))
        assert sorted(record.object_errors) == sorted(frames)
    token = chunk_join.claim_finish(job_id, kw["attempt"], settings=settings)
    assert token is not None
    assert chunk_join.claim_finish(job_id, kw["attempt"], settings=settings) is None
    with session_scope(settings) as s:
        stages = list(s.scalars(select(JobEvent.message).where(
            JobEvent.job_id == job_id, JobEvent.kind == "stage_delivered")))  # fmt: skip
    assert stages.count("augment[0]") == 1 and stages.count("augment[1]") == 1
    assert _job(settings, job_id).chunks_done == {"0": first, "1": second}
    runner.finish_job(job_id, token=token, **kw)
    assert _job(settings, job_id).finish_started_at is not None
    folder = runner.output_sequence(run)  # assembled here: no rebuild from the store
    assert (folder.parent / ".complete").is_file()
    assert len(list(folder.rglob("*.png"))) == 2 * 4  # 2 cameras x 4 frames, both chunks


def test_stage_deliveries_add_up_across_the_jobs_attempts(tmp_path: Path, seq_folder: Path) -> None:
    """A stage that killed its worker in attempt 1, re-queued by the reaper (attempt 2),
    keeps its count: the poison bound is per job, not per attempt (CI saw 5 deliveries
    of a poison prepare when the count started again in the reaper's new attempt)."""
    from worker.orchestration import state

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id)
    first = state.mark_running(job_id, settings=settings)
    assert state.count_stage_delivery(job_id, first, "prepare", settings=settings) == 1
    second = state.mark_running(job_id, settings=settings)  # the reaper's re-queue
    assert second == first + 1
    assert state.count_stage_delivery(job_id, second, "prepare", settings=settings) == 2
    assert state.count_stage_delivery(job_id, second, "fetch", settings=settings) == 1


def test_finish_killed_while_moving_chunk_files_runs_again(
    tmp_path: Path, seq_folder: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """finish MOVES the chunks' files into the output: killed half-way and delivered again,
    it fetches the chunks from the store instead of trusting the half-emptied local ones
    (the sigkill scenario caught a FAILED 'FileNotFoundError' here)."""
    import os

    from worker.orchestration import runner

    settings = _migrated(_settings(tmp_path))
    owner, seq_id = _owner_and_sequence(settings, seq_folder)
    job_id = _new_job(settings, owner, seq_id)
    kw: dict[str, Any] = {"attempt": runner.start_job(job_id, settings=settings)}
    kw["settings"] = settings
    runner.fetch_sequence(job_id, **kw)
    runner.prepare_for_job(job_id, **kw)
    plan = runner.plan_chunks(job_id, **kw)
    chunks = [runner.augment_chunk(job_id, i, frames, **kw) for i, frames in enumerate(plan)]
    real_replace, moved = os.replace, []
    chunk_root = runner.JobRun(job_id, kw["attempt"], settings).workdir / "chunks"

    def replace_then_die(src: Any, dst: Any) -> None:
        real_replace(src, dst)
        if Path(src).is_relative_to(chunk_root):
            moved.append(dst)
            raise SystemExit(-9)  # the process dies right after moving its first chunk file

    monkeypatch.setattr(os, "replace", replace_then_die)
    with pytest.raises(SystemExit):
        runner.finish_job(job_id, chunks, **kw)
    monkeypatch.setattr(os, "replace", real_replace)
    assert len(moved) == 1
    again = runner.finish_job(job_id, chunks, **kw)  # the redelivery
    assert _job(settings, job_id).error is None
    folder = runner.output_sequence(runner.JobRun(job_id, kw["attempt"], settings))

    def contents() -> dict[str, bytes]:
        return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*.png")}

    after_kill = contents()
    assert runner.finish_job(job_id, chunks, **kw) == again  # as a finish never killed
    assert contents() == after_kill  # every augmented frame, none replaced by its input


# ---------------------------------------------------------------------------- (f) config
def test_celery_config_follows_the_reliability_rules(tmp_path: Path) -> None:
    from worker.orchestration.celery_app import make_celery

    settings = Settings(
        data_dir=tmp_path,
        broker_url="redis://127.0.0.1:6379/0",
        database_url="postgresql://u@db/x",
        task_time_limit_s=3600,
        task_soft_time_limit_s=3000,
        visibility_timeout_s=3600 + 900,
        visibility_margin_s=600,
    )
    conf = make_celery(settings).conf
    vt = conf.broker_transport_options["visibility_timeout"]
    assert vt > conf.task_time_limit + settings.visibility_margin_s
    assert conf.result_backend_transport_options["visibility_timeout"] == vt
    assert conf.task_soft_time_limit < conf.task_time_limit == 3600
    assert conf.task_acks_late and conf.task_reject_on_worker_lost
    assert conf.worker_prefetch_multiplier == 1
    assert conf.worker_cancel_long_running_tasks_on_connection_loss
    assert conf.worker_max_memory_per_child > 0 and conf.task_track_started
    assert conf.task_default_queue == "osdar_ar"
    assert conf.result_backend == "db+postgresql+psycopg://u@db/x"
    with pytest.raises(ValueError, match="visibility_timeout_s"):
        Settings(
            data_dir=tmp_path,
            task_time_limit_s=3600,
            task_soft_time_limit_s=3000,
            visibility_timeout_s=3700,
        )
    # the default limits keep the relation too, and every stage task is registered by name
    default = make_celery(Settings(data_dir=tmp_path, broker_url="redis://127.0.0.1:6379/0"))
    vt = default.conf.broker_transport_options["visibility_timeout"]
    assert vt > default.conf.task_time_limit + Settings().visibility_margin_s
    default.loader.import_default_modules()
    from worker.orchestration.tasks import TASK_NAMES

    assert set(TASK_NAMES) <= set(default.tasks)
    assert len(set(TASK_NAMES)) == 10 and all(n.startswith("osdar_ar.") for n in TASK_NAMES)
    # the SQLite broker's transport options are engine arguments (no visibility timeout)
    embedded = make_celery(Settings(data_dir=tmp_path)).conf
    assert "visibility_timeout" not in embedded.broker_transport_options
    assert embedded.result_backend == f"db+sqlite:///{tmp_path}/celery-results.db"


# ---------------------------------------------------------------------------- real workers
def _redis_or_skip() -> str:
    import redis

    try:
        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=2).ping()
    except Exception as exc:
        if os.environ.get("CI"):
            pytest.fail(f"Redis not reachable at {REDIS_URL}: {exc}")
        pytest.skip(f"Redis not reachable at {REDIS_URL}: {exc}")
    return REDIS_URL


@contextlib.contextmanager
def _worker(settings: Settings, log: Path, **kw: Any) -> Iterator[Any]:
    from worker.orchestration.embedded import start_worker, stop_worker

    proc = start_worker(settings, log_file=log, **kw)
    try:
        yield proc
    finally:
        stop_worker(proc)


def _submit(client: Any, headers: dict[str, str], seq_id: str) -> str:
    r = client.post("/v1/jobs", json=_spec(seq_id), headers=headers)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _poll_done(client: Any, headers: dict[str, str], job_id: str, log: Path) -> dict[str, Any]:
    def done() -> dict[str, Any] | None:
        job = client.get(f"/v1/jobs/{job_id}", headers=headers).json()
        return job if job["state"] in ("SUCCEEDED", "FAILED", "CANCELLED") else None

    try:
        return _wait(done, JOB_TIMEOUT_S, f"job {job_id}")
    except AssertionError:
        print(log.read_text()[-5000:] if log.is_file() else "no worker log")
        raise


@pytest.fixture
def redis_pg(tmp_path: Path) -> Iterator[Settings]:
    """Settings on Redis (a test DB number, flushed) and a fresh PostgreSQL schema."""
    import redis

    from tests.conftest_service import make_pg_schema

    url = _redis_or_skip()
    r = redis.Redis.from_url(url)
    r.flushdb()
    schemas = make_pg_schema("osdar_worker")
    pg = next(schemas)
    try:
        yield _settings(tmp_path, database_url=pg.url, broker_url=url)
    finally:
        r.flushdb()
        with contextlib.suppress(StopIteration):
            next(schemas)


def _api(settings: Settings) -> tuple[Any, dict[str, str], Any]:
    from fastapi.testclient import TestClient

    from osdar_platform.keys import create_api_key
    from service.app import create_app
    from worker.orchestration.celery_app import make_celery

    app = create_app(settings, celery_app=make_celery(settings))
    with session_scope(settings) as s:
        _, secret = create_api_key(
            session=s, name="w", pepper=settings.api_key_pepper.get_secret_value()
        )
    return TestClient(app), {"Authorization": f"Bearer {secret}"}, app


def _register(client: Any, headers: dict[str, str], folder: Path) -> str:
    r = client.post("/v1/sequences", json={"path": str(folder)}, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.mark.slow
def test_real_worker_on_redis_and_postgres(redis_pg: Settings, seq_folder: Path) -> None:
    settings = redis_pg
    log = Path(settings.data_dir) / "worker.log"
    client, headers, app = _api(settings)
    with client, _worker(settings, log, pool="prefork", concurrency=2):
        seq_id = _register(client, headers, seq_folder)
        ids = [_submit(client, headers, seq_id) for _ in range(2)]
        for job_id in ids:
            job = _poll_done(client, headers, job_id, log)
            assert job["state"] == "SUCCEEDED", job["error"]
            assert job["progress"]["done"] == job["progress"]["total"] == 4
            r = client.get(f"/v1/jobs/{job_id}/archive", headers=headers)
            assert r.status_code == 200 and r.content[:2] == b"\x1f\x8b"
            assert _archive_keys(app.state.store, job_id) == [
                f"jobs/{job_id}/attempt-1/archive.tar.gz"
            ]
    app.state.engine.dispose()


@pytest.mark.slow
def test_poison_job_fails_after_bounded_deliveries_and_the_queue_drains(
    redis_pg: Settings, seq_folder: Path
) -> None:
    from worker.orchestration.celery_app import make_celery
    from worker.orchestration.queue import enqueue_job

    settings = redis_pg
    log = Path(settings.data_dir) / "worker.log"
    client, headers, app = _api(settings)
    with client, _worker(settings, log, pool="prefork", concurrency=1):
        seq_id = _register(client, headers, seq_folder)
        with session_scope(settings) as s:
            owner = s.scalar(select(ApiKey.id).where(ApiKey.name == "w"))
        poison = _new_job(settings, owner, seq_id, crash_in="prepare")
        enqueue_job(poison, settings=settings, app=make_celery(settings))
        good = _submit(client, headers, seq_id)
        job = _poll_done(client, headers, poison, log)
        assert job["state"] == "FAILED"
        assert "worker died repeatedly (poison input?)" in job["error"]
        with session_scope(settings) as s:
            delivered = list(
                s.scalars(
                    select(JobEvent.message).where(
                        JobEvent.job_id == poison, JobEvent.kind == "stage_delivered"
                    )
                )
            )
        # prepare ran (and killed its worker) max_deliveries times; the next was refused
        assert delivered.count("prepare") == settings.max_deliveries + 1
        job = _poll_done(client, headers, good, log)
        assert job["state"] == "SUCCEEDED", job["error"]
        assert _archive_keys(app.state.store, poison) == []
    app.state.engine.dispose()


# ---------------------------------------------------------------------------- (c) embedded
@pytest.mark.slow
def test_embedded_sqlite_broker_worker(tmp_path: Path, seq_folder: Path) -> None:
    import httpx

    from osdar_platform.keys import create_api_key
    from worker.orchestration.embedded import Embedded

    settings = _settings(tmp_path / "var")
    with Embedded(settings, log_file=tmp_path / "worker.log") as emb:
        with session_scope(settings) as s:
            pepper = settings.api_key_pepper.get_secret_value()
            _, secret = create_api_key(session=s, name="e", pepper=pepper)
        auth = {"Authorization": f"Bearer {secret}"}
        with httpx.Client(base_url=emb.url, headers=auth, timeout=30) as http:
            seq_id = _register(http, {}, seq_folder)
            job_id = _submit(http, {}, seq_id)
            job = _poll_done(http, {}, job_id, tmp_path / "worker.log")
            assert job["state"] == "SUCCEEDED", job["error"]
            assert job["metrics"]["evaluation"]["strategy"] == "ins"
            r = http.get(f"/v1/jobs/{job_id}/archive")
            assert r.status_code == 200
            (tmp_path / "a.tar.gz").write_bytes(r.content)
            with tarfile.open(tmp_path / "a.tar.gz") as tar:
                assert f"{seq_folder.name}/metrics.json" in tar.getnames()
            assert _archive_keys(emb.app.state.store, job_id) == [
                f"jobs/{job_id}/attempt-1/archive.tar.gz"
            ]
            assert http.get(f"/v1/jobs/{job_id}/previews").status_code == 200
    assert emb.worker.returncode is not None
