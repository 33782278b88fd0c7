"""Small synthetic sequences shared by the preparation tests (generated once per session)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from geometry.poses import PoseTrack

STATION = {"scene": "station", "frames": 12, "scale": 0.1, "lidar_density": 0.3, "seed": 0}


def synth_sequence(base: Path, name: str = "station_prep", **overrides: object) -> Path:
    """Generate (once) a small synthetic sequence under ``base``; returns its folder."""
    from worker.synth.generator import SynthConfig, generate

    folder = base / name
    if not (folder / "ground_truth" / "meta.json").is_file():
        generate(folder, SynthConfig(**{**STATION, **overrides}))
    return folder


def true_poses(folder: Path) -> PoseTrack:
    """ground_truth/poses.csv (T_world_base at the lidar timestamps)."""
    return PoseTrack.from_csv(folder / "ground_truth" / "poses.csv")


def landmarks(folder: Path, kind: str | None = None) -> list[dict]:
    lms = json.loads((folder / "ground_truth" / "landmarks.json").read_text())
    return [lm for lm in lms if kind is None or lm["kind"] == kind]


def true_pole_xy(folder: Path) -> np.ndarray:
    """(k, 2) true pole axes from the pole_top landmarks."""
    return np.array([lm["xyz"][:2] for lm in landmarks(folder, "pole_top")]).reshape(-1, 2)
