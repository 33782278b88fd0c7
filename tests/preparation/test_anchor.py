"""Anchoring odometry on all INS positions: recovers heading and climb, ignores a jump."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from worker.preparation.localization.anchor import MIN_PATH_M, fit_anchor


def _arc(n: int = 100, radius: float = 600.0, length: float = 120.0) -> np.ndarray:
    s = np.linspace(0.0, length, n)
    th = s / radius
    return np.stack([radius * np.sin(th), radius * (1 - np.cos(th)), 0.01 * s], axis=1)


def test_recovers_a_heading_and_climb_error_to_hundredths_of_a_degree():
    rng = np.random.default_rng(0)
    p_true = _arc()
    # the trajectory to fix: rotated by 0.6 deg yaw and 0.2 deg climb about its start,
    # shifted by half a metre (a first-pose anchor with a bad INS record)
    R_err = Rotation.from_euler("zy", [0.6, -0.2], degrees=True).as_matrix()
    p_bad = (p_true - p_true[0]) @ R_err.T + p_true[0] + np.array([0.3, -0.4, 0.1])
    p_ins = p_true + rng.normal(0.0, 0.05, p_true.shape)  # noisy INS positions
    p_ins[85:] += np.array([3.0, 0.0, 0.0])  # and a GNSS jump for the last 15 records
    T, info = fit_anchor(p_bad, p_ins)
    fixed = p_bad @ T[:3, :3].T + T[:3, 3]
    R_left = T[:3, :3] @ R_err  # remaining rotation of the trajectory
    angle = np.degrees(Rotation.from_matrix(R_left).magnitude())
    assert angle < 0.05, angle
    # the jump pulls the translation by far less than its 3 m
    assert np.median(np.linalg.norm(fixed - p_true, axis=1)) < 0.5
    assert info["rms_after_m"] < info["rms_before_m"]


def test_roll_about_the_path_is_left_alone():
    p = _arc(radius=1e6)  # a straight: roll about it is not observable from positions
    R_roll = Rotation.from_rotvec(np.deg2rad(0.5) * (p[-1] - p[0]) / np.linalg.norm(p[-1] - p[0]))
    T, _ = fit_anchor(p, p)
    assert np.allclose(T, np.eye(4), atol=1e-9)
    T2, _ = fit_anchor((p - p[0]) @ R_roll.as_matrix().T + p[0], p)
    assert np.degrees(Rotation.from_matrix(T2[:3, :3]).magnitude()) < 1e-6


def test_standstill_keeps_the_first_pose_anchor():
    p = np.zeros((50, 3)) + np.random.default_rng(1).normal(0, 0.01, (50, 3))
    T, info = fit_anchor(p, p + 1.0)
    assert info["path_m"] < MIN_PATH_M * 5 and np.array_equal(T, np.eye(4))
