"""fused's INS velocity steps: each step's displacement along the track and sideways. The
true poses of a synthetic sequence meet the sideways component within its sigma, and a
lateral drift of a centimetre a second (what the rail motion's steps cannot tell from the
body's sway over a short run) puts every step two sigmas further off, sideways only. An
INS 8 m ahead of the base moves sideways in a curve by its lever's turn: the true poses
meet its velocity with the true lever, not without. The steps are compared on the
solution's own axes: an INS mounted 5 deg off in heading changes none of them. At the true
poses KISS-ICP's pairs along the track are better than their design sigma, and their
along-track variance factor may say so (down to ``Sigmas.odo_pair_along_floor``); every
other factor stays at least 1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.geodesy import WorldFrame
from geometry.poses import PoseTrack, reexpress
from tests.synth_fixtures import synth_sequence, true_ego_input
from worker.preparation.localization.base import Health
from worker.preparation.localization.fused import (
    FACTOR_FLOORS,
    Problem,
    Sigmas,
    build_problem,
    factor_floors,
    measurement_blocks,
    n_params,
    variance_factors,
)


def _curve(
    tmp_path_factory: pytest.TempPathFactory, name: str, frames: int, seed: int, **ins: object
) -> Path:
    """A sparse tight curve with the good INS profile, ``ins`` overriding its errors."""
    return synth_sequence(
        tmp_path_factory.mktemp(name), "seq", scene="tight_curve", frames=frames, scale=0.05,
        seed=seed, lidar_density=0.3, ins_profile="good", cameras=(), ins_overrides=ins,
    )  # fmt: skip


@pytest.fixture(scope="module")
def short_curve(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _curve(tmp_path_factory, "curve", 12, 1)


#: An INS this far ahead of the base (m): on the curve's 0.44 deg over 3 s its lever turns
#: at 20 mm/s sideways, four sigmas of the good profile's velocity.
LEVER_M = 8.0


@pytest.fixture(scope="module")
def curve_lever(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _curve(tmp_path_factory, "curve_lever", 30, 3, lever_arm_m=(LEVER_M, 0.0, 0.0))


#: A heading mounting error far beyond any profile's (deg): on the INS's own forward axis
#: a 3 m step would lose 1 - cos(5 deg) of its length, 11 mm, two sigmas of the good
#: profile's velocity, and gain 26 cm sideways.
BORESIGHT_YAW_DEG = 5.0


@pytest.fixture(scope="module")
def curve_boresight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _curve(
        tmp_path_factory, "curve_boresight", 12, 1, boresight_deg=(0.0, 0.0, BORESIGHT_YAW_DEG)
    )


def _true_state(
    folder: Path,
    lateral_drift_mps: float = 0.0,
    lever: tuple[float, float, float] = (0.0, 0.0, 0.0),
    sigmas: Sigmas | None = None,
) -> tuple[Problem, np.ndarray]:
    """The problem and its state at the true poses, each frame moved sideways by
    ``lateral_drift_mps`` times its time (its own left axis), with the lever arm state at
    ``lever`` (m, base axes)."""
    inp = true_ego_input(folder)
    pb = build_problem(inp, Health(), sigmas or Sigmas())
    true_world = WorldFrame.from_json(json.loads((folder / "ground_truth/world.json").read_text()))
    dense = PoseTrack.from_csv(folder / "ground_truth/poses_dense.csv")
    truth = reexpress(dense, true_world, inp.world)
    T = truth.interpolate(inp.times)
    t = np.asarray(inp.times) - inp.times[0]
    p = T[:, :3, 3] + lateral_drift_mps * t[:, None] * T[:, :3, 1]
    n = pb.n
    x = np.zeros(n_params(pb))
    xp = x[: 6 * n].reshape(n, 6)
    xp[:, :3] = Rotation.from_matrix(T[:, :3, :3] @ np.swapaxes(pb.R0, 1, 2)).as_rotvec()
    xp[:, 3:] = p - pb.p0
    x[6 * n : 6 * n + 3] = lever
    return pb, x


def _velocity_residuals(
    folder: Path, lateral_drift_mps: float, lever: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> np.ndarray:
    """(S, 2) the normalised INS velocity residuals (along, sideways) at the true poses
    (:func:`_true_state`)."""
    pb, x = _true_state(folder, lateral_drift_mps, lever)
    assert pb.vel is not None
    return measurement_blocks(pb, x)["ins_v"]


def test_true_poses_meet_the_sideways_velocity_within_its_sigma(short_curve: Path) -> None:
    r = _velocity_residuals(short_curve, 0.0)
    # the good profile's velocity noise: 5 mm/s per record, the sigma 5.1 mm/s
    assert np.sqrt(np.mean(r[:, 1] ** 2)) < 1.5, r
    assert np.max(np.abs(r[:, 1])) < 3.5, r


def test_a_lateral_drift_of_a_centimetre_a_second_is_seen_sideways_only(
    short_curve: Path,
) -> None:
    still = _velocity_residuals(short_curve, 0.0)
    drift = _velocity_residuals(short_curve, 0.01)
    # 10 mm/s against a 5 mm/s sigma: every step two sigmas further, the same sign
    shift = drift[:, 1] - still[:, 1]
    assert np.allclose(shift, shift[0], atol=0.2) and abs(abs(shift[0]) - 2.0) < 0.2, shift
    # along the track nothing moved
    assert np.max(np.abs(drift[:, 0] - still[:, 0])) < 0.05


def test_the_lever_arm_turns_with_the_train(curve_lever: Path) -> None:
    with_lever = _velocity_residuals(curve_lever, 0.0, (LEVER_M, 0.0, 0.0))
    without = _velocity_residuals(curve_lever, 0.0)
    assert np.sqrt(np.mean(with_lever[:, 1] ** 2)) < 1.5, with_lever
    # the curve turns the lever by its heading rate: far outside the 5 mm/s sigma
    assert np.sqrt(np.mean(without[:, 1] ** 2)) > 3.0, without


def test_an_ins_mounted_off_in_heading_changes_no_velocity_step(
    short_curve: Path, curve_boresight: Path
) -> None:
    straight = _velocity_residuals(short_curve, 0.0)
    turned = _velocity_residuals(curve_boresight, 0.0)
    assert straight.shape == turned.shape
    # the same records but for the mounting: every step within a hundredth of a sigma
    assert np.max(np.abs(turned - straight)) < 0.01, turned - straight


def test_odometry_pairs_along_the_track_may_be_trusted_beyond_their_design(
    curve_lever: Path,
) -> None:
    pb, x = _true_state(curve_lever, lever=(LEVER_M, 0.0, 0.0))
    assert pb.odo_pairs is not None
    floor = Sigmas().odo_pair_along_floor
    factors = variance_factors(pb, x)
    along, rest = factors["odo_pair"][0], factors["odo_pair"][1:]
    # KISS-ICP's pairs along this curve are good to a third of their 2 cm design sigma
    assert floor <= along < 0.6, factors["odo_pair"]
    assert np.all(rest >= 1.0), factors["odo_pair"]
    assert all(np.all(v >= 1.0) for k, v in factors.items() if k != "odo_pair"), factors
    # the floors' table names real fields, and only this component has one
    assert np.array_equal(factor_floors(Sigmas(), "odo_pair", 4), [floor, 1.0, 1.0, 1.0])
    assert all(hasattr(Sigmas(), f) for per in FACTOR_FLOORS.values() for f in per.values())
    # with the floor at 1 the pairs are trusted as designed, no more
    pb1, x1 = _true_state(
        curve_lever, lever=(LEVER_M, 0.0, 0.0), sigmas=Sigmas(odo_pair_along_floor=1.0)
    )
    assert variance_factors(pb1, x1)["odo_pair"][0] == pytest.approx(1.0)


def test_odometry_pairs_carry_the_heading(curve_lever: Path) -> None:
    """The pairs' fourth component is frame j's heading in frame k against KISS-ICP's: at
    the true poses within a few sigmas, and a turn of every frame from the middle on by
    a tenth of a degree moves exactly the pairs that straddle the middle, by that turn
    over their sigma."""
    pb, x = _true_state(curve_lever, lever=(LEVER_M, 0.0, 0.0))
    g = pb.odo_pairs
    assert g is not None and np.all(g["w"][:, 2] > 0)
    r0 = measurement_blocks(pb, x)["odo_pair"][:, 3]
    assert np.sqrt(np.mean(r0**2)) < 3.0, r0
    n, mid, turn = pb.n, pb.n // 2, np.radians(0.1)
    xt = x.copy()
    xp = xt[: 6 * n].reshape(n, 6)
    R = Rotation.from_rotvec(xp[mid:, :3]) * Rotation.from_matrix(pb.R0[mid:])
    R = Rotation.from_rotvec([0.0, 0.0, turn]) * R  # about the world's vertical
    xp[mid:, :3] = (R * Rotation.from_matrix(pb.R0[mid:]).inv()).as_rotvec()
    shift = measurement_blocks(pb, xt)["odo_pair"][:, 3] - r0
    straddle = (g["k"] < mid) & (g["j"] >= mid)
    np.testing.assert_allclose(shift[straddle], turn * g["w"][straddle, 2], rtol=0.02)
    assert np.max(np.abs(shift[~straddle])) < 1e-6
