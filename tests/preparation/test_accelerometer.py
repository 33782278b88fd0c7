"""The accelerometers (CORRIMU) as the body's sway: summed twice on the gyros' chain,
their differences at the lidar times reproduce a known motion's (third differences blind
to a constant bias, second ones seeing it as its acceleration), and on a synthetic
sequence (accelerometer noise and bias on) match the true accelerations of the base;
``fused`` with them follows the sway frame to frame and estimates their bias."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.poses import R_INS_BASE_NOMINAL
from tests.synth_fixtures import true_ego_input, with_corrimu_added
from worker.preparation.localization.accelerometer import BRIDGE_SIGMA_FACTOR, accel_differences
from worker.preparation.localization.base import Health
from worker.preparation.localization.fused import FusedStrategy, build_problem, difference_weights
from worker.preparation.localization.fused import Sigmas as FusedSigmas
from worker.preparation.localization.gyro import gyro_chain

WINDOW = 0.1
MM = 1e-3


def _attitude(t: np.ndarray) -> np.ndarray:
    """(m, 3, 3) a turning base with a coach's roll and pitch sway."""
    yaw = 0.02 * (t - 100.0) + 0.002 * (t - 100.0) ** 2
    pitch = np.radians(0.03) * np.sin(6.9 * t + 0.3)
    roll = np.radians(0.04) * np.sin(5.7 * t + 1.1)
    return Rotation.from_euler("xyz", np.stack([roll, pitch, yaw], 1)).as_matrix()


def _position(t: np.ndarray) -> np.ndarray:
    """(m, 3) the base's path: along its heading at 10 m/s plus 6 mm of lateral sway at
    0.7 Hz and 4 mm of bounce at 1.3 Hz in its own axes."""
    R = _attitude(t)
    tau = t - 100.0
    # the forward path, integrated finely
    fine = 100.0 + np.arange(-2.0, 8.0, 1e-3)
    heading = 0.02 * (fine - 100.0) + 0.002 * (fine - 100.0) ** 2
    speed = 10.0 + 0.3 * (fine - 100.0)
    xy = np.cumsum(np.column_stack([np.cos(heading), np.sin(heading)]) * speed[:, None], 0) * 1e-3
    base = np.column_stack([np.interp(t, fine, xy[:, 0]), np.interp(t, fine, xy[:, 1]), 0 * t])
    sway = np.column_stack(
        [0 * t, 0.006 * np.sin(2 * np.pi * 0.7 * tau + 0.4), 0.004 * np.sin(2 * np.pi * 1.3 * tau)]
    )
    return base + np.einsum("nij,nj->ni", R, sway)


def _velocity(t: np.ndarray, h: float = 1e-4) -> np.ndarray:
    return (_position(t + h) - _position(t - h)) / (2 * h)


