"""PCD v0.7 reading and writing (ascii, binary, binary_compressed) and the LZF codec."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from worker.osdar import PointCloud, SequenceError, finite_mask, read_pcd, write_pcd
from worker.osdar.pcd import encode_pcd, lzf_compress, lzf_decompress

DATA_TYPES = ("ascii", "binary", "binary_compressed")
OSDAR_HEADER = "SIZE 4 4 4 4 8 1\nTYPE F F F F F U\n"


def osdar_cloud(n: int = 300, seed: int = 0) -> PointCloud:
    """OSDaR23 fields and dtypes: x y z intensity F4, timestamp F8, sensor_index U1."""
    rng = np.random.default_rng(seed)
    fields = {k: rng.normal(0, 40, n).astype(np.float32) for k in ("x", "y", "z")}
    fields["intensity"] = rng.uniform(0, 255, n).astype(np.float32)
    fields["timestamp"] = np.sort(1631441453.2995 + rng.uniform(0, 0.1, n))
    fields["sensor_index"] = rng.integers(0, 6, n).astype(np.uint8)
    # awkward values: float32 extremes, denormal, negative zero, integers
    extremes = np.array([3.4028235e38, -1.1754944e-38, 1e-45, -0.0, 1.0, 123456.7], np.float32)
    m = min(n, extremes.size)
    fields["x"][:m] = extremes[:m]
    return PointCloud(fields)


def assert_same_fields(a: PointCloud, b: PointCloud) -> None:
    assert list(a.fields) == list(b.fields)
    for k in a.fields:
        assert a.fields[k].dtype == b.fields[k].dtype, k
        assert np.array_equal(a.fields[k], b.fields[k], equal_nan=True), k
        assert np.array_equal(np.signbit(a.fields[k]), np.signbit(b.fields[k])), k


@pytest.mark.parametrize("data", DATA_TYPES)
def test_round_trip_exact(tmp_path: Path, data: str) -> None:
    cloud = osdar_cloud()
    path = write_pcd(tmp_path / "c.pcd", cloud, data=data)
    back = read_pcd(path)
    assert_same_fields(cloud, back)
    h = back.header
    assert h.data == data
    assert h.fields == ["x", "y", "z", "intensity", "timestamp", "sensor_index"]
    assert (h.size, h.type, h.count) == ([4, 4, 4, 4, 8, 1], list("FFFFFU"), [1] * 6)
    assert (h.points, h.width, h.height) == (300, 300, 1)
    assert OSDAR_HEADER in path.read_bytes()[:400].decode("ascii", "replace")
    # rewriting without a DATA type keeps the input's one, byte for byte
    again = write_pcd(tmp_path / "again.pcd", back)
    assert again.read_bytes() == path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.pcd", "c.pcd"]  # no temp left


@pytest.mark.parametrize("src", DATA_TYPES)
@pytest.mark.parametrize("dst", DATA_TYPES)
def test_convert_between_data_types(tmp_path: Path, src: str, dst: str) -> None:
    cloud = read_pcd(write_pcd(tmp_path / "a.pcd", osdar_cloud(50), data=src))
    assert_same_fields(cloud, read_pcd(write_pcd(tmp_path / "b.pcd", cloud, data=dst)))


def test_writer_keeps_input_dtypes_and_organisation(tmp_path: Path) -> None:
    cloud = osdar_cloud(12)
    cloud.header.width, cloud.header.height = 4, 3
    cloud.header.viewpoint = (1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0)
    cloud.fields["x"] = cloud.fields["x"].astype(np.float64)  # processed in float64
    back = read_pcd(write_pcd(tmp_path / "c.pcd", cloud))
    assert back.fields["x"].dtype == np.float32
    assert (back.header.width, back.header.height) == (4, 3)
    assert back.header.viewpoint == (1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0)


def test_count_greater_than_one(tmp_path: Path) -> None:
    rgb = np.arange(30, dtype=np.uint8).reshape(10, 3)
    cloud = PointCloud({"x": np.zeros(10, np.float32), "rgb": rgb})
    for data in DATA_TYPES:
        back = read_pcd(write_pcd(tmp_path / f"{data}.pcd", cloud, data=data))
        assert back.header.count == [1, 3]
        assert np.array_equal(back.fields["rgb"], rgb)


def test_nan_coordinates_are_kept(tmp_path: Path) -> None:
    cloud = osdar_cloud(20)
    cloud.fields["y"][[3, 7]] = np.nan
    cloud.fields["z"][9] = np.inf
    for data in DATA_TYPES:
        back = read_pcd(write_pcd(tmp_path / f"{data}.pcd", cloud, data=data))
        assert len(back) == 20
        mask = finite_mask(back)
        assert mask.shape == (20,) and np.flatnonzero(~mask).tolist() == [3, 7, 9]
        assert back.xyz.shape == (20, 3) and back.xyz.dtype == np.float64
        assert len(back.select(mask)) == 17


def test_empty_cloud(tmp_path: Path) -> None:
    cloud = osdar_cloud(0)
    for data in DATA_TYPES:
        assert len(read_pcd(write_pcd(tmp_path / f"{data}.pcd", cloud, data=data))) == 0


# -- malformed files ----------------------------------------------------------------------


def header(points: int = 3, data: str = "binary", **over: str) -> bytes:
    lines = {
        "VERSION": "0.7",
        "FIELDS": "x y z intensity timestamp sensor_index",
        "SIZE": "4 4 4 4 8 1",
        "TYPE": "F F F F F U",
        "COUNT": "1 1 1 1 1 1",
        "WIDTH": str(points),
        "HEIGHT": "1",
        "VIEWPOINT": "0 0 0 1 0 0 0",
        "POINTS": str(points),
        "DATA": data,
    }
    lines.update(over)
    return "".join(f"{k} {v}\n" for k, v in lines.items() if v is not None).encode()


def expect_error(path: Path, content: bytes, *words: str) -> SequenceError:
    path.write_bytes(content)
    with pytest.raises(SequenceError) as info:
        read_pcd(path)
    err = info.value
    assert err.path == path and str(path) in str(err)
    for w in words:
        assert w in err.reason, err.reason
    return err


def test_header_size_mismatch(tmp_path: Path) -> None:
    expect_error(tmp_path / "a.pcd", header(4) + bytes(3 * 25), "truncated", "100 bytes")
    expect_error(tmp_path / "b.pcd", header(2) + bytes(3 * 25), "too long")
    expect_error(tmp_path / "c.pcd", header(3, WIDTH="2"), "WIDTH")


def test_truncated_files(tmp_path: Path) -> None:
    good = encode_pcd(osdar_cloud(100), "binary")
    expect_error(tmp_path / "a.pcd", good[:-1], "truncated")
    comp = encode_pcd(osdar_cloud(100), "binary_compressed")
    expect_error(tmp_path / "b.pcd", comp[:-5], "truncated")
    asc = encode_pcd(osdar_cloud(100), "ascii")
    expect_error(tmp_path / "c.pcd", asc[: len(asc) * 2 // 3], "ascii data")
    expect_error(tmp_path / "d.pcd", good[:40], "DATA")  # cut inside the header


def test_huge_points_refused_before_reading(tmp_path: Path) -> None:
    huge = 10**15
    expect_error(tmp_path / "a.pcd", header(huge) + bytes(10), "exceeds")
    big = 2**31 - 1  # allowed count, but the data is not there: no allocation attempted
    expect_error(tmp_path / "b.pcd", header(big) + bytes(10), "truncated")
    expect_error(tmp_path / "c.pcd", header(big, data="ascii") + b"1 2 3\n", "truncated")
    payload = struct.pack("<II", 4, 0xFFFFFFFF) + bytes(4)
    expect_error(tmp_path / "d.pcd", header(big, data="binary_compressed") + payload, "size")


def test_bad_header_lines(tmp_path: Path) -> None:
    body = bytes(3 * 25)
    expect_error(tmp_path / "a.pcd", header(FIELDS=None) + body, "no FIELDS")
    expect_error(tmp_path / "b.pcd", header(SIZE="4 4 4") + body, "SIZE has 3 entries")
    expect_error(tmp_path / "c.pcd", header(TYPE="F F F F X U") + body, "unsupported TYPE")
    expect_error(tmp_path / "d.pcd", header(SIZE="4 4 4 4 3 1") + body, "unsupported")
    expect_error(tmp_path / "e.pcd", header(data="binary_lz4") + body, "unknown PCD DATA")
    expect_error(tmp_path / "f.pcd", header(POINTS="three") + body, "POINTS")
    expect_error(tmp_path / "g.pcd", header(VIEWPOINT="0 0 0") + body, "VIEWPOINT")
    expect_error(tmp_path / "h.pcd", b"\x89PNG\r\n\x1a\n" + bytes(100), "not a PCD")


def test_compressed_size_fields_inconsistent(tmp_path: Path) -> None:
    good = encode_pcd(osdar_cloud(10), "binary_compressed")
    start = good.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    comp, raw = struct.unpack("<II", good[start : start + 8])
    assert raw == 10 * 25
    bad_raw = good[:start] + struct.pack("<II", comp, raw + 1) + good[start + 8 :]
    expect_error(tmp_path / "a.pcd", bad_raw, "uncompressed size")
    bad_comp = good[:start] + struct.pack("<II", comp - 3, raw) + good[start + 8 :]
    expect_error(tmp_path / "b.pcd", bad_comp, "extra bytes")
    corrupt = bytearray(good)
    corrupt[start + 8] = 0xFF  # first token: back reference before the start
    expect_error(tmp_path / "c.pcd", bytes(corrupt), "corrupt LZF")


def test_ascii_unparsable_value(tmp_path: Path) -> None:
    body = b"1 2 3 4 5.5 1\n1 2 oops 4 5.5 1\n1 2 3 4 5.5 300\n"
    err = expect_error(tmp_path / "a.pcd", header(3, data="ascii") + body, "unparsable")
    assert "'oops' at point 1" in err.reason
    body = b"1 2 3 4 5.5 1\n1 2 3 4 5.5 1\n1 2 3 4 5.5 300\n"
    expect_error(tmp_path / "b.pcd", header(3, data="ascii") + body, "sensor_index")


# -- LZF ------------------------------------------------------------------------------------


def test_lzf_known_stream() -> None:
    # literal "a", then a back reference of 9 bytes at distance 1 (overlapping copy)
    assert lzf_decompress(b"\x00a\xe0\x00\x00", 10) == b"a" * 10
    # literal "abc", then 5 bytes at distance 3
    assert lzf_decompress(b"\x02abc\x60\x02", 8) == b"abcabcab"
    with pytest.raises(ValueError):
        lzf_decompress(b"\x00a\xe0\x00\x00", 11)
    with pytest.raises(ValueError):
        lzf_decompress(b"\x05ab", 6)
    with pytest.raises(ValueError):  # longer than expected
        lzf_decompress(b"\x00a\xe0\x00\x00", 8)


@pytest.mark.parametrize("n", [0, 1, 2, 3, 31, 32, 33, 263, 264, 265, 1000, 20000])
def test_lzf_round_trip(n: int) -> None:
    rng = np.random.default_rng(n)
    samples = [
        rng.integers(0, 256, n, dtype=np.uint8).tobytes(),
        bytes(n),
        rng.integers(0, 3, n, dtype=np.uint8).tobytes(),
        (b"0123456789abcdef" * (n // 16 + 1))[:n],
    ]
    for data in samples:
        assert lzf_decompress(lzf_compress(data), n) == data
