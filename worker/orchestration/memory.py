"""glibc's malloc told to keep freed memory, in the processes that augment frames.

A frame's work allocates and frees arrays of megabytes: the render's planes, the
composite's layers, decoded PNG bands. glibc serves blocks above its mmap threshold with
fresh ``mmap`` pages and trims its heap's free top back to the kernel, so the next frame's
arrays are new pages again, each zeroed by the kernel on its first touch. On the fallen
tree's rgb_highres_center render (a 1600 x 770 window, 5 MB a plane) the resolve's
``cv2.split`` took 15 ms a call on fresh pages against 3.5 ms on reused ones, the whole
resolve 80-110 ms against 40-45 ms (``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
set for a test process: the same figures as :func:`keep_freed_memory`).

:func:`keep_freed_memory` fixes the mmap threshold at glibc's 64-bit maximum (blocks up to
32 MiB come from the heap; larger ones, a whole point cloud, stay mapped and go back when
freed) and keeps up to ``TRIM_THRESHOLD_BYTES`` free at the heap's top: a worker process
holds at most that much more than it uses. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's largest mmap threshold on 64-bit (HEAP_MAX_SIZE / 2).
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024

_DONE_PID: int | None = None


def keep_freed_memory() -> bool:
    """Set the process's malloc thresholds (module docstring) once per process; True where
    glibc took them."""
    global _DONE_PID
    if _DONE_PID == os.getpid():
        return True
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    if ok:
        _DONE_PID = os.getpid()
    else:
        log.warning("glibc refused the malloc thresholds: frames run on fresh pages")
    return ok
