"""Compositing (ROI only, byte-identical elsewhere) and the lighting estimate."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geometry.transforms import pose_to_T
from renderer.composite import blur_sigma_px, composite, composite_into
from renderer.lighting import (
    Lighting,
    estimate_lighting,
    linear_to_srgb,
    srgb_to_linear,
    sun_dir_enu,
)
from renderer.object_render import ObjectRender


def square_render(
    roi=(40, 30, 80, 70), value: float = 1.0, shadow: bool = False, distance: float = 30.0
) -> ObjectRender:
    """A hand-made render: a 20 x 20 px square of colour ``value`` in the ROI's middle."""
    u0, v0, u1, v1 = roi
    h, w = v1 - v0, u1 - u0
    alpha = np.zeros((h, w), np.float32)
    alpha[10:30, 10:30] = 1.0
    color = np.zeros((h, w, 3), np.float32)
    color[alpha > 0] = value
    color[12:28, 12:28] *= 0.9  # some texture
    depth = np.where(alpha > 0, distance, np.nan).astype(np.float32)
    sh = np.zeros((h, w), np.float32)
    if shadow:
        sh[30:36, 5:35] = 1.0
    return ObjectRender(
        roi=roi, color=color, alpha=alpha, depth=depth, shadow=sh, visible_fraction=1.0,
        anchor_uv=np.array([u0 + 20.0, v0 + 30.0]), bbox=(u0 + 9.5, v0 + 9.5, u0 + 29.5, v0 + 29.5),
        distance_m=distance, motion_uv_per_m=np.array([3.0, 1.0]), focal_px=1152.0,
        pixel_scale=0.25,
    )  # fmt: skip


def frame(value: int = 60, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(value, 8, (120, 160, 3)), 0, 255).astype(np.uint8)


def _L(rgb_u8: np.ndarray) -> np.ndarray:
    rgb = np.ascontiguousarray(rgb_u8.reshape(-1, 1, 3)).astype(np.float32) / 255.0
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab)[:, 0, 0]


def test_outside_roi_untouched_and_none_returns_input():
    img = frame()
    r = square_render(shadow=True)
    out = composite(img, r, speed_mps=20.0)
    assert out is not img and out.shape == img.shape and out.dtype == np.uint8
    u0, v0, u1, v1 = r.roi
    mask = np.ones(img.shape[:2], bool)
    mask[v0:v1, u0:u1] = False
    assert np.array_equal(out[mask], img[mask])
    assert not np.array_equal(out[v0:v1, u0:u1], img[v0:v1, u0:u1])
    # ROI pixels far from the object and its shadow are byte-identical too
    assert np.array_equal(out[v0 : v0 + 3, u0:u1], img[v0 : v0 + 3, u0:u1])
    z = np.zeros((0, 0), np.float32)
    empty = ObjectRender(None, np.zeros((0, 0, 3), np.float32), z, z, z, 0.0,
                         np.full(2, np.nan), (np.nan,) * 4, 10.0)  # fmt: skip
    assert composite(img, empty) is img


def test_in_place_through_a_bgr_view_equals_the_copy():
    img = frame(90)
    r = square_render(shadow=True)
    want = composite(img, r, speed_mps=20.0, noise_seed=3)
    bgr = np.ascontiguousarray(img[..., ::-1])
    assert composite_into(bgr[..., ::-1], r, speed_mps=20.0, noise_seed=3)
    assert np.array_equal(bgr[..., ::-1], want)
    # an object that changes no byte (fully transparent) reports so and leaves the frame
    clear = square_render()
    clear.alpha[:] = 0.0
    before = bgr.copy()
    assert not composite_into(bgr[..., ::-1], clear)
    assert np.array_equal(bgr, before)


def test_opaque_object_without_effects_is_exact():
    img = frame()
    r = square_render(value=0.2)
    out = composite(img, r, lab_match=False, blur=False, match_noise=False)
    u0, v0 = r.roi[:2]
    inner = out[v0 + 12 : v0 + 28, u0 + 12 : u0 + 28]  # 0.9 * 0.2 linear
    want = np.round(linear_to_srgb(np.float32(0.18)) * 255)
    assert np.all(np.abs(inner.astype(int) - want) <= 1)


def test_lab_matching_moves_a_too_bright_object_toward_the_frame():
    img = frame(50)
    r = square_render(value=1.0)
    u0, v0 = r.roi[:2]
    sl = np.s_[v0 + 14 : v0 + 26, u0 + 14 : u0 + 26]
    plain = composite(img, r, lab_match=False, blur=False)
    matched = composite(img, r, lab_match=True, blur=False)
    L_frame = _L(img).mean()
    L_plain, L_matched = _L(plain[sl]).mean(), _L(matched[sl]).mean()
    assert L_plain > 90 and L_frame < 30
    assert L_frame < L_matched < L_plain - 20
    # the object's own contrast survives (texture inside the square)
    edge = _L(matched[v0 + 10 : v0 + 12, u0 + 14 : u0 + 26]).mean()
    assert edge > L_matched + 1


