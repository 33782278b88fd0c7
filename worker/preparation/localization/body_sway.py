"""The train body's sway on its suspension as a Gauss-Markov prior.

A rail vehicle's body moves on its suspension against the track: sideways (sway, the
wheelsets' play in the gauge) and up and down (bounce), millimetres at the body's
suspension modes, about 0.5-1.5 Hz (lateral and lower-sway modes near 0.5-1 Hz, bounce
near 1-1.5 Hz). Such a motion is smooth: its offset moves the same way for a good part of a
second, so over a short sequence it changes by as much as its whole range (6 mm at 0.7 Hz
goes from one side to the other in 0.7 s). A prior of independent per-frame steps under a
bound on the offsets cannot say so: each of its priors narrows the others (per-frame
offsets of 6 mm with 3 mm steps leave a 3 mm offset and a 4 mm change over a second), so
the bound it gives on a short sequence's sideways motion is half what the body does.

Here each axis is a damped oscillator driven by white noise, the stochastic model of a
suspension mode: state (offset, rate), natural frequency ``hz``, damping ratio ``zeta``,
stationary offset sd ``sigma`` (its rate's is ``2 pi hz sigma``). Discretised exactly
between the frames' times (Van Loan's method), it is the prior

    x_0 ~ N(0, P),   x_(k+1) = Phi_k x_k + w_k,   w_k ~ N(0, Q_k),

whose offsets have the oscillator's autocovariance at any frame spacing. A broad,
well-damped mode (zeta 0.5) covers a range of frequencies rather than one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SwayPrior:
    """Whitened prior of one axis' oscillator over a sequence's frames.

    w0 : (2,) 1 / sd of the first frame's (offset, rate) (stationary: independent);
    phi : (n-1, 2, 2) transition of each step; W : (n-1, 2, 2) the whitening of each
    step's process noise (W Q W^T = I, lower triangular).
    The prior's residuals are ``w0 * x_0`` and ``W_k (x_(k+1) - phi_k x_k)``.
    """

    w0: F64
    phi: F64
    W: F64

    def residuals(self, x: F64) -> F64:
        """(2 n,) the whitened residuals for states x (n, 2) (offset m, rate m/s): the
        first frame's two, then each step's two."""
        e = x[1:] - np.einsum("kij,kj->ki", self.phi, x[:-1])
        steps = np.einsum("kij,kj->ki", self.W, e)
        return np.concatenate([self.w0 * x[0], steps.ravel()])


def oscillator_prior(dt: F64, sigma: float, hz: float, zeta: float) -> SwayPrior:
    """The prior of :class:`SwayPrior` for steps dt (n-1,) s (each > 0), stationary
    offset sd ``sigma`` (m), natural frequency ``hz`` and damping ratio ``zeta``."""
    if sigma <= 0 or hz <= 0 or not 0 < zeta:
        raise ValueError(f"sway prior needs sigma, hz, zeta > 0 (got {sigma}, {hz}, {zeta})")
    w = 2.0 * math.pi * hz
    F = np.array([[0.0, 1.0], [-w * w, -2.0 * zeta * w]])
    # white acceleration noise of spectral density q holds the offset's variance at sigma^2
    q = 4.0 * zeta * w**3 * sigma**2
    dt = np.asarray(dt, dtype=np.float64)
    phi = np.empty((len(dt), 2, 2))
    W = np.empty((len(dt), 2, 2))
    for k, h in enumerate(dt):
        phi[k], Q = _van_loan(F, q, float(h))
        W[k] = np.linalg.inv(np.linalg.cholesky(Q))
    w0 = np.array([1.0 / sigma, 1.0 / (w * sigma)])
    return SwayPrior(w0=w0, phi=phi, W=W)


def _van_loan(F: F64, q: float, h: float) -> tuple[F64, F64]:
    """(2, 2) transition and (2, 2) process-noise covariance over h s of dx = F x dt + dw
    with dw white on the rate, spectral density q (Van Loan, 1978)."""
    GQG = np.array([[0.0, 0.0], [0.0, q]])
    M = np.zeros((4, 4))
    M[:2, :2] = -F
    M[:2, 2:] = GQG
    M[2:, 2:] = F.T
    E = expm(M * h)
    phi = E[2:, 2:].T
    Q = phi @ E[:2, 2:]
    return phi, 0.5 * (Q + Q.T)


def offset_change_sd(sigma: float, hz: float, zeta: float, tau: F64) -> F64:
    """(m,) sd of the offset's change over lags tau (m,) s under the stationary
    oscillator: sqrt(2 (R(0) - R(tau))) with its autocovariance R (underdamped)."""
    w = 2.0 * math.pi * hz
    if zeta >= 1.0:
        raise ValueError("offset_change_sd is for an underdamped mode (zeta < 1)")
    wd = w * math.sqrt(1.0 - zeta * zeta)
    tau = np.abs(np.asarray(tau, dtype=np.float64))
    ratio = zeta / math.sqrt(1.0 - zeta * zeta)
    c = np.exp(-zeta * w * tau) * (np.cos(wd * tau) + ratio * np.sin(wd * tau))
    return sigma * np.sqrt(np.maximum(2.0 * (1.0 - c), 0.0))
