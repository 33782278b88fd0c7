"""PCD v0.7 point clouds: read and write DATA ascii, binary and binary_compressed.

Fields are generic (any FIELDS/SIZE/TYPE/COUNT, little-endian); OSDaR23 clouds carry
``x y z intensity timestamp sensor_index``. A :class:`PointCloud` keeps every field as an
array in its stored dtype plus the :class:`PcdHeader` it was read with, so that
:func:`write_pcd` writes it back with the same DATA type and dtypes by default.

binary_compressed is PCL's layout: the fields column-major (all values of the first field,
then the second, ...), LZF-compressed, preceded by two little-endian uint32, the compressed
then the uncompressed size. LZF runs through the C module ``lzf`` (pip ``python-lzf``, a
required dependency).
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path

import lzf
import numpy as np
from numpy.typing import NDArray

from worker.osdar.errors import SequenceError, atomic_write_bytes

logger = logging.getLogger(__name__)

DATA_TYPES = ("ascii", "binary", "binary_compressed")
MAX_POINTS = 1 << 31  # refuse absurd POINTS before any arithmetic on the file size
_MAX_HEADER_LINES = 64
_MAX_HEADER_LINE = 4096
_DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

_PCD_DTYPES: dict[tuple[str, int], str] = {
    ("F", 2): "<f2",
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("I", 1): "i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
    ("I", 8): "<i8",
    ("U", 1): "u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
    ("U", 8): "<u8",
}
_KIND_TO_PCD = {"f": "F", "i": "I", "u": "U", "b": "U"}


# ---------------------------------------------------------------------------------------
# header and cloud
# ---------------------------------------------------------------------------------------


@dataclass
class PcdHeader:
    """The header of a PCD v0.7 file.

    Attributes
    ----------
    fields, size, type, count : list
        One entry per field: name, bytes per value, ``F``/``I``/``U``, values per point.
    width, height : int
        Organisation of the cloud; ``points == width * height``.
    viewpoint : tuple of 7 float
        Acquisition viewpoint ``tx ty tz qw qx qy qz``.
    points : int
        Number of points.
    data : str
        ``ascii``, ``binary`` or ``binary_compressed``.
    version : str
        The VERSION line (``0.7``).
    """

    fields: list[str]
    size: list[int]
    type: list[str]
    count: list[int]
    width: int
    height: int
    viewpoint: tuple[float, ...] = _DEFAULT_VIEWPOINT
    points: int = 0
    data: str = "binary"
    version: str = "0.7"

    def field_dtype(self, i: int) -> np.dtype:
        """Numpy dtype of one value of field ``i``."""
        return np.dtype(_PCD_DTYPES[(self.type[i], self.size[i])])

    @property
    def record_size(self) -> int:
        """Bytes per point in the binary layouts."""
        return sum(s * c for s, c in zip(self.size, self.count, strict=True))

    def to_text(self) -> str:
        """The header as written to a file, DATA line and its newline included."""
        vp = " ".join(_fmt_float64(v) for v in self.viewpoint)
        return (
            "# .PCD v0.7 - Point Cloud Data file format\n"
            f"VERSION {self.version}\n"
            f"FIELDS {' '.join(self.fields)}\n"
            f"SIZE {' '.join(map(str, self.size))}\n"
            f"TYPE {' '.join(self.type)}\n"
            f"COUNT {' '.join(map(str, self.count))}\n"
            f"WIDTH {self.width}\n"
            f"HEIGHT {self.height}\n"
            f"VIEWPOINT {vp}\n"
            f"POINTS {self.points}\n"
            f"DATA {self.data}\n"
        )


@dataclass
class PointCloud:
    """A point cloud as stored in a PCD file.

    Attributes
    ----------
    fields : dict of str to ndarray
        Field name -> (n,) array in its stored dtype ((n, count) when COUNT > 1).
    header : PcdHeader
        The header read (or a header derived from the arrays), used as the default layout
        when writing.
    """

    fields: dict[str, NDArray]
    header: PcdHeader = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.header is None:
            self.header = header_for_fields(self.fields)

    def __len__(self) -> int:
        if not self.fields:
            return 0
        return len(next(iter(self.fields.values())))

    @property
    def xyz(self) -> NDArray[np.float64]:
        """(n, 3) float64 coordinates."""
        return np.stack([self.fields[k].astype(np.float64) for k in ("x", "y", "z")], axis=1)

    def select(self, index: NDArray) -> PointCloud:
        """Points selected by an index array or a boolean mask, as an unorganised cloud."""
        fields = {k: np.asarray(v)[index] for k, v in self.fields.items()}
        n = len(next(iter(fields.values()))) if fields else 0
        return PointCloud(fields, replace(self.header, width=n, height=1, points=n))


def finite_mask(cloud: PointCloud) -> NDArray[np.bool_]:
    """(n,) bool: True where x, y and z are all finite.

    Column by column in the fields' own dtype: the (n, 3) float64 stack of :attr:`xyz`
    took 10.7 ms on a 178k-point frame where this takes 0.4 (every PCD read goes here).
    """
    f = cloud.fields
    return np.isfinite(f["x"]) & np.isfinite(f["y"]) & np.isfinite(f["z"])


def header_for_fields(
    fields: dict[str, NDArray], data: str = "binary", template: PcdHeader | None = None
) -> PcdHeader:
    """Header describing ``fields`` (their dtypes), with ``template``'s viewpoint/organisation.

    Parameters
    ----------
    fields : dict of str to ndarray
        (n,) or (n, count) arrays.
    data : str
        DATA type.
    template : PcdHeader, optional
        Header whose viewpoint, version and width/height (when they still match n) are kept.
    """
    names, sizes, types, counts = [], [], [], []
    n = None
    for name, arr in fields.items():
        arr = np.asarray(arr)
        if arr.ndim not in (1, 2):
            raise ValueError(f"field {name!r}: expected (n,) or (n, count), got {arr.shape}")
        if n is None:
            n = len(arr)
        elif len(arr) != n:
            raise ValueError(f"field {name!r} has {len(arr)} points, expected {n}")
        kind = _KIND_TO_PCD.get(arr.dtype.kind)
        if kind is None or (kind, arr.dtype.itemsize) not in _PCD_DTYPES:
            raise ValueError(f"field {name!r}: dtype {arr.dtype} cannot be stored in a PCD")
        names.append(name)
        sizes.append(arr.dtype.itemsize)
        types.append(kind)
        counts.append(1 if arr.ndim == 1 else arr.shape[1])
    n = n or 0
    width, height = n, 1
    viewpoint, version = _DEFAULT_VIEWPOINT, "0.7"
    if template is not None:
        viewpoint, version = template.viewpoint, template.version
        if template.width * template.height == n:
            width, height = template.width, template.height
    return PcdHeader(names, sizes, types, counts, width, height, viewpoint, n, data, version)


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------


def read_pcd(path: str | Path) -> PointCloud:
    """Read a PCD v0.7 file (DATA ascii, binary or binary_compressed).

    Parameters
    ----------
    path : str or Path
        The .pcd file.

    Returns
    -------
    PointCloud
        Fields in their stored dtypes; non-finite coordinates are kept (see
        :func:`finite_mask`).

    Raises
    ------
    SequenceError
        Missing file, malformed header, data size disagreeing with POINTS, truncated or
        inconsistent compressed data.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SequenceError(path, f"cannot read point cloud: {e.strerror or e}") from e
    header, offset = _parse_header(path, raw)
    body = memoryview(raw)[offset:]
    if header.data == "binary":
        arrays = _read_binary(path, header, body)
    elif header.data == "binary_compressed":
        arrays = _read_compressed(path, header, body)
    else:
        arrays = _read_ascii(path, header, body)
    return PointCloud(arrays, header)


