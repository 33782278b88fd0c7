"""The progress bar of the ``osdar-ar`` commands (on stderr)."""

from __future__ import annotations

import sys
from typing import Any

from tqdm import tqdm  # type: ignore[import-untyped]


def progress_bar(total: int, desc: str) -> Any:
    """A bar over ``total`` frames on stderr (a command sets ``unit`` for other things)."""
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True)
