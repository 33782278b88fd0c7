"""Assets: uploaded obstacle meshes, checked and kept in the object store."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from osdar_platform.models import ACTIVE_STATES, ApiKey, Asset, Job, new_id
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectStore
from service.errors import Conflict, Invalid, NotFound
from worker.orchestration.inspect import InspectionError, inspect_mesh


def create_asset(
    *,
    session: Session,
    owner: ApiKey,
    name: str,
    file_type: str,
    upload: Path,
    size: int,
    settings: Settings,
    store: ObjectStore,
) -> Asset:
    """Load the mesh with its explicit file type (caps on vertices and faces), store it."""

    try:
        info = inspect_mesh(
            upload,
            file_type,
            max_vertices=settings.max_mesh_vertices,
            max_faces=settings.max_mesh_faces,
        )
    except InspectionError as exc:
        raise Invalid(str(exc), loc=("body",)) from exc
    asset_id = new_id()
    key = f"assets/{owner.id}/{asset_id}.{file_type}"
    store.put_file(key, upload)
    asset = Asset(
        id=asset_id,
        owner_id=owner.id,
        name=name,
        file_type=file_type,
        store_key=key,
        size=size,
        vertices=info["vertices"],
        faces=info["faces"],
    )
    session.add(asset)
    try:
        session.commit()
    except BaseException:
        store.delete(key)
        raise
    return asset


def get_asset(*, session: Session, owner: ApiKey, asset_id: str) -> Asset:
    asset = session.get(Asset, asset_id)
    if asset is None or asset.owner_id != owner.id:
        raise NotFound(f"asset {asset_id} not found")
    return asset


def list_assets(
    *, session: Session, owner: ApiKey, limit: int, offset: int
) -> tuple[list[Asset], int]:
    where = Asset.owner_id == owner.id
    total = session.scalar(select(func.count()).select_from(Asset).where(where)) or 0
    rows = session.scalars(
        select(Asset)
        .where(where)
        .order_by(Asset.created_at.desc(), Asset.id)
        .limit(limit)
        .offset(offset)
    )
    return list(rows), total


def delete_asset(*, session: Session, owner: ApiKey, asset_id: str, store: ObjectStore) -> None:
    """Delete an asset; 409 while an active job of the key uses it."""
    asset = get_asset(session=session, owner=owner, asset_id=asset_id)
    active_specs = session.scalars(
        select(Job.spec).where(Job.owner_id == owner.id, Job.state.in_(ACTIVE_STATES))
    )
    if any((spec.get("object") or {}).get("asset_id") == asset_id for spec in active_specs):
        raise Conflict(f"asset {asset_id} is used by an active job")
    key = asset.store_key
    session.delete(asset)
    session.commit()
    store.delete(key)
