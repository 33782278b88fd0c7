"""The example campaigns in examples/ parse and expand."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from osdar_platform.catalog import BUILTIN_OBJECTS
from tests.campaign.scenes import platform, straight_prepared
from worker.augmentation.spec import AugmentSpec
from worker.campaign.expand import expand
from worker.campaign.spec import load_spec

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_the_papers_dataset_is_3_sequences_by_6_classes() -> None:
    spec = load_spec(EXAMPLES / "osdar_ar_paper.yaml")
    assert [s.label for s in spec.sequences] == [
        "3_fire_site_3.1", "5_station_bergedorf_5.1", "6_station_klein_flottbek_6.2"
    ]  # fmt: skip
    prepared = {s.key: straight_prepared() for s in spec.sequences}
    variants = expand(spec, prepared)
    assert len(variants) == 18
    per_sequence = Counter((v.sequence_label, v.objects[0].class_name) for v in variants)
    assert set(per_sequence.values()) == {1}
    assert {c for _, c in per_sequence} == set(BUILTIN_OBJECTS)
    for v in variants:
        r = v.objects[0].resolved
        assert r.zone in ("track", "crossing") and 30.0 <= r.distance_first_view_m <= 100.0
        crossing = v.objects[0].class_name == "fallen_tree" and v.sequence_label != (
            "5_station_bergedorf_5.1"
        )  # Bergedorf's platforms line the track: its tree lies along it (the yaml)
        assert (r.zone == "crossing") == crossing
        if v.objects[0].class_name == "fallen_tree" and not crossing:
            assert -20.0 <= r.yaw_deg <= 20.0 or 160.0 <= r.yaw_deg <= 200.0


def test_the_json_example_expands() -> None:
    spec = load_spec(EXAMPLES / "campaign_rules.json")
    prepared = {
        "out/station": straight_prepared(planes=[platform(40.0, 250.0, -1.75, -9.0)]),
        "out/fire_site": straight_prepared(),
    }
    variants = expand(spec, prepared)
    assert sum(len(v.objects) for v in variants) == spec.object_count()
    assert all(len(v.objects) <= 3 for v in variants)


def test_the_multi_object_example_groups_three_objects_with_walkers() -> None:
    spec = load_spec(EXAMPLES / "multi_object.yaml")
    prepared = {s.key: straight_prepared() for s in spec.sequences}
    variants = expand(spec, prepared)
    assert [len(v.objects) for v in variants] == [3, 3, 3, 3]
    moving = [o for v in variants for o in v.objects if o.motion is not None]
    assert sorted({o.class_name for o in moving}) == ["cow", "person"] and len(moving) == 6
    for v in variants:
        assert "objects" in v.job and all(
            ("motion" in j) == (o.motion is not None)
            for j, o in zip(v.job["objects"], v.objects, strict=True)
        )
        for o in v.objects:
            if o.motion is not None:
                speed = o.motion["speed_mps"]
                assert (1.0 <= speed <= 1.6) if o.class_name == "person" else (0.3 <= speed <= 0.8)


def test_the_campaigns_gauge_envelope_reaches_every_job() -> None:
    spec = load_spec(EXAMPLES / "campaign_rules.json").model_copy(deep=True)
    data = spec.model_dump(mode="json")
    data["job"]["gauge"] = {"margin_m": 0.35}
    spec = type(spec).model_validate(data)
    prepared = {
        "out/station": straight_prepared(planes=[platform(40.0, 250.0, -1.75, -9.0)]),
        "out/fire_site": straight_prepared(),
    }
    variants = expand(spec, prepared)
    assert variants and all(v.job["gauge"] == {"margin_m": 0.35} for v in variants)
    aug = AugmentSpec.from_job_spec(variants[0].job_spec())
    assert aug.gauge.margin_m == 0.35 and aug.gauge.half_width_m == 1.575


def test_the_render_cost_bench_makes_the_same_objects_together_and_apart() -> None:
    together = load_spec(EXAMPLES / "bench" / "three_objects_together.yaml")
    apart = load_spec(EXAMPLES / "bench" / "three_objects_apart.yaml")
    prepared = {"out/fire_site": straight_prepared()}
    (one,) = expand(together, prepared)
    three = expand(apart, prepared)
    assert [len(v.objects) for v in three] == [1, 1, 1]
    assert [o.resolved for o in one.objects] == [v.objects[0].resolved for v in three]
