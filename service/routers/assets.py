"""/v1/assets: upload obstacle meshes, list, show, delete."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request, status
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool

from service.deps import CurrentKey, SessionDep, SettingsDep, StoreDep
from service.routers.common import (
    AUTH_ERRORS,
    BAD_REQUEST,
    CONFLICT,
    INVALID,
    NOT_FOUND,
    TOO_LARGE,
    Limit,
    Offset,
    binary_body,
    content_length,
)
from service.schemas import ID_PATTERN, AssetPublic, MeshFileType, Name, Page
from service.services import assets as svc
from service.services.uploads import receive_upload

AssetId = Annotated[str, PathParam(max_length=64, pattern=ID_PATTERN)]

router = APIRouter(prefix="/assets", tags=["assets"], responses=AUTH_ERRORS)


@router.post(
    "",
    response_model=AssetPublic,
    status_code=status.HTTP_201_CREATED,
    responses={**INVALID, **TOO_LARGE, **BAD_REQUEST},
    summary="Upload a mesh (raw body; its type given explicitly)",
    openapi_extra=binary_body(
        [
            "application/octet-stream",
            "model/gltf-binary",
            "model/gltf+json",
            "model/obj",
            "application/zip",
            "application/gzip",
        ],
        "The mesh file, or a zip / tar.gz with an OBJ, its MTL and its texture images",
    ),
)
async def upload_asset(
    request: Request,
    key: CurrentKey,
    session: SessionDep,
    settings: SettingsDep,
    store: StoreDep,
    name: Annotated[Name, Query(description="asset name")],
    file_type: Annotated[MeshFileType, Query(description="mesh format")],
) -> AssetPublic:
    upload = await receive_upload(
        request.stream(),
        tmp_dir=Path(settings.data_dir) / "tmp",
        limit=settings.max_asset_upload_bytes,
        declared_length=content_length(request),
    )
    try:
        asset = await run_in_threadpool(
            lambda: svc.create_asset(
                session=session,
                owner=key,
                name=name,
                file_type=file_type,
                upload=upload.path,
                size=upload.size,
                settings=settings,
                store=store,
            )
        )
    finally:
        upload.path.unlink(missing_ok=True)
    return AssetPublic.model_validate(asset)


@router.get("", response_model=Page[AssetPublic], summary="List this key's assets")
def list_assets(
    key: CurrentKey, session: SessionDep, limit: Limit = 20, offset: Offset = 0
) -> Page[AssetPublic]:
    rows, total = svc.list_assets(session=session, owner=key, limit=limit, offset=offset)
    items = [AssetPublic.model_validate(r) for r in rows]
    return Page[AssetPublic](items=items, total=total, limit=limit, offset=offset)


@router.get("/{asset_id}", response_model=AssetPublic, responses=NOT_FOUND, summary="An asset")
def get_asset(asset_id: AssetId, key: CurrentKey, session: SessionDep) -> AssetPublic:
    return AssetPublic.model_validate(svc.get_asset(session=session, owner=key, asset_id=asset_id))


@router.delete(
    "/{asset_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_model=None,
    responses={**NOT_FOUND, **CONFLICT},
    summary="Delete an asset",
)
def delete_asset(asset_id: AssetId, key: CurrentKey, session: SessionDep, store: StoreDep) -> None:
    svc.delete_asset(session=session, owner=key, asset_id=asset_id, store=store)
