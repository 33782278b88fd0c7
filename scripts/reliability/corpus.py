"""Hostile inputs: the archive attack set and the mutated-file corpus (deterministic).

``archive_attacks()``: name -> (bytes of the upload, a regex the refusal must match).
``sequence_mutations(folder, quick, seed)``: name -> a function that mutates a copy of a
sequence folder in place (PNG, PCD, CSV, OpenLABEL JSON). ``mesh_corpus(quick, seed)``:
name -> (file_type, bytes) of hostile meshes.
"""

from __future__ import annotations

import io
import json
import random
import stat
import struct
import tarfile
import warnings
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

MiB = 2**20


# ---------------------------------------------------------------------------- archives
def _tar(members: list[tuple[tarfile.TarInfo, bytes | None]], mode: str = "w") -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for info, data in members:
            if data is not None:
                info.size = len(data)
            tf.addfile(info, io.BytesIO(data) if data is not None else None)
    return buf.getvalue()


def _info(name: str, kind: bytes = tarfile.REGTYPE, **kw: object) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    for k, v in kw.items():
        setattr(info, k, v)
    return info


def _zip(members: list[tuple[str | zipfile.ZipInfo, bytes]]) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        warnings.simplefilter("ignore")
        for name, data in members:
            zf.writestr(name, data)
    return buf.getvalue()


def _zip_mode(name: str, mode: int, data: bytes) -> bytes:
    info = zipfile.ZipInfo(name)
    info.external_attr = mode << 16
    return _zip([(info, data)])


def _nested_bomb() -> bytes:
    """A zip inside a tar.gz inside a tar: every level small, the innermost 64 MiB."""
    inner = _zip([("seq/zeros.bin", b"\0" * (64 * MiB))])
    middle = _tar([(_info("seq/inner.zip"), inner)], "w:gz")
    return _tar([(_info("seq/middle.tar.gz"), middle)])


def archive_attacks(max_members: int = 10_000) -> dict[str, tuple[bytes, str]]:
    n = max_members + 1
    return {
        "tar zip-slip": (_tar([(_info("seq/../../evil.txt"), b"x")]), "'[.][.]'"),
        "tar absolute path": (_tar([(_info("/tmp/evil.txt"), b"x")]), "absolute"),
        "tar symlink out": (
            _tar([(_info("seq/l", tarfile.SYMTYPE, linkname="/etc"), None)]),
            "links",
        ),
        "tar symlink then write through it": (
            _tar(
                [
                    (_info("seq/l", tarfile.SYMTYPE, linkname="/tmp"), None),
                    (_info("seq/l/evil.txt"), b"x"),
                ]
            ),
            "links",
        ),
        "tar hardlink out": (
            _tar([(_info("seq/h", tarfile.LNKTYPE, linkname="/etc/passwd"), None)]),
            "links",
        ),
        "tar device": (
            _tar([(_info("seq/dev", tarfile.CHRTYPE, devmajor=1, devminor=3), None)]),
            "special",
        ),
        "tar block device": (
            _tar([(_info("seq/blk", tarfile.BLKTYPE, devmajor=8, devminor=0), None)]),
            "special",
        ),
        "tar fifo": (_tar([(_info("seq/fifo", tarfile.FIFOTYPE), None)]), "special"),
        "tar name too long": (_tar([(_info("seq/" + "a/" * 300 + "f"), b"x")]), "longer"),
        "tar component too long": (_tar([(_info("seq/" + "b" * 600), b"x")]), "longer"),
        f"tar {n} members": (
            _tar([(_info(f"seq/{i}"), b"") for i in range(n)]),
            f"more than {max_members} members",
        ),
        "tar.gz ratio bomb": (
            _tar([(_info("seq/zeros.pcd"), b"\0" * (48 * MiB))], "w:gz"),
            "ratio|extracted size",
        ),
        "nested bomb": (_nested_bomb(), "inside"),
        "tar duplicate member": (
            _tar([(_info("seq/a"), b"1"), (_info("seq/a"), b"2")]),
            "duplicate",
        ),
        "zip zip-slip": (_zip([("../evil.txt", b"x")]), "'[.][.]'"),
        "zip absolute path": (_zip([("/tmp/evil.txt", b"x")]), "absolute"),
        "zip drive letter": (_zip([("C:/evil.txt", b"x")]), "absolute"),
        "zip backslash": (_zip([("..\\evil.txt", b"x")]), "backslash"),
        "zip symlink": (_zip_mode("seq/link", stat.S_IFLNK | 0o777, b"/etc/passwd"), "links"),
        "zip device": (_zip_mode("seq/dev", stat.S_IFCHR | 0o666, b""), "special"),
        "zip ratio bomb": (_zip([("seq/zeros", b"\0" * (48 * MiB))]), "ratio|extracted size"),
        "zip nested archive": (_zip([("seq/inner.tar.gz", b"x")]), "inside"),
        f"zip {n} members": (
            _zip([(f"seq/{i}", b"") for i in range(n)]),
            f"more than {max_members} members",
        ),
        "not an archive": (b"hello" * 100, "not a tar or zip"),
        "truncated tar.gz": (
            _tar([(_info("seq/a"), random.Random(1).randbytes(100_000))], "w:gz")[:3000],
            "unreadable",
        ),
    }


