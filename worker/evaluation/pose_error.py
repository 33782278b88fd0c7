"""True pose errors of a preparation's tracks against a synthetic sequence's ground truth
(``SEQ/ground_truth/poses.csv``), as ``osdar-ar prepare`` prints them."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from geometry.geodesy import WorldFrame
from geometry.poses import PoseTrack, reexpress
from worker.preparation.artifact import PreparedSequence

log = logging.getLogger(__name__)


def pose_error_rows(prepared: PreparedSequence, seq_folder: Path) -> list[dict[str, Any]]:
    """True pose errors (m, deg) per track against SEQ/ground_truth/poses.csv."""
    gt_dir = seq_folder / "ground_truth"
    gt = PoseTrack.from_csv(gt_dir / "poses.csv")
    world_file = gt_dir / "world.json"
    if world_file.is_file():
        gt = reexpress(gt, WorldFrame.from_json(json.loads(world_file.read_text())), prepared.world)
    rows = []
    tracks = {f"{prepared.strategy} (chosen)": prepared.track, **prepared.references}
    for name, track in tracks.items():
        try:
            dt, dr = track.relative_errors(gt, max_extrapolation_s=0.05)
        except ValueError as exc:
            log.warning("pose errors of %s: %s", name, exc)
            continue
        rows.append(
            {
                "track": name,
                "frames": len(dt),
                "translation_mean_m": float(np.mean(dt)),
                "translation_max_m": float(np.max(dt)),
                "rotation_mean_deg": float(np.mean(dr)),
                "rotation_max_deg": float(np.max(dr)),
            }
        )
    return rows
