"""Placement rules against the synthetic scene's GROUND TRUTH (not the preparation's).

The expansion draws positions on a preparation (estimated poles, platforms, ego track,
in the estimated world frame); here every object of every variant is carried into the
true world through the frame it is first seen from (p_true = T_true_world_base @
inv(T_est_world_base) @ p_est: where the augmentation makes it appear in that frame's
images and lidar) and checked there against what the generator built: the true pole
axes (pole_top landmarks; catenary poles 0.17 m, signals 0.08 m in radius), the true
platform edges (platform_corner landmarks on the true ego centreline, 1.72 m from it),
the true ego track bed (1.6 m half-width), and the other objects of the
variant (min_spacing_m). The spec asks for clearance_m = 0.15 m: the preparation's errors
must stay within it for the true scene to be respected.

What the rules cannot honour is a platform the preparation did not find: on this short
station sequence it finds the right-hand platform only, so objects drawn on the left can
stand in the (unseen) left platform. That miss is kept visible as a strict xfail.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from renderer.assets import build_obstacle
from tests.synth_fixtures import landmarks, synth_sequence, true_poses
from worker.campaign.expand import expand
from worker.campaign.placement import points_in_polygon, rectangle_distance
from worker.campaign.spec import CampaignSpec
from worker.preparation.centreline import Centreline
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare

BED_HALF_WIDTH = 1.6
POLE_RADIUS = {"sig": 0.08}  # by landmark id prefix; catenary poles otherwise
CATENARY_RADIUS = 0.17
SPACING = 2.0


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory):
    base = tmp_path_factory.getbasetemp()
    folder = synth_sequence(base)  # shared with the preparation and station tests
    prepared = prepare(folder, PrepareConfig(strategy="ins"), cache_dir=base / "campaign_cache")
    return folder, prepared


def _spec() -> CampaignSpec:
    near = [3.0, 28.0]
    return CampaignSpec.model_validate({
        "name": "truth_rules",
        "seed": 5,
        "sequences": [{"path": "station"}],
        "obstacles": [{"builtin": "person", "seeds": [0, 1, 2]}, {"builtin": "cow"},
                      {"builtin": "rock", "seeds": [0, 1]},
                      {"builtin": "person", "seeds": [3],
                       "motion": {"pattern": "cross", "span_m": 5.0}}],
        "placements": [{"zone": "track", "distance_m": near},
                       {"zone": "gauge_edge", "distance_m": near},
                       {"zone": "beside", "distance_m": near},
                       {"zone": "platform", "distance_m": [19.0, 31.0]}],
        "draws": 2,
        "objects_per_sequence": 3,
        "constraints": {"min_spacing_m": SPACING, "clearance_m": 0.15},
    })  # fmt: skip


def _footprint(xyz: tuple, heading_deg: float, bounds: np.ndarray) -> np.ndarray:
    """(4, 2) world corners of a footprint (counter-clockwise)."""
    (x0, y0, _), (x1, y1, _) = bounds
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    h = math.radians(heading_deg)
    R = np.array([[math.cos(h), -math.sin(h)], [math.sin(h), math.cos(h)]])
    return c @ R.T + np.asarray(xyz[:2])


def _true_ego(folder: Path) -> Centreline:
    cls = [Centreline.from_json(d) for d in
           json.loads((folder / "ground_truth" / "centrelines.json").read_text())]  # fmt: skip
    return next(c for c in cls if c.ego)


def _track_coords(ego: Centreline, xy: np.ndarray) -> np.ndarray:
    """(k, 2) world xy -> (k, 2) [s, lateral (left +)] on the true ego centreline."""
    p = np.column_stack([xy, np.zeros(len(xy))])
    pr = ego.project(p)
    return np.column_stack([pr.s, pr.lateral])


def _est_to_true(folder: Path, prepared, frame: int) -> np.ndarray:
    """(4, 4) estimated world -> true world through ``frame``'s lidar pose."""
    track = prepared.track
    k = [int(f) for f in track.frame_idx].index(int(frame))
    t = np.array([track.timestamps[k]])
    return true_poses(folder).interpolate(t)[0] @ np.linalg.inv(track.interpolate(t)[0])


