"""Splicing a changed band of rows into a PNG's zlib stream (worker/osdar/png_splice.py)."""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Callable
from functools import cache

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from PIL import Image

from worker.osdar.png_splice import (
    ADLER_MOD,
    MAX_DISTANCE,
    _deflate_middle,
    _empty_fixed_blocks,
    _filter_rows,
    _inflate_prefix,
    _libz,
    adler32_combine,
    adler32_tail,
    decode_rows,
    isal_level,
    splice_decoded,
    splice_png,
    splice_png_result,
)

SIGNATURE = b"\x89PNG\r\n\x1a\n"
SOURCES = ("cv2-0", "cv2-1", "cv2-3", "cv2-6", "cv2-9", "pil-1", "pil-6")
# name: (r0, r1) as fractions of the height
BANDS = {
    "middle": (0.42, 0.55),
    "top": (0.0, 0.04),
    "bottom": (0.96, 1.0),
    "whole": (0.0, 1.0),
    "one-row": (0.3, None),
}


# --- images and PNGs ---------------------------------------------------------------------


@cache
def camera_like(height: int, width: int, seed: int = 0) -> NDArray[np.uint8]:
    """(H, W, 3) BGR: smooth gradients, sensor noise, sharp-edged boxes and stripes."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    img = np.stack(
        (
            120 + 90 * np.sin(x / (width / 5)),
            110 + 80 * np.cos(y / (height / 4)),
            255 * (x + y) / (height + width),
        ),
        axis=-1,
    )
    img += rng.normal(0, 2.5, img.shape)
    for _ in range(12):
        y0, x0 = rng.integers(0, max(1, height - 20)), rng.integers(0, max(1, width - 20))
        h, w = rng.integers(1, max(2, height // 4)), rng.integers(1, max(2, width // 4))
        img[y0 : y0 + h, x0 : x0 + w] = rng.uniform(0, 255, 3)
    img[:, width // 3 : width // 3 + 40 : 4] = 250  # vertical stripes
    out: NDArray[np.uint8] = np.clip(img, 0, 255).astype(np.uint8)
    return out


def encode(img_bgr: NDArray[np.uint8], source: str) -> bytes:
    """PNG of ``img_bgr`` by OpenCV (``cv2-<level>``) or Pillow (``pil-<level>``)."""
    writer, level = source.split("-")
    if writer == "cv2":
        ok, buf = cv2.imencode(".png", img_bgr, [cv2.IMWRITE_PNG_COMPRESSION, int(level)])
        assert ok
        return buf.tobytes()
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img_bgr[..., ::-1])).save(
        out, format="PNG", compress_level=int(level)
    )
    return out.getvalue()


@cache
def source_png(height: int, width: int, source: str) -> bytes:
    return encode(camera_like(height, width), source)


def changed(img: NDArray[np.uint8], r0: int, r1: int, seed: int = 1) -> NDArray[np.uint8]:
    """``img`` with rows [r0, r1) given random content in part and an object in part."""
    rng = np.random.default_rng(seed)
    new = img.copy()
    w = img.shape[1]
    new[r0:r1, w // 4 : w // 2] = rng.integers(0, 256, (r1 - r0, w // 2 - w // 4, 3))
    new[r0:r1, w // 2 : w // 2 + w // 8] = (30, 200, 90)
    return new


def chunks(png: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of every chunk, asserting the signature, lengths and CRCs."""
    assert png[:8] == SIGNATURE
    out, pos = [], 8
    while pos < len(png):
        (length,) = struct.unpack_from(">I", png, pos)
        ctype, data = png[pos + 4 : pos + 8], png[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack_from(">I", png, pos + 8 + length)
        assert crc == zlib.crc32(ctype + data), f"bad CRC in {ctype!r} at {pos}"
        out.append((ctype, data))
        pos += 12 + length
    assert pos == len(png)
    return out


def zlib_stream(png: bytes) -> bytes:
    return b"".join(data for ctype, data in chunks(png) if ctype == b"IDAT")


def assert_valid_png_of(png: bytes, img_bgr: NDArray[np.uint8]) -> None:
    """``png`` is a valid PNG (CRCs, zlib Adler-32) that decodes to exactly ``img_bgr``."""
    parsed = chunks(png)
    types = [t for t, _ in parsed]
    assert types[0] == b"IHDR" and types[-1] == b"IEND"
    first = types.index(b"IDAT")
    assert set(types[first : len(types) - types[::-1].index(b"IDAT")]) == {b"IDAT"}
    h, w = img_bgr.shape[:2]
    assert len(zlib.decompress(zlib_stream(png))) == h * (1 + 3 * w)  # checks the Adler-32
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded, img_bgr)
    with Image.open(io.BytesIO(png)) as im:
        im.load()
        np.testing.assert_array_equal(np.asarray(im), img_bgr[..., ::-1])


