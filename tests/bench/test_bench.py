"""``osdar-ar bench``: the quick run CI executes writes the documented JSON keys.

The quick run (20-frame sequences at scale 0.1, lidar density 0.3, strategies ins and
fused, one extra voxel size, the I/O floor with one worker) takes about 1-2.5 minutes on a
2-core machine.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from worker.bench.paper import PAPER_TABLE, format_table, paper_band
from worker.bench.pareto import pareto_front

ROW_KEYS = {
    "sequence", "camera", "strategy", "rpe_mean", "rpe_std", "jitter_mean", "jitter_std",
    "seconds",
}  # fmt: skip


def test_pareto_front() -> None:
    rows = [
        {"config": "a", "seconds": 1.0, "error_px": 10.0},
        {"config": "b", "seconds": 2.0, "error_px": 5.0},
        {"config": "c", "seconds": 3.0, "error_px": 6.0},  # dominated by b
        {"config": "d", "seconds": 4.0, "error_px": 1.0},
        {"config": "e", "seconds": 5.0, "error_px": None},
    ]
    assert [r["config"] for r in pareto_front(rows)] == ["a", "b", "d"]


def test_paper_table_and_band() -> None:
    assert len(PAPER_TABLE) == 6
    assert paper_band("rgb_highres_center") == (31.4, 89.0)
    rows = [
        {"sequence": "3_fire_site_3.1", "camera": "rgb_center", "strategy": "ins",
         "rpe_mean": 5.0, "rpe_std": 1.0, "jitter_mean": 0.5, "jitter_std": 0.1},
    ]  # fmt: skip
    text = format_table(rows, ["ins"])
    assert "5.0±1.0 [81.3±50.1]" in text and "0.50±0.10 [2.71±3.16]" in text


@pytest.mark.slow
def test_bench_quick_json(tmp_path: Path) -> None:
    from worker.cli import main

    out, md = tmp_path / "bench.json", tmp_path / "bench.md"
    argv = ["bench", "--quick", "--json", str(out), "--markdown", str(md)]
    assert main([*argv, "--workdir", str(tmp_path / "w")]) == 0
    res = json.loads(out.read_text())
    report = md.read_text()
    assert res["provenance"] in report and "## Figures" in report
    fused_c2 = next(
        r for r in res["rows"] if r["strategy"] == "fused" and r["camera"] == "rgb_highres_center"
    )
    assert f"{fused_c2['rpe_mean']:.1f}±{fused_c2['rpe_std']:.1f}" in report
    assert {"rows", "pareto", "floor_ratio"} <= set(res)
    assert len(res["rows"]) == 3 * 2 * 2  # sequences x cameras x strategies
    for r in res["rows"]:
        assert ROW_KEYS <= set(r), r
        assert r["seconds"] > 0
        for k in ("rpe_mean", "rpe_std", "jitter_mean", "jitter_std"):
            assert r[k] is not None and math.isfinite(r[k]) and r[k] >= 0, (k, r)
    assert {r["sequence"] for r in res["rows"]} == {
        "3_fire_site_3.1", "5_station_bergedorf_5.1", "6_station_klein_flottbek_6.2",
    }  # fmt: skip
    assert res["pareto"] and all({"config", "seconds", "error_px"} <= set(p) for p in res["pareto"])
    assert res["floor_ratio"] is not None and res["floor_ratio"] > 0
    assert (tmp_path / "w" / "pareto.png").is_file()
    assert (tmp_path / "w" / "per_frame" / "fire_site.csv").is_file()


@pytest.mark.slow
@pytest.mark.gl
def test_bench_hard_json(tmp_path: Path) -> None:
    """``--hard --quick`` writes one row per case with the documented keys."""
    from worker.cli import main

    out, md = tmp_path / "hard.json", tmp_path / "hard.md"
    argv = ["bench", "--hard", "--quick", "--json", str(out), "--markdown", str(md)]
    main([*argv, "--workdir", str(tmp_path / "w")])
    cases = json.loads(out.read_text())["hard_cases"]
    assert md.read_text().count("\n| ") == 1 + len(cases)  # the header row, one per case
    assert [c["case"] for c in cases] == list(range(1, 13))
    for c in cases:
        assert {"title", "degrades", "warning", "error", "bound", "unit", "ok"} <= set(c)


def test_floor_with_a_process_pool(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """The full bench's floor runs in a pool of 2: its functions must unpickle there."""
    from tests.synth_fixtures import synth_sequence
    from worker.bench.floor import measure_floor
    from worker.osdar.sequence import Sequence

    # the station sequence the preparation tests share (generated once per session)
    seq = Sequence.open(synth_sequence(tmp_path_factory.getbasetemp()))
    frames = seq.frame_indices[:4]
    streams = [seq.cameras[0]] + ([seq.lidar_stream] if seq.lidar_stream else [])
    seconds = measure_floor(seq, frames, streams, 2, 1, tmp_path / "floor")
    assert 0.0 < seconds < 120.0
    assert not (tmp_path / "floor").exists()  # nothing left behind


