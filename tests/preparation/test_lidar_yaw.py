"""The merged cloud's yaw against the base, from the train's motion (``lidar_yaw``).

Relative poses of a base moving along a known track (straight, a gentle curve, a tight
curve with the base off the bogies' midpoint) are seen through a cloud turned by a known
angle; the estimate must find that angle where the track is straight enough and refuse
where it is not."""

from __future__ import annotations

import numpy as np
import pytest

from worker.preparation.localization.lidar_yaw import (
    lidar_yaw_offset,
    non_holonomic_angles,
    turn_lidar_poses,
)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = [x, y]
    return T


def _track(n: int, step_m: float, kappa: float, lever_m: float = 0.0) -> np.ndarray:
    """(n, 4, 4) world poses of a base on an arc of curvature ``kappa``; ``lever_m`` ahead
    of the point that follows the track (the bogies' midpoint), heading along the chord."""
    s = np.arange(n) * step_m
    yaw = kappa * s
    if kappa == 0.0:
        x, y = s, np.zeros(n)
    else:
        x, y = np.sin(yaw) / kappa, (1.0 - np.cos(yaw)) / kappa
    return np.stack(
        [_pose(xi + lever_m * np.cos(a), yi + lever_m * np.sin(a), a)
         for xi, yi, a in zip(x, y, yaw, strict=True)]
    )  # fmt: skip


def _pairs(T: np.ndarray, lag: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(len(T) - lag)
    return np.linalg.inv(T[k]) @ T[k + lag], np.full(len(k), lag)


def _seen_through(T_k_j: np.ndarray, delta: float, rng: np.random.Generator) -> np.ndarray:
    """The pairs as a cloud turned by ``delta`` sees them, with 3 mm / 0.1 mrad noise."""
    turned = turn_lidar_poses(T_k_j, -delta)
    noise = np.stack(
        [_pose(*rng.normal(0.0, 0.003, 2), rng.normal(0.0, 1e-4)) for _ in range(len(T_k_j))]
    )
    return turned @ noise


def test_turning_back_and_forth_is_the_identity() -> None:
    T = _pairs(_track(40, 0.9, 2e-3), 10)[0]
    back = turn_lidar_poses(turn_lidar_poses(T, 7e-4), -7e-4)
    np.testing.assert_allclose(back, T, atol=1e-12)
    # the relative yaw is not changed, the translation turns by -delta
    turned = turn_lidar_poses(T, 7e-4)
    a0, k0 = non_holonomic_angles(T)
    a1, k1 = non_holonomic_angles(turned)
    np.testing.assert_allclose(k1, k0, rtol=1e-3)
    np.testing.assert_allclose(a1, a0 - 7e-4, atol=1e-7)  # second order: delta (y/x)^2


@pytest.mark.parametrize("delta", [6.5e-4, -4e-4, 0.0])
def test_straight_track_gives_the_cloud_yaw(delta: float) -> None:
    rng = np.random.default_rng(3)
    T_k_j, lag = _pairs(_track(60, 0.9, 5e-6), 30)
    est = lidar_yaw_offset(_seen_through(T_k_j, delta, rng), np.ones(len(lag), bool), lag)
    assert est is not None and est.pairs == len(lag)
    # 3 mm over 27 m is 0.11 mrad a pair; the median of 30 pairs is well inside 0.1 mrad
    assert abs(est.rad - delta) < 1e-4, (est, delta)
    assert est.significant == (delta != 0.0)


def test_reversing_train_gives_the_same_yaw() -> None:
    rng = np.random.default_rng(4)
    T_k_j, lag = _pairs(_track(60, -0.9, 0.0), 30)
    est = lidar_yaw_offset(_seen_through(T_k_j, 5e-4, rng), np.ones(len(lag), bool), lag)
    assert est is not None and abs(est.rad - 5e-4) < 1e-4


def test_curves_and_short_pairs_are_refused() -> None:
    rng = np.random.default_rng(5)
    # a 1 km curve with the base 12.5 m ahead of the bogies' midpoint: its own angle of
    # travel is 12.5 mrad, which no cloud yaw explains
    T_k_j, lag = _pairs(_track(60, 0.9, 1e-3, lever_m=12.5), 30)
    a, _ = non_holonomic_angles(T_k_j)
    assert np.all(np.abs(a) > 5e-3)
    assert lidar_yaw_offset(_seen_through(T_k_j, 0.0, rng), np.ones(len(lag), bool), lag) is None
    # straight, but pairs 9 m apart: the body's sway would be the angle
    T_k_j, lag = _pairs(_track(60, 0.9, 0.0), 10)
    assert lidar_yaw_offset(T_k_j, np.ones(len(lag), bool), lag) is None
    # straight and long, but registrations that failed
    T_k_j, lag = _pairs(_track(60, 0.9, 0.0), 30)
    assert lidar_yaw_offset(T_k_j, np.zeros(len(lag), bool), lag) is None
