"""Lidar range noise and dropout measured on synthetic scans of known noise: a spinning
lidar over a ground with sleeper-like steps and a wall, a rosette-like one-point-per-time
scan, and a cloud without timestamps (renderer/lidar_noise.py; bound [0.8, 1.25])."""

from __future__ import annotations

import numpy as np
import pytest

from renderer.lidar_noise import (
    core_sigma,
    measure_lidar_noise,
    planar_core_sigma,
    standardised_residuals,
)

H = 3.5  # sensor height (m)


def _hit(o: np.ndarray, u: np.ndarray, slabs: bool = True) -> np.ndarray:
    """Ranges (n,) of rays from ``o`` (3,) along ``u`` (n, 3) on a ground z = 0 with
    0.28 m wide, 0.15 m high slabs every 0.6 m along x (tops only) and a wall at y = 6."""
    r = -o[2] / u[:, 2]
    r_top = (0.15 - o[2]) / u[:, 2]
    x_top = o[0] + r_top * u[:, 0]
    on_slab = (np.mod(x_top, 0.6) < 0.28) & slabs
    r = np.where(on_slab, r_top, r)
    with np.errstate(divide="ignore"):
        r_wall = np.where(u[:, 1] > 1e-9, (6.0 - o[1]) / u[:, 1], np.inf)
    return np.minimum(r, r_wall)


def spinning_scan(
    sigma: float, dropout: float, seed: int, n_col: int = 900, slabs: bool = True
) -> dict:
    """One sweep of a 48-beam spinning lidar at (0, 0, H) over ``_hit``'s scene: columns
    share a timestamp; Gaussian range noise truncated at 3 sigma; random dropout."""
    rng = np.random.default_rng(seed)
    az = np.radians(np.arange(-45.0, 45.0, 360.0 / n_col))
    el = np.radians(np.linspace(-3.0, -20.0, 48))
    A, E = np.meshgrid(az, el, indexing="ij")
    u = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t = 1.6e9 + np.repeat(np.arange(len(az)) * 1e-4, len(el))
    o = np.array([0.0, 0.0, H])
    r = _hit(o, u, slabs) + sigma * np.clip(rng.standard_normal(len(u)), -3, 3)
    keep = (rng.random(len(u)) >= dropout) & (r < 60.0)
    p = o + r[keep, None] * u[keep]
    return {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "timestamp": t[keep],
            "sensor_index": np.zeros(keep.sum(), np.uint8)}  # fmt: skip


