"""Results shared by every job on one prepared sequence (worker/orchestration/
shared_results.py): the evaluation and its plot are computed once and read back the same.

Known answers: the cached evaluation is exactly the direct one (after the JSON round trip
the job's metrics take in the database anyway); a second job on the same preparation and
cameras never calls the evaluation (it would raise here); other cameras are another entry.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.synth_fixtures import synth_sequence
from worker.evaluation.evaluate import evaluate_sequence
from worker.orchestration import shared_results
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare


def _forbidden(*_: object, **__: object) -> None:
    raise AssertionError("computed again although cached")


def test_the_evaluation_and_its_plot_are_computed_once(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    base = tmp_path_factory.mktemp("shared")
    folder = synth_sequence(base, "station_shared", frames=4, scale=0.05, lidar_density=0.1)
    cache = base / "cache"
    prepared = prepare(folder, PrepareConfig(strategy="ins"), cache_dir=cache / "prepared")
    cams = ["rgb_center"]

    metrics, series = shared_results.sequence_evaluation(folder, prepared, cams, cache_dir=cache)
    direct = json.loads(json.dumps(evaluate_sequence(folder, prepared, cams)))
    assert [metrics, series] == direct and series  # the synthetic sequence has ground truth
    files = sorted(p.name for p in (cache / "shared").iterdir())
    assert len(files) == 1 and files[0].startswith("evaluation-")

    monkeypatch.setattr(shared_results, "evaluate_sequence", _forbidden)
    again = shared_results.sequence_evaluation(folder, prepared, cams, cache_dir=cache)
    assert list(again) == [metrics, series]
    with pytest.raises(AssertionError, match="computed again"):
        shared_results.sequence_evaluation(folder, prepared, ["rgb_left"], cache_dir=cache)

    first = shared_results.rpe_plot(series, tmp_path_factory.mktemp("a") / "p.png", "t",
                                    cache_dir=cache)  # fmt: skip
    monkeypatch.setattr(shared_results, "plot_rpe_jitter", _forbidden)
    second = shared_results.rpe_plot(series, tmp_path_factory.mktemp("b") / "p.png", "t",
                                     cache_dir=cache)  # fmt: skip
    assert first is not None and second is not None
    assert Path(second).read_bytes() == Path(first).read_bytes()
    assert Path(first).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert shared_results.rpe_plot({}, base / "none.png", "t", cache_dir=cache) is None
