"""First run: the key commands work on a fresh database (SQLite and PostgreSQL) without a
prior ``migrate``; an unusable database is one line, not a traceback; the demo's tables
say which RPE is the paper's and which is the true error."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text

from osdar_platform.settings import get_settings
from worker.cli import main
from worker.evaluation.tables import rpe_tables

PG_ADMIN = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


def test_keys_create_on_a_fresh_data_dir_database(fresh_data_dir: Path, capsys) -> None:
    assert not (fresh_data_dir / "osdar-ar.db").exists()
    assert main(["keys", "create", "alice"]) == 0
    secret = capsys.readouterr().out.strip()
    assert len(secret) >= 20 and "Traceback" not in secret
    assert main(["keys", "list"]) == 0
    assert "alice" in capsys.readouterr().out


def test_keys_create_on_a_fresh_postgres_schema(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    name = f"first_run_{uuid.uuid4().hex[:8]}"
    admin = create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as exc:  # pragma: no cover - the machine runs PostgreSQL
        pytest.fail(f"PostgreSQL on 127.0.0.1:5432 is needed: {exc}")
    try:
        monkeypatch.setenv("OSDAR_AR_DATA_DIR", str(tmp_path))
        monkeypatch.setenv("DATABASE_URL", f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}")
        get_settings.cache_clear()
        assert main(["keys", "create", "alice"]) == 0
        assert len(capsys.readouterr().out.strip()) >= 20
    finally:
        get_settings.cache_clear()
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def test_an_unusable_database_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.setenv("OSDAR_AR_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("DATABASE_URL", "postgresql+psycopg://nobody@127.0.0.1:1/none")
    get_settings.cache_clear()
    try:
        assert main(["keys", "create", "alice"]) == 2
    finally:
        get_settings.cache_clear()
    err = capsys.readouterr().err
    assert "not usable" in err and "osdar-ar migrate" in err and "Traceback" not in err


def test_demo_tables_name_the_paper_rpe_and_the_true_error_apart() -> None:
    ev = {
        "rpe": {
            "rgb_highres_center": {
                "rpe_px": {"mean": 2.7, "std": 0.4},
                "jitter_px": {"mean": 0.6, "std": 0.1},
            }
        }
    }
    gt = {
        "landmark_rpe": {
            "rgb_highres_center": {
                "auto": {
                    "rpe_px": {"mean": 12.5, "std": 1.0},
                    "jitter_px": {"mean": 0.9, "std": 0.2},
                }
            }
        }
    }
    lines = rpe_tables(ev, gt)
    paper = next(i for i, s in enumerate(lines) if "paper RPE" in s)
    true = next(i for i, s in enumerate(lines) if "true error" in s)
    assert paper < true
    assert "2.70" in " ".join(lines[paper:true]) and "12.50" not in " ".join(lines[paper:true])
    assert "12.50" in " ".join(lines[true:])


def test_demo_tables_show_the_paper_rpe_of_synthetic_clicks() -> None:
    """Without clicks of the user's, the evaluation clicks the synthetic landmarks and
    keeps the paper RPE per track under ``paper_rpe`` (worker/evaluation/evaluate.py):
    the demo's table shows every track's row (it printed the header alone)."""
    st = {"rpe_mean": 0.27, "rpe_std": 0.17, "jitter_mean": 0.048, "jitter_std": 0.035, "n": 59}
    ins = {"rpe_mean": 31.4, "rpe_std": 5.0, "jitter_mean": 2.1, "jitter_std": 1.0, "n": 59}
    ev = {"strategy": "fused", "paper_rpe": {"rgb_center": {"auto": st, "ins": ins}}}
    lines = rpe_tables(ev, {})
    rows = [s.split() for s in lines[2:]]
    assert rows == [
        ["rgb_center", "auto", "0.27", "±", "0.17", "0.05", "±", "0.04"],
        ["rgb_center", "ins", "31.40", "±", "5.00", "2.10", "±", "1.00"],
    ]
