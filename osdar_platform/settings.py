"""The one settings class of the job service and its workers (pydantic-settings).

Every field reads ``OSDAR_AR_<FIELD>`` from the environment; the deployment-level ones also
read their plain names (``DATABASE_URL``, ``BROKER_URL``, ``STORE_URL``,
``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``S3_ENDPOINT_URL``). Derived defaults
(the folders' default factories, the URLs in :meth:`Settings._derived`) put everything
under ``data_dir`` unless told otherwise, so the embedded default (SQLite, a SQLite broker,
a file-system store) needs no server. ``environment="prod"`` refuses the default secret and SQLite.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

from pydantic import AliasChoices, Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

#: The pepper used when none is configured; refused in production.
DEFAULT_PEPPER = "osdar-ar-dev-pepper-not-secret"
#: The dashboard's cookie-signing secret when none is configured; refused in production.
DEFAULT_DASHBOARD_SECRET = "osdar-ar-dev-dashboard-secret-not-secret"
GiB = 1024**3
MiB = 1024**2


def _env(name: str, *plain: str) -> AliasChoices:
    """OSDAR_AR_<NAME> first, then the plain env names (init kwargs use the field name)."""
    return AliasChoices(f"OSDAR_AR_{name.upper()}", *plain)


def _under_data_dir(validated: dict[str, Any], name: str) -> Path:
    """Default of a folder field: ``name`` under the (validated, declared earlier) data_dir."""
    return Path(validated["data_dir"]) / name


class Settings(BaseSettings):
    """Configuration of the API and the workers (one instance per process)."""

    model_config = SettingsConfigDict(
        env_prefix="OSDAR_AR_", extra="ignore", populate_by_name=True, validate_default=True
    )

    #: "test" enables test-only job-spec hooks (worker/orchestration/runner.py); never deploy it.
    environment: Literal["dev", "test", "prod"] = "dev"
    data_dir: Path = Path("./var")

    # --- where things live (None: derived from data_dir) ------------------------------
    database_url: str | None = Field(None, validation_alias=_env("database_url", "DATABASE_URL"))
    broker_url: str | None = Field(None, validation_alias=_env("broker_url", "BROKER_URL"))
    store_url: str | None = Field(None, validation_alias=_env("store_url", "STORE_URL"))
    #: The workers' cache: prepared sequences, job attempts, fetched sequences, render setups.
    cache_dir: Path = Field(default_factory=lambda data: _under_data_dir(data, "cache"))
    #: Extracted sequence uploads (the workers must read it).
    sequences_dir: Path = Field(default_factory=lambda data: _under_data_dir(data, "sequences"))
    #: Folders under which a registered sequence path must lie; empty = anywhere (dev only).
    sequence_roots: list[Path] = Field(default_factory=list)

    # --- S3-compatible object store ----------------------------------------------------
    aws_access_key_id: str | None = Field(
        None, validation_alias=_env("aws_access_key_id", "AWS_ACCESS_KEY_ID")
    )
    aws_secret_access_key: SecretStr | None = Field(
        None, validation_alias=_env("aws_secret_access_key", "AWS_SECRET_ACCESS_KEY")
    )
    s3_endpoint_url: str | None = Field(
        None, validation_alias=_env("s3_endpoint_url", "S3_ENDPOINT_URL")
    )
    s3_region: str = "us-east-1"

    # --- secrets -----------------------------------------------------------------------
    api_key_pepper: SecretStr = SecretStr(DEFAULT_PEPPER)
    #: Signs the dashboard's session cookies (service/dashboard/auth.py).
    dashboard_secret: SecretStr = SecretStr(DEFAULT_DASHBOARD_SECRET)

    # --- upload and archive limits -----------------------------------------------------
    max_sequence_upload_bytes: int = Field(20 * GiB, gt=0)
    max_asset_upload_bytes: int = Field(256 * MiB, gt=0)
    max_archive_members: int = Field(100_000, gt=0)
    max_archive_total_bytes: int = Field(60 * GiB, gt=0)  # extracted
    max_archive_name_length: int = Field(512, gt=0)  # whole member path
    max_archive_ratio: float = Field(200.0, gt=1.0)  # extracted / compressed, zip members
    max_mesh_vertices: int = Field(2_000_000, gt=0)
    max_mesh_faces: int = Field(4_000_000, gt=0)

    # --- fairness ------------------------------------------------------------------------
    rate_limit_per_s: float = Field(20.0, gt=0)  # token refill per API key
    rate_limit_burst: int = Field(100, gt=0)  # bucket size
    max_concurrent_jobs_per_key: int = Field(4, gt=0)  # QUEUED + RUNNING
    max_page_size: int = Field(100, gt=0)
    #: With an S3 store, archive and manifest downloads answer 307 to a presigned URL
    #: valid this long (after the API's ownership check); the local store streams.
    download_url_ttl_s: int = Field(300, gt=0, le=7 * 24 * 3600)
    #: ``POST /v1/campaigns?dry_run=true`` waits this long for the worker's expansion
    #: (200 with the variants), then answers 202 and the client polls.
    campaign_dry_run_wait_s: float = Field(20.0, ge=0, le=600)

    # --- workers -------------------------------------------------------------------------
    task_time_limit_s: int = Field(6 * 3600, gt=0)
    task_soft_time_limit_s: int = Field(6 * 3600 - 300, gt=0)
    visibility_timeout_s: int = Field(8 * 3600, gt=0)
    visibility_margin_s: int = Field(600, ge=0)
    max_deliveries: int = Field(3, gt=0)
    worker_max_memory_per_child_kib: int = Field(8 * 1024 * 1024, gt=0)  # recycle above
    #: Frames per augmentation chunk (one chord member; chunks run on several workers).
    frames_per_chunk: int = Field(25, gt=0)
    #: Store calls of a job retried on StoreError (osdar_platform/retry.py, the only retry
    #: layer): attempts after the first (default 6), with exponential backoff from
    #: ``store_retry_base_s`` (0.5 s) capped at ``store_retry_max_s`` (30 s), all within
    #: ``store_retry_budget_s`` (120 s) of the first try; past it the job fails saying so.
    store_retries: int = Field(6, ge=0)
    store_retry_base_s: float = Field(0.5, gt=0)
    store_retry_max_s: float = Field(30.0, gt=0)
    store_retry_budget_s: float = Field(120.0, gt=0)
    #: The reaper (worker/orchestration/reaper.py), run by every worker at start and then every
    #: ``reaper_interval_s`` (0: never). A RUNNING job with an expired lease of its attempt
    #: (worker/orchestration/lease.py: taken when a stage starts, renewed every
    #: ``lease_renew_s`` for ``lease_ttl_s``) is re-queued or FAILED. A job whose message was
    #: handed to a Redis broker before the reaper's sentinel key there was (re)written (the
    #: data was lost: restarted without persistence, flushed) is re-queued;
    #: ``broker_restart_margin_s`` covers clock differences between the hosts and the time
    #: between a send and its timestamp. With a broker other than Redis, a RUNNING job
    #: without a row update for ``reaper_stale_after_s`` (None: task_time_limit_s +
    #: visibility_margin_s) is re-queued. PENDING jobs older than ``reaper_orphan_grace_s``
    #: are sent again.
    reaper_interval_s: float = Field(60.0, ge=0)
    reaper_stale_after_s: float | None = Field(None, gt=0)
    reaper_orphan_grace_s: float = Field(120.0, gt=0)
    lease_ttl_s: float = Field(90.0, gt=0)
    lease_renew_s: float = Field(15.0, gt=0)
    broker_restart_margin_s: float = Field(2.0, ge=0)

    @model_validator(mode="after")
    def _derived(self) -> Settings:
        data = self.data_dir
        if self.database_url is None:
            self.database_url = f"sqlite:///{data}/osdar-ar.db"
        if self.broker_url is None:
            self.broker_url = f"sqla+sqlite:///{data}/broker.db"
        if self.store_url is None:
            self.store_url = f"file://{data.resolve()}/store"
        if not self.store_url.startswith(("file://", "s3://")):
            raise ValueError(f"store_url {self.store_url!r}: expected file://PATH or s3://BUCKET")
        if self.task_soft_time_limit_s >= self.task_time_limit_s:
            raise ValueError(
                f"task_soft_time_limit_s ({self.task_soft_time_limit_s}) must be below "
                f"task_time_limit_s ({self.task_time_limit_s})"
            )
        # A broker redelivers a message whose ack has not arrived within the visibility
        # timeout: shorter than a task may run, and a running job is delivered twice.
        need = self.task_time_limit_s + self.visibility_margin_s
        if self.visibility_timeout_s < need:
            raise ValueError(
                f"visibility_timeout_s ({self.visibility_timeout_s}) must be at least "
                f"task_time_limit_s + visibility_margin_s ({need})"
            )
        # a lease survives two missed renewals (a slow database, a busy core)
        if self.lease_renew_s * 3 > self.lease_ttl_s:
            raise ValueError(
                f"lease_renew_s ({self.lease_renew_s}) must be at most a third of "
                f"lease_ttl_s ({self.lease_ttl_s})"
            )
        if self.environment == "prod":
            self._check_prod()
        return self

    def _check_prod(self) -> None:
        problems = []
        if self.api_key_pepper.get_secret_value() == DEFAULT_PEPPER:
            problems.append("OSDAR_AR_API_KEY_PEPPER is the default: set a secret")
        if self.dashboard_secret.get_secret_value() == DEFAULT_DASHBOARD_SECRET:
            problems.append("OSDAR_AR_DASHBOARD_SECRET is the default: set a secret")
        if str(self.database_url).startswith("sqlite"):
            problems.append("DATABASE_URL is SQLite: use PostgreSQL in production")
        if "sqlite" in str(self.broker_url):
            problems.append("BROKER_URL is the SQLite broker: use Redis in production")
        if not self.sequence_roots:
            problems.append("OSDAR_AR_SEQUENCE_ROOTS is empty: name the readable folders")
        if problems:
            raise ValueError("refusing to start in prod: " + "; ".join(problems))

    @property
    def prepared_cache_dir(self) -> Path:
        """Where prepared sequences are cached (the workers' and the CLI's alike)."""
        return Path(self.cache_dir) / "prepared"

    @property
    def is_sqlite(self) -> bool:
        return str(self.database_url).startswith("sqlite")


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings (read from the environment once)."""
    return Settings()
