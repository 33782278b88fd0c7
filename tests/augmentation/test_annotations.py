"""The built-in obstacle's provenance (seed, pose, variant) in the labels, read back with
raillabel: with the class they rebuild the same mesh."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from renderer.assets.obstacles import build_obstacle
from worker.augmentation.annotations import (
    BUILTIN_PROVENANCE,
    CameraView,
    FrameAnnotation,
    add_object,
    builtin_provenance,
)


def test_builtin_provenance_rebuilds_the_same_mesh() -> None:
    mesh = build_obstacle("person", seed=17, detail=0.5, pose="crouching")
    attrs = builtin_provenance(mesh.meta)
    assert attrs == {"osdarArSeed": "17", "osdarArPose": "crouching",
                     "osdarArVariant": mesh.meta["variant"]}  # fmt: skip
    again = build_obstacle("person", seed=int(attrs["osdarArSeed"]), detail=0.5,
                           pose=attrs["osdarArPose"])  # fmt: skip
    np.testing.assert_array_equal(again.vertices, mesh.vertices)
    other = build_obstacle("person", seed=18, detail=0.5, pose="crouching")
    assert builtin_provenance(other.meta)["osdarArSeed"] == "18"


def test_an_uploaded_meshs_pose_dict_is_left_out() -> None:
    assert builtin_provenance({"pose": {"yaw_deg": 30.0}, "name": "box"}) == {}
    assert builtin_provenance({"seed": 3, "pose": "standing", "variant": True}) == {
        "osdarArSeed": "3",
        "osdarArPose": "standing",
    }


def test_labels_carry_seed_pose_variant_raillabel_loads(tiny_sequence, tmp_path: Path) -> None:
    raillabel = pytest.importorskip("raillabel")
    from worker.osdar.labels import dump_labels, validate_openlabel

    folder = tiny_sequence()
    raw = json.loads(next(folder.glob("*_labels.json")).read_text())
    meta = build_obstacle("cow", seed=5, detail=0.4).meta
    box, outline = (8.0, 6.0, 2.0, 4.0), [7.0, 4.0, 9.0, 4.0, 9.0, 8.0, 7.0, 8.0]
    frames = [
        FrameAnnotation(
            f,
            [10.0, 0.0, 0.9, 0.0, 0.0, 0.0, 1.0, 2.4, 0.8, 1.4],
            {"rgb_center": CameraView(box, outline, 0.9, False, 12.5, 7)},
            [1, 2, 3],
        )
        for f in (12, 13)
    ]
    oid = add_object(raw, obj_class="cow", frames=frames, attributes=builtin_provenance(meta))
    out = dump_labels(raw, tmp_path / "provenance_labels.json")
    assert validate_openlabel(json.loads(out.read_text())) == []
    pointers = raw["openlabel"]["objects"][oid]["object_data_pointers"]
    for p in pointers.values():
        assert all(p["attribute_pointers"][n] == "text" for n in BUILTIN_PROVENANCE.values())
    want = {"osdarArSeed": "5", "osdarArPose": "standing", "osdarArVariant": meta["variant"]}
    seen = set()
    for f, frame in raillabel.load(out).frames.items():
        for ann in frame.annotations.values():
            if str(ann.object_id) != oid:
                continue
            assert {k: ann.attributes[k] for k in want} == want
            assert ann.attributes["osdarArClass"] == "cow"
            seen.add((f, type(ann).__name__))
    assert {k for _, k in seen} == {"Cuboid", "Seg3d", "Bbox", "Poly2d"} and len(seen) == 8
