"""tune_malloc: a frame's big arrays reuse freed pages instead of fresh ones."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from worker.orchestration.malloc_tuning import tune_malloc

_PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "1":
    from worker.orchestration.malloc_tuning import tune_malloc
    assert tune_malloc()
def frame():  # arrays of a few MB made and freed, as a frame's planes are
    a = [np.ones((770, 1600), np.float32) for _ in range(6)]
    return sum(float(x[0, 0]) for x in a)
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""

glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


@pytest.mark.skipif(not glibc, reason="glibc's mallopt")
def test_freed_arrays_are_reused_not_faulted_in_again() -> None:
    """20 frames of six 4.9 MB arrays (1200 pages each): by default glibc maps and
    unmaps or trims them, and a frame faults thousands of pages in again; with the
    thresholds kept, the pages of the first frame serve the rest."""

    def faults(tuned: bool) -> int:
        out = subprocess.run(
            [sys.executable, "-c", _PROBE, "1" if tuned else "0"],
            check=True, capture_output=True, text=True,
        )  # fmt: skip
        return int(out.stdout.split()[-1])

    default, kept = faults(False), faults(True)
    assert default > 20 * 1000, default
    assert kept < 0.02 * default, (kept, default)


@pytest.mark.skipif(not glibc, reason="glibc's mallopt")
def test_tune_malloc_is_taken_and_idempotent() -> None:
    assert tune_malloc() and tune_malloc()
