"""Streaming objects out of the store, with single-range ``Range`` support (RFC 9110)."""

from __future__ import annotations

import re
from typing import Any, Literal

from fastapi.responses import RedirectResponse, Response, StreamingResponse

from osdar_platform.store import ObjectNotFound, ObjectStore, StoreError, presigned_url
from service.errors import NotFound

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


def parse_range(header: str | None, size: int) -> tuple[int, int] | Literal["unsatisfiable"] | None:
    """(start, end inclusive), None (serve whole), or "unsatisfiable"."""
    if not header:
        return None
    m = _RANGE.match(header.strip())
    if m is None:  # multiple ranges or another unit: the whole object is a valid answer
        return None
    first, last = m.groups()
    if not first and not last:
        return None
    if not first:  # suffix: the last N bytes
        n = int(last)
        if n == 0 or size == 0:
            return "unsatisfiable"
        return max(0, size - n), size - 1
    start = int(first)
    end = min(int(last), size - 1) if last else size - 1
    if start >= size or (last and int(last) < start):
        return "unsatisfiable"
    return start, end


def archive_media_type(name: str) -> str:
    """The media type of a published archive, by its file name (``archive.tar.gz``)."""
    if name.endswith((".tar.gz", ".tgz")):
        return "application/gzip"
    return "application/zip" if name.endswith(".zip") else "application/x-tar"


def image_media_type(name: str) -> str:
    """The media type of a preview image: JPEG by its suffix, PNG otherwise."""
    return "image/jpeg" if name.endswith((".jpg", ".jpeg")) else "image/png"


def stream_object(
    store: ObjectStore,
    key: str,
    *,
    range_header: str | None,
    media_type: str,
    filename: str | None = None,
) -> Response:
    try:
        size = store.size(key)
    except ObjectNotFound as exc:
        raise NotFound("the object is missing from the store") from exc
    headers = {"Accept-Ranges": "bytes"}
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    rng = parse_range(range_header, size)
    if isinstance(rng, str):  # "unsatisfiable"
        return Response(status_code=416, headers={**headers, "Content-Range": f"bytes */{size}"})
    if rng is None:
        headers["Content-Length"] = str(size)
        return StreamingResponse(store.open_read(key), media_type=media_type, headers=headers)
    start, end = rng
    headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    headers["Content-Length"] = str(end - start + 1)
    return StreamingResponse(
        store.open_read(key, start, end), status_code=206, media_type=media_type, headers=headers
    )


def download_object(
    store: ObjectStore,
    key: str,
    *,
    range_header: str | None,
    media_type: str,
    filename: str | None = None,
    ttl_s: int,
) -> Response:
    """A download after the caller's ownership check: with a store that presigns (S3),
    307 to a URL valid ``ttl_s`` seconds (the store serves the bytes and honours
    ``Range``, so a client resumes there); otherwise the API streams (``Range``: 206)."""
    try:
        url = presigned_url(store, key, expires_s=ttl_s, filename=filename)
    except StoreError:
        url = None  # cannot sign (no credentials): stream instead
    if url is None:
        return stream_object(
            store, key, range_header=range_header, media_type=media_type, filename=filename
        )
    return RedirectResponse(url, status_code=307, headers={"Cache-Control": "no-store"})


#: OpenAPI description of a streamed download.
def download_responses(
    media_type: str, *, redirect: bool = False
) -> dict[int | str, dict[str, Any]]:
    """200 / 206 / 416 of a streamed download, and the 307 of :func:`download_object`."""
    out: dict[int | str, dict[str, Any]] = {}
    if redirect:
        out[307] = {
            "description": "With an S3 store: the object at a short-lived presigned URL "
            "(`Location`; Range is honoured there)",
            "headers": {"Location": {"schema": {"type": "string"}}},
        }
    return out | {
        200: {"content": {media_type: {"schema": {"type": "string", "format": "binary"}}}},
        206: {
            "description": "Partial content (Range)",
            "content": {media_type: {"schema": {"type": "string", "format": "binary"}}},
        },
        416: {"description": "Range not satisfiable"},
    }
