"""The object's errors against the true poses, measured where each frame is augmented
(the chunks, in parallel) and only summed up by the finish: the same figures as one
measurement of every frame in the finish, with no render left for the finish to do."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from geometry.poses import PoseTrack
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.records import dump_chunk, load_chunk
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel
from worker.evaluation import object_error
from worker.evaluation.object_error import evaluate_object, measure_chunk, truth_prepared

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("objerr") / "fire_err"
    generate(folder, SynthConfig(scene="fire_site", frames=6, scale=0.15,
                                 lidar_density=0.2, seed=5))  # fmt: skip
    return folder


def _off_truth(seq: Path):
    """The ground truth with every pose 6 cm to the left and 0.05 deg of yaw off: a
    preparation whose object errors are known to be well above zero."""
    truth = truth_prepared(seq)
    c, s = np.cos(np.radians(0.05)), np.sin(np.radians(0.05))
    D = np.array([[c, -s, 0, 0], [s, c, 0, 0.06], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    track = PoseTrack(truth.track.timestamps, truth.track.T @ D, truth.track.frame_idx)
    return dataclasses.replace(truth, track=track)


def test_chunks_measure_what_the_finish_would(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spec = AugmentSpec(
        object=ObjectSource(builtin="rock"),
        placement=PlacementModel.parse("s=20,offset=0.5,yaw=30"),
        lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"),
    )
    plan = plan_augmentation(seq, spec, _off_truth(seq))
    frames = list(plan.frames)
    chunks = []
    for i, part in enumerate((frames[:2], frames[2:])):
        ch = augment_frames(plan, part, tmp_path / f"chunk{i}")
        measure_chunk(plan, ch)
        assert sorted(ch.object_errors) == part
        ch = load_chunk(dump_chunk(ch))  # as the finish gets it: from the store
        assert sorted(ch.object_errors) == part  # frame numbers stay ints
        chunks.append(ch)
    records = [r for ch in chunks for r in ch.frames]
    reference = evaluate_object(plan, records)  # every frame rendered here

    def no_render(*args: object, **kwargs: object) -> None:
        raise AssertionError("the finish rendered a frame the chunks had measured")

    monkeypatch.setattr(object_error, "frame_object_errors", no_render)
    metrics = finish_augmentation(plan, chunks, tmp_path / "fire_err_rock")
    got = metrics["object_errors"]
    assert got["true_object_xyz"] == pytest.approx(reference["true_object_xyz"], abs=1e-12)
    for cam, ref in reference["cameras"].items():
        assert ref["frames"] == len(frames)
        # 6 cm and 0.05 deg of pose error: whole pixels at 20 m, not a rounding error
        assert ref["anchor_px_mean"] > 0.3, (cam, ref)
        for k, v in ref.items():
            assert got["cameras"][cam][k] == pytest.approx(v, rel=1e-12, abs=1e-12), (cam, k)


def test_frames_a_chunk_lacks_are_measured_by_the_finish(seq: Path, tmp_path: Path) -> None:
    spec = AugmentSpec(
        object=ObjectSource(builtin="rock"),
        placement=PlacementModel.parse("s=20,offset=0.5,yaw=30"),
        lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"),
    )
    plan = plan_augmentation(seq, spec, _off_truth(seq))
    measured = augment_frames(plan, plan.frames[:3], tmp_path / "a")
    measure_chunk(plan, measured)
    unmeasured = augment_frames(plan, plan.frames[3:], tmp_path / "b")
    reference = evaluate_object(plan, measured.frames + unmeasured.frames)
    got = finish_augmentation(plan, [measured, unmeasured], tmp_path / "out")["object_errors"]
    for cam, ref in reference["cameras"].items():
        assert got["cameras"][cam] == pytest.approx(ref, rel=1e-12, abs=1e-12)
