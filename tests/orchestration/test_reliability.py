"""RELIABILITY.md's scenarios, reduced form (``make reliability`` runs the full form).

Each scenario is a module of ``scripts/reliability/`` whose ``run(workdir, quick=True)``
returns its figures; these tests assert on them. They need this machine's Redis and
PostgreSQL (skipped without them, failed under CI). ``redis_restart`` stops and starts the
machine's Redis. ``OSDAR_FULL=1`` adds the full forms (marked slow).

Fast checks of the pieces come first: the Celery/settings relations, the store retries,
the reaper on a stale row, and the alembic stdout fix.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _scenario(name: str, tmp_path: Path, quick: bool = True, **kw: Any) -> dict[str, Any]:
    from scripts.reliability import common

    mod = importlib.import_module(f"scripts.reliability.{name}")
    try:
        figures = common.loaded(mod.run, tmp_path, quick=quick, **kw)
    except common.Unavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(str(exc))
        pytest.skip(str(exc))
    common.report(name, {k: v for k, v in figures.items() if k not in ("records", "outcomes")})
    # the figures as JSON: pytest would cut a dict short, and they are the diagnosis
    assert mod.ok(figures), json.dumps(figures, default=str)
    return figures


# ---------------------------------------------------------------------------- config
def test_visibility_timeout_exceeds_the_longest_task_time_limit(tmp_path: Path) -> None:
    from osdar_platform.retry import backoff_delays
    from osdar_platform.settings import Settings
    from scripts.reliability.common import reliability_settings
    from worker.orchestration.celery_app import make_celery
    from worker.orchestration.reaper import stale_after_s

    for settings in (
        Settings(data_dir=tmp_path, broker_url="redis://127.0.0.1:6379/0"),  # the defaults
        reliability_settings(tmp_path, broker_url="redis://127.0.0.1:6379/0"),
    ):
        conf = make_celery(settings).conf
        vt = conf.broker_transport_options["visibility_timeout"]
        # every task has the same limits (none overrides them): the global ones are the longest
        from worker.orchestration import tasks

        for name in tasks.TASK_NAMES:
            t = getattr(tasks, name.split(".")[1], None)
            if t is not None:
                assert getattr(t, "time_limit", None) in (None, conf.task_time_limit)
        assert vt >= conf.task_time_limit + settings.visibility_margin_s
        assert conf.result_backend_transport_options["visibility_timeout"] == vt
        assert 1 <= conf.broker_transport_options["unacked_restore_interval"] <= vt
        # the reaper never calls a live task stale; a store outage is retried within a stage
        assert stale_after_s(settings) >= conf.task_time_limit
        retry_budget = (
            sum(
                backoff_delays(
                    settings.store_retries, settings.store_retry_base_s, settings.store_retry_max_s
                )
            )
            * 1.25
        )
        assert retry_budget < conf.task_soft_time_limit


# ---------------------------------------------------------------------------- retries
class _Flaky:
    def __init__(self, failures: int) -> None:
        self.failures = failures
        self.calls = 0
        self.objects: dict[str, bytes] = {}

    def put_bytes(self, key: str, data: bytes) -> None:
        from osdar_platform.store import StoreError

        self.calls += 1
        if self.calls <= self.failures:
            raise StoreError("connection refused")
        self.objects[key] = data

    def size(self, key: str) -> int:
        from osdar_platform.store import ObjectNotFound

        self.calls += 1
        raise ObjectNotFound(key)


def test_store_calls_retry_with_exponential_backoff(monkeypatch: pytest.MonkeyPatch) -> None:
    from osdar_platform import retry
    from osdar_platform.store import ObjectNotFound, StoreError

    slept: list[float] = []
    monkeypatch.setattr(retry.time, "sleep", slept.append)
    seen: list[tuple[str, int]] = []
    flaky = _Flaky(failures=4)
    store = retry.RetryingStore(
        flaky, retries=6, base=0.5, cap=3.0, on_retry=lambda op, key, n, d, e: seen.append((op, n))
    )
    store.put_bytes("a/b", b"x")
    assert flaky.objects == {"a/b": b"x"} and flaky.calls == 5
    assert seen == [("put_bytes", n) for n in (1, 2, 3, 4)]
    nominal = retry.backoff_delays(4, 0.5, 3.0)
    assert nominal == [0.5, 1.0, 2.0, 3.0]
    assert all(0.75 * n <= s <= 1.25 * n for s, n in zip(slept, nominal, strict=True))
    # bounded: gives up after the retries; an absent object is an answer, never retried
    with pytest.raises(StoreError):
        retry.RetryingStore(_Flaky(failures=99), retries=2, base=0.01, cap=0.01).put_bytes("k", b"")
    flaky = _Flaky(failures=0)
    with pytest.raises(ObjectNotFound):
        retry.RetryingStore(flaky, retries=5, base=0.01, cap=0.01).size("k")
    assert flaky.calls == 1


def test_an_outage_past_the_retry_budget_fails_saying_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """The budget bounds the time as well as the attempts: with 10 retries allowed but a
    20 s budget, a store away for good is given up after the tries that fit, and the
    error says how long, against which budget; one that comes back within it is fine."""
    from osdar_platform import retry
    from osdar_platform.store import StoreError

    now = [0.0]

    def sleep(s: float) -> None:
        now[0] += s

    kw = dict(what="put_bytes", key="k", retries=10, base=1.0, cap=8.0, budget_s=20.0)
    calls = []

    def down() -> None:
        calls.append(now[0])
        raise StoreError("connection refused")

    # the message rounds the time given up after (19.5 s reads "20 s"); calls[-1] bounds it
    given_up = r"unavailable for (1\d|20) s \(budget 20 s"
    with pytest.raises(retry.StoreUnavailable, match=given_up) as e:
        retry.call_with_retries(down, sleep=sleep, clock=lambda: now[0], **kw)
    assert isinstance(e.value, StoreError) and "connection refused" in str(e.value)
    # tries at 0, 1, 3, 7, 15 s (+-25 % jitter per delay): the 6th fits when the jitter is
    # low (17.25 s at 0.75), never a 7th (it would start at 23.25 s or later)
    assert 5 <= len(calls) <= 6 and calls[-1] <= 20.0
    back = iter([StoreError("refused")] * 3 + [None])

    def flaky() -> str:
        err = next(back)
        if err is not None:
            raise err
        return "ok"

    assert retry.call_with_retries(flaky, sleep=sleep, clock=lambda: now[0], **kw) == "ok"


def test_a_failed_store_call_reads_as_such_in_the_job_error() -> None:
    from osdar_platform.retry import StoreUnavailable
    from worker.orchestration.runner import describe_error

    msg = describe_error(
        "publish", StoreUnavailable("object store unavailable for 121 s (budget 120 s")
    )
    assert msg.startswith("publish: object store unavailable for 121 s") and "internal" not in msg


# ---------------------------------------------------------------------------- reaper
def test_reaper_requeues_a_stale_running_job_and_fails_it_at_the_delivery_bound(
    tmp_path: Path,
) -> None:
    from sqlalchemy import update

    from osdar_platform.db import session_scope
    from osdar_platform.migrate import upgrade
    from osdar_platform.models import ApiKey, Job, JobEvent, JobState, utcnow
    from osdar_platform.settings import Settings
    from tests.conftest_service import memory_celery, sent_tasks
    from worker.orchestration.reaper import reap

    settings = Settings(
        data_dir=tmp_path,
        task_time_limit_s=60,
        task_soft_time_limit_s=50,
        visibility_margin_s=10,
        visibility_timeout_s=70,
    )
    upgrade(database_url=str(settings.database_url))
    with session_scope(settings) as s:
        key = ApiKey(name="k", key_hash="h" * 64, prefix="p")
        s.add(key)
        s.flush()
        jobs = [
            Job(owner_id=key.id, spec={}, state=JobState.RUNNING, attempt=1, deliveries=d)
            for d in (1, 3, 1)
        ]
        s.add_all(jobs)
        s.flush()
        ids = [j.id for j in jobs]
    old = utcnow() - timedelta(seconds=71)  # older than the hard limit + margin
    with session_scope(settings) as s:
        s.execute(update(Job).where(Job.id.in_(ids[:2])).values(updated_at=old))
    app = memory_celery()
    sent_tasks()
    report = reap(settings, app)  # no leases, no broker identity (SQLite): the stale rule
    assert report.requeued == [ids[0]] and report.failed == [ids[1]]
    assert [t["id"] for t in sent_tasks()] == [ids[0]]
    with session_scope(settings) as s:
        rows = {j.id: j for j in s.query(Job)}
        kinds = {e.job_id: e.kind for e in s.query(JobEvent)}
    assert rows[ids[0]].state == JobState.QUEUED and rows[ids[0]].stage == "requeued"
    assert rows[ids[1]].state == JobState.FAILED and "poison" in rows[ids[1]].error
    assert rows[ids[2]].state == JobState.RUNNING  # recent heartbeat: left alone
    assert kinds == {ids[0]: "requeued", ids[1]: "failed"}
    # a second sweep (another worker's reaper) finds nothing to do
    assert reap(settings, app).requeued == [] and sent_tasks() == []


# ---------------------------------------------------------------------------- alembic
def test_alembic_writes_to_the_stdout_of_the_moment(monkeypatch: pytest.MonkeyPatch) -> None:
    """Alembic's Config bound sys.stdout at import: a closed pytest capture afterwards.
    The fix writes to whatever sys.stdout is when it writes (the whole-session form: the
    subprocess test below)."""
    import io

    from osdar_platform.migrate import alembic_config

    first = io.StringIO()
    monkeypatch.setattr(sys, "stdout", first)
    cfg = alembic_config(database_url="sqlite://")
    first.close()  # the capture of a test that has ended
    later = io.StringIO()
    monkeypatch.setattr(sys, "stdout", later)
    cfg.print_stdout("no new upgrade operations detected")
    assert later.getvalue() == "no new upgrade operations detected\n"


@pytest.mark.slow  # 3.5 s: a pytest session in a subprocess
def test_db_tests_pass_after_the_cli_tests_in_one_session() -> None:
    """Alembic's Config bound sys.stdout at import: a closed pytest capture afterwards."""
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "tests/cli/test_service_cli.py",
            "tests/platform/test_db_postgres.py",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode in (0, 5) and " failed" not in r.stdout, r.stdout[-3000:]


