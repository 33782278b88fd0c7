"""A run shorter than the odometry pairs' shortest lag (10 frames) gets one pair over its
whole length (``Sigmas.odo_pair_whole_run``): without it the only lateral reference beyond
KISS-ICP's steps was the gyros' heading, whose noise the rail motion carries sideways.
Not where the odometry is degenerate along the track (a straight without structure along
it), where a registration's lateral moves with its along-track start.
The answer is the generator's ground truth; seed 7 is none of the robustness matrix's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.synth_fixtures import true_ego_input, true_poses_at
from worker.preparation.localization.base import Health
from worker.preparation.localization.fused import (
    MIN_WHOLE_RUN_LAG,
    FusedStrategy,
    Sigmas,
    _odometry_pairs,
)


def _sequence(root: Path, scene: str, density: float) -> Path:
    from worker.synth.generator import SynthConfig, generate

    cfg = SynthConfig(
        scene=scene, frames=10, scale=0.05, seed=7, lidar_density=density,
        ins_profile="osdar23", cameras=(),
    )  # fmt: skip
    return generate(root / scene, cfg).folder


@pytest.fixture(scope="module")
def short_runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("short_run")
    return [_sequence(root, "fire_site", 0.3), _sequence(root, "klein_flottbek", 1.0)]


@pytest.fixture(scope="module")
def straight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sequence(tmp_path_factory.mktemp("short_straight"), "straight_sparse", 1.0)


def _end_error_mm(T: np.ndarray, T_true: np.ndarray) -> float:
    """(mm) the error of the last frame's position across the track in the first frame."""

    def lateral(T: np.ndarray) -> float:
        return float(T[0, :3, 1] @ (T[-1, :3, 3] - T[0, :3, 3]))

    return 1000.0 * abs(lateral(T) - lateral(T_true))


def test_a_short_run_gets_one_pair_over_its_length(short_runs: list[Path]) -> None:
    inp = true_ego_input(short_runs[0])
    n = len(inp.frames)
    sig = Sigmas()
    w_t, w_r = np.full((n - 1, 3), 1 / sig.odo_t), np.full((n - 1, 3), 1 / sig.odo_r)
    still = np.zeros(n - 1, dtype=bool)
    pairs = _odometry_pairs(inp, w_t, w_r, still, False, Health(), Sigmas(scan_pairs=False))
    assert pairs is not None
    assert list(pairs["k"]) == [0] and list(pairs["j"]) == [n - 1]
    off = _odometry_pairs(
        inp, w_t, w_r, still, False, Health(), Sigmas(scan_pairs=False, odo_pair_whole_run=False)
    )
    assert off is None  # the default lags (10, 30) do not fit 10 frames
    assert n - 1 >= MIN_WHOLE_RUN_LAG
    # a lag that fits stays, the one that does not becomes the whole run beside it
    both = _odometry_pairs(
        inp, w_t, w_r, still, False, Health(), Sigmas(scan_pairs=False, odo_pair_lags=(5, 30))
    )
    assert both is not None
    assert sorted(set((both["j"] - both["k"]).tolist())) == [5, n - 1]
    # none on a degenerate run, none when no lag is asked for
    assert _odometry_pairs(inp, w_t, w_r, still, True, Health(), Sigmas(scan_pairs=False)) is None
    none = Sigmas(scan_pairs=False, odo_pair_lags=())
    assert _odometry_pairs(inp, w_t, w_r, still, False, Health(), none) is None


def test_the_pair_holds_a_short_run_across_the_track(short_runs: list[Path]) -> None:
    # Design: the pair's lateral sigma is 5-8 mm (a scan pair or KISS-ICP's over 9
    # frames), so the end of a 10-frame run stays within 5 mm of the truth across the
    # track. Measured: fire_site 6.4 -> 1.2 mm, klein_flottbek 3.0 -> 2.1.
    errors = {}
    for folder in short_runs:
        inp = true_ego_input(folder)
        T_true = true_poses_at(folder, np.asarray(inp.times))
        without = FusedStrategy(Sigmas(odo_pair_whole_run=False)).run(inp)
        with_pair = FusedStrategy().run(true_ego_input(folder))
        assert with_pair.health.metrics.get("fused_odometry_pairs") == 1.0
        errors[folder.name] = (
            _end_error_mm(without.track.T, T_true),
            _end_error_mm(with_pair.track.T, T_true),
        )
    assert all(e1 < 5.0 for _, e1 in errors.values()), errors
    assert sum(e1 for _, e1 in errors.values()) < sum(e0 for e0, _ in errors.values()), errors


def test_no_whole_run_pair_where_the_odometry_is_degenerate(straight: Path) -> None:
    res = FusedStrategy().run(true_ego_input(straight))
    assert "fused_odometry_pairs" not in res.health.metrics
    assert any("degenerate along the track" in w for w in res.health.warnings)
