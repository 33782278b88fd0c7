"""Assets: uploaded obstacle meshes, checked and kept in the object store."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive
from osdar_platform.catalog import MESH_ARCHIVE_TYPES, MESH_FILE_TYPES
from osdar_platform.models import ACTIVE_STATES, ApiKey, Asset, Job, new_id
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectStore
from service.errors import Conflict, Invalid
from service.schemas import spec_asset_ids
from service.services.ownership import owned_or_404
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
    """Load the mesh with its explicit file type (caps on vertices and faces), store it.
    An archive (``zip``, ``tar.gz``: an OBJ with its MTL and images, or a glTF with its
    files) is extracted safely, must hold exactly one mesh file whose references stay
    inside it, and is stored as uploaded."""

    try:
        if file_type in MESH_ARCHIVE_TYPES:
            info = _inspect_archive(upload, settings)
        else:
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
    return owned_or_404(session, Asset, asset_id, owner=owner, what="asset")


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
    if any(asset_id == used for spec in active_specs for _, used in spec_asset_ids(spec)):
        raise Conflict(f"asset {asset_id} is used by an active job")
    key = asset.store_key
    session.delete(asset)
    session.commit()
    store.delete(key)


_REF = re.compile(rb"(?m)^\s*(?:mtllib|map_\w+|bump|norm|disp)\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$")


def _inspect_archive(upload: Path, settings: Settings) -> dict[str, Any]:
    """Counts of the one mesh file in the archive; InspectionError for anything else
    (unsafe archive, no or several mesh files, a reference leaving the archive)."""
    inner_types = tuple(t for t in MESH_FILE_TYPES if t not in MESH_ARCHIVE_TYPES)
    tmp = Path(tempfile.mkdtemp(prefix="asset_", dir=upload.parent))
    try:
        try:
            res = extract_archive(upload, tmp / "x", ArchiveLimits.from_settings(settings))
        except UnsafeArchive as exc:
            raise InspectionError(f"archive refused: {exc}") from exc
        root = res.dest.resolve()
        meshes = sorted(p for p in root.rglob("*") if p.is_file()
                        and p.suffix.lower().lstrip(".") in inner_types)  # fmt: skip
        if len(meshes) != 1:
            names = [str(p.relative_to(root)) for p in meshes][:10]
            raise InspectionError(
                f"the archive must hold exactly one mesh file ({', '.join(inner_types)}), "
                f"found {len(meshes)}: {names}"
            )
        mesh = meshes[0]
        for ref, base in _references(mesh):
            target = (base / unquote(ref).replace("\\", "/")).resolve()
            alt = (base / Path(unquote(ref)).name).resolve()
            inside = [t for t in (target, alt) if t.is_relative_to(root) and t.is_file()]
            if not inside:
                raise InspectionError(
                    f"{mesh.name} references {ref[:80]!r}, not a file in the archive"
                )
        ft = mesh.suffix.lower().lstrip(".")
        if ft == "gltf" and any(True for _ in _references(mesh)):
            raise InspectionError(
                "a .gltf in an archive must embed its buffers and images (data: URIs) or "
                "be a .glb; OBJ files may reference their .mtl and images"
            )
        info = inspect_mesh(mesh, ft, max_vertices=settings.max_mesh_vertices,
                            max_faces=settings.max_mesh_faces)  # fmt: skip
        info["inner"] = str(mesh.relative_to(root))
        return info
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _references(mesh: Path) -> list[tuple[str, Path]]:
    """(reference, folder it is relative to) of an OBJ's material libraries and their
    texture maps, or of a glTF's external buffer and image URIs."""
    out: list[tuple[str, Path]] = []
    ft = mesh.suffix.lower()
    if ft == ".obj":
        for m in _REF.finditer(mesh.read_bytes()):
            ref = m.group(1).decode("utf-8", "replace")
            out.append((ref, mesh.parent))
            lib = (mesh.parent / ref).resolve()
            if ref.lower().endswith(".mtl") and lib.is_file() and lib.is_relative_to(mesh.parent):
                out += [(x.group(1).decode("utf-8", "replace"), lib.parent)
                        for x in _REF.finditer(lib.read_bytes())]  # fmt: skip
    elif ft == ".gltf":
        try:
            doc = json.loads(mesh.read_bytes())
        except ValueError as exc:
            raise InspectionError(f"gltf: not JSON ({exc})") from exc
        for section in ("buffers", "images"):
            for item in doc.get(section, []) if isinstance(doc, dict) else []:
                uri = item.get("uri", "") if isinstance(item, dict) else ""
                if uri and not uri.startswith("data:"):
                    out.append((uri, mesh.parent))
    return out
