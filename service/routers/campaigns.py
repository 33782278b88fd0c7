"""/v1/campaigns: submit (idempotent; dry run), status with per-variant states, list,
cancel, the manifest (JSON, CSV). A variant's archive is its job's (/v1/jobs/{id}/archive)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query, Response, status

from osdar_platform.models import CampaignState
from service.campaign_schemas import CampaignDetail, CampaignPublic
from service.deps import CurrentKey, DispatcherDep, SessionDep, SettingsDep
from service.routers.common import (
    AUTH_ERRORS,
    BAD_REQUEST,
    CONFLICT,
    INVALID,
    NOT_FOUND,
    DownloadsDep,
    Limit,
    Offset,
    download_route,
)
from service.routers.jobs import IdempotencyKey
from service.schemas import ID_PATTERN, Page
from service.services import campaigns as svc
from worker.campaign.spec import CampaignSpec

router = APIRouter(prefix="/campaigns", tags=["campaigns"], responses=AUTH_ERRORS)

CampaignId = Annotated[str, Path(max_length=64, pattern=ID_PATTERN)]
VariantsLimit = Annotated[int, Query(ge=1, le=1000, description="variants per page")]
MANIFEST_MEDIA = {"json": "application/json", "csv": "text/csv"}


@router.post(
    "",
    response_model=CampaignDetail,
    status_code=status.HTTP_201_CREATED,
    responses={
        200: {
            "model": CampaignDetail,
            "description": "A dry run's expansion (its variants with resolved positions), "
            "or the replay of an Idempotency-Key",
        },
        202: {
            "model": CampaignDetail,
            "description": "A dry run still expanding after the wait: poll `Location`",
        },
        **INVALID,
        **CONFLICT,
        **BAD_REQUEST,
    },
    summary="Submit a campaign (checked against the key's sequences now)",
)
def create_campaign(
    spec: CampaignSpec,
    response: Response,
    key: CurrentKey,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
    dry_run: Annotated[
        bool, Query(description="expand only: the variants and their positions, no job")
    ] = False,
    idempotency_key: IdempotencyKey = None,
) -> CampaignDetail:
    row, created = svc.submit_campaign(
        session=session, spec=spec, owner=key, dry_run=dry_run,
        idempotency_key=idempotency_key, send_expand=dispatcher.send_expand,
    )  # fmt: skip
    response.headers["Location"] = f"/v1/campaigns/{row.id}"
    if dry_run:
        row = svc.wait_expanded(session=session, campaign_id=row.id,
                                timeout_s=settings.campaign_dry_run_wait_s)  # fmt: skip
        done = row.state.terminal
        response.status_code = status.HTTP_200_OK if done else status.HTTP_202_ACCEPTED
    elif not created:
        response.status_code = status.HTTP_200_OK
    return svc.detail(session, row, limit=1000, offset=0)


@router.get("", response_model=Page[CampaignPublic], summary="List this key's campaigns")
def list_campaigns(
    key: CurrentKey,
    session: SessionDep,
    limit: Limit = 20,
    offset: Offset = 0,
    state: Annotated[list[CampaignState] | None, Query(description="filter; repeatable")] = None,
) -> Page[CampaignPublic]:
    rows, total = svc.list_campaigns(session=session, owner=key, limit=limit, offset=offset,
                                     state=state)  # fmt: skip
    progress = svc.progress_of(session, [c.id for c in rows])
    items = [svc.public(c, progress.get(c.id)) for c in rows]
    return Page[CampaignPublic](items=items, total=total, limit=limit, offset=offset)


@router.get(
    "/{campaign_id}",
    response_model=CampaignDetail,
    responses=NOT_FOUND,
    summary="State, aggregate progress and a page of the variants with their jobs' states",
)
def get_campaign(
    campaign_id: CampaignId,
    key: CurrentKey,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
    variants_limit: VariantsLimit = 100,
    variants_offset: Offset = 0,
) -> CampaignDetail:
    row = svc.get_campaign(session=session, owner=key, campaign_id=campaign_id)
    svc.nudge(
        session=session,
        campaign=row,
        settings=settings,
        send_expand=dispatcher.send_expand,
        send_finalize=dispatcher.send_finalize,
    )
    return svc.detail(session, row, limit=variants_limit, offset=variants_offset)


@router.post(
    "/{campaign_id}/cancel",
    response_model=CampaignPublic,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**NOT_FOUND, **CONFLICT},
    summary="Cancel: before the expansion nothing is made; afterwards every variant job",
)
def cancel_campaign(
    campaign_id: CampaignId, key: CurrentKey, session: SessionDep, dispatcher: DispatcherDep
) -> CampaignPublic:
    row = svc.cancel_campaign(session=session, owner=key, campaign_id=campaign_id,
                              cancel_job=dispatcher.cancel,
                              send_finalize=dispatcher.send_finalize)  # fmt: skip
    return svc.public(row, svc.progress_of(session, [row.id]).get(row.id))


def _manifest(
    fmt: Literal["json", "csv"],
    campaign_id: str,
    key: CurrentKey,
    session: SessionDep,
    download: DownloadsDep,
) -> Response:
    store_key = svc.manifest_key(session=session, owner=key, campaign_id=campaign_id, fmt=fmt)
    return download.send(
        store_key,
        media_type=MANIFEST_MEDIA[fmt],
        filename=f"osdar-ar-campaign-{campaign_id}-manifest.{fmt}",
    )


@router.get(
    "/{campaign_id}/manifest.json",
    **download_route(
        MANIFEST_MEDIA["json"],
        summary="The manifest (one row per variant: objects, classes, gauge, AR quality), JSON",
    ),
)
def manifest_json(
    campaign_id: CampaignId, key: CurrentKey, session: SessionDep, download: DownloadsDep
) -> Response:
    return _manifest("json", campaign_id, key, session, download)


@router.get(
    "/{campaign_id}/manifest.csv",
    **download_route(
        MANIFEST_MEDIA["csv"], summary="The manifest as CSV (the same rows flattened)"
    ),
)
def manifest_csv(
    campaign_id: CampaignId, key: CurrentKey, session: SessionDep, download: DownloadsDep
) -> Response:
    return _manifest("csv", campaign_id, key, session, download)