def _records(t_rec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3) rates (rad/s) and (m, 3) accelerations (m/s^2), INS axes, over the window
    before each record, as CORRIMU has them."""
    R_now, R_prev = _attitude(t_rec), _attitude(t_rec - WINDOW)
    dtheta = Rotation.from_matrix(np.swapaxes(R_prev, 1, 2) @ R_now).as_rotvec()
    rates = dtheta @ R_INS_BASE_NOMINAL.T / WINDOW
    a_world = (_velocity(t_rec) - _velocity(t_rec - WINDOW)) / WINDOW
    R_mid = _attitude(t_rec - 0.5 * WINDOW)
    a_base = np.einsum("nji,nj->ni", R_mid, a_world)
    return rates, a_base @ R_INS_BASE_NOMINAL.T


def _true_jerks(t: np.ndarray) -> np.ndarray:
    c = difference_weights(t, 3)
    p, R = _position(t), _attitude(t)
    n = len(t)
    j = sum(c[:, i : i + 1] * p[i : n - 3 + i] for i in range(4))
    return np.einsum("nji,nj->ni", R[1 : n - 2], j)


def test_the_third_differences_match_a_known_motion() -> None:
    t_rec = 100.0 + WINDOW * np.arange(50)
    rates, acc = _records(t_rec)
    chain = gyro_chain(t_rec, rates)
    t_lidar = t_rec[2:-2] + 0.037  # lidar frames between the records
    got = accel_differences(chain, t_rec, acc, t_lidar, 0.0, difference_weights(t_lidar, 3))
    truth = _true_jerks(t_lidar)
    assert got.ok.all()
    # the sway's jerks are 0.3 mm (lateral) and 1.4 mm (vertical) a stencil
    assert np.max(np.abs(truth[:, 1])) > 0.2 * MM and np.max(np.abs(truth[:, 2])) > 0.8 * MM
    err = np.abs(got.value - truth)
    assert np.all(err.max(axis=0) < 0.03 * MM), err.max(axis=0) / MM


def test_a_constant_bias_and_a_wrong_start_velocity_do_not_count() -> None:
    t_rec = 100.0 + WINDOW * np.arange(50)
    rates, acc = _records(t_rec)
    chain = gyro_chain(t_rec, rates)
    t_lidar = t_rec[2:-2] + 0.037
    c = difference_weights(t_lidar, 3)
    clean = accel_differences(chain, t_rec, acc, t_lidar, 0.0, c).value
    biased = accel_differences(chain, t_rec, acc + np.array([0.03, -0.02, 0.05]), t_lidar, 0.0, c)
    # 3-5 mg of bias: 15-25 mm over a second, nothing in a third difference (the base
    # turns by 0.02-0.04 rad/s here: a bias fixed to the body leaves micrometres)
    assert np.max(np.abs(biased.value - clean)) < 0.002 * MM


def test_a_constant_bias_shows_in_the_second_differences_as_its_acceleration() -> None:
    t_rec = 100.0 + WINDOW * np.arange(50)
    rates, acc = _records(t_rec)
    chain = gyro_chain(t_rec, rates)
    t_lidar = t_rec[2:-2] + 0.037
    c = difference_weights(t_lidar, 2)
    bias_ins = np.array([0.03, -0.02, 0.05])
    clean = accel_differences(chain, t_rec, acc, t_lidar, 0.0, c).value
    biased = accel_differences(chain, t_rec, acc + bias_ins, t_lidar, 0.0, c).value
    # b h^2 per stencil (0.2-0.5 mm), the body turning by 0.02-0.04 rad/s: within 1 %
    h2 = float(np.median(np.diff(t_lidar))) ** 2
    expected = bias_ins @ R_INS_BASE_NOMINAL * h2
    err = np.abs(biased - clean - expected)
    assert np.all(err < 0.01 * np.abs(expected).max()), err.max(axis=0) / MM


def test_a_missing_record_is_bridged_and_its_stencils_flagged() -> None:
    t_rec = 100.0 + WINDOW * np.arange(50)
    rates, acc = _records(t_rec)
    keep = np.ones(len(t_rec), dtype=bool)
    keep[20] = False
    chain = gyro_chain(t_rec[keep], rates[keep])
    t_lidar = t_rec[2:-2] + 0.037
    got = accel_differences(
        chain, t_rec[keep], acc[keep], t_lidar, 0.0, difference_weights(t_lidar, 3)
    )
    assert got.ok.all()
    # the stencils whose span holds the missing window: three or four
    assert 3 <= np.sum(got.bridged > 0) <= 4
    err = np.abs(got.value - _true_jerks(t_lidar))
    # within the bound, widened as their sigma is (BRIDGE_SIGMA_FACTOR)
    limit = 0.03 * MM * (1.0 + BRIDGE_SIGMA_FACTOR * got.bridged)
    assert np.all(err.max(axis=1) < limit), err.max(axis=1) / MM


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene="station", frames=30, scale=0.05, seed=5, lidar_density=0.3,
        ins_profile="hard", cameras=(),
    )  # fmt: skip
    return generate(tmp_path_factory.mktemp("accel") / "seq", cfg).folder


def test_the_accelerometers_of_a_synthetic_sequence_see_the_true_accelerations(
    sequence: Path,
) -> None:
    from geometry.poses import reexpress
    from worker.bench.matrix import _truth as matrix_truth

    inp = true_ego_input(sequence)
    health = Health()
    pb = build_problem(inp, health, FusedSigmas())
    assert pb.accel is not None
    world, truth, _ = matrix_truth(sequence)
    T = reexpress(truth, world, inp.world).interpolate(inp.times)
    c, p, R, n = pb.diff2, T[:, :3, 3], T[:, :3, :3], pb.n
    aw = sum(c[:, i : i + 1] * p[i : n - 2 + i] for i in range(3))
    true_a = np.einsum("nji,nj->ni", R[1 : n - 1], aw)
    ok = pb.accel["w"][:, 1] > 0
    assert ok.sum() >= n - 4  # the ends aside
    err = (pb.accel["meas"] - true_a)[ok]
    # hard profile: a constant bias of 3 mg per axis (1 sigma; 0.29 mm a stencil of 0.1 s)
    # that fused estimates, 0.15 m/s/sqrt(h) -> 0.8 mm/s a window, and the INS's lever
    # arm (0.4 m) turning with the body's sway
    offset = np.mean(err, axis=0)
    assert np.all(np.abs(offset) < 3 * 0.0294 * pb.accel["h2"]), offset / MM
    rms = np.sqrt(np.mean((err - offset) ** 2, axis=0))
    signal = np.sqrt(np.mean((true_a[ok] - np.mean(true_a[ok], axis=0)) ** 2, axis=0))
    assert rms[1] < 0.1 * MM and rms[2] < 0.3 * MM, (rms / MM, signal / MM)
    assert np.all(rms[1:] < 0.3 * signal[1:]), (rms / MM, signal / MM)


@pytest.fixture(scope="module")
def fused_lag1_sideways(sequence: Path) -> dict[bool, float]:
    """fused's lag-1 error sideways and up (mm, RMS), without and with the
    accelerometers."""
    inp = true_ego_input(sequence)
    from geometry.poses import reexpress
    from worker.bench.matrix import _truth as matrix_truth

    world, truth, _ = matrix_truth(sequence)
    Tt = reexpress(truth, world, inp.world).interpolate(inp.times)
    true_steps = np.einsum("nji,nj->ni", Tt[:-1, :3, :3], Tt[1:, :3, 3] - Tt[:-1, :3, 3])
    out = {}
    for accel in (False, True):
        inp.options["fused_accel"] = accel
        T = FusedStrategy().run(inp).track.interpolate(inp.times)
        steps = np.einsum("nji,nj->ni", T[:-1, :3, :3], T[1:, :3, 3] - T[:-1, :3, 3])
        e = (steps - true_steps)[:, 1:] / MM
        out[accel] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    return out


def test_fused_follows_the_sway_with_the_accelerometers(
    fused_lag1_sideways: dict[bool, float],
) -> None:
    # the sway moves the base 2-3 mm a frame sideways and up; without the accelerometers
    # fused follows little of it on this sparse station
    assert fused_lag1_sideways[True] < 1.5, fused_lag1_sideways
    assert fused_lag1_sideways[True] < 0.6 * fused_lag1_sideways[False], fused_lag1_sideways


def test_a_sequence_without_imu_records_runs_without_accelerometers(
    sequence: Path, tmp_path: Path
) -> None:
    folder = tmp_path / "seq"
    shutil.copytree(sequence, folder, ignore=shutil.ignore_patterns("novatel_oem7_corrimu"))
    inp = true_ego_input(folder)
    res = FusedStrategy().run(inp)
    assert "fused_variance_factor_accel" not in res.health.metrics
    assert not res.health.degraded, res.health.degraded


def _with_accel_bias(src: Path, dst: Path, column: str, mg: float) -> Path:
    """A copy of the sequence at ``src`` whose CORRIMU ``column`` (m/s per IMU sample at
    the synthetic 100 Hz) carries ``mg`` more."""
    return with_corrimu_added(src, dst, column, 9.80665e-3 * mg / 100.0)


@pytest.mark.slow
def test_an_accelerometer_bias_is_estimated_and_kept_out_of_the_poses(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    from geometry.poses import reexpress
    from worker.bench.matrix import _truth as matrix_truth
    from worker.synth.generator import SynthConfig, generate

    root = tmp_path_factory.mktemp("accel_bias")
    cfg = SynthConfig(
        scene="fire_site", frames=60, scale=0.05, seed=0, lidar_density=1.0,
        ins_profile="good", cameras=(),
    )  # fmt: skip
    clean = generate(root / "clean", cfg).folder
    # 10 mg along INS X: 0.1 mm a stencil, 18 cm over the 6 s if it went into the poses
    expected = float((np.array([10.0, 0.0, 0.0]) @ R_INS_BASE_NOMINAL)[1])
    biased = _with_accel_bias(clean, root / "biased", "lateral_acc", 10.0)
    got = {}
    for name, folder in (("clean", clean), ("biased", biased)):
        inp = true_ego_input(folder)
        world, truth, _ = matrix_truth(folder)
        Tt = reexpress(truth, world, inp.world).interpolate(inp.times)
        res = FusedStrategy().run(inp)
        T = res.track.interpolate(inp.times)
        lat = np.einsum("nj,nj->n", Tt[:-1, :3, 1], T[1:, :3, 3] - T[:-1, :3, 3])
        lat_true = np.einsum("nj,nj->n", Tt[:-1, :3, 1], Tt[1:, :3, 3] - Tt[:-1, :3, 3])
        got[name] = (
            res.health.metrics["fused_accel_bias_lateral_mg"],
            float(np.sqrt(np.mean((lat - lat_true) ** 2)) / MM),
        )
    seen = got["biased"][0] - got["clean"][0]
    assert abs(seen - expected) < 2.0, (expected, got)
    # the poses' lateral steps no worse than by a tenth of a millimetre
    assert got["biased"][1] < got["clean"][1] + 0.1, got
