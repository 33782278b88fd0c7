"""``osdar-ar info``: validate a sequence folder and summarise it."""

from __future__ import annotations

import argparse
import json

from worker.osdar.summary import summarize


def run(args: argparse.Namespace) -> int:
    summary = summarize(args.sequence)
    if args.json:
        print(json.dumps(summary, indent=1))  # noqa: T201 - CLI output
    else:
        for k, v in summary.items():
            print(f"{k:>16}: {v}")  # noqa: T201 - CLI output
    return 0
