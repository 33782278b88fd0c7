"""The harness of the reliability scenarios: real servers, real workers, figures.

Every scenario (one script each, ``python -m scripts.reliability.<name> [--quick]``)
runs against the servers of this machine on loopback: PostgreSQL (a fresh schema in the
``test`` database, dropped afterwards), Redis (database 12, flushed), prefork
``celery worker`` subprocesses, and the API under uvicorn in a thread. Each returns a dict
of figures (printed as a table and one JSON line) that ``tests/orchestration/test_reliability.py``
asserts on in the reduced (``quick``) form.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import psutil
import redis
import uvicorn
from sqlalchemy import create_engine, select, text
from sqlalchemy.engine import make_url

from osdar_platform.db import _engine_for, session_scope
from osdar_platform.keys import create_api_key
from osdar_platform.migrate import upgrade
from osdar_platform.models import Job, JobEvent
from service.app import create_app
from worker.orchestration.celery_app import make_celery
from worker.orchestration.embedded import embedded_settings, free_port, start_worker, stop_worker
from worker.synth.generator import SynthConfig, generate

REDIS_URL = os.environ.get("OSDAR_AR_RELIABILITY_REDIS_URL", "redis://127.0.0.1:6379/12")
PG_CANDIDATES = (
    os.environ.get("OSDAR_AR_TEST_PG_URL", ""),
    "postgresql+psycopg://postgres@127.0.0.1:5432/test",
    "postgresql+psycopg://root@127.0.0.1:5432/test",
)
#: The Redis server of REDIS_URL's port: the machine's (6379), or one of the run's own
#: (another port, e.g. when other runs share this machine's Redis and would restart it).
REDIS_PORT = urlsplit(REDIS_URL).port or 6379
_OWN_REDIS = REDIS_PORT != 6379
REDIS_START = [
    "redis-server",
    "--daemonize",
    "yes",
    "--bind",
    "127.0.0.1",
    *(() if _OWN_REDIS else ("-::1",)),
    "--port",
    str(REDIS_PORT),
    "--save",
    "",
    "--appendonly",
    "no",
    "--dir",
    tempfile.gettempdir() if _OWN_REDIS else "/var/lib/redis",
    "--logfile",
    f"{tempfile.gettempdir()}/redis-{REDIS_PORT}.log" if _OWN_REDIS else "/var/log/redis/ci.log",
]
TERMINAL = ("SUCCEEDED", "FAILED", "CANCELLED")


class Unavailable(RuntimeError):
    """A server the scenario needs is not reachable (tests skip, scripts exit 2)."""


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)  # noqa: T201


# ---------------------------------------------------------------------------- servers
def pg_admin_url() -> Any:

    errors = []
    for raw in filter(None, PG_CANDIDATES):
        url = make_url(raw)
        engine = create_engine(url, connect_args={"connect_timeout": 3})
        try:
            with engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            return url
        except Exception as exc:
            errors.append(str(exc).splitlines()[0])
        finally:
            engine.dispose()
    raise Unavailable("PostgreSQL not reachable: " + "; ".join(errors))


@contextlib.contextmanager
def pg_database(prefix: str = "osdar_rel") -> Iterator[str]:
    """A fresh, migrated schema in the test database (its URL); dropped at the end."""

    admin = pg_admin_url()
    schema = f"{prefix}_{uuid.uuid4().hex[:10]}"
    engine = create_engine(admin, pool_pre_ping=True)  # db_restart restarts the server
    with engine.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    url = admin.update_query_dict({"options": f"-csearch_path={schema}"})
    rendered = url.render_as_string(hide_password=False)
    try:
        upgrade(database_url=rendered)
        yield rendered
    finally:
        _engine_for.cache_clear()
        with engine.begin() as conn:
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        engine.dispose()


def redis_client(url: str = REDIS_URL) -> Any:

    return redis.Redis.from_url(url, socket_connect_timeout=2, socket_timeout=5)


def redis_up(url: str = REDIS_URL) -> bool:
    try:
        return bool(redis_client(url).ping())
    except Exception:
        return False


@contextlib.contextmanager
def redis_db(url: str = REDIS_URL) -> Iterator[str]:
    if not redis_up(url):
        raise Unavailable(f"Redis not reachable at {url}")
    redis_client(url).flushdb()
    try:
        yield url
    finally:
        with contextlib.suppress(Exception):
            redis_client(url).flushdb()


def redis_stop() -> None:
    subprocess.run(
        ["redis-cli", "-p", str(REDIS_PORT), "shutdown", "nosave"], capture_output=True, timeout=20
    )
    wait_for(lambda: not redis_up(), 20, "Redis to stop")


def redis_start() -> None:
    if not redis_up():
        subprocess.run(REDIS_START, capture_output=True, timeout=20, check=False)
    wait_for(redis_up, 20, "Redis to start")


def _pg_cluster() -> list[str]:
    version = sorted(os.listdir("/etc/postgresql"))[-1]
    return ["pg_ctlcluster", "--skip-systemctl-redirect", version, "main"]


def pg_up() -> bool:
    try:
        pg_admin_url()
        return True
    except Unavailable:
        return False


def pg_stop() -> None:
    """Stop the machine's PostgreSQL (fast shutdown: sessions are cut, as in a crash of
    the clients' view)."""
    subprocess.run([*_pg_cluster(), "stop", "-m", "fast"], capture_output=True, timeout=60)
    wait_for(lambda: not pg_up(), 30, "PostgreSQL to stop")


