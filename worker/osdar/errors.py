"""Errors and warnings of the OSDaR23 sequence I/O.

Every hard failure is a :class:`SequenceError` that names the file or folder at fault and
says what is wrong with it; survivable gaps (a dropped frame, a missing INS row) are
:class:`SequenceWarning` s, both warned and logged. :func:`atomic_write_bytes` is the one
way the package writes a file: a temporary file beside it, then ``os.replace``.
"""

from __future__ import annotations

import logging
import os
import tempfile
import warnings
from pathlib import Path

logger = logging.getLogger(__name__)


class SequenceError(ValueError):
    """A sequence file or folder is missing or malformed.

    Parameters
    ----------
    path : str or Path
        The file or folder at fault.
    reason : str
        What is wrong with it.
    """

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"

    def __reduce__(self) -> tuple:
        return (type(self), (self.path, self.reason))


class SequenceWarning(UserWarning):
    """A survivable gap in a sequence (dropped frame, missing INS row, dropped points)."""


def warn_sequence(path: str | Path, reason: str, stacklevel: int = 3) -> None:
    """Emit a :class:`SequenceWarning` ``"<path>: <reason>"`` and log it.

    Parameters
    ----------
    path : str or Path
        The file or folder concerned.
    reason : str
        What is missing or was dropped.
    stacklevel : int
        Passed to :func:`warnings.warn`.
    """
    message = f"{path}: {reason}"
    logger.warning(message)
    warnings.warn(message, SequenceWarning, stacklevel=stacklevel)


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once: os.umask is process-global


def atomic_write_bytes(path: str | Path, data: bytes | bytearray | memoryview) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file beside it + ``os.replace``).

    Parameters
    ----------
    path : str or Path
        Destination; its parent folders are created.
    data : bytes-like
        The whole file content.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
