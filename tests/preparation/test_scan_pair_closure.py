"""The scan pairs' closure (``scan_pairs.closure_factor``): three chained 10-frame pairs
against the direct 30-frame one. Pairs drawn with the noise their sigmas state close as
the sigmas say; pairs whose lateral positions sit centimetres off with a 5 mm sigma (what
a sparse station with blind near-field lidars gave) do not."""

from __future__ import annotations

import numpy as np

from worker.preparation.localization.scan_pairs import ScanPairs, closure_factor


def _poses(n: int, step_m: float, kappa: float) -> np.ndarray:
    s = np.arange(n) * step_m
    yaw = kappa * s
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = (
        np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw),
    )  # fmt: skip
    T[:, 0, 3], T[:, 1, 3] = np.sin(yaw) / kappa, (1.0 - np.cos(yaw)) / kappa
    return T


def _pairs(lateral_sd_m: float, true_sd_m: float, seed: int) -> ScanPairs:
    rng = np.random.default_rng(seed)
    T = _poses(60, 0.9, 2e-3)
    k = np.concatenate([np.arange(50), np.arange(30)])
    j = np.concatenate([np.arange(50) + 10, np.arange(30) + 30])
    T_k_j = np.linalg.inv(T[k]) @ T[j]
    T_k_j[:, 1, 3] += rng.normal(0.0, true_sd_m, len(k))
    sd_t = np.tile([0.01, lateral_sd_m, 0.01], (len(k), 1))
    sd_r = np.full((len(k), 3), 1e-5)
    return ScanPairs(k, j, T_k_j, sd_t, sd_r, np.ones(len(k), dtype=bool))


def test_pairs_as_good_as_their_sigmas_close() -> None:
    f, m = closure_factor(_pairs(0.005, 0.005, 1), 10, 30)
    assert m == 30
    assert 0.6 < f < 1.5, f


def test_pairs_off_by_centimetres_do_not() -> None:
    f, m = closure_factor(_pairs(0.005, 0.04, 2), 10, 30)
    assert m == 30
    assert f > 5.0, f  # 4 cm of scatter against a stated 5 mm: about 8


def test_no_chain_no_closure() -> None:
    p = _pairs(0.005, 0.005, 3)
    p.ok[:50] = False  # no 10-frame link converged
    assert closure_factor(p, 10, 30) == (1.0, 0)
    assert closure_factor(p, 10, 25) == (1.0, 0)  # 25 is no multiple of 10
