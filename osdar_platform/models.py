"""Database tables of the job service (SQLAlchemy 2, typed declarative).

The API writes API keys, sequences, assets and new jobs; the workers write job state,
events and results (``worker/orchestration/state.py``). The schema is created by the Alembic
migrations in ``migrations/``, never by ``create_all``.
"""

from __future__ import annotations

import enum
import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Enum,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

#: Constraint names fixed by convention, so migrations can name what they alter.
NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

#: An integer primary key that SQLite auto-increments (INTEGER PRIMARY KEY) too.
BigIntPK = BigInteger().with_variant(Integer(), "sqlite")


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return str(uuid.uuid4())


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON}  # noqa: RUF012


class JobState(enum.StrEnum):
    PENDING = "PENDING"  # row written, not yet handed to the broker
    QUEUED = "QUEUED"  # message sent
    RUNNING = "RUNNING"
    SUCCEEDED = "SUCCEEDED"
    FAILED = "FAILED"
    CANCELLED = "CANCELLED"

    @property
    def terminal(self) -> bool:
        return self in TERMINAL_STATES


TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})
ACTIVE_STATES = frozenset({JobState.PENDING, JobState.QUEUED, JobState.RUNNING})


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC timestamp on every backend (SQLite stores it naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value


Timestamp = UTCDateTime()


class ApiKey(Base):
    """An API key: only the peppered SHA-256 of its secret is stored."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(BigIntPK, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(200))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))  # first characters, to recognise a key
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)
    #: An operator key sees every key's jobs and campaigns on the dashboard, the workers,
    #: the queue depth and the failure rate (granted by ``osdar-ar keys grant-operator``).
    operator: Mapped[bool] = mapped_column(Boolean, default=False)


class Sequence(Base):
    """An OSDaR23 sequence folder the workers can read (registered or uploaded)."""

    __tablename__ = "sequences"
    __table_args__ = (Index("ix_sequences_owner_created", "owner_id", "created_at"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(255))
    source: Mapped[str] = mapped_column(String(16))  # "path" | "upload"
    path: Mapped[str] = mapped_column(Text)  # the folder the workers read
    content_key: Mapped[str | None] = mapped_column(Text, default=None)  # store key of upload
    frames: Mapped[int] = mapped_column(Integer, default=0)
    cameras: Mapped[list[Any]] = mapped_column(JSON, default=list)
    time_span_s: Mapped[float] = mapped_column(Float, default=0.0)
    validation: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    state: Mapped[str] = mapped_column(String(16), default="ready")
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)


class Asset(Base):
    """An uploaded object mesh (stored in the object store)."""

    __tablename__ = "assets"
    __table_args__ = (Index("ix_assets_owner_created", "owner_id", "created_at"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(255))
    file_type: Mapped[str] = mapped_column(String(8))
    store_key: Mapped[str] = mapped_column(Text)
    size: Mapped[int] = mapped_column(BigInteger)
    vertices: Mapped[int] = mapped_column(Integer)
    faces: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)


class Job(Base):
    """One augmentation job: its spec, state, progress and published result."""

    __tablename__ = "jobs"
    __table_args__ = (
        UniqueConstraint("owner_id", "idempotency_key", name="uq_jobs_owner_idempotency_key"),
        Index("ix_jobs_owner_created", "owner_id", "created_at"),
        Index("ix_jobs_owner_state", "owner_id", "state"),
        Index("ix_jobs_state_created", "state", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"))
    sequence_id: Mapped[str | None] = mapped_column(
        ForeignKey("sequences.id", ondelete="SET NULL"), index=True
    )
    idempotency_key: Mapped[str | None] = mapped_column(String(255), default=None)
    #: The campaign this job is a variant of (None: a job submitted on its own).
    campaign_id: Mapped[str | None] = mapped_column(
        ForeignKey("campaigns.id", ondelete="CASCADE"), default=None, index=True
    )
    spec: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[JobState] = mapped_column(
        Enum(JobState, native_enum=False, length=16, validate_strings=True),
        default=JobState.PENDING,
    )
    stage: Mapped[str | None] = mapped_column(String(64), default=None)
    progress_done: Mapped[int] = mapped_column(Integer, default=0)
    progress_total: Mapped[int] = mapped_column(Integer, default=0)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    deliveries: Mapped[int] = mapped_column(Integer, default=0)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    timings: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    #: Store key of the published archive: set once, atomically, by the publish step.
    result_key: Mapped[str | None] = mapped_column(Text, default=None)
    previews: Mapped[list[Any] | None] = mapped_column(JSON, default=None)  # store keys
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow, onupdate=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)
    #: When a message of the job was last known to be in the broker (handed to it at the
    #: end of a stage, or taken from it when a stage started): the reaper compares it with
    #: the time since which the broker's data is intact (worker/orchestration/reaper.py).
    broker_seen_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)
    #: The broker sentinel's token the reaper last re-sent the job under (its own sends).
    broker_run_id: Mapped[str | None] = mapped_column(String(64), default=None)
    #: The join of the current attempt's chunks before its ``finish``
    #: (worker/orchestration/chunk_join.py), reset by every new attempt: how many chunks
    #: the attempt has (0: not planned yet), the results of those done ({index: store
    #: keys}), and the one ``finish`` sent for them: its token (the message carrying
    #: another is a stale duplicate), when it was sent, when it started.
    chunks_total: Mapped[int] = mapped_column(Integer, default=0)
    chunks_done: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    finish_token: Mapped[str | None] = mapped_column(String(32), default=None)
    finish_sent_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)
    finish_started_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)

    events: Mapped[list[JobEvent]] = relationship(
        back_populates="job", cascade="all, delete-orphan", order_by="JobEvent.id"
    )


class JobLease(Base):
    """A worker process running one stage of one attempt, for as long as it renews this.

    Taken when the stage starts, renewed by a heartbeat thread, deleted when the stage
    ends (worker/orchestration/lease.py); the reaper re-queues a RUNNING job whose
    attempt's leases have all expired (worker/orchestration/reaper.py).
    """

    __tablename__ = "job_leases"

    id: Mapped[int] = mapped_column(BigIntPK, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    attempt: Mapped[int] = mapped_column(Integer)
    stage: Mapped[str] = mapped_column(String(64))
    holder: Mapped[str] = mapped_column(String(255))  # "hostname:pid"
    taken_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    renewed_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(Timestamp)


class JobEvent(Base):
    """Something that happened to a job (state change, attempt start, error, retry)."""

    __tablename__ = "job_events"

    id: Mapped[int] = mapped_column(BigIntPK, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    kind: Mapped[str] = mapped_column(String(32))
    message: Mapped[str | None] = mapped_column(Text, default=None)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    data: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)

    job: Mapped[Job] = relationship(back_populates="events")


class CampaignState(enum.StrEnum):
    """A campaign's life (docs/api.md#campaign-states)."""

    PENDING = "PENDING"  # row written, the expansion not yet handed to the broker
    EXPANDING = "EXPANDING"  # a worker prepares the sequences and expands the spec
    EXPANDED = "EXPANDED"  # a dry run: the variants are there, nothing was queued
    RUNNING = "RUNNING"  # the variants' jobs exist; some are not finished
    SUCCEEDED = "SUCCEEDED"  # every variant SUCCEEDED
    PARTIAL = "PARTIAL"  # some variants SUCCEEDED, others FAILED or were CANCELLED
    FAILED = "FAILED"  # the expansion failed, or no variant SUCCEEDED
    CANCELLED = "CANCELLED"  # cancelled before any variant SUCCEEDED

    @property
    def terminal(self) -> bool:
        return self in CAMPAIGN_TERMINAL_STATES


CAMPAIGN_TERMINAL_STATES = frozenset(
    {
        CampaignState.EXPANDED,
        CampaignState.SUCCEEDED,
        CampaignState.PARTIAL,
        CampaignState.FAILED,
        CampaignState.CANCELLED,
    }
)


class Campaign(Base):
    """A dataset campaign: a spec expanded (by a worker) into variants, each one job."""

    __tablename__ = "campaigns"
    __table_args__ = (
        UniqueConstraint("owner_id", "idempotency_key", name="uq_campaigns_owner_idempotency_key"),
        Index("ix_campaigns_owner_created", "owner_id", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    owner_id: Mapped[int] = mapped_column(ForeignKey("api_keys.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(200))
    idempotency_key: Mapped[str | None] = mapped_column(String(255), default=None)
    spec: Mapped[dict[str, Any]] = mapped_column(JSON)
    dry_run: Mapped[bool] = mapped_column(Boolean, default=False)
    state: Mapped[CampaignState] = mapped_column(
        Enum(CampaignState, native_enum=False, length=16, validate_strings=True),
        default=CampaignState.PENDING,
    )
    stage: Mapped[str | None] = mapped_column(String(64), default=None)
    #: How often the expansion was delivered (a campaign that kills its workers fails).
    deliveries: Mapped[int] = mapped_column(Integer, default=0)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    #: The expansion's issues: [{level, where, message}].
    issues: Mapped[list[Any] | None] = mapped_column(JSON, default=None)
    variants_total: Mapped[int] = mapped_column(Integer, default=0)
    #: Written when the campaign ends: counts per state, quality summary.
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    manifest_json_key: Mapped[str | None] = mapped_column(Text, default=None)
    manifest_csv_key: Mapped[str | None] = mapped_column(Text, default=None)
    created_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(Timestamp, default=utcnow, onupdate=utcnow)
    expanded_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)
    finished_at: Mapped[datetime | None] = mapped_column(Timestamp, default=None)

    variants: Mapped[list[CampaignVariant]] = relationship(
        back_populates="campaign",
        cascade="all, delete-orphan",
        order_by="CampaignVariant.index",
    )


class CampaignVariant(Base):
    """One variant of a campaign (``worker.campaign.variant.Variant`` as JSON) and its job.

    The expansion writes every variant and its job in one transaction, keyed by
    (campaign, index): a redelivered expansion can never make a variant twice.
    """

    __tablename__ = "campaign_variants"

    campaign_id: Mapped[str] = mapped_column(
        ForeignKey("campaigns.id", ondelete="CASCADE"), primary_key=True
    )
    index: Mapped[int] = mapped_column(Integer, primary_key=True)
    variant_id: Mapped[str] = mapped_column(String(16))  # "v0000"
    key: Mapped[str] = mapped_column(String(32))  # the variant's digest
    sequence_id: Mapped[str] = mapped_column(String(64))
    sequence_label: Mapped[str] = mapped_column(String(255))
    classes: Mapped[list[Any]] = mapped_column(JSON, default=list)
    variant: Mapped[dict[str, Any]] = mapped_column(JSON)
    job_id: Mapped[str | None] = mapped_column(
        ForeignKey("jobs.id", ondelete="SET NULL"), default=None, unique=True
    )
    #: The variant's manifest row, written when the campaign ends (gauge, quality).
    row: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)

    campaign: Mapped[Campaign] = relationship(back_populates="variants")
