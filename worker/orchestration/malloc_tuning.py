"""glibc malloc settings for processes that churn through big numpy arrays.

Preparation allocates and frees arrays of 1-25 MB by the hundred (a frame's points, a
projection of the registered cloud). glibc serves every allocation above its mmap threshold
(128 kB by default, adapting up to 32 MB) with a fresh ``mmap`` and returns it with
``munmap`` on free, so each new array pays its page faults again. Raising the threshold to
its maximum and keeping freed memory at the top of the heap lets later arrays reuse those
pages: the non-odometry stages of a 100-frame preparation took 2.2-2.5 s instead of
2.4-3.7 s on the 2-core machine (``scripts/bench_prepare.py``). The augmentation's frames
likewise (the render's planes, the composite's layers, decoded PNG bands): on the fallen
tree's rgb_highres_center render the resolve's ``cv2.split`` took 15 ms a call on fresh
pages against 3.5 ms on reused ones, the resolve 80-110 ms against 40-45 ms. Applied by
the preparation, the augmentation pool's initializer and every Celery worker (prefork
children and a solo worker: ``lifecycle.py``). The cost is that the process keeps up to
``TRIM_THRESHOLD`` bytes of freed memory instead of handing it back at once.

:func:`tune_malloc` is idempotent and does nothing off glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

# mallopt parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 1024 * 1024  # bytes: where glibc's own adaptive threshold tops out (64-bit)
TRIM_THRESHOLD = 512 * 1024 * 1024  # bytes of free heap kept before trimming
TOP_PAD = 64 * 1024 * 1024  # bytes added whenever the heap grows

_done: bool | None = None


def tune_malloc() -> bool:
    """Apply the settings above to this process (once); True when glibc accepted them."""
    global _done
    if _done is not None:
        return _done
    _done = False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        log.debug("mallopt unavailable: malloc left as it is")
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    ok = all(
        mallopt(param, value) == 1
        for param, value in (
            (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
            (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (_M_TOP_PAD, TOP_PAD),
        )
    )
    _done = ok
    log.debug("malloc tuned: %s", ok)
    return ok
