"""The merged cloud's pitch against the base, from the ground pairs (``lidar_yaw``).

A base climbing a grade (constant, or a long vertical curve) bounces a few millimetres
and pitches a few tenths of a milliradian on its suspension; its relative poses seen
through a cloud pitched by a known angle must give that angle back where the pairs are
far enough apart on a near-constant grade, and nothing where they are not."""

from __future__ import annotations

import numpy as np
import pytest

from worker.preparation.localization.lidar_yaw import (
    lidar_pitch_offset,
    tilt_lidar_poses,
    vertical_angles,
)


def _grade(n: int, step_m: float, grade: float, kappa: float) -> np.ndarray:
    """(n, 4, 4) poses of a base on a vertical arc: climbing angle ``grade + kappa s``, its
    x axis along the track (a pitch about +y lowers the nose)."""
    s = np.arange(n) * step_m
    gamma = grade + kappa * s
    if kappa == 0.0:
        x, z = s * np.cos(grade), s * np.sin(grade)
    else:
        x = (np.sin(gamma) - np.sin(grade)) / kappa
        z = (np.cos(grade) - np.cos(gamma)) / kappa
    T = np.tile(np.eye(4), (n, 1, 1))
    c, si = np.cos(-gamma), np.sin(-gamma)
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, si, -si, c
    T[:, 0, 3], T[:, 2, 3] = x, z
    return T


def _bounced(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The body's bounce (3 mm) and pitching (0.2 mrad) on its suspension, per frame."""
    out = T.copy()
    for k in range(len(T)):
        a = rng.normal(0.0, 2e-4)
        B = np.eye(4)
        B[0, 0], B[0, 2], B[2, 0], B[2, 2] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
        B[2, 3] = rng.normal(0.0, 0.003)
        out[k] = T[k] @ B
    return out


def _pairs(T: np.ndarray, lag: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(len(T) - lag)
    return np.linalg.inv(T[k]) @ T[k + lag], np.full(len(k), lag)


def test_tilting_back_and_forth_is_the_identity() -> None:
    T = _pairs(_grade(40, 0.7, 0.01, 1e-5), 10)[0]
    np.testing.assert_allclose(tilt_lidar_poses(tilt_lidar_poses(T, 8e-4), -8e-4), T, atol=1e-12)
    # the relative pitch is not changed, the angle of climb is by the tilt
    a0, k0 = vertical_angles(T)
    a1, k1 = vertical_angles(tilt_lidar_poses(T, 8e-4))
    np.testing.assert_allclose(k1, k0, rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(a1, a0 - 8e-4, atol=1e-7)
    np.testing.assert_allclose(a0, 0.0, atol=1e-9)  # a base following its rails: 0


@pytest.mark.parametrize(("pitch", "kappa"), [(9e-4, 0.0), (-6e-4, 2e-5), (0.0, 1e-5)])
def test_a_grade_gives_the_cloud_pitch(pitch: float, kappa: float) -> None:
    rng = np.random.default_rng(11)
    T_k_j, lag = _pairs(_bounced(_grade(100, 0.7, 0.008, kappa), rng), 10)
    seen = tilt_lidar_poses(T_k_j, -pitch)  # what a cloud pitched by `pitch` measures
    est = lidar_pitch_offset(seen, np.ones(len(lag), bool), lag)
    # a pair whose pitching shows as a curvature above the limit may be left out
    assert est is not None and est.pairs >= 0.9 * len(lag)
    # 3 mm of bounce over 7 m is 0.6 mrad a pair, nine independent stretches of 10 frames
    assert abs(est.rad - pitch) < 0.3e-3, (est, pitch)
    assert est.significant == (pitch != 0.0)


def test_vertical_curves_short_pairs_and_failed_pairs_are_refused() -> None:
    # a 5 km vertical curve (a crest): 0.2 mrad of relative pitch per metre
    T_k_j, lag = _pairs(_grade(100, 0.7, 0.0, 2e-4), 10)
    assert lidar_pitch_offset(T_k_j, np.ones(len(lag), bool), lag) is None
    # pairs 3.5 m apart: the bounce would be the angle
    T_k_j, lag = _pairs(_grade(100, 0.7, 0.01, 0.0), 5)
    assert lidar_pitch_offset(T_k_j, np.ones(len(lag), bool), lag) is None
    T_k_j, lag = _pairs(_grade(100, 0.7, 0.01, 0.0), 10)
    assert lidar_pitch_offset(T_k_j, np.zeros(len(lag), bool), lag) is None
