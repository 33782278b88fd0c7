"""``osdar-ar info``: validate a sequence folder and summarise it."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("info", help="validate an OSDaR23 sequence folder and summarise it")
    p.add_argument("sequence", type=Path)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(command_group="info")
