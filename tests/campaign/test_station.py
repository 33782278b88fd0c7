"""Rules on a real preparation: a small synthetic station (platform, poles, curve noise).

Every check here is made in the world frame against the preparation's own poles and
platform polygons, not through the expansion's track coordinates.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from renderer.assets import build_obstacle
from tests.synth_fixtures import synth_sequence
from worker.augmentation.placement import PlacementSpec, resolve_placement
from worker.campaign.expand import expand
from worker.campaign.placement import points_in_polygon
from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import dump_variants
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.getbasetemp()
    folder = synth_sequence(base)  # shared with the preparation tests
    return prepare(folder, PrepareConfig(strategy="ins"), cache_dir=base / "campaign_cache")


def _spec() -> CampaignSpec:
    near = [3.0, 28.0]
    return CampaignSpec.model_validate({
        "name": "station_rules",
        "seed": 2,
        "sequences": [{"path": "station"}],
        "obstacles": [{"builtin": "person", "seeds": [0, 1]}, {"builtin": "cow"},
                      {"builtin": "rock"}],
        "placements": [{"zone": "track", "distance_m": near},
                       {"zone": "crossing", "distance_m": near},
                       {"zone": "gauge_edge", "distance_m": near},
                       {"zone": "beside", "distance_m": near},
                       {"zone": "platform", "distance_m": [19.0, 31.0]}],
        "draws": 2,
        "objects_per_sequence": 2,
        "constraints": {"min_spacing_m": 1.5, "clearance_m": 0.1},
    })  # fmt: skip


def _corners_world(xyz: tuple, heading_deg: float, bounds: np.ndarray, grow: float) -> np.ndarray:
    (x0, y0, _), (x1, y1, _) = bounds
    c = np.array([[x0 - grow, y0 - grow], [x1 + grow, y0 - grow],
                  [x1 + grow, y1 + grow], [x0 - grow, y1 + grow]])  # fmt: skip
    h = math.radians(heading_deg)
    R = np.array([[math.cos(h), -math.sin(h)], [math.sin(h), math.cos(h)]])
    return c @ R.T + np.asarray(xyz[:2])


def test_rules_hold_on_a_prepared_station(station) -> None:
    spec = _spec()
    variants = expand(spec, {"station": station})
    assert len(variants) == 5 * 2 * 4 // 2
    assert dump_variants(expand(spec, {"station": station})) == dump_variants(variants)
    platforms = [p for p in station.planes if p.kind == "platform"]
    assert platforms and station.poles  # the scene has what the rules must avoid
    frames = station.track.frame_idx
    first_xyz = station.track.T[0, :3, 3]
    s0 = float(station.ego.project(first_xyz[None]).s[0])
    for v in variants:
        assert len(v.objects) == 2
        spots = []
        for o in v.objects:
            r = o.resolved
            rule = spec.placements[o.placement_index]
            assert rule.distance_m[0] <= r.distance_first_view_m <= rule.distance_m[1]
            assert r.first_view_frame in frames
            mesh = build_obstacle(o.class_name, seed=o.variation_seed)
            grown = _corners_world(r.xyz_world, r.heading_deg, mesh.bounds, 0.1)
            for pole in station.poles:
                inside = points_in_polygon(np.asarray(pole.axis_xy)[None, :2], grown)[0]
                dist = np.min(np.linalg.norm(grown - pole.axis_xy[:2], axis=1))
                assert not inside and dist > pole.radius, (v.id, pole.id)
            for pl in platforms:
                n_in = points_in_polygon(grown, pl.polygon[:, :2]).sum()
                assert n_in in (0, 4), (v.id, r.zone)  # wholly on the platform or off it
                if r.zone in ("track", "crossing", "gauge_edge"):
                    assert n_in == 0, (v.id, r.zone)
            if r.zone == "platform":
                assert any(points_in_polygon(grown, p.polygon[:, :2]).all() for p in platforms)
            # the job's placement puts the object where the expansion says
            spec_pl = PlacementSpec("track", s=o.placement["s"], offset=o.placement["offset"],
                                    yaw_deg=o.placement["yaw_deg"])  # fmt: skip
            times = dict(zip(frames.tolist(), station.track.timestamps.tolist(), strict=True))
            res = resolve_placement(spec_pl, ego=station.ego, track=station.track,
                                    frame_times=times, proxies=None, poles=station.poles,
                                    obj=mesh)  # fmt: skip
            assert np.allclose(res.T_world_obj[:3, 3], r.xyz_world, atol=2e-3)
            assert r.s_m == pytest.approx(s0 + r.s_job_m, abs=2e-3)
            spots.append(grown)
        gap = min(np.linalg.norm(a[:, None] - b[None], axis=2).min()
                  for a, b in [(spots[0], spots[1])])  # fmt: skip
        assert points_in_polygon(spots[0], spots[1]).sum() == 0 and gap > 1.5 - 0.2


def test_preparations_are_found_by_path_or_label(station) -> None:
    spec = CampaignSpec.model_validate(
        {"name": "p", "sequences": [{"path": str(Path("x") / "station")}],
         "obstacles": [{"builtin": "rock"}],
         "placements": [{"zone": "platform", "distance_m": [19.0, 31.0]}]}
    )  # fmt: skip
    (by_label,) = expand(spec, {"station": station})  # the folder's name
    (by_path,) = expand(spec, {str(Path("x") / "station"): station})
    assert by_label == by_path and by_path.sequence == str(Path("x") / "station")
