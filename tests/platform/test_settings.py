"""The one settings class: derived defaults, plain env names, the relations it enforces."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from osdar_platform.settings import DEFAULT_PEPPER, Settings, get_settings


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in (
        "DATABASE_URL",
        "BROKER_URL",
        "STORE_URL",
        "AWS_ACCESS_KEY_ID",
        "AWS_SECRET_ACCESS_KEY",
        "S3_ENDPOINT_URL",
    ):
        monkeypatch.delenv(name, raising=False)
        monkeypatch.delenv(f"OSDAR_AR_{name}", raising=False)


def test_embedded_defaults_live_under_data_dir(tmp_path: Path) -> None:
    s = Settings(data_dir=tmp_path)
    assert s.database_url == f"sqlite:///{tmp_path}/osdar-ar.db"
    assert s.broker_url == f"sqla+sqlite:///{tmp_path}/broker.db"
    assert s.store_url == f"file://{tmp_path.resolve()}/store"
    assert s.cache_dir == tmp_path / "cache" and s.sequences_dir == tmp_path / "sequences"
    assert s.environment == "dev" and s.is_sqlite


def test_plain_and_prefixed_env_names(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DATABASE_URL", "postgresql://u@db/osdar")
    monkeypatch.setenv("BROKER_URL", "redis://redis:6379/0")
    monkeypatch.setenv("STORE_URL", "s3://bucket/prefix")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "AK")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "SK")
    monkeypatch.setenv("S3_ENDPOINT_URL", "http://minio:9000")
    monkeypatch.setenv("OSDAR_AR_MAX_CONCURRENT_JOBS_PER_KEY", "7")
    s = Settings()
    assert s.database_url == "postgresql://u@db/osdar" and s.broker_url == "redis://redis:6379/0"
    assert s.store_url == "s3://bucket/prefix" and s.s3_endpoint_url == "http://minio:9000"
    assert s.aws_access_key_id == "AK" and s.aws_secret_access_key.get_secret_value() == "SK"
    assert s.max_concurrent_jobs_per_key == 7
    assert "SK" not in repr(s)  # secrets stay out of logs
    monkeypatch.setenv("OSDAR_AR_DATABASE_URL", "sqlite:///x.db")
    assert Settings().database_url == "sqlite:///x.db"  # the prefixed name wins


def test_visibility_timeout_must_exceed_the_longest_task() -> None:
    """RELIABILITY: a broker redelivers after the visibility timeout; shorter than a task's
    time limit plus margin, and a running job is delivered twice."""
    s = Settings()
    assert s.visibility_timeout_s >= s.task_time_limit_s + s.visibility_margin_s
    assert s.task_soft_time_limit_s < s.task_time_limit_s
    with pytest.raises(ValidationError, match="visibility_timeout_s"):
        Settings(task_time_limit_s=7200, task_soft_time_limit_s=7000, visibility_timeout_s=7300)
    with pytest.raises(ValidationError, match="task_soft_time_limit_s"):
        Settings(task_time_limit_s=100, task_soft_time_limit_s=100)


def test_prod_refuses_default_secret_and_sqlite(tmp_path: Path) -> None:
    with pytest.raises(ValidationError) as err:
        Settings(environment="prod", data_dir=tmp_path)
    msg = str(err.value)
    assert "PEPPER" in msg and "SQLite" in msg and "SEQUENCE_ROOTS" in msg
    assert "DASHBOARD_SECRET" in msg
    ok = Settings(
        environment="prod",
        database_url="postgresql://u@db/osdar",
        broker_url="redis://redis:6379/0",
        api_key_pepper="a-real-secret",
        dashboard_secret="another-real-secret",
        sequence_roots=[tmp_path],
    )
    assert ok.api_key_pepper.get_secret_value() != DEFAULT_PEPPER


@pytest.mark.parametrize(
    "bad",
    [
        {"store_url": "ftp://x"},
        {"environment": "staging"},
        {"max_concurrent_jobs_per_key": 0},
        {"rate_limit_per_s": -1},
    ],
)
def test_bad_values_stop_the_start(bad: dict) -> None:
    with pytest.raises(ValidationError):
        Settings(**bad)


def test_get_settings_is_cached(monkeypatch: pytest.MonkeyPatch) -> None:
    get_settings.cache_clear()
    try:
        assert get_settings() is get_settings()
    finally:
        get_settings.cache_clear()


def test_the_workers_cache_has_one_source(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """OSDAR_AR_CACHE_DIR is read by Settings only; the render-setup cache follows it."""
    from worker.augmentation.pool import default_setup_cache

    monkeypatch.setenv("OSDAR_AR_DATA_DIR", str(tmp_path / "data"))
    get_settings.cache_clear()
    try:
        assert default_setup_cache() == tmp_path / "data" / "cache" / "render_setup"
        monkeypatch.setenv("OSDAR_AR_CACHE_DIR", str(tmp_path / "c"))
        get_settings.cache_clear()
        assert default_setup_cache() == tmp_path / "c" / "render_setup"
    finally:
        get_settings.cache_clear()


def test_celery_side_agrees_with_the_catalog() -> None:
    """The names the API validates against are the pipeline's own."""
    from osdar_platform.catalog import STRATEGIES
    from worker.preparation.localization import STRATEGIES as PIPELINE_STRATEGIES

    assert tuple(STRATEGIES) == tuple(PIPELINE_STRATEGIES)


def test_one_prepared_cache_for_workers_and_cli(monkeypatch: pytest.MonkeyPatch) -> None:
    """``$OSDAR_AR_CACHE_DIR`` is the workers' cache; prepared sequences live in its
    ``prepared/``, for the job runner and ``osdar-ar prepare / augment / evaluate`` alike."""
    monkeypatch.setenv("OSDAR_AR_CACHE_DIR", "/srv/cache")
    assert Settings().prepared_cache_dir == Path("/srv/cache/prepared")
    monkeypatch.delenv("OSDAR_AR_CACHE_DIR")
    assert Settings(data_dir=Path("/d")).prepared_cache_dir == Path("/d/cache/prepared")
