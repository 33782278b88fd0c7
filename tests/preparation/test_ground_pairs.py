"""Ground pairs: height, roll and pitch of one frame in another from the ground both see."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.poses import PoseTrack
from worker.osdar.sequence import Sequence
from worker.preparation.localization import make_input
from worker.preparation.localization.ground_pairs import (
    frame_ground,
    ground_pair,
    symmetric_ground_pair,
)
from worker.preparation.localization.odometry import _frame_input

DEG = np.pi / 180.0


def _surface(xy: np.ndarray) -> np.ndarray:
    """A sloped, canted, undulating ground (world heights, m)."""
    x, y = xy[:, 0], xy[:, 1]
    return 0.01 * x + 0.02 * y + 0.08 * np.sin(0.25 * x) * np.cos(0.3 * y)


def _frame_points(T_world_base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(m, 3) base points of ground (5 mm noise) and poles seen from a base pose."""
    local = rng.uniform([-25.0, -18.0], [75.0, 18.0], size=(40000, 2))
    xy_w = local @ T_world_base[:2, :2].T + T_world_base[:2, 3]
    ground = np.column_stack([xy_w, _surface(xy_w) + rng.normal(0.0, 0.005, len(xy_w))])
    poles = []
    for px, py in ((20.0, 4.0), (45.0, -5.0), (60.0, 6.0)):
        h = rng.uniform(0.0, 6.0, 300)
        poles.append(np.column_stack([np.full(300, px), np.full(300, py), h]))
    pts_w = np.concatenate([ground, *poles])
    T_base_world = np.linalg.inv(T_world_base)
    return pts_w @ T_base_world[:3, :3].T + T_base_world[:3, 3]


def _pose(t: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def test_ground_pair_recovers_height_roll_and_pitch() -> None:
    rng = np.random.default_rng(3)
    T_w_k = _pose((0.0, 0.0, 0.3), (0.04, -0.6, 10.0))
    T_w_j = T_w_k @ _pose((8.0, 0.05, 0.08), (0.03, 0.05, 0.4))
    gk = frame_ground(_frame_points(T_w_k, rng))
    gj = frame_ground(_frame_points(T_w_j, rng))
    T_true = np.linalg.inv(T_w_k) @ T_w_j
    # The odometry's guess: 3 cm low, 0.05 deg of pitch and 0.04 of roll off.
    T_guess = _pose((0.0, 0.0, -0.03), (0.04, 0.05, 0.0)) @ T_true
    pair = ground_pair(gk, gj, T_guess, 0, 1)
    assert pair is not None
    E = np.linalg.inv(T_true) @ pair.T_k_j
    roll, pitch, _ = np.degrees(Rotation.from_matrix(E[:3, :3]).as_rotvec())
    # The guess was 30 mm / 0.05 deg / 0.04 deg off; the ground brings it within 1 mm and 0.003 deg.
    assert abs(E[2, 3]) < 0.001
    assert abs(pitch) < 0.002
    assert abs(roll) < 0.003
    # Along-track, lateral and heading are the guess's: the ground says nothing of them.
    assert np.allclose(pair.T_k_j[:2, 3], T_guess[:2, 3], atol=0.01)
    assert pair.matched > 1000


def test_ground_pair_without_common_ground_says_nothing() -> None:
    rng = np.random.default_rng(4)
    gk = frame_ground(_frame_points(np.eye(4), rng))
    far = _pose((500.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # no overlap
    gj = frame_ground(_frame_points(far, rng))
    assert ground_pair(gk, gj, far, 0, 1) is None
    empty = frame_ground(np.zeros((0, 3)))
    assert ground_pair(gk, empty, np.eye(4), 0, 1) is None


def test_column_floor_is_each_columns_lowest_point() -> None:
    """Against a brute-force minimum per 1 m column, for a compact cloud (dense table) and one
    with a point 5 km away (occupied columns only)."""
    from worker.preparation.localization.ground_pairs import column_floor

    rng = np.random.default_rng(6)
    p = np.column_stack([rng.uniform(-10, 10, (3000, 2)), rng.normal(0, 1, 3000)])
    for cloud in (p, np.vstack([p, [[5000.0, -3000.0, 7.0]]])):
        got = column_floor(cloud, 1.0)
        cols = np.floor(cloud[:, :2]).astype(np.int64)
        for c in {tuple(c) for c in cols[::50]}:
            same = np.all(cols == c, axis=1)
            assert np.all(got[same] == cloud[same, 2].min())
    assert column_floor(np.zeros((0, 3)), 1.0).shape == (0,)


def test_odometry_keeps_each_frames_ground_from_its_own_column_floors() -> None:
    """The odometry loop hands its column floors to frame_ground: the same ground as computed
    from scratch, and the points it registers are the rest (above the ground band)."""
    from worker.preparation.localization.ground_pairs import COLUMN_M, column_floor
    from worker.preparation.localization.odometry import remove_ground

    rng = np.random.default_rng(8)
    p = _frame_points(_pose((0.0, 0.0, 0.0), (0.1, -0.3, 5.0)), rng)
    floor = column_floor(p, COLUMN_M)
    shared, own = frame_ground(p, floor), frame_ground(p)
    assert np.array_equal(shared.points, own.points)
    assert np.array_equal(shared.grid, own.grid, equal_nan=True)
    assert len(own.points) > 1000
    above = remove_ground(p, floor)
    assert np.array_equal(above, remove_ground(p))
    # What KISS-ICP registers is the poles (900 points, 0-6 m tall) above the 20 cm band.
    assert 800 < len(above) <= 900


@pytest.fixture(scope="module")
def klein(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene="klein_flottbek", frames=30, scale=0.05, seed=5, lidar_density=1.0,
        ins_profile="good", cameras=(),
    )  # fmt: skip
    return generate(tmp_path_factory.mktemp("klein") / "seq", cfg).folder


def test_symmetric_pairs_cancel_the_ground_selection_bias(klein: Path) -> None:
    """Lag-1 pairs from the generator's lidar, started at the TRUE relative poses: one way
    they carry the two frames' different ground selections as a height bias of about a
    millimetre; both ways cancel it."""
    seq = Sequence.open(klein)
    inp = make_input(seq)
    T = PoseTrack.from_csv(klein / "ground_truth/poses_dense.csv").interpolate(inp.times)
    grounds = [_frame_input(inp, f)[1] for f in inp.frames]
    err: dict[str, list[float]] = {"one way": [], "both ways": []}
    for k in range(len(grounds) - 1):
        T_k_j = np.linalg.inv(T[k]) @ T[k + 1]
        for name, f in (("one way", ground_pair), ("both ways", symmetric_ground_pair)):
            pair = f(grounds[k], grounds[k + 1], T_k_j, k, k + 1)
            assert pair is not None
            err[name].append(1e3 * (pair.T_k_j[2, 3] - T_k_j[2, 3]))  # mm
    bias = {name: abs(float(np.mean(v))) for name, v in err.items()}
    assert bias["one way"] > 0.5, bias  # the case
    assert bias["both ways"] < 0.3 * bias["one way"], bias
