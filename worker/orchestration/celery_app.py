"""The Celery app of the workers, built from :class:`~osdar_platform.settings.Settings`.

Delivery is *at least once* (../shared/design/RELIABILITY.md); the settings below make
it so, and the job code (``runner.py``, ``state.py``) makes the effects exactly once:

- ``task_acks_late`` + ``task_reject_on_worker_lost``: a message is acknowledged after its
  task ran; a worker process that dies mid-task puts the message back (it is run again,
  and a job that keeps killing workers is FAILED after ``max_deliveries``);
- ``worker_prefetch_multiplier=1``: a worker reserves one long task at a time;
- ``task_time_limit`` / ``task_soft_time_limit``: a stuck stage is stopped (the soft limit
  raises in the task, which fails the job with a readable reason);
- ``visibility_timeout`` (Redis and SQS transports; the SQLite transport has none) above
  the hard time limit plus a margin - validated by Settings - or a long task would be
  delivered again while it still runs;
- ``worker_cancel_long_running_tasks_on_connection_loss``: a task whose message can no
  longer be acknowledged (broker connection lost) is cancelled: it will be redelivered;
- ``worker_max_memory_per_child``: prefork children are recycled above that resident size;
- the reaper (``reaper.py``, started by ``lifecycle.py``) runs in every worker once
  ready: jobs left RUNNING by a task stopped at the hard time limit, or whose messages a
  broker restart lost, are re-queued (or FAILED once delivered ``max_deliveries`` times).

Results: job state lives in our ``jobs`` table, and so does the join of a job's chunks of
frames (``chunk_join.py``; a chord on the database result backend was finished by
``celery.chord_unlock`` polling once a second). No task stores a result: they are
ignored everywhere, and the backend (the database, ``db+`` URL; SQLite gets its own
file) is only configured, never written.
"""

from __future__ import annotations

from typing import Any

from celery import Celery
from sqlalchemy.engine import make_url

from osdar_platform.settings import Settings, get_settings

#: The one queue of the service.
QUEUE = "osdar_ar"
#: How long a SQLite connection (broker, results) waits for a lock (s).
SQLITE_BUSY_TIMEOUT_S = 30
#: Results of the chunk tasks are kept this long (s); job state is in our table.
RESULT_EXPIRES_S = 7 * 24 * 3600


def result_backend_url(settings: Settings) -> str:
    """``db+`` URL of the result backend for ``settings.database_url``."""
    url = make_url(str(settings.database_url))
    if url.get_backend_name() == "sqlite":
        db = url.database or ""
        if db and db != ":memory:":
            return f"db+sqlite:///{db.rsplit('/', 1)[0] or '.'}/celery-results.db"
        return f"db+sqlite:///{settings.data_dir}/celery-results.db"
    if url.drivername in ("postgresql", "postgres"):
        url = url.set(drivername="postgresql+psycopg")
    return "db+" + url.render_as_string(hide_password=False)


def celery_config(settings: Settings) -> dict[str, Any]:
    """Celery settings for ``settings`` (module docstring)."""
    vt = int(settings.visibility_timeout_s)
    # kombu's Redis transport looks for expired unacked messages every interval x throttle
    # seconds (default 10 x 10): scan every vt/10 (1..60 s), so that a message of a killed
    # worker comes back soon after its visibility timeout, not up to 100 s later.
    broker_options: dict[str, Any] = {
        "visibility_timeout": vt,
        "unacked_restore_interval": max(1, min(60, vt // 10)),
        "unacked_restore_throttle": 1,
    }
    if str(settings.broker_url).startswith("sqla+"):
        # kombu's SQLAlchemy transport hands its transport options to create_engine() and
        # has no visibility timeout (a delivered message stays invisible until acked or
        # put back by the worker): only engine arguments belong here.
        broker_options = {"connect_args": {"timeout": SQLITE_BUSY_TIMEOUT_S}}
    backend = result_backend_url(settings)
    config: dict[str, Any] = {
        "broker_url": str(settings.broker_url),
        "broker_transport_options": broker_options,
        "broker_connection_retry_on_startup": True,
        "result_backend": backend,
        "result_backend_transport_options": {"visibility_timeout": vt},
        "result_expires": RESULT_EXPIRES_S,
        "result_extended": False,
        "task_ignore_result": True,  # every task: the job's state is in our tables
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "task_track_started": True,
        "task_time_limit": int(settings.task_time_limit_s),
        "task_soft_time_limit": int(settings.task_soft_time_limit_s),
        "worker_prefetch_multiplier": 1,
        "worker_cancel_long_running_tasks_on_connection_loss": True,
        "worker_max_memory_per_child": int(settings.worker_max_memory_per_child_kib),
        "task_default_queue": QUEUE,
        "task_routes": {"osdar_ar.*": {"queue": QUEUE}, "celery.*": {"queue": QUEUE}},
        "task_serializer": "json",
        "result_serializer": "json",
        "accept_content": ["json"],
        "worker_hijack_root_logger": False,
    }
    if backend.startswith("db+sqlite"):
        config["database_engine_options"] = {"connect_args": {"timeout": SQLITE_BUSY_TIMEOUT_S}}
    return config


def make_celery(settings: Settings | None = None, *, main: str = "osdar_ar") -> Celery:
    """A Celery app for ``settings`` (default: the environment's) with our tasks."""
    settings = settings or get_settings()
    # The tasks are shared tasks: every app built here (tests, embedded mode) has them;
    # a worker also loads the lifecycle hooks (the reaper thread).
    app = Celery(
        main,
        include=["worker.orchestration.tasks", "worker.orchestration.lifecycle"],
        set_as_current=False,
    )
    app.conf.update(celery_config(settings))
    return app


#: The process's app (``celery -A worker.orchestration.celery_app worker``; the API's sender).
celery_app = make_celery()
app = celery_app

__all__ = ["QUEUE", "app", "celery_app", "celery_config", "make_celery", "result_backend_url"]
