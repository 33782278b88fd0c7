"""Streaming objects out of the store, with single-range ``Range`` support (RFC 9110)."""

from __future__ import annotations

import re
from typing import Any, Literal

from fastapi.responses import Response, StreamingResponse

from osdar_platform.store import ObjectNotFound, ObjectStore
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


#: OpenAPI description of a streamed download.
def download_responses(media_type: str) -> dict[int | str, dict[str, Any]]:
    return {
        200: {"content": {media_type: {"schema": {"type": "string", "format": "binary"}}}},
        206: {
            "description": "Partial content (Range)",
            "content": {media_type: {"schema": {"type": "string", "format": "binary"}}},
        },
        416: {"description": "Range not satisfiable"},
    }
