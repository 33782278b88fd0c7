"""Worker liveness in the database: job_leases; jobs.broker_seen_at, jobs.broker_run_id.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-25

A lease per stage a worker process runs (taken at its start, renewed by a heartbeat,
deleted at its end), when a job's message was last known to be in the broker, and the
broker sentinel the reaper last re-sent it under: the reaper decides from these instead
of reading the broker's internal structures
(worker/orchestration/reaper.py). Plain SQLAlchemy types only; the columns added to
``jobs`` go through batch mode (SQLite recreates the table; PostgreSQL alters it).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "job_leases",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("job_id", sa.String(36), nullable=False),
        sa.Column("attempt", sa.Integer(), nullable=False),
        sa.Column("stage", sa.String(64), nullable=False),
        sa.Column("holder", sa.String(255), nullable=False),
        sa.Column("taken_at", TS, nullable=False),
        sa.Column("renewed_at", TS, nullable=False),
        sa.Column("expires_at", TS, nullable=False),
        sa.ForeignKeyConstraint(
            ["job_id"], ["jobs.id"], ondelete="CASCADE", name="fk_job_leases_job_id_jobs"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_job_leases"),
    )
    op.create_index("ix_job_leases_job_id", "job_leases", ["job_id"])
    with op.batch_alter_table("jobs") as b:
        b.add_column(sa.Column("broker_seen_at", TS, nullable=True))
        b.add_column(sa.Column("broker_run_id", sa.String(64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as b:
        b.drop_column("broker_run_id")
        b.drop_column("broker_seen_at")
    op.drop_index("ix_job_leases_job_id", table_name="job_leases")
    op.drop_table("job_leases")
