"""The frame's own blur, measured from its straight step edges (renderer/frame_blur.py),
and given to the composited object.

Test frames are made as a camera makes them: a scene drawn at ``S`` x the resolution,
blurred by a Gaussian of known sigma, integrated over the pixels (area averaging),
noise of known std added, rounded to 8 bits. The edge spread the pixels hold has the
variance ``sigma^2 + (1 - 1/S^2) / 12`` (the Gaussian, the pixel's box); that is what the
estimate must give, within ``TOL`` (15 %, chosen before measuring), from 0.3 to 2 px,
with noise of 2 and 4 levels, also where ballast-like texture (stones of 1.5-6 px, 1-px
grain) holds nearly all the frame's edges.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from renderer.composite import composite, gaussian_blur, gaussian_kernel
from renderer.frame_blur import candidate_pixels, estimate_blur_sigma
from renderer.sensor_noise import sharpness_inside_outside
from tests.renderer.test_sensor_noise import square

H, W = 240, 320
S = 8  # supersampling of the drawn scenes
TOL = 0.15
SIGMAS = [0.3, 0.5, 0.8, 1.2, 2.0]


def true_spread(sigma: float) -> float:
    """The edge spread (px) of a scene blurred by ``sigma`` and integrated over pixels."""
    return float(np.sqrt(sigma**2 + (1.0 - 1.0 / S**2) / 12.0))


def camera(scene_s: np.ndarray, sigma: float, noise: float, seed: int) -> np.ndarray:
    """(H, W, 3) uint8 of a scene (H S, W S) float32 levels: blur, pixel box, noise."""
    img = cv2.GaussianBlur(scene_s, (0, 0), sigma * S)
    img = cv2.resize(img, (scene_s.shape[1] // S, scene_s.shape[0] // S),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    img = img + np.random.default_rng(seed + 1000).normal(0.0, noise, img.shape)
    g = np.clip(np.round(img), 0, 255).astype(np.uint8)
    return np.dstack([g, g, g])


def boxes(seed: int, n: int = 30) -> np.ndarray:
    """Rectangles of 15-50 px at random angles and levels on a flat ground."""
    rng = np.random.default_rng(seed)
    out = np.full((H * S, W * S), 60.0, np.float32)
    for _ in range(n):
        c = rng.uniform([0, 0], [W, H]) * S
        size = rng.uniform(15, 50, 2) * S
        pts = cv2.boxPoints(((c[0], c[1]), (size[0], size[1]), rng.uniform(0, 180)))
        cv2.fillPoly(out, [np.round(pts).astype(np.int32)], float(rng.uniform(30, 220)))
    return out


def ballast(seed: int, track: bool = True) -> np.ndarray:
    """Stones (ellipses of 1.5-6 px, levels 50-200) with a 1-px grain of std 10 levels
    everywhere; with ``track``, over the middle half of the width: a flat far
    background over the top quarter with a mast, and two rails (a bright head over a
    dark shadow, 8 px each, slanted by 2 degrees as perspective has them). Their edges
    are under a tenth of the frame's."""
    rng = np.random.default_rng(seed)
    out = np.full((H * S, W * S), 90.0, np.float32)
    for _ in range(H * W // 12):
        c = rng.uniform([0, 0], [W, H]) * S
        ax = rng.uniform(1.5, 6.0, 2) * S
        box = ((float(c[0]), float(c[1])), (float(ax[0]), float(ax[1])), rng.uniform(0, 180))
        cv2.ellipse(out, box, float(rng.uniform(50, 200)), -1)
    grain = rng.normal(0.0, 10.0, (H, W)).astype(np.float32)
    out += cv2.resize(grain, (W * S, H * S), interpolation=cv2.INTER_NEAREST)
    if track:
        top = H // 4 * S
        out[:top, W // 4 * S : 3 * W // 4 * S] = 150.0
        out[:top, int(W * 0.6) * S : int(W * 0.6 + 12) * S] = 60.0
        slope = np.tan(np.radians(2.0))
        for y0 in (0.5 * H, 0.8 * H):
            for dy, level in ((0.0, 210.0), (8.0, 35.0)):
                a, b = W // 4, 3 * W // 4
                ya, yb = y0 + dy + a * slope, y0 + dy + b * slope
                pts = np.array([[a, ya], [b, yb], [b, yb + 8], [a, ya + 8]])
                cv2.fillPoly(out, [np.round(pts * S).astype(np.int32)], level)
    return out


EXCLUDE = np.zeros((H, W), bool)
EXCLUDE[80:160, 120:200] = True


@pytest.mark.parametrize("noise", [2.0, 4.0])
@pytest.mark.parametrize("sigma", SIGMAS)
@pytest.mark.parametrize("kind", ["boxes", "ballast"])
def test_estimate_recovers_a_known_blur(kind: str, sigma: float, noise: float) -> None:
    scene = boxes(int(sigma * 10)) if kind == "boxes" else ballast(int(sigma * 10))
    est = estimate_blur_sigma(camera(scene, sigma, noise, 1), (0, 0, W, H), EXCLUDE)
    assert est is not None
    assert abs(est / true_spread(sigma) - 1.0) <= TOL, (est, true_spread(sigma))


def test_ballast_holds_nearly_all_the_edges() -> None:
    """The ballast frame is the hard case it is meant to be: more than 90 % of the
    Canny candidates lie in the ballast (not on the edges of the rails, the mast, the
    sky)."""
    img = camera(ballast(3), 1.0, 2.0, 3)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    from renderer.frame_blur import DERIV_SIGMA_PX, _gradient

    gx, gy = _gradient(gray, DERIV_SIGMA_PX)
    cand = candidate_pixels(gray, gx, gy, None)
    structure = np.zeros((H, W), bool)  # within 2 px of the rails', sky's, mast's edges
    structure[H // 4 - 2 : H // 4 + 3, W // 4 - 2 : 3 * W // 4 + 3] = True
    structure[: H // 4 + 3, W // 4 - 2 : W // 4 + 3] = True
    structure[: H // 4 + 3, 3 * W // 4 - 2 : 3 * W // 4 + 3] = True
    u_mast = int(W * 0.6)
    structure[: H // 4 + 3, u_mast - 2 : u_mast + 3] = True
    structure[: H // 4 + 3, u_mast + 10 : u_mast + 15] = True
    for y0 in (0.5 * H, 0.8 * H):
        for u in range(W // 4 - 2, 3 * W // 4 + 3):
            for dy in (0, 8, 16):
                y = round(y0 + dy + u * np.tan(np.radians(2.0)))
                structure[y - 2 : y + 3, u] = True
    assert cand[~structure].sum() > 0.9 * cand.sum(), (cand[~structure].sum(), cand.sum())


def test_texture_alone_gives_no_estimate() -> None:
    """Stones and grain without a straight step edge: no estimate (the composite falls
    back to the lens model) rather than a sharp one read off the texture."""
    for sigma in (0.5, 2.0):
        img = camera(ballast(5, track=False), sigma, 2.0, 5)
        assert estimate_blur_sigma(img, (0, 0, W, H), EXCLUDE) is None


def test_edges_along_the_motion_are_left_out() -> None:
    """Vertical edges only, smeared horizontally: with the motion given, only edges
    across it count; vertical ones have none, so no estimate; horizontal ones do."""
    scene = np.full((H * S, W * S), 50.0, np.float32)
    for x in range(20, W, 40):
        scene[:, (x * S + 3) : (x + 20) * S + 3] = 170.0
    img = camera(scene, 1.2, 2.0, 3)
    assert estimate_blur_sigma(img, (0, 0, W, H), None, motion_uv=(4.0, 0.0)) is None
    rot = np.ascontiguousarray(np.transpose(img, (1, 0, 2)))
    est = estimate_blur_sigma(rot, (0, 0, H, W), None, motion_uv=(4.0, 0.0))
    assert est is not None and abs(est / true_spread(1.2) - 1.0) <= TOL


def test_edges_across_the_motion_are_kept_among_many_along_it() -> None:
    """Dense horizontal stripes (edges along a vertical motion: over 12k candidates) around
    a bar whose vertical sides (about 100 edge pixels) are the only edges across it: the
    candidate cap must not thin the few usable ones out (a cap taken before the direction
    test kept a third of them, too few for an estimate)."""
    scene = np.full((H * S, W * S), 60.0, np.float32)
    for y in [*range(0, H // 2, 6), *range(H // 2 + 90, H, 6)]:
        scene[y * S : (y + 3) * S, :] = 180.0
    scene[(H // 2 + 20) * S : (H // 2 + 70) * S, 150 * S + 3 : 170 * S + 3] = 190.0
    img = camera(scene, 1.2, 2.0, 4)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    from renderer.frame_blur import DERIV_SIGMA_PX, MAX_CANDIDATES, _gradient

    gx, gy = _gradient(gray, DERIV_SIGMA_PX)
    assert candidate_pixels(gray, gx, gy, None).sum() > 3 * MAX_CANDIDATES
    est = estimate_blur_sigma(img, (0, 0, W, H), None, motion_uv=(0.0, 4.0))
    assert est is not None and abs(est / true_spread(1.2) - 1.0) <= TOL, est


@pytest.mark.parametrize("sigma", [0.3, 0.49, 1.0, 2.0])
def test_the_composites_gaussian_delivers_the_variance_asked(sigma: float) -> None:
    """A point blurred by the composite's Gaussian spreads with variance sigma^2 in each
    direction (within 0.5 %; a sampled Gaussian gives 0.20 px^2 for 0.49 px)."""
    assert abs(float(gaussian_kernel(sigma).sum()) - 1.0) < 1e-6
    n = 41
    point = np.zeros((n, n), np.float32)
    point[n // 2, n // 2] = 1.0
    out = gaussian_blur(point, sigma).astype(np.float64)
    x = np.arange(n) - n // 2
    var_u = float(np.sum(out.sum(0) * x**2))
    var_v = float(np.sum(out.sum(1) * x**2))
    for var in (var_u, var_v):
        assert abs(var / sigma**2 - 1.0) <= 0.005, (var, sigma**2)


@pytest.mark.parametrize("sigma", [0.6, 1.2, 2.0])
def test_object_edges_match_the_frames_blur(sigma: float) -> None:
    """The composite gives the object the measured blur: silhouette / real edge sigma
    in [0.8, 1.25]; the lens model alone (match_sharpness off, ~0.8 px here) misses at
    2 px."""
    img = camera(boxes(20 + int(sigma * 10)), sigma, 2.0, 2)
    r = square(0.5)
    assert r.roi is not None
    out = composite(img, r, lab_match=False)
    s_obj, s_real = sharpness_inside_outside(out, r.roi, r.alpha)
    assert 0.8 <= s_obj / s_real <= 1.25, (s_obj, s_real, sigma)
    model = composite(img, r, lab_match=False, match_sharpness=False)
    m_obj, m_real = sharpness_inside_outside(model, r.roi, r.alpha)
    if sigma == 2.0:
        assert m_obj / m_real < 0.8, (m_obj, m_real, sigma)


def test_a_pinhole_camera_gets_no_defocus_floor() -> None:
    """A near object (5 m, focal 8000 px: a 4 mm aperture's defocus is 1.6 px) on a sharp
    frame (0.3 px): with the default aperture the defocus floor makes the object much
    softer than the frame, as a lens focused at infinity would; with ``aperture_m=0`` (a
    pinhole, the synthetic generator's cameras) it gets the frame's own blur."""
    import dataclasses

    from renderer.composite import defocus_sigma_px

    img = camera(boxes(31), 0.3, 2.0, 2)
    base = square(0.5)
    r = dataclasses.replace(
        base, focal_px=8000.0, distance_m=5.0, depth=np.where(base.alpha > 0, 5.0, np.nan)
    )
    assert r.roi is not None
    assert defocus_sigma_px(r) == pytest.approx(1.6, rel=0.01)
    assert defocus_sigma_px(r, aperture_m=0.0) == 0.0
    lens = composite(img, r, lab_match=False)
    s_obj, s_real = sharpness_inside_outside(lens, r.roi, r.alpha, real_rgb=img)
    assert s_obj / s_real > 2.0, (s_obj, s_real)
    pinhole = composite(img, r, lab_match=False, aperture_m=0.0)
    s_obj, s_real = sharpness_inside_outside(pinhole, r.roi, r.alpha, real_rgb=img)
    assert 0.8 <= s_obj / s_real <= 1.25, (s_obj, s_real)


def test_a_large_window_measured_on_bands_reads_the_same_blur(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 1200 x 1000 window (above ``BLUR_MAX_PIXELS``) is measured on stacked bands of
    rows with their joins left out: its estimate is the whole window's within 5 % and the
    truth within ``TOL``, as a small window's."""
    import renderer.frame_blur as fb

    h, w, s, sigma = 1200, 1000, 4, 1.2
    rng = np.random.default_rng(7)
    scene = np.full((h * s, w * s), 60.0, np.float32)
    for _ in range(400):
        c = rng.uniform([0, 0], [w, h]) * s
        size = rng.uniform(15, 60, 2) * s
        pts = cv2.boxPoints(((c[0], c[1]), (size[0], size[1]), rng.uniform(0, 180)))
        cv2.fillPoly(scene, [np.round(pts).astype(np.int32)], float(rng.uniform(30, 220)))
    img = cv2.resize(cv2.GaussianBlur(scene, (0, 0), sigma * s), (w, h),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    img = np.clip(np.round(img + rng.normal(0.0, 3.0, img.shape)), 0, 255).astype(np.uint8)
    frame = np.dstack([img, img, img])
    truth = float(np.sqrt(sigma**2 + (1.0 - 1.0 / s**2) / 12.0))
    assert len(fb.band_rows(h, w, fb.BLUR_MAX_PIXELS, fb.BLUR_BAND_ROWS)) < 0.7 * h
    banded = estimate_blur_sigma(frame, (0, 0, w, h))
    monkeypatch.setattr(fb, "BLUR_MAX_PIXELS", 10**9)
    whole = estimate_blur_sigma(frame, (0, 0, w, h))
    assert banded is not None and whole is not None
    assert abs(banded / whole - 1.0) <= 0.05, (banded, whole)
    assert abs(banded / truth - 1.0) <= TOL, (banded, truth)


def test_the_joins_of_stacked_bands_are_left_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a frame whose level ramps down the rows (0.35 levels a row) the stacked bands
    meet in sharp steps of ~34 levels across the whole width, which no camera made: left
    out (``JOIN_PX``), the banded estimate is the whole window's within 5 %; read, they
    pull it far below."""
    import renderer.frame_blur as fb

    h, w, s, sigma = 1200, 1000, 4, 1.2
    rng = np.random.default_rng(11)
    scene = np.zeros((h * s, w * s), np.float32)
    for _ in range(60):
        c = rng.uniform([0, 0], [w, h]) * s
        size = rng.uniform(15, 60, 2) * s
        pts = cv2.boxPoints(((c[0], c[1]), (size[0], size[1]), rng.uniform(0, 180)))
        cv2.fillPoly(scene, [np.round(pts).astype(np.int32)], float(rng.uniform(-60, 60)))
    img = cv2.resize(cv2.GaussianBlur(scene, (0, 0), sigma * s), (w, h),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    img += 40.0 + 0.35 * np.arange(h, dtype=np.float32)[:, None]
    img = np.clip(np.round(img + rng.normal(0.0, 2.0, img.shape)), 0, 255).astype(np.uint8)
    frame = np.dstack([img, img, img])
    rows = fb.band_rows(h, w, fb.BLUR_MAX_PIXELS, fb.BLUR_BAND_ROWS)
    assert np.count_nonzero(np.diff(rows) > 1) >= 4
    banded = estimate_blur_sigma(frame, (0, 0, w, h))
    monkeypatch.setattr(fb, "JOIN_PX", 0)
    joins_read = estimate_blur_sigma(frame, (0, 0, w, h))
    monkeypatch.setattr(fb, "BLUR_MAX_PIXELS", 10**9)
    whole = estimate_blur_sigma(frame, (0, 0, w, h))
    assert banded is not None and whole is not None and joins_read is not None
    assert abs(banded / whole - 1.0) <= 0.05, (banded, whole)
    assert joins_read < 0.8 * whole, (joins_read, whole)
