"""Reductions of (n, k) point arrays (k small: 2 or 3), one column at a time.

NumPy reduces a C-ordered (n, 3) array along either axis through a generic strided loop
that is several times slower than reducing each column on its own. Measured on 900k x 3
float64: ``min(axis=0)`` 7.0 ms against 0.7 ms; ``isfinite(p).all(axis=1)`` 18.7 ms
against 6.2 ms. Preparation does these on every frame and on registered clouds of
millions of points, so its hot paths use these helpers. The results are exactly NumPy's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


def column_min(a: NDArray[Any]) -> NDArray[Any]:
    """(k,) smallest value of each column of (n, k) ``a`` (n >= 1)."""
    return np.array([a[:, i].min() for i in range(a.shape[1])], dtype=a.dtype)


def column_max(a: NDArray[Any]) -> NDArray[Any]:
    """(k,) largest value of each column of (n, k) ``a`` (n >= 1)."""
    return np.array([a[:, i].max() for i in range(a.shape[1])], dtype=a.dtype)


def finite_rows(a: NDArray[Any]) -> NDArray[np.bool_]:
    """(n,) whether every value of each row of (n, k) ``a`` is finite."""
    out: NDArray[np.bool_] = np.isfinite(a[:, 0])
    for i in range(1, a.shape[1]):
        out &= np.isfinite(a[:, i])
    return out


def zero_centre(a: NDArray[np.float64], axis: int | None = None) -> NDArray[np.float64]:
    """Zeros shaped like ``np.median(a, axis=axis)``: the ``center`` to give
    ``scipy.stats.median_abs_deviation`` for residuals that should be zero (their spread
    about zero, not about their median)."""
    return np.zeros_like(np.median(a, axis=axis))
