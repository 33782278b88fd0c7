"""Response schemas of /v1/campaigns. The request body is the campaign spec itself,
:class:`worker.campaign.spec.CampaignSpec` (a pydantic model that imports no pipeline),
never re-defined here; a variant's job spec is what worker/campaign/variant.py makes.

(A module of its own: worker/campaign/spec.py imports service/schemas.py, so the campaign
schemas cannot live there.)
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from osdar_platform.models import CampaignState, JobState
from service.schemas import Progress


class CampaignProgress(BaseModel):
    """Aggregate progress over the variants' jobs."""

    variants: int = Field(description="variants in the campaign (0 until expanded)")
    pending: int = Field(description="PENDING or QUEUED")
    running: int
    succeeded: int
    failed: int
    cancelled: int
    frames_done: int
    frames_total: int
    fraction: float = Field(description="frames done / frames total (0-1)")


class CampaignLinks(BaseModel):
    self: str
    cancel: str
    manifest_json: str | None = Field(None, description="once the campaign has ended")
    manifest_csv: str | None = None


class VariantLinks(BaseModel):
    job: str | None
    archive: str | None = Field(None, description="the job's archive, once SUCCEEDED")
    previews: str | None = None


class CampaignVariantPublic(BaseModel):
    """One variant: what it places where (resolved against the prepared sequence), and
    its job's state."""

    index: int
    id: str = Field(description="v0000, v0001, ...")
    key: str = Field(description="digest of what the variant makes")
    sequence_id: str
    sequence_label: str
    classes: list[str]
    objects: list[dict[str, Any]] = Field(
        description="per object: class_name, variation_seed, object, placement, resolved"
    )
    warnings: list[str]
    job_id: str | None = Field(description="None in a dry run")
    state: JobState | None
    stage: str | None
    progress: Progress | None
    error: str | None
    row: dict[str, Any] | None = Field(
        description="the variant's manifest row (gauge, quality), once the campaign ended"
    )
    links: VariantLinks


class CampaignIssue(BaseModel):
    level: str
    where: str
    message: str


class CampaignPublic(BaseModel):
    id: str
    name: str
    state: CampaignState
    stage: str | None
    dry_run: bool
    cancel_requested: bool
    error: str | None
    issues: list[CampaignIssue]
    spec: dict[str, Any]
    progress: CampaignProgress
    summary: dict[str, Any] | None
    created_at: datetime
    updated_at: datetime
    expanded_at: datetime | None
    finished_at: datetime | None
    links: CampaignLinks


class CampaignDetail(CampaignPublic):
    """A campaign with a page of its variants (``variants_limit``, ``variants_offset``)."""

    variants: list[CampaignVariantPublic]
    variants_offset: int
    variants_limit: int


__all__ = [
    "CampaignDetail",
    "CampaignIssue",
    "CampaignLinks",
    "CampaignProgress",
    "CampaignPublic",
    "CampaignVariantPublic",
    "VariantLinks",
]