# ---------------------------------------------------------------------------- scenarios
def test_idempotency_100_concurrent_submissions_make_one_job(tmp_path: Path) -> None:
    f = _scenario("idempotency_burst", tmp_path, n=100)
    assert f["job_rows_with_key"] == 1 and f["status_codes"] == {200: 99, 201: 1}


def test_a_second_key_gets_404_on_every_object_of_the_first(tmp_path: Path) -> None:
    f = _scenario("authz_matrix", tmp_path)
    assert f["cross_key_404_percent"] == 100.0 and f["cross_key_requests"] >= 50


def test_413_reads_a_bounded_number_of_bytes_and_rate_limits_give_429(tmp_path: Path) -> None:
    f = _scenario("limits", tmp_path)
    assert f["sequence_upload_declared_bytes_read_by_app"] == 0 and f["rate_429"] > 0


@pytest.mark.slow
def test_hostile_uploads_refused_and_mutated_files_fail_cleanly(tmp_path: Path) -> None:
    f = _scenario("hostile_uploads", tmp_path)
    assert f["archive_attacks_refused_cleanly"] == f["archive_attacks"] >= 20
    assert f["api_5xx"] == 0 and f["worker_deaths"] == 0 and f["jobs_not_terminal"] == 0
    big = f["outcomes"]["file: png 50k x 50k header"]
    assert "50000 x 50000" in (big.get("reason") or "")


