"""``osdar-ar evaluate``: every strategy prepared (cached), then the paper's RPE and jitter
per camera and strategy, the true errors on synthetic data; metrics, CSV, plot, overlays."""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from osdar_platform.settings import get_settings
from worker.cli.errors import CliError
from worker.evaluation.evaluate import (
    evaluate_strategies,
    plot_rpe_by_strategy,
    render_overlays,
    write_rows_csv,
)
from worker.evaluation.tables import strategy_rpe_table
from worker.preparation.calibration_point import Clicks, ClicksError
from worker.preparation.config import PrepareConfig
from worker.preparation.lidar_alignment import corrections_from_summary
from worker.preparation.prepare import prepare


def run(args: argparse.Namespace) -> int:
    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    try:
        clicks = [Clicks.load(c) for c in args.clicks] or None
        configs = {
            s: PrepareConfig(strategy=s).with_overrides(
                registration={} if args.voxel_size is None else {"voxel_size": args.voxel_size}
            )
            for s in strategies
        }
    except (ClicksError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    cache = args.cache_dir or get_settings().prepared_cache_dir
    tracks, prep, world, corrections = {}, {}, None, None
    for s, cfg in configs.items():
        t0 = time.perf_counter()
        prepared = prepare(args.sequence, cfg, cache_dir=cache)
        tracks[s] = (prepared.track, prepared.cloud.xyz)
        world = prepared.world
        corrections = corrections_from_summary(prepared.summary.get("lidar_alignment"))
        prep[s] = {
            "seconds": time.perf_counter() - t0,
            "reused": bool(prepared.summary.get("reused")),
            "preparation_seconds": prepared.summary.get("total_seconds"),
            "chosen": prepared.strategy,
            "warnings": prepared.summary.get("warnings", []),
        }
    cameras = None if args.cameras is None else [c.strip() for c in args.cameras.split(",")]
    if args.dense_radius is not None and args.dense_radius < 0:
        raise CliError(f"--dense-radius must be >= 0 m (got {args.dense_radius})")
    dense_kw = {} if args.dense_radius is None else {"dense_radius_m": args.dense_radius}
    try:
        metrics, rows = evaluate_strategies(
            args.sequence, tracks, world=world, cameras=cameras, clicks=clicks,
            near=args.near, far=args.far, click_noise_px=args.click_noise, seed=args.seed,
            max_landmarks=args.max_landmarks, preparation=prep, click_target=args.click_target,
            lidar_corrections=corrections, **dense_kw,
        )  # fmt: skip
    except (ClicksError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Any] = {"per_frame_csv": str(write_rows_csv(rows, out / "per_frame.csv"))}
    plot = plot_rpe_by_strategy(rows, out / "rpe.png", f"RPE over frames, {metrics['sequence']}")
    files["rpe_png"] = None if plot is None else str(plot)
    if not args.no_overlay:
        frames = None
        if args.overlay_frames:
            frames = [int(f) for f in args.overlay_frames.split(",") if f.strip()]
        paths = render_overlays(args.sequence, rows, metrics, tracks, out / "overlays", frames)
        files["overlays"] = [str(p) for p in paths]
    metrics["files"] = files
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, allow_nan=False))
    print(f"{metrics['sequence']}: clicks from {metrics['clicks_source']}, landmarks "  # noqa: T201
          f"{', '.join(metrics['landmarks_clicked']) or 'none'}")  # fmt: skip
    for line in strategy_rpe_table(metrics):
        print(line)  # noqa: T201 - CLI output
    print(f"wrote {out}/metrics.json, per_frame.csv, rpe.png, overlays/")  # noqa: T201
    return 0
