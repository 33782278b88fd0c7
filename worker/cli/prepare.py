"""``osdar-ar prepare``: pipeline step 2 on a sequence, the artifact copied to OUT, and the
true pose errors where the sequence has ground truth."""

from __future__ import annotations

import argparse
import json
from typing import Any

from pydantic import ValidationError

from osdar_platform.settings import get_settings
from worker.cli.errors import CliError
from worker.cli.progress import progress_bar
from worker.evaluation.pose_error import pose_error_rows
from worker.evaluation.tables import pose_error_table
from worker.preparation.artifact import copy_artifact, write_artifact
from worker.preparation.calibration_point import ClicksError
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import STAGES, PreparationError, prepare


def _prepare_config(args: argparse.Namespace) -> PrepareConfig:
    data: dict[str, Any] = {}
    if args.config is not None:
        try:
            data = json.loads(args.config.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CliError(f"--config {args.config}: {exc}") from exc
    data["strategy"] = args.strategy
    if args.voxel_size is not None:
        data["registration"] = {**data.get("registration", {}), "voxel_size": args.voxel_size}
    try:
        return PrepareConfig.model_validate(data)
    except ValidationError as exc:
        msgs = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'config'}: {e['msg']}" for e in exc.errors()
        )
        raise CliError(msgs) from exc


def run(args: argparse.Namespace) -> int:
    config = _prepare_config(args)
    cache_dir = args.cache_dir or get_settings().prepared_cache_dir
    bar = progress_bar(len(STAGES), f"prepare {args.sequence.name}")
    bar.unit = "stage"

    def progress(stage: str, done: int, total: int) -> None:
        bar.set_postfix_str(stage)
        bar.update(done - bar.n)

    try:
        prepared = prepare(
            args.sequence, config, clicks=args.clicks, cache_dir=cache_dir, progress=progress
        )
        bar.update(bar.total - bar.n)
    except (PreparationError, ClicksError) as exc:
        raise CliError(str(exc)) from exc
    finally:
        bar.close()
    if prepared.folder is not None:
        copy_artifact(prepared.folder, args.out)
    else:  # pragma: no cover - prepare() always writes under a cache folder
        write_artifact(prepared, args.out)
    s = prepared.summary
    errors = []
    if (args.sequence / "ground_truth" / "poses.csv").is_file():
        errors = pose_error_rows(prepared, args.sequence)
    if args.json:
        out = {**s, "out": str(args.out), "true_pose_errors": errors or None}
        print(json.dumps(out, indent=1))  # noqa: T201 - CLI output
        return 0
    how = "reused" if s.get("reused") else f"prepared in {s.get('total_seconds', 0.0):.1f} s"
    print(  # noqa: T201 - CLI output
        f"{s['sequence']['name']}: {how}, strategy {s['strategy']} "
        f"(requested {s['requested_strategy']}), key {prepared.key[:16]} -> {args.out}"
    )
    timings = s.get("timings", {})
    if timings and not s.get("reused"):
        print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()))  # noqa: T201
    health = s.get("health", {})
    print(  # noqa: T201 - CLI output
        f"  health: {'ok' if health.get('ok') else 'degraded'}"
        + (f", fallback {health['fallback']}" if health.get("fallback") else "")
    )
    for w in s.get("warnings", []):
        print(f"  warning: {w}")  # noqa: T201 - CLI output
    sc, cal = s.get("scene", {}), s.get("calibration") or {}
    print(  # noqa: T201 - CLI output
        f"  cloud {s['cloud']['points']} points, {s['tracks']['count']} track(s) "
        f"(ego {'found' if s['tracks']['ego_found'] else 'NOT found'}), "
        f"{sc.get('planes', 0)} planes ({sc.get('platforms', 0)} platforms), "
        f"{sc.get('poles', 0)} poles"
    )
    if cal:
        res = cal.get("residual_mean_px")
        print(  # noqa: T201 - CLI output
            f"  calibration point ({cal['mode']}): {cal['landmark']}, "
            + ("not found" if not cal["found"] else "found")
            + ("" if res is None else f", mean residual {res:.2f} px over {cal['views']} views")
        )
    for line in pose_error_table(errors):
        print(line)  # noqa: T201 - CLI output
    return 0
