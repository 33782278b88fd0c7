"""Sensor noise: measured in synthetic frames of known noise, and matched inside the
composited object (robust noise ratio inside / outside in [0.8, 1.25], the issue's bound)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from renderer.composite import FEATHER_SIGMA_PX, blur_sigma_px, composite
from renderer.object_render import ObjectRender, edge_var_px2
from renderer.sensor_noise import (
    edge_sigma_px,
    estimate_noise,
    robust_sigma,
    sharpness_inside_outside,
    silhouette_band,
)

H, W = 240, 320


def sigma_of(level: np.ndarray) -> np.ndarray:
    """The synthetic sensor: std 1.5 + 0.04 x level (8-bit units), shot-noise-like."""
    return 1.5 + 0.04 * level


def noisy_frame(seed: int, texture: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal ramp 20 -> 230 (every intensity bin sampled), a few edges, plus
    known noise; returns (frame uint8, the clean frame)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(20.0, 230.0, W)
    clean = np.repeat(np.tile(x, (H, 1))[..., None], 3, axis=2)
    clean[:, :, 1] *= 0.95
    clean[60:64, :, :] = 40.0  # edges and lines: real frames are not all flat
    clean[:, 200:203, :] = 210.0
    if texture:
        clean += 6.0 * np.sin(np.arange(W) / 3.0)[None, :, None]
    noisy = clean + sigma_of(clean) * rng.standard_normal(clean.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8), clean


def square(level_lin: float, roi=(100, 60, 220, 180), size: int = 80) -> ObjectRender:
    """A square of ``size`` px turned by 2 degrees, its coverage the mean of 8 x 8
    supersamples like the renderer's (edge spread ``edge_var_px2(8)``: a binary
    pixel-aligned mask has none and would not be the render it claims to be)."""
    u0, v0, u1, v1 = roi
    h, w = v1 - v0, u1 - u0
    s = 8
    hi = np.zeros((h * s, w * s), np.float32)
    corners = cv2.boxPoints(((w * s / 2, h * s / 2), (size * s, size * s), 2.0))
    cv2.fillPoly(hi, [np.round(corners).astype(np.int32)], 1.0)
    alpha = np.asarray(cv2.resize(hi, (w, h), interpolation=cv2.INTER_AREA), np.float32)
    yy = np.linspace(0.9, 1.1, h, dtype=np.float32)[:, None, None]
    color = np.where(alpha[..., None] > 0, level_lin * yy, 0.0).astype(np.float32) * np.ones(3)
    return ObjectRender(
        roi=roi, color=color.astype(np.float32), alpha=alpha,
        depth=np.where(alpha > 0, 30.0, np.nan).astype(np.float32),
        shadow=np.zeros((h, w), np.float32), visible_fraction=1.0,
        anchor_uv=np.array([160.0, 160.0]), bbox=(0.0, 0.0, 1.0, 1.0), distance_m=30.0,
        focal_px=1000.0, pixel_scale=1.0, edge_var_px2=edge_var_px2(s),
    )  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_estimate_matches_the_known_noise_per_level(seed: int) -> None:
    img, _ = noisy_frame(seed, texture=seed == 2)
    exclude = np.zeros((H, W), bool)
    exclude[80:160, 120:200] = True
    prof = estimate_noise(img, (0, 0, W, H), exclude)
    assert prof is not None
    for c in range(3):
        for lev, sig in zip(prof.levels[1:-1], prof.sigma[c, 1:-1], strict=True):
            want = sigma_of(lev)
            assert 0.8 <= sig / want <= 1.25, (c, lev, sig, want)


def test_a_large_window_is_measured_on_bands_to_the_same_noise() -> None:
    """A window of 5.7x ``MAX_PIXELS`` (the frame tiled 5 x 5 with fresh noise): measured
    on every 6th band of rows, the estimate is still within the issue's [0.8, 1.25] of the
    known noise at every level, with lines that cross the bands (every 100th row)."""
    from renderer.sensor_noise import BAND_ROWS, MAX_PIXELS, band_rows

    tiles = [[noisy_frame(10 + 5 * i + j)[0] for j in range(5)] for i in range(5)]
    big = np.stack([np.block([[t[..., c] for t in row] for row in tiles]) for c in range(3)], 2)
    h, w = big.shape[:2]
    rows = band_rows(h, w)
    assert len(rows) * w <= MAX_PIXELS < h * w and len(rows) % BAND_ROWS == 0
    exclude = np.zeros((h, w), bool)
    exclude[400:800, 500:1000] = True
    prof = estimate_noise(big, (0, 0, w, h), exclude)
    assert prof is not None and prof.samples < MAX_PIXELS
    x = np.linspace(20.0, 230.0, W)
    for c in range(3):
        for lev, sig in zip(prof.levels[1:-1], prof.sigma[c, 1:-1], strict=True):
            if x.min() <= lev <= x.max():
                want = sigma_of(lev)
                assert 0.8 <= sig / want <= 1.25, (c, lev, sig, want)


@pytest.mark.parametrize(("level", "seed"), [(0.05, 3), (0.25, 4), (0.6, 5)])
def test_noise_inside_the_object_matches_the_frame(level: float, seed: int) -> None:
    img, _ = noisy_frame(seed)
    r = square(level)
    out = composite(img, r, lab_match=False, noise_seed=seed)
    u0, v0, u1, v1 = r.roi
    inner = np.zeros((H, W), bool)
    inner[v0:v1, u0:u1] = r.alpha > 0.99
    inner &= (
        np.roll(inner, 4, 0) & np.roll(inner, -4, 0) & np.roll(inner, 4, 1) & np.roll(inner, -4, 1)
    )
    value = out[inner].astype(float).mean(axis=0)
    quiet = composite(img, r, lab_match=False, match_noise=False)
    for c in range(3):
        got = robust_sigma(out[..., c], inner)
        want = float(sigma_of(value[c]))  # the frame's noise at the object's level
        assert 0.8 <= got / want <= 1.25, (c, got, want)
        assert robust_sigma(quiet[..., c], inner) < 0.35 * want  # noise-free without it
    # outside the object nothing changed
    changed = np.any(out != img, axis=2)
    grown = np.zeros((H, W), bool)
    grown[v0:v1, u0:u1] = r.alpha > 0
    assert not np.any(changed & ~_dilate(grown, 4))


def _dilate(m: np.ndarray, k: int) -> np.ndarray:
    out = m.copy()
    for _ in range(k):
        out = (
            out
            | np.roll(out, 1, 0)
            | np.roll(out, -1, 0)
            | np.roll(out, 1, 1)
            | np.roll(out, -1, 1)
        )
    return out


def test_same_seed_same_bytes_and_no_noise_on_clean_frames() -> None:
    img, clean = noisy_frame(7)
    r = square(0.3)
    a = composite(img, r, noise_seed=3)
    assert np.array_equal(a, composite(img, r, noise_seed=3))
    assert not np.array_equal(a, composite(img, r, noise_seed=4))
    flat = np.clip(np.round(clean), 0, 255).astype(np.uint8)
    b = composite(flat, r, lab_match=False)
    u0, v0, u1, v1 = r.roi
    inner = np.zeros((H, W), bool)
    inner[v0 + 30 : v1 - 30, u0 + 30 : u1 - 30] = True
    assert robust_sigma(b[..., 1], inner) < 0.6  # a noise-free frame: nothing added


# ----------------------------------------------------------------- sharpness
@pytest.mark.parametrize("sigma", [0.8, 1.5, 2.5])
def test_edge_sigma_recovers_a_known_blur(sigma: float) -> None:
    rng = np.random.default_rng(int(sigma * 10))
    img = np.full((100, 100), 60.0, np.float32)
    img[:, 50:] = 180.0
    img = cv2.GaussianBlur(img, (0, 0), sigma) + rng.normal(0, 2.0, img.shape)
    pts = np.stack([np.full(60, 49.5), np.arange(20, 80)], 1)
    s = edge_sigma_px(img, pts, np.tile([1.0, 0.0], (60, 1)))
    assert abs(np.nanmedian(s) / sigma - 1.0) < 0.15


def test_object_edges_as_sharp_as_the_frames() -> None:
    """A frame whose real edges are blurred by the sigma the composite gives the object:
    the measured silhouette and real-edge sigmas agree within [0.8, 1.25]."""
    r = square(0.5)
    want = float(np.hypot(blur_sigma_px(r), FEATHER_SIGMA_PX))
    rng = np.random.default_rng(11)
    clean = np.full((H, W, 3), 50.0, np.float32)
    for x in range(20, W, 40):  # stripes: real edges all around the object
        clean[:, x : x + 20] = 170.0
    clean = cv2.GaussianBlur(clean, (0, 0), want)
    img = np.clip(np.round(clean + rng.normal(0, 2.0, clean.shape)), 0, 255).astype(np.uint8)
    out = composite(img, r, lab_match=False)
    s_obj, s_real = sharpness_inside_outside(out, r.roi, r.alpha)
    assert 0.8 <= s_obj / s_real <= 1.25, (s_obj, s_real, want)
    assert abs(s_real / want - 1.0) < 0.2


def test_real_edges_read_in_the_frame_before_the_object() -> None:
    """With ``real_rgb`` the ring's real edges are read in the frame the object was added
    to: edges the composite changed around the object (its shadow's) do not count."""
    r = square(0.5)
    want = float(np.hypot(blur_sigma_px(r), FEATHER_SIGMA_PX))
    rng = np.random.default_rng(12)
    clean = np.full((H, W, 3), 50.0, np.float32)
    for x in range(20, W, 40):
        clean[:, x : x + 20] = 170.0
    clean = cv2.GaussianBlur(clean, (0, 0), want)
    img = np.clip(np.round(clean + rng.normal(0, 2.0, clean.shape)), 0, 255).astype(np.uint8)
    out = composite(img, r, lab_match=False)
    a = np.zeros((H, W), np.float32)
    u0, v0, u1, v1 = r.roi
    a[v0:v1, u0:u1] = r.alpha
    ring = ~cv2.dilate((a > 0.02).astype(np.uint8), np.ones((11, 11), np.uint8)).astype(bool)
    softened = out.copy()
    softened[ring] = cv2.GaussianBlur(out, (0, 0), 1.5)[ring]  # like a soft shadow's edges
    _, s_soft = sharpness_inside_outside(softened, r.roi, r.alpha)
    _, s_real = sharpness_inside_outside(softened, r.roi, r.alpha, real_rgb=img)
    assert s_soft > 1.5 * want, (s_soft, want)
    assert abs(s_real / want - 1.0) < 0.2, (s_real, want)


def test_edge_sigma_reads_steps_only() -> None:
    """Across a 5 px bar (its far side within the profile: a thin limb) no sigma is
    read, across a fine texture at most a quarter of the profiles (the monotonic
    envelope alone read the bar and two thirds of the texture: 1.8 px in the median);
    across the step next to them the known blur is."""
    rng = np.random.default_rng(5)
    img = np.full((120, 160), 60.0, np.float32)
    img[:, 40:45] = 180.0  # a thin bar
    img[:, 100:] = 180.0  # a step
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (40, 160)).astype(np.float32), (0, 0), 1.2)
    img[80:120] = 120.0 + 40.0 * tex / tex.std()  # a fine texture, no steps
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 2.0, img.shape)
    rows = np.arange(10, 70)
    right = np.tile([1.0, 0.0], (len(rows), 1))
    bar = edge_sigma_px(img, np.stack([np.full(len(rows), 39.5), rows], 1), right)
    assert np.isnan(bar).all()
    step = edge_sigma_px(img, np.stack([np.full(len(rows), 99.5), rows], 1), right)
    assert abs(np.nanmedian(step) / 0.8 - 1.0) < 0.15 and np.isfinite(step).all()
    tv, tu = np.mgrid[85:115:3, 10:150:3]
    pts = np.stack([tu.ravel(), tv.ravel()], 1).astype(float)
    gy, gx = np.gradient(cv2.GaussianBlur(img, (0, 0), 1.0))
    g = np.stack([gx[tv, tu].ravel(), gy[tv, tu].ravel()], 1)
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)
    texture = edge_sigma_px(img, pts, g)
    assert np.isfinite(texture).mean() < 0.25, np.isfinite(texture).mean()


