"""zero_centre: scipy's MAD about zero equals the Gaussian sigma of zero-mean residuals and
grows with an offset (the reason to measure about zero, not about the median)."""

from __future__ import annotations

import numpy as np
from scipy.stats import median_abs_deviation

from geometry.columns import zero_centre


def test_spread_about_zero_sees_an_offset_the_median_hides() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(0.0, 2.0, 20000)
    about_zero = median_abs_deviation(x, center=zero_centre, scale="normal")
    assert abs(about_zero - 2.0) < 0.05
    shifted = x + 5.0
    assert median_abs_deviation(shifted, center=zero_centre, scale="normal") > 5.0
    assert abs(median_abs_deviation(shifted, scale="normal") - 2.0) < 0.05
    cols = np.column_stack([rng.normal(0, 1, 5000), rng.normal(0, 3, 5000)])
    np.testing.assert_allclose(
        median_abs_deviation(cols, axis=0, center=zero_centre, scale="normal"), [1, 3], atol=0.1
    )
