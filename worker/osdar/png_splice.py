"""Re-encode a PNG of which only a band of rows changed, recompressing only that band.

An augmented camera frame differs from its source PNG in a few hundred rows. Encoding the
whole 4112 x 2504 image again is most of the job's CPU; :func:`splice_png` instead writes a
PNG whose zlib stream is the source's compressed bits before the band (the *head*), the
band deflated anew (the *middle*), and the source's compressed bits after it (the *tail*),
both copied verbatim.

How the three parts fit (RFC 1950 zlib, RFC 1951 deflate, PNG filtered scanlines):

* The uncompressed stream is H scanlines of ``1 + 3 W`` bytes (filter type, then RGB).
  Pixel rows [r0, r1) change the filtered bytes of scanlines r0 .. r1 (scanline r1 is
  filtered against row r1 - 1): bytes ``[lo, hi)``.
* The source's deflate data is inflated with ``Z_BLOCK`` (libz through ctypes; Python's
  ``zlib`` module has no ``Z_BLOCK``), recording every block boundary as (bit position in
  the deflate data, uncompressed position). The head ends at the last boundary A at or
  before ``lo``; the tail starts at the first boundary B at least 32 KiB past ``hi`` (no
  back-reference of a tail block then reaches a changed byte) whose bit offset in its byte
  is even. Inflating stops at B.
* The middle is uncompressed bytes [out_A, out_B): the source's, with scanlines r0 .. r1
  filtered anew from the image. ISA-L (the ``isal`` package; 3.5x faster than libz's
  level 1 and smaller, :func:`isal_level`) deflates it as a raw stream with the window
  before out_A as dictionary, so the decoder's history matches, after an empty stored
  block that takes the head's last partial byte to a byte boundary (level 0: Python's
  zlib writes stored blocks the same way). It ends with
  ``Z_SYNC_FLUSH`` (byte aligned, not final) when a tail follows, else ``Z_FINISH``.
  It uses deflate's largest window, 32 KiB, and the zlib header says so (CINFO 7, as every
  PNG of more than 16 KiB of data has already; libpng declares smaller windows for smaller
  images, where the header is rewritten: a window declared larger than used is valid).
* The tail's first block starts at bit ``k = B % 8`` of its byte. ``k / 2`` empty
  fixed-Huffman blocks (10 bits each) after the byte-aligned middle leave exactly k
  pending bits; they fill the low bits of the tail's first byte, the rest is copied.
* The Adler-32 of the new stream comes from the bytes at hand and the source's: the tail's
  Adler-32 is recovered from the source's total and its prefix's, then combined.

Every chunk but the IDATs is copied, and so are the IDAT chunks wholly in the head or the
tail (CRCs included); the bytes between them go into new IDAT chunks of up to
:data:`IDAT_CHUNK` bytes.

What is checked: the PNG's chunk layout and IHDR, the zlib header, and the inflated part of
the deflate data (a valid stream; when it is inflated to its end, its length and
Adler-32). A tail is copied without being inflated: a corrupt tail in the source stays as
corrupt in the output.
"""

from __future__ import annotations

import bisect
import ctypes
import ctypes.util
import itertools
import logging
import struct
import zlib
from dataclasses import dataclass
from functools import cache
from typing import Any

import cv2
import numpy as np
from isal import isal_zlib
from numpy.typing import NDArray

from worker.osdar.images import PNG_SIGNATURE

logger = logging.getLogger(__name__)

#: Adler-32 modulus (RFC 1950, 9).
ADLER_MOD = 65521
#: The longest back-reference distance of deflate (RFC 1951): the tail starts at least this
#: far past the changed bytes whatever window the zlib header declares. It is the window of
#: the recompressed middle too.
MAX_DISTANCE = 32768
_WINDOW_BITS = 15
#: Longest IDAT chunk written (any length up to 2^31 - 1 is valid).
IDAT_CHUNK = 1 << 20
#: Rows filtered per numpy batch (bounds the temporaries).
_FILTER_BATCH_BYTES = 1 << 20

# zlib.h constants
_Z_OK = 0
_Z_STREAM_END = 1
_Z_BLOCK = 5
_Z_DEFLATED = 8
#: ``strm->data_type`` after inflate(): the unused-bit count, +64 in the last block,
#: +128 right after an end-of-block code (the unused bits are then fewer than 8).
_DT_LAST = 64
_DT_BOUNDARY = 128


