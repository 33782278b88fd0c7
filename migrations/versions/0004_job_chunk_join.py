"""The join of a job's chunks in our database: jobs.chunks_total, chunks_done, finish_*.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-26

A job's chunks of frames were joined by a Celery chord, which the database result backend
finishes by polling once a second (``celery.chord_unlock``). Each chunk now records its
result on its job's row, and the chunk that completes the last one sends ``finish``
under a token claimed on the row (worker/orchestration/chunk_join.py). Plain SQLAlchemy
types only; the columns go through batch mode (SQLite recreates the table; PostgreSQL
alters it); ``chunks_total`` gets a server default for the rows already there.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    with op.batch_alter_table("jobs") as b:
        b.add_column(sa.Column("chunks_total", sa.Integer(), nullable=False, server_default="0"))
        b.add_column(sa.Column("chunks_done", sa.JSON(), nullable=True))
        b.add_column(sa.Column("finish_token", sa.String(32), nullable=True))
        b.add_column(sa.Column("finish_sent_at", TS, nullable=True))
        b.add_column(sa.Column("finish_started_at", TS, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as b:
        b.drop_column("finish_started_at")
        b.drop_column("finish_sent_at")
        b.drop_column("finish_token")
        b.drop_column("chunks_done")
        b.drop_column("chunks_total")
