"""Receiving a request body as a file: streamed, counted, capped (413 past the cap)."""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from service.errors import BadRequest, PayloadTooLarge


@dataclass(frozen=True)
class Upload:
    path: Path
    size: int
    sha256: str


async def receive_upload(
    chunks: AsyncIterator[bytes],
    *,
    tmp_dir: Path,
    limit: int,
    declared_length: int | None = None,
) -> Upload:
    """Write ``chunks`` to a new file in ``tmp_dir``; stop reading once past ``limit``.

    A declared ``Content-Length`` over the limit is refused before any byte is read; an
    undeclared or lying body is refused as soon as the counter passes the limit, so at
    most ``limit`` plus one chunk is ever read. The partial file is removed on any error.
    """
    if declared_length is not None and declared_length > limit:
        raise PayloadTooLarge(f"body of {declared_length} bytes exceeds the limit of {limit}")
    tmp_dir.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix="upload-", suffix=".part", dir=tmp_dir)
    path = Path(name)
    digest = hashlib.sha256()
    size = 0
    try:
        with os.fdopen(fd, "wb") as f:
            async for chunk in chunks:
                size += len(chunk)
                if size > limit:
                    raise PayloadTooLarge(f"body exceeds the limit of {limit} bytes")
                digest.update(chunk)
                f.write(chunk)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    if size == 0:
        path.unlink(missing_ok=True)
        raise BadRequest("empty body: send the file as the request body")
    return Upload(path=path, size=size, sha256=digest.hexdigest())
