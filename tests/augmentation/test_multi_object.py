"""Several objects in one augmented sequence: each annotated, hiding each other right.

Ground truth by construction: the same two objects are also augmented ALONE (same
sequence, same true poses, same placements). Where both alone-renders cover a pixel, the
near one must win in the two-object run: the far object's mask is its alone mask minus
the near object's, in both cameras; in the lidar, a ray that meets both objects lands on
the near one, so the far object keeps exactly its alone points minus the near object's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.spec import (
    AugmentSpec,
    ObjectSource,
    PlacementModel,
    RenderSpec,
    SceneObject,
)
from worker.evaluation.object_error import truth_prepared
from worker.osdar.pcd import read_pcd

pytestmark = pytest.mark.gl

NO_LIDAR_NOISE = RenderSpec(lidar_noise=False)
SEQ = {"scene": "fire_site", "frames": 4, "scale": 0.15, "lidar_density": 0.35, "seed": 5}
# a person on the track in front of a horse standing across it, 8 m behind
NEAR = SceneObject(object=ObjectSource(builtin="person"),
                   placement=PlacementModel.parse("s=22,offset=0.1,yaw=0"))  # fmt: skip
FAR = SceneObject(object=ObjectSource(builtin="horse"),
                  placement=PlacementModel.parse("s=30,offset=0,yaw=90"))  # fmt: skip


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory):
    from worker.synth.generator import SynthConfig, generate

    base = tmp_path_factory.mktemp("multi")
    seq = base / "fire_multi"
    generate(seq, SynthConfig(**SEQ))
    truth = truth_prepared(seq)
    origins = str(seq / "ground_truth" / "lidar_origins.json")
    out = {}
    for name, objects in {"both": (NEAR, FAR), "near": (NEAR,), "far": (FAR,)}.items():
        # lidar noise off: the tests below check where exact rays land (noise: test_frame.py)
        spec = AugmentSpec(objects=objects, lidar_origins=origins, render=NO_LIDAR_NOISE)
        plan = plan_augmentation(seq, spec, truth)
        chunk = augment_frames(plan, plan.frames, base / f"scratch_{name}")
        out[name] = (plan, chunk)
    return seq, base, out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return 1.0 if u == 0 else float(np.logical_and(a, b).sum() / u)


def test_the_far_objects_mask_is_cut_where_the_near_one_is(runs) -> None:
    _, _, out = runs
    plan, both = out["both"]
    _, near = out["near"]
    _, far = out["far"]
    overlap_px = dict.fromkeys(plan.cameras, 0)
    for rb, rn, rf in zip(both.frames, near.frames, far.frames, strict=True):
        for name, cam in plan.cameras.items():
            shape = (cam.height, cam.width)
            near_alone = rn.objects[0].cameras[name].mask(shape)
            far_alone = rf.objects[0].cameras[name].mask(shape)
            near_both = rb.objects[0].cameras[name].mask(shape)
            far_both = rb.objects[1].cameras[name].mask(shape)
            overlap_px[name] += int(np.logical_and(near_alone, far_alone).sum())
            # one depth test: no pixel is more than half covered by both (up to a pixel
            # where the two renders' supersampling grids differ along the near one's edge)
            assert int((near_both & far_both).sum()) <= 2, (rb.frame_idx, name)
            assert _iou(near_both, near_alone) > 0.99, (rb.frame_idx, name)
            expected_far = far_alone & ~near_alone
            assert _iou(far_both, expected_far) > 0.95, (rb.frame_idx, name)
            assert rb.objects[1].cameras[name].visible_fraction < rf.objects[0].cameras[
                name].visible_fraction + 1e-6  # fmt: skip
    # the scene really puts the person in front of the horse in both cameras
    assert all(v > 50 for v in overlap_px.values()), overlap_px


def test_lidar_rays_that_meet_both_land_on_the_near_object(runs) -> None:
    _, base, out = runs
    plan, both = out["both"]
    _, near = out["near"]
    _, far = out["far"]
    shared = 0
    for rb, rn, rf in zip(both.frames, near.frames, far.frames, strict=True):
        n_alone = set(rn.objects[0].annotation.lidar_indices)
        f_alone = set(rf.objects[0].annotation.lidar_indices)
        n_both = set(rb.objects[0].annotation.lidar_indices)
        f_both = set(rb.objects[1].annotation.lidar_indices)
        shared += len(n_alone & f_alone)
        assert n_both == n_alone and f_both == f_alone - n_alone, rb.frame_idx
        uri = plan.uris[rb.frame_idx]["lidar"].lstrip("/")
        c_both = read_pcd(base / "scratch_both" / uri)
        c_near = read_pcd(base / "scratch_near" / uri)
        idx = np.array(sorted(n_both), dtype=np.int64)
        for k in "xyz":  # the shared rays end on the near object's surface, as alone (the
            # one-scene cast is in the base frame, the alone cast in the object's: float32)
            assert np.allclose(c_both.fields[k][idx], c_near.fields[k][idx], atol=1e-4, rtol=0)
    assert shared > 5, shared


def test_each_object_is_its_own_annotated_object(runs, tmp_path: Path) -> None:
    raillabel = pytest.importorskip("raillabel")
    _, _, out = runs
    plan, chunk = out["both"]
    metrics = finish_augmentation(plan, [chunk], tmp_path / "fire_multi_out", evaluate=False)
    uuids = [o["uuid"] for o in metrics["objects"]]
    assert len(set(uuids)) == 2 and None not in uuids
    assert [o["class"] for o in metrics["objects"]] == ["person", "horse"]
    labels = next((tmp_path / "fire_multi_out").glob("*_labels.json"))
    scene = raillabel.load(labels)
    names = {str(k): o.name for k, o in scene.objects.items()}
    assert [names[u] for u in uuids] == ["person_synthetic_0001", "horse_synthetic_0002"]
    speeds = {(str(a.object_id), type(a).__name__): a.attributes.get("velocity")
              for fr in scene.frames.values() for a in fr.annotations.values()}  # fmt: skip
    assert {k[0] for k in speeds} == set(uuids) and ("Seg3d" in {k[1] for k in speeds})
    assert all(v == [0.0, 0.0, 0.0] for (_, kind), v in speeds.items() if kind == "Cuboid")
    raw = json.loads(labels.read_text())["openlabel"]
    f0 = str(plan.frames[0])
    track_m = []
    for u in uuids:
        cub = raw["frames"][f0]["objects"][u]["object_data"]["cuboid"][0]
        vec = {a["name"]: a["val"] for a in cub["attributes"]["vec"]}
        assert vec["velocity"] == [0.0, 0.0, 0.0]  # static objects
        flags = {a["name"]: a["val"] for a in cub["attributes"]["boolean"]}
        nums = {a["name"]: a["val"] for a in cub["attributes"]["num"]}
        assert flags["gaugeIntrusion"] is True  # both stand on the track
        track_m.append(nums["trackDistanceM"])
    # each object's own gauge label: the horse (across the track, 30 m) is ~8 m farther
    # along the track than the person (22 m), less the two bodies' half-lengths
    assert 6.5 < track_m[1] - track_m[0] < 8.0, track_m


def test_old_single_object_specs_still_parse() -> None:
    old = {"object": {"builtin": "cow"}, "placement": {"mode": "track", "s": 30}}
    spec = AugmentSpec.from_job_spec(old)
    assert [o.object.builtin for o in spec.scene_objects] == ["cow"]
    assert spec.object is not None and spec.placement.s == 30
    many = AugmentSpec.from_job_spec({"objects": [old, {"object": {"builtin": "rock"},
                                                        "placement": {"s": 40}}]})  # fmt: skip
    assert [o.object.builtin for o in many.scene_objects] == ["cow", "rock"]
    with pytest.raises(ValueError, match="exactly one of"):
        AugmentSpec(object=ObjectSource(builtin="rock"), objects=(NEAR,))
    with pytest.raises(ValueError, match="objects\\[1\\]: object needs"):
        AugmentSpec.from_job_spec({"objects": [old, {"placement": {"s": 40}}]})


def test_the_job_spec_sets_the_gauge_envelope() -> None:
    spec = AugmentSpec.from_job_spec(
        {"object": {"builtin": "rock"}, "gauge": {"margin_m": 0.3, "height_m": 5.0}}
    )
    assert spec.gauge.edge_m == pytest.approx(1.575 + 0.3) and spec.gauge.height_m == 5.0
    with pytest.raises(ValueError, match="margin_m"):
        AugmentSpec.from_job_spec({"object": {"builtin": "rock"}, "gauge": {"margin_m": -1}})


def test_a_list_of_one_object_is_the_single_object_form() -> None:
    """One spelling per job: readers of ``object`` / ``placement`` (the evaluation) see the
    object whichever form the job used."""
    one = AugmentSpec(objects=(FAR,))
    assert one.objects == () and one.object == FAR.object and one.placement == FAR.placement
    assert (
        AugmentSpec.from_job_spec(
            {"objects": [{"object": {"builtin": "horse"}, "placement": {"s": 30, "yaw_deg": 90}}]}
        ).placement.s
        == 30
    )
