"""Evaluation (pipeline step 8): the paper's RPE and jitter per camera and strategy.

A small synthetic fire_site (20 frames): the clicks are the true pixels of the lidar return
nearest each measured landmark (or of the landmark itself). Bounds: with the TRUE poses and
a cloud registered with them, the RPE of the return clicks is hundredths of a pixel, that
of the landmark clicks is limited by how near a cloud point lies to the landmark (a few px
at full resolution); a 2 m sideways jump in half the frames makes the RPE and jitter grow
by far.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from geometry.poses import PoseTrack
from worker.evaluation.evaluate import (
    _jitter,
    cloud_for_track,
    evaluate_strategies,
    nearest_returns,
    summarize_rpe,
    synthetic_clicks,
)
from worker.osdar.sequence import Sequence

CAMS = ["rgb_center", "rgb_highres_center"]


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("ev") / "fire_ev"
    generate(folder, SynthConfig(scene="fire_site", frames=20, scale=0.05, lidar_density=0.5))
    return folder


@pytest.fixture(scope="module")
def prep_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One preparation cache for the module: the CLI run prepares the sequence with the
    ins and fused strategies, the tests after it read those preparations back."""
    return tmp_path_factory.mktemp("ev_cache")


@pytest.fixture(scope="module")
def truth_tracks(seq: Path) -> dict:
    """{"truth": (true poses, cloud registered with them), "jumpy": (poses with a 2 m
    sideways jump from frame 10 on, the same cloud re-registered with them)}."""
    from geometry.geodesy import WorldFrame
    from worker.preparation.registration import register_clouds

    s = Sequence.open(seq)
    truth = PoseTrack.from_csv(seq / "ground_truth/poses.csv")
    cloud = register_clouds(s, truth, voxel_size=0.05, frames=s.frame_indices, max_range=90.0)
    T = truth.T.copy()
    T[10:, :3, 3] += T[10:, :3, :3] @ np.array([0.0, 2.0, 0.0])
    jumpy = PoseTrack(truth.timestamps, T, truth.frame_idx)
    world = WorldFrame.from_json(json.loads((seq / "ground_truth/world.json").read_text()))

    class _Prepared:  # the two attributes cloud_for_track reads
        pass

    p = _Prepared()
    p.track, p.cloud = truth, cloud
    return {
        "world": world,
        "truth": (truth, cloud.xyz),
        "jumpy": (jumpy, cloud_for_track(p, jumpy)),
    }


def test_jitter_only_between_consecutive_frames() -> None:
    assert _jitter([3, 4, 6, 7], [1.0, 2.5, 9.0, 8.0]) == [None, 1.5, None, 1.0]
    s = summarize_rpe({"a": {"frames": [0, 1, 2], "rpe": [1.0, 2.0, 4.0], "xyz": [0, 0, 0]}})
    assert s["rpe_mean"] == pytest.approx(7 / 3) and s["jitter_mean"] == pytest.approx(1.5)
    assert s["n"] == 3 and s["n_jitter"] == 2 and s["landmark_mean"] == pytest.approx(7 / 3)


def test_synthetic_clicks_are_30_to_80_m_ahead(seq: Path) -> None:
    clicks = synthetic_clicks(seq, CAMS, near=30.0, far=80.0, click_target="landmark")
    assert clicks, "no landmark 30-80 m ahead"
    lms = {lm["id"]: lm for lm in json.loads((seq / "ground_truth/landmarks.json").read_text())}
    for c in clicks:
        for cam, frames in c.uv.items():
            assert len(frames) >= 5
            for f, uv in frames.items():
                assert np.allclose(uv, lms[c.landmark]["pixels"][cam][str(f)])
    noisy = synthetic_clicks(seq, CAMS, click_noise_px=2.0, seed=1, click_target="landmark")
    d = [
        np.linalg.norm(noisy[0].uv[cam][f] - clicks[0].uv[cam][f])
        for cam in clicks[0].uv
        for f in clicks[0].uv[cam]
    ]
    assert 0.5 < np.mean(d) < 5.0


