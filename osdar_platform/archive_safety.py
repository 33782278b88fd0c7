"""Safe extraction of uploaded tar/zip archives into a fresh directory.

An uploaded archive is hostile until proven otherwise. Refused, with
:class:`UnsafeArchive` naming the member and the reason:

- absolute paths, drive letters, ``..`` components (zip-slip), backslashes, NUL bytes,
  names longer than the cap;
- symlinks, hardlinks, devices, FIFOs, sparse members, duplicate names;
- more members than the cap; more extracted bytes than the cap, counted while the
  bytes are written (a zip's headers are not trusted); extracted/compressed ratios
  beyond the cap (ratio bombs); archives inside the archive (nested bombs: an OSDaR23
  sequence has none, so they are refused rather than left for someone to open).

A first pass reads only the headers (tar) or the central directory (zip) and refuses
before anything is written; the second pass extracts, tar members with ``filter="data"``
(PEP 706), zip members with their bytes counted as they are written. On any refusal the
destination is removed whole: nothing partial stays, nothing was written outside it.
"""

from __future__ import annotations

import shutil
import stat
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO, TYPE_CHECKING, BinaryIO

if TYPE_CHECKING:
    from osdar_platform.settings import Settings

CHUNK = 1024 * 1024
MAX_COMPONENT = 255
NESTED_SUFFIXES = (".zip", ".tar", ".tgz", ".tbz2", ".txz", ".gz", ".bz2", ".xz", ".7z", ".rar")


class UnsafeArchive(ValueError):
    """The archive is refused; the message says which member and why."""


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int = 100_000
    max_total_bytes: int = 60 * 1024**3
    max_name_length: int = 512
    max_ratio: float = 200.0  # extracted / compressed
    ratio_grace_bytes: int = 16 * 1024**2  # small outputs may compress well

    @classmethod
    def from_settings(cls, settings: Settings) -> ArchiveLimits:
        return cls(
            max_members=settings.max_archive_members,
            max_total_bytes=settings.max_archive_total_bytes,
            max_name_length=settings.max_archive_name_length,
            max_ratio=settings.max_archive_ratio,
        )


@dataclass(frozen=True)
class ExtractResult:
    kind: str  # "tar" | "zip"
    dest: Path
    members: int
    total_bytes: int

    @property
    def root(self) -> Path:
        """The single top-level folder if there is exactly one entry and it is a folder."""
        entries = list(self.dest.iterdir())
        if len(entries) == 1 and entries[0].is_dir():
            return entries[0]
        return self.dest


def extract_archive(
    archive: str | Path, dest: str | Path, limits: ArchiveLimits | None = None
) -> ExtractResult:
    """Extract a tar (optionally gz/bz2/xz) or zip archive into the new folder ``dest``.

    Raises
    ------
    UnsafeArchive
        The archive breaks a rule above or is not a readable tar/zip; ``dest`` is removed.
    FileExistsError
        ``dest`` exists already (extraction always goes into a fresh folder).
    """
    archive, dest = Path(archive), Path(dest)
    limits = limits or ArchiveLimits()
    dest.mkdir(parents=True, exist_ok=False)
    try:
        if zipfile.is_zipfile(archive):
            return _extract_zip(archive, dest, limits)
        if tarfile.is_tarfile(archive):
            return _extract_tar(archive, dest, limits)
        raise UnsafeArchive("not a tar or zip archive")
    except UnsafeArchive:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise UnsafeArchive(f"unreadable archive: {exc}") from exc
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise


def _check_name(name: str, limits: ArchiveLimits) -> PurePosixPath:
    """The member's relative path, or UnsafeArchive."""
    if len(name) > limits.max_name_length:
        raise UnsafeArchive(f"member name longer than {limits.max_name_length}: {name[:80]!r}...")
    if "\x00" in name or "\\" in name:
        raise UnsafeArchive(f"member {name!r}: NUL or backslash in the name")
    if name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise UnsafeArchive(f"member {name!r}: absolute path")
    path = PurePosixPath(name)
    if any(part == ".." for part in path.parts):
        raise UnsafeArchive(f"member {name!r}: '..' leads outside the archive")
    if any(len(part) > MAX_COMPONENT for part in path.parts):
        raise UnsafeArchive(f"member {name!r}: a path component is longer than {MAX_COMPONENT}")
    parts = [p for p in path.parts if p not in ("", ".")]
    if not parts:
        raise UnsafeArchive(f"member {name!r}: empty name")
    return PurePosixPath(*parts)


def _is_root_dir(m: tarfile.TarInfo) -> bool:
    """The archive's own root (``.`` or ``./``, as ``tar -C dir .`` and the workers' chunk
    archives write it): a directory that is the destination itself, skipped."""
    return m.isdir() and all(p in ("", ".") for p in m.name.split("/"))


def _check_nested(rel: PurePosixPath) -> None:
    if rel.name.lower().endswith(NESTED_SUFFIXES):
        raise UnsafeArchive(f"member {str(rel)!r}: archives inside the archive are refused")


class _Budget:
    """Counts members and extracted bytes against the limits while extracting."""

    def __init__(self, limits: ArchiveLimits, compressed_size: int) -> None:
        self.limits = limits
        self.compressed = max(compressed_size, 1)
        self.members = 0
        self.total = 0

    def member(self, name: str) -> None:
        self.members += 1
        if self.members > self.limits.max_members:
            raise UnsafeArchive(f"more than {self.limits.max_members} members (at {name!r})")

    def add(self, n: int, name: str) -> None:
        self.total += n
        if self.total > self.limits.max_total_bytes:
            raise UnsafeArchive(
                f"extracted size exceeds {self.limits.max_total_bytes} bytes (at {name!r})"
            )
        if (
            self.total > self.limits.ratio_grace_bytes
            and self.total > self.limits.max_ratio * self.compressed
        ):
            raise UnsafeArchive(
                f"compression ratio exceeds {self.limits.max_ratio:g} (at {name!r}): "
                "refused as a decompression bomb"
            )


