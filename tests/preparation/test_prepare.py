"""Preparation end to end: the CLI, the artifact, the cache and its lock."""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from geometry.poses import PoseTrack
from tests.synth_fixtures import synth_sequence, true_poses
from worker.cli import main
from worker.preparation import artifact as art
from worker.preparation import prepare as prep
from worker.preparation.calibration_point import Clicks
from worker.preparation.config import PrepareConfig

FILES = (*art.FILES, "reference_poses/ins.csv", "reference_poses/odometry.csv")


@pytest.fixture(scope="module")
def seq_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth_sequence(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def localization() -> None:
    """The localization package (a stand-in strategy only until ``run_strategy`` lands)."""
    import worker.preparation.localization as loc

    if hasattr(loc, "run_strategy"):
        yield
        return
    from worker.preparation.localization.odometry import OdometryStrategy, odometry_track

    mp = pytest.MonkeyPatch()
    mp.setattr(loc, "odometry_track", odometry_track, raising=False)
    mp.setattr(loc, "run_strategy", lambda name, inp: OdometryStrategy().run(inp), raising=False)
    yield
    mp.undo()


@pytest.fixture(scope="module")
def first_run(seq_folder: Path, tmp_path_factory: pytest.TempPathFactory, localization) -> dict:
    base = tmp_path_factory.mktemp("prep")
    out, cache = base / "out", base / "cache"
    argv = ["prepare", str(seq_folder), "--strategy", "ins", "--out", str(out)]
    argv += ["--cache-dir", str(cache), "--json"]
    t0 = time.perf_counter()
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(argv)
    return {
        "rc": rc,
        "summary": json.loads(buf.getvalue()),
        "seconds": time.perf_counter() - t0,
        "out": out,
        "cache": cache,
        "argv": argv,
    }


def test_cli_writes_every_file(first_run: dict) -> None:
    assert first_run["rc"] == 0
    out = first_run["out"]
    for name in FILES:
        assert (out / name).is_file(), name
    s = first_run["summary"]
    assert s["artifact_version"] == art.ARTIFACT_VERSION
    assert s["requested_strategy"] == "ins"
    assert set(prep.STAGES) <= set(s["timings"])
    assert s["cloud"]["points"] > 1000
    assert s["true_pose_errors"] and s["true_pose_errors"][0]["frames"] == 12
    world = json.loads((out / "world.json").read_text())
    assert set(world) == {"latitude", "longitude", "height"}
    prepared = art.read_artifact(out)
    assert prepared.key == s["key"]
    assert len(prepared.cloud) == s["cloud"]["points"]
    assert prepared.cloud.xyz.dtype == np.float64
    assert json.loads((out / "calibration_point.json").read_text())["mode"] == "auto"


def test_poses_csv_compares_directly_with_ground_truth(first_run: dict, seq_folder: Path) -> None:
    ours = PoseTrack.from_csv(first_run["out"] / "poses.csv")
    gt = true_poses(seq_folder)
    assert np.array_equal(ours.frame_idx, gt.frame_idx)
    assert np.allclose(ours.timestamps, gt.timestamps, rtol=0.0, atol=1e-6)  # same stamps
    dt, dr = ours.relative_errors(gt)
    assert np.all(np.isfinite(dt)) and np.all(np.isfinite(dr))
    assert dt.mean() < 10.0 and dr.mean() < 10.0  # same frame (ENU at the first INS record)


def test_second_run_reuses_the_cache(first_run: dict, capsys: pytest.CaptureFixture) -> None:
    argv = [a for a in first_run["argv"] if a != "--json"]
    t0 = time.perf_counter()
    assert main(argv) == 0
    seconds = time.perf_counter() - t0
    text = capsys.readouterr().out
    assert "reused" in text and first_run["summary"]["key"][:16] in text
    assert "true pose errors" in text
    assert seconds < max(3.0, 0.3 * first_run["seconds"])
    assert art.artifact_key(first_run["out"]) == first_run["summary"]["key"]


def test_changed_config_or_clicks_gives_a_new_key(seq_folder: Path) -> None:
    from worker.osdar.sequence import Sequence

    content = Sequence.open(seq_folder).content_key()
    base = PrepareConfig(strategy="ins")
    keys = {
        art.cache_key(content, base.config_hash()),
        art.cache_key(content, base.with_overrides(registration={"voxel_size": 0.2}).config_hash()),
        art.cache_key(content, base.with_overrides(strategy="rails").config_hash()),
        art.cache_key(content, base.config_hash(), Clicks("a", {}).digest()),
    }
    assert len(keys) == 4
    assert art.cache_key(content, PrepareConfig(strategy="ins").config_hash()) in keys


def test_broken_sequence_is_a_clear_cli_error(
    seq_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(seq_folder, broken)
    next((broken / "lidar").glob("*.pcd")).unlink()
    rc = main(["prepare", str(broken), "--out", str(tmp_path / "o"), "--cache-dir", str(tmp_path)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "osdar-ar prepare: error:" in err and "missing" in err
    rc = main(["prepare", str(tmp_path / "nope"), "--out", str(tmp_path / "o")])
    assert rc == 2


def test_bad_clicks_and_strategy_are_cli_errors(
    seq_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    clicks = tmp_path / "c.csv"
    clicks.write_text("camera,frame_idx,u,v\nrgb_left,0,10,20\n")
    argv = ["prepare", str(seq_folder), "--out", str(tmp_path / "o"), "--cache-dir", str(tmp_path)]
    assert main([*argv, "--clicks", str(clicks)]) == 2
    assert "rgb_left" in capsys.readouterr().err
    assert main([*argv, "--strategy", "magic"]) == 2
    assert "unknown strategy" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_one_preparation_per_key(
    seq_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Concurrent preparations of one key: one computes, the others wait and reuse it."""
    real = art.read_artifact
    calls: list[float] = []

    def fake_run(seq, config, *, clicks=None, progress=None, key=""):
        calls.append(time.perf_counter())
        time.sleep(0.5)
        from geometry.geodesy import WorldFrame
        from worker.preparation.registration import RegisteredCloud

        cloud = RegisteredCloud(
            np.zeros((3, 3)), np.zeros(3, np.int32), np.zeros(3, np.uint8), np.zeros(3, np.float32)
        )
        track = PoseTrack(np.array([0.0, 0.1]), np.tile(np.eye(4), (2, 1, 1)), [0, 1])
        return art.PreparedSequence(
            key=key, world=WorldFrame(53.5, 10.0, 30.0), track=track, centrelines=[],
            planes=[], poles=[], calibration=None,
            summary={"artifact_version": art.ARTIFACT_VERSION, "timings": {}}, _cloud=cloud,
        )  # fmt: skip

    monkeypatch.setattr(prep, "run_preparation", fake_run)
    monkeypatch.setattr(art, "read_artifact", real)
    results: list[art.PreparedSequence] = []
    threads = [
        threading.Thread(
            target=lambda: results.append(prep.prepare(seq_folder, cache_dir=tmp_path / "c"))
        )
        for _ in range(3)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len({r.key for r in results}) == 1
    assert sorted(bool(r.summary.get("reused")) for r in results) == [False, True, True]
    assert not list((tmp_path / "c").glob(".*tmp*"))


def test_pre_registration_keeps_its_own_band_and_voxel() -> None:
    """The pre-registration registers a narrower band (pre_lateral_limit, 10 m) with coarser
    voxels than the final cloud (lateral_limit 30 m); both knobs reach register_clouds."""
    cfg = PrepareConfig()
    pre, final = cfg.registration_kwargs(False), cfg.registration_kwargs(True)
    assert pre["lateral_limit"] == 10.0 and final["lateral_limit"] == 30.0
    assert pre["voxel_size"] == 0.25 and final["voxel_size"] == 0.1
    wide = cfg.with_overrides(registration={"pre_lateral_limit": None})
    assert wide.registration_kwargs(False)["lateral_limit"] is None
    assert wide.config_hash() != cfg.config_hash()


def test_poses_csv_keeps_the_input_timestamp_strings(first_run: dict, seq_folder: Path) -> None:
    """Every poses.csv the preparation writes has each frame's lidar timestamp exactly as
    the labels write it (nanosecond digits included), not as float64 printed back."""
    import csv

    from worker.osdar.sequence import Sequence

    seq = Sequence.open(seq_folder)
    expected = seq.timestamp_text(seq.lidar_stream)
    assert any(len(v.split(".")[1]) == 9 for v in expected.values())
    for path in [
        first_run["out"] / "poses.csv",
        *(first_run["out"] / "reference_poses").glob("*.csv"),
    ]:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        assert rows and {int(r["frame_idx"]): r["timestamp"] for r in rows} == expected, path