def test_only_landmarks_the_lidar_measured_are_clicked(seq: Path) -> None:
    """nearest_returns gives the nearest return of any frame (true poses) and its distance; the
    synthetic operator clicks only landmarks with one within 0.25 m (none within 1 mm)."""
    from worker.preparation.frame_clouds import FrameClouds
    from worker.preparation.registration import register_clouds

    s = Sequence.open(seq)
    truth = PoseTrack.from_csv(seq / "ground_truth/poses.csv")
    lms = json.loads((seq / "ground_truth/landmarks.json").read_text())
    xyz = np.array([lm["xyz"] for lm in lms], dtype=np.float64)
    got, p_ret = nearest_returns(FrameClouds(s, max_range=120.0), truth, xyz)
    full = register_clouds(s, truth, voxel_size=0.0, max_range=120.0).xyz
    brute = np.array([np.min(np.linalg.norm(full - p, axis=1)) for p in xyz])
    near = brute <= 2.0
    assert near.any() and (~near).any()  # the test means something both ways
    np.testing.assert_allclose(got[near], brute[near], atol=1e-5)  # float32 points
    assert np.all(np.isinf(got[~near]))
    brute_p = np.array([full[np.argmin(np.linalg.norm(full - p, axis=1))] for p in xyz])
    np.testing.assert_allclose(p_ret[near], brute_p[near], atol=1e-4)
    assert np.all(np.isnan(p_ret[~near]))
    clicked = {c.landmark for c in synthetic_clicks(seq, CAMS)}
    supported = {lm["id"] for lm, d in zip(lms, got, strict=True) if d <= 0.25}
    assert clicked and clicked <= supported
    unsupported_in_view = {c.landmark for c in synthetic_clicks(seq, CAMS, lidar_support_m=0.0)}
    assert clicked == unsupported_in_view & supported
    # none measured within 1 mm: the unmeasured ones are clicked (with a warning)
    every = [c.landmark for c in synthetic_clicks(seq, CAMS, lidar_support_m=0.0)]
    assert [c.landmark for c in synthetic_clicks(seq, CAMS, lidar_support_m=1e-3)] == every