def test_silhouette_band_follows_every_side() -> None:
    """The band of a binary square (smoothed as sharpness_inside_outside does) runs
    along all four sides on both sides of the boundary; the old band |a - 0.5| < 0.2
    held its corners only. A disc's anti-aliased coverage and its binary mask give
    the same band but for a few pixels."""
    a = np.zeros((120, 120), np.float32)
    a[20:100, 30:90] = 1.0
    band = silhouette_band(cv2.GaussianBlur(a, (5, 5), 1.0))
    for rows, cols in (
        (slice(19, 21), slice(35, 85)),
        (slice(99, 101), slice(35, 85)),
        (slice(25, 95), slice(29, 31)),
        (slice(25, 95), slice(89, 91)),
    ):
        assert band[rows, cols].all()
    old = np.abs(cv2.GaussianBlur(a, (5, 5), 1.0) - 0.5) < 0.2
    assert not old[25:95, 29:31].any()
    yy, xx = (np.mgrid[0:480, 0:480] + 0.5) / 4.0
    disc = ((xx - 60.2) ** 2 + (yy - 59.7) ** 2 < 30.0**2).astype(np.float32)
    soft = cv2.resize(disc, (120, 120), interpolation=cv2.INTER_AREA)
    b_soft = silhouette_band(cv2.GaussianBlur(soft, (5, 5), 1.0))
    b_bin = silhouette_band(cv2.GaussianBlur((soft > 0.5).astype(np.float32), (5, 5), 1.0))
    assert (b_soft != b_bin).sum() <= 0.05 * b_soft.sum()


