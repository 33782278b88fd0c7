"""The pieces the throughput benches share (scripts/bench_throughput.py for jobs,
scripts/bench_campaign_throughput.py for campaigns): a fresh database (SQLite, or a fresh
PostgreSQL schema) and store, a Redis broker on a DB number of the bench's own (flushed),
a real ``celery worker --pool prefork --concurrency N`` subprocess, the API in-process;
polling until jobs end, the CPU seconds of the worker's process tree, the stage seconds of
the jobs, and the machine's load averages beside every figure (the machine is shared).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
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
            "LP_NUM_THREADS": n, "OPENCV_FOR_THREADS_NUM": n}  # fmt: skip


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


#: Clock ticks per second of /proc/<pid>/stat's utime / stime.
_HZ = os.sysconf("SC_CLK_TCK")


def _proc_stat(path: str) -> tuple[str, float] | None:
    """(comm, user + system CPU seconds) of ``/proc/<pid>[/task/<tid>]/stat``."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    head, _, rest = text.rpartition(")")
    fields = rest.split()  # fields[0] is the state (the stat's 3rd field)
    return head.split("(", 1)[1], (int(fields[11]) + int(fields[12])) / _HZ


def _machine_busy_s() -> tuple[float, float]:
    """(busy, all) CPU seconds of the machine since boot, all cores (/proc/stat)."""
    user, nice, system, idle, iowait, irq, softirq, steal = (
        int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]
    )
    busy = user + nice + system + irq + softirq + steal
    return busy / _HZ, (busy + idle + iowait) / _HZ


