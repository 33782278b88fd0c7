# ruff: noqa: T201 (a script: prints its table)
"""Does a strategy's pose covariance tell the truth? Relative rotation error against its sd.

For robustness-matrix cells (``worker.bench.matrix.Cell``: scene, frames, density, INS
profile, seed), generated once under ``--root``: the strategy's relative rotation error
over lags 1, 5, 10 and 30 frames against the ground truth (rotation vector of
``(T_i^-1 T_i+L)_true^-1 (T_i^-1 T_i+L)_est`` in frame i's base axes) beside the standard
deviation its information matrix gives the same relative rotation
(``PoseInformation.relative_covariance``). Per lag and axis (roll, pitch, heading): the
RMS error, the median sd (mdeg) and the RMS of their ratio, |z| (about 1 where the
covariance is honest; the per-frame placement bound is built from it).

    .venv/bin/python scripts/bench_pose_consistency.py klein_flottbek:60:0.3:hard:10 \\
        klein_flottbek:60:0.3:hard:11 --strategy fused
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from worker.bench.matrix import Cell, _truth
from worker.osdar.sequence import Sequence
from worker.preparation.config import PrepareConfig
from worker.preparation.localization import run_strategy
from worker.preparation.prepare import localization_setup
from worker.synth.generator import generate

LAGS = (1, 5, 10, 30)
MDEG = np.degrees(1.0) * 1000.0  # rad -> mdeg


def parse_cell(text: str) -> Cell:
    """``scene:frames:density:profile:seed`` -> a moving matrix cell."""
    try:
        scene, frames, density, profile, seed = text.split(":")
        return Cell(scene, int(frames), float(density), profile, int(seed))
    except ValueError as exc:
        raise SystemExit(f"cell {text!r}: expected scene:frames:density:profile:seed") from exc


def consistency(cell: Cell, root: Path, strategy: str) -> dict[int, dict[str, list[float]]]:
    """Per lag: RMS error, median sd (mdeg) and RMS |z| per axis (roll, pitch, heading)."""
    folder = root / cell.name
    if not (folder / "ground_truth" / "meta.json").is_file():
        generate(folder, cell.synth_config())
    setup = localization_setup(Sequence.open(folder), PrepareConfig())
    res = run_strategy(strategy, setup.inp)
    if res.information is None:
        raise SystemExit(f"{strategy} gives no information matrix")
    _, truth, _ = _truth(folder)
    T_true = truth.interpolate(setup.inp.times, max_extrapolation_s=0.2)
    T = res.track.T
    out = {}
    for lag in LAGS:
        err, sd = [], []
        for i in range(0, len(T) - lag, max(1, lag // 2)):
            D_est = np.linalg.inv(T[i]) @ T[i + lag]
            D_true = np.linalg.inv(T_true[i]) @ T_true[i + lag]
            err.append(Rotation.from_matrix((np.linalg.inv(D_true) @ D_est)[:3, :3]).as_rotvec())
            C = res.information.relative_covariance(i, i + lag)[:3, :3]  # world axes
            R = T[i, :3, :3]
            sd.append(np.sqrt(np.diag(R.T @ C @ R)))
        if not err:
            continue
        e, s = np.array(err), np.array(sd)
        out[lag] = {
            "rms_mdeg": list(np.sqrt(np.mean(e**2, axis=0)) * MDEG),
            "sd_mdeg": list(np.median(s, axis=0) * MDEG),
            "z": list(np.sqrt(np.mean((e / s) ** 2, axis=0))),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cells", nargs="+", help="scene:frames:density:profile:seed")
    ap.add_argument("--strategy", default="fused")
    ap.add_argument("--root", type=Path, default=Path("/tmp/osdar_pose_consistency"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    args.root.mkdir(parents=True, exist_ok=True)
    for text in args.cells:
        cell = parse_cell(text)
        head = "error rms / sd median (mdeg), |z|; roll pitch heading"
        print(f"{cell.name} ({args.strategy}): {head}")
        for lag, d in consistency(cell, args.root, args.strategy).items():
            cols = "  ".join(
                f"{e:6.2f} / {s:6.2f} ({z:4.2f})"
                for e, s, z in zip(d["rms_mdeg"], d["sd_mdeg"], d["z"], strict=True)
            )
            print(f"  lag {lag:2d}: {cols}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