def _paper_result() -> dict[str, object]:
    rows = [
        {"sequence": "3_fire_site_3.1", "camera": "rgb_highres_center", "strategy": st,
         "rpe_mean": rpe, "rpe_std": 1.0, "jitter_mean": 0.25, "jitter_std": 0.1,
         "seconds": sec}
        for st, rpe, sec in (("ins", 44.5, 0.5), ("fused", 1.25, 9.0))
    ]  # fmt: skip
    return {
        "quick": True, "provenance": "osdar-ar 9.9, commit abc1234, 2026-01-01, 2 cores.",
        "settings": {"frames": 20, "lidar_density": 0.3, "ins_profile": "osdar23", "seed": 0,
                     "strategies": ["ins", "fused"]},
        "rows": rows, "seconds": 61.0,
        "goal": {"camera": "rgb_highres_center", "best_strategy": "fused", "best_rpe_mean": 1.25,
                 "best_jitter_mean": 0.25, "rpe_goal": 3.0, "jitter_goal": 0.5, "met": True,
                 "ins_rpe_mean": 44.5, "ins_paper_band": [31.4, 89.0]},
        "pareto_all": [{"config": "fused@0.1", "seconds": 9.0, "error_px": 1.25,
                        "jitter_px": 0.25}],
        "pareto": [{"config": "fused@0.1", "seconds": 9.0, "error_px": 1.25}],
    }  # fmt: skip


def test_report_from_json_keeps_the_prose_and_stamps_the_figures(tmp_path: Path) -> None:
    """``bench --report JSON --markdown MD`` regenerates the figures below '## Figures' and
    keeps what is above; the stamp is the one recorded in the JSON, not today's."""
    from worker.cli import main

    saved = tmp_path / "bench.json"
    saved.write_text(json.dumps(_paper_result()))
    md = tmp_path / "paper.md"
    md.write_text("# The paper table\n\nHand-written method text.\n\n## Figures\n\nold figures\n")
    assert main(["bench", "--report", str(saved), "--markdown", str(md)]) == 0
    text = md.read_text()
    assert text.startswith("# The paper table\n\nHand-written method text.\n\n## Figures\n")
    assert "old figures" not in text
    assert "commit abc1234, 2026-01-01" in text
    assert "44.5±1.0 [89.0±92.0]" in text  # ours beside the paper's, ins on 3.1 C2
    assert "| ins | 44.5 | 89.0 | 0.50 |" in text  # ours / paper
    assert "**met**" in text and "inside" in text
    assert "| fused@0.1 | 9.0 | 1.25 | 0.25 | * |" in text


def test_report_of_hard_cases_marks_a_miss(tmp_path: Path) -> None:
    from worker.bench.report import bench_markdown

    cases = [
        {"case": 1, "title": "far origin", "error": 4.8e-8, "bound": 0.1, "unit": "px",
         "ok": True, "warning": "", "degrades": "float32 | UTM"},
        {"case": 2, "title": "standing still", "error": 0.9, "bound": 0.7, "unit": "m",
         "ok": False, "warning": "standstill", "degrades": "heading"},
    ]  # fmt: skip
    title, text = bench_markdown({"quick": False, "hard_cases": cases, "seconds": 5.0})
    assert title == "The hard cases"
    assert "1 of 2 cases within their bounds" in text
    assert "| 1 | far origin | 4.8e-08 | 0.1 | px | ok | - | float32 / UTM |" in text
    assert "| 2 | standing still | 0.9 | 0.7 | m | **MISS** | standstill | heading |" in text


@pytest.mark.parametrize(
    ("content", "needle"),
    [("not json", "not a readable bench JSON"), ('{"cells": []}', "no 'rows' or 'hard_cases'")],
)
def test_report_refuses_what_is_not_a_bench_json(
    tmp_path: Path, content: str, needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from worker.cli import main

    saved = tmp_path / "x.json"
    saved.write_text(content)
    md = tmp_path / "out.md"
    assert main(["bench", "--report", str(saved), "--markdown", str(md)]) != 0
    assert needle in capsys.readouterr().err
    assert not md.exists()