@pytest.mark.slow
def test_poison_job_fails_after_bounded_deliveries(tmp_path: Path) -> None:
    f = _scenario("poison", tmp_path)
    assert f["max_stage_deliveries_seen"] <= f["max_deliveries_setting"] + 1


@pytest.mark.slow
def test_sigkill_workers_at_random_points_loses_no_job(tmp_path: Path) -> None:
    f = _scenario("kill_workers", tmp_path)
    assert f["kills_by_kind"].get("worker") == 1 and f["attempts_total"] >= f["kills"]


@pytest.mark.slow
def test_sigkill_workers_during_a_campaign_loses_no_variant_and_makes_none_twice(
    tmp_path: Path,
) -> None:
    # unmarked reduced form: tests/campaign/test_service_campaigns.py (a redelivered
    # expansion, a failing variant, an idempotent submit, in process)
    f = _scenario("campaign_kill", tmp_path)
    assert f["kills_by_stage"] and f["variants_made"] == f["variant_job_rows"] == 4
    assert f["campaign_state"] == "PARTIAL" and f["submit_status_codes"] == {201: 1, 200: 19}


@pytest.mark.slow
def test_store_outage_during_publish_is_retried(tmp_path: Path) -> None:
    f = _scenario("store_outage", tmp_path)
    assert f["store_retries_total"] > 0 and f["partial_archives_visible"] == 0


