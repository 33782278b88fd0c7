"""Scan-to-map odometry's step errors as differences of per-scan errors, for the information.

A scan-to-map odometry (KISS-ICP) registers every scan against one slowly growing map: the
error of a scan's pose is mostly that scan's own registration error ``e_k`` (its sampling
pattern against the map's), and the map's own slow drift ``d_k`` adds up underneath. A
frame step's error is then ``e_(k+1) - e_k + d_k``: neighbouring steps' errors are
anti-correlated, and over L steps the error is ``e_(k+L) - e_k + sum(d)``, of variance
``2 sigma_e^2 + L sigma_d^2``, not L times a step's. On the synthetic scenes the fused
solution's heading-step residuals have lag-1 autocorrelations of -0.3 to -0.6 and their
10-step sums 0.06-0.28 of a random walk's variance; treated as independent, the steps made
the covariance of frames 10-20 apart 3-20x too wide (the per-frame placement bound 6-16 px
against 0.3-1 px true errors).

:func:`with_scan_errors` adds ``e_k`` as nuisance columns of the information: each step row
depends on ``e_(k+1) - e_k`` and keeps the drift's share of its variance, each ``e_k`` gets
a prior of the rest, so the step's total variance ``2 sigma_e^2 + sigma_d^2`` is what the
step's sigma says. The solution itself is unchanged (the same rows, the same minimum); the
nuisance columns are marginalised when the covariance is solved
(:class:`~geometry.pose_uncertainty.PoseInformation`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csc_matrix, diags, vstack

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def with_scan_errors(
    J: csc_matrix,
    w: F64,
    rows_t: I64,
    a_t: F64,
    rows_r: I64,
    a_r: F64,
    use: NDArray[np.bool_],
    drift_share: float,
) -> tuple[csc_matrix, F64]:
    """The Jacobian and row weights with per-scan error columns and their priors.

    J : (R, m) the residuals' Jacobian (m parameters, frames first); w : (R,) its row
    weights; rows_t, rows_r : (n-1, 3) the rows of the steps' translation and rotation
    components (base axes of the step's first frame); a_t, a_r : (n-1, 3) each row's
    weight (1 / its sigma, m^-1 and rad^-1); use : (n-1,) the steps to model so (not a
    zero-velocity step); drift_share : share in (0, 1] of a step's variance that adds up
    as a random walk (1: the independent steps of before).

    Returns (J', w'): J' is (R + P, m + 6 n) with frame k's scan error in columns
    ``m + 6 k .. m + 6 k + 6`` (rotation, then translation, as the frames' own columns),
    P prior rows of weight 1 appended.
    """
    return with_step_differences(
        J, w, np.hstack([rows_r, rows_t]), np.hstack([a_r, a_t]), use, drift_share
    )


def with_step_differences(
    J: csc_matrix,
    w: F64,
    rows: I64,
    a: F64,
    use: NDArray[np.bool_],
    drift_share: float,
) -> tuple[csc_matrix, F64]:
    """Step rows whose errors are differences of per-frame errors, as nuisance columns.

    J : (R, m); w : (R,); rows : (n-1, C) the rows of C components of each step
    between frames k and k + 1; a : (n-1, C) their weights (1 / sigma); use : (n-1,)
    the steps to model so; drift_share : as :func:`with_scan_errors`.

    Returns (J', w'): J' is (R + C n, m + C n) with frame k's error of component c in
    column ``m + C k + c``, its prior rows (weight 1) appended. A component no modelled
    step touches gets a unit prior (decoupled: it only keeps the matrix regular).
    """
    if not 0.0 < drift_share <= 1.0:
        raise ValueError(f"drift_share {drift_share} outside (0, 1]")
    R, m = J.shape
    n = len(use) + 1
    C = rows.shape[1]
    if drift_share >= 1.0 or n < 2 or not np.any(use):
        return J, w
    # the modelled rows keep the drift's share of their variance
    row_scale = np.ones(R)
    new_rows, new_cols, new_vals = [], [], []
    sig_e = np.full((n, C), np.inf)
    for c in range(C):
        k = np.flatnonzero(use & (a[:, c] > 0.0))
        if not len(k):
            continue
        r = rows[k, c]
        row_scale[r] = 1.0 / np.sqrt(drift_share)
        v = a[k, c] / np.sqrt(drift_share)
        new_rows += [r, r]
        new_cols += [m + C * (k + 1) + c, m + C * k + c]
        new_vals += [v, -v]
        # e's prior: (1 - share) / 2 of the tighter adjacent step's variance
        s_e = np.sqrt(0.5 * (1.0 - drift_share)) / a[k, c]
        np.minimum.at(sig_e[:, c], k, s_e)
        np.minimum.at(sig_e[:, c], k + 1, s_e)
    scaled = (diags(row_scale) @ J).tocoo()
    rows_all = np.concatenate([scaled.row, *new_rows])
    cols_all = np.concatenate([scaled.col, *new_cols])
    vals_all = np.concatenate([scaled.data, *new_vals])
    J_wide = coo_matrix((vals_all, (rows_all, cols_all)), shape=(R, m + C * n))
    s_e = np.where(np.isfinite(sig_e), sig_e, 1.0).ravel()
    P = coo_matrix((1.0 / s_e, (np.arange(C * n), m + np.arange(C * n))), shape=(C * n, m + C * n))
    return vstack([J_wide, P]).tocsc(), np.concatenate([w, np.ones(C * n)])