def pg_start() -> None:
    if not pg_up():
        subprocess.run([*_pg_cluster(), "start"], capture_output=True, timeout=60, check=False)
    wait_for(pg_up, 60, "PostgreSQL to start")


# ---------------------------------------------------------------------------- helpers
def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str, every: float = 0.2) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise TimeoutError(f"timed out after {timeout_s:.0f}s waiting for {what}")


def synth_sequence(folder: Path, frames: int = 4) -> Path:
    """A small synthetic OSDaR23 sequence (made once per folder)."""

    if not (folder / "ground_truth" / "meta.json").is_file():
        generate(
            folder, SynthConfig(scene="fire_site", frames=frames, scale=0.05, lidar_density=0.05)
        )
    return folder


def reliability_settings(data_dir: Path, **overrides: Any) -> Any:
    """Settings of the scenarios: environment "test", short limits, no API throttling."""

    values: dict[str, Any] = {
        "environment": "test",
        "frames_per_chunk": 2,
        "rate_limit_per_s": 100_000,
        "rate_limit_burst": 1_000_000,
        "max_concurrent_jobs_per_key": 100_000,
        # short limits, so that lost messages come back within the scenario
        "task_time_limit_s": 60,
        "task_soft_time_limit_s": 50,
        "visibility_margin_s": 5,
        "visibility_timeout_s": 65,
        "reaper_interval_s": 2,
        "reaper_orphan_grace_s": 5,
        # a killed worker's job is re-queued ~10 s after its last renewal
        "lease_ttl_s": 10,
        "lease_renew_s": 2,
        "store_retry_base_s": 0.5,
        "store_retry_max_s": 8,
        "store_retries": 6,
    }
    values.update(overrides)
    return embedded_settings(data_dir, **values)


def new_api_key(settings: Any, name: str = "rel") -> str:

    with session_scope(settings) as s:
        _, secret = create_api_key(
            session=s, name=name, pepper=settings.api_key_pepper.get_secret_value()
        )
    return secret


def job_spec(sequence_id: str, **overrides: Any) -> dict[str, Any]:
    spec: dict[str, Any] = {
        "sequence_id": sequence_id,
        "cameras": ["rgb_center", "rgb_highres_center"],
        "lidar": True,
        "object": {"builtin": "person", "scale": 1.0},
        "placement": {"mode": "track", "s": 5.0, "offset": 0.0, "yaw_deg": 90.0},
        "strategy": "ins",
    }
    spec.update(overrides)
    return spec


def job_rows(settings: Any, ids: list[str]) -> dict[str, Any]:

    with session_scope(settings) as s:
        return {j.id: j for j in s.scalars(select(Job).where(Job.id.in_(ids)))}


def job_events(settings: Any, job_id: str) -> list[Any]:

    with session_scope(settings) as s:
        return list(
            s.scalars(select(JobEvent).where(JobEvent.job_id == job_id).order_by(JobEvent.id))
        )


def wait_terminal(settings: Any, ids: list[str], timeout_s: float) -> dict[str, Any]:
    """Rows of ``ids`` once all are terminal, or at the deadline (some still active)."""
    deadline = time.monotonic() + timeout_s
    rows = job_rows(settings, ids)
    while time.monotonic() < deadline:
        rows = job_rows(settings, ids)
        if all(r.state.value in TERMINAL for r in rows.values()):
            break
        time.sleep(0.5)
    return rows