def _positions(v, prepared, folder: Path) -> list[list[np.ndarray]]:
    """Every footprint (true world corners) each object of a variant takes: one for a
    static object, one every 0.25 m of a moving one's path (on the ESTIMATED ego track,
    where the augmentation puts it, then carried into the true world)."""
    out = []
    ego = prepared.ego
    for o in v.objects:
        mesh = build_obstacle(o.class_name, seed=o.variation_seed)
        r = o.resolved
        T = _est_to_true(folder, prepared, r.first_view_frame or int(prepared.track.frame_idx[0]))
        yaw_true = math.degrees(math.atan2(T[1, 0], T[0, 0]))
        if o.motion is None:
            p = T[:3, :3] @ np.asarray(r.xyz_world) + T[:3, 3]
            out.append([_footprint(tuple(p), r.heading_deg + yaw_true, mesh.bounds)])
            continue
        (s_a, l_a), (s_b, l_b) = o.motion["path"]
        s_first = r.s_m - r.s_job_m  # the path is in the job's s (from the first frame)
        n = int(math.hypot(s_b - s_a, l_b - l_a) / 0.25) + 2
        spots = []
        for t in np.linspace(0.0, 1.0, n):
            s = s_first + s_a + t * (s_b - s_a)
            lat = l_a + t * (l_b - l_a)
            c = ego.point([s])[0]
            tg = ego.tangent([s])[0]
            left = np.array([-tg[1], tg[0], 0.0]) / math.hypot(tg[0], tg[1])
            p = T[:3, :3] @ (c + lat * left) + T[:3, 3]
            heading = math.degrees(math.atan2(tg[1], tg[0]) + math.atan2(l_b - l_a, s_b - s_a))
            spots.append(_footprint(tuple(p), heading + yaw_true, mesh.bounds))
        out.append(spots)
    return out


def test_drawn_positions_respect_the_true_scene(station) -> None:
    _check_true_scene(*station, only_found_platforms=True)


@pytest.mark.xfail(
    strict=True,
    reason="the preparation finds the right-hand platform of the synthetic station only: "
    "objects on the left can stand in the unseen left platform",
)
def test_drawn_positions_keep_off_every_true_platform_edge(station) -> None:
    _check_true_scene(*station, only_found_platforms=False)


def _check_true_scene(folder: Path, prepared, *, only_found_platforms: bool) -> None:
    spec = _spec()
    variants = expand(spec, {"station": prepared})
    assert len(variants) == math.ceil(4 * 7 * 2 / 3)  # placements x objects x draws / 3
    ego = _true_ego(folder)
    poles = [(np.asarray(lm["xyz"][:2]), POLE_RADIUS.get(lm["id"].split("_")[0], CATENARY_RADIUS))
             for lm in landmarks(folder, "pole_top")]  # fmt: skip
    corners = {lm["id"]: np.asarray(lm["xyz"][:2]) for lm in landmarks(folder, "platform_corner")}
    edges = []  # (s_lo, s_hi, signed edge offset) on the true ego centreline
    for pid in {k.rsplit("_corner", 1)[0] for k in corners}:
        sl = _track_coords(ego, np.stack([corners[f"{pid}_corner_start"],
                                          corners[f"{pid}_corner_end"]]))  # fmt: skip
        edges.append((sl[:, 0].min(), sl[:, 0].max(), float(np.mean(sl[:, 1]))))
    assert poles and edges  # the scene has what the rules must avoid
    if only_found_platforms:  # the sides the preparation found a platform on
        found = {np.sign(np.median(prepared.ego.project(np.asarray(pl.polygon)).lateral))
                 for pl in prepared.planes if pl.kind == "platform"}  # fmt: skip
        edges = [e for e in edges if np.sign(e[2]) in found]
        assert edges
    moving = 0
    for v in variants:
        spots = _positions(v, prepared, folder)
        moving += sum(o.motion is not None for o in v.objects)
        for o, per in zip(v.objects, spots, strict=True):
            where = (v.id, o.class_name, o.resolved.zone)
            for fp in per:
                for axis, radius in poles:  # never inside a pole
                    assert not points_in_polygon(axis[None], fp)[0], where
                    assert rectangle_distance(fp, _disc(axis, radius)) > 0.0, where
                sl = _track_coords(ego, fp)
                for s_lo, s_hi, e in edges:  # never across a platform's edge
                    on = (sl[:, 0] >= s_lo) & (sl[:, 0] <= s_hi) & (np.sign(e) * sl[:, 1] > abs(e))
                    assert on.sum() in (0, 4), (where, sl.round(2).tolist(), e)
            if o.motion is None and o.resolved.zone in ("beside", "platform"):
                sl = _track_coords(ego, per[0])  # off the bed: never half on it
                assert np.all(np.abs(sl[:, 1]) > BED_HALF_WIDTH), (where, sl.round(2).tolist())
        # the objects of a variant keep min_spacing_m, every position of a moving one
        for i in range(len(spots)):
            for j in range(i + 1, len(spots)):
                gap = min(rectangle_distance(a, b) for a in spots[i] for b in spots[j])
                assert gap > SPACING - 0.05, (v.id, i, j, gap)
    assert moving > 0


def _disc(c: np.ndarray, r: float, n: int = 16) -> np.ndarray:
    """A pole's cross-section as a (n, 2) polygon circumscribing the circle."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return c + (r / math.cos(math.pi / n)) * np.column_stack([np.cos(a), np.sin(a)])