def test_shadow_darkens_real_pixels():
    img = np.full((120, 160, 3), 180, np.uint8)
    r = square_render(shadow=True)
    out = composite(img, r, lab_match=False, blur=False, shadow_strength=0.6)
    u0, v0 = r.roi[:2]
    got = srgb_to_linear(out[v0 + 32, u0 + 20] / 255.0)
    want = srgb_to_linear(np.float32(180 / 255.0)) * 0.4
    assert np.allclose(got, want, atol=0.01)


def test_pixel_offset_and_blur():
    img = np.zeros((120, 160, 3), np.uint8)
    r = square_render(value=1.0)

    def centroid(out):
        w = out[..., 1].astype(float)
        vs, us = np.mgrid[0 : w.shape[0], 0 : w.shape[1]]
        return np.array([(w * us).sum(), (w * vs).sum()]) / w.sum()

    base = composite(img, r, lab_match=False, blur=False)
    shifted = composite(img, r, lab_match=False, blur=False, pixel_offset=(0.5, -1.25))
    assert np.allclose(centroid(shifted) - centroid(base), [0.5, -1.25], atol=0.05)
    # blur: softer edges, same centroid; nearer objects blur more
    blurred = composite(img, r, lab_match=False, blur=True)
    assert np.allclose(centroid(blurred), centroid(base), atol=0.05)
    near = square_render(distance=3.0)
    assert blur_sigma_px(near) > blur_sigma_px(r) > 0.1
    moving = composite(img, r, lab_match=False, blur=True, speed_mps=40.0, exposure_s=0.02)
    u0, v0 = r.roi[:2]
    row = np.s_[v0 + 20, u0 : u0 + 40, 1]
    assert (moving[row] > 0).sum() > (blurred[row] > 0).sum()  # smeared along the motion


def test_sun_position():
    lat, lon = 53.55, 10.0  # Hamburg
    # March equinox 2021, local solar noon: 12:00 - 40 min (10 deg E) + 7.5 min (eq. of time)
    t = dt.datetime(2021, 3, 20, 11, 27, tzinfo=dt.UTC).timestamp()
    d = sun_dir_enu(lat, lon, t)
    assert np.degrees(np.arcsin(d[2])) == pytest.approx(90 - lat, abs=1.0)
    assert np.degrees(np.arctan2(d[0], d[1])) % 360 == pytest.approx(180, abs=1.5)
    # June solstice noon: +23.4 deg; morning sun in the east
    t = dt.datetime(2021, 6, 21, 11, 20, tzinfo=dt.UTC).timestamp()
    assert np.degrees(np.arcsin(sun_dir_enu(lat, lon, t)[2])) == pytest.approx(59.9, abs=1.0)
    t = dt.datetime(2021, 6, 21, 5, 0, tzinfo=dt.UTC).timestamp()
    assert sun_dir_enu(lat, lon, t)[0] > 0.5


@pytest.fixture(scope="module")
def fire_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-frame synthetic fire_site sequence (small images, sparse lidar)."""
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("seq") / "fire_site"
    generate(folder, SynthConfig(scene="fire_site", frames=2, scale=0.25, lidar_density=0.1))
    return folder


@pytest.mark.gl
def test_estimate_lighting_on_a_synthetic_frame(fire_site: Path):
    """The synthetic renderer's light (camera_sim.py) is known: sky ambient 0.85 x
    (0.42, 0.47, 0.56) on an upward surface, sun 0.85 x (0.95, 0.89, 0.80)."""
    from geometry.camera import load_cameras
    from geometry.poses import PoseTrack
    from worker.osdar.sequence import Sequence

    FIRE_SITE = fire_site

    seq = Sequence.open(FIRE_SITE)
    cams = load_cameras(seq.labels.raw)
    track = PoseTrack.from_csv(FIRE_SITE / "ground_truth/poses_dense.csv")
    meta = json.loads((FIRE_SITE / "ground_truth/meta.json").read_text())
    T_ws = pose_to_T(meta["T_world_scene"]["translation"], meta["T_world_scene"]["quaternion"])
    sun = T_ws[:3, :3] @ np.array([0.45, -0.55, 0.7])
    i = seq.frame_indices[0]
    t = seq.timestamps("rgb_center")[0]
    T_wb = track.interpolate(np.array([t]))[0]
    est = estimate_lighting(seq.image(i, "rgb_center"), cams["rgb_center"], T_wb, sun_dir_world=sun)
    assert np.allclose(est.sun_dir_world, sun / np.linalg.norm(sun))
    sky_true = 0.85 * np.array([0.42, 0.47, 0.56])
    assert np.all(est.sky_rgb > 0.6 * sky_true) and np.all(est.sky_rgb < 1.6 * sky_true)
    assert est.sky_rgb[2] > est.sky_rgb[0]  # blue sky
    assert 0.5 * 0.75 < est.sun_intensity < 1.6 * 0.75
    assert est.ambient_rgb.mean() < est.sky_rgb.mean()
    # an overcast (grey) frame gives no direct sun
    grey = np.full((400, 616, 3), 170, np.uint8)
    assert estimate_lighting(grey, cams["rgb_center"], T_wb).sun_intensity == 0.0
    assert not Lighting(sun_intensity=0.0).casts_shadows
