"""/v1/jobs: submit (idempotent), status, list, cancel, events, archive, metrics, previews."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Query, Response, status

from osdar_platform.models import JobState
from service.deps import CurrentKey, DispatcherDep, SessionDep, SettingsDep
from service.downloads import archive_media_type, image_media_type
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
from service.schemas import ID_PATTERN, JobCreate, JobEventPublic, JobPublic, Page
from service.services import jobs as svc

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=AUTH_ERRORS)

IdempotencyKey = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=255,
        pattern=r"^[\x21-\x7e]+$",
        description="the same key returns the same job (per API key)",
    ),
]
JobId = Annotated[str, Path(max_length=64, pattern=ID_PATTERN)]


@router.post(
    "",
    response_model=JobPublic,
    status_code=status.HTTP_201_CREATED,
    responses={
        200: {"model": JobPublic, "description": "Replay of an Idempotency-Key"},
        **NOT_FOUND,
        **INVALID,
        **CONFLICT,
        **BAD_REQUEST,
    },
    summary="Submit a job (checked against its sequence now, not an hour later)",
)
def create_job(
    spec: JobCreate,
    response: Response,
    key: CurrentKey,
    session: SessionDep,
    settings: SettingsDep,
    dispatcher: DispatcherDep,
    idempotency_key: IdempotencyKey = None,
) -> JobPublic:
    job, created = svc.submit_job(
        session=session,
        spec=spec,
        owner=key,
        idempotency_key=idempotency_key,
        settings=settings,
        enqueue=dispatcher.enqueue,
    )
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    if not created:
        response.status_code = status.HTTP_200_OK
    return JobPublic.from_row(job)


@router.get("", response_model=Page[JobPublic], summary="List this key's jobs, newest first")
def list_jobs(
    key: CurrentKey,
    session: SessionDep,
    limit: Limit = 20,
    offset: Offset = 0,
    state: Annotated[list[JobState] | None, Query(description="filter; repeatable")] = None,
    sequence_id: Annotated[str | None, Query(max_length=64, pattern=ID_PATTERN)] = None,
) -> Page[JobPublic]:
    rows, total = svc.list_jobs(
        session=session,
        owner=key,
        limit=limit,
        offset=offset,
        state=state,
        sequence_id=sequence_id,
    )
    items = [JobPublic.from_row(j) for j in rows]
    return Page[JobPublic](items=items, total=total, limit=limit, offset=offset)


@router.get(
    "/{job_id}",
    response_model=JobPublic,
    responses=NOT_FOUND,
    summary="State, stage, progress, timings, errors, metrics",
)
def get_job(job_id: JobId, key: CurrentKey, session: SessionDep) -> JobPublic:
    return JobPublic.from_row(svc.get_job(session=session, owner=key, job_id=job_id))


@router.post(
    "/{job_id}/cancel",
    response_model=JobPublic,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**NOT_FOUND, **CONFLICT},
    summary="Cancel (queued jobs at once, running ones at their next check)",
)
def cancel_job(
    job_id: JobId, key: CurrentKey, session: SessionDep, dispatcher: DispatcherDep
) -> JobPublic:
    job = svc.cancel_job(session=session, owner=key, job_id=job_id, cancel=dispatcher.cancel)
    return JobPublic.from_row(job)


@router.get(
    "/{job_id}/events",
    response_model=list[JobEventPublic],
    responses=NOT_FOUND,
    summary="What happened to the job: attempts, state changes, errors",
)
def job_events(job_id: JobId, key: CurrentKey, session: SessionDep) -> list[JobEventPublic]:
    rows = svc.list_events(session=session, owner=key, job_id=job_id)
    return [JobEventPublic.model_validate(e) for e in rows]


@router.get(
    "/{job_id}/archive",
    **download_route(
        "application/x-tar",
        summary="Download the augmented sequence (streamed with Range; S3: 307 to a presigned URL)",
    ),
)
def job_archive(
    job_id: JobId, key: CurrentKey, session: SessionDep, download: DownloadsDep
) -> Response:
    store_key = svc.archive_key(session=session, owner=key, job_id=job_id)
    name = store_key.rsplit("/", 1)[-1]
    return download.send(
        store_key, media_type=archive_media_type(name), filename=f"osdar-ar-{job_id}-{name}"
    )


@router.get(
    "/{job_id}/metrics",
    response_model=dict[str, Any],
    responses={**NOT_FOUND, **CONFLICT},
    summary="AR-quality metrics of a finished job (metrics.json)",
)
def job_metrics(job_id: JobId, key: CurrentKey, session: SessionDep) -> dict[str, Any]:
    return svc.job_metrics(session=session, owner=key, job_id=job_id)


@router.get(
    "/{job_id}/previews",
    response_model=list[str],
    responses={**NOT_FOUND, **CONFLICT},
    summary="URLs of the job's preview images (once it SUCCEEDED)",
)
def job_previews(job_id: JobId, key: CurrentKey, session: SessionDep) -> list[str]:
    keys = svc.preview_keys(session=session, owner=key, job_id=job_id)
    return [f"/v1/jobs/{job_id}/previews/{i}" for i in range(len(keys))]


@router.get(
    "/{job_id}/previews/{index}",
    **download_route("image/png", summary="One preview image", redirect=False),
)
def job_preview(
    job_id: JobId,
    index: Annotated[int, Path(ge=0, le=10_000)],
    key: CurrentKey,
    session: SessionDep,
    download: DownloadsDep,
) -> Response:
    store_key = svc.preview_key(session=session, owner=key, job_id=job_id, index=index)
    return download.stream(store_key, media_type=image_media_type(store_key))