class CpuSplit:
    """Who had the machine's cores during a window, robust to other work on it: a thread
    samples every ``interval_s`` the CPU seconds (/proc/<pid>/stat, user + system) of the
    worker's children, the celery parent, this process (the bench's polling thread apart
    from the in-process API's threads), Redis, and the machine's busy time (/proc/stat);
    "other" is the machine's busy time less those (other sessions' work, the kernel).
    A process that exits between samples keeps its last sample (its last second is lost).
    """

    def __init__(self, proc: Any, interval_s: float = 1.0) -> None:
        self.proc = proc
        self.interval_s = interval_s
        self.redis = [p.pid for p in psutil.process_iter(["name"])
                      if (p.info["name"] or "").startswith("redis-server")]  # fmt: skip
        self._main_tid = threading.get_native_id()
        self._first: dict[tuple[str, int], float] = {}
        self._last: dict[tuple[str, int], float] = {}
        self._threads: dict[tuple[int, int], tuple[str, float, float]] = {}
        self._threads_last: dict[tuple[int, int], tuple[str, float, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="cpu-split", daemon=True)
        self._busy0 = self._busy1 = (0.0, 0.0)
        self._t0 = self._t1 = 0.0
        self._series: list[tuple[float, float, float]] = []  # (time, busy s, total s)

    def _sample(self) -> None:
        try:
            children = [c.pid for c in psutil.Process(self.proc.pid).children(recursive=True)]
        except psutil.NoSuchProcess:
            children = []
        seen: dict[tuple[str, int], float] = {}
        for kind, pids in (("child", children), ("parent", [self.proc.pid]),
                           ("redis", self.redis)):  # fmt: skip
            for pid in pids:
                s = _proc_stat(f"/proc/{pid}/stat")
                if s is not None:
                    seen[(kind, pid)] = s[1]
        me = os.getpid()
        for task in Path(f"/proc/{me}/task").iterdir():
            tid = int(task.name)
            s = _proc_stat(f"{task}/stat")
            if s is not None:
                kind = "bench-poll" if tid == self._main_tid else "bench-api"
                seen[("bench-sampler" if s[0] == "cpu-split" else kind, tid)] = s[1]
        for pid in children:  # per thread of the worker children (name, CPU, runqueue wait)
            for task in Path(f"/proc/{pid}/task").glob("*"):
                s = _proc_stat(f"{task}/stat")
                try:
                    wait = int((task / "schedstat").read_text().split()[1]) / 1e9
                except (OSError, ValueError, IndexError):
                    continue
                if s is not None:
                    key = (pid, int(task.name))
                    if key not in self._threads and self._t1:  # born in the window
                        self._threads[key] = (s[0], 0.0, 0.0)
                    first = self._threads.setdefault(key, (s[0], s[1], wait))
                    self._threads_last[key] = (s[0], s[1] - first[1], wait - first[2])
        for key, v in seen.items():
            if key not in self._first:
                self._first[key] = 0.0 if self._t1 else v  # born in the window: from 0
            self._last[key] = v
        self._t1 = time.perf_counter()
        self._busy1 = _machine_busy_s()
        self._series.append((self._t1, *self._busy1))

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def __enter__(self) -> CpuSplit:
        self._t0 = time.perf_counter()
        self._busy0 = _machine_busy_s()
        self._sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()

    @property
    def wall_s(self) -> float:
        return self._t1 - self._t0

    def cores(self) -> dict[str, float]:
        """Cores used on average over the window by kind: ``child`` (the worker processes
        together), ``parent``, ``bench-poll``, ``bench-api``, ``bench-sampler``, ``redis``,
        ``other`` (the machine's busy time less these) and ``idle``."""
        out: dict[str, float] = {}
        for key, last in self._last.items():
            out[key[0]] = out.get(key[0], 0.0) + (last - self._first[key]) / self.wall_s
        busy = (self._busy1[0] - self._busy0[0]) / self.wall_s
        total = (self._busy1[1] - self._busy0[1]) / self.wall_s
        out["other"] = busy - sum(out.values())
        out["idle"] = total - busy
        return out

    def threads(self) -> list[tuple[str, int, float, float]]:
        """The worker children's threads by name: (name, how many, cores on a CPU, threads
        runnable waiting for a CPU), summed over the children, busiest first."""
        by: dict[str, list[float]] = {}
        for name, on, wait in self._threads_last.values():
            name = name.rstrip("0123456789:-") or name
            acc = by.setdefault(name, [0.0, 0.0, 0.0])
            acc[0] += 1
            acc[1] += on / self.wall_s
            acc[2] += wait / self.wall_s
        return sorted(((n, int(a[0]), a[1], a[2]) for n, a in by.items()), key=lambda x: -x[2])

    def main_threads(self) -> tuple[float, float, float]:
        """The worker children's main threads (the tasks' code), as threads on average
        over the window: (on a CPU, runnable waiting for one, neither: sleeping - waiting
        for a task, I/O, a lock, the llvmpipe thread's rendering). Summed over the
        children (with 2 children they add up to 2)."""
        on = wait = 0.0
        n = 0
        for (pid, tid), (_, t_on, t_wait) in self._threads_last.items():
            if pid == tid:
                on, wait, n = on + t_on, wait + t_wait, n + 1
        w = self.wall_s
        return on / w, wait / w, max(0.0, n - (on + wait) / w) if n else 0.0

    def demand(self) -> float:
        """Threads of the worker children that wanted a CPU (on one or runnable waiting
        for one) on average: their main threads and their llvmpipe threads (the main
        thread sleeps while its llvmpipe thread renders). On a machine of their own they
        would have used at most ``min(cores, demand)`` cores (the waits would turn into
        CPU time; the sleeps would stay)."""
        w = self.wall_s
        wanting = [on + wait for (pid, tid), (name, on, wait) in self._threads_last.items()
                   if pid == tid or name.startswith("llvmpipe")]  # fmt: skip
        return sum(wanting) / w

    def idle_by_part(self, parts: int = 10) -> list[float]:
        """The machine's idle cores in each of ``parts`` equal parts of the window (from the
        once-a-second samples): whether the idle time is the start, the end or spread."""
        if len(self._series) < 2:
            return []
        t = np.array([x[0] for x in self._series])
        busy = np.array([x[1] for x in self._series])
        total = np.array([x[2] for x in self._series])
        edges = np.linspace(t[0], t[-1], parts + 1)
        out = []
        for a, b in itertools.pairwise(edges):
            ba, bb = (np.interp(x, t, busy) for x in (a, b))
            ta, tb = (np.interp(x, t, total) for x in (a, b))
            out.append(float(((tb - ta) - (bb - ba)) / (b - a)))
        return out

    def line(self) -> str:
        c = self.cores()
        order = ("child", "parent", "bench-poll", "bench-api", "bench-sampler", "redis",
                 "other", "idle")  # fmt: skip
        names = {"child": "worker processes", "parent": "celery parent"}
        return ", ".join(f"{names.get(k, k)} {c.get(k, 0.0):.2f}" for k in order)


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
    proc_log: Path

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
                yield Service(settings, client, headers, proc, log)
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
    "CpuSplit",
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
