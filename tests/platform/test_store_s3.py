"""The object store: one contract, the local file system and S3 (moto's server on loopback)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from osdar_platform.settings import Settings
from osdar_platform.store import LocalStore, ObjectNotFound, ObjectStore, S3Store, store_from_url


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3_endpoint() -> Iterator[str]:
    from moto.server import ThreadedMotoServer

    port = _free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.stop()


def _s3_settings(endpoint: str, bucket: str) -> Settings:
    return Settings(
        store_url=f"s3://{bucket}/some/prefix",
        s3_endpoint_url=endpoint,
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
    )


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> ObjectStore:
    if request.param == "local":
        return store_from_url(f"file://{tmp_path}/store")
    endpoint = request.getfixturevalue("s3_endpoint")
    bucket = f"b-{abs(hash(request.node.name)) % 10**8}"
    settings = _s3_settings(endpoint, bucket)
    s3 = store_from_url(str(settings.store_url), settings)
    assert isinstance(s3, S3Store) and s3.prefix == "some/prefix"
    s3.create_bucket()
    return s3


def test_round_trip_and_ranges(store: ObjectStore, tmp_path: Path) -> None:
    data = bytes(range(256)) * 12_000  # 3 MB: several read chunks
    src = tmp_path / "src.bin"
    src.write_bytes(data)
    store.put_file("jobs/j1/attempt-1/result.tar", src)
    store.put_bytes("jobs/j1/attempt-1/metrics.json", b'{"a": 1}')
    assert store.exists("jobs/j1/attempt-1/result.tar")
    assert store.size("jobs/j1/attempt-1/result.tar") == len(data)
    assert b"".join(store.open_read("jobs/j1/attempt-1/result.tar")) == data
    assert b"".join(store.open_read("jobs/j1/attempt-1/result.tar", 10, 19)) == data[10:20]
    assert b"".join(store.open_read("jobs/j1/attempt-1/result.tar", len(data) - 3)) == data[-3:]
    big = b"".join(store.open_read("jobs/j1/attempt-1/result.tar", 5, 2_500_000))
    assert big == data[5:2_500_001]
    out = tmp_path / "out.bin"
    store.get_file("jobs/j1/attempt-1/result.tar", out)
    assert out.read_bytes() == data
    assert store.list("jobs/j1/") == [
        "jobs/j1/attempt-1/metrics.json",
        "jobs/j1/attempt-1/result.tar",
    ]
    assert store.list("jobs/none") == []
    store.put_bytes("jobs/j1/attempt-1/metrics.json", b"{}")  # overwrite
    assert b"".join(store.open_read("jobs/j1/attempt-1/metrics.json")) == b"{}"
    store.delete("jobs/j1/attempt-1/metrics.json")
    store.delete("jobs/j1/attempt-1/metrics.json")  # absent: no error
    assert not store.exists("jobs/j1/attempt-1/metrics.json")
    with pytest.raises(ObjectNotFound):
        store.size("jobs/j1/attempt-1/metrics.json")
    with pytest.raises(ObjectNotFound):
        store.open_read("nope")


@pytest.mark.parametrize("key", ["", "/abs", "a/../b", "a//b", "a/", "..", "a\\b"])
def test_bad_keys_are_refused(store: ObjectStore, key: str) -> None:
    with pytest.raises(ValueError, match="invalid store key"):
        store.put_bytes(key, b"x")


def test_local_writes_are_atomic(tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "s")
    src = tmp_path / "src"
    src.write_bytes(b"x" * 1000)

    class Boom(Exception):
        pass

    def failing(f) -> None:  # type: ignore[no-untyped-def]
        f.write(b"partial")
        raise Boom

    with pytest.raises(Boom):
        store._atomic("k/result.tar", failing)
    assert not store.exists("k/result.tar")
    assert list((tmp_path / "s").rglob("*.part")) == []  # no temporary left
    store.put_file("k/result.tar", src)
    assert store.list() == ["k/result.tar"]


def test_a_consumed_file_is_stored_whole_and_outlives_its_source(
    store: ObjectStore, tmp_path: Path
) -> None:
    """``consume=True``: the caller only deletes the file afterwards; the stored object
    is the file's bytes (local: the same inode, no byte copied) and survives the delete
    and a new file written at the source's path."""
    src = tmp_path / "chunk.tar"
    src.write_bytes(b"\2" * 300_000)
    store.put_file("jobs/j/chunks/0000.tar", src, consume=True)
    if isinstance(store, LocalStore):
        assert store._path("jobs/j/chunks/0000.tar").stat().st_ino == src.stat().st_ino
        assert list(store.root.rglob("*.link")) == []  # no temporary left
    src.unlink()
    src.write_bytes(b"new")  # a new file at the old path
    assert b"".join(store.open_read("jobs/j/chunks/0000.tar")) == b"\2" * 300_000
    store.put_file("jobs/j/chunks/0000.tar", src, consume=True)  # replaces atomically
    assert b"".join(store.open_read("jobs/j/chunks/0000.tar")) == b"new"


def test_a_consumed_file_on_another_device_is_copied(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import os

    def cross_device(src: object, dst: object) -> None:
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    monkeypatch.setattr(os, "link", cross_device)
    store = LocalStore(tmp_path / "s")
    src = tmp_path / "a.bin"
    src.write_bytes(b"abc" * 1000)
    store.put_file("k/a.bin", src, consume=True)
    assert store._path("k/a.bin").stat().st_ino != src.stat().st_ino
    assert b"".join(store.open_read("k/a.bin")) == b"abc" * 1000


def test_s3_object_appears_only_complete(s3_endpoint: str, tmp_path: Path) -> None:
    """A multipart upload (past the 8 MB threshold) is invisible until completed."""
    settings = _s3_settings(s3_endpoint, "multipart")
    store = store_from_url(str(settings.store_url), settings)
    store.create_bucket()  # type: ignore[attr-defined]
    src = tmp_path / "big.bin"
    src.write_bytes(b"\1" * (9 * 1024 * 1024))
    store.put_file("jobs/big/result.tar", src)
    assert store.size("jobs/big/result.tar") == src.stat().st_size
    raw = store.client.list_objects_v2(Bucket="multipart")["Contents"]  # type: ignore[attr-defined]
    assert [o["Key"] for o in raw] == ["some/prefix/jobs/big/result.tar"]


def test_unreachable_s3_is_a_store_error(tmp_path: Path) -> None:
    from osdar_platform.store import StoreError

    settings = _s3_settings(f"http://127.0.0.1:{_free_port()}", "x")
    store = store_from_url(str(settings.store_url), settings)
    # botocore makes one attempt: the retries are osdar_platform/retry.py's alone
    assert store.client.meta.config.retries["total_max_attempts"] == 1  # type: ignore[attr-defined]
    calls = []
    store.client.meta.events.register(  # type: ignore[attr-defined]
        "before-send.s3.*", lambda **kw: calls.append(kw["request"].url)
    )
    with pytest.raises(StoreError):
        store.put_bytes("a", b"b")
    assert len(calls) == 1, calls


def test_store_url_schemes(tmp_path: Path) -> None:
    assert isinstance(store_from_url(f"file://{tmp_path}"), LocalStore)
    with pytest.raises(ValueError, match="no bucket"):
        store_from_url("s3:///x")
    with pytest.raises(ValueError, match="expected"):
        store_from_url("ftp://x")