def test_nearest_returns_when_landmarks_share_their_nearest_points() -> None:
    """Two landmarks 0.3 m apart: the return nearest A lies nearer still to B, and is A's
    nearest all the same; a return of a later frame counts where it is nearer."""
    from types import SimpleNamespace

    A, B = np.array([10.0, 0.0, 2.0]), np.array([10.0, 0.3, 2.0])
    frame0 = np.array([[10.0, 0.2, 2.0], [10.0, -0.5, 2.0], [50.0, 0.0, 0.0]], np.float32)
    frame1 = np.array([[9.0, 0.05, 2.0], [9.0, 3.0, 2.0]], np.float32)

    def clouds(frames: list[int]) -> SimpleNamespace:
        return SimpleNamespace(
            frames=frames,
            frame_times={0: 0.0, 1: 0.1},
            get=lambda f: SimpleNamespace(p_base32=[frame0, frame1][f]),
        )

    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, 0, 3] = 1.0  # frame 1's base 1 m further along x: its points 1 m further in the world
    track = PoseTrack(np.array([0.0, 0.1]), T, np.array([0, 1]))
    lms = np.stack([A, B, [90.0, 0.0, 0.0]])
    d, p = nearest_returns(clouds([0]), track, lms)
    np.testing.assert_allclose(d[:2], [0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(p[:2], [[10.0, 0.2, 2.0], [10.0, 0.2, 2.0]], atol=1e-6)
    d, p = nearest_returns(clouds([0, 1]), track, lms)
    np.testing.assert_allclose(d[:2], [0.05, 0.1], atol=1e-6)
    np.testing.assert_allclose(p[:2], [[10.0, 0.05, 2.0], [10.0, 0.2, 2.0]], atol=1e-6)
    assert np.isinf(d[2]) and np.all(np.isnan(p[2]))


def test_return_clicks_are_the_nearest_returns_true_pixels(seq: Path) -> None:
    """The default synthetic click on a measured landmark is its nearest return's true
    pixel, projected as the generator projects the landmark's own (same pixels to 0.01 px),
    in the frames where the landmark is in view, within 0.25 m (3D) of the landmark."""
    from worker.evaluation.evaluate import _camera_times, full_resolution_cameras
    from worker.preparation.frame_clouds import FrameClouds

    s = Sequence.open(seq)
    truth = PoseTrack.from_csv(seq / "ground_truth/poses_dense.csv")
    lms = {lm["id"]: lm for lm in json.loads((seq / "ground_truth/landmarks.json").read_text())}
    cams = full_resolution_cameras(s, CAMS)
    at_lm = synthetic_clicks(seq, CAMS, click_target="landmark")
    at_ret = synthetic_clicks(seq, CAMS)
    assert [c.landmark for c in at_ret] == [c.landmark for c in at_lm]
    ids = [c.landmark for c in at_ret]
    xyz = np.array([lms[i]["xyz"] for i in ids], dtype=np.float64)
    d, p_ret = nearest_returns(FrameClouds(s, max_range=120.0), truth, xyz)
    assert np.all(d <= 0.25)
    moved = []
    for k, c_ret in enumerate(at_ret):
        for cam, frames in c_ret.uv.items():
            times = _camera_times(s, cam)
            assert all(lms[ids[k]]["pixels"][cam][str(f)] is not None for f in frames)
            for f, uv in frames.items():
                T = truth.interpolate(np.array([times[f]]))[0]
                lm_uv, _ = cams[cam].project_world(xyz[k], T)
                np.testing.assert_allclose(lm_uv[0], lms[ids[k]]["pixels"][cam][str(f)], atol=0.01)
                ret_uv, _ = cams[cam].project_world(p_ret[k], T)
                np.testing.assert_allclose(uv, ret_uv[0], atol=1e-9)
                T_opt_world = np.linalg.inv(T @ cams[cam].T_base_opt)
                assert 30.0 <= T_opt_world[2, :3] @ p_ret[k] + T_opt_world[2, 3] <= 80.0
                moved.append(np.linalg.norm(uv - lm_uv[0]))
    assert moved and max(moved) > 0.5  # the returns are not the landmarks
    # none measured within 1 mm: the fallback clicks every landmark in view at its nearest
    # return within 2 m, still a point of the cloud
    fallback = synthetic_clicks(seq, CAMS, lidar_support_m=1e-3)
    ids = [c.landmark for c in fallback]
    xyz = np.array([lms[i]["xyz"] for i in ids], dtype=np.float64)
    d, p_ret = nearest_returns(FrameClouds(s, max_range=120.0), truth, xyz)
    assert len(fallback) and np.all(np.isfinite(d))
    for k, c in enumerate(fallback):
        for cam, frames in c.uv.items():
            times = _camera_times(s, cam)
            for f, uv in frames.items():
                T = truth.interpolate(np.array([times[f]]))[0]
                np.testing.assert_allclose(uv, cams[cam].project_world(p_ret[k], T)[0][0])
    with pytest.raises(ValueError, match="click_target"):
        synthetic_clicks(seq, CAMS, click_target="pole")


def test_rpe_with_true_poses_is_small_and_grows_with_a_jump(seq: Path, truth_tracks) -> None:
    tracks = {k: truth_tracks[k] for k in ("truth", "jumpy")}
    m, rows = evaluate_strategies(seq, tracks, world=truth_tracks["world"], cameras=CAMS)
    assert m["clicks_source"] == "ground_truth" and m["landmarks_clicked"]
    for cam in CAMS:
        t, j = m["rpe"][cam]["truth"], m["rpe"][cam]["jumpy"]
        assert t["n"] > 10 and t["n_jitter"] > 5
        # the clicked return is a point of the cloud: with the true poses it is found again
        # and projects onto its clicks (float32 points: hundredths of a pixel)
        assert t["rpe_mean"] < 0.1, (cam, t)
        assert t["jitter_mean"] < 0.05, (cam, t)
        assert j["jitter_max"] > 10 * max(t["jitter_max"], 1.0), (cam, j)
        for key in ("rpe_mean", "rpe_std", "jitter_mean", "jitter_std", "landmark_mean"):
            assert np.isfinite(t[key])
    te = m["true_errors"]["truth"]
    assert te["translation_m_max"] < 1e-6 and te["rotation_deg_max"] < 1e-6
    for cam in CAMS:
        assert te["anchor_px"][cam]["rpe_mean"] < 0.05  # true poses (10 Hz, interpolated)
    assert m["true_errors"]["jumpy"]["translation_m_max"] == pytest.approx(2.0, abs=1e-6)
    # rows: one per (camera, strategy, landmark, frame), jitter empty at a run's start
    assert {r["strategy"] for r in rows} == {"truth", "jumpy"}
    first = [r for r in rows if r["jitter_px"] is None]
    assert first and all(r["rpe_px"] >= 0 for r in rows)
    # clicks on the pole tops themselves: the RPE carries their distance to the nearest
    # return (cloud discreteness: sparse lidar, a few px with the true poses)
    at_lm = synthetic_clicks(seq, CAMS, click_target="landmark")
    m, _ = evaluate_strategies(
        seq, {"truth": truth_tracks["truth"]}, world=truth_tracks["world"], cameras=CAMS,
        clicks=at_lm,
    )  # fmt: skip
    for cam in CAMS:
        t = m["rpe"][cam]["truth"]
        assert 0.5 < t["rpe_mean"] < 4.0, (cam, t)
        assert t["jitter_mean"] < 1.0, (cam, t)


def test_cloud_for_track_is_the_registration_with_that_track(seq: Path, truth_tracks) -> None:
    from scipy.spatial import cKDTree

    from worker.preparation.registration import register_clouds

    s = Sequence.open(seq)
    jumpy, moved = truth_tracks["jumpy"]
    assert len(moved) == len(truth_tracks["truth"][1]) and np.all(np.isfinite(moved))
    direct = register_clouds(s, jumpy, voxel_size=0.05, frames=s.frame_indices, max_range=90.0)
    # every moved point lies where registering with the jumpy poses puts a point
    dist, _ = cKDTree(direct.xyz).query(moved[:: max(1, len(moved) // 2000)])
    assert np.percentile(dist, 95) < 0.06


def test_clicks_file_cli_writes_everything(
    seq: Path, tmp_path: Path, prep_cache: Path, capsys
) -> None:
    """A clicks CSV of one landmark (the README's format) through ``osdar-ar evaluate``."""
    from worker.cli import main

    c = synthetic_clicks(seq, CAMS)[0]
    clicks_csv = tmp_path / "pole.csv"
    with clicks_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["camera", "frame_idx", "u", "v"])
        for cam, frames in c.uv.items():
            for fr, uv in sorted(frames.items()):
                w.writerow([cam, fr, f"{uv[0]:.3f}", f"{uv[1]:.3f}"])
            w.writerow([cam, 19, "", ""])  # no click in that frame
    out = tmp_path / "ev"
    rc = main(
        [
            "evaluate", str(seq), "--out", str(out), "--strategies", "ins,fused",
            "--clicks", str(clicks_csv), "--cache-dir", str(prep_cache),
        ]
    )  # fmt: skip
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["clicks_source"] == "file" and m["landmarks_clicked"] == ["pole"]
    assert m["strategies"] == ["ins", "fused"]
    for cam in c.uv:
        for s in ("ins", "fused"):
            st = m["rpe"][cam][s]
            assert st["n"] == len(c.uv[cam]) and st["rpe_mean"] is not None
            assert {"rpe_std", "jitter_mean", "jitter_std", "landmarks"} <= set(st)
    assert m["preparation"]["fused"]["chosen"] == "fused"
    assert "true_errors" in m
    with (out / "per_frame.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows and list(rows[0]) == [
        "camera", "strategy", "landmark", "frame_idx", "click_u", "click_v", "proj_u",
        "proj_v", "rpe_px", "jitter_px",
    ]  # fmt: skip
    assert (out / "rpe.png").stat().st_size > 1000
    overlays = m["files"]["overlays"]
    assert overlays and all(Path(p).is_file() for p in overlays)
    assert "RPE mean" in capsys.readouterr().out


def test_cli_click_target(seq: Path, tmp_path: Path, prep_cache: Path) -> None:
    """``--click-target landmark`` clicks the landmarks themselves: their RPE with the same
    poses is that of the returns plus their distance to them, larger on the whole."""
    from worker.cli import main

    got = {}
    for target in ("return", "landmark"):
        out = tmp_path / target
        args = ["evaluate", str(seq), "--out", str(out), "--strategies", "fused", "--no-overlay"]
        assert main([*args, "--click-target", target, "--cache-dir", str(prep_cache)]) == 0
        got[target] = json.loads((out / "metrics.json").read_text())
        assert got[target]["click_target"] == target
    ret, lm = (got[t]["rpe"]["rgb_highres_center"]["fused"] for t in ("return", "landmark"))
    assert ret["n"] > 10 and lm["n"] > 10
    assert lm["rpe_mean"] > ret["rpe_mean"]


def test_cli_errors_exit_2(seq: Path, tmp_path: Path, prep_cache: Path) -> None:
    from worker.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("camera,frame_idx,u,v\nrgb_nope,0,1,2\n")
    args = ["evaluate", str(seq), "--out", str(tmp_path / "o"), "--strategies", "ins"]
    assert main([*args, "--clicks", str(bad), "--cache-dir", str(prep_cache)]) == 2


def test_evaluate_sequence_keeps_the_job_keys_and_adds_the_paper_rpe(
    seq: Path, prep_cache: Path
) -> None:
    from worker.evaluation.evaluate import evaluate_sequence
    from worker.preparation.config import PrepareConfig
    from worker.preparation.prepare import prepare

    prepared = prepare(seq, PrepareConfig(strategy="fused"), cache_dir=prep_cache)
    m, series = evaluate_sequence(seq, prepared, CAMS)
    assert m["strategy"] == "fused"
    assert m["ground_truth"]["pose_error"]["ins"]["translation_m_mean"] >= 0
    assert m["ground_truth"]["landmark_rpe"]["rgb_center"]["fused"]["rpe_px"]["n"] > 0
    assert set(m["paper_rpe"]["rgb_highres_center"]) == {"fused", "ins", "odometry"}
    assert series
    json.dumps(m, allow_nan=False)


@pytest.fixture(scope="module")
def merged_twins(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The fixture's fire_site twice with the same seed: merged without a calibration error
    and with one (5 cm per axis per lidar, no rotation): the same beams, the same hits, the
    second's points moved by their lidar's error."""
    from worker.synth.generator import SynthConfig, generate

    root = tmp_path_factory.mktemp("twins")
    out = []
    for name, err in (("exact", (0.0, 0.0)), ("merged", (0.0, 0.05))):
        cfg = SynthConfig(
            scene="fire_site", frames=20, scale=0.05, lidar_density=0.5, lidar_merge_error=err
        )
        generate(root / name, cfg)
        out.append(root / name)
    return out[0], out[1]


def test_return_clicks_see_the_merged_clouds_calibration_error(merged_twins) -> None:
    """The operator clicks where the beam truly hit: on the cloud merged with an error the
    return clicks are those of its error-free twin (the same hits), the recorded-return
    clicks are not; with the true poses the RPE of the return clicks is then the cloud's
    calibration error seen in the image (the calibration point is a point of that cloud),
    that of the recorded-return clicks hundredths of a pixel as on the exact cloud."""
    from geometry.geodesy import WorldFrame
    from worker.evaluation.evaluate import merge_errors_of
    from worker.preparation.registration import register_clouds

    exact, merged = merged_twins
    errors = merge_errors_of(merged)
    assert merge_errors_of(exact) == {} and len(errors) >= 2
    shift = [np.linalg.norm(E[:3, 3]) for E in errors.values()]
    assert 0.02 < np.median(shift) < 0.2  # what the error is: centimetres per lidar
    want = synthetic_clicks(exact, CAMS)
    got = synthetic_clicks(merged, CAMS)
    recorded = synthetic_clicks(merged, CAMS, click_target="return_recorded")
    assert [c.landmark for c in got] == [c.landmark for c in want] and want
    moved: dict[str, list[float]] = {c: [] for c in CAMS}
    for w, g, r in zip(want, got, recorded, strict=True):
        assert g.uv.keys() == w.uv.keys()
        for cam, frames in w.uv.items():
            for f, uv in frames.items():
                np.testing.assert_allclose(g.uv[cam][f], uv, atol=0.05)  # float32 points
                if f in r.uv.get(cam, {}):
                    moved[cam].append(np.linalg.norm(r.uv[cam][f] - uv))
    c2 = "rgb_highres_center"
    assert moved[c2] and np.median(moved[c2]) > 1.0  # the recorded returns are elsewhere

    s = Sequence.open(merged)
    truth = PoseTrack.from_csv(merged / "ground_truth/poses.csv")
    world = WorldFrame.from_json(json.loads((merged / "ground_truth/world.json").read_text()))
    cloud = register_clouds(s, truth, voxel_size=0.05, frames=s.frame_indices, max_range=90.0)
    tracks = {"truth": (truth, cloud.xyz)}
    m_ret, _ = evaluate_strategies(merged, tracks, world=world, cameras=CAMS, clicks=got)
    m_rec, _ = evaluate_strategies(merged, tracks, world=world, cameras=CAMS, clicks=recorded)
    for cam in CAMS:
        assert m_rec["rpe"][cam]["truth"]["rpe_mean"] < 0.1
        # each click's recorded return projected with the true poses is the error the cloud
        # shows at the click (6 / 10 px here); the calibration point, the cloud point
        # nearest the clicks' rays, is that return or a point of another lidar's, shifted
        # by another error: the RPE is of the errors' size, at most the recorded return's
        ret = m_ret["rpe"][cam]["truth"]["rpe_mean"]
        assert 0.25 * np.median(moved[cam]) < ret < 1.1 * np.mean(moved[cam]), cam


def test_corrected_cloud_gives_the_return_clicks_back(merged_twins) -> None:
    """The merge error undone exactly (every lidar's correction E^-1, applied to the
    registered cloud and, through ``lidar_corrections``, to the full-density points): with
    the true poses the RPE of the return clicks is hundredths of a pixel again."""
    from geometry.geodesy import WorldFrame
    from worker.evaluation.evaluate import merge_errors_of
    from worker.preparation.frame_clouds import FrameClouds
    from worker.preparation.registration import register_clouds

    _, merged = merged_twins
    exact = {s: np.linalg.inv(E) for s, E in merge_errors_of(merged).items()}
    s = Sequence.open(merged)
    truth = PoseTrack.from_csv(merged / "ground_truth/poses.csv")
    world = WorldFrame.from_json(json.loads((merged / "ground_truth/world.json").read_text()))
    clouds = FrameClouds(s, max_range=90.0)
    clouds.set_corrections(exact)
    cloud = register_clouds(
        s, truth, voxel_size=0.05, frames=s.frame_indices, max_range=90.0, clouds=clouds
    )
    m, _ = evaluate_strategies(
        merged, {"truth": (truth, cloud.xyz)}, world=world, cameras=CAMS,
        lidar_corrections=exact,
    )  # fmt: skip
    assert m["lidar_corrections"] == sorted(exact)
    for cam in CAMS:
        assert m["rpe"][cam]["truth"]["rpe_mean"] < 0.1, cam


def test_corrections_read_back_from_the_summary() -> None:
    """A preparation summary's ``lidar_alignment`` gives back the applied corrections only."""
    from worker.preparation.lidar_alignment import (
        LidarAlignment,
        SensorCorrection,
        corrections_from_summary,
    )

    def corr(s: int, applied: bool) -> SensorCorrection:
        T = np.eye(4)
        T[:3, 3] = [0.01 * s, -0.02, 0.005]
        return SensorCorrection(
            s, T, applied, "" if applied else "halves disagree", 500, (250, 250), 0.001,
            0.001, 0.001, 0.001, 0.02, 0.01,
        )  # fmt: skip

    alignment = LidarAlignment(0, {1: corr(1, True), 2: corr(2, False), 3: corr(3, True)})
    back = corrections_from_summary(json.loads(json.dumps(alignment.summary())))
    assert sorted(back) == [1, 3]
    for k, T in alignment.corrections().items():
        np.testing.assert_array_equal(back[k], T)
    assert corrections_from_summary(None) == {}
