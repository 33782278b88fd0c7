"""Preparation time against KISS-ICP alone on the same clouds (BENCHMARK.md).

Per run, in one process: (a) KISS-ICP alone (read every cloud, drop its ground, register
it: the preparation's odometry without its diagnostics), on a fresh input; (b) the whole
preparation (every stage, artifact written to a temporary folder). Prints per-run times and
the ratio (b)/(a), then medians and per-stage medians; also the CPU seconds of both sides
(threads and the KISS-ICP child process included), less disturbed by a loaded machine.
Target: ratio <= 1.5.

    .venv/bin/python scripts/bench_prepare.py /tmp/seqs/fire_site --runs 3 --strategy auto
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from kiss_icp.kiss_icp import KissICP

from worker.orchestration.malloc_tuning import tune_malloc
from worker.osdar.sequence import Sequence
from worker.preparation.artifact import write_artifact
from worker.preparation.config import PrepareConfig
from worker.preparation.localization.common import make_input
from worker.preparation.localization.odometry import (
    MIN_POINTS,
    _kiss_config,
    read_points,
    remove_ground,
)
from worker.preparation.prepare import run_preparation

TARGET_RATIO = 1.5


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its ended children (the KISS-ICP
    process): a figure that a loaded machine disturbs less than the wall time."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def kiss_alone(seq: Sequence, config: PrepareConfig) -> float:
    """Wall time of KISS-ICP alone over the sequence's clouds: read each cloud, drop its
    ground (KISS-ICP needs that on these clouds, see odometry.remove_ground), register it.
    None of the preparation's diagnostics (information, ground heights) is counted here."""

    inp = make_input(seq, options=dict(config.localization.options))
    t0 = time.perf_counter()
    kiss = KissICP(_kiss_config(inp))
    for frame in inp.frames:
        p = remove_ground(read_points(inp, frame))
        if len(p) >= MIN_POINTS:
            kiss.register_frame(p, np.zeros(len(p)))
    return time.perf_counter() - t0


def prepare_once(seq: Sequence, config: PrepareConfig) -> tuple[float, dict[str, float]]:
    t0 = time.perf_counter()
    prepared = run_preparation(seq, config)
    with tempfile.TemporaryDirectory() as tmp:
        t1 = time.perf_counter()
        write_artifact(prepared, Path(tmp) / "artifact")
        stages = dict(prepared.summary["timings"], artifact=time.perf_counter() - t1)
    return time.perf_counter() - t0, stages


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path, nargs="?", default=Path("/tmp/seqs/fire_site"))
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--strategy", default="auto")
    ap.add_argument("--voxel-size", type=float, default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument(
        "--option", action="append", default=[], metavar="KEY=JSON",
        help="a localization option, e.g. fused_scan_pairs=false (repeatable)",
    )  # fmt: skip
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    tune_malloc()  # as run_preparation does: both sides measured with the same allocator
    reg = {} if args.voxel_size is None else {"voxel_size": args.voxel_size}
    options = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.option)}
    config = PrepareConfig(strategy=args.strategy).with_overrides(
        registration=reg, localization={"options": options}
    )
    seq = Sequence.open(args.sequence)
    rows = []
    for k in range(args.runs):
        c0 = cpu_seconds()
        t_kiss = kiss_alone(seq, config)
        c1 = cpu_seconds()
        t_prep, stages = prepare_once(seq, config)
        c2 = cpu_seconds()
        rows.append(
            {"kiss": t_kiss, "prepare": t_prep, "ratio": t_prep / t_kiss,
             "kiss_cpu": c1 - c0, "prepare_cpu": c2 - c1, "cpu_ratio": (c2 - c1) / (c1 - c0),
             **stages}
        )  # fmt: skip
        print(  # noqa: T201 - script output
            f"run {k + 1}: KISS-ICP alone {t_kiss:.1f} s, preparation {t_prep:.1f} s, "
            f"ratio {t_prep / t_kiss:.2f} (CPU {c1 - c0:.1f} s and {c2 - c1:.1f} s)"
        )
    med = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
    print(  # noqa: T201 - script output
        f"\n{seq.name}: {len(seq.frame_indices)} frames, strategy {args.strategy}, voxel "
        f"{config.registration.voxel_size} m, median of {args.runs} run(s)\n"
        f"  KISS-ICP alone {med['kiss']:.1f} s, preparation {med['prepare']:.1f} s, "
        f"ratio {med['ratio']:.2f} (target <= {TARGET_RATIO})\n"
        f"  CPU (all threads and processes): KISS-ICP alone {med['kiss_cpu']:.1f} s, "
        f"preparation {med['prepare_cpu']:.1f} s, ratio {med['cpu_ratio']:.2f}\n"
        f"  stages (wall):"
    )
    for key, v in med.items():
        if key not in ("kiss", "prepare", "ratio", "kiss_cpu", "prepare_cpu", "cpu_ratio"):
            print(f"    {key:<18} {v:7.2f} s")  # noqa: T201 - script output
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, "median": med}, indent=1))
    return 0 if med["ratio"] <= TARGET_RATIO else 1


if __name__ == "__main__":
    sys.exit(main())