@pytest.mark.slow
def test_redis_restart_mid_job_loses_no_job(tmp_path: Path) -> None:
    f = _scenario("redis_restart", tmp_path)
    assert f["jobs_lost"] == 0


@pytest.mark.slow
def test_postgres_restart_mid_job_loses_no_job_and_answers_503(tmp_path: Path) -> None:
    f = _scenario("db_restart", tmp_path)
    assert f["jobs_lost"] == 0 and f["api_answers_while_down"].get("503", 0) > 0


@pytest.mark.slow
def test_schemathesis_finds_no_server_error_and_no_auth_bypass(tmp_path: Path) -> None:
    f = _scenario("schemathesis_run", tmp_path)
    assert f["requests_answered"] > 100


@pytest.mark.slow
def test_polling_under_load_reports_latency_and_no_errors(tmp_path: Path) -> None:
    f = _scenario("load_poll", tmp_path)
    assert f["errors"] == 0 and f["latency_ms_p99"] > 0


FULL = [
    "idempotency_burst",
    "authz_matrix",
    "limits",
    "hostile_uploads",
    "poison",
    "kill_workers",
    "campaign_kill",
    "store_outage",
    "redis_restart",
    "db_restart",
    "schemathesis_run",
    "load_poll",
]


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("OSDAR_FULL"), reason="full form: OSDAR_FULL=1")
@pytest.mark.parametrize("name", FULL)
def test_full_form(tmp_path: Path, name: str) -> None:
    _scenario(name, tmp_path, quick=False)


def test_a_chunk_archive_of_another_worker_extracts(tmp_path: Path) -> None:
    """Found by kill_workers: a child killed in ``finish`` after the local chunk folders
    were removed makes the redelivery download the chunk tars, written with
    ``arcname="."``; their ``.`` member was refused ("empty name") and the job FAILED."""
    import tarfile

    from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive

    src = tmp_path / "chunk"
    (src / "rgb_center").mkdir(parents=True)
    (src / "rgb_center" / "000.png").write_bytes(b"png")
    with tarfile.open(tmp_path / "0000.tar", "w") as tar:  # as runner.augment_chunk does
        tar.add(src, arcname=".")
    limits = ArchiveLimits(max_members=100, max_total_bytes=2**20, max_name_length=512)
    res = extract_archive(tmp_path / "0000.tar", tmp_path / "out", limits)
    assert (tmp_path / "out" / "rgb_center" / "000.png").read_bytes() == b"png"
    assert res.total_bytes == 3
    # a "." that is not a directory is still refused
    info = tarfile.TarInfo(".")
    info.size = 1
    with tarfile.open(tmp_path / "bad.tar", "w") as tar:
        import io

        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(UnsafeArchive, match="empty name"):
        extract_archive(tmp_path / "bad.tar", tmp_path / "out2", limits)
