"""Embedded mode: the API and a worker on one machine, with nothing else to start.

SQLite for the database, the local file system for the store, and kombu's SQLAlchemy
transport on a SQLite file as the broker (``sqla+sqlite:///.../broker.db``): no server.
The API (uvicorn) runs in a thread of this process; the worker is a ``celery worker``
subprocess with the ``solo`` pool: tasks run in the worker's main thread, one at a
time, which is what the renderer's EGL contexts need (an OpenGL context belongs to the
thread that made it current; ``threads`` would hand a chunk to another thread). Both get
the same settings: the worker through ``OSDAR_AR_*`` environment variables
(:func:`settings_env`).

Used by ``osdar-ar demo`` and the tests::

    with Embedded(settings) as emb:
        httpx.get(emb.url + "/v1/health")
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import uvicorn
from pydantic import SecretStr

from osdar_platform.migrate import upgrade
from osdar_platform.settings import Settings
from service.app import create_app
from worker.orchestration.celery_app import QUEUE, make_celery
from worker.orchestration.threads import thread_caps

log = logging.getLogger(__name__)

STARTUP_TIMEOUT_S = 60.0


def embedded_settings(data_dir: str | Path, **overrides: Any) -> Settings:
    """Settings of the one-machine mode under ``data_dir`` whatever the environment says."""
    data = Path(data_dir).resolve()
    values: dict[str, Any] = {
        "data_dir": data,
        "database_url": f"sqlite:///{data}/osdar-ar.db",
        "broker_url": f"sqla+sqlite:///{data}/broker.db",
        "store_url": f"file://{data}/store",
        "cache_dir": data / "cache",
        "sequences_dir": data / "sequences",
    }
    values.update(overrides)
    return Settings(**values)


def settings_env(settings: Settings) -> dict[str, str]:
    """``OSDAR_AR_<FIELD>`` variables that rebuild ``settings`` in another process."""
    env: dict[str, str] = {}
    for name in type(settings).model_fields:
        value = getattr(settings, name)
        if value is None:
            continue
        if isinstance(value, SecretStr):
            value = value.get_secret_value()
        if isinstance(value, list | dict):
            text = json.dumps([str(v) for v in value] if isinstance(value, list) else value)
        else:
            text = str(value)
        env[f"OSDAR_AR_{name.upper()}"] = text
    return env


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def worker_command(
    *, pool: str = "solo", concurrency: int = 1, loglevel: str = "INFO"
) -> list[str]:
    """The ``celery worker`` command line of our app and queue."""
    return [
        sys.executable,
        "-m",
        "celery",
        "-A",
        "worker.orchestration.celery_app",
        "worker",
        "--pool",
        pool,
        "--concurrency",
        str(concurrency),
        "--queues",
        QUEUE,
        "--loglevel",
        loglevel,
        "--without-gossip",
        "--without-mingle",
        "--without-heartbeat",
    ]


def start_worker(
    settings: Settings,
    *,
    pool: str = "solo",
    concurrency: int = 1,
    log_file: str | Path | None = None,
    extra_env: dict[str, str] | None = None,
) -> subprocess.Popen[bytes]:
    """A ``celery worker`` subprocess configured by ``settings``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("OSDAR_AR_")}
    for plain in ("DATABASE_URL", "BROKER_URL", "STORE_URL"):
        env.pop(plain, None)
    env.update(settings_env(settings))
    env.update(thread_caps(concurrency, env))
    env.update(extra_env or {})
    out: Any = subprocess.DEVNULL
    if log_file is not None:
        Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        out = open(log_file, "ab")
    root = Path(__file__).resolve().parents[2]
    try:
        return subprocess.Popen(
            worker_command(pool=pool, concurrency=concurrency),
            env=env,
            cwd=root,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    finally:
        if out is not subprocess.DEVNULL:
            out.close()


def stop_worker(proc: subprocess.Popen[bytes], timeout_s: float = 15.0) -> None:
    """Warm shutdown (SIGTERM: unacknowledged messages go back), then SIGKILL."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)


class Embedded:
    """The API (a uvicorn thread) and a worker (a subprocess) for ``settings``."""

    def __init__(
        self,
        settings: Settings,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        pool: str = "solo",
        concurrency: int = 1,
        log_file: str | Path | None = None,
        migrate: bool = True,
    ) -> None:
        self.settings = settings
        self.host = host
        self.port = port or free_port(host)
        self.pool = pool
        self.concurrency = concurrency
        self.log_file = log_file
        self.migrate = migrate
        self.worker: subprocess.Popen[bytes] | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self.app: Any = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self) -> Embedded:

        if self.migrate:
            upgrade(database_url=str(self.settings.database_url))
        self.worker = start_worker(
            self.settings, pool=self.pool, concurrency=self.concurrency, log_file=self.log_file
        )
        self.app = create_app(self.settings, celery_app=make_celery(self.settings))
        config = uvicorn.Config(
            self.app, host=self.host, port=self.port, log_level="warning", lifespan="on"
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="api", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the API did not start on {self.url}")
            if self.worker.poll() is not None:
                self.stop()
                raise RuntimeError(f"the worker exited at start (see {self.log_file})")
            time.sleep(0.05)
        log.info("API on %s, worker pid %d", self.url, self.worker.pid)
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(10)
        if self.worker is not None:
            stop_worker(self.worker)
        if self.app is not None:
            self.app.state.engine.dispose()

    def __enter__(self) -> Embedded:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = [
    "Embedded",
    "embedded_settings",
    "free_port",
    "settings_env",
    "start_worker",
    "stop_worker",
    "worker_command",
]
