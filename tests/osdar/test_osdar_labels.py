"""OpenLABEL labels: parsing the real OSDaR23 file, lossless rewrite, schema validation."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from osdar_platform.shared_data import openlabel_schema_path
from worker.osdar import SequenceError, dump_labels, load_labels, parse_labels, validate_openlabel
from worker.osdar.labels import encode_labels, pose_to_matrix


@pytest.fixture(scope="module")
def real(real_labels_path: Path):
    return load_labels(real_labels_path)


def test_coordinate_systems(real) -> None:
    cs = real.coordinate_systems
    assert len(cs) == 12 and cs["base"].parent == "" and cs["base"].type == "local"
    np.testing.assert_array_equal(cs["lidar"].T_parent_cs, np.eye(4))
    np.testing.assert_array_equal(cs["base"].T_parent_cs, np.eye(4))
    T = cs["rgb_center"].T_parent_cs
    assert T.shape == (4, 4) and T.dtype == np.float64 and cs["rgb_center"].parent == "base"
    np.testing.assert_allclose(T[:3, 3], [0.0669458, -0.000911152, 2.05432])
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_streams_frames_objects(real) -> None:
    assert real.streams["lidar"].type == "lidar" and real.streams["lidar"].intrinsics is None
    cam = real.streams["rgb_center"]
    assert cam.type == "camera" and cam.uri == "rgb_center"
    assert cam.intrinsics["camera_matrix"][0] == pytest.approx(4609.471892628096)
    assert cam.intrinsics["width_px"] == 2464
    assert [f.index for f in real.frames] == list(range(12, 22))
    f12 = real.frames[0]
    assert f12.timestamp_str == "1631441453.299504000"
    assert f12.timestamp == pytest.approx(1631441453.299504, abs=1e-6)
    rgb = f12.streams["rgb_center"]
    assert rgb.uri == "/rgb_center/012_1631441453.300000000.png"
    assert rgb.timestamp_str == "1631441453.300000000"
    assert f12.streams["lidar"].uri.endswith(f"012_{f12.streams['lidar'].timestamp_str}.pcd")
    assert len(real.objects) == 37
    info = real.objects["004bce8f-bb3f-4af8-bdc1-25d1ab1518f8"]
    assert (info.name, info.type) == ("catenary_pole0003", "catenary_pole")
    objs = real.frame_objects(12)
    assert objs and set(objs["004bce8f-bb3f-4af8-bdc1-25d1ab1518f8"]) == {"bbox", "cuboid", "vec"}
    assert real.frame_objects(99) == {}
    assert real.frame(13).index == 13


def test_round_trip_real_file(real, real_labels_path: Path, tmp_path: Path) -> None:
    out = dump_labels(real.raw, tmp_path / "copy_labels.json")
    again = load_labels(out)
    assert again.raw == real.raw == json.loads(real_labels_path.read_bytes())
    data = out.read_bytes()
    # OSDaR23 formatting: compact separators, newline at the end
    assert data.startswith(b'{"openlabel":{"metadata":{"schema_version":"1.0.0",')
    assert data.endswith(b'"frame_intervals":[{"frame_start":12,"frame_end":21}]}}\n')
    assert abs(len(data) - real_labels_path.stat().st_size) < 1000
    # atomic: nothing but the file in the folder
    assert [p.name for p in tmp_path.iterdir()] == ["copy_labels.json"]


def test_raillabel_reads_rewritten_file(real, tmp_path: Path) -> None:
    raillabel = pytest.importorskip("raillabel")
    raw = copy.deepcopy(real.raw)
    raw["openlabel"]["metadata"]["comment"] += " Rewritten by osdar-ar."
    scene = raillabel.load(dump_labels(raw, tmp_path / "x_labels.json"))
    assert sorted(scene.frames) == list(range(12, 22))
    assert "rgb_center" in scene.sensors


def test_schema_validation(real, tmp_path: Path) -> None:
    if not openlabel_schema_path().is_file():
        pytest.skip("OpenLABEL schema not available")
    assert validate_openlabel(real.raw) == []
    rewritten = load_labels(dump_labels(real.raw, tmp_path / "r_labels.json"))
    assert validate_openlabel(rewritten.raw) == []
    broken = copy.deepcopy(real.raw)
    del broken["openlabel"]["metadata"]["schema_version"]
    broken["openlabel"]["frames"]["12"]["frame_properties"]["streams"]["lidar"]["uri"] = 5
    errors = validate_openlabel(broken)
    assert len(errors) == 2 and any("schema_version" in e for e in errors)


def test_schema_missing_returns_empty(tmp_path: Path) -> None:
    assert validate_openlabel({"openlabel": {}}, schema_path=tmp_path / "none.json") == []


def test_poses() -> None:
    T = pose_to_matrix({"translation": [1, 2, 3], "quaternion": [0, 0, 2, 2]})  # unnormalised
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_array_equal(T[:3, 3], [1, 2, 3])
    M = np.arange(16.0).reshape(4, 4)
    np.testing.assert_array_equal(pose_to_matrix({"matrix4x4": M.ravel().tolist()}), M)


@pytest.mark.parametrize(
    ("pose", "words"),
    [
        (
            {"translation": [0, float("nan"), 0], "quaternion": [0, 0, 0, 1]},
            "non-finite translation",
        ),
        (
            {"translation": [0, 0, 0], "quaternion": [0, 0, float("nan"), 1]},
            "non-finite quaternion",
        ),
        ({"translation": [0, 0, 0], "quaternion": [0, 0, 0, 0]}, "zero quaternion"),
        ({"translation": [0, 0], "quaternion": [0, 0, 0, 1]}, "bad pose"),
    ],
)
def test_bad_pose(real, pose: dict, words: str) -> None:
    raw = copy.deepcopy(real.raw)
    raw["openlabel"]["coordinate_systems"]["rgb_center"]["pose_wrt_parent"] = pose
    with pytest.raises(SequenceError) as info:
        parse_labels(raw, "seq_labels.json")
    assert "rgb_center" in str(info.value) and words in str(info.value)
    assert str(info.value).startswith("seq_labels.json: ")


def test_unreadable_labels(tmp_path: Path) -> None:
    bad = tmp_path / "bad_labels.json"
    bad.write_text('{"openlabel": {"frames": ')
    with pytest.raises(SequenceError, match="not valid JSON") as info:
        load_labels(bad)
    assert info.value.path == bad
    bad.write_text('{"metadata": {}}')
    with pytest.raises(SequenceError, match="no top-level 'openlabel'"):
        load_labels(bad)
    with pytest.raises(SequenceError, match="cannot read"):
        load_labels(tmp_path / "missing_labels.json")


def test_dump_refuses_nan(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        encode_labels({"openlabel": {"x": float("nan")}})
    with pytest.raises(ValueError):
        dump_labels({"openlabel": {"x": float("inf")}}, tmp_path / "n_labels.json")
    assert list(tmp_path.iterdir()) == []
