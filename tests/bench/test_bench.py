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

    out = tmp_path / "bench.json"
    assert main(["bench", "--quick", "--json", str(out), "--workdir", str(tmp_path / "w")]) == 0
    res = json.loads(out.read_text())
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

    out = tmp_path / "hard.json"
    main(["bench", "--hard", "--quick", "--json", str(out), "--workdir", str(tmp_path / "w")])
    cases = json.loads(out.read_text())["hard_cases"]
    assert [c["case"] for c in cases] == list(range(1, 13))
    for c in cases:
        assert {"title", "degrades", "warning", "error", "bound", "unit", "ok"} <= set(c)


def test_floor_with_a_process_pool(tmp_path: Path) -> None:
    """The full bench's floor runs in a pool of 2: its functions must unpickle there."""
    from tests.synth_fixtures import synth_sequence
    from worker.bench.floor import measure_floor
    from worker.osdar.sequence import Sequence

    seq = Sequence.open(synth_sequence(tmp_path))
    frames = seq.frame_indices[:4]
    streams = [seq.cameras[0]] + ([seq.lidar_stream] if seq.lidar_stream else [])
    seconds = measure_floor(seq, frames, streams, 2, 1, tmp_path / "floor")
    assert 0.0 < seconds < 120.0
    assert not (tmp_path / "floor").exists()  # nothing left behind
