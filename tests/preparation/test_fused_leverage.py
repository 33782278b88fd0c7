"""The hat matrix diagonal of the fused solve, computed from the sparse Jacobian's rows."""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor
from scipy.sparse import diags
from scipy.sparse import random as sparse_random

from worker.preparation.localization.fused import _inverse_from_cholesky, _quadratic_forms


def _problem(seed: int) -> tuple:
    rng = np.random.default_rng(seed)
    keep = np.ones(400)
    keep[7] = 0.0  # a row with no nonzeros
    J = diags(keep) @ sparse_random(400, 60, density=0.08, random_state=rng, format="csr")
    J = J.tocsr()
    J.eliminate_zeros()
    w = rng.uniform(0.2, 1.0, J.shape[0])
    N = (J.T.multiply(w[None, :]) @ J).toarray() + 1e-3 * np.eye(J.shape[1])
    return J, w, N


def test_inverse_from_cholesky_is_the_inverse() -> None:
    _, _, N = _problem(0)
    for lower in (False, True):
        inv = _inverse_from_cholesky(cho_factor(N, lower=lower))
        assert inv is not None
        np.testing.assert_allclose(inv @ N, np.eye(len(N)), atol=1e-8)
        np.testing.assert_array_equal(inv, inv.T)


def test_quadratic_forms_match_the_dense_diagonal() -> None:
    J, w, N = _problem(1)
    inv = np.linalg.inv(N)
    dense = np.einsum("ij,jk,ik->i", J.toarray(), inv, J.toarray())
    got = _quadratic_forms(J, inv)
    assert got[7] == 0.0
    np.testing.assert_allclose(got, dense, rtol=1e-10, atol=1e-14)
    # the leverages w h of a weighted least-squares fit sum to its parameter count
    assert abs(float(np.sum(w * got)) - J.shape[1]) < 0.5
