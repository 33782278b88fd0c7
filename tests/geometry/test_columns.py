"""The column-wise reductions give exactly NumPy's axis reductions."""

from __future__ import annotations

import numpy as np

from geometry.columns import column_max, column_min, finite_rows


def test_column_reductions_equal_numpys() -> None:
    rng = np.random.default_rng(0)
    for a in (
        rng.normal(size=(1000, 3)),
        rng.integers(-50, 50, size=(777, 2)),
        rng.normal(size=(1, 3)).astype(np.float32),
    ):
        np.testing.assert_array_equal(column_min(a), a.min(axis=0))
        np.testing.assert_array_equal(column_max(a), a.max(axis=0))
        assert column_min(a).dtype == a.dtype


def test_finite_rows_flags_every_kind_of_non_finite_value() -> None:
    a = np.ones((6, 3))
    a[1, 0], a[2, 1], a[3, 2], a[4] = np.nan, np.inf, -np.inf, np.nan
    np.testing.assert_array_equal(finite_rows(a), [True, False, False, False, False, True])
    np.testing.assert_array_equal(finite_rows(a), np.isfinite(a).all(axis=1))
