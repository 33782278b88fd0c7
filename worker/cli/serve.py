"""``osdar-ar serve`` (the API under uvicorn) and ``osdar-ar worker`` (a Celery worker)."""

from __future__ import annotations

import argparse
import os

import uvicorn

from osdar_platform.migrate import upgrade
from osdar_platform.settings import get_settings
from worker.orchestration.celery_app import QUEUE, celery_app
from worker.orchestration.threads import thread_caps


def serve(args: argparse.Namespace) -> int:
    if not args.no_migrate:
        upgrade(database_url=str(get_settings().database_url))
    uvicorn.run("service.app:app", host=args.host, port=args.port, workers=args.workers)
    return 0


def worker(args: argparse.Namespace) -> int:
    # Before anything imports numpy: the prefork children inherit the caps. Nothing
    # imported so far has (tests/cli/test_cli_package.py).
    os.environ.update(thread_caps(args.concurrency))
    argv = ["worker", "--pool", args.pool, "--queues", QUEUE, "--loglevel", args.loglevel]
    if args.concurrency is not None:
        argv += ["--concurrency", str(args.concurrency)]
    if args.hostname:
        argv += ["--hostname", args.hostname]
    celery_app.worker_main(argv)
    return 0


def run(args: argparse.Namespace) -> int:
    return worker(args) if args.command == "worker" else serve(args)