def _parse_header(path: Path, raw: bytes) -> tuple[PcdHeader, int]:
    """Parse the header lines; returns the header and the offset of the data."""
    entries: dict[str, list[str]] = {}
    offset = 0
    for _ in range(_MAX_HEADER_LINES):
        end = raw.find(b"\n", offset, offset + _MAX_HEADER_LINE)
        if end < 0:
            raise SequenceError(path, "not a PCD file: header ends before its DATA line")
        try:
            line = raw[offset:end].decode("ascii").strip()
        except UnicodeDecodeError as e:
            raise SequenceError(path, "not a PCD file: non-ASCII bytes in the header") from e
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        entries[key.upper()] = values
        if key.upper() == "DATA":
            return _header_from_entries(path, entries), offset
    raise SequenceError(path, f"not a PCD file: no DATA line in the first {_MAX_HEADER_LINES}")


def _header_from_entries(path: Path, e: dict[str, list[str]]) -> PcdHeader:
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA"):
        if key not in e:
            raise SequenceError(path, f"PCD header has no {key} line")
    names = e["FIELDS"]
    nf = len(names)
    if nf == 0 or len(set(names)) != nf:
        raise SequenceError(path, f"PCD FIELDS must be unique and non-empty: {names}")
    size = _ints(path, "SIZE", e["SIZE"])
    count = _ints(path, "COUNT", e.get("COUNT", ["1"] * nf))
    types = [t.upper() for t in e["TYPE"]]
    for key, values in (("SIZE", size), ("TYPE", types), ("COUNT", count)):
        if len(values) != nf:
            raise SequenceError(path, f"PCD {key} has {len(values)} entries for {nf} FIELDS")
    for name, t, s, c in zip(names, types, size, count, strict=True):
        if (t, s) not in _PCD_DTYPES:
            raise SequenceError(path, f"PCD field {name!r}: unsupported TYPE {t} SIZE {s}")
        if c < 1:
            raise SequenceError(path, f"PCD field {name!r}: COUNT {c} < 1")
    width = _one_int(path, "WIDTH", e["WIDTH"])
    height = _one_int(path, "HEIGHT", e["HEIGHT"])
    points = _one_int(path, "POINTS", e.get("POINTS", [str(width * height)]))
    if points > MAX_POINTS:
        raise SequenceError(path, f"PCD POINTS {points} exceeds the limit of {MAX_POINTS}")
    if width * height != points:
        raise SequenceError(path, f"PCD POINTS {points} != WIDTH {width} * HEIGHT {height}")
    data = e["DATA"][0].lower() if len(e["DATA"]) == 1 else " ".join(e["DATA"])
    if data not in DATA_TYPES:
        raise SequenceError(path, f"unknown PCD DATA type {data!r} (expected {DATA_TYPES})")
    viewpoint = _DEFAULT_VIEWPOINT
    if "VIEWPOINT" in e:
        try:
            viewpoint = tuple(float(v) for v in e["VIEWPOINT"])
        except ValueError:
            viewpoint = ()
        if len(viewpoint) != 7:
            raise SequenceError(path, f"PCD VIEWPOINT needs 7 numbers: {e['VIEWPOINT']}")
    version = e.get("VERSION", ["0.7"])[0]
    return PcdHeader(names, size, types, count, width, height, viewpoint, points, data, version)


