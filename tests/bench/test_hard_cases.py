"""The 12 hard cases of BENCHMARK.md, collected by case (worker/bench/hard_cases.py).

Each case finishes with finite numbers, gives its warning where the method degrades, and
stays within its stated bound (the bound is in the case's row: ``osdar-ar bench --hard``).
Many cases already have detailed tests elsewhere; ``EXISTING_TESTS`` lists them by case and
``test_existing_tests_exist`` keeps that list honest. The rows here run the reduced form
(20-frame sequences; the sequence cases' rows are marked slow, their own tests stay in the
quick set); ``OSDAR_FULL=1`` adds the full form (60 frames, marked slow).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from worker.bench.hard_cases import CASES, EXISTING_TESTS, GL_CASES, HardContext, run_case

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> HardContext:
    return HardContext(tmp_path_factory.mktemp("hard"), reduced=True)


def test_every_case_is_collected() -> None:
    assert sorted(CASES) == list(range(1, 13))
    assert set(EXISTING_TESTS) <= set(CASES)
    assert SEQUENCE_CASES <= set(EXISTING_TESTS)  # what the quick set keeps of them


def test_existing_tests_exist() -> None:
    for case, node_ids in EXISTING_TESTS.items():
        for node in node_ids:
            path, _, name = node.partition("::")
            text = (ROOT / path).read_text()
            if name:
                assert re.search(rf"^def {re.escape(name)}\(", text, re.M), (case, node)


#: The sequence cases (a 20-frame synthetic sequence and every localization strategy on it,
#: 2-5 s each): their rows run in ``make test``; the quick set keeps the cases' own tests
#: (EXISTING_TESTS: the same detections and bounds on the localization and rails tests'
#: sequences) and the rows of the geometry and rendering cases.
SEQUENCE_CASES = {2, 3, 4, 5, 6, 10}


def _params() -> list:
    return [
        pytest.param(
            n,
            marks=([pytest.mark.gl] if n in GL_CASES else [])
            + ([pytest.mark.slow] if n in SEQUENCE_CASES else []),
            id=f"case{n:02d}",
        )
        for n in sorted(CASES)
    ]


@pytest.mark.parametrize("n", _params())
def test_hard_case_within_bound(ctx: HardContext, n: int) -> None:
    row = run_case(n, ctx)
    assert row["ok"], row
    assert row["error"] is not None and row["error"] <= row["bound"]
    assert row["degrades"] and row["warning"]


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("OSDAR_FULL"), reason="full form: OSDAR_FULL=1")
@pytest.mark.parametrize("n", [2, 3, 4, 5, 6, 10, 12])
def test_hard_case_full_form(tmp_path_factory: pytest.TempPathFactory, n: int) -> None:
    row = run_case(n, HardContext(tmp_path_factory.mktemp(f"hard_full{n}"), reduced=False))
    assert row["ok"], row
