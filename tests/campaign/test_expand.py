"""The expansion on hand-made preparations: determinism, validation, the rules' geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.schemas import JobCreate
from tests.campaign.scenes import FIRST_X, LENGTH, platform, pole, straight_prepared
from worker.campaign.expand import expand, expand_with_issues, validate
from worker.campaign.placement import BESIDE_WIDTH_M, Footprint, Placed
from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import CampaignError, dump_variants

KEY = "seq/straight"


def _spec(**kw: object) -> CampaignSpec:
    base: dict = {
        "name": "t",
        "seed": 5,
        "sequences": [{"path": KEY}],
        "obstacles": [{"builtin": "person", "seeds": [0, 1]}, {"builtin": "cow"}],
        "placements": [{"zone": "track", "distance_m": [30, 100]}],
    }
    return CampaignSpec.model_validate({**base, **kw})


def _messages(spec: CampaignSpec, prepared: object) -> list[str]:
    return [f"{i.level}: {i.message}" for i in validate(spec, {KEY: prepared})]


@pytest.fixture(scope="module")
def straight():
    return straight_prepared(
        planes=[platform(150.0, 260.0, -1.75, -8.0)], poles=[pole("p0", 90.0, 2.4)]
    )


def test_same_spec_same_bytes_other_seed_other_positions(straight) -> None:
    spec = _spec(draws=3, placements=[{"zone": "track", "distance_m": [30, 100]},
                                      {"zone": "beside", "distance_m": [30, 100]}])  # fmt: skip
    a = dump_variants(expand(spec, {KEY: straight}))
    b = dump_variants(expand(spec, {KEY: straight}))
    assert a == b
    other = dump_variants(expand(spec.model_copy(update={"seed": 6}), {KEY: straight}))
    assert other != a
    assert len(expand(spec, {KEY: straight})) == 2 * 3 * 3  # placements x draws x obstacles


def test_variants_are_todays_job_specs(straight) -> None:
    variants = expand(_spec(), {KEY: straight})
    assert [v.id for v in variants] == ["v0000", "v0001", "v0002"]
    assert len({v.key for v in variants}) == 3
    for v in variants:
        (obj,) = v.objects
        job = v.job_spec("3f2a9c51")
        if obj.variation_seed == 0:  # seeds other than 0 need the service's ObjectSpec.seed
            assert JobCreate.model_validate(job).placement.mode == "track"
        assert job["placement"] == {"mode": "track", "s": obj.resolved.s_job_m,
                                    "offset": obj.resolved.offset_m,
                                    "yaw_deg": obj.resolved.yaw_deg}  # fmt: skip
        assert job["object"]["builtin"] == obj.class_name


def test_rules_hold_on_a_straight_track(straight) -> None:
    spec = _spec(
        draws=4,
        placements=[{"zone": z, "distance_m": [30, 100]} for z in
                    ("track", "gauge_edge", "beside", "crossing")]
        + [{"zone": "platform", "distance_m": [135, 200], "side": "right"}],
        constraints={"clearance_m": 0.1},
    )  # fmt: skip
    variants = expand(spec, {KEY: straight})
    assert len(variants) == 5 * 4 * 3
    W, B = 1.775, 1.6
    for v in variants:
        (o,) = v.objects
        r = o.resolved
        d_lo, d_hi = spec.placements[o.placement_index].distance_m
        # straight and level, the train at FIRST_X at frame 0: in view from the start
        assert r.first_view_frame == 0
        assert d_lo <= r.distance_first_view_m <= d_hi
        assert r.distance_first_view_m == pytest.approx(r.s_m - FIRST_X, abs=2e-3)
        assert r.xyz_world[0] == pytest.approx(r.s_m) and r.xyz_world[1] == pytest.approx(
            r.offset_m
        )
        length, width = r.footprint_m
        fp = Footprint((-length / 2, length / 2), (-width / 2, width / 2), 1.0)
        lo, hi = Placed(fp, r.s_m, r.offset_m, math.radians(r.yaw_deg)).lateral_range()
        if r.zone == "track":
            assert -W <= lo and hi <= W and abs(r.offset_m) <= B
        elif r.zone == "crossing":
            assert lo < 0 < hi and abs(r.offset_m) <= B
            assert any(a <= r.yaw_deg % 360 <= b for a, b in ((60, 120), (240, 300)))
        elif r.zone == "gauge_edge":
            assert (lo < W < hi and lo > 0) or (lo < -W < hi and hi < 0)
        elif r.zone == "beside":
            assert lo >= W + 0.1 - 1e-3 or hi <= -W - 0.1 + 1e-3
            assert abs(r.offset_m) <= W + BESIDE_WIDTH_M
        else:  # platform: inside it, clear of its edge
            assert r.zone == "platform" and 150.0 <= r.s_m <= 260.0
            assert -8.0 + 0.1 - 1e-3 <= lo and hi <= -1.75 - 0.1 + 1e-3
        # never across the bed's edge from the ground, never in the pole
        if abs(r.offset_m) > B:
            assert lo >= B + 0.1 - 1e-3 or hi <= -B - 0.1 + 1e-3
        p = Placed(fp, r.s_m, r.offset_m, math.radians(r.yaw_deg))
        assert p.distance_to_point(np.array([90.0, 2.4])) >= 0.15 + 0.1 - 1e-6


def test_several_objects_keep_their_spacing(straight) -> None:
    spec = _spec(
        obstacles=[{"builtin": "rock", "seeds": list(range(12))}],
        objects_per_sequence=4,
        constraints={"min_spacing_m": 3.0},
        placements=[{"zone": "track", "distance_m": [30, 60]}],
    )
    variants = expand(spec, {KEY: straight})
    assert [len(v.objects) for v in variants] == [4, 4, 4]
    for v in variants:
        assert "objects" in v.job and "object" not in v.job and len(v.job["objects"]) == 4
        spots = []
        for o in v.objects:
            length, width = o.resolved.footprint_m
            fp = Footprint((-length / 2, length / 2), (-width / 2, width / 2), 1.0)
            spots.append(Placed(fp, o.resolved.s_m, o.resolved.offset_m,
                                math.radians(o.resolved.yaw_deg)))  # fmt: skip
        for i in range(4):
            for j in range(i):
                assert spots[i].distance_to(spots[j]) >= 3.0 - 1e-6


def test_explicit_placements_resolve_and_keep_their_form(straight) -> None:
    spec = _spec(placements=[
        {"explicit": {"mode": "track", "s": 40.0, "offset": 0.5, "yaw_deg": 90}},
        {"explicit": {"mode": "world", "xyz": [70.0, -3.0, 0.0], "yaw_deg": 45}},
        {"explicit": {"mode": "lidar_frame", "xyz": [30.0, 0.0, 0.0], "frame_idx": 10}},
    ], draws=3)  # fmt: skip
    variants = expand(spec, {KEY: straight})
    assert len(variants) == 3 * 3  # explicit placements are drawn once
    by_mode = {v.job["placement"]["mode"]: v.objects[0].resolved for v in variants}
    assert by_mode["track"].s_m == pytest.approx(FIRST_X + 40.0)  # from the first frame
    assert by_mode["world"].s_m == pytest.approx(70.0)
    assert by_mode["world"].offset_m == pytest.approx(-3.0)
    assert by_mode["world"].yaw_deg == pytest.approx(45.0)
    assert by_mode["lidar_frame"].s_m == pytest.approx(FIRST_X + 10 + 30.0)
    # placements outside, obstacles inside: the 4th variant is the world placement's first
    assert variants[3].job["placement"] == {"mode": "world", "xyz": [70.0, -3.0, 0.0],
                                            "yaw_deg": 45.0, "frame_idx": None}  # fmt: skip


@pytest.mark.parametrize(
    ("prepared", "change", "needle"),
    [
        (straight_prepared(), {"placements": [{"zone": "platform"}]},
         "found no platform in straight"),
        (straight_prepared(planes=[platform(20.0, 60.0, -1.75, -8.0)]),
         {"placements": [{"zone": "platform", "distance_m": [100, 200]}]},
         "no platform of straight lies 100-200 m ahead"),
        (straight_prepared(), {"placements": [{"zone": "track", "distance_m": [290, 400]}]},
         f"reaches only {LENGTH - FIRST_X:.1f} m ahead of the train at frame 0"),
        (straight_prepared(ego=False), {}, "found no ego track"),
        (straight_prepared(), {"placements": [{"explicit": {"mode": "track", "s": 500}}]},
         "beyond the prepared ego track"),
        (straight_prepared(poles=[pole("p7", FIRST_X + 40.0, 0.2)]),
         {"placements": [{"explicit": {"mode": "track", "s": 40}}]}, "in pole p7"),
        (straight_prepared(), {"obstacles": [{"asset_id": "a1"}]}, "its footprint is unknown"),
        (straight_prepared(),
         {"obstacles": [{"builtin": "fallen_tree"}],
          "placements": [{"zone": "track", "yaw_deg": [80, 100], "distance_m": [30, 40]}]},
         "could not place fallen_tree"),
        (straight_prepared(),
         {"sequences": [{"path": KEY, "frame_range": [900, 950]}]}, "holds no frame"),
    ],
)  # fmt: skip
def test_impossible_specs_are_reported(prepared, change: dict, needle: str) -> None:
    spec = _spec(**change)
    msgs = _messages(spec, prepared)
    assert any(m.startswith("error") and needle in m for m in msgs), msgs
    with pytest.raises(CampaignError) as err:
        expand(spec, {KEY: prepared})
    assert needle in str(err.value)


def test_a_missing_preparation_is_an_error() -> None:
    (issue,) = validate(_spec(), {"elsewhere": straight_prepared()})
    assert issue.level == "error" and "no preparation given for 'seq/straight'" in issue.message


def test_a_clipped_distance_is_a_warning(straight) -> None:
    spec = _spec(placements=[{"zone": "track", "distance_m": [100, 500]}])
    variants, issues = expand_with_issues(spec, {KEY: straight})
    assert len(variants) == 3
    assert [i.level for i in issues] == ["warning"] and "clipped" in issues[0].message
    assert all(v.objects[0].resolved.s_m <= LENGTH for v in variants)


def test_rules_apply_to_their_sequences_only() -> None:
    with_platform = straight_prepared(planes=[platform(60.0, 200.0, -1.75, -8.0)])
    spec = _spec(
        sequences=[{"path": KEY}, {"path": "seq/plain", "name": "plain"}],
        placements=[{"zone": "platform", "sequences": [KEY]}, {"zone": "track"}],
    )
    variants = expand(spec, {KEY: with_platform, "seq/plain": straight_prepared()})
    zones = {(v.sequence_label, v.objects[0].resolved.zone) for v in variants}
    assert zones == {("straight", "platform"), ("straight", "track"), ("plain", "track")}


def test_pieces_of_one_platform_are_joined() -> None:
    """The preparation outlines a platform per 40 m piece, with gaps between: a footprint
    in a gap still meets the platform's edge."""
    from worker.campaign.placement import SequenceGeometry, platform_outlines

    pieces = [platform(100.0, 149.0, -1.75, -8.0), platform(151.0, 200.0, -1.75, -8.0),
              platform(120.0, 180.0, 2.0, 6.0)]  # fmt: skip
    prepared = straight_prepared(planes=pieces)
    (left, right) = platform_outlines(pieces, prepared.ego)
    assert (left.side, right.side) == ("left", "right")
    assert right.s_range == (100.0, 200.0) and right.lateral == (-8.0, -1.75)
    geom = SequenceGeometry.from_prepared(prepared, key=KEY, label="straight")
    fp = Footprint((-0.3, 0.3), (-0.3, 0.3), 1.8)
    assert "across the edge" in str(geom.conflict(Placed(fp, 150.0, -1.9, 0.0), clearance=0.1))
    assert geom.conflict(Placed(fp, 150.0, -4.0, 0.0), clearance=0.1, zone="platform") is None


