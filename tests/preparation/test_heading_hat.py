"""The heading's three-cornered hat (INS, odometry, course over ground) on known errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.preparation.localization.heading_hat import course_over_ground, heading_errors

DEG = np.pi / 180.0


def _arc(n: int, speed: float, radius: float, dt: float = 0.1):
    """A train on a circular arc: (n,) times, yaw (rad), (n, 3) world velocity."""
    t = np.arange(n) * dt
    yaw = speed * t / radius
    v = np.c_[np.cos(yaw), np.sin(yaw), np.zeros(n)] * speed
    return t, yaw, v


def _yaw_R(yaw: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("Z", yaw[:, None]).as_matrix()


def test_the_source_that_drifts_is_found() -> None:
    """A good INS (white 0.005 deg) and an odometry that turns 20 % too little in a tight
    curve: the hat puts the heading error on the odometry, not on the INS."""
    rng = np.random.default_rng(0)
    n, lag = 100, 10
    t, yaw, v = _arc(n, speed=10.0, radius=300.0)
    R_ins = _yaw_R(yaw + rng.normal(0.0, 0.005 * DEG, n))
    R_odo = _yaw_R(0.8 * yaw)
    v_meas = v + rng.normal(0.0, 0.02, v.shape)
    h = heading_errors(R_ins, R_odo, v_meas, t, np.ones(n, dtype=bool), lag)
    assert h is not None and h.lag == lag
    odo_err = 0.2 * (yaw[lag:] - yaw[:-lag])  # its true error over the lag (constant)
    assert np.sqrt(h.odometry) == pytest.approx(float(np.mean(odo_err)), rel=0.15)
    # The INS's own error over the lag is two records' white noise, 0.007 deg; next to a
    # systematic 0.38 deg the hat resolves a small source only to about
    # sqrt(2 c mean(e)) ~ 0.06 deg (the cross term of the large error with the others'
    # sample means): it still puts the error on the odometry.
    assert np.sqrt(h.ins) < 0.25 * np.sqrt(h.odometry)


def test_a_wandering_ins_is_found() -> None:
    """An INS whose heading wanders 0.05 deg per step against a good odometry."""
    rng = np.random.default_rng(1)
    n, lag = 120, 10
    t, yaw, v = _arc(n, speed=8.0, radius=500.0)
    wander = np.cumsum(rng.normal(0.0, 0.05 * DEG, n))
    R_ins = _yaw_R(yaw + wander)
    R_odo = _yaw_R(yaw + rng.normal(0.0, 0.005 * DEG, n))
    h = heading_errors(R_ins, R_odo, v, t, np.ones(n, dtype=bool), lag)
    assert h is not None
    true_ins = np.sqrt(np.mean((wander[lag:] - wander[:-lag]) ** 2))
    assert np.sqrt(h.ins) == pytest.approx(float(true_ins), rel=0.3)
    assert np.degrees(np.sqrt(h.odometry)) < 0.05


def test_a_standing_train_has_no_course() -> None:
    t, _, v = _arc(50, speed=0.3, radius=300.0)
    assert np.all(np.isnan(course_over_ground(v, t)))
    R = np.tile(np.eye(3), (50, 1, 1))
    assert heading_errors(R, R, v, t, np.ones(50, dtype=bool), 10) is None


def test_too_few_pairs_give_none_and_the_ends_do_not_lag() -> None:
    """A 25-frame sequence has 15 pairs at a lag of 10: too few for the hat. The course near
    either end comes from a shrunk symmetric window: no lag in a curve."""
    t, yaw, v = _arc(25, speed=10.0, radius=200.0)
    R = _yaw_R(yaw)
    assert heading_errors(R, R, v, t, np.ones(25, dtype=bool), 10) is None
    np.testing.assert_allclose(course_over_ground(v, t), yaw, atol=1e-3 * DEG)
