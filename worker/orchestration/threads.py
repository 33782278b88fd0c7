"""Thread caps for worker processes: one core's worth of threads per process.

numpy's BLAS, OpenMP (open3d, KISS-ICP), OpenCV and Mesa's llvmpipe each start a thread per
core in every process. With ``--concurrency N`` on C cores, N worker processes each running C
threads oversubscribe the machine: on 2 cores, 2 worker processes ran a batch of 40-frame
jobs only 1.06-1.29 times faster than one, the evaluate stage taking 2.9-3.6 s per job
instead of 1.3 (``scripts/bench_throughput.py``); with the caps below, 1.60 times faster.

A lone worker process (``--concurrency 1``) keeps every core: the second thread is worth
little but not nothing. A 24-variant campaign with one process ran 9.9 variants/min with
2 threads against 9.4 with 1 (load 2.9-4.7, the bench alone on the machine) and 7.2
against 5.8 beside other work (load 5.0) (``scripts/bench_campaign_throughput.py
--one-threads 0,1``). One thread would make the 2-process / 1-process ratio look better
(1.74 instead of 1.66) by making one process slower. Several worker services on one
machine, each started with ``--concurrency 1``, do not know of each other: set
``OMP_NUM_THREADS`` (etc., :data:`THREAD_VARS`) yourself there; a variable set is kept.
"""

from __future__ import annotations

import os

#: Environment variables that size the thread pools of the libraries the workers use.
THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "LP_NUM_THREADS",
    # OpenCV's own pool (pthreads) reads none of the above. Uncapped, each of 2 worker
    # processes on 2 cores kept a second OpenCV thread that the frames' cv2 calls woke
    # 120-170 times a second for almost no work (0.01 CPU s in 5 s) and that waited
    # 1.7-2.1 s of those 5 s for a CPU (schedstat, load 4-5); capped, the children's
    # threads besides the main and llvmpipe ones waited 0.30-0.40 threads on average over
    # a campaign instead of 1.19-1.41 (scripts/bench_campaign_throughput.py's thread
    # split). CPU per variant did not measurably change (3.57-3.70 s against 3.69-3.74).
    "OPENCV_FOR_THREADS_NUM",
)


def thread_caps(concurrency: int | None, environ: dict[str, str] | None = None) -> dict[str, str]:
    """The thread variables to set for ``concurrency`` worker processes on this machine:
    ``max(1, cores // concurrency)`` each (``None``: Celery's default, one per core), leaving
    any the user already set (in ``environ``, default ``os.environ``) alone."""
    env = os.environ if environ is None else environ
    cores = os.cpu_count() or 1
    n = max(1, cores // max(1, concurrency or cores))
    return {k: str(n) for k in THREAD_VARS if k not in env}


def thread_budget(most: int = 4) -> int:
    """Threads a process may run its own work in (a pool of Python threads around
    GIL-releasing calls: open3d's ICP, scipy's KD-trees): its thread cap
    (``OMP_NUM_THREADS``, set for worker processes by :func:`thread_caps`) or else its
    cores, at most ``most``."""
    cap = os.environ.get("OMP_NUM_THREADS", "").strip()
    n = int(cap) if cap.isdigit() and int(cap) > 0 else (os.cpu_count() or 1)
    return max(1, min(n, most))
