"""The onnxruntime segmentation runner, with small real ONNX graphs (tests/onnx_models.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.onnx_models import RAIL_RAISED, TERRAIN, rust_rail_model
from worker.preparation.segmentation import (
    DEFAULT_RAIL_CLASSES,
    RAILSEM19_CLASSES,
    SegmentationModel,
)


def test_railsem19_class_map() -> None:
    assert len(RAILSEM19_CLASSES) == 19
    assert RAILSEM19_CLASSES[12] == "rail-track"
    assert RAILSEM19_CLASSES[RAIL_RAISED] == "rail-raised"
    assert RAILSEM19_CLASSES[18] == "rail-embedded"
    assert set(DEFAULT_RAIL_CLASSES) <= set(RAILSEM19_CLASSES)


def _image() -> np.ndarray:
    img = np.full((40, 60, 3), (150, 146, 143), np.uint8)  # ballast grey
    img[:, 20:22] = (126, 110, 100)  # a rust-brown rail
    img[:, 40:42] = (126, 110, 100)
    img[:10] = (177, 190, 212)  # sky
    return img


@pytest.mark.parametrize("output", ["logits", "labels"])
def test_rule_model_logits_and_labels(tmp_path: Path, output: str) -> None:
    m = SegmentationModel(rust_rail_model(tmp_path / "m.onnx", output=output))
    lab = m.predict(_image())
    assert lab.shape == (40, 60)
    assert set(np.unique(lab)) <= {RAIL_RAISED, TERRAIN}
    mask = m.rail_mask(_image())
    expect = np.zeros((40, 60), bool)
    expect[10:, 20:22] = expect[10:, 40:42] = True
    assert np.array_equal(mask, expect)


def test_resize_and_small_output(tmp_path: Path) -> None:
    # model input resized to (20, 30); output at half that: labels come back at 40 x 60
    m = SegmentationModel(rust_rail_model(tmp_path / "d.onnx", downsample=2), input_size=(20, 30))
    lab = m.predict(_image())
    assert lab.shape == (40, 60)
    assert lab[30, 5] == TERRAIN


def test_normalisation_is_configurable(tmp_path: Path) -> None:
    path = rust_rail_model(tmp_path / "n.onnx", mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5))
    good = SegmentationModel(path, mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5))
    assert good.rail_mask(_image()).sum() == 2 * 2 * 30
    cfg = good.to_config()
    again = SegmentationModel.from_config(json.loads(json.dumps(cfg)))
    assert np.array_equal(again.rail_mask(_image()), good.rail_mask(_image()))


def test_bad_config(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        SegmentationModel(tmp_path / "missing.onnx")
    path = rust_rail_model(tmp_path / "m.onnx")
    with pytest.raises(ValueError):
        SegmentationModel(path, rail_classes=["no-such-class"])
    with pytest.raises(ValueError):
        SegmentationModel.from_config({"input_size": (10, 10)})


def test_rule_segments_synthetic_rails(tmp_path: Path) -> None:
    """On a synthetic frame the rule model finds the rails the renderer drew."""
    from geometry.camera import load_cameras
    from geometry.poses import PoseTrack
    from geometry.transforms import invert_T, pose_to_T
    from worker.osdar.sequence import Sequence
    from worker.synth.camera_sim import CameraSimulator
    from worker.synth.generator import SynthConfig, generate
    from worker.synth.scene_mesh import MATERIAL_ID
    from worker.synth.scenes import build_scene

    out = tmp_path / "switch"
    generate(out, SynthConfig(scene="switch", frames=3, scale=0.1, lidar_density=0.05, seed=5))
    seq = Sequence.open(out)
    meta = json.loads((out / "ground_truth/meta.json").read_text())
    poses = PoseTrack.from_csv(out / "ground_truth/poses.csv")
    T_world_scene = pose_to_T(
        meta["T_world_scene"]["translation"], meta["T_world_scene"]["quaternion"]
    )
    driven = 30.0 + meta["speed_mps"] * meta["frames"] * 0.1 * 1.1 + 1.0
    scene = build_scene(meta["scene"], seed=meta["seed"], length_m=driven)
    cams = load_cameras(seq.labels.raw, ["rgb_center"])
    sim = CameraSimulator(scene, cams, seed=meta["seed"])
    f = seq.frame_indices[1]
    t = seq.timestamps("rgb_center")[1]
    T_scene_base = invert_T(T_world_scene) @ poses.interpolate(np.array([t]))[0]
    truth = sim.render_labels("rgb_center", T_scene_base) == MATERIAL_ID["rail"]
    sim.close()
    img = seq.image(f, "rgb_center")
    model = SegmentationModel(rust_rail_model(tmp_path / "rule.onnx"))
    pred = model.rail_mask(img)
    # precision against the true rail pixels dilated by one pixel (anti-aliased edges)
    from scipy.ndimage import binary_dilation

    near = binary_dilation(truth, iterations=1)
    precision = (pred & near).sum() / max(pred.sum(), 1)
    recall = (pred & truth).sum() / max(truth.sum(), 1)
    assert pred.sum() > 50
    assert precision > 0.5, precision
    assert recall > 0.3, recall