class _ZStream(ctypes.Structure):
    """``z_stream`` of zlib.h (field for field; pointers as void pointers)."""

    _fields_ = (
        ("next_in", ctypes.c_void_p),
        ("avail_in", ctypes.c_uint),
        ("total_in", ctypes.c_ulong),
        ("next_out", ctypes.c_void_p),
        ("avail_out", ctypes.c_uint),
        ("total_out", ctypes.c_ulong),
        ("msg", ctypes.c_char_p),
        ("state", ctypes.c_void_p),
        ("zalloc", ctypes.c_void_p),
        ("zfree", ctypes.c_void_p),
        ("opaque", ctypes.c_void_p),
        ("data_type", ctypes.c_int),
        ("adler", ctypes.c_ulong),
        ("reserved", ctypes.c_ulong),
    )


class _Libz:
    """The libz functions used here, with their C signatures."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        p = ctypes.POINTER(_ZStream)
        lib.zlibVersion.restype = ctypes.c_char_p
        lib.zlibVersion.argtypes = []
        self.version: bytes = lib.zlibVersion()
        self.inflateInit2_ = lib.inflateInit2_
        self.inflateInit2_.argtypes = [p, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
        self.inflate = lib.inflate
        self.inflate.argtypes = [p, ctypes.c_int]
        self.inflateEnd = lib.inflateEnd
        self.inflateEnd.argtypes = [p]
        for f in (
            self.inflateInit2_,
            self.inflate,
            self.inflateEnd,
        ):
            f.restype = ctypes.c_int


@cache
def _libz() -> _Libz | None:
    """The system's libz, or None when it cannot be loaded."""
    name = ctypes.util.find_library("z")
    try:
        return _Libz(ctypes.CDLL(name or "libz.so.1"))
    except (OSError, AttributeError) as e:
        logger.warning("libz not loadable (%s): PNGs are not spliced", e)
        return None


@dataclass(frozen=True)
class PngSplice:
    """A spliced PNG and where its zlib stream came from.

    Bit positions count in the source's raw deflate data (the IDAT payload without its 2
    byte zlib header and 4 byte Adler-32), least significant bit of each byte first.

    Attributes
    ----------
    png : bytes
        The new PNG.
    head_bit : int
        Source bits [0, head_bit) are the head: copied (whole bytes verbatim, the last
        partial byte as the first byte of the middle).
    tail_bit : int or None
        Source bits [tail_bit, end) are the tail: copied (the first byte's bits below
        ``tail_bit % 8`` replaced by filler); None when the middle runs to the end.
    recompressed : tuple of int
        The uncompressed (filtered) bytes [start, stop) deflated anew.
    middle_bytes : int
        Bytes written between the head's whole bytes and the tail's first byte.
    """

    png: bytes
    head_bit: int
    tail_bit: int | None
    recompressed: tuple[int, int]
    middle_bytes: int


def splice_png(
    src: bytes, img_bgr: NDArray[np.uint8], rows: tuple[int, int], level: int
) -> bytes | None:
    """PNG bytes of ``img_bgr`` (H, W, 3 uint8, OpenCV BGR order, the same size as the
    source) where only pixel rows [rows[0], rows[1]) differ from the PNG ``src``; None
    when the source is not splicable (then the caller encodes the whole image as before).

    Parameters
    ----------
    src : bytes
        The source PNG: 8-bit RGB (colour type 2), not interlaced, (H, W).
    img_bgr : ndarray
        (H, W, 3) uint8, BGR: the new image, equal to the source outside ``rows``.
    rows : tuple of int
        (r0, r1) with 0 <= r0 <= r1 <= H: the band of pixel rows that may differ.
    level : int
        zlib level 0..9 of the recompressed part.

    Returns
    -------
    bytes or None
        The new PNG (``src`` itself when r0 == r1), or None when ``src`` is not a PNG of
        that kind and size, or its zlib stream is inconsistent or unsupported.

    Raises
    ------
    ValueError
        ``img_bgr`` is not (H, W, 3) uint8, ``rows`` is out of range, or ``level`` is not
        0..9 (the caller's mistakes, not the source's).
    """
    result = splice_png_result(src, img_bgr, rows, level)
    return None if result is None else result.png


