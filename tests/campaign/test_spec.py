"""The campaign spec: parsing YAML and JSON, and the errors a bad spec gets."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from worker.campaign.spec import (
    CampaignSpec,
    ExplicitPlacement,
    PlacementRule,
    load_spec,
    parse_spec,
    spec_issues,
)

YAML = """
name: two_sequences
seed: 11
sequences:
  - path: data/synth/station
  - id: 3f2a9c51
    frame_range: [0, 49]
obstacles:
  - builtin: person
    seeds: [0, 1, 2]
  - asset_id: a81b3c
    scale: 0.5
placements:
  - zone: crossing
    distance_m: [30, 100]
  - zone: platform
    side: right
    yaw_deg: [-20, 20]
    sequences: [station]
  - explicit: {mode: track, s: 45, offset: 0.0, yaw_deg: 90}
draws: 2
objects_per_sequence: 2
"""


def _errors(text: str) -> str:
    with pytest.raises(ValidationError) as err:
        parse_spec(text)
    return str(err.value)


def test_yaml_and_json_give_the_same_spec(tmp_path) -> None:
    spec = parse_spec(YAML)
    as_json = tmp_path / "c.json"
    as_json.write_text(json.dumps(spec.model_dump(mode="json")))
    assert load_spec(as_json) == spec
    as_yaml = tmp_path / "c.yaml"
    as_yaml.write_text(YAML)
    assert load_spec(as_yaml) == spec
    assert isinstance(spec.placements[0], PlacementRule)
    assert isinstance(spec.placements[2], ExplicitPlacement)
    assert spec.placements[1].yaw_ranges == [(-20.0, 20.0)]  # one pair becomes a list
    assert spec.placements[0].yaw_ranges == [(60.0, 120.0), (240.0, 300.0)]  # crossing
    assert spec.sequences[0].label == "station" and spec.sequences[1].key == "3f2a9c51"


def test_object_count_follows_the_product() -> None:
    spec = parse_spec(YAML)
    # station: (crossing 2 draws + platform 2 draws + explicit once) x 4 obstacles
    # 3f2a9c51: (crossing 2 draws + explicit once) x 4 obstacles
    assert spec.object_count() == 5 * 4 + 3 * 4


def test_obstacle_reuses_the_job_object_spec() -> None:
    spec = parse_spec(YAML)
    person, asset = spec.obstacles
    assert person.variation_seeds == [0, 1, 2] and asset.variation_seeds == [0]
    assert person.job_object(0) == {"builtin": "person", "scale": 1.0}
    assert person.job_object(2) == {"builtin": "person", "scale": 1.0, "seed": 2}
    assert asset.job_object(0) == {"asset_id": "a81b3c", "scale": 0.5}


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ("obstacles: [{builtin: dragon}]", "'person', 'rock', 'fallen_tree', 'cow'"),
        ("obstacles: [{builtin: rock, asset_id: x}]", "exactly one of 'builtin' and 'asset_id'"),
        ("obstacles: [{asset_id: x, seeds: [1]}]", "'seeds' vary built-in obstacles only"),
        ("obstacles: [{builtin: rock, seeds: [1, 1]}]", "seeds must not repeat"),
        ("placements: [{zone: moon}]", "'track', 'gauge_edge', 'beside', 'platform'"),
        ("placements: [{zone: track, distance_m: [100, 30]}]", "low <= high"),
        ("placements: [{zone: track, lateral_m: [-80, 0]}]", "within [-50, 50]"),
        ("placements: [{zone: track, sequences: [nowhere]}]", "name no sequence"),
        ("placements: [{explicit: {mode: track, s: -3}}]", "greater than or equal to 0"),
        ("placements: [{explicit: {mode: lidar_frame, xyz: [1, 2, 0]}}]", "needs 'frame_idx'"),
        ("placements: [{zone: track, bogus: 1}]", "Extra inputs are not permitted"),
        ("objects_per_sequence: 0", "greater than or equal to 1"),
    ],
)
def test_bad_specs_say_what_is_wrong(change: str, needle: str) -> None:
    base = "name: t\nsequences: [{path: a}]\nobstacles: [{builtin: rock}]\n"
    key = change.split(":", 1)[0]
    text = "\n".join(line for line in base.splitlines() if not line.startswith(key))
    assert needle in _errors(text + "\n" + change)


@pytest.mark.parametrize(
    ("sequences", "needle"),
    [
        ("[{path: a}, {path: a}]", "must not repeat"),
        ("[{path: a, id: b}]", "exactly one of 'id' and 'path'"),
        ("[{path: a, frame_range: [9, 3]}]", "first <= last"),
        ("[]", "at least 1 item"),
    ],
)
def test_bad_sequences(sequences: str, needle: str) -> None:
    assert needle in _errors(f"name: t\nsequences: {sequences}\nobstacles: [{{builtin: rock}}]")


def test_a_spec_is_a_mapping() -> None:
    with pytest.raises(ValueError, match="is a mapping"):
        parse_spec("- just\n- a list\n")


def test_too_many_variants_is_an_error() -> None:
    seeds = list(range(1000))
    spec = {"name": "big", "sequences": [{"path": "a"}],
            "obstacles": [{"builtin": "rock", "seeds": seeds}], "draws": 11}  # fmt: skip
    with pytest.raises(ValidationError, match="more than 10000 variants"):
        CampaignSpec.model_validate(spec)


def test_placements_filter_obstacles() -> None:
    spec = parse_spec(
        "name: t\nsequences: [{path: a}]\n"
        "obstacles: [{builtin: person, seeds: [0, 1]}, {builtin: fallen_tree}, {asset_id: x9}]\n"
        "placements: [{zone: track, obstacles: [person, x9]}, {zone: crossing, "
        "obstacles: [fallen_tree]}]\ndraws: 2\n"
    )
    assert spec.object_count() == 2 * (2 + 1) + 2 * 1
    assert "name no obstacle of the campaign" in _errors(
        "name: t\nsequences: [{path: a}]\nobstacles: [{builtin: rock}]\n"
        "placements: [{zone: track, obstacles: [cow]}]"
    )


def test_spec_issues_name_the_field() -> None:
    spec, issues = spec_issues(
        {"name": "t", "sequences": [{"path": "a"}],
         "obstacles": [{"builtin": "dragon"}, {"builtin": "rock"}],
         "placements": [{"zone": "track"}, {"zone": "moon"},
                        {"explicit": {"mode": "track", "s": -1}}]}
    )  # fmt: skip
    assert spec is None
    where = {i.where: i.message for i in issues}
    assert "'person', 'rock'" in where["obstacles[0].builtin"]
    assert "'track', 'gauge_edge'" in where["placements[1].zone"]
    assert "greater than or equal to 0" in where["placements[2].explicit.track.s"]
    assert all(i.level == "error" for i in issues)
    ok, none = spec_issues({"name": "t", "sequences": [{"path": "a"}],
                            "obstacles": [{"builtin": "rock"}]})  # fmt: skip
    assert ok is not None and none == []
