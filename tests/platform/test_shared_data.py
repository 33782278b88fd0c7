"""``../shared`` is found beside the checkout, or where ``OSDAR_AR_SHARED`` says."""

from __future__ import annotations

from pathlib import Path

import pytest

from osdar_platform.shared_data import SHARED_ENV, real_labels_path, shared_dir


def test_default_is_beside_the_checkout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(SHARED_ENV, raising=False)
    assert shared_dir() == Path(__file__).resolve().parents[2].parent / "shared"


def test_environment_variable_overrides(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(SHARED_ENV, str(tmp_path))
    assert shared_dir() == tmp_path
    assert real_labels_path() == tmp_path / "data/osdar23/1_calibration_1.1_labels.json"
