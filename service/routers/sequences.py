"""/v1/sequences: register a folder, upload an archive, list, show, delete."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from starlette.convertors import Convertor, register_url_convertor

from service.deps import CurrentKey, SessionDep, SettingsDep, StoreDep
from service.routers.common import (
    AUTH_ERRORS,
    BAD_REQUEST,
    CONFLICT,
    FORBIDDEN,
    INVALID,
    NOT_FOUND,
    TOO_LARGE,
    Limit,
    Offset,
    binary_body,
    content_length,
)
from service.schemas import Name, Page, SequencePublic, SequenceRegister
from service.services import sequences as svc
from service.services.uploads import receive_upload


class SequenceIdConvertor(Convertor[str]):
    """A sequence id in a path: an id's characters (``ID_PATTERN``), but not ``upload``, so
    that GET and DELETE of ``/v1/sequences/upload`` are not served as a sequence named
    "upload" (its only method is POST, and a 405 says so). Anything else is no route: 404."""

    regex = "(?!upload$)[A-Za-z0-9_-]{1,64}"

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("sequence_id", SequenceIdConvertor())

router = APIRouter(prefix="/sequences", tags=["sequences"], responses=AUTH_ERRORS)


@router.post(
    "",
    response_model=SequencePublic,
    status_code=status.HTTP_201_CREATED,
    responses={**INVALID, **BAD_REQUEST, **FORBIDDEN, **NOT_FOUND},
    summary="Register a sequence folder the workers can read",
)
def register_sequence(
    body: SequenceRegister, key: CurrentKey, session: SessionDep, settings: SettingsDep
) -> SequencePublic:
    seq = svc.register_sequence(
        session=session, owner=key, path=body.path, name=body.name, settings=settings
    )
    return SequencePublic.from_row(seq)


@router.post(
    "/upload",
    response_model=SequencePublic,
    status_code=status.HTTP_201_CREATED,
    responses={**INVALID, **TOO_LARGE, **BAD_REQUEST},
    summary="Upload an OSDaR23 sequence as a tar or zip archive (raw body, streamed)",
    openapi_extra=binary_body(
        ["application/x-tar", "application/zip", "application/gzip", "application/octet-stream"],
        "The archive (tar, tar.gz/bz2/xz or zip) of one sequence folder",
    ),
)
async def upload_sequence(
    request: Request,
    key: CurrentKey,
    session: SessionDep,
    settings: SettingsDep,
    store: StoreDep,
    name: Annotated[Name | None, Query(description="sequence name (default: folder)")] = None,
) -> SequencePublic:
    upload = await receive_upload(
        request.stream(),
        tmp_dir=Path(settings.data_dir) / "tmp",
        limit=settings.max_sequence_upload_bytes,
        declared_length=content_length(request),
    )
    try:
        seq = await run_in_threadpool(
            lambda: svc.create_uploaded_sequence(
                session=session,
                owner=key,
                archive=upload.path,
                sha256=upload.sha256,
                name=name,
                settings=settings,
                store=store,
            )
        )
    finally:
        upload.path.unlink(missing_ok=True)
    return SequencePublic.from_row(seq)


@router.get("", response_model=Page[SequencePublic], summary="List this key's sequences")
def list_sequences(
    key: CurrentKey, session: SessionDep, limit: Limit = 20, offset: Offset = 0
) -> Page[SequencePublic]:
    rows, total = svc.list_sequences(session=session, owner=key, limit=limit, offset=offset)
    items = [SequencePublic.from_row(r) for r in rows]
    return Page[SequencePublic](items=items, total=total, limit=limit, offset=offset)


@router.get(
    "/{sequence_id:sequence_id}",
    response_model=SequencePublic,
    responses=NOT_FOUND,
    summary="Frames, cameras, time span and validation result of a sequence",
)
def get_sequence(sequence_id: str, key: CurrentKey, session: SessionDep) -> SequencePublic:
    seq = svc.get_sequence(session=session, owner=key, sequence_id=sequence_id)
    return SequencePublic.from_row(seq)


@router.delete(
    "/{sequence_id:sequence_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_model=None,
    responses={**NOT_FOUND, **CONFLICT},
    summary="Delete a sequence (uploaded files too; a registered folder is left alone)",
)
def delete_sequence(
    sequence_id: str, key: CurrentKey, session: SessionDep, settings: SettingsDep, store: StoreDep
) -> None:
    svc.delete_sequence(
        session=session, owner=key, sequence_id=sequence_id, settings=settings, store=store
    )