def archive_keys(store: Any, job_id: str) -> list[str]:
    return [k for k in store.list(f"jobs/{job_id}/") if k.endswith("archive.tar.gz")]


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    v = sorted(values)
    i = min(len(v) - 1, max(0, round(q / 100 * (len(v) - 1))))
    return v[i]


# ---------------------------------------------------------------------------- processes
_STARTED: list[subprocess.Popen[bytes]] = []


@atexit.register
def _kill_leftovers() -> None:
    """Workers run in their own session: never leave one consuming after we exit."""
    for proc in _STARTED:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)


@dataclass
class Workers:
    """Prefork ``celery worker`` subprocesses for ``settings`` (restartable, killable)."""

    settings: Any
    log_file: Path
    concurrency: int = 1
    procs: list[subprocess.Popen[bytes]] = field(default_factory=list)
    deaths_seen: int = 0

    def start(self) -> subprocess.Popen[bytes]:

        proc = start_worker(
            self.settings, pool="prefork", concurrency=self.concurrency, log_file=self.log_file
        )
        self.procs.append(proc)
        _STARTED.append(proc)
        wait_for(lambda: self.children(proc) or proc.poll() is not None, 60, "worker children")
        if proc.poll() is not None:
            raise RuntimeError(f"worker exited at start, see {self.log_file}")
        return proc

    @staticmethod
    def children(proc: subprocess.Popen[bytes]) -> list[int]:

        try:
            return [c.pid for c in psutil.Process(proc.pid).children()]
        except psutil.NoSuchProcess:
            return []

    def alive(self) -> list[subprocess.Popen[bytes]]:
        return [p for p in self.procs if p.poll() is None]

    def kill_child(self, rng: Any) -> int | None:
        """SIGKILL one pool process of a live worker (its parent forks another)."""
        for proc in self.alive():
            kids = self.children(proc)
            if kids:
                pid = rng.choice(kids)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
                return pid
        return None

    def kill_worker(self, proc: subprocess.Popen[bytes] | None = None) -> int | None:
        """SIGKILL a whole worker (parent and children: its process group), like an OOM kill
        of its container; a new worker is started in its place."""
        proc = proc or (self.alive() or [None])[0]
        if proc is None:
            return None
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        return proc.pid

    def stop(self) -> None:

        for proc in self.procs:
            stop_worker(proc, timeout_s=20)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)  # stray children of a killed parent

    def log_count(self, pattern: str) -> int:
        if not self.log_file.is_file():
            return 0
        return len(re.findall(pattern, self.log_file.read_text(errors="replace")))

    def deaths(self) -> int:
        """Pool processes that died (the parent logs each once) plus workers that exited."""
        lost = self.log_count(r"Process 'ForkPoolWorker-\d+' pid:\d+ exited with")
        return lost + sum(1 for p in self.procs if p.poll() not in (None, 0, -15))

    def __enter__(self) -> Workers:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ApiServer:
    """The API under uvicorn in a thread of this process, on a free loopback port."""

    def __init__(self, settings: Any, celery_app: Any = None, **uvicorn_kw: Any) -> None:

        self.settings = settings
        self.celery_app = celery_app
        self.port = free_port()
        self.uvicorn_kw = uvicorn_kw
        self.app: Any = None
        self._server: Any = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> ApiServer:

        celery = self.celery_app if self.celery_app is not None else make_celery(self.settings)
        self.app = create_app(self.settings, celery_app=celery)
        config = uvicorn.Config(
            self.app,
            host="127.0.0.1",
            port=self.port,
            log_level="error",
            lifespan="on",
            **self.uvicorn_kw,
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="api", daemon=True)
        self._thread.start()
        wait_for(lambda: self._server.started, 30, "the API to start", every=0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(15)
        self.app.state.engine.dispose()

    def client(self, secret: str | None = None, **kw: Any) -> Any:

        headers = {"Authorization": f"Bearer {secret}"} if secret else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=kw.pop("timeout", 60), **kw)


# ---------------------------------------------------------------------------- load
class CpuHog:
    """``processes`` busy-looping processes beside a scenario, as a loaded cluster node
    has: timing races that an idle machine hides show up under it."""

    def __init__(self, processes: int = 1) -> None:
        self.processes = max(0, processes)
        self.procs: list[subprocess.Popen[bytes]] = []

    def __enter__(self) -> CpuHog:
        for _ in range(self.processes):
            self.procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
        if self.procs:
            log(f"{len(self.procs)} CPU hog process(es) running")
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait(10)
        self.procs.clear()


