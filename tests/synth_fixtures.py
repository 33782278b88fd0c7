"""Small synthetic sequences shared by the preparation tests (generated once per session)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np

from geometry.poses import PoseTrack
from worker.preparation.localization import LocalizationInput

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


def true_poses_at(folder: Path, times: np.ndarray) -> np.ndarray:
    """(n, 4, 4) the true T_world_base at ``times`` (n,), from the dense ground truth."""
    return PoseTrack.from_csv(folder / "ground_truth" / "poses_dense.csv").interpolate(times)


def landmarks(folder: Path, kind: str | None = None) -> list[dict]:
    lms = json.loads((folder / "ground_truth" / "landmarks.json").read_text())
    return [lm for lm in lms if kind is None or lm["kind"] == kind]


def true_pole_xy(folder: Path) -> np.ndarray:
    """(k, 2) true pole axes from the pole_top landmarks."""
    return np.array([lm["xyz"][:2] for lm in landmarks(folder, "pole_top")]).reshape(-1, 2)


def true_ego_input(folder: Path, **options: object) -> LocalizationInput:
    """The sequence's localization input with its TRUE ego centreline (the strategies'
    own rail extraction left out), ``options`` as the strategies' options."""
    from worker.osdar.sequence import Sequence
    from worker.preparation.centreline import Centreline
    from worker.preparation.localization import make_input

    entries = json.loads((folder / "ground_truth" / "centrelines.json").read_text())
    ego = next(Centreline.from_json(e) for e in entries if e.get("ego"))
    return make_input(Sequence.open(folder), ego=ego, options=dict(options))


def with_corrimu_added(src: Path, dst: Path, column: str, per_sample: float) -> Path:
    """A copy of the sequence at ``src`` whose CORRIMU ``column`` (per IMU sample) carries
    ``per_sample`` more: a known gyro or accelerometer bias."""
    shutil.copytree(src, dst)
    for f in sorted((dst / "novatel_oem7_corrimu").glob("*.csv")):
        with f.open() as fh:
            rows = list(csv.DictReader(fh))
        for r in rows:
            r[column] = repr(float(r[column]) + per_sample)
        with f.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
            w.writeheader()
            w.writerows(rows)
    return dst
