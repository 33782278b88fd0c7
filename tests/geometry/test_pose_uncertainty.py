"""Pose-track uncertainty: known covariances, the anchor's pixel Jacobian, the bound's
coverage by Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.pose_uncertainty import (
    PoseInformation,
    _perturbed,
    anchor_bound_px,
    anchor_pixel_jacobian,
    gaussian_radius_quantile,
)

F = 5000.0  # focal length (px) of the test camera, looking along the base's x axis


def _project(p_world: np.ndarray, T_world_base: np.ndarray) -> np.ndarray:
    p = np.linalg.solve(T_world_base, np.append(p_world, 1.0))[:3]
    return F * np.array([-p[1] / p[0], -p[2] / p[0]])


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_independent_frames_have_no_cross_covariance() -> None:
    info = PoseInformation.independent(0.001, 0.1, 5)
    C = info.covariance(1, 3)
    np.testing.assert_allclose(np.diag(C), [1e-6] * 3 + [1e-2] * 3 + [1e-6] * 3 + [1e-2] * 3)
    assert np.max(np.abs(C[:6, 6:])) < 1e-12


def test_random_walk_relative_variance_grows_with_the_lag() -> None:
    s_rot, s_pos = 0.0002, 0.01
    info = PoseInformation.random_walk(s_rot, s_pos, 30)
    for r, i in ((0, 1), (3, 13), (5, 29)):
        rel = info.relative_covariance(r, i)
        np.testing.assert_allclose(
            np.diag(rel), (i - r) * np.array([s_rot**2] * 3 + [s_pos**2] * 3), rtol=1e-6
        )


def test_npz_round_trip() -> None:
    info = PoseInformation.random_walk(0.001, 0.01, 7)
    info.scale = 2.5
    back = PoseInformation.from_npz_bytes(info.to_npz_bytes())
    assert back.n_frames == 7 and back.scale == 2.5
    np.testing.assert_allclose(back.covariance(0, 6), info.covariance(0, 6))


def test_pixel_jacobian_knows_a_lateral_offset() -> None:
    """Moving the viewing frame 1 cm to the left moves an object 30 m ahead by
    F * 0.01 / 30 px to the right; the same move of the mapping frame cancels it."""
    T_r, T_i = _pose(0.0), _pose(10.0)
    p_obj = np.array([40.0, 0.0, 0.0])
    J = anchor_pixel_jacobian(_project, T_r, T_i, p_obj)
    np.testing.assert_allclose(J[0, 6 + 4], F / 30.0, rtol=1e-4)  # dp_i along y
    np.testing.assert_allclose(J[0, 4], -F / 30.0, rtol=1e-4)  # dp_r along y
    assert abs(J[1, 6 + 4]) < 1e-6


def test_the_bound_covers_90_percent_of_sampled_errors() -> None:
    rng = np.random.default_rng(3)
    T_r, T_i = _pose(0.0), _pose(15.0)
    p_obj = np.array([50.0, 1.0, 0.5])
    info = PoseInformation.random_walk(np.radians(0.01), 0.01, 20, np.radians(0.05), 0.1)
    C = info.covariance(2, 17)
    J = anchor_pixel_jacobian(_project, T_r, T_i, p_obj)
    bound = anchor_bound_px(J, C, 0.9)
    L = np.linalg.cholesky(C + 1e-18 * np.eye(12))
    q = np.linalg.solve(T_r, np.append(p_obj, 1.0))
    base = _project(p_obj, T_i)
    errs = []
    for _ in range(2000):
        d = L @ rng.standard_normal(12)
        p = (_perturbed(T_r, d[:6]) @ q)[:3]
        errs.append(np.linalg.norm(_project(p, _perturbed(T_i, d[6:])) - base))
    inside = float(np.mean(np.array(errs) <= bound))
    # the exact 90 % radius of the propagated Gaussian: 90 % within 3 binomial sigmas
    # (0.0067 at 2000 samples), neither loose nor tight
    assert abs(inside - 0.9) <= 0.02, (inside, bound)


def test_radius_quantile_matches_the_closed_forms_and_sampling() -> None:
    # a circle: r = sigma sqrt(-2 ln(1 - q)); a flat ellipse: the 1-D two-sided quantile
    assert gaussian_radius_quantile(4.0, 4.0, 0.9) == pytest.approx(
        2.0 * np.sqrt(-2.0 * np.log(0.1)), rel=1e-6
    )
    assert gaussian_radius_quantile(4.0, 0.0, 0.9) == pytest.approx(2.0 * 1.6448536, rel=1e-6)
    assert gaussian_radius_quantile(0.0, 0.0, 0.9) == 0.0
    rng = np.random.default_rng(7)
    for lam1, lam2, q in ((9.0, 1.0, 0.9), (1.0, 0.02, 0.5), (2.0, 1.5, 0.95)):
        z = rng.standard_normal((400_000, 2))
        d = np.sqrt(lam1 * z[:, 0] ** 2 + lam2 * z[:, 1] ** 2)
        got = gaussian_radius_quantile(lam1, lam2, q)
        assert np.mean(d <= got) == pytest.approx(q, abs=0.002), (lam1, lam2, q)


def test_pixel_jacobian_in_one_batched_projection_matches_the_loop() -> None:
    """The 13 projections taken in one call (a perturbed viewing pose as the point it
    puts in the unperturbed one's view) give the loop's Jacobian."""
    T_r, T_i = _pose(0.0), _pose(12.0)
    T_i[:3, :3] = Rotation.from_euler("zyx", [3.0, -1.0, 0.5], degrees=True).as_matrix()
    p_obj = np.array([45.0, -2.0, 1.2])

    def many(P: np.ndarray, T: np.ndarray) -> np.ndarray:
        return np.stack([_project(p, T) for p in P])

    loop = anchor_pixel_jacobian(_project, T_r, T_i, p_obj)
    batched = anchor_pixel_jacobian(_project, T_r, T_i, p_obj, many)
    np.testing.assert_allclose(batched, loop, rtol=1e-5, atol=1e-6 * np.abs(loop).max())
    assert np.abs(loop[:, 6:]).max() > 1.0  # the viewing pose's columns are not empty
