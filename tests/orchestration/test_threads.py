"""Thread caps of the worker processes (worker/orchestration/threads.py)."""

from __future__ import annotations

import os
import subprocess
import sys

from worker.orchestration.threads import THREAD_VARS, thread_caps


def test_caps_split_the_cores_between_processes(monkeypatch) -> None:
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    assert thread_caps(2, {}) == {k: "4" for k in THREAD_VARS}
    assert thread_caps(3, {}) == {k: "2" for k in THREAD_VARS}
    assert thread_caps(16, {}) == {k: "1" for k in THREAD_VARS}  # never 0
    assert thread_caps(None, {}) == {k: "1" for k in THREAD_VARS}  # celery: one per core
    assert thread_caps(1, {}) == {k: "8" for k in THREAD_VARS}


def test_a_users_setting_is_kept(monkeypatch) -> None:
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    caps = thread_caps(2, {"OMP_NUM_THREADS": "3"})
    assert "OMP_NUM_THREADS" not in caps and caps["LP_NUM_THREADS"] == "1"


def test_a_cap_of_one_reaches_opencvs_own_pool() -> None:
    """OpenCV's pthreads pool reads none of the BLAS / OpenMP variables: its own is
    capped too (uncapped, OpenCV starts a thread per core in every worker process)."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    code = "import cv2; print(cv2.getNumThreads())"
    run = [sys.executable, "-c", code]
    one = subprocess.run(run, env={**env, **thread_caps(64, {})}, capture_output=True, text=True)
    assert one.stdout.strip() == "1", one.stderr
    two = subprocess.run(run, env={**env, "OPENCV_FOR_THREADS_NUM": "2"}, capture_output=True,
                         text=True)  # fmt: skip
    assert two.stdout.strip() == "2", two.stderr
