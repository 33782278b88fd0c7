"""``osdar-ar evaluate``: RPE and jitter per camera and strategy."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "evaluate",
        help="RPE and jitter per camera and strategy (the paper's definition), true errors",
        description="Prepare SEQ with every strategy (cached), then for every camera, "
        "strategy and landmark: the calibration point (the cloud point registered with that "
        "strategy's poses nearest to the clicks), RPE_i and jitter J_i per frame, mean and "
        "std. Clicks come from --clicks files (CSV / JSON, see the README) or, on synthetic "
        "sequences, from ground_truth/landmarks.json (landmarks --near..--far m ahead). "
        "Writes OUT/metrics.json, OUT/per_frame.csv, OUT/rpe.png and OUT/overlays/*.png.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--strategies", default="ins,odometry,rails,fused", help="comma-separated")
    p.add_argument(
        "--clicks", type=Path, action="append", default=[],
        help="clicks file of one landmark (repeatable); default: ground truth (synthetic)",
    )  # fmt: skip
    p.add_argument("--cameras", default=None, help="comma-separated (default: clicked ones)")
    p.add_argument("--near", type=float, default=30.0, help="m, synthetic landmarks from")
    p.add_argument("--far", type=float, default=80.0, help="m, synthetic landmarks to")
    p.add_argument("--click-noise", type=float, default=0.0, help="px, synthetic click noise")
    p.add_argument(
        "--click-target", choices=["return", "return_recorded", "landmark"], default="return",
        help="synthetic clicks on the lidar return nearest each landmark where its beam truly "
        "hit (default: the RPE carries the merged cloud's calibration error, as a real "
        "operator's would), on that return where the merged cloud puts it (return_recorded), "
        "or on the landmark itself (its RPE then includes its distance to the nearest return)",
    )  # fmt: skip
    p.add_argument("--max-landmarks", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--voxel-size", type=float, default=None, help="m, registered cloud voxel")
    p.add_argument(
        "--dense-radius", type=float, default=None,
        help="m: refine each calibration point among every frame's full-density points this "
        "close (default 0.5; 0: the registered cloud's point only, as in the paper)",
    )  # fmt: skip
    p.add_argument(
        "--overlay-frames", default=None, help="comma-separated frames (default: 3 per camera)"
    )
    p.add_argument("--no-overlay", action="store_true")
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default: prepared/ in the workers' cache, "
        "$OSDAR_AR_CACHE_DIR, itself default ./var/cache)",
    )
    p.set_defaults(command_group="evaluate")
