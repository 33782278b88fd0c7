"""mad_sigma: a Gaussian's sigma from its MAD, unmoved by a few outliers."""

from __future__ import annotations

import numpy as np

from worker.robust_stats import mad_sigma


def test_mad_sigma_is_the_gaussian_sigma_and_ignores_outliers() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(5.0, 2.0, 20000)
    x[:100] = 1e6  # 0.5 % outliers
    assert abs(float(mad_sigma(x)) - 2.0) < 0.05
    # about zero, the offset of 5 counts as spread
    assert float(mad_sigma(x, centred=False)) > 5.0
    cols = np.stack([rng.normal(0, 1, 5000), rng.normal(0, 3, 5000)], axis=1)
    assert np.allclose(mad_sigma(cols, axis=0), [1.0, 3.0], atol=0.1)
    assert float(mad_sigma(np.full(10, 7.0))) == 0.0
