"""``osdar-ar bench``: the paper's table, speed against error, the I/O floor; the hard
cases (``--hard``) or the robustness matrix (``--matrix``)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from worker.bench.matrix import design, format_summary, run_and_report
from worker.bench.report import write_bench_markdown
from worker.bench.run import FULL, QUICK, run_bench
from worker.cli.errors import CliError
from worker.cli.progress import progress_bar


def _bench_matrix(args: argparse.Namespace) -> int:
    if args.seed_offset < 0:
        raise CliError(f"bench --seed-offset {args.seed_offset}: must be 0 or more")
    bar = progress_bar(len(design(args.quick, args.seed_offset)), "robustness matrix")
    bar.unit = "cell"

    def progress(done: int, total: int, name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(done - bar.n)

    try:
        result = run_and_report(
            args.workdir / "matrix", quick=args.quick, json_path=args.json,
            markdown_path=args.markdown, progress=progress, seed_offset=args.seed_offset,
        )  # fmt: skip
        bar.update(bar.total - bar.n)
    finally:
        bar.close()
    print(format_summary(result))  # noqa: T201 - CLI output
    for kind, path in result["outputs"].items():
        print(f"{kind}: {path}")  # noqa: T201 - CLI output
    return 1 if result["failed_cells"] else 0


def _report(args: argparse.Namespace) -> int:
    if args.markdown is None:
        raise CliError("bench --report needs --markdown OUT.md (where to write the report)")
    try:
        result = json.loads(Path(args.report).read_text())
    except (OSError, ValueError) as exc:
        raise CliError(f"bench --report {args.report}: not a readable bench JSON ({exc})") from exc
    if not isinstance(result, dict) or not ("rows" in result or "hard_cases" in result):
        raise CliError(
            f"bench --report {args.report}: no 'rows' or 'hard_cases' (the JSON of "
            "`osdar-ar bench [--hard] --json`; a matrix report is written by --matrix itself)"
        )
    print(f"markdown: {write_bench_markdown(result, args.markdown)}")  # noqa: T201 - CLI output
    return 0


def run(args: argparse.Namespace) -> int:
    if args.report is not None:
        return _report(args)
    if args.matrix:
        return _bench_matrix(args)
    settings = replace(QUICK if args.quick else FULL, ins_profile=args.ins_profile)
    result = run_bench(
        quick=args.quick, workdir=args.workdir, json_path=args.json, hard=args.hard,
        floor=not args.no_floor, settings=settings,
    )  # fmt: skip
    if args.markdown is not None:
        print(f"markdown: {write_bench_markdown(result, args.markdown)}")  # noqa: T201 - CLI output
    if args.hard:
        return 0 if all(c["ok"] for c in result["hard_cases"]) else 1
    return 0
