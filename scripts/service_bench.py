"""The pieces the throughput benches share (scripts/bench_throughput.py for jobs,
scripts/bench_campaign_throughput.py for campaigns): a fresh database (SQLite, or a fresh
PostgreSQL schema) and store, a Redis broker on a DB number of the bench's own (flushed),
a real ``celery worker --pool prefork --concurrency N`` subprocess, the API in-process;
polling until jobs end, the CPU seconds of the worker's process tree, the stage seconds of
the jobs, and the machine's load averages beside every figure (the machine is shared).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
import redis
from fastapi.testclient import TestClient

from osdar_platform.migrate import upgrade
from osdar_platform.settings import Settings
from scripts.reliability.common import new_api_key, pg_database
from service.app import create_app
from worker.orchestration.celery_app import make_celery
from worker.orchestration.embedded import embedded_settings, start_worker, stop_worker

TERMINAL = ("SUCCEEDED", "FAILED", "CANCELLED")
#: The API's limits out of the way: a bench submits everything at once.
UNTHROTTLED: dict[str, Any] = {
    "rate_limit_per_s": 10_000,
    "rate_limit_burst": 100_000,
    "max_concurrent_jobs_per_key": 10_000,
}


def thread_env(threads: int) -> dict[str, str]:
    """Environment capping each worker process's BLAS / OpenMP / llvmpipe threads at
    ``threads`` (0: the workers' own caps, worker/orchestration/threads.py)."""
    if threads <= 0:
        return {}
    n = str(threads)
    return {"OMP_NUM_THREADS": n, "OPENBLAS_NUM_THREADS": n, "MKL_NUM_THREADS": n,
            "LP_NUM_THREADS": n}  # fmt: skip


def load_averages() -> str:
    """``uptime``'s load averages (1, 5, 15 min): the machine is shared with other work."""
    one, five, fifteen = os.getloadavg()
    return f"load {one:.2f} {five:.2f} {fifteen:.2f}"


def tree_cpu_s(proc: Any) -> float:
    """User + system CPU seconds of a process and its live children (psutil)."""
    total = 0.0
    try:
        root = psutil.Process(proc.pid)
        for p in [root, *root.children(recursive=True)]:
            try:
                t = p.cpu_times()
                total += t.user + t.system
            except psutil.NoSuchProcess:
                pass
    except psutil.NoSuchProcess:
        pass
    return total


def tree_sched_s(proc: Any) -> tuple[float, float]:
    """(seconds on a CPU, seconds runnable but waiting for one) of every thread of a
    process and its live children, from Linux's ``/proc/<pid>/task/<tid>/schedstat``: the
    second is the CPU the machine's other work took from the workers (0, 0 elsewhere)."""
    on = wait = 0.0
    try:
        root = psutil.Process(proc.pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return on, wait
    for p in procs:
        for task in Path(f"/proc/{p.pid}/task").glob("*/schedstat"):
            try:
                run_ns, wait_ns, _ = task.read_text().split()
            except (OSError, ValueError):
                continue
            on, wait = on + int(run_ns) / 1e9, wait + int(wait_ns) / 1e9
    return on, wait


@contextlib.contextmanager
def database(data: Path, kind: str) -> Iterator[str]:
    """A fresh, migrated database: ``sqlite`` (a file under ``data``) or ``postgres`` (a
    schema of its own in the test database, dropped at the end); yields its URL."""
    if kind == "postgres":
        with pg_database("osdar_bench") as url:
            yield url
        return
    url = f"sqlite:///{data}/osdar-ar.db"
    upgrade(database_url=url)
    yield url


@dataclass
class Service:
    """The API client (one key) and a worker subprocess of ``workers`` processes."""

    settings: Settings
    client: Any
    headers: dict[str, str]
    proc: Any

    def post(self, path: str, body: dict[str, Any]) -> dict[str, Any]:
        r = self.client.post(path, json=body, headers=self.headers)
        if r.status_code >= 300:
            raise RuntimeError(f"POST {path}: {r.status_code} {r.text[:2000]}")
        out: dict[str, Any] = r.json()
        return out

    def get(self, path: str, **params: Any) -> dict[str, Any]:
        r = self.client.get(path, headers=self.headers, params=params)
        r.raise_for_status()
        out: dict[str, Any] = r.json()
        return out

    def job(self, job_id: str) -> dict[str, Any]:
        return self.get(f"/v1/jobs/{job_id}")

    def wait_jobs(self, ids: list[str], timeout_s: float) -> None:
        """Until every job ended; raises if one did not succeed or time ran out."""
        deadline = time.monotonic() + timeout_s
        pending = set(ids)
        while pending and time.monotonic() < deadline:
            for job_id in list(pending):
                job = self.job(job_id)
                if job["state"] in TERMINAL:
                    if job["state"] != "SUCCEEDED":
                        raise RuntimeError(f"job {job_id} ended {job['state']}: {job['error']}")
                    pending.discard(job_id)
            time.sleep(0.25)
        if pending:
            raise RuntimeError(f"{len(pending)} jobs still running after {timeout_s} s")

    def register(self, folder: Path) -> str:
        return str(self.post("/v1/sequences", {"path": str(folder)})["id"])

    def cpu_s(self) -> float:
        return tree_cpu_s(self.proc)

    def sched_s(self) -> tuple[float, float]:
        return tree_sched_s(self.proc)


@contextlib.contextmanager
def service(
    data: Path,
    workers: int,
    *,
    redis_url: str,
    db: str = "sqlite",
    threads: int = 0,
    **overrides: Any,
) -> Iterator[Service]:
    """A fresh service under ``data`` with a prefork worker of ``workers`` processes on the
    Redis DB ``redis_url`` (flushed before and after)."""
    redis.Redis.from_url(redis_url).flushdb()
    data.mkdir(parents=True, exist_ok=True)
    with database(data, db) as url:
        settings = embedded_settings(
            data, database_url=url, broker_url=redis_url, **{**UNTHROTTLED, **overrides}
        )
        app = create_app(settings, celery_app=make_celery(settings))
        headers = {"Authorization": f"Bearer {new_api_key(settings, 'bench')}"}
        log = data / "worker.log"
        proc = start_worker(settings, pool="prefork", concurrency=workers, log_file=log,
                            extra_env=thread_env(threads))  # fmt: skip
        try:
            with TestClient(app) as client:
                yield Service(settings, client, headers, proc)
        finally:
            stop_worker(proc)
            app.state.engine.dispose()
            redis.Redis.from_url(redis_url).flushdb()


def stage_seconds(svc: Service, ids: list[str]) -> dict[str, float]:
    """Mean seconds per job of each stage (chunks summed: ``augment[0]``, ... count as
    ``augment``), from the jobs' timings."""
    stages: dict[str, float] = {}
    for job_id in ids:
        for name, sec in (svc.job(job_id)["timings"] or {}).items():
            key = name.split("[")[0]
            stages[key] = stages.get(key, 0.0) + float(sec)
    return {k: v / len(ids) for k, v in sorted(stages.items())}


def stage_line(stages: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.2f}" for k, v in stages.items())


__all__ = [
    "Service",
    "database",
    "load_averages",
    "service",
    "stage_line",
    "stage_seconds",
    "thread_env",
    "tree_cpu_s",
    "tree_sched_s",
]