# ---------------------------------------------------------------------------- files
def png_header(width: int, height: int) -> bytes:
    """A valid PNG signature + IHDR of ``width`` x ``height`` RGB, one tiny IDAT, IEND."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


def _first(folder: Path, pattern: str) -> Path:
    return sorted(folder.glob(pattern))[0]


def _flip(data: bytes, rng: random.Random, n: int, start: int = 0) -> bytes:
    b = bytearray(data)
    for _ in range(n):
        i = rng.randrange(start, len(b))
        b[i] ^= 1 << rng.randrange(8)
    return bytes(b)


def _pcd_header_edit(path: Path, key: str, value: str) -> None:
    raw = path.read_bytes()
    end = raw.index(b"DATA")
    end = raw.index(b"\n", end) + 1
    lines = raw[:end].decode().splitlines()
    lines = [f"{key} {value}" if ln.startswith(key + " ") else ln for ln in lines]
    path.write_bytes(("\n".join(lines) + "\n").encode() + raw[end:])


def _pcd_nan(path: Path) -> None:
    raw = bytearray(path.read_bytes())
    start = raw.index(b"\n", raw.index(b"DATA")) + 1
    nan = struct.pack("<f", float("nan"))
    for off in range(start, min(len(raw) - 4, start + 25 * 200), 25):  # x of 200 points
        raw[off : off + 4] = nan
    path.write_bytes(bytes(raw))


def _labels(folder: Path) -> Path:
    return _first(folder, "*_labels.json")


def _json_edit(folder: Path, edit: Callable[[dict], None]) -> None:
    p = _labels(folder)
    data = json.loads(p.read_text())
    edit(data)
    p.write_text(json.dumps(data))


Mutation = Callable[[Path], None]


def sequence_mutations(quick: bool, seed: int = 0) -> dict[str, Mutation]:
    """Named mutations of a sequence folder (a copy), the named set plus random flips."""
    rng = random.Random(seed)

    def write(pattern: str, data: Callable[[Path], bytes]) -> Mutation:
        def m(folder: Path) -> None:
            p = _first(folder, pattern)
            p.write_bytes(data(p))

        return m

    png = "rgb_center/*.png"
    pcd = "lidar/*.pcd"
    csv = "novatel_oem7_inspva/*.csv"
    muts: dict[str, Mutation] = {
        "png 50k x 50k header": write(png, lambda p: png_header(50_000, 50_000)),
        "png truncated": write(png, lambda p: p.read_bytes()[: len(p.read_bytes()) // 2]),
        "png not a png": write(png, lambda p: b"\xff\xd8\xff\xe0 JFIF" + b"\0" * 500),
        "png 16 bit": write(png, lambda p: png_header(8, 8)[:24] + b"\x10" + png_header(8, 8)[25:]),
        "pcd POINTS overflows": lambda f: _pcd_header_edit(
            _first(f, pcd), "POINTS", "99999999999999999999"
        ),
        "pcd POINTS larger than the data": lambda f: _pcd_header_edit(
            _first(f, pcd), "POINTS", "100000000"
        ),
        "pcd WIDTH negative": lambda f: _pcd_header_edit(_first(f, pcd), "WIDTH", "-5"),
        "pcd truncated": write(pcd, lambda p: p.read_bytes()[: len(p.read_bytes()) // 3]),
        "pcd NaN points": lambda f: _pcd_nan(_first(f, pcd)),
        "pcd garbage header": write(pcd, lambda p: b"# .PCD\nFIELDS \xff\xfe\nDATA ascii\n1 2"),
        "csv garbage": write(csv, lambda p: b"\x00\xff garbage,,,\n\n;;;"),
        "csv missing columns": write(csv, lambda p: b"frame_idx,timestamp\n0,1.0\n"),
        "csv NaN and huge values": write(
            csv, lambda p: p.read_bytes().replace(b"53.55", b"nan1").replace(b"9.99", b"1e308")
        ),
        "json truncated": lambda f: _labels(f).write_bytes(_labels(f).read_bytes()[:5000]),
        "json wrong types": lambda f: _json_edit(f, lambda d: d["openlabel"].update(frames=[1, 2])),
        "json deeply nested": lambda f: _labels(f).write_text(
            '{"openlabel": ' + "[" * 100_000 + "]" * 100_000 + "}"
        ),
        "json huge numbers": lambda f: _labels(f).write_text(
            _labels(f).read_text().replace('"frame_start": 0', '"frame_start": 1e999')
        ),
        "json streams missing": lambda f: _json_edit(f, lambda d: d["openlabel"].pop("streams")),
        "json camera intrinsics NaN": lambda f: _labels(f).write_text(
            _labels(f).read_text().replace('"camera_matrix": [', '"camera_matrix": [NaN, ', 1)
        ),
    }
    if quick:
        keep = (
            "png 50k x 50k header",
            "pcd POINTS overflows",
            "pcd NaN points",
            "csv garbage",
            "json wrong types",
            "png truncated",
        )
        muts = {k: muts[k] for k in keep}
    flips = 1 if quick else 6
    for kind, pattern, skip in (
        ("png", png, 60),
        ("pcd", pcd, 300),
        ("csv", csv, 0),
        ("json", "*_labels.json", 0),
    ):
        for i in range(flips):
            s = rng.randrange(2**31)

            def m(folder: Path, pattern: str = pattern, s: int = s, skip: int = skip) -> None:
                p = _first(folder, pattern)
                p.write_bytes(_flip(p.read_bytes(), random.Random(s), 20, start=skip))

            muts[f"{kind} random flips #{i}"] = m
    return muts


def mesh_corpus(quick: bool, seed: int = 0) -> dict[str, tuple[str, bytes]]:
    rng = random.Random(seed)
    tetra = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    gltf_uri = json.dumps(
        {"asset": {"version": "2.0"}, "buffers": [{"uri": "file:///etc/passwd", "byteLength": 10}]}
    )
    gltf_http = json.dumps(
        {"asset": {"version": "2.0"}, "images": [{"uri": "http://127.0.0.1:1/x.png"}]}
    )
    out = {
        "gltf external file uri": ("gltf", gltf_uri.encode()),
        "gltf external http image uri": ("gltf", gltf_http.encode()),
        "glb garbage": ("glb", b"glTF" + rng.randbytes(200)),
        "obj face index out of range": ("obj", b"v 0 0 0\nv 1 0 0\nf 1 2 99999999\n"),
        "obj NaN vertices": ("obj", b"v nan nan nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
        "obj no faces": ("obj", b"v 0 0 0\nv 1 0 0\n"),
        "obj too many vertices": ("obj", b"v 0 0 0\n" * 600_000 + b"f 1 2 3\n"),
        "ply header lies": (
            "ply",
            b"ply\nformat ascii 1.0\nelement vertex 99999999999\nproperty float x\nend_header\n0\n",
        ),
        "obj random flips": ("obj", _flip(tetra, rng, 10)),
    }
    if quick:
        keep = (
            "gltf external file uri",
            "glb garbage",
            "obj NaN vertices",
            "obj face index out of range",
        )
        out = {k: out[k] for k in keep}
    return out


def tar_folder(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=1) as tar:
        for p in sorted(folder.rglob("*")):
            if p.is_file() and "ground_truth" not in p.parts:
                tar.add(p, arcname=f"{folder.name}/{p.relative_to(folder).as_posix()}")
    return buf.getvalue()
