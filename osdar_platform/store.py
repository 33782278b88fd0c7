"""The object store: one interface, the local file system or an S3-compatible service.

Keys are ``/``-separated relative paths (``jobs/<id>/attempt-1/result.tar``). Writes are
atomic: a reader sees the whole object or nothing (local: a temporary file beside the
target, then ``os.replace``; S3: an object appears only once its upload completed).
``open_read(key, start, end)`` streams a byte range (``end`` inclusive, as in HTTP Range).
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Protocol, runtime_checkable
from urllib.parse import unquote, urlparse

import boto3
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

if TYPE_CHECKING:
    from osdar_platform.settings import Settings

CHUNK = 1024 * 1024


class StoreError(OSError):
    """The store failed (unreachable, refused); transient errors are worth a retry."""


class ObjectNotFound(KeyError):
    """No object under that key."""


def check_key(key: str) -> str:
    """A relative key without ``..``, empty parts or a leading ``/``; ValueError otherwise."""
    if not key or key.startswith("/") or "\\" in key or "\x00" in key:
        raise ValueError(f"invalid store key {key!r}")
    if any(p in ("", ".", "..") for p in key.split("/")):
        raise ValueError(f"invalid store key {key!r}")
    return key


@runtime_checkable
class ObjectStore(Protocol):
    """What the service and the workers need from an object store."""

    def put_file(self, key: str, path: str | Path, *, consume: bool = False) -> None:
        """Store the file at ``path`` under ``key`` atomically. ``consume``: the caller
        will not write to ``path`` again (only delete it), so the store may take the
        file's bytes as they are instead of copying them (local: a hard link)."""

    def put_bytes(self, key: str, data: bytes) -> None:
        """Store ``data`` under ``key`` atomically."""

    def open_read(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        """Chunks of bytes ``start..end`` (inclusive; ``None`` = to the end)."""

    def get_file(self, key: str, path: str | Path) -> None:
        """Copy the object to a local file."""

    def size(self, key: str) -> int:
        """Size in bytes; ObjectNotFound if absent."""

    def exists(self, key: str) -> bool: ...

    def delete(self, key: str) -> None:
        """Remove the object (no error if absent)."""

    def list(self, prefix: str = "") -> list[str]:
        """Keys starting with ``prefix``, sorted."""


class LocalStore:
    """Objects as files under ``root``."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()  # created by the first write

    def __repr__(self) -> str:
        return f"LocalStore({str(self.root)!r})"

    def _path(self, key: str) -> Path:
        return self.root / check_key(key)

    def _atomic(self, key: str, write: Any) -> None:
        target = self._path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def put_file(self, key: str, path: str | Path, *, consume: bool = False) -> None:
        if consume and self._link(key, Path(path)):
            return

        def write(f: BinaryIO) -> None:
            with open(path, "rb") as src:
                shutil.copyfileobj(src, f, CHUNK)

        self._atomic(key, write)

    def _link(self, key: str, path: Path) -> bool:
        """``path`` under ``key`` as a hard link (its data synced first, then the link
        renamed into place): no byte copied. False where the file system cannot link
        there (another device, no hard links); the caller copies then."""
        target = self._path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.{os.getpid()}.{os.urandom(4).hex()}.link"
        try:
            os.link(path, tmp)
        except OSError as exc:
            if exc.errno in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP):
                return False
            raise
        try:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return True

    def put_bytes(self, key: str, data: bytes) -> None:
        self._atomic(key, lambda f: f.write(data))

    def open_read(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        path = self._path(key)
        try:
            f = open(path, "rb")
        except FileNotFoundError as exc:
            raise ObjectNotFound(key) from exc
        return _read_range(f, start, end)

    def get_file(self, key: str, path: str | Path) -> None:
        try:
            shutil.copyfile(self._path(key), path)
        except FileNotFoundError as exc:
            raise ObjectNotFound(key) from exc

    def size(self, key: str) -> int:
        try:
            return self._path(key).stat().st_size
        except FileNotFoundError as exc:
            raise ObjectNotFound(key) from exc

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def delete(self, key: str) -> None:
        self._path(key).unlink(missing_ok=True)

    def list(self, prefix: str = "") -> list[str]:
        out: list[str] = []
        if not self.root.is_dir():
            return out
        for p in self.root.rglob("*"):
            if p.is_file() and not (p.name.startswith(".") and p.name.endswith(".part")):
                key = p.relative_to(self.root).as_posix()
                if key.startswith(prefix):
                    out.append(key)
        return sorted(out)


def _read_range(f: BinaryIO, start: int, end: int | None) -> Iterator[bytes]:
    with f:
        f.seek(start)
        remaining = None if end is None else end - start + 1
        while remaining is None or remaining > 0:
            chunk = f.read(CHUNK if remaining is None else min(CHUNK, remaining))
            if not chunk:
                break
            if remaining is not None:
                remaining -= len(chunk)
            yield chunk


class S3Store:
    """Objects in an S3 bucket (AWS, MinIO, moto...) under an optional key prefix."""

    def __init__(
        self,
        bucket: str,
        prefix: str = "",
        *,
        endpoint_url: str | None = None,
        region: str = "us-east-1",
        access_key_id: str | None = None,
        secret_access_key: str | None = None,
        client: Any = None,
    ) -> None:

        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self.client = client or boto3.client(
            "s3",
            endpoint_url=endpoint_url,
            region_name=region,
            aws_access_key_id=access_key_id,
            aws_secret_access_key=secret_access_key,
            config=Config(
                # one attempt per call: the retries are osdar_platform/retry.py's alone
                retries={"total_max_attempts": 1, "mode": "standard"},
                s3={"addressing_style": "path"},
                signature_version="s3v4",  # presigned URLs too (X-Amz-Expires, up to 7 days)
                connect_timeout=5,
                read_timeout=60,
            ),
        )

    def __repr__(self) -> str:
        return f"S3Store(bucket={self.bucket!r}, prefix={self.prefix!r})"

    def _key(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _call(self, fn: Any, key: str, **kwargs: Any) -> Any:

        try:
            return fn(**kwargs)
        except ClientError as exc:
            code = str(exc.response.get("Error", {}).get("Code", ""))
            if code in ("404", "NoSuchKey", "NotFound"):
                raise ObjectNotFound(key) from exc
            raise StoreError(f"s3 {self.bucket}/{key}: {exc}") from exc
        except BotoCoreError as exc:
            raise StoreError(f"s3 {self.bucket}/{key}: {exc}") from exc

    def create_bucket(self) -> None:
        """Create the bucket if it does not exist (tests, first start of a MinIO)."""

        try:
            self.client.head_bucket(Bucket=self.bucket)
        except ClientError:
            self.client.create_bucket(Bucket=self.bucket)

    def put_file(self, key: str, path: str | Path, *, consume: bool = False) -> None:
        # upload_file switches to a multipart upload for big files; the object becomes
        # visible only when CompleteMultipartUpload succeeds.
        self._call(
            self.client.upload_file,
            key,
            Filename=str(path),
            Bucket=self.bucket,
            Key=self._key(key),
        )

    def put_bytes(self, key: str, data: bytes) -> None:
        self._call(self.client.put_object, key, Bucket=self.bucket, Key=self._key(key), Body=data)

    def open_read(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        kwargs: dict[str, Any] = {"Bucket": self.bucket, "Key": self._key(key)}
        if start or end is not None:
            kwargs["Range"] = f"bytes={start}-{'' if end is None else end}"
        body = self._call(self.client.get_object, key, **kwargs)["Body"]
        return _stream_body(body)

    def get_file(self, key: str, path: str | Path) -> None:
        self._call(
            self.client.download_file,
            key,
            Bucket=self.bucket,
            Key=self._key(key),
            Filename=str(path),
        )

    def size(self, key: str) -> int:
        head = self._call(self.client.head_object, key, Bucket=self.bucket, Key=self._key(key))
        return int(head["ContentLength"])

    def exists(self, key: str) -> bool:
        try:
            self.size(key)
        except ObjectNotFound:
            return False
        return True

    def delete(self, key: str) -> None:
        self._call(self.client.delete_object, key, Bucket=self.bucket, Key=self._key(key))

    def presigned_url(self, key: str, *, expires_s: int, filename: str | None = None) -> str:
        """A URL that GETs the object (``Range`` honoured by S3) without credentials, for
        ``expires_s`` seconds; ``filename`` sets the download's Content-Disposition."""
        params: dict[str, Any] = {"Bucket": self.bucket, "Key": self._key(key)}
        if filename:
            params["ResponseContentDisposition"] = f'attachment; filename="{filename}"'
        url = self._call(self.client.generate_presigned_url, key, ClientMethod="get_object",
                         Params=params, ExpiresIn=int(expires_s))  # fmt: skip
        return str(url)

    def list(self, prefix: str = "") -> list[str]:
        base = f"{self.prefix}/" if self.prefix else ""
        full, strip = base + prefix.lstrip("/"), len(base)
        out: list[str] = []
        paginator = self.client.get_paginator("list_objects_v2")
        for page in self._call(paginator.paginate, prefix, Bucket=self.bucket, Prefix=full):
            out.extend(obj["Key"][strip:] for obj in page.get("Contents", []))
        return sorted(out)


def _stream_body(body: Any) -> Iterator[bytes]:
    try:
        yield from body.iter_chunks(CHUNK)
    finally:
        body.close()


def presigned_url(
    store: ObjectStore, key: str, *, expires_s: int, filename: str | None = None
) -> str | None:
    """A short-lived direct download URL of ``key`` when the store can make one (S3), None
    otherwise (the local store: the API streams the bytes itself)."""
    make = getattr(store, "presigned_url", None)
    if make is None:
        return None
    return str(make(key, expires_s=expires_s, filename=filename))


def store_from_url(url: str, settings: Settings | None = None) -> ObjectStore:
    """``file:///abs/path`` (or ``file://rel/path``) -> LocalStore; ``s3://bucket/prefix``
    -> S3Store with the endpoint and credentials of ``settings``."""
    parsed = urlparse(url)
    if parsed.scheme == "file":
        return LocalStore(unquote(parsed.netloc + parsed.path))
    if parsed.scheme == "s3":
        if not parsed.netloc:
            raise ValueError(f"store url {url!r}: no bucket")
        secret = settings.aws_secret_access_key if settings else None
        return S3Store(
            parsed.netloc,
            parsed.path.strip("/"),
            endpoint_url=settings.s3_endpoint_url if settings else None,
            region=settings.s3_region if settings else "us-east-1",
            access_key_id=settings.aws_access_key_id if settings else None,
            secret_access_key=secret.get_secret_value() if secret else None,
        )
    raise ValueError(f"store url {url!r}: expected file://PATH or s3://BUCKET[/PREFIX]")
