"""``osdar-ar bench``: speed against error, hard cases, robustness matrix."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "bench",
        help="speed against error: the paper's table, knobs / Pareto front, I/O floor",
        description="Run the synthetic counterparts of the paper's three sequences with "
        "every strategy and print the paper's table with its numbers beside ours, the time "
        "per strategy, the speed-against-error table with its Pareto front and the I/O "
        "floor ratio; --hard runs the hard-case suite instead.",
    )
    p.add_argument("--quick", action="store_true", help="reduced run (CI): 20 frames, 2 strategies")
    p.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    p.add_argument("--hard", action="store_true", help="the 12 hard cases with their bounds")
    p.add_argument(
        "--matrix", action="store_true",
        help="the robustness matrix (scenes x lengths x densities x INS profiles x seeds, "
        "slow and standing trains; --quick: the 8 CI cells): per-strategy distributions, "
        "goals (ok / MISS), heatmap PNG",
    )  # fmt: skip
    p.add_argument(
        "--seed-offset", type=int, default=0, metavar="N",
        help="with --matrix: every cell's seed shifted by N (sequences the method was not "
        "developed on; default 0: the matrix's own seeds 0 and 1)",
    )  # fmt: skip
    p.add_argument(
        "--markdown", type=Path, default=None,
        help="write the figures as a markdown report (an existing report keeps its text above "
        "'## Figures'); with --report: from a saved JSON instead of a run",
    )  # fmt: skip
    p.add_argument(
        "--report", type=Path, default=None, metavar="JSON",
        help="run nothing: write --markdown from the JSON of an earlier `bench [--hard] --json`",
    )  # fmt: skip
    p.add_argument("--no-floor", action="store_true", help="skip the I/O floor measurement")
    p.add_argument(
        "--ins-profile", default="osdar23",
        help="synthetic INS of the sequences: osdar23 (default: wanders like the real INS), "
        "paper, good, perfect, hard",
    )  # fmt: skip
    p.add_argument(
        "--workdir", type=Path, default=Path("/tmp/osdar_bench"),
        help="generated sequences, per-frame CSVs, pareto.png (reused between runs)",
    )  # fmt: skip
    p.set_defaults(command_group="bench")
