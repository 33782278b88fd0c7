"""Odometry steps as differences of per-scan errors: the covariance they give is the model's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix, csc_matrix, diags

from geometry.pose_uncertainty import PoseInformation
from worker.preparation.localization.scan_errors import with_scan_errors

N = 12
SIG_R, SIG_T = 1e-4, 5e-3  # a step's total sigma: rad, m


def _steps() -> tuple[csc_matrix, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The Jacobian of a pure odometry chain (rows: steps' translation, then rotation, 3
    components each; columns: 6 per frame) and a tight prior on frame 0's pose."""
    rows, cols, vals = [], [], []
    rows_t = np.arange(3 * (N - 1)).reshape(N - 1, 3)
    rows_r = 3 * (N - 1) + rows_t
    a_t = np.full((N - 1, 3), 1.0 / SIG_T)
    a_r = np.full((N - 1, 3), 1.0 / SIG_R)
    for k in range(N - 1):
        for c in range(3):
            for r, a, off in ((rows_t[k, c], a_t[k, c], 3), (rows_r[k, c], a_r[k, c], 0)):
                rows += [r, r]
                cols += [6 * (k + 1) + off + c, 6 * k + off + c]
                vals += [a, -a]
    n_rows = 6 * (N - 1)
    J = coo_matrix((vals, (rows, cols)), shape=(n_rows, 6 * N)).tocsc()
    return J, np.ones(n_rows), rows_t, a_t, rows_r, a_r


def _information(J: csc_matrix, w: np.ndarray) -> PoseInformation:
    A = (J.T @ diags(w) @ J).tocsc()
    anchor = np.zeros(A.shape[0])
    anchor[:6] = 1e12  # frame 0 fixed: relative covariances are what is left
    return PoseInformation(csc_matrix(A + diags(anchor)), N)


@pytest.mark.parametrize("share", [1.0, 0.5, 0.25, 0.1])
def test_lag_variance_is_two_scan_errors_plus_the_drift(share: float) -> None:
    """Over L steps the variance is 2 sigma_e^2 + L sigma_d^2 with 2 sigma_e^2 + sigma_d^2
    a step's: (1 - share) + L share times a step's variance, exactly."""
    J, w, rows_t, a_t, rows_r, a_r = _steps()
    use = np.ones(N - 1, dtype=bool)
    Jx, wx = with_scan_errors(J, w, rows_t, a_t, rows_r, a_r, use, share)
    info = _information(Jx, wx)
    for lag in (1, 4, N - 1):
        var = np.diag(info.relative_covariance(0, lag))
        expect = (1.0 - share) + lag * share
        assert var[:3] == pytest.approx(np.full(3, expect * SIG_R**2), rel=1e-6)
        assert var[3:] == pytest.approx(np.full(3, expect * SIG_T**2), rel=1e-6)


def test_independent_steps_are_left_as_they_are() -> None:
    J, w, rows_t, a_t, rows_r, a_r = _steps()
    use = np.ones(N - 1, dtype=bool)
    Jx, wx = with_scan_errors(J, w, rows_t, a_t, rows_r, a_r, use, 1.0)
    assert Jx is J and wx is w
    with pytest.raises(ValueError, match="outside"):
        with_scan_errors(J, w, rows_t, a_t, rows_r, a_r, use, 0.0)


def test_unmodelled_steps_keep_their_random_walk() -> None:
    """A zero-velocity step (not the ICP's) keeps its own independent sigma."""
    J, w, rows_t, a_t, rows_r, a_r = _steps()
    use = np.ones(N - 1, dtype=bool)
    use[5] = False
    info = _information(*with_scan_errors(J, w, rows_t, a_t, rows_r, a_r, use, 0.25))
    # frames 5 -> 6: only that step, independent: its full variance
    var = np.diag(info.relative_covariance(5, 6))
    assert var[:3] == pytest.approx(np.full(3, SIG_R**2), rel=1e-6)