def splice_png_result(
    src: bytes, img_bgr: NDArray[np.uint8], rows: tuple[int, int], level: int
) -> PngSplice | None:
    """:func:`splice_png` with the provenance of the new zlib stream (:class:`PngSplice`).

    When r0 == r1 the result is ``src`` with ``head_bit = 0``, ``tail_bit = 0`` (all of it
    copied) and an empty ``recompressed`` range.
    """
    img = np.asarray(img_bgr)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    if not 0 <= level <= 9:
        raise ValueError(f"zlib level must be 0..9, got {level}")
    r0, r1 = int(rows[0]), int(rows[1])
    if not 0 <= r0 <= r1 <= img.shape[0]:
        raise ValueError(f"rows {rows} outside [0, {img.shape[0]}]")

    try:
        png = _parse_png(src)
        if (png.height, png.width) != img.shape[:2]:
            raise _Unsplicable(
                f"PNG is {png.width} x {png.height}, image {img.shape[1]} x {img.shape[0]}"
            )
        if r0 == r1:
            return PngSplice(src, 0, 0, (0, 0), 0)
        return _splice(src, png, img, r0, r1, level)
    except _Unsplicable as e:
        logger.debug("not splicing: %s", e)
        return None


class _Unsplicable(Exception):
    """The source cannot be spliced (the message says why)."""


_Inflated = tuple[NDArray[np.uint8], list[tuple[int, int]], tuple[int, int] | None]


@dataclass(frozen=True)
class DecodedRows:
    """The first rows of a PNG, decoded from as much of its stream as a splice of them
    needs (:func:`decode_rows`, :func:`splice_decoded`).

    Attributes
    ----------
    src : bytes
        The PNG.
    img_bgr : ndarray
        (n, W, 3) uint8, OpenCV's BGR order: its pixel rows [0, n).
    height : int
        The PNG's height H (n <= H).
    """

    src: bytes
    img_bgr: NDArray[np.uint8]
    height: int
    png: _Png
    inflated: _Inflated


