"""The robustness matrix: its design covers every level of every factor, and a small run
measures what it says (known answers on a standing train), reports every goal, writes a
heatmap."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from worker.bench.matrix import (
    DENSITIES,
    GOALS,
    LENGTHS,
    PROFILES,
    SCENES,
    SEEDS,
    STRATEGIES,
    Cell,
    design,
    format_summary,
    plot_heatmap,
    plot_paper_floor,
    run_matrix,
)


@pytest.mark.parametrize("quick", [False, True])
def test_design_has_every_level_of_every_factor(quick: bool) -> None:
    cells = design(quick)
    assert len({c.name for c in cells}) == len(cells)
    assert {c.scene for c in cells} == set(SCENES)
    assert {c.density for c in cells} == set(DENSITIES)
    assert {c.profile for c in cells} == set(PROFILES)
    assert {c.seed for c in cells} == set(SEEDS)
    assert {"moving", "slow", "stationary"} <= {c.motion for c in cells}
    lengths = {c.frames for c in cells}
    assert lengths == set(LENGTHS) if not quick else lengths >= {10, 20, 35, 60}
    if not quick:
        assert any(c.merge_error is False for c in cells)


def test_a_seed_offset_gives_the_same_cells_on_fresh_seeds() -> None:
    base, fresh = design(), design(seed_offset=10)
    assert [c.seed + 10 for c in base] == [c.seed for c in fresh]
    assert {c.seed for c in fresh}.isdisjoint(SEEDS)
    strip = [(c.scene, c.frames, c.density, c.profile, c.motion) for c in base]
    assert strip == [(c.scene, c.frames, c.density, c.profile, c.motion) for c in fresh]


STILL = Cell("stationary", 10, 0.3, "osdar23", 0, "stationary")
MOVING = Cell("fire_site", 12, 0.3, "good", 1)


@pytest.fixture(
    scope="module",
    params=["still", pytest.param("still_and_moving", marks=pytest.mark.slow)],
)
def small_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The matrix on a standing train's cell (5 s), and in make test also with a moving
    train's (10 s more): every test below runs on both runs there."""
    cells = [STILL] if request.param == "still" else [STILL, MOVING]
    return run_matrix(tmp_path_factory.mktemp("matrix"), cells=cells)


def test_a_standing_train_has_no_relative_pose_error(small_run: dict) -> None:
    still = next(c for c in small_run["cells"] if c["cell"]["motion"] == "stationary")
    fused = still["strategies"]["fused"]["rpe"]["1"]
    assert fused["t_mean_m"] < 1e-3 and fused["r_mean_deg"] < 1e-3
    # the raw INS wanders by centimetres between frames (osdar23 profile)
    assert still["strategies"]["ins"]["rpe"]["1"]["t_mean_m"] > 0.01
    # a 10-frame sequence has no lag-30 pair: reported as None, not as 0
    assert still["strategies"]["fused"]["rpe"]["30"]["t_mean_m"] is None


def test_every_cell_measures_every_strategy_and_camera(small_run: dict) -> None:
    assert not small_run["failed_cells"]
    for c in small_run["cells"]:
        assert set(c["strategies"]) == set(STRATEGIES)
        for s in STRATEGIES:
            anchor = c["strategies"][s]["anchor"]
            assert set(anchor) == {"rgb_center", "rgb_highres_center"}
            assert anchor["rgb_highres_center"]["frames"] > 0
        bound = c["strategies"]["auto"]["anchor"]["rgb_highres_center"]
        assert bound["bound_frames"] > 0 and bound["bound_median_px"] > 0


def test_summary_reports_every_goal_and_a_heatmap(small_run: dict, tmp_path: Path) -> None:
    goals = small_run["summary"]["goals"]
    for name in (
        "moving_c2_rpe_p90_px", "fused_within_10pct_of_inputs", "auto_within_1p25_of_best",
        "confidence_bound_coverage", "confidence_bound_looseness", "ins_in_paper_band_osdar23",
    ):  # fmt: skip
        assert "ok" in goals[name], name
    assert goals["confidence_bound_coverage"]["bound"] == GOALS["bound_coverage"]
    text = format_summary(small_run)
    assert "goals" in text and ("MISS" in text or "ok" in text)
    json.dumps(small_run)  # JSON-able
    png = plot_heatmap(small_run, tmp_path / "m.png")
    assert png.stat().st_size > 1000


def test_the_paper_rpe_floor_is_the_same_measure_with_the_true_poses(
    small_run: dict, tmp_path: Path
) -> None:
    """The floor is the paper measure on the same clicks with the true poses: a point
    fixed in the world seen from a standing train's true poses keeps its offset from the
    clicks, so its jitter there is nil (the offset itself is the cloud's sampling)."""
    c2 = "rgb_highres_center"
    for c in small_run["cells"]:
        floor, auto = c["paper_floor"][c2], c["strategies"]["auto"]["paper"][c2]
        assert floor["n"] == auto["n"] > 0 and floor["rpe_mean"] >= 0.0
    still = next(c for c in small_run["cells"] if c["cell"]["motion"] == "stationary")
    assert still["paper_floor"][c2]["jitter_mean"] < 0.05
    g = small_run["summary"]["goals"]["short_c2_rpe_p90_px"]
    assert g["floor_p90"] is not None and isinstance(g["cells_floor_above_bound"], list)
    assert plot_paper_floor(small_run, tmp_path / "f.png").stat().st_size > 1000


@pytest.mark.slow
def test_cli_quick_matrix_writes_json_markdown_and_heatmap(tmp_path: Path, capsys) -> None:
    """``osdar-ar bench --matrix --quick``: the documented CI subset, end to end."""
    from worker.cli import main

    out_json, out_md = tmp_path / "m.json", tmp_path / "m.md"
    rc = main(
        ["bench", "--matrix", "--quick", "--json", str(out_json), "--markdown", str(out_md),
         "--workdir", str(tmp_path / "w")]
    )  # fmt: skip
    assert rc == 0
    result = json.loads(out_json.read_text())
    assert len(result["cells"]) == len(design(True)) and not result["failed_cells"]
    text = out_md.read_text()
    assert "| fused |" in text and ("MISS" in text or "| ok |" in text)
    assert (tmp_path / "figures" / "m.png").stat().st_size > 1000
    assert "figures/m.png" in text and "commit " in text
    assert "goals" in capsys.readouterr().out


def test_a_regenerated_report_keeps_its_method_text(small_run, tmp_path: Path) -> None:
    """The documented command rewrites docs/robustness_matrix.md: the text above its
    figures stays, the old figures go, the new ones carry version, commit and date."""
    from worker.bench.matrix import FIGURES_HEADING, report_text

    md = tmp_path / "report.md"
    md.write_text(f"# Title\n\nHow it is measured.\n\n{FIGURES_HEADING}\n\nOLD FIGURES\n")
    text = report_text(md, small_run, tmp_path / "figures" / "report.png")
    assert text.startswith("# Title\n\nHow it is measured.\n\n## Figures\n\n")
    assert "OLD FIGURES" not in text and "| fused |" in text
    assert "osdar-ar " in text and ", commit " in text
    fresh = report_text(tmp_path / "new.md", small_run, tmp_path / "figures" / "new.png")
    assert fresh.startswith("# The robustness matrix") and "figures/new.png" in fresh
