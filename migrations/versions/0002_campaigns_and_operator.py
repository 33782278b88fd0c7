"""Campaigns: campaigns, campaign_variants, jobs.campaign_id; api_keys.operator.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25

Plain SQLAlchemy types only (no imports from the application), constraint names from the
models' naming convention, the campaign state as VARCHAR. The columns added to existing
tables go through batch mode (SQLite recreates the table; PostgreSQL alters it).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)
CAMPAIGN_STATES = (
    "PENDING",
    "EXPANDING",
    "EXPANDED",
    "RUNNING",
    "SUCCEEDED",
    "PARTIAL",
    "FAILED",
    "CANCELLED",
)


def upgrade() -> None:
    op.create_table(
        "campaigns",
        sa.Column("id", sa.String(36), nullable=False),
        sa.Column("owner_id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("idempotency_key", sa.String(255), nullable=True),
        sa.Column("spec", sa.JSON(), nullable=False),
        sa.Column("dry_run", sa.Boolean(), nullable=False),
        sa.Column(
            "state",
            sa.Enum(*CAMPAIGN_STATES, name="campaignstate", native_enum=False, length=16),
            nullable=False,
        ),
        sa.Column("stage", sa.String(64), nullable=True),
        sa.Column("deliveries", sa.Integer(), nullable=False),
        sa.Column("cancel_requested", sa.Boolean(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("issues", sa.JSON(), nullable=True),
        sa.Column("variants_total", sa.Integer(), nullable=False),
        sa.Column("summary", sa.JSON(), nullable=True),
        sa.Column("manifest_json_key", sa.Text(), nullable=True),
        sa.Column("manifest_csv_key", sa.Text(), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("updated_at", TS, nullable=False),
        sa.Column("expanded_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.ForeignKeyConstraint(
            ["owner_id"], ["api_keys.id"], ondelete="CASCADE", name="fk_campaigns_owner_id_api_keys"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_campaigns"),
        sa.UniqueConstraint(
            "owner_id", "idempotency_key", name="uq_campaigns_owner_idempotency_key"
        ),
    )
    op.create_index("ix_campaigns_owner_created", "campaigns", ["owner_id", "created_at"])
    with op.batch_alter_table("jobs") as b:
        b.add_column(sa.Column("campaign_id", sa.String(36), nullable=True))
        b.create_foreign_key(
            "fk_jobs_campaign_id_campaigns",
            "campaigns",
            ["campaign_id"],
            ["id"],
            ondelete="CASCADE",
        )
        b.create_index("ix_jobs_campaign_id", ["campaign_id"])
    op.create_table(
        "campaign_variants",
        sa.Column("campaign_id", sa.String(36), nullable=False),
        sa.Column("index", sa.Integer(), nullable=False),
        sa.Column("variant_id", sa.String(16), nullable=False),
        sa.Column("key", sa.String(32), nullable=False),
        sa.Column("sequence_id", sa.String(64), nullable=False),
        sa.Column("sequence_label", sa.String(255), nullable=False),
        sa.Column("classes", sa.JSON(), nullable=False),
        sa.Column("variant", sa.JSON(), nullable=False),
        sa.Column("job_id", sa.String(36), nullable=True),
        sa.Column("row", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(
            ["campaign_id"],
            ["campaigns.id"],
            ondelete="CASCADE",
            name="fk_campaign_variants_campaign_id_campaigns",
        ),
        sa.ForeignKeyConstraint(
            ["job_id"], ["jobs.id"], ondelete="SET NULL", name="fk_campaign_variants_job_id_jobs"
        ),
        sa.PrimaryKeyConstraint("campaign_id", "index", name="pk_campaign_variants"),
        sa.UniqueConstraint("job_id", name="uq_campaign_variants_job_id"),
    )
    with op.batch_alter_table("api_keys") as b:
        b.add_column(sa.Column("operator", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("api_keys") as b:
        b.drop_column("operator")
    op.drop_table("campaign_variants")
    with op.batch_alter_table("jobs") as b:
        b.drop_index("ix_jobs_campaign_id")
        b.drop_constraint("fk_jobs_campaign_id_campaigns", type_="foreignkey")
        b.drop_column("campaign_id")
    op.drop_index("ix_campaigns_owner_created", table_name="campaigns")
    op.drop_table("campaigns")
