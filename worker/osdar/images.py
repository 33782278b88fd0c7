"""PNG images of an OSDaR23 sequence: guarded reading, atomic writing.

Colour images are RGB uint8 (H, W, 3) in memory (OpenCV's BGR order stays inside this
module); grey images (IR) are (H, W).
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.osdar.errors import SequenceError, atomic_write_bytes

logger = logging.getLogger(__name__)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
DEFAULT_MAX_PIXELS = 40_000_000


def png_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR, without decoding.

    Raises
    ------
    SequenceError
        Missing file, not a PNG, or a malformed IHDR.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(24)
    except OSError as e:
        raise SequenceError(path, f"cannot read image: {e.strerror or e}") from e
    if head[:8] != PNG_SIGNATURE:
        raise SequenceError(path, "not a PNG file (bad signature)")
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise SequenceError(path, "PNG truncated or without IHDR chunk")
    width, height = struct.unpack(">II", head[16:24])
    if width == 0 or height == 0:
        raise SequenceError(path, f"PNG has an empty size {width} x {height}")
    return width, height


def read_png(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> NDArray[np.uint8]:
    """Read a PNG as RGB uint8 (H, W, 3) or grey (H, W).

    Parameters
    ----------
    path : str or Path
        The .png file.
    max_pixels : int
        Refuse images larger than this (checked on the header, before decoding).

    Returns
    -------
    ndarray
        (H, W, 3) RGB uint8 for colour images (alpha dropped), (H, W) uint8 for grey.

    Raises
    ------
    SequenceError
        Not a PNG, too large, undecodable, or not 8 bit.
    """
    path = Path(path)
    width, height = png_size(path)
    if width * height > max_pixels:
        raise SequenceError(
            path, f"PNG of {width} x {height} px exceeds the limit of {max_pixels} px"
        )
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SequenceError(path, "PNG could not be decoded (corrupt or truncated)")
    if img.dtype != np.uint8:
        raise SequenceError(path, f"PNG is {img.dtype}, 8 bit expected")
    if img.ndim == 2:
        return img
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def encode_png(img: NDArray[np.uint8], compression: int = 1) -> bytes:
    """PNG bytes of an RGB (H, W, 3) or grey (H, W) uint8 image.

    Parameters
    ----------
    img : ndarray
        (H, W, 3) RGB or (H, W) grey, uint8.
    compression : int
        zlib level 0 (none) to 9 (smallest, slowest); 1 is fast.
    """
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {img.dtype}")
    if not 0 <= compression <= 9:
        raise ValueError(f"PNG compression level must be 0..9, got {compression}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim != 2:
        raise ValueError(f"expected (H, W, 3) RGB or (H, W) grey, got shape {img.shape}")
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise ValueError("OpenCV failed to encode the PNG")
    return buf.tobytes()


def write_png(path: str | Path, img_rgb: NDArray[np.uint8], compression: int = 1) -> Path:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG, atomically.

    Parameters
    ----------
    path : str or Path
        Destination .png file.
    img_rgb : ndarray
        (H, W, 3) RGB or (H, W) grey, uint8.
    compression : int
        zlib level 0..9, default 1 (fast).

    Returns
    -------
    Path
        ``path``.
    """
    return atomic_write_bytes(path, encode_png(img_rgb, compression))
