"""Sequences: register a readable folder, take an uploaded archive, list, show, delete."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive
from osdar_platform.models import ACTIVE_STATES, ApiKey, Job, Sequence, new_id
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectStore
from service.errors import Conflict, Forbidden, Invalid, NotFound
from service.services.ownership import owned_or_404
from worker.orchestration.inspect import InspectionError, inspect_sequence


def _inspect(folder: Path, loc: tuple[str | int, ...]) -> dict[str, Any]:
    # The pipeline (numpy, the OSDaR23 reader) is imported here, at request time only.

    try:
        return inspect_sequence(folder)
    except InspectionError as exc:
        raise Invalid(str(exc), loc=loc) from exc


def _row(
    *, owner: ApiKey, seq_id: str, name: str, source: str, folder: Path, summary: dict[str, Any]
) -> Sequence:
    return Sequence(
        id=seq_id,
        owner_id=owner.id,
        name=name[:255],
        source=source,
        path=str(folder),
        frames=int(summary.get("frames") or 0),
        cameras=list(summary.get("cameras") or []),
        time_span_s=float(summary.get("time_span_s") or 0.0),
        validation={"ok": True, **summary},
        state="ready",
    )


def _allowed(path: Path, settings: Settings) -> bool:
    roots = [Path(r).resolve() for r in settings.sequence_roots]
    return not roots or any(path == r or r in path.parents for r in roots)


def register_sequence(
    *, session: Session, owner: ApiKey, path: str, name: str | None, settings: Settings
) -> Sequence:
    """Validate the folder at ``path`` (absolute, under the allowed roots) and record it."""
    raw = Path(path)
    if not raw.is_absolute():
        raise Invalid("path must be absolute", loc=("body", "path"))
    folder = raw.resolve()
    if not _allowed(folder, settings):
        raise Forbidden(f"{raw}: outside the folders this service may read (its sequence roots)")
    if not folder.is_dir():
        raise NotFound(f"{raw}: no such folder")
    summary = _inspect(folder, ("body", "path"))
    seq = _row(
        owner=owner,
        seq_id=new_id(),
        name=name or folder.name,
        source="path",
        folder=folder,
        summary=summary,
    )
    session.add(seq)
    session.commit()
    return seq


def create_uploaded_sequence(
    *,
    session: Session,
    owner: ApiKey,
    archive: Path,
    sha256: str,
    name: str | None,
    settings: Settings,
    store: ObjectStore,
) -> Sequence:
    """Extract an uploaded archive safely into a fresh folder, validate it, record it.

    The archive itself is kept in the object store (``content_key``) so that workers
    without the shared sequences folder can fetch it.
    """
    seq_id = new_id()
    dest = Path(settings.sequences_dir).resolve() / seq_id
    try:
        try:
            result = extract_archive(archive, dest, ArchiveLimits.from_settings(settings))
        except UnsafeArchive as exc:
            raise Invalid(f"archive refused: {exc}", loc=("body",)) from exc
        folder = result.root
        summary = _inspect(folder, ("body",))
        summary["archive"] = {
            "kind": result.kind,
            "members": result.members,
            "bytes": result.total_bytes,
            "sha256": sha256,
        }
        content_key = f"sequences/{seq_id}/source.{result.kind}"
        store.put_file(content_key, archive)
        seq = _row(
            owner=owner,
            seq_id=seq_id,
            name=name or summary.get("name") or folder.name,
            source="upload",
            folder=folder,
            summary=summary,
        )
        seq.content_key = content_key
        session.add(seq)
        session.commit()
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    return seq


def get_sequence(*, session: Session, owner: ApiKey, sequence_id: str) -> Sequence:
    return owned_or_404(session, Sequence, sequence_id, owner=owner, what="sequence")


def list_sequences(
    *, session: Session, owner: ApiKey, limit: int, offset: int
) -> tuple[list[Sequence], int]:
    where = Sequence.owner_id == owner.id
    total = session.scalar(select(func.count()).select_from(Sequence).where(where)) or 0
    rows = session.scalars(
        select(Sequence)
        .where(where)
        .order_by(Sequence.created_at.desc(), Sequence.id)
        .limit(limit)
        .offset(offset)
    )
    return list(rows), total


def delete_sequence(
    *, session: Session, owner: ApiKey, sequence_id: str, settings: Settings, store: ObjectStore
) -> None:
    """Forget a sequence (its jobs keep their results); 409 while jobs on it are active.

    An uploaded sequence's extracted folder and stored archive are removed; a registered
    folder is never touched.
    """
    seq = get_sequence(session=session, owner=owner, sequence_id=sequence_id)
    active = session.scalar(
        select(func.count())
        .select_from(Job)
        .where(Job.sequence_id == seq.id, Job.state.in_(ACTIVE_STATES))
    )
    if active:
        raise Conflict(f"sequence {sequence_id} has {active} active job(s): cancel them first")
    source, folder, content_key = seq.source, Path(seq.path), seq.content_key
    session.delete(seq)
    session.commit()
    if source == "upload":
        root = Path(settings.sequences_dir).resolve() / sequence_id
        if root == folder or root in folder.parents:
            shutil.rmtree(root, ignore_errors=True)
        if content_key:
            store.delete(content_key)
