"""The augmentation job against its I/O floor (BENCHMARK.md), in one run.

The floor is ``scripts/bench_augment.py``'s :func:`measure_floor` (decode + re-encode the
same PNGs at the same compression, read + write the same PCDs, same worker count); the
job is :func:`worker.augmentation.augment.augment` with the preparation given. Returns
job seconds / floor seconds (median over ``runs``, floor and job alternating).
"""

from __future__ import annotations

import importlib.util
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_augment.py"


def _measure_floor() -> Any:
    """``measure_floor`` of scripts/bench_augment.py (one implementation of the floor)."""
    spec = importlib.util.spec_from_file_location("_osdar_bench_augment", SCRIPT)
    if spec is None or spec.loader is None:
        raise RuntimeError(f"{SCRIPT}: cannot load the floor measurement")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.measure_floor


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
    from worker.augmentation.augment import augment
    from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
    from worker.osdar.sequence import Sequence

    measure_floor = _measure_floor()
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