def _ints(path: Path, key: str, values: list[str]) -> list[int]:
    try:
        return [int(v) for v in values]
    except ValueError as err:
        raise SequenceError(path, f"PCD {key} is not a list of integers: {values}") from err


def _one_int(path: Path, key: str, values: list[str]) -> int:
    ints = _ints(path, key, values)
    if len(ints) != 1 or ints[0] < 0:
        raise SequenceError(path, f"PCD {key} must be one integer >= 0: {values}")
    return ints[0]


def _record_dtype(header: PcdHeader) -> np.dtype:
    """Packed structured dtype of one point (row-major binary layout)."""
    return np.dtype(
        [
            (n, header.field_dtype(i), (c,) if c > 1 else ())
            for i, (n, c) in enumerate(zip(header.fields, header.count, strict=True))
        ]
    )


def _read_binary(path: Path, header: PcdHeader, body: memoryview) -> dict[str, NDArray]:
    expected = header.points * header.record_size
    if len(body) != expected:
        what = "truncated" if len(body) < expected else "too long"
        raise SequenceError(
            path,
            f"binary data {what}: POINTS {header.points} x {header.record_size} bytes = "
            f"{expected} bytes expected, {len(body)} found",
        )
    records = np.frombuffer(body, dtype=_record_dtype(header), count=header.points)
    return {name: records[name].copy() for name in header.fields}