def _check_tar_member(m: tarfile.TarInfo, limits: ArchiveLimits) -> PurePosixPath:
    rel = _check_name(m.name, limits)
    if m.issym() or m.islnk():
        raise UnsafeArchive(f"member {m.name!r}: links are refused")
    if m.isdev() or m.isfifo() or not (m.isfile() or m.isdir()):
        raise UnsafeArchive(f"member {m.name!r}: special files are refused")
    if m.issparse():
        raise UnsafeArchive(f"member {m.name!r}: sparse files are refused")
    if m.isfile():
        _check_nested(rel)
    return rel


def _extract_tar(archive: Path, dest: Path, limits: ArchiveLimits) -> ExtractResult:
    # Pass 1 reads the headers only (data is skipped, or decompressed and dropped): a
    # refused archive writes nothing at all, whatever its size or member count.
    budget = _Budget(limits, archive.stat().st_size)
    seen: set[PurePosixPath] = set()
    with tarfile.open(archive, "r:*") as tf:
        for m in tf:  # lazily: a 10^6-member archive stops at the cap
            budget.member(m.name)
            if _is_root_dir(m):
                continue
            rel = _check_tar_member(m, limits)
            if m.isfile():
                if rel in seen:
                    raise UnsafeArchive(f"member {m.name!r}: duplicate name")
                seen.add(rel)
                budget.add(m.size, m.name)  # tarfile writes exactly m.size bytes
            _forget_members(tf)  # keep memory flat on huge archives
    # Pass 2 extracts with filter="data" (PEP 706) and the same checks again.
    with tarfile.open(archive, "r:*") as tf:
        for m in tf:
            if _is_root_dir(m):
                continue
            _check_tar_member(m, limits)
            try:
                tf.extract(m, dest, filter="data")
            except tarfile.FilterError as exc:
                raise UnsafeArchive(f"member {m.name!r}: {exc}") from exc
            _forget_members(tf)
    return ExtractResult("tar", dest, budget.members, budget.total)


def _forget_members(tf: tarfile.TarFile) -> None:
    """Drop the members ``tf`` has read so far: iterating a TarFile appends each one to its
    ``members`` list (an attribute typeshed does not declare)."""
    members: list[tarfile.TarInfo] = vars(tf)["members"]
    members.clear()


def _zip_mode(info: zipfile.ZipInfo) -> int:
    return (info.external_attr >> 16) & 0xFFFF


def _check_zip_member(info: zipfile.ZipInfo, root: Path, limits: ArchiveLimits) -> Path:
    rel = _check_name(info.filename, limits)
    mode = _zip_mode(info)
    if stat.S_ISLNK(mode):
        raise UnsafeArchive(f"member {info.filename!r}: links are refused")
    kind = stat.S_IFMT(mode)  # 0 when the writer set no type bits
    if kind and kind not in (stat.S_IFREG, stat.S_IFDIR):
        raise UnsafeArchive(f"member {info.filename!r}: special files are refused")
    if info.flag_bits & 0x1:
        raise UnsafeArchive(f"member {info.filename!r}: encrypted members are refused")
    target = (root / rel).resolve()
    if root not in target.parents:
        raise UnsafeArchive(f"member {info.filename!r}: leads outside the archive")
    if not info.is_dir():
        _check_nested(rel)
    return target


def _extract_zip(archive: Path, dest: Path, limits: ArchiveLimits) -> ExtractResult:
    root = dest.resolve()
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        if len(infos) > limits.max_members:
            raise UnsafeArchive(f"more than {limits.max_members} members ({len(infos)})")
        # Pass 1 over the central directory: names and types, before writing anything.
        targets, seen = [], set()
        for info in infos:
            target = _check_zip_member(info, root, limits)
            if not info.is_dir():
                if target in seen:
                    raise UnsafeArchive(f"member {info.filename!r}: duplicate name")
                seen.add(target)
            targets.append(target)
        # Pass 2 extracts, counting the bytes actually produced (headers are not trusted).
        budget = _Budget(limits, archive.stat().st_size)
        for info, target in zip(infos, targets, strict=True):
            budget.member(info.filename)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                out = open(target, "xb")
            except FileExistsError as exc:
                raise UnsafeArchive(f"member {info.filename!r}: duplicate name") from exc
            with out, zf.open(info) as src:
                _copy_counted(src, out, info, budget, limits)
    return ExtractResult("zip", dest, budget.members, budget.total)


def _copy_counted(
    src: IO[bytes],
    out: BinaryIO,
    info: zipfile.ZipInfo,
    budget: _Budget,
    limits: ArchiveLimits,
) -> None:
    """Copy one member, counting the bytes actually produced (headers may lie)."""
    written = 0
    compressed = max(info.compress_size, 1)
    while chunk := src.read(CHUNK):
        written += len(chunk)
        if written > info.file_size:
            raise UnsafeArchive(f"member {info.filename!r}: larger than its header says")
        if written > limits.ratio_grace_bytes and written > limits.max_ratio * compressed:
            raise UnsafeArchive(
                f"member {info.filename!r}: compression ratio exceeds {limits.max_ratio:g}"
            )
        budget.add(len(chunk), info.filename)
        out.write(chunk)