def band_rows(height: int, band: str) -> tuple[int, int]:
    f0, f1 = BANDS[band]
    r0 = round(f0 * height)
    return r0, r0 + 1 if f1 is None else round(f1 * height)


# --- Adler-32 and filler helpers ---------------------------------------------------------


@pytest.mark.parametrize("len_x", [0, 1, 5552, 70_000])
@pytest.mark.parametrize("len_y", [0, 1, 3, 65_521, 200_000])
def test_adler32_combine_and_tail(len_x: int, len_y: int) -> None:
    rng = np.random.default_rng(len_x * 7 + len_y)
    x = rng.integers(0, 256, len_x, dtype=np.uint8).tobytes()
    y = (b"\xff" * len_y) if len_y == 65_521 else rng.integers(0, 256, len_y, np.uint8).tobytes()
    ax, ay, axy = zlib.adler32(x), zlib.adler32(y), zlib.adler32(x + y)
    assert adler32_combine(ax, ay, len_y) == axy
    assert adler32_tail(axy, ax, len_y) == ay
    assert adler32_tail(axy, ax, len_y + ADLER_MOD) == ay  # lengths count mod 65521


def _fixed_literal_blocks(literals: list[bytes]) -> tuple[bytes, int, int]:
    """Non-final fixed-Huffman blocks, one per item of ``literals``, as (whole bytes,
    pending bit count, pending bits): literals 0-143 take 8 bits, 144-255 9 (RFC 1951,
    3.2.6), so the blocks end at any bit of a byte."""
    acc, n = 0, 0

    def put(value: int, nbits: int) -> None:  # LSB first
        nonlocal acc, n
        acc |= value << n
        n += nbits

    def code(c: int, nbits: int) -> None:  # Huffman codes go MSB first
        put(int(f"{c:0{nbits}b}"[::-1], 2), nbits)

    for block in literals:
        put(0, 1)  # BFINAL
        put(1, 2)  # BTYPE 01
        for lit in block:
            code(0x30 + lit, 8) if lit < 144 else code(0x190 + lit - 144, 9)
        code(0, 7)  # end of block
    whole = n // 8
    return acc.to_bytes(whole + 1, "little")[:whole], n % 8, acc >> (8 * whole)


@pytest.mark.parametrize("level", [0, 1, 9])
@pytest.mark.parametrize("finish", [True, False])
def test_middle_continues_a_stream_at_every_bit(finish: bool, level: int) -> None:
    """The middle after a head that ends at each bit 0-7 of a byte, with the head's bytes
    as history: the stream inflates to head + middle (the stored-block lead); deflated
    (ISA-L), it refers back into the history."""
    rng = np.random.default_rng(5)
    seen = set()
    for k in range(48):
        head = [bytes(rng.integers(0, 256, 300, dtype=np.uint8))] + [
            bytes(rng.integers(0, 256, int(rng.integers(1, 6)), dtype=np.uint8))
            for _ in range(k % 4 + 1)
        ]
        whole, nbits, pending = _fixed_literal_blocks(head)
        seen.add(nbits)
        history = b"".join(head)
        data = np.frombuffer(history, np.uint8)  # all of it a match into the history
        middle = _deflate_middle(data, level, data, nbits, pending, finish=finish)
        d = zlib.decompressobj(-15)
        out = d.decompress(whole + middle + (b"" if finish else b"\x03\x00"))
        assert out == history + history
        assert d.eof and d.unused_data == b""
        if level:
            assert len(middle) < 40  # 300+ random bytes as a few matches
    assert seen == set(range(8))