def hog_processes(quick: bool) -> int:
    """The scenarios' CPU hog: one process in the reduced form (CI), one per core in full."""
    return 1 if quick else os.cpu_count() or 2


def loaded(run: Callable[..., dict[str, Any]], workdir: Path, *, quick: bool, **kw: Any) -> Any:
    """``run(workdir, quick=quick, **kw)`` beside the CPU hog (every scenario, both forms:
    a user's cluster is a loaded machine); its figures say how many hog processes ran."""
    hogs = hog_processes(quick)
    with CpuHog(hogs):
        figures = run(workdir, quick=quick, **kw)
    return {**figures, "cpu_hog_processes": hogs}


class ResultPoller:
    """A client polling each watched job's archive, then its state, as a client waiting
    for its result would. An archive served while the state read AFTER it is not
    SUCCEEDED is premature (SUCCEEDED is terminal, so a state read after the archive
    cannot be older than the archive; read before it, it could be, and a job finishing
    between the two reads was once miscounted as premature)."""

    def __init__(self, http: Any, *, store_up: Callable[[], bool] = lambda: True) -> None:
        self.http = http
        self.store_up = store_up
        self.watched: list[str] = []
        self.premature = 0
        self.served = 0
        self.five_xx = 0
        self.transport_errors = 0
        self.polls = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.is_set():
            for jid in list(self.watched):
                try:
                    a = self.http.get(f"/v1/jobs/{jid}/archive", headers={"Range": "bytes=0-1"})
                    r = self.http.get(f"/v1/jobs/{jid}")
                except httpx.TransportError:  # a keep-alive connection closed by the server
                    self.transport_errors += 1
                    continue
                self.polls += 1
                self.five_xx += r.status_code >= 500
                self.five_xx += a.status_code >= 500 and self.store_up()
                state = r.json().get("state") if r.status_code == 200 else None
                if a.status_code in (200, 206):
                    self.served += 1
                    self.premature += state != "SUCCEEDED"
            self._stop.wait(0.2)

    def __enter__(self) -> ResultPoller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    def figures(self) -> dict[str, int]:
        return {
            "api_archive_before_success": self.premature,
            "poller_archives_served": self.served,
            "poller_polls": self.polls,
        }


# ---------------------------------------------------------------------------- CLI
def parser(doc: str | None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=(doc or "").splitlines()[0] if doc else None)
    p.add_argument("--quick", action="store_true", help="the reduced form CI runs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workdir", type=Path, default=None, help="scratch (default: a temp dir)")
    return p


@contextlib.contextmanager
def workdir(path: Path | None, name: str) -> Iterator[Path]:

    if path is not None:
        path.mkdir(parents=True, exist_ok=True)
        yield path
        return
    tmp = Path(tempfile.mkdtemp(prefix=f"osdar-rel-{name}-"))
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def report(name: str, figures: dict[str, Any]) -> None:
    """The figures as a table and one JSON line (``FIGURES {...}``) on stdout."""
    print(f"== {name} ==")  # noqa: T201
    width = max(len(k) for k in figures) if figures else 0
    for k, v in figures.items():
        if isinstance(v, float):
            v = f"{v:.3f}"
        elif isinstance(v, list | dict):
            v = json.dumps(v, default=str)
            v = v if len(v) < 300 else v[:297] + "..."
        print(f"  {k:<{width}}  {v}")  # noqa: T201
    print("FIGURES " + json.dumps({"scenario": name, **figures}, default=str), flush=True)  # noqa: T201


def main(
    name: str,
    run: Callable[..., dict[str, Any]],
    doc: str | None,
    ok: Callable[[dict[str, Any]], bool],
) -> int:
    """Parse --quick/--seed/--workdir, run, print the figures; exit 1 if not ``ok``."""
    args = parser(doc).parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run atexit (kill workers)
    try:
        with workdir(args.workdir, name) as wd:
            figures = loaded(run, wd, quick=args.quick, seed=args.seed)
    except Unavailable as exc:
        print(f"{name}: skipped: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    report(name, figures)
    good = ok(figures)
    print(f"{name}: {'PASS' if good else 'FAIL'}")  # noqa: T201
    return 0 if good else 1
