"""The body's sway prior: a damped oscillator discretised exactly between frames."""

from __future__ import annotations

import numpy as np
import pytest

from worker.preparation.localization.body_sway import offset_change_sd, oscillator_prior


def _covariance(dt: np.ndarray, sigma: float, hz: float, zeta: float) -> np.ndarray:
    """(2n, 2n) covariance of the states (offset, rate per frame) the prior implies."""
    prior = oscillator_prior(dt, sigma, hz, zeta)
    n = len(dt) + 1
    A = np.column_stack([prior.residuals(np.eye(2 * n)[j].reshape(n, 2)) for j in range(2 * n)])
    return np.linalg.inv(A.T @ A)


def test_the_prior_has_the_oscillators_autocovariance_at_any_spacing() -> None:
    # frames 0.1 s apart with a 0.35 s gap: every offset keeps the stationary sd and
    # every change has the continuous oscillator's sd at its own lag
    dt = np.full(30, 0.1)
    dt[12] = 0.35
    t = np.concatenate([[0.0], np.cumsum(dt)])
    C = _covariance(dt, 0.005, 1.0, 0.5)[::2, ::2]
    assert np.sqrt(np.diag(C)) == pytest.approx(0.005, rel=1e-6)
    for i, j in [(0, 1), (3, 8), (10, 14), (2, 30)]:
        sd = np.sqrt(C[i, i] + C[j, j] - 2.0 * C[i, j])
        assert sd == pytest.approx(offset_change_sd(0.005, 1.0, 0.5, t[j] - t[i]), rel=1e-6)


def test_a_smooth_sway_changes_by_its_range_within_a_second() -> None:
    # the point of the model: 0.9 s after, a 5 mm mode's offset has changed by more
    # than its own sd (1.4x), where independent 3 mm steps under a 6 mm offset prior
    # allowed 4 mm
    change = float(offset_change_sd(0.005, 1.0, 0.5, np.array([0.9]))[0])
    assert 0.0065 < change < 0.0075
    # and a lightly damped mode is back near where it was after one period, having been
    # on the other side after half of one
    half, back = offset_change_sd(0.005, 1.0, 0.05, np.array([0.5, 1.0]))
    assert half > 0.0095
    assert back < 0.4 * half


def test_the_rate_is_the_offsets_derivative() -> None:
    # a noise-free oscillation is what the transition predicts: residuals ~ 0 against
    # the prior's own scale on a trajectory that follows the undamped dynamics' flow
    prior = oscillator_prior(np.full(20, 0.1), 0.005, 1.0, 0.5)
    x = np.zeros((21, 2))
    x[0] = [0.004, 0.0]
    for k in range(20):
        x[k + 1] = prior.phi[k] @ x[k]
    r = prior.residuals(x)
    assert np.max(np.abs(r[2:])) < 1e-9
    assert r[0] == pytest.approx(0.8)  # 4 mm against a 5 mm sd


def test_bad_parameters_say_which() -> None:
    with pytest.raises(ValueError, match="sigma, hz, zeta"):
        oscillator_prior(np.full(3, 0.1), 0.005, 0.0, 0.5)
