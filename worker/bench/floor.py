"""The augmentation job against its I/O floor (BENCHMARK.md), in one run.

The floor is :func:`measure_floor` (decode + re-encode the same PNGs at the same
compression, read + write the same PCDs, same worker count; ``scripts/bench_augment.py``
uses it too); the job is :func:`worker.augmentation.augment.augment` with the preparation
given. Returns job seconds / floor seconds (median over ``runs``, floor and job
alternating). The floor's pool runs functions of this module: an importable module, which
the pool's processes can unpickle them from.
"""

from __future__ import annotations

import shutil
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import cv2

from worker.augmentation.augment import augment
from worker.augmentation.pool import pool_context
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
from worker.orchestration.malloc_tuning import tune_malloc
from worker.osdar.errors import atomic_write_bytes
from worker.osdar.pcd import read_pcd, write_pcd
from worker.osdar.sequence import Sequence


def _io_frame(jobs: list[tuple[str, str, str]], compression: int) -> float:
    """Decode + encode PNGs (OpenCV, BGR as decoded: no colour conversion), read + write
    PCDs, of one frame; returns seconds. The strictest floor of the job's own I/O."""
    tic = time.perf_counter()
    for kind, src, dst in jobs:
        if kind == "png":
            img = cv2.imread(src, cv2.IMREAD_UNCHANGED)
            _, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, compression])
            atomic_write_bytes(dst, buf.tobytes())
        else:
            write_pcd(dst, read_pcd(src))
    return time.perf_counter() - tic


def _noop(_: int = 0) -> int:
    return 0


def measure_floor(
    seq: Sequence, frames: list[int], streams: list[str], workers: int, compression: int, out: Path
) -> float:
    """Wall seconds of the I/O floor (module docstring)."""
    shutil.rmtree(out, ignore_errors=True)
    tasks = []
    for f in frames:
        jobs = []
        for s in streams:
            src = seq.path(f, s)
            rel = src.relative_to(seq.folder)
            jobs.append(("png" if src.suffix == ".png" else "pcd", str(src), str(out / rel)))
        tasks.append(jobs)
    if workers <= 1:
        tic = time.perf_counter()
        for jobs in tasks:
            _io_frame(jobs, compression)
        wall = time.perf_counter() - tic
    else:
        # the augmentation pool's processes, malloc settings included (malloc_tuning.py)
        with ProcessPoolExecutor(
            workers, mp_context=pool_context(), initializer=tune_malloc
        ) as pool:
            list(pool.map(_noop, range(workers * 2)))  # workers up before the clock
            tic = time.perf_counter()
            list(pool.map(_io_frame, tasks, [compression] * len(tasks)))
            wall = time.perf_counter() - tic
    shutil.rmtree(out, ignore_errors=True)
    return wall


def floor_ratio(
    seq_folder: Path,
    prepared: Any,
    scratch: Path,
    *,
    workers: int = 1,
    runs: int = 1,
    obj: str = "person",
    place: str = "s=40,offset=0,yaw=90",
    png_compression: int = 1,
) -> dict[str, Any]:
    """{"floor_ratio", "floor_s", "job_s", "workers", "frames"}."""

    seq = Sequence.open(seq_folder)
    spec = AugmentSpec(
        object=ObjectSource.from_cli(obj),
        placement=PlacementModel.parse(place),
        strategy=prepared.strategy or "auto",
        render=RenderSpec(png_compression=png_compression),
    )
    cams = spec.camera_names(seq.cameras)
    streams = cams + ([seq.lidar_stream] if seq.lidar_stream else [])
    frames = seq.frame_indices
    floors, jobs = [], []
    for k in range(runs):
        for what in ("floor", "job") if k % 2 == 0 else ("job", "floor"):
            if what == "floor":
                floors.append(
                    measure_floor(seq, frames, streams, workers, png_compression, scratch / "floor")
                )
            else:
                t0 = time.perf_counter()
                augment(
                    seq_folder, spec, scratch / "out" / seq.name, prepared=prepared,
                    workers=workers, overwrite=True, evaluate=False,
                )  # fmt: skip
                jobs.append(time.perf_counter() - t0)
    shutil.rmtree(scratch, ignore_errors=True)
    ratios = [j / f for j, f in zip(jobs, floors, strict=True)]
    return {
        "floor_ratio": statistics.median(ratios),
        "floor_s": statistics.median(floors),
        "job_s": statistics.median(jobs),
        "workers": workers,
        "frames": len(frames),
        "streams": streams,
    }
