"""fused's ground-pair drifts: where the merged cloud's lidars disagree (the osdar23
profile merges its lidars with calibration errors, as real clouds are), the ground two
frames share comes from different lidars in each, and the pairs' roll is off in
proportion to the distance between the frames; the longer pairs' pitch is too. Each
drift is a state of the solve; the gyros tell the roll drift from the track's own roll,
the lag-1 pairs and the gyros the pitch drift from the track's grade."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.synth_fixtures import true_poses_at
from worker.osdar.sequence import Sequence
from worker.preparation.config import PrepareConfig
from worker.preparation.localization.base import Health, LocalizationInput
from worker.preparation.localization.fused import FusedStrategy, Sigmas, _ground_constraints
from worker.preparation.prepare import localization_setup


@pytest.fixture(scope="module")
def merged_with_errors(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, LocalizationInput]:
    """A sparse straight (30 frames, osdar23 INS and lidar merge errors, no cameras)."""
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene="straight_sparse", frames=30, scale=0.05, seed=11, lidar_density=0.3,
        ins_profile="osdar23", cameras=(),
    )  # fmt: skip
    folder = generate(tmp_path_factory.mktemp("ground_tilt") / "seq", cfg).folder
    return folder, localization_setup(Sequence.open(folder), PrepareConfig()).inp


def _relative_tilt_error_mdeg(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(2,) the largest roll and pitch error of frame k relative to frame 0 (mdeg)."""
    rel_e = np.linalg.inv(T_est[0]) @ T_est
    rel_t = np.linalg.inv(T_true[0]) @ T_true
    E = np.swapaxes(rel_t[:, :3, :3], 1, 2) @ rel_e[:, :3, :3]
    return 1e3 * np.degrees(np.max(np.abs(Rotation.from_matrix(E).as_rotvec()[:, :2]), axis=0))


def _pair_errors(folder: Path, inp: LocalizationInput) -> tuple[dict, np.ndarray, np.ndarray]:
    """The ground pairs, their rotation errors (P, 3) against the truth (rotation vector of
    frame j in frame k, rad) and the true distances (P,) between their frames (m)."""
    T = true_poses_at(folder, inp.times)
    g = _ground_constraints(inp, Health(), Sigmas())
    assert g is not None
    T_k_j = np.linalg.inv(T[g["k"]]) @ T[g["j"]]
    err = Rotation.from_matrix(
        np.swapaxes(T_k_j[:, :3, :3], 1, 2) @ g["T_k_j"][:, :3, :3]
    ).as_rotvec()
    return g, err, T_k_j[:, 0, 3]


def _drift_mdeg_per_m(err: np.ndarray, d: np.ndarray) -> float:
    """The errors' (P,) drift per metre of the distances (P,) (least squares through 0)."""
    return float(1e3 * np.degrees(np.sum(err * d) / np.sum(d * d)))


def _with_and_without(
    inp: LocalizationInput, T: np.ndarray, off: Sigmas
) -> tuple[dict, np.ndarray, dict, np.ndarray]:
    """fused's health metrics and worst relative (roll, pitch) errors (mdeg) with the
    default sigmas and with ``off``."""
    out = []
    for sig in (Sigmas(), off):
        res = FusedStrategy(sig).run(inp)
        out += [res.health.metrics, _relative_tilt_error_mdeg(res.track.interpolate(inp.times), T)]
    return tuple(out)  # type: ignore[return-value]


def test_the_ground_pairs_drift_and_the_solve_measures_it(merged_with_errors) -> None:
    folder, inp = merged_with_errors
    T = true_poses_at(folder, inp.times)
    _, err, d = _pair_errors(folder, inp)
    true_drift = _drift_mdeg_per_m(err[:, 0], d)  # the roll's
    assert abs(true_drift) > 1.0  # mdeg/m: 30 mdeg over a 20 m lag-10 pair
    metrics, worst, metrics_0, worst_0 = _with_and_without(inp, T, Sigmas(ground_tilt=0.0))
    est = metrics["fused_ground_tilt_roll_mdeg_per_m"]
    assert est == pytest.approx(true_drift, abs=0.3 * abs(true_drift))
    # with it the roll over the sequence follows the gyros; without, the pairs' drift
    assert worst[0] < 10.0, worst
    assert worst_0[0] > 4.0 * worst[0], (worst, worst_0)
    assert "fused_ground_tilt_roll_mdeg_per_m" not in metrics_0


def test_the_longer_pairs_pitch_drift_is_a_state_of_its_own(merged_with_errors) -> None:
    """The lag-10 pairs' pitch is off in proportion to the distance between their frames
    (here -0.40 mdeg/m against the lag-1 pairs' -0.08): the state takes it, and the
    lag-1 pairs and the gyros keep the pitch over the sequence."""
    folder, inp = merged_with_errors
    T = true_poses_at(folder, inp.times)
    g, err, d = _pair_errors(folder, inp)
    lag = g["j"] - g["k"]
    long = g["long"] > 0
    assert np.array_equal(long, lag > lag.min())
    true_drift = _drift_mdeg_per_m(err[long, 1], d[long])  # the long pairs' pitch's
    assert abs(true_drift) > 0.2  # mdeg/m: 4 mdeg over a 20 m lag-10 pair
    off = Sigmas(ground_pitch_drift=0.0)
    metrics, worst, metrics_0, worst_0 = _with_and_without(inp, T, off)
    est = metrics["fused_ground_pitch_drift_mdeg_per_m"]
    assert est == pytest.approx(true_drift, abs=0.25 * abs(true_drift))
    assert worst[1] < 6.0, worst
    assert worst_0[1] > 3.0 * worst[1], (worst, worst_0)
    assert "fused_ground_pitch_drift_mdeg_per_m" not in metrics_0