def test_isal_levels_from_zlib_levels() -> None:
    assert [isal_level(lv) for lv in range(1, 10)] == [1, 1, 1, 2, 2, 2, 3, 3, 3]


@pytest.mark.parametrize("n", range(5))
def test_empty_fixed_blocks_inflate_to_nothing(n: int) -> None:
    whole, pending = _empty_fixed_blocks(n)
    nbits = 10 * n
    assert len(whole) == nbits // 8 and pending < 1 << (nbits % 8)
    # then a final empty fixed block (BFINAL 1, BTYPE 01, EOB 0000000)
    bits = int.from_bytes(whole, "little") | pending << (8 * len(whole)) | 0b11 << nbits
    stream = bits.to_bytes((nbits + 10 + 7) // 8, "little")
    d = zlib.decompressobj(-15)
    assert d.decompress(stream) == b""
    assert d.eof and d.unused_data == b""


def test_filters_match_libpng() -> None:
    """OpenCV's libpng picks each row's filter by the same heuristic: same bytes."""
    img = camera_like(480, 640)
    src = source_png(480, 640, "cv2-1")
    filtered = np.frombuffer(zlib.decompress(zlib_stream(src)), np.uint8).reshape(480, -1)
    ours = _filter_rows(img, 0, 480)
    assert len(set(ours[:, 0].tolist())) >= 3  # the image exercises several filters
    np.testing.assert_array_equal(ours, filtered)
    np.testing.assert_array_equal(_filter_rows(img, 200, 260), filtered[200:260])


# --- splicing ----------------------------------------------------------------------------


@pytest.mark.parametrize("level", [1, 6])
@pytest.mark.parametrize("band", list(BANDS))
@pytest.mark.parametrize("source", SOURCES)
def test_splice_decodes_to_the_new_image(source: str, band: str, level: int) -> None:
    h, w = 480, 640
    src = source_png(h, w, source)
    r0, r1 = band_rows(h, band)
    new = changed(camera_like(h, w), r0, r1)
    res = splice_png_result(src, new, (r0, r1), level)
    assert res is not None
    assert_valid_png_of(res.png, new)

    # the head and the tail are the source's compressed bytes, copied
    src_deflate, out_deflate = zlib_stream(src)[2:-4], zlib_stream(res.png)[2:-4]
    head = res.head_bit // 8
    assert out_deflate[:head] == src_deflate[:head]
    stride = 1 + 3 * w
    start, stop = res.recompressed
    assert start <= r0 * stride and stop >= min(r1 + 1, h) * stride
    if res.tail_bit is None:
        assert stop == h * stride
    else:
        assert res.tail_bit % 2 == 0 and stop >= min(r1 + 1, h) * stride + MAX_DISTANCE
        copied = len(src_deflate) - (res.tail_bit // 8 + 1)
        assert copied > 0 and out_deflate[-copied:] == src_deflate[-copied:]
        assert len(out_deflate) == head + res.middle_bytes + 1 + copied
    if band == "top":
        assert res.head_bit == 0 and res.tail_bit is not None
    if band in ("bottom", "whole"):
        assert res.tail_bit is None
    if band == "middle":
        assert res.head_bit > 0 and res.tail_bit is not None
    assert splice_png(src, new, (r0, r1), level) == res.png


@pytest.mark.parametrize("source", ["cv2-1", "pil-6"])
def test_middle_band_of_a_large_image_recompresses_little(source: str) -> None:
    h, w = 1200, 2000
    src = source_png(h, w, source)
    r0, r1 = 560, 620
    new = changed(camera_like(h, w), r0, r1, seed=5)
    res = splice_png_result(src, new, (r0, r1), 1)
    assert res is not None
    assert_valid_png_of(res.png, new)
    assert res.head_bit > 0 and res.tail_bit is not None
    stride = 1 + 3 * w
    start, stop = res.recompressed
    # the recompressed range is the band (61 scanlines) and some blocks around it
    assert stop - start < 0.15 * h * stride
    assert res.middle_bytes < 0.15 * len(src)
    src_deflate_bits = 8 * (len(zlib_stream(src)) - 6)
    assert res.head_bit > 0.3 * src_deflate_bits
    assert src_deflate_bits - res.tail_bit > 0.3 * src_deflate_bits


def test_odd_tail_boundary_is_skipped() -> None:
    """Where the first boundary far enough past the band starts at an odd bit, the tail
    starts at a later boundary with an even one."""
    h, w = 480, 640
    z = _libz()
    assert z is not None
    stride = 1 + 3 * w
    found = 0
    for source in SOURCES[1:]:  # not cv2-0: stored blocks end on byte boundaries
        src = source_png(h, w, source)
        deflate = memoryview(zlib_stream(src))[2:-4]
        _, bounds, _ = _inflate_prefix(z, deflate, h * stride, h * stride + 1)
        for r0 in range(0, h - 100, 23):
            need = (r0 + 11) * stride + MAX_DISTANCE
            first = next(b for b in bounds if b[1] >= need)
            if first[0] % 2 == 0 or first[1] == h * stride or found >= 6:
                continue
            found += 1
            new = changed(camera_like(h, w), r0, r0 + 10)
            res = splice_png_result(src, new, (r0, r0 + 10), 1)
            assert res is not None and res.tail_bit is not None
            assert res.tail_bit > first[0] and res.tail_bit % 2 == 0
            assert_valid_png_of(res.png, new)
    assert found > 0


def test_splice_of_a_splice_and_level_0() -> None:
    """A spliced PNG is a source like another; level 0 writes stored blocks."""
    h, w = 480, 640
    img = camera_like(h, w)
    first = changed(img, 100, 140)
    png1 = splice_png(source_png(h, w, "cv2-1"), first, (100, 140), 0)
    assert png1 is not None
    assert_valid_png_of(png1, first)
    second = changed(first, 120, 300, seed=9)
    png2 = splice_png(png1, second, (120, 300), 6)
    assert png2 is not None
    assert_valid_png_of(png2, second)


def rechunked(png: bytes, sizes: list[int]) -> bytes:
    """``png`` with its zlib stream in IDAT chunks of ``sizes`` (cycled; 0 allowed), the
    last one ending with the last 2 bytes of the Adler-32 alone."""
    parsed = chunks(png)
    stream = zlib_stream(png)
    body, pieces, i, k = stream[:-2], [], 0, 0
    while i < len(body):
        size = sizes[k % len(sizes)]
        pieces.append(body[i : i + size])
        i, k = i + size, k + 1
    pieces.append(stream[-2:])
    first = next(i for i, (t, _) in enumerate(parsed) if t == b"IDAT")
    rest = [c for c in parsed[first:] if c[0] != b"IDAT"]
    out = [SIGNATURE]
    for t, data in [*parsed[:first], *((b"IDAT", p) for p in pieces), *rest]:
        out.append(
            struct.pack(">I", len(data)) + t + data + struct.pack(">I", zlib.crc32(t + data))
        )
    return b"".join(out)


@pytest.mark.parametrize("sizes", [[10**9], [97], [5000, 0, 1, 3]], ids=["one", "97", "mixed"])
@pytest.mark.parametrize("band", ["middle", "top", "bottom"])
def test_idat_chunking_of_the_source(sizes: list[int], band: str) -> None:
    """Chunks wholly in the head or the tail are copied, the others rewritten."""
    h, w = 480, 640
    src = rechunked(source_png(h, w, "cv2-1"), sizes)
    r0, r1 = band_rows(h, band)
    new = changed(camera_like(h, w), r0, r1)
    png = splice_png(src, new, (r0, r1), 1)
    assert png is not None
    assert_valid_png_of(png, new)
    if sizes == [97] and band == "middle":
        src_chunks, out_chunks = chunks(src), chunks(png)
        assert out_chunks[:100] == src_chunks[:100]
        # the source ends ..., 97 bytes with 2 of the Adler-32, its last 2 bytes, IEND; the
        # output ..., the 95 bytes and the new Adler-32, IEND
        assert out_chunks[-100:-2] == src_chunks[-101:-3]
        assert out_chunks[-2][1] == src_chunks[-3][1][:-2] + zlib_stream(png)[-4:]


@pytest.mark.parametrize("size", [(4, 5), (30, 40), (60, 80)])
def test_small_window_of_small_images(size: tuple[int, int]) -> None:
    """libpng declares a window under 32 KiB for small images: the output declares 32 KiB."""
    h, w = size
    img = camera_like(h, w)
    src = encode(img, "cv2-6")
    assert zlib_stream(src)[0] >> 4 < 7
    for r0, r1 in ((0, 1), (h // 2, h // 2 + 1), (h - 1, h)):
        new = changed(img, r0, r1)
        png = splice_png(src, new, (r0, r1), 1)
        assert png is not None
        assert_valid_png_of(png, new)
        assert zlib_stream(png)[0] == 0x78


def test_unchanged_rows_return_the_source() -> None:
    src = source_png(480, 640, "cv2-1")
    assert splice_png(src, camera_like(480, 640), (200, 200), 1) is src


# --- what is not spliced -----------------------------------------------------------------


def with_chunk_data(png: bytes, ctype: bytes, edit: Callable[[bytes], bytes]) -> bytes:
    """``png`` with the data of its first ``ctype`` chunk replaced by ``edit(data)``."""
    out = [SIGNATURE]
    done = False
    for t, data in chunks(png):
        if t == ctype and not done:
            data = edit(data)
            done = True
        out.append(
            struct.pack(">I", len(data)) + t + data + struct.pack(">I", zlib.crc32(t + data))
        )
    return b"".join(out)


def zlib_header(cmf: int, flg: int) -> bytes:
    flg = (flg & 0xE0) | (31 - ((cmf << 8) | (flg & 0xE0)) % 31) % 31
    return bytes((cmf, flg))


def _not_splicable() -> dict[str, tuple[bytes, NDArray[np.uint8], tuple[int, int]]]:
    h, w = 120, 160
    img = camera_like(h, w)
    src = encode(img, "cv2-1")
    bottom = (100, 120)

    def ihdr_byte(i: int, value: int) -> bytes:
        return with_chunk_data(src, b"IHDR", lambda d: d[:i] + bytes((value,)) + d[i + 1 :])

    def idat(edit: Callable[[bytes], bytes]) -> bytes:
        data = edit(zlib_stream(src))
        before = src[: src.index(b"IDAT") - 4]
        return (
            before
            + struct.pack(">I", len(data))
            + b"IDAT"
            + data
            + struct.pack(">I", zlib.crc32(b"IDAT" + data))
            + src[-12:]
        )

    rgba = np.dstack((img, np.full((h, w), 255, np.uint8)))
    return {
        "not a PNG": (b"GIF89a" + bytes(100), img, (10, 20)),
        "empty": (b"", img, (10, 20)),
        "truncated": (src[: len(src) // 2], img, (10, 20)),
        "RGBA": (cv2.imencode(".png", rgba)[1].tobytes(), img, (10, 20)),
        "16-bit": (cv2.imencode(".png", img.astype(np.uint16) * 257)[1].tobytes(), img, (10, 20)),
        "grey": (cv2.imencode(".png", img[..., 0])[1].tobytes(), img, (10, 20)),
        "interlaced": (ihdr_byte(12, 1), img, (10, 20)),
        "palette": (ihdr_byte(9, 3), img, (10, 20)),
        "wrong width": (src, np.zeros((h, w + 1, 3), np.uint8), (10, 20)),
        "wrong height": (src, np.zeros((h - 1, w, 3), np.uint8), (10, 20)),
        "FDICT": (idat(lambda s: zlib_header(s[0], s[1] | 0x20) + s[2:]), img, (10, 20)),
        "not deflate": (idat(lambda s: zlib_header(0x79, s[1]) + s[2:]), img, (10, 20)),
        "window 2^16": (idat(lambda s: zlib_header(0x88, s[1]) + s[2:]), img, (10, 20)),
        "bad header check": (idat(lambda s: s[:1] + bytes((s[1] ^ 1,)) + s[2:]), img, (10, 20)),
        "corrupt deflate": (idat(lambda s: s[:40] + bytes(8) + s[48:]), img, bottom),
        "short deflate": (idat(lambda s: s[:-30] + s[-4:]), img, bottom),
        "data after deflate": (idat(lambda s: s[:-4] + b"\0\0" + s[-4:]), img, bottom),
        "wrong Adler-32": (idat(lambda s: s[:-1] + bytes((s[-1] ^ 1,))), img, bottom),
        "no IDAT": (src[:33] + src[-12:], img, (10, 20)),
    }


NOT_SPLICABLE = _not_splicable()


@pytest.mark.parametrize("case", list(NOT_SPLICABLE))
def test_not_splicable_returns_none(case: str) -> None:
    src, img, rows = NOT_SPLICABLE[case]
    assert splice_png(src, img, rows, 1) is None


def test_caller_errors_raise() -> None:
    src = source_png(480, 640, "cv2-1")
    img = camera_like(480, 640)
    with pytest.raises(ValueError, match="rows"):
        splice_png(src, img, (10, 481), 1)
    with pytest.raises(ValueError, match="rows"):
        splice_png(src, img, (20, 10), 1)
    with pytest.raises(ValueError, match="level"):
        splice_png(src, img, (10, 20), 10)
    with pytest.raises(ValueError, match="uint8"):
        splice_png(src, img.astype(np.float32), (10, 20), 1)
    with pytest.raises(ValueError, match="uint8"):
        splice_png(src, img[..., 0], (10, 20), 1)


# --- decoding the rows a splice needs ----------------------------------------------------


@pytest.mark.parametrize("band", list(BANDS))
@pytest.mark.parametrize("source", SOURCES)
def test_decoded_rows_splice_to_the_new_image(source: str, band: str) -> None:
    """The rows down to the band's end (and the one below) decode to the source's, and
    their splice is the whole file's splice: the same PNG bytes."""
    h, w = 480, 640
    src = source_png(h, w, source)
    r0, r1 = band_rows(h, band)
    new = changed(camera_like(h, w), r0, r1)
    n = min(r1 + 1, h)
    decoded = decode_rows(src, n)
    assert decoded is not None and decoded.height == h
    np.testing.assert_array_equal(decoded.img_bgr, camera_like(h, w)[:n])
    res = splice_decoded(decoded, new[:n].copy(), (r0, r1), 1)
    assert res is not None
    assert_valid_png_of(res.png, new)
    assert res.png == splice_png(src, new, (r0, r1), 1)


def test_decoded_rows_of_more_than_the_image_are_all_of_it() -> None:
    src = source_png(120, 160, "pil-6")
    decoded = decode_rows(src, 10_000)
    assert decoded is not None
    np.testing.assert_array_equal(decoded.img_bgr, camera_like(120, 160))
    unchanged = splice_decoded(decoded, decoded.img_bgr.copy(), (50, 50), 1)
    assert unchanged is not None and unchanged.png == src


@pytest.mark.parametrize(
    "case", [c for c in NOT_SPLICABLE if not c.startswith("wrong ")] + ["wrong Adler-32"]
)
def test_unsplicable_sources_do_not_decode_rows(case: str) -> None:
    """What splice_png refuses, decode_rows refuses too (or, where the damage lies past the
    rows, splice_decoded): the caller then decodes and encodes the whole file."""
    src, _, (r0, r1) = NOT_SPLICABLE[case]
    decoded = decode_rows(src, r1 + 1)
    if decoded is not None:
        assert splice_decoded(decoded, decoded.img_bgr.copy(), (r0, r1), 1) is None


def test_decoded_rows_caller_errors_raise() -> None:
    src = source_png(480, 640, "cv2-1")
    decoded = decode_rows(src, 100)
    assert decoded is not None
    img = decoded.img_bgr.copy()
    with pytest.raises(ValueError, match="need more"):
        splice_decoded(decoded, img, (10, 100), 1)  # row 100 is filtered against row 99
    with pytest.raises(ValueError, match="level"):
        splice_decoded(decoded, img, (10, 20), 10)
    with pytest.raises(ValueError, match="uint8"):
        splice_decoded(decoded, img[:50], (10, 20), 1)