def _read_compressed(path: Path, header: PcdHeader, body: memoryview) -> dict[str, NDArray]:
    if len(body) < 8:
        raise SequenceError(path, "binary_compressed data truncated: no size fields")
    compressed_size, uncompressed_size = struct.unpack("<II", body[:8])
    expected = header.points * header.record_size
    if uncompressed_size != expected:
        raise SequenceError(
            path,
            f"binary_compressed uncompressed size {uncompressed_size} != POINTS "
            f"{header.points} x {header.record_size} bytes = {expected}",
        )
    if compressed_size != len(body) - 8:
        what = "truncated" if compressed_size > len(body) - 8 else "followed by extra bytes"
        raise SequenceError(
            path,
            f"binary_compressed data {what}: compressed size field {compressed_size}, "
            f"{len(body) - 8} bytes present",
        )
    try:
        flat = lzf_decompress(bytes(body[8:]), uncompressed_size)
    except ValueError as e:
        raise SequenceError(path, f"corrupt LZF data: {e}") from e
    arrays: dict[str, NDArray] = {}
    pos = 0
    for i, (name, count) in enumerate(zip(header.fields, header.count, strict=True)):
        dt = header.field_dtype(i)
        arr = np.frombuffer(flat, dtype=dt, count=header.points * count, offset=pos)
        pos += header.points * count * dt.itemsize
        arrays[name] = (arr.reshape(header.points, count) if count > 1 else arr).copy()
    return arrays


def _read_ascii(path: Path, header: PcdHeader, body: memoryview) -> dict[str, NDArray]:
    ncols = sum(header.count)
    # each value takes at least 2 bytes (digit + separator): cheap bound before splitting
    if header.points * ncols * 2 > len(body) + 1:
        raise SequenceError(
            path,
            f"ascii data truncated: POINTS {header.points} x {ncols} values need at least "
            f"{header.points * ncols * 2} bytes, {len(body)} found",
        )
    tokens = bytes(body).split()
    if len(tokens) != header.points * ncols:
        lines = len(bytes(body).strip().splitlines())
        raise SequenceError(
            path,
            f"ascii data has {len(tokens)} values on {lines} lines, POINTS {header.points} x "
            f"{ncols} = {header.points * ncols} expected",
        )
    table = np.array(tokens, dtype=np.bytes_).reshape(header.points, ncols)
    arrays: dict[str, NDArray] = {}
    col = 0
    for i, (name, count) in enumerate(zip(header.fields, header.count, strict=True)):
        block = table[:, col : col + count]
        col += count
        arrays[name] = _parse_column(path, name, block, header.field_dtype(i), count)
    return arrays


def _parse_column(path: Path, name: str, block: NDArray, dt: np.dtype, count: int) -> NDArray:
    strings = block
    try:
        if dt.kind == "f":
            values = strings.astype(np.float64).astype(dt)
        else:
            wide = strings.astype(np.int64 if dt.kind == "i" else np.uint64)
            info = np.iinfo(dt)
            if wide.size and (wide.min() < info.min or wide.max() > info.max):
                raise ValueError(f"value out of range of {dt}")
            values = wide.astype(dt)
    except ValueError as e:
        bad = _first_unparsable(strings, dt)
        raise SequenceError(path, f"ascii field {name!r}: unparsable value {bad}: {e}") from e
    return values if count > 1 else values[:, 0]


def _first_unparsable(strings: NDArray, dt: np.dtype) -> str:
    conv = float if dt.kind == "f" else int
    for point, row in enumerate(strings):
        for s in row:
            try:
                conv(s)
            except ValueError:
                return f"{s.decode(errors='replace')!r} at point {point}"
    return "(out of range)"


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------


def write_pcd(path: str | Path, cloud: PointCloud, data: str | None = None) -> Path:
    """Write ``cloud`` to ``path`` atomically.

    Parameters
    ----------
    path : str or Path
        Destination .pcd file.
    cloud : PointCloud
        Fields to write. Fields named in ``cloud.header`` are cast to the header's dtype
        (the input's dtypes), new fields keep their own; field order follows the header.
    data : str, optional
        ``ascii``, ``binary`` or ``binary_compressed``; default ``cloud.header.data``.

    Returns
    -------
    Path
        ``path``.
    """
    return atomic_write_bytes(path, encode_pcd(cloud, data))


