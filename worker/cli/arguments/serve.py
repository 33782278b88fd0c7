"""``osdar-ar serve`` (the API) and ``osdar-ar worker`` (a Celery worker)."""

from __future__ import annotations

import argparse


def _add_serve(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "serve",
        help="run the API (uvicorn); migrates the database first unless --no-migrate",
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1, help="uvicorn worker processes")
    p.add_argument("--no-migrate", action="store_true", help="skip alembic upgrade head")
    p.set_defaults(command_group="serve")


def _add_worker(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "worker",
        help="run a Celery worker for the configured broker (BROKER_URL)",
        description="A Celery worker on the osdar_ar queue. Start as many as you like, on "
        "as many machines (they share DATABASE_URL, BROKER_URL and STORE_URL).",
    )
    p.add_argument("--concurrency", type=int, default=None, help="default: number of CPUs")
    p.add_argument("--pool", choices=["prefork", "solo", "threads"], default="prefork")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--hostname", default=None, help="worker node name (default celery@host)")
    p.set_defaults(command_group="serve")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """The sub-commands ``serve`` and ``worker``."""
    _add_serve(sub)
    _add_worker(sub)