def decode_rows(src: bytes, n_rows: int) -> DecodedRows | None:
    """Pixel rows [0, min(n_rows, H)) of the 8-bit RGB PNG ``src``, or None when it is not
    splicable (then decode it whole).

    Its zlib stream is inflated to the first splice point past those rows (the splice
    needs that much, :func:`_inflate_prefix`), not to its end, and those rows' filtered
    scanlines are unfiltered by OpenCV from a PNG of stored deflate blocks made of them
    (inflating stored blocks is a copy). An augmented frame needs its rows down to the
    object's window only: on a 4112 x 2504 frame whose band ends at 60 % of its height,
    this decodes in 0.45 the time of ``cv2.imdecode`` of the whole file
    (scripts/bench_augment.py ``frames_decode``)."""
    try:
        png = _parse_png(src)
        z = _libz()
        if z is None:
            raise _Unsplicable("libz not loadable")
        n = min(max(int(n_rows), 1), png.height)
        stride = 1 + 3 * png.width
        deflate = memoryview(png.zdata)[2:-4]
        inflated = _inflate_prefix(z, deflate, png.height * stride, n * stride + MAX_DISTANCE)
        rows = inflated[0][: n * stride]
        ihdr = struct.pack(">IIBBBBB", png.width, n, 8, 2, 0, 0, 0)
        part = b"".join(
            (
                PNG_SIGNATURE,
                _chunk(b"IHDR", ihdr),
                _chunk(b"IDAT", zlib.compress(rows.data, 0)),
                _chunk(b"IEND", b""),
            )
        )
        img = cv2.imdecode(np.frombuffer(part, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.shape != (n, png.width, 3) or img.dtype != np.uint8:
            raise _Unsplicable("OpenCV did not decode the rows")
    except _Unsplicable as e:
        logger.debug("not decoding rows: %s", e)
        return None
    return DecodedRows(src, img, png.height, png, inflated)


def splice_decoded(
    decoded: DecodedRows, img_bgr: NDArray[np.uint8], rows: tuple[int, int], level: int
) -> PngSplice | None:
    """:func:`splice_png_result` for a source read by :func:`decode_rows`: ``img_bgr`` is
    (n, W, 3) uint8 BGR, the decoded rows [0, n) with rows [r0, r1) changed, where
    ``min(r1 + 1, H) <= n`` (the row below the band is filtered against it). None when the
    source's stream turns out inconsistent (then decode and encode it whole).

    Raises
    ------
    ValueError
        ``img_bgr`` is not the decoded rows' shape, ``rows`` reaches too far, or ``level``
        is not 0..9.
    """
    img = np.asarray(img_bgr)
    if img.shape != decoded.img_bgr.shape or img.dtype != np.uint8:
        raise ValueError(f"expected a {decoded.img_bgr.shape} uint8 image, got {img.shape}")
    if not 0 <= level <= 9:
        raise ValueError(f"zlib level must be 0..9, got {level}")
    r0, r1 = int(rows[0]), int(rows[1])
    if not 0 <= r0 <= r1 or min(r1 + 1, decoded.height) > img.shape[0]:
        raise ValueError(f"rows {rows} need more than the {img.shape[0]} decoded")
    if r0 == r1:
        return PngSplice(decoded.src, 0, 0, (0, 0), 0)
    try:
        return _splice(decoded.src, decoded.png, img, r0, r1, level, decoded.inflated)
    except _Unsplicable as e:
        logger.debug("not splicing: %s", e)
        return None


def _splice(
    src: bytes,
    png: _Png,
    img: NDArray[np.uint8],
    r0: int,
    r1: int,
    level: int,
    inflated: _Inflated | None = None,
) -> PngSplice:
    """:func:`splice_png_result` past the checks of its arguments, for r0 < r1; the
    source's stream inflated far enough already when ``inflated`` is given."""
    z = _libz()
    if z is None:
        raise _Unsplicable("libz not loadable")
    height, width = png.height, png.width
    stride = 1 + 3 * width
    total = height * stride
    stop_row = min(r1 + 1, height)
    lo, hi = r0 * stride, stop_row * stride
    deflate = memoryview(png.zdata)[2:-4]

    if inflated is None:
        inflated = _inflate_prefix(z, deflate, total, hi + MAX_DISTANCE)
    out, bounds, tail = inflated
    bit_a, out_a = max(b for b in bounds if b[1] <= lo)
    out_b = total if tail is None else tail[1]

    new_rows = _filter_rows(img, r0, stop_row)
    middle = np.concatenate((out[out_a:lo], new_rows.reshape(-1), out[hi:out_b]))
    prime_bits = bit_a & 7
    prime_value = deflate[bit_a >> 3] & ((1 << prime_bits) - 1) if prime_bits else 0
    compressed = _deflate_middle(
        middle,
        level,
        out[max(0, out_a - MAX_DISTANCE) : out_a],
        prime_bits,
        prime_value,
        finish=tail is None,
    )

    src_adler = int.from_bytes(png.zdata[-4:], "big")
    head_adler = zlib.adler32(out[:out_a].data)
    new_adler = zlib.adler32(middle.data, head_adler)
    prefix_adler = zlib.adler32(out[out_a:out_b].data, head_adler)
    if tail is None:
        if prefix_adler != src_adler:
            raise _Unsplicable("the source's Adler-32 does not match its data")
        new_middle = compressed
        tail_z = len(png.zdata) - 4
    else:
        bit_b = tail[0]
        k = bit_b & 7
        filler, pending = _empty_fixed_blocks(k // 2)
        first = pending | (deflate[bit_b >> 3] & (0xFF << k) & 0xFF)
        new_middle = b"".join((compressed, filler, bytes((first,))))
        tail_z = 2 + (bit_b >> 3) + 1
        tail_len = total - out_b
        tail_adler = adler32_tail(src_adler, prefix_adler, tail_len)
        new_adler = adler32_combine(new_adler, tail_adler, tail_len)
    new_png = _assemble(src, png, 2 + (bit_a >> 3), new_middle, tail_z, new_adler)
    middle_bytes = len(new_middle) - (tail is not None)
    logger.debug(
        "spliced rows [%d, %d): head %d bits, recompressed [%d, %d) of %d bytes into %d, "
        "tail from bit %s",
        r0,
        r1,
        bit_a,
        out_a,
        out_b,
        total,
        middle_bytes,
        None if tail is None else tail[0],
    )
    return PngSplice(
        new_png,
        bit_a,
        None if tail is None else tail[0],
        (out_a, out_b),
        middle_bytes,
    )


# --- Adler-32 arithmetic ---------------------------------------------------------------


def adler32_combine(adler_x: int, adler_y: int, len_y: int) -> int:
    """Adler-32 of X || Y from the Adler-32 of X, of Y and the length of Y.

    With A = 1 + sum of bytes, B = sum of the A's after each byte (mod 65521) and
    Adler = B << 16 | A: A_XY = A_X + A_Y - 1, B_XY = B_X + B_Y + len(Y) (A_X - 1).
    """
    a_x, b_x = adler_x & 0xFFFF, adler_x >> 16
    a_y, b_y = adler_y & 0xFFFF, adler_y >> 16
    a = (a_x + a_y - 1) % ADLER_MOD
    b = (b_x + b_y + (len_y % ADLER_MOD) * (a_x - 1)) % ADLER_MOD
    return (b << 16) | a


def adler32_tail(adler_xy: int, adler_x: int, len_y: int) -> int:
    """Adler-32 of Y from the Adler-32 of X || Y, of X and the length of Y.

    The inverse of :func:`adler32_combine` in its second argument.
    """
    a_xy, b_xy = adler_xy & 0xFFFF, adler_xy >> 16
    a_x, b_x = adler_x & 0xFFFF, adler_x >> 16
    a = (a_xy - a_x + 1) % ADLER_MOD
    b = (b_xy - b_x - (len_y % ADLER_MOD) * (a_x - 1)) % ADLER_MOD
    return (b << 16) | a


# --- PNG chunks ------------------------------------------------------------------------


@dataclass(frozen=True)
class _Png:
    """A parsed PNG: where its IDAT chunks are, their concatenated payload, the header."""

    width: int
    height: int
    header: bytes  # the zlib header to write: the source's with CINFO 7
    zdata: bytes  # the zlib stream: concatenated IDAT data
    chunk_starts: list[int]  # where each IDAT chunk starts in the file
    z_starts: list[int]  # where each IDAT chunk's data starts in ``zdata``
    idat_end: int  # where the last IDAT chunk ends in the file


def _chunk(ctype: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC-32 of type and data."""
    crc = zlib.crc32(data, zlib.crc32(ctype))
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", crc)


def _parse_png(src: bytes) -> _Png:
    """The parts of an 8-bit RGB non-interlaced PNG.

    Raises
    ------
    _Unsplicable
        Not such a PNG, malformed, or with a zlib header not handled here.
    """
    if not src.startswith(PNG_SIGNATURE):
        raise _Unsplicable("not a PNG (bad signature)")
    pos = len(PNG_SIGNATURE)
    idat: list[tuple[int, int]] = []  # (start, end) of each IDAT chunk
    first_idat = last_idat_end = -1
    ihdr: bytes | None = None
    while pos < len(src):
        if pos + 12 > len(src):
            raise _Unsplicable("truncated chunk header")
        length, ctype = struct.unpack_from(">I4s", src, pos)
        end = pos + 12 + length
        if length > 0x7FFFFFFF or end > len(src):
            raise _Unsplicable(f"chunk {ctype!r} overruns the file")
        if ihdr is None:
            if ctype != b"IHDR" or length != 13:
                raise _Unsplicable("first chunk is not a 13-byte IHDR")
            ihdr = src[pos + 8 : pos + 21]
        elif ctype == b"IDAT":
            if first_idat < 0:
                first_idat = pos
            elif last_idat_end != pos:
                raise _Unsplicable("IDAT chunks not consecutive")
            idat.append((pos, end))
            last_idat_end = end
        elif ctype == b"acTL":
            raise _Unsplicable("animated PNG")
        pos = end
        if ctype == b"IEND":
            break
    if ihdr is None or not idat:
        raise _Unsplicable("no IHDR or no IDAT")
    width, height, depth, colour, method, filt, interlace = struct.unpack(">IIBBBBB", ihdr)
    if width == 0 or height == 0:
        raise _Unsplicable("empty image")
    if (depth, colour, method, filt, interlace) != (8, 2, 0, 0, 0):
        raise _Unsplicable(
            f"bit depth {depth}, colour type {colour}, compression {method}, filter {filt}, "
            f"interlace {interlace}: only 8-bit RGB, not interlaced"
        )
    view = memoryview(src)
    zdata = b"".join([view[a + 8 : b - 4] for a, b in idat])
    if len(zdata) < 2 + 1 + 4:
        raise _Unsplicable("zlib stream too short")
    cmf, flg = zdata[0], zdata[1]
    if (cmf << 8 | flg) % 31 or cmf & 0x0F != _Z_DEFLATED or flg & 0x20:
        raise _Unsplicable(f"zlib header {cmf:#04x} {flg:#04x}: bad check, not deflate, or FDICT")
    if cmf >> 4 > 7:
        raise _Unsplicable(f"zlib window 2^{(cmf >> 4) + 8} is not allowed (CINFO > 7)")
    cmf = ((_WINDOW_BITS - 8) << 4) | _Z_DEFLATED
    flg &= 0xE0  # FLEVEL, FDICT 0; then FCHECK
    header = bytes((cmf, flg | (31 - (cmf << 8 | flg) % 31) % 31))
    z_starts = [0, *itertools.accumulate(b - a - 12 for a, b in idat[:-1])]
    return _Png(width, height, header, zdata, [a for a, _ in idat], z_starts, last_idat_end)


def _assemble(src: bytes, png: _Png, head_z: int, middle: bytes, tail_z: int, adler: int) -> bytes:
    """The new PNG: ``src`` with its zlib stream's bytes [head_z, tail_z) replaced by
    ``middle``, its header by ``png.header`` and its Adler-32 by ``adler``.

    IDAT chunks wholly before ``head_z`` (unless the header changes) or wholly within
    [tail_z, the Adler-32) are copied with their CRCs; the bytes between them are written
    as new chunks.
    """
    zdata, starts = png.zdata, png.z_starts
    adler_z = len(zdata) - 4
    ends = [*starts[1:], len(zdata)]
    head = 0  # chunks [0, head) copied
    if png.header == zdata[:2]:
        head = bisect.bisect_right(ends, head_z)
    before_head = zdata[starts[head] : head_z] if head else png.header + zdata[2:head_z]
    first_tail = bisect.bisect_left(starts, tail_z)  # chunks [first_tail, last_tail) copied
    last_tail = bisect.bisect_right(ends, adler_z)
    trailer = struct.pack(">I", adler)
    if first_tail < last_tail:
        rewritten = [before_head, middle, zdata[tail_z : starts[first_tail]]]
        copied_tail = src[png.chunk_starts[first_tail] : png.chunk_starts[last_tail]]
        last = zdata[starts[last_tail] : adler_z] + trailer
    else:
        rewritten = [before_head, middle, zdata[tail_z:adler_z], trailer]
        copied_tail, last = b"", b""
    parts = [src[: png.chunk_starts[head]], *_idat_chunks(b"".join(rewritten)), copied_tail]
    parts += [*_idat_chunks(last), src[png.idat_end :]]
    return b"".join(parts)


def _idat_chunks(data: bytes) -> list[bytes]:
    """``data`` as IDAT chunks of at most :data:`IDAT_CHUNK` bytes (none when empty)."""
    return [_chunk(b"IDAT", data[i : i + IDAT_CHUNK]) for i in range(0, len(data), IDAT_CHUNK)]


# --- inflating the source, deflating the middle ---------------------------------------


def _inflate_prefix(
    z: _Libz, deflate: memoryview, total: int, need_out: int
) -> tuple[NDArray[np.uint8], list[tuple[int, int]], tuple[int, int] | None]:
    """Inflate raw deflate data up to the first splice point at or past ``need_out``.

    Parameters
    ----------
    z : _Libz
        libz.
    deflate : memoryview
        The raw deflate data, the whole of it.
    total : int
        Its expected uncompressed length.
    need_out : int
        Stop at the first block boundary whose uncompressed position is at least this and
        whose bit offset within its byte is even (not the end of the stream).

    Returns
    -------
    tuple
        (out, bounds, tail): ``out`` (total + 1,) uint8 with the inflated bytes in front;
        ``bounds`` every block boundary passed as (bit position, uncompressed position),
        starting with (0, 0); ``tail`` the boundary stopped at, None when the stream was
        inflated to its end (then checked to end where the data ends, at ``total``).

    Raises
    ------
    _Unsplicable
        The data is not a valid deflate stream of that length.
    """
    src = np.frombuffer(deflate, dtype=np.uint8)
    out = np.empty(total + 1, dtype=np.uint8)
    strm = _ZStream()
    _zcheck(
        z.inflateInit2_(ctypes.byref(strm), -15, z.version, ctypes.sizeof(strm)), "inflateInit2"
    )
    try:
        strm.next_in = src.ctypes.data
        strm.avail_in = src.size
        strm.next_out = out.ctypes.data
        strm.avail_out = out.size
        bounds = [(0, 0)]
        while True:
            before = (strm.total_in, strm.total_out)
            ret = z.inflate(ctypes.byref(strm), _Z_BLOCK)
            if ret == _Z_STREAM_END:
                if strm.total_out != total or strm.avail_in != 0:
                    raise _Unsplicable(
                        f"deflate data inflates to {strm.total_out} bytes ({total} expected) "
                        f"and leaves {strm.avail_in} bytes over"
                    )
                return out, bounds, None
            if ret != _Z_OK or before == (strm.total_in, strm.total_out):
                msg = strm.msg.decode(errors="replace") if strm.msg else f"code {ret}"
                raise _Unsplicable(f"inflate stopped at input byte {strm.total_in}: {msg}")
            if strm.total_out > total:
                raise _Unsplicable(f"deflate data inflates to over {total} bytes")
            dt = strm.data_type
            if dt & _DT_BOUNDARY:
                bound = (strm.total_in * 8 - (dt & 7), strm.total_out)
                bounds.append(bound)
                if not dt & _DT_LAST and bound[1] >= need_out and bound[0] % 2 == 0:
                    return out, bounds, bound
    finally:
        z.inflateEnd(ctypes.byref(strm))


def isal_level(level: int) -> int:
    """ISA-L's deflate level (1-3) for a zlib level 1-9: 1-3 -> 1, 4-6 -> 2, 7-9 -> 3.

    On a 700-row band of a synthetic 4112 x 2504 frame (8.6 MB filtered) ISA-L's level 1
    gives 0.529 of the size in 38 ms, zlib's level 1 0.561 in 134 ms and its level 3
    0.546 in 301 ms: every ISA-L level is smaller than zlib's levels 1-3 and faster."""
    return 1 + (min(max(level, 1), 9) - 1) // 3


def _deflate_middle(
    data: NDArray[np.uint8],
    level: int,
    dictionary: NDArray[np.uint8],
    prime_bits: int,
    prime_value: int,
    *,
    finish: bool,
) -> bytes:
    """Raw deflate of ``data`` (n,) uint8 continuing a stream that ends ``prime_bits`` bits
    ``prime_value`` into a byte, with ``dictionary`` (m,) uint8 as history; ends with
    ``Z_FINISH`` (final block) when ``finish``, else ``Z_SYNC_FLUSH`` (byte aligned).

    ``level`` is zlib's (0-9): 0 writes stored blocks (Python's zlib), 1-9 ISA-L's
    deflater at :func:`isal_level`. Neither continues a stream mid-byte (libz's
    ``deflatePrime`` is not in Python's zlib, ISA-L has none), so an empty stored block
    after the pending bits (3 header bits of zeros, padding to the byte, LEN 0, NLEN
    0xFFFF) first brings the stream to a byte boundary."""
    lead = b""
    if prime_bits:
        lead = bytes((prime_value,)) + (b"\x00" if prime_bits > 5 else b"") + b"\x00\x00\xff\xff"
    lib: Any = zlib if level == 0 else isal_zlib
    extra = {"zdict": np.ascontiguousarray(dictionary).data} if dictionary.size else {}
    comp = lib.compressobj(
        0 if level == 0 else isal_level(level), lib.DEFLATED, -_WINDOW_BITS, **extra
    )
    body = comp.compress(np.ascontiguousarray(data).data)
    end = comp.flush(lib.Z_FINISH if finish else lib.Z_SYNC_FLUSH)
    return b"".join((lead, body, end))


def _zcheck(ret: int, what: str) -> None:
    """Raise :class:`_Unsplicable` (and warn: libz should not fail here) unless Z_OK."""
    if ret != _Z_OK:
        logger.warning("%s failed with code %d", what, ret)
        raise _Unsplicable(f"{what} failed")


def _empty_fixed_blocks(n: int) -> tuple[bytes, int]:
    """n empty non-final fixed-Huffman deflate blocks from a byte boundary.

    Each is 10 bits, LSB first: BFINAL 0, BTYPE 01, end-of-block code 0000000.

    Returns
    -------
    tuple
        (whole bytes, the remaining ``(10 n) % 8 = 2 n % 8`` bits as an int).
    """
    acc = 0
    for i in range(n):
        acc |= 0b10 << (10 * i)
    nbits = 10 * n
    whole = nbits // 8
    return acc.to_bytes(whole + 1, "little")[:whole], acc >> (8 * whole)


# --- PNG filtering ---------------------------------------------------------------------


def _filter_rows(img_bgr: NDArray[np.uint8], start: int, stop: int) -> NDArray[np.uint8]:
    """Filtered scanlines ``start .. stop - 1`` of ``img_bgr`` (H, W, 3) BGR.

    Each row takes the filter libpng's adaptive heuristic takes: the least sum of the
    filtered bytes' magnitudes as signed bytes, among None, Sub, Up, Average, Paeth (in
    that order on ties); row ``start - 1`` (zeros above row 0) is the prior row.

    Returns
    -------
    ndarray
        (stop - start, 1 + 3 W) uint8: filter type byte, then the filtered RGB bytes.
    """
    width = img_bgr.shape[1]
    n_bytes = 3 * width
    out = np.empty((stop - start, 1 + n_bytes), dtype=np.uint8)
    batch = max(1, _FILTER_BATCH_BYTES // n_bytes)
    for s in range(start, stop, batch):
        e = min(s + batch, stop)
        first = max(s - 1, 0)
        bgr = np.ascontiguousarray(img_bgr[first:e])
        rgb = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)
        rgb = rgb.reshape(e - first, n_bytes)
        cur = rgb[s - first :]
        if s == 0:
            prev = np.zeros_like(cur)
            prev[1:] = cur[:-1]
        else:
            prev = rgb[:-1]
        out[s - start : e - start] = _filter_batch(cur, prev)
    return out


def _filter_batch(cur: NDArray[np.uint8], prev: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(n, 1 + m) filtered rows of (n, m) raw RGB rows ``cur`` below ``prev`` (n, m)."""
    n, m = cur.shape
    a = np.zeros_like(cur)  # left (3 bytes per pixel)
    a[:, 3:] = cur[:, :-3]
    c = np.zeros_like(prev)  # upper left
    c[:, 3:] = prev[:, :-3]
    # Paeth: p = a + b - c; |p - a| = |b - c|, |p - b| = |a - c|, |p - c| = |a + b - 2 c|
    c16 = c.astype(np.int16)
    pa = np.subtract(prev, c16, dtype=np.int16)
    pb = np.subtract(a, c16, dtype=np.int16)
    pc = np.add(pa, pb)
    for d in (pa, pb, pc):
        np.abs(d, out=d)
    # select by byte masks (0x00 / 0xFF): much faster than np.where on uint8
    take_a = pa <= pb
    take_a &= pa <= pc
    mask_a = np.negative(take_a.view(np.uint8))
    mask_b = np.negative((pb <= pc).view(np.uint8))
    paeth = prev & mask_b
    paeth |= c & ~mask_b
    paeth &= ~mask_a
    paeth |= a & mask_a
    average = np.add(a, prev, dtype=np.uint16)
    average >>= 1
    candidates = np.empty((5, n, m), dtype=np.uint8)  # None, Sub, Up, Average, Paeth
    candidates[0] = cur
    np.subtract(cur, a, out=candidates[1])
    np.subtract(cur, prev, out=candidates[2])
    np.subtract(cur, average, out=candidates[3], casting="unsafe")  # mod 256
    np.subtract(cur, paeth, out=candidates[4])
    # |v| of each byte read as int8, as uint8 (|-128| wraps to -128, read back as 128)
    cost = np.abs(candidates.view(np.int8)).view(np.uint8).sum(axis=2, dtype=np.int64)
    best = np.argmin(cost, axis=0)  # the first of equal costs, as libpng
    out = np.empty((n, 1 + m), dtype=np.uint8)
    out[:, 0] = best
    out[:, 1:] = candidates[best, np.arange(n)]
    return out
