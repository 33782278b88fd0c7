"""The archive attack set: every attack refused, nothing written outside, nothing left."""

from __future__ import annotations

import io
import os
import stat
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import pytest

from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive


def _tar(path: Path, members: list[tuple[tarfile.TarInfo, bytes | None]], mode: str = "w") -> Path:
    with tarfile.open(path, mode) as tf:
        for info, data in members:
            if data is not None:
                info.size = len(data)
            tf.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


def _info(name: str, kind: bytes = tarfile.REGTYPE, **kw: object) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    for k, v in kw.items():
        setattr(info, k, v)
    return info


def _zip(path: Path, members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> Path:
    with (
        warnings.catch_warnings(),  # "Duplicate name" is the point of one attack
        zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf,
    ):
        warnings.simplefilter("ignore")
        for name, data in members:
            zf.writestr(name, data)
    return path


def _zip_symlink(path: Path) -> Path:
    info = zipfile.ZipInfo("seq/link")
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return _zip(path, [(info, b"/etc/passwd")])


def _zip_device(path: Path) -> Path:
    info = zipfile.ZipInfo("seq/dev")
    info.external_attr = (stat.S_IFCHR | 0o666) << 16
    return _zip(path, [(info, b"")])


ATTACKS: dict[str, tuple[Callable[[Path], Path], str]] = {
    "tar zip-slip": (lambda p: _tar(p, [(_info("seq/../../evil.txt"), b"x")]), "'..'"),
    "tar absolute": (lambda p: _tar(p, [(_info("/tmp/evil.txt"), b"x")]), "absolute"),
    "tar symlink out": (
        lambda p: _tar(p, [(_info("seq/l", tarfile.SYMTYPE, linkname="/etc"), None)]),
        "links",
    ),
    "tar symlink inside": (
        lambda p: _tar(p, [(_info("seq/l", tarfile.SYMTYPE, linkname="a.txt"), None)]),
        "links",
    ),
    "tar hardlink out": (
        lambda p: _tar(p, [(_info("seq/h", tarfile.LNKTYPE, linkname="/etc/passwd"), None)]),
        "links",
    ),
    "tar device": (
        lambda p: _tar(p, [(_info("seq/dev", tarfile.CHRTYPE, devmajor=1, devminor=3), None)]),
        "special",
    ),
    "tar fifo": (lambda p: _tar(p, [(_info("seq/fifo", tarfile.FIFOTYPE), None)]), "special"),
    "tar long name": (lambda p: _tar(p, [(_info("seq/" + "a/" * 300 + "f"), b"x")]), "longer"),
    "tar nested archive": (lambda p: _tar(p, [(_info("seq/inner.zip"), b"PK..")]), "inside"),
    "tar duplicate": (
        lambda p: _tar(p, [(_info("seq/a"), b"1"), (_info("seq/a"), b"2")]),
        "duplicate",
    ),
    "tar 10,001 members": (
        lambda p: _tar(p, [(_info(f"seq/{i}"), b"") for i in range(10_001)]),
        "more than 10000 members",
    ),
    "tar.gz ratio bomb": (
        lambda p: _tar(p, [(_info("seq/zeros.pcd"), b"\0" * (24 * 2**20))], mode="w:gz"),
        "ratio",
    ),
    "tar over the total": (
        lambda p: _tar(p, [(_info(f"seq/{i}.png"), b"\1" * 2**20) for i in range(40)]),
        "extracted size",
    ),
    "zip zip-slip": (lambda p: _zip(p, [("../evil.txt", b"x")]), "'..'"),
    "zip absolute": (lambda p: _zip(p, [("/tmp/evil.txt", b"x")]), "absolute"),
    "zip drive letter": (lambda p: _zip(p, [("C:/evil.txt", b"x")]), "absolute"),
    "zip backslash": (lambda p: _zip(p, [("..\\evil.txt", b"x")]), "backslash"),
    "zip symlink": (_zip_symlink, "links"),
    "zip device": (_zip_device, "special"),
    "zip ratio bomb": (lambda p: _zip(p, [("seq/zeros", b"\0" * (24 * 2**20))]), "ratio"),
    "zip nested archive": (lambda p: _zip(p, [("seq/inner.tar.gz", b"x")]), "inside"),
    "zip duplicate": (lambda p: _zip(p, [("seq/a", b"1"), ("seq/a", b"2")]), "duplicate"),
    "zip 10,001 members": (
        lambda p: _zip(p, [(f"seq/{i}", b"") for i in range(10_001)]),
        "more than 10000 members",
    ),
    "not an archive": (lambda p: (p.write_bytes(b"hello" * 100), p)[1], "not a tar or zip"),
    "truncated tar.gz": (
        lambda p: (
            p.write_bytes(
                _tar(p, [(_info("seq/a"), os.urandom(100_000))], "w:gz").read_bytes()[:3000]
            ),
            p,
        )[1],
        "unreadable",
    ),
}

LIMITS = ArchiveLimits(max_members=10_000, max_total_bytes=32 * 2**20, max_name_length=512)


@pytest.mark.parametrize("name", list(ATTACKS))
def test_attack_is_refused_and_nothing_is_written(tmp_path: Path, name: str) -> None:
    make, needle = ATTACKS[name]
    src = tmp_path / "in"
    src.mkdir()
    archive = make(src / "upload.bin")
    work = tmp_path / "work"
    work.mkdir()
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(UnsafeArchive, match=needle):
        extract_archive(archive, work / "dest", LIMITS)
    after = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert after == before  # nothing outside, and the destination is gone
    assert not Path("/tmp/evil.txt").exists()


def test_good_archives_extract(tmp_path: Path) -> None:
    files = {"seq/seq_labels.json": b"{}", "seq/lidar/000.pcd": b"\1" * 5000}
    t = _tar(tmp_path / "a.tar.gz", [(_info(n), d) for n, d in files.items()], mode="w:gz")
    z = _zip(tmp_path / "a.zip", list(files.items()))
    for archive in (t, z):
        dest = tmp_path / f"out_{archive.name}"
        res = extract_archive(archive, dest, LIMITS)
        assert res.members == 2 and res.total_bytes == 5002
        assert res.root == dest / "seq"
        for n, d in files.items():
            assert (dest / n).read_bytes() == d
        assert res.kind == ("zip" if archive.suffix == ".zip" else "tar")


def test_destination_must_be_fresh(tmp_path: Path) -> None:
    archive = _zip(tmp_path / "a.zip", [("seq/a", b"1")])
    (tmp_path / "dest").mkdir()
    with pytest.raises(FileExistsError):
        extract_archive(archive, tmp_path / "dest", LIMITS)


def test_zip_sizes_are_counted_while_streaming(tmp_path: Path) -> None:
    """A zip whose header under-states a member's size is caught by the byte counter."""
    archive = _zip(tmp_path / "a.zip", [("seq/a", b"\2" * 100_000)])
    raw = bytearray(archive.read_bytes())
    # patch the uncompressed size (central directory and local header) to 10 bytes
    for sig, off in ((b"PK\x01\x02", 24), (b"PK\x03\x04", 22)):
        i = raw.find(sig)
        raw[i + off : i + off + 4] = (10).to_bytes(4, "little")
    archive.write_bytes(bytes(raw))
    with pytest.raises(UnsafeArchive):
        extract_archive(archive, tmp_path / "dest", LIMITS)
    assert not (tmp_path / "dest").exists()
