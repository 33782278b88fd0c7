"""A gzip file whose deflate stream keeps some parts stored: PNGs are not compressed again.

zlib deflates every byte it is given at one level. A PNG is deflated already: deflating
it again costs the CPU and gains nothing (measured on a 40-frame variant archive: the
camera PNGs 23.46 MB stored, 23.34 MB at level 1, 0.51 s of CPU). :class:`GzipStoredWriter`
deflates what it is written while :attr:`~GzipStoredWriter.stored` is False and emits it
as stored deflate blocks (RFC 1951, 3.2.4: ``BTYPE=00``) while it is True, all in ONE
deflate stream of ONE gzip member, so every reader of ``.tar.gz`` reads it: ``gzip -d``,
``tar xz``, ``tarfile`` both ``r:gz`` and streaming ``r|gz``. (Several gzip members, one
per level, would be simpler, but ``tarfile``'s ``r|gz`` stops at the end of the first
member, without an error.)

Before the first stored block the deflater is flushed with ``Z_FULL_FLUSH``: its output
ends on a byte boundary and nothing it writes later refers back to bytes before it.

The deflater and the CRC-32 are ISA-L's (the ``isal`` package), not zlib's: on a lidar
PCD (float fields, 18.6 MB) ISA-L's level 1 deflates 343 MB/s to 0.574 of the size
against zlib's level 1 at 53 MB/s to 0.588, and its CRC-32 takes 5 ms per 100 MB against
40. Packaging deflates every PCD of a variant, gigabytes at full resolution.
"""

from __future__ import annotations

import struct
import zlib
from types import TracebackType
from typing import BinaryIO

from isal import isal_zlib

#: The longest stored block (its LEN field has 16 bits).
STORED_BLOCK_MAX = 0xFFFF
#: ISA-L's deflate levels (0 fastest, 3 smallest).
LEVELS = range(0, 4)
#: gzip header XFL: the deflater's fastest / best level (the rest: 0).
_XFL_FASTEST, _XFL_BEST = 4, 2


class GzipStoredWriter:
    """Write-only binary file (``write``, ``tell``, ``close``) of gzip to ``out``.

    ``level``: ISA-L's deflate level (0-3) of the parts not stored. Set :attr:`stored` before
    writing a part that does not compress. ``tell()`` is the uncompressed offset (what
    ``tarfile`` asks of its file). ``close()`` ends the stream; ``out`` stays open.
    """

    def __init__(self, out: BinaryIO, level: int = 1) -> None:
        if level not in LEVELS:
            raise ValueError(f"deflate level must be 0..3 (ISA-L's), got {level}")
        self._out = out
        self._deflate = isal_zlib.compressobj(level, isal_zlib.DEFLATED, -zlib.MAX_WBITS)
        self._crc = 0
        self._size = 0
        self._stored = False
        self.closed = False
        xfl = _XFL_FASTEST if level <= 1 else _XFL_BEST if level == LEVELS[-1] else 0
        # magic, CM=deflate, no flags, MTIME 0 (reproducible bytes), XFL, OS unknown
        out.write(b"\x1f\x8b\x08\x00" + struct.pack("<I", 0) + bytes([xfl, 255]))

    @property
    def stored(self) -> bool:
        """True: what is written next goes into stored blocks, uncompressed."""
        return self._stored

    @stored.setter
    def stored(self, value: bool) -> None:
        if value and not self._stored:
            self._out.write(self._deflate.flush(isal_zlib.Z_FULL_FLUSH))
        self._stored = value

    def write(self, data: bytes | bytearray | memoryview) -> int:
        if self.closed:
            raise ValueError("write to a closed GzipStoredWriter")
        view = memoryview(data).cast("B")
        n = len(view)
        self._crc = isal_zlib.crc32(view, self._crc)
        self._size += n
        if not self._stored:
            self._out.write(self._deflate.compress(view))
            return n
        for i in range(0, n, STORED_BLOCK_MAX):
            block = view[i : i + STORED_BLOCK_MAX]
            # BFINAL=0, BTYPE=00 and the padding to the byte boundary: one zero byte.
            self._out.write(b"\x00" + struct.pack("<HH", len(block), len(block) ^ 0xFFFF))
            self._out.write(block)
        return n

    def tell(self) -> int:
        return self._size

    def flush(self) -> None:
        self._out.flush()

    def close(self) -> None:
        """The final deflate block and the gzip trailer (CRC-32, size mod 2**32)."""
        if self.closed:
            return
        self._out.write(self._deflate.flush(isal_zlib.Z_FINISH))
        self._out.write(struct.pack("<II", self._crc, self._size & 0xFFFFFFFF))
        self._out.flush()
        self.closed = True

    def __enter__(self) -> GzipStoredWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