def test_moving_obstacles_walk_through_their_drawn_position(straight) -> None:
    """A crossing walker's path runs across the track through its drawn (s, offset), an
    along-walker's along it; speeds and starts in their ranges; no path position meets
    the pole or the platform, and a later object keeps min_spacing from every one."""
    spec = _spec(
        draws=6, objects_per_sequence=2,
        obstacles=[{"builtin": "person", "motion": {"pattern": "cross", "span_m": 6,
                                                    "speed_mps": [1.0, 1.5],
                                                    "start_s": [0.0, 2.0]}},
                   {"builtin": "cow", "motion": {"pattern": "along", "span_m": 4,
                                                 "speed_mps": [0.4, 0.4]}}],
        placements=[{"zone": "track", "distance_m": [30, 200]}],
        constraints={"min_spacing_m": 3.0},
    )  # fmt: skip
    variants = expand(spec, {KEY: straight})
    assert len(variants) == 6
    for v in variants:
        walker, cow = v.objects
        for o, half in ((walker, 3.0), (cow, 2.0)):
            r, m = o.resolved, o.motion
            assert m is not None and m["mode"] == "track"
            (s_a, l_a), (s_b, l_b) = m["path"]
            mid = (0.5 * (s_a + s_b), 0.5 * (l_a + l_b))
            assert mid == pytest.approx((r.s_job_m, r.offset_m), abs=2e-3)
            if o is walker:
                assert s_a == s_b and abs(l_b - l_a) == pytest.approx(2 * half)
                assert 1.0 <= m["speed_mps"] <= 1.5 and 0.0 <= m["start_s"] <= 2.0
            else:
                assert l_a == l_b and abs(s_b - s_a) == pytest.approx(2 * half)
                assert m["speed_mps"] == 0.4 and m["start_s"] == 0.0
        assert v.job["objects"][0]["motion"] == walker.motion
        # every position of the walker's path against the pole (x 90 m, y 2.4 m, r 0.15)
        # and the platform (s 150-260, right): the walker crosses neither
        (s_a, l_a), (s_b, l_b) = walker.motion["path"]
        s_abs = FIRST_X + s_a
        assert not (150.0 - 0.5 <= s_abs <= 260.0 + 0.5 and min(l_a, l_b) < -1.75 + 0.5)
        ys = np.linspace(l_a, l_b, 50)
        assert np.min(np.hypot(s_abs - 90.0, ys - 2.4)) > 0.15 + 0.1
