"""Camera simulation: landmarks land where the calibrated camera model projects them."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from osdar_platform.shared_data import real_labels_path
from worker.synth.scene_mesh import MATERIAL_ID

CALIB = real_labels_path()
pytestmark = [
    pytest.mark.gl,
    pytest.mark.skipif(not CALIB.exists(), reason="real OSDaR23 calibration not available"),
]
CAMS = ("rgb_center", "rgb_highres_center")


@pytest.fixture(scope="module")
def setup():
    from geometry.camera import load_cameras
    from worker.synth.camera_sim import CameraSimulator
    from worker.synth.scenes import build_scene

    cams = load_cameras(json.loads(CALIB.read_text()))
    sel = {n: cams[n].scaled(0.2) for n in CAMS}
    scene = build_scene("klein_flottbek", 4, 120.0, origin_offset=(5.6e5, 5.93e6, 20.0))
    sim = CameraSimulator(scene, sel, seed=2)
    sign = scene.landmark("sig_000_board_center")
    s = scene.ego.sample(0.5)
    s_sign = s[np.argmin(np.linalg.norm(scene.ego.point(s) - sign.xyz, axis=1))]
    T_world_base = scene.ego.frame_at(s_sign - 45.0)[0]
    yield scene, sel, sim, T_world_base
    sim.close()


def _optical_z(cam, T_world_base: np.ndarray, p_world: np.ndarray) -> float:
    from geometry.transforms import invert_T, transform_points

    T_opt_world = cam.T_opt_base @ invert_T(T_world_base)
    return float(transform_points(T_opt_world, p_world[None])[0, 2])


@pytest.mark.parametrize("cam_name", CAMS)
def test_depth_at_projected_landmarks(setup, cam_name: str) -> None:
    scene, cams, sim, T = setup
    cam = cams[cam_name]
    depth = sim.render_depth(cam_name, T)
    assert depth.shape == (cam.height, cam.width)
    checked = 0
    for lm in scene.landmarks:
        if lm.kind not in ("sign_center", "pole_top"):
            continue
        uv, ok = cam.project_world(lm.xyz[None], T)
        z = _optical_z(cam, T, lm.xyz)
        if not ok[0] or not cam.in_image(uv, margin=3)[0] or not 5.0 < z < 150.0:
            continue
        u, v = np.round(uv[0]).astype(int)
        if lm.kind == "pole_top":
            v += 2  # just below the top, on the pole
        win = depth[v - 1 : v + 2, u - 1 : u + 2]
        rel = np.nanmin(np.abs(win - z)) / z
        assert rel < 0.03, (lm.id, z, win)
        checked += 1
    assert checked >= 2


@pytest.mark.parametrize("cam_name", CAMS)
def test_sign_corners_on_board_edge(setup, cam_name: str) -> None:
    scene, cams, sim, T = setup
    cam = cams[cam_name]
    labels = sim.render_labels(cam_name, T)
    sign = (labels == MATERIAL_ID["sign"]) | (labels == MATERIAL_ID["sign_dark"])
    corners = [
        lm for lm in scene.landmarks if lm.kind == "sign_corner" and lm.id.startswith("sig_000")
    ]
    uv, ok = cam.project_world(np.array([lm.xyz for lm in corners]), T)
    assert ok.all() and cam.in_image(uv, margin=3).all()
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    vv, uu = np.nonzero(sign)
    near = (uu > lo[0] - 3) & (uu < hi[0] + 3) & (vv > lo[1] - 3) & (vv < hi[1] + 3)
    uu, vv = uu[near], vv[near]
    assert hi[0] - lo[0] > 8.0 and len(uu) > 50
    # the rasterised board's outermost pixel centres lie within 1 px of the projected corners
    assert abs(uu.min() - lo[0]) <= 1.0 and abs(uu.max() - hi[0]) <= 1.0
    assert abs(vv.min() - lo[1]) <= 1.0 and abs(vv.max() - hi[1]) <= 1.0


def test_rgb_looks_like_a_scene(setup) -> None:
    _, cams, sim, T = setup
    cam = cams["rgb_highres_center"]
    img = sim.render("rgb_highres_center", T)
    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
    labels = sim.render_labels("rgb_highres_center", T)
    lum = img.astype(float).mean(axis=2)
    ballast = labels == MATERIAL_ID["ballast"]
    assert ballast.sum() > 1000 and lum[ballast].std() > 8.0
    sky = labels < 0
    assert sky[: cam.height // 10].mean() > 0.5
    assert lum[sky].mean() > lum[~sky].mean() + 20.0
    # deterministic per frame, noise changes with the noise seed
    np.testing.assert_array_equal(img, sim.render("rgb_highres_center", T))
    other = sim.render("rgb_highres_center", T, noise_seed=99)
    assert 0.3 < np.abs(other.astype(int) - img.astype(int)).mean() < 5.0


def test_depth_nan_for_sky_and_speed(setup) -> None:
    _, _, sim, T = setup
    d = sim.render_depth("rgb_center", T)
    assert np.isnan(d[0]).mean() > 0.5
    assert np.nanmin(d) > 1.0
    t0 = time.perf_counter()
    for name in CAMS:
        sim.render(name, T)
    assert time.perf_counter() - t0 < 5.0
