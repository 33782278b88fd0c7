"""Robust spread of samples: the median absolute deviation scaled to a Gaussian sigma."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: MAD -> sigma for Gaussian samples (1 / Phi^-1(3/4)).
MAD_TO_SIGMA = 1.4826


def mad_sigma(x: ArrayLike, axis: int | None = None, centred: bool = True) -> NDArray[np.float64]:
    """``MAD_TO_SIGMA`` x median |x - median(x)| along ``axis`` (about zero when not
    ``centred``: residuals that should be zero). A scalar array for ``axis`` None."""
    a = np.asarray(x, dtype=np.float64)
    centre = np.median(a, axis=axis, keepdims=True) if centred else 0.0
    return MAD_TO_SIGMA * np.median(np.abs(a - centre), axis=axis)
