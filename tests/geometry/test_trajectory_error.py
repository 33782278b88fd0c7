"""Relative pose error over lags: known answers, and agreement with evo's RPE."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core import metrics
from evo.core.trajectory import PosePath3D
from scipy.spatial.transform import Rotation

from geometry.trajectory_error import relative_pose_error, relative_pose_errors


def _random_track(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.cumsum(rng.normal(0, 0.01, n))
    T[:, :3, :3] = Rotation.from_euler(
        "zyx", np.column_stack([yaw, rng.normal(0, 0.002, (n, 2))])
    ).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal([1.5, 0, 0], 0.05, (n, 3)), axis=0)
    return T


def _perturbed(rng: np.random.Generator, T: np.ndarray) -> np.ndarray:
    E = np.tile(np.eye(4), (len(T), 1, 1))
    E[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.002, (len(T), 3))).as_matrix()
    E[:, :3, 3] = rng.normal(0, 0.03, (len(T), 3))
    return T @ E


def test_a_rigid_shift_of_the_whole_trajectory_is_no_error() -> None:
    rng = np.random.default_rng(1)
    T = _random_track(rng, 40)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("z", 37, degrees=True).as_matrix()
    G[:3, 3] = [1000.0, -250.0, 12.0]
    for lag in (1, 10, 30):
        e = relative_pose_error(G @ T, T, lag)
        assert len(e.translation_m) == 40 - lag
        assert np.max(e.translation_m) < 1e-9
        assert np.max(e.rotation_deg) < 1e-6


def test_a_known_error_in_one_frame_shows_at_the_pairs_that_include_it() -> None:
    T = np.tile(np.eye(4), (12, 1, 1))
    T[:, 0, 3] = np.arange(12) * 2.0
    est = T.copy()
    est[5, 1, 3] += 0.1  # 10 cm to the left in frame 5
    e = relative_pose_error(est, T, 3)
    bad = np.flatnonzero(e.translation_m > 1e-12)
    assert bad.tolist() == [2, 5]  # the pairs (2, 5) and (5, 8)
    np.testing.assert_allclose(e.translation_m[bad], 0.1, atol=1e-12)


def test_no_pair_when_the_sequence_is_shorter_than_the_lag() -> None:
    T = np.tile(np.eye(4), (8, 1, 1))
    e = relative_pose_errors(T, T, (1, 10))
    assert len(e[1].translation_m) == 7 and len(e[10].translation_m) == 0
    assert e[10].summary()["t_mean_m"] is None
    with pytest.raises(ValueError):
        relative_pose_error(T, T[:5], 1)


@pytest.mark.parametrize("lag", [1, 10, 30])
def test_matches_evo_rpe_all_pairs(lag: int) -> None:
    rng = np.random.default_rng(lag)
    T_true = _random_track(rng, 60)
    T_est = _perturbed(rng, T_true)
    ours = relative_pose_error(T_est, T_true, lag)
    ref, est = PosePath3D(poses_se3=list(T_true)), PosePath3D(poses_se3=list(T_est))
    for relation, mine in (
        (metrics.PoseRelation.translation_part, ours.translation_m),
        (metrics.PoseRelation.rotation_angle_deg, ours.rotation_deg),
    ):
        rpe = metrics.RPE(relation, delta=lag, delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe.process_data((ref, est))
        np.testing.assert_allclose(mine, rpe.error, rtol=1e-6, atol=1e-9)
