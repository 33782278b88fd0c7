"""KISS-ICP on a slow train with a sparse lidar (issue 16): the heading must not drift.

A spinning lidar samples the scene in the same pattern every revolution; at 15 cm steps
a map holding the previous frames pulled point-to-point ICP towards the previous pose's
pattern and turned the heading about 30 mdeg every frame on a straight track
(tight_curve and station at 1.5 m/s, density 0.3: -577 and -909 mdeg at the end). The
odometry's map now takes a frame only once the train has moved on
(``kiss_process.LaggedKissICP``); these tests know the answer from the generator's
ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.synth_fixtures import true_poses_at
from worker.osdar.sequence import Sequence
from worker.preparation.kiss_process import LaggedKissICP, kiss_config
from worker.preparation.localization import make_input, run_strategy
from worker.preparation.localization import odometry as od

F64 = np.ndarray


def _generate(root: Path, scene: str) -> Path:
    """A 20-frame ``scene`` at 1.5 m/s (2.85 m), lidar density 0.3, no cameras, seed 2
    (the robustness matrix's cells use seeds 0 and 1)."""
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene=scene, frames=20, scale=0.05, seed=2, lidar_density=0.3,
        ins_profile="osdar23", speed_mps=1.5, cameras=(),
    )  # fmt: skip
    return generate(root / scene, cfg).folder


@pytest.fixture(scope="module")
def slow_sparse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """klein_flottbek: KISS-ICP's own map turned it by -0.63 deg (true turn 0)."""
    return _generate(tmp_path_factory.mktemp("slow"), "klein_flottbek")


@pytest.fixture(scope="module", params=["klein_flottbek", "fire_site"])
def slow_scene(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Path:
    """klein_flottbek as :func:`slow_sparse`; fire_site: +0.58 deg without the lag."""
    return _generate(tmp_path_factory.mktemp("slow"), str(request.param))


def _rotation_errors_deg(T_est: F64, T_true: F64, lag: int) -> F64:
    """(n - lag, 3) rotation vector (deg) of the relative rotation error over ``lag``."""
    a = np.swapaxes(T_est[:-lag, :3, :3], 1, 2) @ T_est[lag:, :3, :3]
    b = np.swapaxes(T_true[:-lag, :3, :3], 1, 2) @ T_true[lag:, :3, :3]
    return np.degrees(Rotation.from_matrix(np.swapaxes(b, 1, 2) @ a).as_rotvec())


def _odometry_T(folder: Path, **options: object) -> tuple[F64, F64]:
    inp = make_input(Sequence.open(folder), options=dict(options))
    res = run_strategy("odometry", inp)
    return res.track.T, true_poses_at(folder, np.asarray(inp.times, dtype=np.float64))


def test_slow_sparse_heading_does_not_drift(slow_scene: Path) -> None:
    T_est, T_true = _odometry_T(slow_scene)
    n = len(T_true)
    whole = _rotation_errors_deg(T_est, T_true, n - 1)[0]
    lag10 = _rotation_errors_deg(T_est, T_true, 10)
    # 0.15 deg over 2.85 m is 7.5 mm of lateral offset at the end; the pattern-locked map
    # gave about 0.03 deg a frame: -0.63 and +0.58 deg over these 19 steps, lag-10 RMS
    # 0.39 and 0.34 deg (with the lag: 0.000 and 0.027, 0.029 and 0.079)
    assert abs(whole[2]) < 0.15, whole
    assert float(np.sqrt(np.mean(lag10[:, 2] ** 2))) < 0.12, lag10[:, 2]
    # travelled distance within 5 % of the truth (the pattern lock also shortened it: 1.82
    # and 1.92 m of 2.85; with the lag 2.77 and 2.79 m)
    d_est = np.sum(np.linalg.norm(np.diff(T_est[:, :3, 3], axis=0), axis=1))
    d_true = np.sum(np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1))
    assert abs(d_est / d_true - 1.0) < 0.05, (d_est, d_true)


@pytest.mark.slow
def test_slow_sparse_without_the_lag_drifts(slow_scene: Path) -> None:
    """The case (KISS-ICP's own map, ``odometry_map_lag_m = 0``): it drifts, the lag
    removes at least three quarters of the end heading error."""
    T_off, T_true = _odometry_T(slow_scene, odometry_map_lag_m=0.0)
    T_on, _ = _odometry_T(slow_scene)
    n = len(T_true)
    off = _rotation_errors_deg(T_off, T_true, n - 1)[0, 2]
    on = _rotation_errors_deg(T_on, T_true, n - 1)[0, 2]
    assert abs(off) > 0.3, off
    assert abs(on) < 0.25 * abs(off), (on, off)


def _clouds(folder: Path, k: int) -> list[F64]:
    inp = make_input(Sequence.open(folder))
    return [od._frame_input(inp, f)[0] for f in inp.frames[:k]]


def test_zero_lag_is_kiss_icp(slow_sparse: Path) -> None:
    """``map_lag_m = 0`` registers as kiss-icp's KissICP."""
    from kiss_icp.kiss_icp import KissICP

    settings = od._kiss_settings(make_input(Sequence.open(slow_sparse)))
    cfg = kiss_config(settings)
    ours, theirs = LaggedKissICP(cfg, 0.0), KissICP(cfg)
    for p in _clouds(slow_sparse, 6):
        ours.register_frame(p, np.zeros(len(p)))
        theirs.register_frame(p, np.zeros(len(p)))
        # equal but for the order of kiss-icp's parallel sums (measured: < 5e-15)
        np.testing.assert_allclose(ours.last_pose, theirs.last_pose, rtol=0.0, atol=1e-9)


def test_map_takes_a_frame_once_the_train_moved_on(slow_sparse: Path) -> None:
    """Frames wait until the predicted pose is ``map_lag_m`` away; the first enters at once."""
    settings = od._kiss_settings(make_input(Sequence.open(slow_sparse)))
    kiss = LaggedKissICP(kiss_config(settings), 1.0)
    clouds = _clouds(slow_sparse, 10)
    step = np.eye(4)
    step[0, 3] = 0.15  # the generator's 1.5 m/s at 10 Hz
    pending = []
    for k, p in enumerate(clouds):
        if k:
            kiss.last_delta = step
        kiss.register_frame(p, np.zeros(len(p)))
        pending.append(len(kiss.pending))
    # frame 0 in the map before frame 1; a frame enters after about 1 m / 0.15 m steps
    assert pending[1] == 1, pending
    assert max(pending) <= 8, pending
    assert min(pending[7:]) >= 5, pending


def test_a_fast_train_keeps_kiss_icps_map(slow_sparse: Path) -> None:
    """At a predicted step of ``fast_step_m`` or more every frame enters before the next."""
    settings = od._kiss_settings(make_input(Sequence.open(slow_sparse)))
    kiss = LaggedKissICP(kiss_config(settings), 1.0, fast_step_m=0.5)
    step = np.eye(4)
    step[0, 3] = 0.6
    for k, p in enumerate(_clouds(slow_sparse, 4)):
        if k:
            kiss.last_delta = step
        kiss.register_frame(p, np.zeros(len(p)))
        assert len(kiss.pending) == 1, (k, len(kiss.pending))
