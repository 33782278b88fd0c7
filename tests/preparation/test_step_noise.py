"""A source's own rotation noise from its third differences (known synthetic noise)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.preparation.localization.step_noise import step_noise, white_noise

DEG = np.pi / 180.0


def _curve_attitudes(n: int, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) attitudes of a train entering a curve (yaw rate ramping up, a clothoid)
    with a slow roll into the cant, and (n,) times."""
    t = np.arange(n) * dt
    yaw = 0.5 * 0.02 * t**2  # yaw rate ramps at 0.02 rad/s^2
    roll = 0.01 * np.sin(0.3 * t)
    return Rotation.from_euler("ZYX", np.c_[yaw, 0.002 * t, roll]).as_matrix(), t


@pytest.mark.parametrize("sigma_deg", [0.003, 0.01, 0.05])
def test_white_noise_of_a_noisy_attitude(sigma_deg: float) -> None:
    rng = np.random.default_rng(3)
    R, t = _curve_attitudes(200)
    noise = Rotation.from_rotvec(rng.normal(0.0, sigma_deg * DEG, (200, 3))).as_matrix()
    got = white_noise(R @ noise, t, np.ones(199, dtype=bool))
    assert got is not None
    # 200 records: the robust RMS of ~200 samples is good to about 10 %
    np.testing.assert_allclose(np.degrees(got), sigma_deg, rtol=0.2)


def test_step_noise_of_odometry_steps() -> None:
    """Steps that are differences of per-scan errors (sigma_e) plus a drift (sigma_d):
    the step's error is sqrt(2 sigma_e^2 + sigma_d^2), measured a little low where the
    drift is large (module docstring: less 0.4 sigma_d^2)."""
    rng = np.random.default_rng(5)
    n = 300
    R, t = _curve_attitudes(n)
    sigma_e, sigma_d = 0.01 * DEG, 0.004 * DEG
    e = rng.normal(0.0, sigma_e, (n, 3))
    drift = np.cumsum(rng.normal(0.0, sigma_d, (n, 3)), axis=0)
    R_odo = R @ Rotation.from_rotvec(e + drift).as_matrix()
    d_R = np.swapaxes(R_odo[:-1], 1, 2) @ R_odo[1:]
    got = step_noise(d_R, t, np.ones(n - 1, dtype=bool))
    assert got is not None
    want = np.sqrt(2 * sigma_e**2 + 0.6 * sigma_d**2)
    np.testing.assert_allclose(got, want, rtol=0.2)


def test_a_dropped_frame_is_left_out_and_too_few_steps_give_none() -> None:
    rng = np.random.default_rng(8)
    R, t = _curve_attitudes(240)
    keep = np.ones(240, dtype=bool)
    keep[[50, 150]] = False  # a dropped frame: a 0.2 s step
    R, t = R[keep], t[keep]
    noise = Rotation.from_rotvec(rng.normal(0.0, 0.01 * DEG, (len(t), 3))).as_matrix()
    got = white_noise(R @ noise, t, np.ones(len(t) - 1, dtype=bool))
    assert got is not None
    np.testing.assert_allclose(np.degrees(got), 0.01, rtol=0.25)
    assert white_noise(R[:6], t[:6], np.ones(5, dtype=bool)) is None
