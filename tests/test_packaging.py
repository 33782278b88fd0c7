"""The result archive: one gzip member, PNGs stored in its deflate stream, the rest
deflated; every reader of ``.tar.gz`` reads it (worker/packaging.py, worker/gzip_stored.py)."""

from __future__ import annotations

import gzip
import io
import shutil
import subprocess
import tarfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from worker.gzip_stored import LEVELS, STORED_BLOCK_MAX, GzipStoredWriter
from worker.osdar.images import write_png
from worker.packaging import build_archive


def _parts() -> list[tuple[bool, bytes]]:
    rng = np.random.default_rng(7)
    noise = rng.integers(0, 256, 3 * STORED_BLOCK_MAX + 17, dtype=np.uint8).tobytes()
    text = b"x y z intensity\n" * 20000
    return [(False, text), (True, noise), (True, b""), (False, b"header" * 10), (True, b"a"),
            (False, text[:999]), (True, noise[:STORED_BLOCK_MAX])]  # fmt: skip


@pytest.mark.parametrize("level", LEVELS)
def test_stored_and_deflated_parts_decompress_to_what_was_written(level: int) -> None:
    buf = io.BytesIO()
    with GzipStoredWriter(buf, level=level) as gz:
        for stored, data in _parts():
            gz.stored = stored
            assert gz.write(data) == len(data)
    expected = b"".join(d for _, d in _parts())
    assert gz.tell() == len(expected)
    raw = buf.getvalue()
    assert gzip.decompress(raw) == expected
    d = zlib.decompressobj(wbits=31)  # exactly one member: nothing after its trailer
    assert d.decompress(raw) == expected and d.eof and d.unused_data == b""
    # the stored noise is in the file as it is; the text is deflated
    noise = _parts()[1][1]
    assert noise[:STORED_BLOCK_MAX] in raw
    assert len(raw) < len(expected) - 0.9 * len(_parts()[0][1])


def test_gzip_tool_accepts_the_stream(tmp_path: Path) -> None:
    if shutil.which("gzip") is None:
        pytest.skip("no gzip tool")
    path = tmp_path / "x.gz"
    with open(path, "wb") as f, GzipStoredWriter(f) as gz:
        for stored, data in _parts():
            gz.stored = stored
            gz.write(data)
    out = subprocess.run(["gzip", "-dc", str(path)], capture_output=True, check=True).stdout
    assert out == b"".join(d for _, d in _parts())


def test_level_out_of_range_is_refused() -> None:
    for level in (-1, 4, 9):  # ISA-L's levels are 0..3
        with pytest.raises(ValueError, match=r"0\.\.3"):
            GzipStoredWriter(io.BytesIO(), level=level)


@pytest.fixture
def seq(tmp_path: Path) -> Path:
    root = tmp_path / "seq_a"
    rng = np.random.default_rng(3)
    write_png(root / "rgb_center" / "000_rgb.png", rng.integers(0, 256, (60, 80, 3), np.uint8))
    (root / "lidar").mkdir()
    (root / "lidar" / "000.pcd").write_bytes(b"0.5 1.25 -3.0 17\n" * 5000)
    (root / "seq_a_labels.json").write_text('{"openlabel": {}}')
    (root / "ground_truth").mkdir()
    (root / "ground_truth" / "poses.csv").write_text("t,x\n")
    return root


def _members(tar: tarfile.TarFile) -> dict[str, bytes]:
    got = {}
    with tar:
        for m in tar:
            f = tar.extractfile(m)
            assert f is not None
            got[m.name] = f.read()
    return got


def test_archive_reads_back_in_every_tarfile_mode(seq: Path, tmp_path: Path) -> None:
    report = tmp_path / "metrics.json"
    report.write_text('{"ok": true}')
    labels = tmp_path / "labels.json"
    labels.write_text('{"openlabel": {"objects": {}}}')
    extra = {"metrics.json": report, "seq_a_labels.json": labels}
    archive = build_archive(seq, tmp_path / "out" / "result.tar.gz", extra=extra)
    expected = {
        "seq_a/rgb_center/000_rgb.png": (seq / "rgb_center" / "000_rgb.png").read_bytes(),
        "seq_a/lidar/000.pcd": (seq / "lidar" / "000.pcd").read_bytes(),
        "seq_a/seq_a_labels.json": labels.read_bytes(),  # ours replaces the input's
        "seq_a/metrics.json": report.read_bytes(),
    }
    # no ground_truth/, nothing twice; streaming r|gz reads it all too
    assert _members(tarfile.open(archive, "r:gz")) == expected
    assert _members(tarfile.open(archive, "r|gz")) == expected
    assert _members(tarfile.open(archive)) == expected
    raw = archive.read_bytes()
    assert expected["seq_a/rgb_center/000_rgb.png"] in raw  # the PNG stored as it is
    assert expected["seq_a/lidar/000.pcd"] not in raw  # the PCD deflated
    png, pcd = expected["seq_a/rgb_center/000_rgb.png"], expected["seq_a/lidar/000.pcd"]
    assert len(raw) < len(png) + len(pcd) / 10 + 2048  # + the tar headers, deflated
    assert not list(archive.parent.glob("*.partial"))
