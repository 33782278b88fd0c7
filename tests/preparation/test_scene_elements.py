"""Scene elements: planes by RANSAC, platform edges, poles by DBSCAN."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from geometry.poses import PoseTrack
from tests.synth_fixtures import synth_sequence, true_pole_xy, true_poses
from worker.osdar.sequence import Sequence
from worker.preparation.centreline import Centreline
from worker.preparation.config import PlaneConfig, PoleConfig, PrepareConfig
from worker.preparation.registration import register_clouds
from worker.preparation.scene_elements import (
    find_scene_elements,
    fit_plane_svd,
    reference_centreline,
)


# ---------------------------------------------------------------------------- synthetic arrays
def _straight_line(length: float = 60.0) -> Centreline:
    x = np.linspace(0.0, length, 7)
    return Centreline(np.column_stack([x, np.zeros_like(x), np.zeros_like(x)]))


def _toy_scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Track bed at z=-0.2, a left platform at +0.76 from y=1.72, one pole at (30, -3.3)."""
    bed = np.column_stack([rng.uniform(0, 60, 20000), rng.uniform(-4, 1.7, 20000)])
    bed = np.column_stack([bed, -0.2 + rng.normal(0, 0.01, len(bed))])
    pf = np.column_stack([rng.uniform(10, 50, 8000), rng.uniform(1.72, 7.0, 8000)])
    pf = np.column_stack([pf, 0.76 + rng.normal(0, 0.01, len(pf))])
    a = rng.uniform(0.0, np.pi, 600)  # the half facing the track (y > -3.3)
    pole = np.column_stack(
        [30.0 + 0.15 * np.cos(a), -3.3 + 0.15 * np.sin(a), rng.uniform(-0.2, 7.0, 600)]
    )
    return np.vstack([bed, pf, pole]), np.array([30.0, -3.3])


def test_planes_and_pole_on_known_geometry() -> None:
    rng = np.random.default_rng(1)
    xyz, pole_xy = _toy_scene(rng)
    se = find_scene_elements(xyz, _straight_line(), PlaneConfig(), PoleConfig())
    ground = [p for p in se.ground if p.lateral[0] < 0 < p.lateral[1]]
    assert ground, se.planes
    assert all(abs(p.height + 0.2) < 0.02 and p.normal[2] > 0.999 for p in ground)
    assert se.platforms
    for p in se.platforms:
        assert p.side == "left"
        assert abs(p.height - 0.76) < 0.02
        assert abs(p.edge_offset - 1.72) < 0.1
        assert p.edge is not None and p.edge.shape[1] == 3
        assert np.all(np.isfinite(p.polygon))
    assert len(se.poles) == 1
    pole = se.poles[0]
    assert np.linalg.norm(pole.axis_xy - pole_xy) < 0.1
    assert pole.base_z < -0.15 and pole.height > 7.0 and 0.05 < pole.radius < 0.3
    assert pole.to_json()["size"][2] == pytest.approx(pole.height)


@pytest.mark.parametrize("radius", [190.0, -300.0, 1e6])
def test_project_many_agrees_with_the_exact_projection(radius: float) -> None:
    """The cell-based projection of big clouds (track_coords) against Newton on the spline:
    within 5 mm in s, lateral, vertical, for points 20 m either side of a 190 m curve."""
    th = np.linspace(0.0, 150.0 / abs(radius), 200)
    r = abs(radius)
    xyz = np.column_stack(
        [r * np.sin(th), radius * (1 - np.cos(th)), 0.01 * r * th + 0.5 * np.sin(3 * th * r / 150)]
    )
    line = Centreline(xyz)
    rng = np.random.default_rng(1)
    s_true = rng.uniform(0.5, line.length - 0.5, 50_000)
    lat, up = rng.uniform(-20, 20, len(s_true)), rng.uniform(-3, 8, len(s_true))
    t = line.tangent(s_true)
    left = np.column_stack([-t[:, 1], t[:, 0], np.zeros(len(t))])
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    p = line.point(s_true) + lat[:, None] * left + up[:, None] * np.array([0.0, 0.0, 1.0])
    exact, fast = line.project(p, exact=True), line.project_many(p)
    assert np.allclose(exact.lateral, lat, atol=1e-3) and np.allclose(exact.s, s_true, atol=1e-3)
    for k in ("s", "lateral", "vertical", "distance"):
        assert np.max(np.abs(getattr(fast, k) - getattr(exact, k))) < 0.005, k
    beyond = line.project_many(line.point(np.array([line.length])) + 5 * t[-1:] * [1, 1, 0])
    assert beyond.s[0] == pytest.approx(line.length) and beyond.distance[0] > 4.0