def encode_pcd(cloud: PointCloud, data: str | None = None) -> bytes:
    """The bytes of the PCD file :func:`write_pcd` writes."""
    data = (data or cloud.header.data).lower()
    if data not in DATA_TYPES:
        raise ValueError(f"unknown PCD DATA type {data!r} (expected {DATA_TYPES})")
    fields = _fields_in_header_dtypes(cloud)
    header = header_for_fields(fields, data, template=cloud.header)
    text = header.to_text().encode("ascii")
    if data == "binary":
        return text + _encode_binary(header, fields)
    if data == "binary_compressed":
        return text + _encode_compressed(fields)
    return text + _encode_ascii(fields)


def _fields_in_header_dtypes(cloud: PointCloud) -> dict[str, NDArray]:
    old = cloud.header
    order = [f for f in old.fields if f in cloud.fields]
    order += [f for f in cloud.fields if f not in old.fields]
    out: dict[str, NDArray] = {}
    for name in order:
        arr = np.asarray(cloud.fields[name])
        if name in old.fields:
            arr = arr.astype(old.field_dtype(old.fields.index(name)), copy=False)
        out[name] = np.ascontiguousarray(arr.astype(arr.dtype.newbyteorder("<"), copy=False))
    return out


def _encode_binary(header: PcdHeader, fields: dict[str, NDArray]) -> bytes:
    records = np.empty(header.points, dtype=_record_dtype(header))
    for name, arr in fields.items():
        records[name] = arr
    return records.tobytes()


def _encode_compressed(fields: dict[str, NDArray]) -> bytes:
    flat = b"".join(arr.tobytes() for arr in fields.values())
    packed = lzf_compress(flat)
    return struct.pack("<II", len(packed), len(flat)) + packed


def _encode_ascii(fields: dict[str, NDArray]) -> bytes:
    if not fields or len(next(iter(fields.values()))) == 0:
        return b""
    columns: list[NDArray] = []
    for arr in fields.values():
        a2 = arr.reshape(len(arr), -1)
        columns.extend(_format_column(a2[:, j]) for j in range(a2.shape[1]))
    rows = zip(*(c.tolist() for c in columns), strict=True)
    return ("\n".join(" ".join(row) for row in rows) + "\n").encode("ascii")


def _format_column(values: NDArray) -> NDArray:
    """Strings that parse back to exactly ``values``.

    Floats use numpy's shortest round-trip repr of their own precision (float32 as
    float32, timestamps as float64), integers their decimal value.
    """
    if values.dtype.kind in "iub":
        return values.astype(np.int64 if values.dtype.kind == "i" else np.uint64).astype(str)
    return values.astype(str)


def _fmt_float64(v: float) -> str:
    return repr(float(v)) if not float(v).is_integer() else str(int(v))


# ---------------------------------------------------------------------------------------
# LZF (liblzf format, as used by PCL), through the C module ``lzf`` (pip ``python-lzf``)
# ---------------------------------------------------------------------------------------


def lzf_decompress(data: bytes, out_len: int) -> bytes:
    """Decompress an LZF stream whose uncompressed size is ``out_len``.

    Raises
    ------
    ValueError
        Corrupt stream or a size other than ``out_len``.
    """
    if out_len == 0:
        return b""
    # one byte of room more than expected: a longer stream fails rather than fits
    out = lzf.decompress(data, out_len + 1)
    if out is None or len(out) != out_len:
        raise ValueError(f"LZF stream does not decompress to {out_len} bytes")
    return bytes(out)


def lzf_compress(data: bytes) -> bytes:
    """Compress ``data`` to an LZF stream (never fails: incompressible data grows ~3 %)."""
    if not data:
        return b""
    out = lzf.compress(data, len(data) + len(data) // 31 + 16)  # liblzf's worst case fits
    if out is None:  # pragma: no cover - the bound above is liblzf's own
        raise ValueError(f"LZF could not compress {len(data)} bytes")
    return bytes(out)
