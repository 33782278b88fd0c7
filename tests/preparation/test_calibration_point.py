"""The calibration point: clicked landmark -> nearest-projection cloud point; pole tops."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from geometry.camera import load_cameras
from geometry.voxels import unique_first, voxel_keep
from tests.synth_fixtures import landmarks, synth_sequence, true_poses
from worker.osdar.sequence import Sequence
from worker.preparation.calibration_point import (
    OSDAR23_FULL_RESOLUTION,
    CalibrationPoint,
    Clicks,
    ClicksError,
    calibration_point_from_clicks,
    camera_at_resolution,
    points_near_rays,
    propose_pole_tops,
)
from worker.preparation.config import CalibrationConfig
from worker.preparation.frame_clouds import FrameClouds
from worker.preparation.registration import points_near, register_clouds
from worker.preparation.scene_elements import Pole

VOXEL = 0.1


# ---------------------------------------------------------------------------- clicks files
def test_csv_and_json_formats_agree(tmp_path: Path) -> None:
    csv_path = tmp_path / "pole_a.csv"
    csv_path.write_text(
        "camera,frame_idx,u,v\nrgb_center,3,100.5,200.25\nrgb_center,4,,\n"
        "rgb_highres_center,3,1000,2000\n"
    )
    js = tmp_path / "pole_a.json"
    js.write_text(
        json.dumps(
            {
                "landmark": "pole_a",
                "clicks": {
                    "rgb_center": {"3": [100.5, 200.25], "4": None},
                    "rgb_highres_center": {"3": [1000, 2000]},
                },
            }
        )
    )
    a, b = Clicks.load(csv_path), Clicks.load(js)
    assert a.to_json() == b.to_json()
    assert a.digest() == b.digest()
    assert len(a) == 2 and 4 not in a.uv["rgb_center"]  # an empty row is a missing frame


def test_explicit_resolution_and_bad_files(tmp_path: Path) -> None:
    p = tmp_path / "c.csv"
    p.write_text("camera,frame_idx,u,v,width,height\nrgb_center,0,10,20,616,400\n")
    assert Clicks.load(p).resolution == {"rgb_center": (616, 400)}
    bad = tmp_path / "bad.csv"
    bad.write_text("cam,frame,u,v\nx,0,1,2\n")
    with pytest.raises(ClicksError, match="camera,frame_idx,u,v"):
        Clicks.load(bad)
    with pytest.raises(ClicksError, match="not found"):
        Clicks.load(tmp_path / "missing.json")
    j = tmp_path / "bad.json"
    j.write_text('{"landmark": "x", "clicks": {"rgb_center": {"zero": [1, 2]}}}')
    with pytest.raises(ClicksError, match="not an integer"):
        Clicks.load(j)


# ---------------------------------------------------------------------------- on a sequence
@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    folder = synth_sequence(tmp_path_factory.getbasetemp())
    seq = Sequence.open(folder)
    gt = true_poses(folder)
    cloud = register_clouds(seq, gt, voxel_size=VOXEL, max_range=80.0)
    cams = load_cameras(seq.labels.raw, seq.cameras)
    times = {c: dict(zip(seq.frame_indices, seq.timestamps(c).tolist(), strict=True)) for c in cams}
    return {"folder": folder, "seq": seq, "gt": gt, "cloud": cloud, "cams": cams, "times": times}


def _measured_pole_tops(scene: dict, min_clicks: int = 8) -> list[dict]:
    """pole_top landmarks the lidar measured (a cloud point within 0.2 m) with many clicks."""
    tree = cKDTree(scene["cloud"].xyz)
    out = []
    for lm in landmarks(scene["folder"], "pole_top"):
        n = sum(uv is not None for px in lm["pixels"].values() for uv in px.values())
        d, _ = tree.query(lm["xyz"])
        if n >= min_clicks and d < 0.2:
            out.append(lm)
    return out


def _clicks(lm: dict) -> Clicks:
    uv = {
        cam: {int(f): np.asarray(p, dtype=np.float64) for f, p in px.items() if p is not None}
        for cam, px in lm["pixels"].items()
    }
    return Clicks(lm["id"], {c: v for c, v in uv.items() if v})


def test_true_clicks_and_true_poses_give_the_landmark(scene: dict) -> None:
    lms = _measured_pole_tops(scene)
    assert lms, "the test sequence must show at least one measured pole top"
    for lm in lms:
        cp = calibration_point_from_clicks(
            scene["cloud"].xyz, scene["gt"], scene["cams"], scene["times"], _clicks(lm),
            CalibrationConfig(),
        )  # fmt: skip
        assert cp.xyz is not None, cp.warnings
        err = np.linalg.norm(cp.xyz - np.asarray(lm["xyz"]))
        # the nearest measured point sits on the pole's surface (radius 0.12 m) near its top
        assert err < 2.0 * VOXEL + 0.12, (lm["id"], err)
        assert cp.point_index is not None
        assert np.allclose(scene["cloud"].xyz[cp.point_index], cp.xyz)
        s = cp.summary()
        assert s["inliers"] == s["views"] == len(_clicks(lm))
        assert s["residual_mean_px"] < 15.0  # full-resolution px
        assert cp.resolution["rgb_center"] == OSDAR23_FULL_RESOLUTION["rgb_center"]


def test_points_near_gathers_every_frame_at_full_density(scene: dict) -> None:
    seq, gt = scene["seq"], scene["gt"]
    lm = _measured_pole_tops(scene)[0]
    centre = np.asarray(lm["xyz"], dtype=np.float64)
    near = points_near(seq, gt, centre, 0.5)
    assert len(near) and np.all(np.linalg.norm(near - centre, axis=1) <= 0.5 + 1e-9)
    full = register_clouds(seq, gt, voxel_size=0.0, max_range=200.0).xyz
    inside = np.linalg.norm(full - centre, axis=1) <= 0.5
    assert len(near) == int(inside.sum())  # the same points as a full registration there
    assert len(near) > int((np.linalg.norm(scene["cloud"].xyz - centre, axis=1) <= 0.5).sum())


def test_registration_frame_by_frame_equals_one_voxel_filter(scene: dict) -> None:
    """The per-frame voxel set keeps exactly what one filter over all the points keeps:
    the first point (in frame order) of every occupied world voxel."""
    seq, gt = scene["seq"], scene["gt"]
    full = register_clouds(seq, gt, voxel_size=0.0, max_range=80.0)
    keep = voxel_keep(full.xyz, VOXEL)
    cloud = scene["cloud"]
    assert len(cloud) == len(keep) < 0.8 * len(full)
    assert np.array_equal(full.xyz[keep], cloud.xyz)
    assert np.array_equal(full.frame_idx[keep], cloud.frame_idx)


@pytest.mark.parametrize("n", [1, 2, 50, 20_000])
def test_unique_first_equals_numpy_unique(n: int) -> None:
    keys = np.random.default_rng(n).integers(0, max(2, n // 4), n).astype(np.int64)
    uniq, first = unique_first(keys)
    expected = np.unique(keys, return_index=True)
    assert np.array_equal(uniq, expected[0]) and np.array_equal(first, expected[1])


def test_dense_refinement_moves_the_point_onto_the_landmark(scene: dict) -> None:
    seq, gt = scene["seq"], scene["gt"]
    # a coarse registered cloud (0.5 m voxels, every third frame): its nearest point to a
    # pole top is far from the top; every frame's points near it are not
    coarse_cloud = register_clouds(
        seq, gt, voxel_size=0.5, max_range=80.0, frames=seq.frame_indices[::3]
    ).xyz
    for lm in _measured_pole_tops(scene):
        args = (coarse_cloud, gt, scene["cams"], scene["times"], _clicks(lm))
        coarse = calibration_point_from_clicks(*args, CalibrationConfig(dense_radius_m=0.0))
        fine = calibration_point_from_clicks(
            *args, CalibrationConfig(), dense=lambda c, r: points_near(seq, gt, c, r)
        )
        assert fine.refined and not coarse.refined
        assert fine.point_index == coarse.point_index  # the registered cloud's point is kept
        truth = np.asarray(lm["xyz"])
        e_coarse, e_fine = (np.linalg.norm(p.xyz - truth) for p in (coarse, fine))
        r_coarse, r_fine = (p.summary()["residual_mean_px"] for p in (coarse, fine))
        # measured: 7.6 -> 2.3 px, 0.135 -> 0.115 m (the pole's radius is 0.12 m: the
        # nearest measured point is on its rim)
        assert r_fine < 0.5 * r_coarse, (lm["id"], r_fine, r_coarse)
        assert e_fine < e_coarse and e_fine < 0.15, (lm["id"], e_fine, e_coarse)
        assert fine.to_json()["refined"] is True
        assert CalibrationPoint.from_json(fine.to_json()).refined


def test_frames_without_clicks_are_skipped(scene: dict) -> None:
    lm = _measured_pole_tops(scene)[0]
    clicks = _clicks(lm)
    cam = next(iter(clicks.uv))
    frames = sorted(clicks.uv[cam])
    kept = {f: clicks.uv[cam][f] for f in frames[::3]}  # most frames unclicked
    kept[9999] = np.array([100.0, 100.0])  # a frame the sequence lacks
    cp = calibration_point_from_clicks(
        scene["cloud"].xyz, scene["gt"], scene["cams"], scene["times"],
        Clicks(lm["id"], {cam: kept}), CalibrationConfig(),
    )  # fmt: skip
    assert len(cp.observations) == len(frames[::3])
    assert cp.skipped == [{"camera": cam, "frame_idx": 9999, "reason": "no such frame"}]
    assert any("9999" in w for w in cp.warnings)
    assert np.linalg.norm(cp.xyz - np.asarray(lm["xyz"])) < 2.0 * VOXEL + 0.12


def test_unknown_camera_is_a_clear_error(scene: dict) -> None:
    clicks = Clicks("x", {"rgb_left": {0: np.array([1.0, 2.0])}})
    with pytest.raises(ClicksError, match=r"rgb_left.*lacks"):
        calibration_point_from_clicks(
            scene["cloud"].xyz, scene["gt"], scene["cams"], scene["times"], clicks,
            CalibrationConfig(),
        )  # fmt: skip


def test_camera_at_resolution_round_trip(scene: dict) -> None:
    cam = scene["cams"]["rgb_center"]
    full = camera_at_resolution(cam, 2464, 1600)
    back = camera_at_resolution(full, cam.width, cam.height)
    assert np.allclose(back.K, cam.K, atol=1e-9)
    p = np.array([[20.0, 1.0, 2.0]])
    uv_s, _ = cam.project(p)
    uv_f, _ = full.project(p)
    sx, sy = 2464 / cam.width, 1600 / cam.height
    assert np.allclose((uv_s + 0.5) * [sx, sy] - 0.5, uv_f, atol=1e-6)


def test_auto_mode_proposes_the_most_visible_pole_top(scene: dict) -> None:
    lms = landmarks(scene["folder"], "pole_top")
    poles = [
        Pole(lm["id"], np.asarray(lm["xyz"][:2]), 0.0, lm["xyz"][2], 0.15,
             np.asarray(lm["xyz"]), 100, 0.0, 0.0)
        for lm in lms
    ]  # fmt: skip
    cp = propose_pole_tops(poles, scene["gt"], scene["cams"], scene["times"], CalibrationConfig())
    assert cp.mode == "auto" and cp.xyz is not None
    views = [p["views"] for p in cp.proposals]
    assert views == sorted(views, reverse=True) and views[0] > 0
    best = next(lm for lm in lms if lm["id"] == cp.proposals[0]["pole"])
    n_true = sum(uv is not None for px in best["pixels"].values() for uv in px.values())
    assert abs(views[0] - n_true) <= 0.2 * n_true + 2  # occlusion is not modelled
    assert np.allclose(cp.xyz, best["xyz"])
    assert cp.landmark == f"{best['id']}_top"


def _frame_points(seq: Sequence, track: object) -> object:
    """``frame_points`` of :func:`points_near_rays`: every frame at full density."""
    clouds = FrameClouds(seq, max_range=200.0)
    frames = clouds.frames
    T_all = track.interpolate(np.array([clouds.frame_times[f] for f in frames]))  # type: ignore[attr-defined]
    return lambda: ((T, clouds.get(f).p_base32) for f, T in zip(frames, T_all, strict=True))


def test_points_near_rays_are_the_points_in_the_cone(scene: dict) -> None:
    seq, gt = scene["seq"], scene["gt"]
    lm = _measured_pole_tops(scene)[0]
    top = np.asarray(lm["xyz"], dtype=np.float64)
    origin = gt.T[0, :3, 3] + np.array([0.0, 0.0, 3.0])
    d = (top - origin) / np.linalg.norm(top - origin)
    tol = 0.01
    got = points_near_rays(_frame_points(seq, gt))(origin[None], d[None], tol)
    full = register_clouds(seq, gt, voxel_size=0.0, max_range=200.0).xyz
    v = full - origin
    along = v @ d
    perp = np.linalg.norm(v - along[:, None] * d, axis=1)
    inside = (along > 0.5) & (perp <= tol * along)
    margin = np.abs(perp - tol * along) > 1e-4  # float32 selection: away from the edge
    assert len(got) >= int((inside & margin).sum()) > 0
    assert len(got) <= int((inside | ~margin).sum())
    v_got = got - origin
    a_got = v_got @ d
    assert np.all(np.linalg.norm(v_got - a_got[:, None] * d, axis=1) <= tol * a_got + 1e-4)


def test_a_landmark_missing_from_the_registered_cloud_is_found_near_the_rays(
    scene: dict,
) -> None:
    """A registered cloud without the landmark's points (a pole top that only frames left
    out of it were hit at): the point nearest the rays is on another surface, refined
    among the points around that one; the frames' points near the click rays hold the
    landmark's own."""
    seq, gt = scene["seq"], scene["gt"]
    rays = points_near_rays(_frame_points(seq, gt))
    for lm in _measured_pole_tops(scene):
        top = np.asarray(lm["xyz"], dtype=np.float64)
        cloud = scene["cloud"].xyz
        without = cloud[np.linalg.norm(cloud - top, axis=1) > 1.0]
        args = (without, gt, scene["cams"], scene["times"], _clicks(lm), CalibrationConfig())
        dense = lambda c, r: points_near(seq, gt, c, r)  # noqa: E731
        before = calibration_point_from_clicks(*args, dense=dense)
        after = calibration_point_from_clicks(*args, dense=dense, dense_rays=rays)
        assert after.xyz is not None and after.refined
        e_after = float(np.linalg.norm(after.xyz - top))
        r_after = after.summary()["residual_mean_px"]
        # the pole's radius is 0.12 m: the nearest measured point is on its rim
        assert e_after < 0.2, (lm["id"], e_after)
        assert r_after < 15.0, (lm["id"], r_after)  # as with the whole cloud (test above)
        if before.xyz is not None:  # else: nothing within the search radius at all
            e_before = float(np.linalg.norm(before.xyz - top))
            assert e_before > 0.5, (lm["id"], e_before)
            assert r_after < 0.5 * before.summary()["residual_mean_px"], lm["id"]
