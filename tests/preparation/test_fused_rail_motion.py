"""fused's rail motion: a rail vehicle's base moves along its own axis (the chord of a
turn aside), within the body's sway. The true poses of a synthetic sequence satisfy it to
its sigma, and with it the frame-to-frame lateral motion of a short sparse sequence, where
the odometry's last steps slip sideways, follows the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.poses import PoseTrack
from tests.synth_fixtures import true_ego_input, true_poses_at
from worker.preparation.localization.base import Health
from worker.preparation.localization.fused import (
    FusedStrategy,
    Sigmas,
    _rail_motion_residuals,
    build_problem,
)


def _switch(tmp_path_factory: pytest.TempPathFactory, frames: int) -> Path:
    """A sparse synthetic switch sequence (hard INS, no cameras) of ``frames`` frames."""
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene="switch", frames=frames, scale=0.05, seed=0, lidar_density=0.3,
        ins_profile="hard", cameras=(),
    )  # fmt: skip
    return generate(tmp_path_factory.mktemp(f"switch{frames}") / "seq", cfg).folder


@pytest.fixture(scope="module")
def short_switch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _switch(tmp_path_factory, 12)


def _with_poses_and_sway(pb, T: np.ndarray, sway: np.ndarray, d: float = 0.0) -> np.ndarray:
    """A parameter vector with poses T (n, 4, 4), sway offsets (n, 2) and bogie offset d."""
    from worker.preparation.localization.fused import _extra_cols, n_params

    x = np.zeros(n_params(pb))
    xp = x[: 6 * pb.n].reshape(pb.n, 6)
    xp[:, :3] = Rotation.from_matrix(T[:, :3, :3] @ np.swapaxes(pb.R0, 1, 2)).as_rotvec()
    xp[:, 3:] = T[:, :3, 3] - pb.p0
    i0 = _extra_cols(pb)["sway"]
    x[i0 : i0 + 2 * pb.n] = sway.ravel()
    x[_extra_cols(pb)["bogie"]] = d
    return x


def test_true_motion_keeps_to_the_rails_with_the_true_sway(short_switch: Path) -> None:
    """The true poses with the true sway (the base's offset from the true centreline,
    sideways and up) meet every rail-motion step within its sigma (1 mm); without the sway
    the steps are off by its changes (up to 2.6 mm sideways, 3.3 mm up a frame)."""
    inp = true_ego_input(short_switch)
    pb = build_problem(inp, Health(), Sigmas())
    assert pb.nh is not None and inp.ego is not None
    T = true_poses_at(short_switch, inp.times)
    proj = inp.ego.project(T[:, :3, 3])
    sway = np.column_stack([proj.lateral, proj.vertical - np.mean(proj.vertical)])
    R, p = T[:, :3, :3], T[:, :3, 3]
    r = _rail_motion_residuals(pb, R, p, _with_poses_and_sway(pb, T, sway))
    assert np.max(np.abs(r)) < 1.0, r
    assert np.max(np.abs(sway)) < 0.008, sway  # the generator's 6 mm sway, 4 mm bounce
    r0 = _rail_motion_residuals(pb, R, p, _with_poses_and_sway(pb, T, 0.0 * sway))
    assert np.max(np.abs(r0)) > 1.5, r0


def _lateral_step_errors_mm(track: PoseTrack, folder: Path, times: np.ndarray) -> np.ndarray:
    T = track.interpolate(times)
    G = true_poses_at(folder, times)
    est = np.einsum("nji,nj->ni", T[:-1, :3, :3], T[1:, :3, 3] - T[:-1, :3, 3])
    tru = np.einsum("nji,nj->ni", G[:-1, :3, :3], G[1:, :3, 3] - G[:-1, :3, 3])
    return 1000.0 * (est[:, 1] - tru[:, 1])


def test_rail_motion_holds_the_lateral_steps_of_a_short_sparse_run(short_switch: Path) -> None:
    # the accelerometers follow the sway itself (test_accelerometer.py) and the INS velocity
    # its mean (test_fused_velocity.py): without them the rail motion is what holds the
    # lateral steps here
    inp = true_ego_input(short_switch, fused_accel=False)
    isolated = FusedStrategy(Sigmas(use_ins_velocity=False))
    inp.options["fused_rail_motion"] = False
    without = _lateral_step_errors_mm(isolated.run(inp).track, short_switch, inp.times)
    inp.options["fused_rail_motion"] = True
    with_nh = _lateral_step_errors_mm(isolated.run(inp).track, short_switch, inp.times)
    # the sway is what remains: 2.6 mm a frame at most, 1.8 mm RMS
    rms, rms_without = np.sqrt(np.mean(with_nh**2)), np.sqrt(np.mean(without**2))
    assert rms < 1.3 * 1.84, (with_nh, without)
    assert rms < rms_without, (with_nh, without)
    inp.options["fused_accel"] = True
    with_accel = _lateral_step_errors_mm(FusedStrategy().run(inp).track, short_switch, inp.times)
    assert np.sqrt(np.mean(with_accel**2)) < 1.3 * 1.84, with_accel


def test_rail_motion_keeps_every_lateral_step_within_the_sway(short_switch: Path) -> None:
    inp = true_ego_input(short_switch)
    inp.options["fused_rail_motion"] = True
    err = _lateral_step_errors_mm(FusedStrategy().run(inp).track, short_switch, inp.times)
    assert np.max(np.abs(err)) < 3.0, err


def test_a_grade_change_keeps_to_the_rails_vertically(short_switch: Path) -> None:
    """A base climbing along a vertical curve of radius 2 km (10 m steps, its pitch the
    track's tangent) meets the vertical rows exactly: each step rises by the chord of its
    pitch change, 25 mm (with the chord's sign turned, 50 mm off against a 1 mm sigma).
    One frame 6 mm too high (and no bounce to explain it) shows in its two steps, by 6 mm
    each, with opposite signs."""
    inp = true_ego_input(short_switch)
    pb = build_problem(inp, Health(), Sigmas())
    assert pb.nh is not None
    n, rho, sigma = pb.n, 2000.0, Sigmas().rail_motion_vert
    a = 10.0 * np.arange(n) / rho  # the arc's angle at each base
    p = np.column_stack([rho * np.sin(a), np.zeros(n), rho * (1.0 - np.cos(a))])
    # climbing: the nose up, a negative rotation about +y (the left axis)
    R = np.stack([Rotation.from_rotvec([0.0, -ak, 0.0]).as_matrix() for ak in a])
    x = _with_poses_and_sway(pb, np.tile(np.eye(4), (n, 1, 1)), np.zeros((n, 2)))
    vert = _rail_motion_residuals(pb, R, p, x).reshape(-1, 2)[:, 1]
    assert np.max(np.abs(vert)) * sigma < 1e-4, vert
    bumped = p.copy()
    bumped[4, 2] += 0.006
    bump = _rail_motion_residuals(pb, R, bumped, x).reshape(-1, 2)[:, 1]
    assert abs(bump[3] * sigma - 0.006) < 1e-4 and abs(bump[4] * sigma + 0.006) < 1e-4, bump
    assert np.max(np.abs(np.delete(bump, [3, 4]))) * sigma < 1e-4, bump


def test_a_significant_cloud_pitch_is_taken_out_of_every_lidar_step(
    short_switch: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the ground pairs show the cloud pitched by p, the ground pairs and KISS-ICP's
    steps both lose its climb: p per metre of the step along the track."""
    from worker.preparation.localization import fused
    from worker.preparation.localization.lidar_yaw import YawOffset

    p = 1e-3
    monkeypatch.setattr(fused, "lidar_pitch_offset", lambda *a, **kw: YawOffset(p, 1e-4, 50))
    plain = build_problem(true_ego_input(short_switch, fused_lidar_pitch=False), Health(), Sigmas())
    tilted = build_problem(true_ego_input(short_switch), Health(), Sigmas())
    assert plain.ground is not None and tilted.ground is not None
    assert tilted.ground["pitch_offset"] == p and plain.ground["pitch_offset"] == 0.0
    g0, g1 = plain.ground["T_k_j"][:, :3, 3], tilted.ground["T_k_j"][:, :3, 3]
    np.testing.assert_allclose(g1[:, 2] - g0[:, 2], -p * g0[:, 0], atol=1e-6)
    np.testing.assert_allclose(tilted.d_t[:, 2] - plain.d_t[:, 2], -p * plain.d_t[:, 0], atol=1e-6)


@pytest.fixture(scope="module")
def switch_30(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _switch(tmp_path_factory, 30)


def test_a_pitched_cloud_is_estimated_with_the_poses_not_followed(switch_30: Path) -> None:
    """Lidar steps and ground pairs measured in a cloud pitched by c against the base climb
    by c per metre: the solve estimates c (the rail motion says the base moves along its
    own axis) instead of climbing the poses by it. (On 12 frames two thirds of it.)"""
    from worker.preparation.localization.fused import _cloud_pitch_of, _tilted, solve

    inp = true_ego_input(switch_30, fused_lidar_pitch=False)
    est, z_end = [], []
    for c in (0.0, 1e-3):  # rad: 1 mrad
        pb = build_problem(inp, Health(), Sigmas())
        assert pb.ground is not None
        T = pb.ground["T_k_j"]
        T[:, :3, 3] = _tilted(T[:, :3, 3], -c)
        pb.d_t = _tilted(pb.d_t, -c)
        x = solve(pb)
        est.append(_cloud_pitch_of(x, pb))
        z = x[: 6 * pb.n].reshape(pb.n, 6)[:, 5]
        z_end.append(z[-1] - z[0])
        length = float(np.max(pb.ground["T_k_j"][:, 0, 3]))
    assert abs(est[1] - est[0] - 1e-3) < 0.2e-3, est
    # the poses' last height moves by far less than the climb over a pair, c x
    assert abs(z_end[1] - z_end[0]) < 0.25 * 1e-3 * length, z_end


def test_the_bogie_offset_is_free_only_where_the_turn_measures_it() -> None:
    """The base's distance ahead of its bogies moves it sideways by itself times each
    step's turn: a straight (0.06 deg over 35 frames) measures it to 6 m, too little to
    free it; a curve (10 deg over 60 frames) to 4.5 cm, free; a short or degenerate run
    keeps it pinned whatever its turn."""
    from math import radians

    from worker.preparation.localization.fused import (
        BOGIE_PINNED_M,
        _bogie_sigma,
        bogie_information,
    )

    sig = Sigmas()
    straight = bogie_information(radians(0.06), 34, sig.rail_motion_lat)
    curve = bogie_information(radians(10.0), 59, sig.rail_motion_lat)
    assert 0.02 < straight < 0.04, straight  # 1 / 6 m squared
    assert 400 < curve < 600, curve  # 1 / 4.5 cm squared
    far = Health(metrics={"ins_travelled_m": 60.0})
    assert _bogie_sigma(far, False, sig, radians(0.06), 34) == BOGIE_PINNED_M
    assert _bogie_sigma(far, False, sig, radians(10.0), 59) == sig.bogie_offset
    assert _bogie_sigma(far, True, sig, radians(10.0), 59) == BOGIE_PINNED_M
    short = Health(metrics={"ins_travelled_m": 10.0})
    assert _bogie_sigma(short, False, sig, radians(10.0), 59) == BOGIE_PINNED_M
    assert far.metrics["fused_bogie_information_m2"] == pytest.approx(curve)
