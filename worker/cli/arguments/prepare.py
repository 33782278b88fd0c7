"""``osdar-ar prepare``: pipeline step 2 on a sequence, the artifact written out."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "prepare",
        help="prepare a sequence: poses, registered cloud, tracks, scene elements",
        description="Run pipeline step 2 on a sequence and write the artifact to OUT: "
        "poses.csv, world.json, centrelines.json, planes.json, poles.json, "
        "calibration_point.json, summary.json, cloud.npz. The artifact is cached by the "
        "sequence's content, the config and the clicks, and reused. When SEQ/ground_truth "
        "exists, the true pose errors are printed too.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument("--strategy", default="auto", help="ins, odometry, rails, fused or auto")
    p.add_argument("--out", type=Path, required=True, help="artifact folder (replaced)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--voxel-size", type=float, default=None, help="m, registered cloud voxel")
    p.add_argument(
        "--clicks", type=Path, default=None, help="clicked landmark pixels (CSV or JSON)"
    )
    p.add_argument(
        "--config", type=Path, default=None, help="JSON file with PrepareConfig sections"
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default: prepared/ in the workers' cache, "
        "$OSDAR_AR_CACHE_DIR, itself default ./var/cache)",
    )
    p.set_defaults(command_group="prepare")