def rosette_scan(sigma: float, dropout: float, seed: int, n: int = 20000) -> dict:
    """A rose curve of directions fired one point per time step over the same scene."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    c1, c2 = 131.7 * k * 5e-6, 83.9 * k * 5e-6
    a = np.radians(7.0) / 2.0
    du = a * (np.cos(2 * np.pi * c1) + np.cos(2 * np.pi * c2))
    dv = a * (np.sin(2 * np.pi * c1) - np.sin(2 * np.pi * c2)) - np.radians(12.0)
    u = np.stack([np.ones(n), du, dv], 1)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = np.array([0.0, 0.0, H])
    r = _hit(o, u) + sigma * np.clip(rng.standard_normal(n), -3, 3)
    keep = rng.random(n) >= dropout
    p = o + r[keep, None] * u[keep]
    return {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "timestamp": 1.6e9 + k[keep] * 5e-6,
            "sensor_index": np.full(keep.sum(), 1, np.uint8)}  # fmt: skip


@pytest.mark.parametrize(("sigma", "seed"), [(0.01, 0), (0.02, 1), (0.04, 2)])
def test_spinning_range_noise_and_dropout_over_steps(sigma: float, seed: int) -> None:
    cloud = spinning_scan(sigma, 0.02, seed)
    est = measure_lidar_noise(cloud, {0: [0.0, 0.0, H]}, [15.0, 0.0, 1.0], 1.5, shell_m=12.0)
    n = est[0]
    assert 0.8 <= n.range_sigma_m / sigma <= 1.25, n
    assert 0.8 <= n.dropout / 0.02 <= 1.25, n
    assert 10 <= n.rings <= 48  # the beams that reach the shell


@pytest.mark.parametrize(("sigma", "seed"), [(0.02, 3), (0.05, 4)])
def test_rosette_range_noise_and_dropout(sigma: float, seed: int) -> None:
    cloud = rosette_scan(sigma, 0.02, seed)
    est = measure_lidar_noise(cloud, {1: [0.0, 0.0, H]}, [15.0, 0.0, 1.0], 1.5, shell_m=20.0)
    n = est[1]
    assert 0.8 <= n.range_sigma_m / sigma <= 1.25, n
    assert 0.8 <= n.dropout / 0.02 <= 1.25, n
    assert n.rings == 0  # one point per time: no beams


def test_without_timestamps_the_direction_neighbours_do() -> None:
    """The fallback (2-D patches, more often across an edge) on a ground without steps;
    the dropout from the gaps along elevation rings (none here)."""
    cloud = spinning_scan(0.02, 0.0, 5, slabs=False)
    del cloud["timestamp"]
    n = measure_lidar_noise(cloud, {0: [0.0, 0.0, H]}, [15.0, 0.0, 1.0], 1.5, shell_m=12.0)[0]
    assert 0.8 <= n.range_sigma_m / 0.02 <= 1.25, n
    assert n.dropout < 0.01 and n.rings >= 5, n


def test_residuals_are_exact_on_a_plane_seen_from_any_origin() -> None:
    """Noise-free points of the ground and the wall: |z| below 0.05 mm (rounding at up to
    60 m) from the true origin and from an origin 0.6 m off (inverse range is linear
    from any origin)."""
    cloud = spinning_scan(0.0, 0.0, 6, slabs=False)
    p = np.stack([cloud[k] for k in "xyz"], 1)
    wall = (p[:, 1] > 5.99) & (p[:, 2] > 1e-9)
    for sel in (wall, p[:, 2] < 1e-9):
        for o in ([0.0, 0.0, H], [0.3, -0.5, H + 0.2]):
            oo = np.tile(o, (int(sel.sum()), 1))
            z = standardised_residuals(p[sel], oo, cloud["timestamp"][sel])
            z = z[np.isfinite(z)]
            assert len(z) > 50 and np.max(np.abs(z)) < 5e-5, (o, np.abs(z).max())


def test_core_sigma_ignores_a_wide_minority() -> None:
    rng = np.random.default_rng(7)
    z = np.concatenate([0.02 * rng.standard_normal(3000), 0.3 * rng.standard_normal(1500)])
    assert core_sigma(z) == pytest.approx(0.02, rel=0.08)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_kinks_at_the_noise_scale_are_left_out(seed: int) -> None:
    """Residuals of known noise (2 cm, 600 points on planes) mixed with 500 next to a
    kink or a step (shifted by 0.5-2.5 sigma, the noise's own scale, their neighbours'
    spread grown alike, as on a track bed): the mixture's core alone reads more than
    1.25x the noise; keeping the points whose neighbours are a plane, [0.8, 1.25]."""
    rng = np.random.default_rng(seed)
    s = 0.02
    z_plane = s * np.clip(rng.standard_normal(600), -3, 3)
    spread_plane = s * np.sqrt(rng.chisquare(3, 600) / 3)  # three degrees of freedom
    shift = s * rng.uniform(0.5, 2.5, 500) * rng.choice([-1.0, 1.0], 500)
    z_kink = shift + s * np.clip(rng.standard_normal(500), -3, 3)
    spread_kink = np.sqrt(s**2 * rng.chisquare(3, 500) / 3 + shift**2)
    z, spread = np.r_[z_plane, z_kink], np.r_[spread_plane, spread_kink]
    assert core_sigma(z) / s > 1.25
    assert 0.8 <= planar_core_sigma(z, spread) / s <= 1.25
