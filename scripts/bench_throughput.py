# ruff: noqa: T201 (a script: prints its table)
"""Throughput of a batch of jobs with 1 and with 2 worker processes (ARCHITECTURE.md).

Per worker count, in one run: a fresh database (SQLite) and store, a Redis broker (a test
DB number, flushed), a real ``celery worker --pool prefork --concurrency N`` subprocess,
the API in-process (scripts/service_bench.py); one warm-up job (fills the preparation
cache, which every later job on the same sequence reuses), then a batch of jobs submitted
at once over the API; the batch's wall time from the first submission to the last job
finished. Prints jobs per minute for each worker count and the ratio.

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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scripts.service_bench import (
    load_averages,
    service,
    stage_line,
    stage_seconds,
)
from worker.synth.generator import SynthConfig, generate

REDIS_URL = "redis://127.0.0.1:6379/11"


def _spec(seq_id: str) -> dict[str, Any]:
    return {
        "sequence_id": seq_id,
        "cameras": ["rgb_center", "rgb_highres_center"],
        "lidar": True,
        "object": {"builtin": "person", "scale": 1.0},
        "placement": {"mode": "track", "s": 5.0, "offset": 0.0, "yaw_deg": 90.0},
        "strategy": "ins",
    }


def run_batch(
    seq_folder: Path, workers: int, jobs: int, root: Path, args: argparse.Namespace
) -> tuple[float, float]:
    """(seconds, busy cores) for a batch of ``jobs`` on a worker with ``workers`` processes.

    Busy cores = CPU seconds of the worker's process tree during the batch / its wall time
    (prefork children live for the whole run, so their counters cover the batch)."""
    with service(root / f"w{workers}", workers, redis_url=args.redis_url, db=args.db,
                 threads=args.threads, frames_per_chunk=5) as svc:  # fmt: skip
        seq_id = svc.register(seq_folder)
        warm = svc.post("/v1/jobs", _spec(seq_id))["id"]
        svc.wait_jobs([warm], 600)
        cpu0, t0 = svc.cpu_s(), time.perf_counter()
        ids = [svc.post("/v1/jobs", _spec(seq_id))["id"] for _ in range(jobs)]
        svc.wait_jobs(ids, 1800)
        wall = time.perf_counter() - t0
        cores = (svc.cpu_s() - cpu0) / wall
        stages = stage_line(stage_seconds(svc, ids))
        print(f"{workers} worker(s), stage seconds per job: {stages} ({load_averages()})")
        return wall, cores


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=6)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--redis-url", default=REDIS_URL, help="a Redis DB this run may flush")
    ap.add_argument("--db", choices=("sqlite", "postgres"), default="sqlite")
    ap.add_argument(
        "--threads", type=int, default=0,
        help="threads per worker process (0: the workers' own caps)",
    )  # fmt: skip
    args = ap.parse_args()

    root = Path(tempfile.mkdtemp(prefix="osdar_throughput_"))
    try:
        seq = generate(
            root / "fire_site",
            SynthConfig(scene="fire_site", frames=args.frames, scale=0.1, lidar_density=0.2),
        ).folder
        seconds = {w: run_batch(seq, w, args.jobs, root, args) for w in (1, 2)}
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
