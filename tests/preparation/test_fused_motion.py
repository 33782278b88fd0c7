"""fused estimates how smoothly the train turns (motion_factors): on a sequence whose
heading is smooth the odometry's per-frame heading noise leaves the poses (the placed
object's jitter), and in a curve's transition the real yaw acceleration stays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.poses import PoseTrack
from tests.synth_fixtures import true_ego_input
from worker.preparation.localization import LocalizationInput
from worker.preparation.localization.fused import FusedStrategy, Sigmas


def _sequence(tmp: pytest.TempPathFactory, scene: str, frames: int, seed: int) -> Path:
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene=scene, frames=frames, scale=0.05, seed=seed, lidar_density=0.3,
        ins_profile="hard", cameras=(),
    )  # fmt: skip
    return generate(tmp.mktemp(scene) / "seq", cfg).folder


@pytest.fixture(scope="module")
def straight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sequence(tmp_path_factory, "straight_sparse", 40, 7)


@pytest.fixture(scope="module")
def curve(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sequence(tmp_path_factory, "tight_curve", 40, 7)


def _input(folder: Path) -> LocalizationInput:
    # without the gyros (a sequence with no CORRIMU): the smoothness prior is then what
    # separates the odometry's and the INS's per-frame noise from the train's turning
    inp = true_ego_input(folder)
    inp.options["fused_gyro"] = False
    return inp


def _rotation_error_mdeg(track: PoseTrack, folder: Path, lag: int) -> float:
    """RMS (mdeg) of the relative rotation error over ``lag`` frames, all axes."""
    gt = PoseTrack.from_csv(folder / "ground_truth/poses_dense.csv").interpolate(track.timestamps)
    a = np.swapaxes(track.T[:-lag, :3, :3], 1, 2) @ track.T[lag:, :3, :3]
    b = np.swapaxes(gt[:-lag, :3, :3], 1, 2) @ gt[lag:, :3, :3]
    e = Rotation.from_matrix(np.swapaxes(b, 1, 2) @ a).as_rotvec()
    return float(1000 * np.degrees(np.sqrt(np.mean(np.sum(e**2, axis=1)))))


def _both(folder: Path) -> tuple[dict[int, float], dict[int, float], dict[str, float]]:
    inp = _input(folder)
    fixed = FusedStrategy(Sigmas(estimate_motion=False)).run(inp)
    est = FusedStrategy().run(inp)
    lags = (1, 10)
    return (
        {k: _rotation_error_mdeg(fixed.track, folder, k) for k in lags},
        {k: _rotation_error_mdeg(est.track, folder, k) for k in lags},
        est.health.metrics,
    )


@pytest.mark.slow
def test_a_smooth_heading_sheds_the_odometry_noise(straight: Path) -> None:
    fixed, est, metrics = _both(straight)
    # the straight line's heading is smooth: the estimated sigma is far below the 20 mdeg
    # default, and the frame-to-frame rotation error falls by a fifth or more
    assert metrics["fused_rotation_acceleration_heading_mdeg"] < 10.0, metrics
    assert est[1] < 0.8 * fixed[1], (est, fixed)
    assert est[10] < 1.05 * fixed[10], (est, fixed)


@pytest.mark.slow
def test_a_curve_keeps_its_transition(curve: Path) -> None:
    fixed, est, _ = _both(curve)
    # the transition's yaw acceleration is real: no rotation error grows over 10 frames
    assert est[10] < 1.05 * fixed[10], (est, fixed)
    assert est[1] < 1.05 * fixed[1], (est, fixed)
