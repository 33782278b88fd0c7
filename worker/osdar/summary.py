"""A validated summary of an OSDaR23 sequence folder (``osdar-ar info``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from worker.osdar.sequence import Sequence


def summarize(folder: Path) -> dict[str, Any]:
    """Open (and so validate) a sequence; frames, cameras, time span, INS rows, point counts."""
    seq = Sequence.open(Path(folder))
    frames = seq.frame_indices
    lidar_ts = seq.timestamps(seq.lidar_stream) if seq.lidar_stream else np.array([])
    out: dict[str, Any] = {
        "name": seq.name,
        "frames": len(frames),
        "first_frame": int(frames[0]) if frames else None,
        "last_frame": int(frames[-1]) if frames else None,
        "cameras": list(seq.cameras),
        "lidar": seq.lidar_stream,
        "time_span_s": float(lidar_ts[-1] - lidar_ts[0]) if len(lidar_ts) > 1 else 0.0,
    }
    try:
        out["ins_rows"] = len(seq.ins())
    except Exception as exc:
        out["ins_rows"] = f"unavailable ({exc})"
    if frames and seq.lidar_stream:
        cloud = seq.pcd(frames[0])
        out["points_first_frame"] = len(cloud)
    return out
