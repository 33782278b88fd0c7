"""Gauge labels: the clearance envelope's geometry on known cases, and the attributes
the annotations carry (read back with raillabel)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from worker.augmentation.annotations import (
    GAUGE_INTRUSION_ATTRIBUTE,
    GAUGE_LATERAL_ATTRIBUTE,
    TRACK_DISTANCE_ATTRIBUTE,
    VISIBLE_PIXELS_ATTRIBUTE,
    CameraView,
    FrameAnnotation,
    add_object,
)
from worker.augmentation.gauge import (
    GaugeLabel,
    GaugeOutline,
    gauge_labels,
    measure_against_envelope,
    smoothed_curvature,
    track_coordinates,
)
from worker.preparation.centreline import RAIL_HEAD_SPACING, Centreline

W = GaugeOutline().edge_m  # 1.575 + 0.2 on straight track


def _straight(length: float = 100.0) -> Centreline:
    xs = np.linspace(0.0, length, 11)
    return Centreline(np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)]), ego=True)


def _left_curve(radius: float, roll: float = 0.0, length: float = 120.0) -> Centreline:
    """A circle turning left from the origin heading east, constant roll."""
    a = np.linspace(0.0, length / radius, 61)
    pts = np.column_stack([radius * np.sin(a), radius * (1.0 - np.cos(a)), np.zeros_like(a)])
    return Centreline(pts, roll=np.full(len(a), roll), ego=True)


def _box(x: float, y: tuple[float, float], z: tuple[float, float] = (0.0, 1.8)) -> np.ndarray:
    """(8, 3) corners of a box 0.6 m long centred at x (straight track along x)."""
    return np.array([[xx, yy, zz] for xx in (x - 0.3, x + 0.3) for yy in y for zz in z])


def _at(ego: Centreline, s: float, lateral: float, height: float) -> np.ndarray:
    """(1, 3) world point at arc length s, horizontal offset ``lateral`` (left +), height
    above the centreline (vertical)."""
    c, t = ego.point([s])[0], ego.tangent([s])[0]
    left = np.array([-t[1], t[0], 0.0]) / np.hypot(t[0], t[1])
    return (c + lateral * left + np.array([0.0, 0.0, height]))[None]


@pytest.mark.parametrize(
    ("y", "z", "inside", "lateral"),
    [
        ((-0.3, 0.3), (0.0, 1.8), True, -W),  # on the centreline: the half-width inside
        ((2.7, 3.3), (0.0, 1.8), False, 2.7 - W),  # 3 m to the side: outside
        ((-3.3, -2.7), (0.0, 1.8), False, 2.7 - W),  # and on the right
        ((1.5, 2.1), (0.0, 1.8), True, 1.5 - W),  # across the envelope's side
        ((-0.3, 0.3), (-0.2, -0.05), False, -W),  # flat between the rails, below their top
        ((-0.3, 0.3), (4.8, 5.5), False, -W),  # above the envelope (a bridge, a wire)
    ],
)
def test_envelope_on_straight_track(y, z, inside: bool, lateral: float) -> None:
    m = measure_against_envelope(_straight(), _box(50.0, y, z))
    assert m.inside is inside
    assert m.lateral_distance_m == pytest.approx(lateral, abs=1e-9)
    assert m.s_range == pytest.approx((49.7, 50.3))


def test_track_distance_follows_the_train_and_intrusion_is_ahead_only() -> None:
    ego = _straight()
    poses = {}
    for f, x in enumerate((10.0, 30.0, 49.9, 60.0)):
        T = np.eye(4)
        T[0, 3] = x
        poses[f] = T
    labels = gauge_labels(ego, _box(50.0, (-0.3, 0.3)), poses)
    assert [round(g.track_distance_m, 6) for g in labels.values()] == [39.7, 19.7, 0.0, -9.7]
    assert [g.intrusion for g in labels.values()] == [True, True, True, False]
    assert gauge_labels(None, _box(50.0, (-0.3, 0.3)), poses) == {}


def test_track_coordinates_extrapolate_beyond_the_ends() -> None:
    ego = _straight(100.0)
    syz = track_coordinates(ego, np.array([[105.0, 1.0, 2.0], [-4.0, -1.0, 0.5], [50, 0, 0]]))
    assert syz == pytest.approx(np.array([[105.0, 1.0, 2.0], [-4.0, -1.0, 0.5], [50, 0, 0]]))


def test_the_envelope_tilts_with_the_cant() -> None:
    """A left curve, the right (outer) rail 150 mm higher: the track and its envelope lean
    to the left, so its top moves ~0.4 m left at 4 m: a point 2 m left at 4 m height comes
    inside, one 2 m right at that height stays out, and without cant the left one is out."""
    roll = -math.asin(0.150 / RAIL_HEAD_SPACING)
    canted, level = _left_curve(300.0, roll), _left_curve(300.0, 0.0)
    high_left, high_right = _at(canted, 60.0, 2.0, 4.0), _at(canted, 60.0, -2.0, 4.0)
    assert measure_against_envelope(canted, high_left).inside
    assert not measure_against_envelope(canted, high_right).inside
    assert not measure_against_envelope(level, _at(level, 60.0, 2.0, 4.0)).inside
    y = track_coordinates(canted, high_left)[0, 1]
    assert y == pytest.approx(2.0 * math.cos(roll) + 4.0 * math.sin(roll), abs=1e-3)
    # at rail height the cant hardly matters: 1.7 m is inside on both tracks
    assert measure_against_envelope(canted, _at(canted, 60.0, 1.7, 0.1)).inside
    assert measure_against_envelope(level, _at(level, 60.0, 1.7, 0.1)).inside


def test_curves_widen_the_envelope() -> None:
    curve = _left_curve(100.0)
    assert smoothed_curvature(curve, [60.0])[0] == pytest.approx(0.01, rel=1e-3)
    widened = W + GaugeOutline().curve_widening_m2 / 100.0  # 1.8 m
    assert measure_against_envelope(curve, _at(curve, 60.0, widened - 0.01, 1.0)).inside
    assert not measure_against_envelope(_straight(), _box(50.0, (W + 0.015, W + 0.02))).inside
    no_widening = GaugeOutline(curve_widening_m2=0.0)
    p = _at(curve, 60.0, widened - 0.01, 1.0)
    assert not measure_against_envelope(curve, p, no_widening).inside


def test_outline_is_configurable() -> None:
    wide = GaugeOutline(half_width_m=2.0, margin_m=0.5)
    m = measure_against_envelope(_straight(), _box(50.0, (2.3, 2.9)), wide)
    assert m.inside and m.lateral_distance_m == pytest.approx(2.3 - 2.5)
    assert not measure_against_envelope(_straight(), _box(50.0, (2.3, 2.9))).inside
    with pytest.raises(ValueError):
        GaugeOutline(half_width_m=-1.0)


def test_labels_carry_gauge_attributes_raillabel_loads(tiny_sequence, tmp_path: Path) -> None:
    raillabel = pytest.importorskip("raillabel")
    from worker.osdar.labels import dump_labels, validate_openlabel

    folder = tiny_sequence()
    labels_path = next(folder.glob("*_labels.json"))
    raw = json.loads(labels_path.read_text())
    gauges = {12: GaugeLabel(True, -1.2, 40.5), 13: GaugeLabel(True, -1.2, 39.5),
              14: GaugeLabel(False, -1.2, -0.4)}  # fmt: skip
    box, outline = (8.0, 6.0, 2.0, 4.0), [7.0, 4.0, 9.0, 4.0, 9.0, 8.0, 7.0, 8.0]
    frames = [
        FrameAnnotation(
            f,
            [10.0, 0.0, 0.9, 0.0, 0.0, 0.0, 1.0, 0.5, 0.6, 1.8],
            {"rgb_center": CameraView(box, outline, 0.9, False, 12.5, 7 + f)},
            [1, 2, 3],
            gauges[f],
        )
        for f in (12, 13, 14)
    ]
    oid = add_object(raw, obj_class="person", frames=frames)
    out = dump_labels(raw, tmp_path / "gauge_labels.json")
    assert validate_openlabel(json.loads(out.read_text())) == []
    pointers = raw["openlabel"]["objects"][oid]["object_data_pointers"]
    kinds = pointers["rgb_center__bbox__person"]["attribute_pointers"]
    assert kinds[GAUGE_INTRUSION_ATTRIBUTE] == "boolean"
    assert kinds[VISIBLE_PIXELS_ATTRIBUTE] == kinds[TRACK_DISTANCE_ATTRIBUTE] == "num"
    scene = raillabel.load(out)
    seen = set()
    for f, frame in scene.frames.items():
        for ann in frame.annotations.values():
            if ann.object_id != oid and str(ann.object_id) != oid:
                continue
            a = ann.attributes
            assert a[GAUGE_INTRUSION_ATTRIBUTE] is gauges[f].intrusion
            assert a[GAUGE_LATERAL_ATTRIBUTE] == pytest.approx(-1.2)
            assert a[TRACK_DISTANCE_ATTRIBUTE] == pytest.approx(gauges[f].track_distance_m)
            if type(ann).__name__ in ("Bbox", "Poly2d"):
                assert a[VISIBLE_PIXELS_ATTRIBUTE] == 7 + f
            seen.add((f, type(ann).__name__))
    # raillabel calls the vec of lidar point indices Seg3d
    assert {k for _, k in seen} == {"Cuboid", "Seg3d", "Bbox", "Poly2d"} and len(seen) == 12


@pytest.mark.gl
def test_an_augmentation_writes_gauge_labels(tmp_path: Path) -> None:
    """End to end on a tiny synthetic sequence with its true track: a person on the
    centreline 22 m ahead intrudes in every frame, at the distance the poses say."""
    raillabel = pytest.importorskip("raillabel")
    from worker.augmentation.finish import finish_augmentation
    from worker.augmentation.frame import augment_frames
    from worker.augmentation.plan import plan_augmentation
    from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel
    from worker.evaluation.object_error import truth_prepared
    from worker.synth.generator import SynthConfig, generate

    seq = tmp_path / "fire_gauge"
    generate(seq, SynthConfig(scene="fire_site", frames=3, scale=0.1, lidar_density=0.1, seed=3))
    truth = truth_prepared(seq)
    spec = AugmentSpec(
        object=ObjectSource(builtin="person"),
        placement=PlacementModel.parse("s=22,offset=0,yaw=90"),
        cameras=("rgb_center",),
    )
    plan = plan_augmentation(seq, spec, truth)
    assert sorted(plan.gauge) == plan.frames
    s_obj = truth.ego.project(plan.T_world_obj[None, :3, 3]).s[0]
    for f, g in plan.gauge.items():
        T = plan.T_world_base[plan.lidar_stream][f]
        s_train = truth.ego.project(T[None, :3, 3]).s[0]
        assert g.intrusion and g.lateral_distance_m == pytest.approx(-W, abs=0.01)
        assert g.track_distance_m == pytest.approx(s_obj - s_train, abs=0.4)  # nearest part
    chunk = augment_frames(plan, plan.frames, tmp_path / "scratch")
    metrics = finish_augmentation(plan, [chunk], tmp_path / "fire_gauge_out")
    assert metrics["gauge"]["intrusion_frames"] == metrics["frames"]["annotated"] > 0
    scene = raillabel.load(next((tmp_path / "fire_gauge_out").glob("*_labels.json")))
    anns = [a for fr in scene.frames.values() for a in fr.annotations.values()]
    bboxes = [a for a in anns if type(a).__name__ == "Bbox" and "visiblePixels" in a.attributes]
    assert bboxes and all(a.attributes[GAUGE_INTRUSION_ATTRIBUTE] is True for a in bboxes)
    assert all(a.attributes[VISIBLE_PIXELS_ATTRIBUTE] > 0 for a in bboxes)
