"""The rendered object's own edge: a pixel's box, not the lens resampling's extra blur.

A straight edge of a flat panel, rendered through the real (distorted) camera model, is
compared with the analytic edge (its 3-D line projected by ``CameraModel.project_optical``):
over many sub-pixel phases (a slanted edge), the coverage against the signed distance to
the analytic edge is the edge spread function; its derivative's variance is the render's
own blur. A pixel that integrates its area has 1/12 px^2; the render reports
``(s^2 + 1) / (12 s^2)`` for s x s supersamples (renderer/object_render.py, step 4). The
old order (average the supersamples, then resample bilinearly through the distortion)
measured 0.25 px^2 at s = 4. The composite then gives the object the frame's blur less
that variance, so a rendered object in a frame of known blur is as sharp as the frame's
own edges (edge sigma inside / outside in [0.8, 1.25], the issue's bound).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from geometry.camera import CameraModel, load_cameras
from geometry.transforms import invert_T, make_T, quat_to_matrix
from osdar_platform.shared_data import real_labels_path
from renderer.composite import composite
from renderer.mesh import ObjectMesh
from renderer.object_render import ObjectRender, ObjectRenderer, edge_var_px2
from renderer.sensor_noise import sharpness_inside_outside

REAL_LABELS = real_labels_path()
SCALE = 0.25
PANEL_W, PANEL_H = 3.0, 2.5


@pytest.fixture(scope="module")
def cam() -> CameraModel:
    if not REAL_LABELS.is_file():
        pytest.skip(f"{REAL_LABELS} not available")
    raw = json.loads(REAL_LABELS.read_text())
    return load_cameras(raw)["rgb_highres_center"].scaled(SCALE)


def panel() -> ObjectMesh:
    """A flat grey panel in the object's y-z plane, bottom edge on z = 0."""
    w, h = PANEL_W / 2, PANEL_H
    v = np.array([[0, -w, 0], [0, w, 0], [0, w, h], [0, -w, h]], np.float64)
    return ObjectMesh(v, [[0, 1, 2], [0, 2, 3]], np.full((4, 3), 0.5, np.float32),
                      np.ones(4, np.float32))  # fmt: skip


def panel_pose(distance: float, lateral: float, roll: float) -> np.ndarray:
    """T_world_obj (vehicle at the world origin): the panel faces the vehicle, rolled by
    ``roll`` rad about the viewing direction (slanted edges)."""
    R = quat_to_matrix([0.0, 0.0, 1.0, 0.0]) @ quat_to_matrix(
        [np.sin(roll / 2), 0.0, 0.0, np.cos(roll / 2)]
    )
    return make_T(R, [distance, lateral, -0.5])


