"""Worker lifecycle hooks: the reaper thread starts when a worker is ready and stops with it;
every worker process keeps its freed memory (``malloc_tuning.py``).

Loaded by every worker through the Celery app's ``include`` list (``celery_app.py``); the
API, which only sends tasks, never imports it.
"""

from __future__ import annotations

from typing import Any

from celery.signals import worker_process_init, worker_ready, worker_shutdown

from osdar_platform.settings import get_settings
from worker.orchestration.celery_app import celery_app
from worker.orchestration.malloc_tuning import tune_malloc
from worker.orchestration.reaper import start_reaper, stop_reaper


@worker_process_init.connect
def _tune_malloc(**_: Any) -> None:
    """A prefork child keeps its freed memory for the next frame (malloc_tuning.py)."""
    tune_malloc()


@worker_ready.connect
def _start_reaper(sender: Any = None, **_: Any) -> None:
    """Every worker sweeps for lost jobs at start and then periodically (reaper.py); a solo
    worker, which runs its tasks itself, keeps its freed memory (malloc_tuning.py)."""
    tune_malloc()

    app = getattr(sender, "app", None) or celery_app
    start_reaper(get_settings(), app)


@worker_shutdown.connect
def _stop_reaper(**_: Any) -> None:

    stop_reaper()
