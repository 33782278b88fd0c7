# ruff: noqa: T201 (a script: prints its table)
"""Throughput of a batch of jobs with 1 and with 2 worker processes (ARCHITECTURE.md).

Per worker count, in one run: a fresh database (SQLite) and store, a Redis broker (a test
DB number, flushed), a real ``celery worker --pool prefork --concurrency N`` subprocess,
the API in-process; one warm-up job (fills the preparation cache, which every later job
on the same sequence reuses), then a batch of jobs submitted at once over the API; the
batch's wall time from the first submission to the last job finished. Prints jobs per
minute for each worker count and the ratio.

    .venv/bin/python scripts/bench_throughput.py [--jobs 6] [--frames 10]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import redis
from fastapi.testclient import TestClient

from osdar_platform.db import session_scope
from osdar_platform.keys import create_api_key
from osdar_platform.migrate import upgrade
from service.app import create_app
from worker.orchestration.celery_app import make_celery
from worker.orchestration.embedded import embedded_settings, start_worker, stop_worker
from worker.synth.generator import SynthConfig, generate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REDIS_URL = "redis://127.0.0.1:6379/11"
#: Environment of the worker processes (``--threads N`` caps each process's BLAS / OpenMP /
#: llvmpipe threads).
THREAD_ENV: dict[str, str] = {}


def _spec(seq_id: str) -> dict[str, Any]:
    return {
        "sequence_id": seq_id,
        "cameras": ["rgb_center", "rgb_highres_center"],
        "lidar": True,
        "object": {"builtin": "person", "scale": 1.0},
        "placement": {"mode": "track", "s": 5.0, "offset": 0.0, "yaw_deg": 90.0},
        "strategy": "ins",
    }


def _wait_all(client: Any, headers: dict[str, str], ids: list[str], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    pending = set(ids)
    while pending and time.monotonic() < deadline:
        for job_id in list(pending):
            state = client.get(f"/v1/jobs/{job_id}", headers=headers).json()["state"]
            if state in ("SUCCEEDED", "FAILED", "CANCELLED"):
                if state != "SUCCEEDED":
                    raise RuntimeError(f"job {job_id} ended {state}")
                pending.discard(job_id)
        time.sleep(0.25)
    if pending:
        raise RuntimeError(f"{len(pending)} jobs still running after {timeout_s} s")


def _tree_cpu_s(proc: Any) -> float:
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


def run_batch(seq_folder: Path, workers: int, jobs: int, root: Path) -> tuple[float, float]:
    """(seconds, busy cores) for a batch of ``jobs`` on a worker with ``workers`` processes.

    Busy cores = CPU seconds of the worker's process tree during the batch / its wall time
    (prefork children live for the whole run, so their counters cover the batch)."""

    redis.Redis.from_url(REDIS_URL).flushdb()
    data = root / f"w{workers}"
    settings = embedded_settings(
        data,
        broker_url=REDIS_URL,
        frames_per_chunk=5,
        rate_limit_per_s=10_000,
        rate_limit_burst=100_000,
        max_concurrent_jobs_per_key=10_000,
    )
    upgrade(database_url=str(settings.database_url))
    app = create_app(settings, celery_app=make_celery(settings))
    with session_scope(settings) as s:
        _, secret = create_api_key(
            session=s, name="bench", pepper=settings.api_key_pepper.get_secret_value()
        )
    headers = {"Authorization": f"Bearer {secret}"}
    proc = start_worker(
        settings, pool="prefork", concurrency=workers, log_file=data / "w.log",
        extra_env=THREAD_ENV,
    )  # fmt: skip
    try:
        with TestClient(app) as client:
            r = client.post("/v1/sequences", json={"path": str(seq_folder)}, headers=headers)
            r.raise_for_status()
            seq_id = r.json()["id"]
            warm = client.post("/v1/jobs", json=_spec(seq_id), headers=headers).json()["id"]
            _wait_all(client, headers, [warm], 600)
            cpu0, t0 = _tree_cpu_s(proc), time.perf_counter()
            ids = [
                client.post("/v1/jobs", json=_spec(seq_id), headers=headers).json()["id"]
                for _ in range(jobs)
            ]
            _wait_all(client, headers, ids, 1800)
            wall = time.perf_counter() - t0
            cores = (_tree_cpu_s(proc) - cpu0) / wall
            stages: dict[str, list[float]] = {}
            for job_id in ids:
                timings = client.get(f"/v1/jobs/{job_id}", headers=headers).json()["timings"]
                for name, sec in (timings or {}).items():
                    stages.setdefault(name.split("[")[0], []).append(float(sec))
            summary = ", ".join(f"{k} {sum(v) / len(ids):.2f}" for k, v in sorted(stages.items()))
            print(f"{workers} worker(s), stage seconds per job: {summary}")
            return wall, cores
    finally:
        stop_worker(proc)
        app.state.engine.dispose()
        redis.Redis.from_url(REDIS_URL).flushdb()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=6)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--redis-url", default=REDIS_URL, help="a Redis DB this run may flush")
    ap.add_argument(
        "--threads", type=int, default=0,
        help="threads per worker process (0: the workers' own caps)",
    )  # fmt: skip
    args = ap.parse_args()
    globals()["REDIS_URL"] = args.redis_url
    if args.threads > 0:
        n = str(args.threads)
        THREAD_ENV.update(
            OMP_NUM_THREADS=n, OPENBLAS_NUM_THREADS=n, MKL_NUM_THREADS=n, LP_NUM_THREADS=n
        )

    root = Path(tempfile.mkdtemp(prefix="osdar_throughput_"))
    try:
        seq = generate(
            root / "fire_site",
            SynthConfig(scene="fire_site", frames=args.frames, scale=0.1, lidar_density=0.2),
        ).folder
        seconds = {w: run_batch(seq, w, args.jobs, root) for w in (1, 2)}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    for w, (s, cores) in seconds.items():
        print(
            f"{w} worker process(es): {args.jobs} jobs in {s:.1f} s = "
            f"{60 * args.jobs / s:.1f} jobs/min, {cores:.2f} cores busy"
        )
    print(f"throughput ratio 2 / 1 workers: {seconds[1][0] / seconds[2][0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