def test_fit_plane_svd_recovers_a_tilted_plane() -> None:
    rng = np.random.default_rng(2)
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    xy = rng.uniform(-5, 5, (500, 2))
    z = -(n[0] * xy[:, 0] + n[1] * xy[:, 1] - 0.3) / n[2]
    normal, d, rms = fit_plane_svd(np.column_stack([xy, z]))
    assert np.allclose(normal, n, atol=1e-9)
    assert d == pytest.approx(-0.3)
    assert rms < 1e-9


def test_empty_cloud_warns_without_failing() -> None:
    se = find_scene_elements(np.zeros((0, 3)), _straight_line(), PlaneConfig(), PoleConfig())
    assert se.planes == [] and se.poles == []
    assert se.warnings


def test_reference_from_a_standing_train() -> None:
    T = np.tile(np.eye(4), (5, 1, 1))
    ref = reference_centreline(None, PoseTrack(np.arange(5) * 0.1, T))
    assert ref.length == pytest.approx(160.0)
    assert np.allclose(ref.tangent([0.0])[0], [1, 0, 0])


# ---------------------------------------------------------------------------- synthetic station
@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, Centreline]:
    folder = synth_sequence(tmp_path_factory.getbasetemp())
    seq = Sequence.open(folder)
    gt = true_poses(folder)
    cloud = register_clouds(seq, gt, voxel_size=0.1, max_range=80.0)
    cls = json.loads((folder / "ground_truth" / "centrelines.json").read_text())
    ego = next(Centreline.from_json(c) for c in cls if c["ego"])
    ts = dict(zip(seq.frame_indices, seq.timestamps("lidar"), strict=True))
    uf = np.unique(cloud.frame_idx)
    views = gt.interpolate(np.array([ts[f] for f in uf]))[:, :3, 3]
    views = views[np.searchsorted(uf, cloud.frame_idx)]
    cfg = PrepareConfig()
    se = find_scene_elements(cloud.xyz, ego, cfg.planes, cfg.poles, view_xyz=views)
    return folder, se, ego


def test_station_ground_plane_is_the_track_bed(station) -> None:
    _, se, _ = station
    bed = [p for p in se.ground if p.lateral[0] < -1.0 and p.lateral[1] > 1.0]
    assert bed
    # the biggest near-track ground patch: near-vertical normal, at the track bed level
    best = max(bed, key=lambda p: p.points * (abs(p.height + 0.2) < 0.3))
    assert best.normal[2] > np.cos(np.radians(2.0))
    assert -0.35 < best.height < -0.05


def test_station_platforms_and_edges(station) -> None:
    _, se, _ = station
    sides = {p.side for p in se.platforms}
    assert sides == {"left", "right"}, [p.to_json()["side"] for p in se.platforms]
    for p in se.platforms:
        assert abs(p.height - 0.76) < 0.05
        assert p.edge is not None and len(p.edge) >= 2
        assert abs(p.edge_offset - 1.72) < 0.1
        assert p.normal[2] > np.cos(np.radians(2.0))


def test_station_poles_near_true_poles(station) -> None:
    folder, se, _ = station
    truth = true_pole_xy(folder)
    assert len(se.poles) >= 3
    d = np.array([np.min(np.linalg.norm(truth - p.axis_xy, axis=1)) for p in se.poles])
    # the poles found are true poles, placed within 0.2 m
    assert np.mean(d < 0.2) >= 0.8, d
    assert np.median(d) < 0.1