def edge_distances(
    cam: CameraModel, r: ObjectRender, T_world_obj: np.ndarray, a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(coverage, signed distance px, negative inside) of the ROI pixels within 3 px of
    the analytic image of the edge a -> b (object frame), away from its ends."""
    T_opt_obj = invert_T(cam.T_base_opt) @ T_world_obj
    t = np.linspace(0.0, 1.0, 4001)
    p = a[None] + t[:, None] * (b - a)[None]
    uv, ok = cam.project_optical(p @ T_opt_obj[:3, :3].T + T_opt_obj[:3, 3])
    assert ok.all()
    u0, v0, u1, v1 = r.roi
    vv, uu = np.mgrid[v0:v1, u0:u1]
    pix = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    _, idx = cKDTree(uv).query(pix)
    idx = np.clip(idx, 1, len(uv) - 2)
    tan = uv[idx + 1] - uv[idx - 1]
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    d = ((pix - uv[idx]) * np.stack([tan[:, 1], -tan[:, 0]], 1)).sum(1)
    keep = (idx > 400) & (idx < len(uv) - 400) & (np.abs(d) < 3.0)
    cov, d = r.alpha.ravel()[keep].astype(np.float64), d[keep]
    if np.corrcoef(cov, d)[0, 1] > 0:
        d = -d
    return cov, d


def line_spread(cov: np.ndarray, d: np.ndarray, bin_px: float = 0.05) -> tuple[float, float]:
    """(variance px^2, mean px) of the line spread: the binned edge spread's derivative."""
    bins = np.arange(-3.0, 3.0 + 1e-9, bin_px)
    k = np.digitize(d, bins) - 1
    n = np.bincount(k, minlength=len(bins))[: len(bins) - 1]
    s = np.bincount(k, weights=cov, minlength=len(bins))[: len(bins) - 1]
    c = 0.5 * (bins[1:] + bins[:-1])
    ok = n > 0
    F, c = s[ok] / n[ok], c[ok]
    f = -np.gradient(F, c)
    m = float((f * c).sum() / f.sum())
    return float((f * (c - m) ** 2).sum() / f.sum()), m


@pytest.mark.parametrize("ss", [1, 2, 4])
def test_rendered_edge_is_a_pixel_box(cam: CameraModel, ss: int) -> None:
    """Over the panel's four edges at six places in the image: the measured line-spread
    variance is the reported one within 0.01 px^2 in every render (s = 1: 0.086-0.157
    reported, 0.088-0.161 measured, where the phase-average 1/6 said 0.167; s = 4: 0.089,
    a pixel's box 0.083; the old order 0.25), the edge within 0.03 px of the camera
    model's, pooled."""
    rend = ObjectRenderer(cam, antialias=f"ssaa{ss}")
    obj = panel()
    v = obj.vertices
    covs, ds = [], []
    for distance, lateral, roll in (
        (24.0, 0.0, 0.13), (28.0, -3.0, -0.09), (22.0, 3.0, 0.21),
        (12.0, 1.0, 0.12), (26.0, 1.0, 0.12), (40.0, 1.0, 0.12),
    ):  # fmt: skip
        T_wo = panel_pose(distance, lateral, roll)
        r = rend.render(obj, T_wo, np.eye(4))
        assert r.roi is not None
        c_r, d_r = [], []
        for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
            c, d = edge_distances(cam, r, T_wo, v[a], v[b])
            c_r.append(c)
            d_r.append(d)
        var, _ = line_spread(np.concatenate(c_r), np.concatenate(d_r))
        assert var == pytest.approx(r.edge_var_px2, abs=0.01), (distance, var, r.edge_var_px2)
        if ss > 1:  # the phases vary within each pixel's sub-samples: about the average
            assert r.edge_var_px2 == pytest.approx(edge_var_px2(ss), abs=0.01)
        covs += c_r
        ds += d_r
    _, mean = line_spread(np.concatenate(covs), np.concatenate(ds))
    assert abs(mean) < 0.03, mean
    rend.close()


def boxes_frame(shape: tuple[int, int], sigma: float, seed: int) -> np.ndarray:
    """Random boxes of random levels blurred by a Gaussian of ``sigma`` px, noise of std
    2 levels; uint8 RGB of ``shape`` (H, W)."""
    rng = np.random.default_rng(seed)
    H, W = shape
    clean = np.full((H, W, 3), 60.0, np.float32)
    for _ in range(400):
        x, y = rng.integers(0, W - 40), rng.integers(0, H - 40)
        w, h = rng.integers(10, 40, 2)
        clean[y : y + h, x : x + w] = rng.uniform(20, 230)
    clean = cv2.GaussianBlur(clean, (0, 0), sigma)
    return np.clip(np.round(clean + rng.normal(0, 2.0, clean.shape)), 0, 255).astype(np.uint8)


def subpixel_boxes_frame(shape: tuple[int, int], sigma: float, seed: int) -> np.ndarray:
    """Random boxes of random levels at sub-pixel corners, blurred by a continuous
    Gaussian of ``sigma`` px and sampled at the pixel centres (each box's blurred coverage
    in closed form, painted over the ones before), noise of std 2 levels; uint8 RGB of
    ``shape`` (H, W). Its edge spread is ``sigma`` by any measure over many sub-pixel
    phases; :func:`boxes_frame`'s pixel-aligned steps under OpenCV's sampled kernel (sd
    0.38 px for 0.45) are not a blur of 0.45 px in that sense."""
    from scipy.special import ndtr

    rng = np.random.default_rng(seed)
    H, W = shape
    clean = np.full((H, W, 3), 60.0, np.float64)
    r = int(np.ceil(5.0 * sigma)) + 1
    for _ in range(400):
        x, y = rng.uniform(0, W - 40), rng.uniform(0, H - 40)
        w, h = rng.uniform(10, 40, 2)
        level = rng.uniform(20, 230)
        u0, u1 = max(int(x) - r, 0), min(int(x + w) + r + 1, W)
        v0, v1 = max(int(y) - r, 0), min(int(y + h) + r + 1, H)
        u, v = np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64)
        cx = ndtr((x + w - u) / sigma) - ndtr((x - u) / sigma)
        cy = ndtr((y + h - v) / sigma) - ndtr((y - v) / sigma)
        c = (cy[:, None] * cx[None])[..., None]
        clean[v0:v1, u0:u1] = clean[v0:v1, u0:u1] * (1.0 - c) + level * c
    return np.clip(np.round(clean + rng.normal(0, 2.0, clean.shape)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("sigma", [0.5, 0.8, 1.5])
def test_rendered_object_as_sharp_as_the_frame(cam: CameraModel, sigma: float) -> None:
    """A rendered panel (auto anti-aliasing) composited into a frame of known blur: its
    silhouette's edge sigma over the real edges' around it in [0.8, 1.25]."""
    rend = ObjectRenderer(cam)
    T_wo = panel_pose(26.0, 1.0, 0.12)
    r = rend.render(panel(), T_wo, np.eye(4))
    frame = boxes_frame((cam.height, cam.width), sigma, int(10 * sigma))
    out = composite(frame, r, lab_match=False, match_noise=False)
    s_obj, s_real = sharpness_inside_outside(out, r.roi, r.alpha)
    assert 0.8 <= s_obj / s_real <= 1.25, (s_obj, s_real, sigma)
    rend.close()


@pytest.fixture(scope="module")
def small_blur_case(cam: CameraModel) -> tuple[float, float, float]:
    """A straight panel edge (no limbs, no shading) composited into a frame of boxes
    blurred by 0.45 px (point-sampled at sub-pixel phases, as the twin's frames nearly
    are: the look's small-blur regime), through a pinhole (no defocus floor, no motion).
    Returns (the object's true edge spread over the frame's 0.45 px: its render's pixel box and
    sub-sampling, ``edge_var_px2``, plus the Gaussian the composite gave it; the look
    measure's object sigma; its real-edge sigma)."""
    from renderer.composite import frame_blur, gaussian_sigma_px

    rend = ObjectRenderer(cam)
    r = rend.render(panel(), panel_pose(26.0, 1.0, 0.12), np.eye(4))
    frame = subpixel_boxes_frame((cam.height, cam.width), 0.45, 4)
    out = composite(frame, r, lab_match=False, match_noise=False, aperture_m=0.0,
                    exposure_s=0.0)  # fmt: skip
    g = gaussian_sigma_px(r, frame_blur(frame, r, (0.0, 0.0)), 0.0)
    true_ratio = float(np.sqrt(g * g + r.edge_var_px2)) / 0.45
    s_obj, s_real = sharpness_inside_outside(out, r.roi, r.alpha)
    rend.close()
    return true_ratio, s_obj, s_real


def test_a_small_blur_is_composited_right(small_blur_case: tuple[float, float, float]) -> None:
    """The composite itself is right in the small-blur case: the object's true edge
    spread is within 0.8-1.05 of the frame's (0.97 measured)."""
    true_ratio, _, _ = small_blur_case
    assert 0.8 <= true_ratio <= 1.05, true_ratio


def test_the_look_measure_reads_a_small_blur_as_it_is(
    small_blur_case: tuple[float, float, float],
) -> None:
    """The look's measure (``sharpness_inside_outside``) reads the small-blur case's
    ratio within 15 % of its truth: 0.87x where the truth is 0.97x (0.90 of it; the
    object 0.55 px, the frame 0.63 by the 10-90 measure's bilinear profiles). Before the
    render reported its resampling's variance at its own phases it read 0.81x: the object
    had been given too little blur, its spread taken as 0.167 px^2 where it was ~0.11."""
    true_ratio, s_obj, s_real = small_blur_case
    assert abs((s_obj / s_real) / true_ratio - 1.0) <= 0.15, (s_obj, s_real, true_ratio)