def test_remap_rows_takes_more_points_than_opencv_maps_hold() -> None:
    """40 000 sample rows (OpenCV's maps stop at 32 767): the same values as one remap of
    each half."""
    import cv2

    from renderer.sensor_noise import remap_rows

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, (50, 60)).astype(np.float32)
    mx = rng.uniform(0, 59, (40000, 3)).astype(np.float32)
    my = rng.uniform(0, 49, (40000, 3)).astype(np.float32)
    out = remap_rows(img, mx, my)
    assert out.shape == (40000, 3)
    half = cv2.remap(img, mx[20000:], my[20000:], cv2.INTER_LINEAR)
    assert np.array_equal(out[20000:], half)
    # bilinear: a sample at a pixel centre is that pixel
    exact = remap_rows(img, np.array([[7.0]], np.float32), np.array([[3.0]], np.float32))
    assert exact[0, 0] == img[3, 7]


def test_robust_sigma_on_bands_of_a_large_channel_reads_the_same_noise():
    """A 1200 x 1000 channel of std 3 on a ramp, with a 40 px bright bar every 64 rows (so
    that an operator straddling two bands would see a step): the banded estimate (every
    k-th band of rows, their edge rows left out) reads the noise within 3 % of the full
    one and of the truth."""
    rng = np.random.default_rng(5)
    clean = np.tile(np.linspace(40.0, 200.0, 1000), (1200, 1))
    clean[(np.arange(1200) % 64) >= 24] += 30.0
    ch = (clean + 3.0 * rng.standard_normal(clean.shape)).astype(np.float32)
    full = robust_sigma(ch)
    banded = robust_sigma(ch, max_pixels=200_000)
    assert abs(banded - 3.0) < 0.09 and abs(banded - full) < 0.09
    assert robust_sigma(ch[:100, :100], max_pixels=200_000) == robust_sigma(ch[:100, :100])
