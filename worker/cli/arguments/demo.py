"""``osdar-ar demo``: the job service embedded, one job end to end."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "demo",
        help="run the job service embedded and one job end to end on a synthetic sequence",
        description="Start the API and a worker (SQLite, local store, a SQLite broker: no "
        "server), make a synthetic sequence, submit a job over HTTP and poll it, download "
        "and check the archive, print the metrics and the dashboard's address. Everything "
        "is kept under --workdir.",
    )
    p.add_argument("--workdir", type=Path, default=Path("demo_out"))
    p.add_argument("--scene", default="fire_site")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--lidar-density", type=float, default=0.25)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="API port (0: any free port)")
    p.add_argument(
        "--serve", action="store_true", help="keep the API and worker running until Ctrl-C"
    )
    p.set_defaults(command_group="demo")
