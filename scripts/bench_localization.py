# ruff: noqa: T201 (a script: prints its table)
"""Benchmark the localization strategies on synthetic sequences (true pose errors, time).

Usage::

    .venv/bin/python scripts/bench_localization.py SEQ_FOLDER [SEQ_FOLDER ...]
    .venv/bin/python scripts/bench_localization.py --generate fire_site straight_sparse \
        --frames 100 --out /tmp/bench_loc

For each sequence: KISS-ICP alone (read the PCDs + KissICP with its default voxel size,
deskew off, raw clouds), then every strategy on a fresh input (``auto`` last, on its own
fresh input, which is the whole localization of a preparation), with the TRUE ego
centreline as the rails (the benchmark may read ground truth; the pipeline never does).
Prints translation (m) and rotation (deg) errors, mean / max, frame-to-frame errors
(mm, mdeg) and seconds.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP
from scipy.spatial.transform import Rotation

from geometry.poses import PoseTrack
from worker.osdar.sequence import Sequence
from worker.preparation.centreline import Centreline
from worker.preparation.localization import STRATEGIES, make_input, run_strategy
from worker.preparation.localization.common import relative_motions
from worker.synth.generator import SynthConfig, generate


def kiss_alone(folder: Path) -> float:
    """Seconds for reading the clouds and running KISS-ICP (default voxel, deskew off)."""

    seq = Sequence.open(folder)
    started = time.perf_counter()
    cfg = KISSConfig()
    cfg.data.deskew = False
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0
    kiss = KissICP(cfg)
    for f in seq.frame_indices:
        p = np.asarray(seq.pcd(f, allow_nonfinite=True).xyz, dtype=np.float64)
        p = p[np.all(np.isfinite(p), axis=1)]
        kiss.register_frame(p, np.zeros(len(p)))
    return time.perf_counter() - started


def errors(track: PoseTrack, gt: PoseTrack) -> list[float]:
    et, er = track.relative_errors(gt)
    a, b = relative_motions(track.T), relative_motions(gt.T)
    rel_t = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    rel_r = np.degrees(
        Rotation.from_matrix(np.swapaxes(b[:, :3, :3], 1, 2) @ a[:, :3, :3]).magnitude()
    )
    return [et.mean(), et.max(), er.mean(), er.max(), rel_t.mean() * 1e3, rel_r.mean() * 1e3]


def bench(folder: Path) -> None:
    entries = json.loads((folder / "ground_truth/centrelines.json").read_text())
    ego = next(Centreline.from_json(e) for e in entries if e.get("ego"))
    gt = PoseTrack.from_csv(folder / "ground_truth/poses.csv")
    t_kiss = kiss_alone(folder)
    seq = Sequence.open(folder)
    print(f"\n{folder.name}: {len(seq.frame_indices)} frames; KISS-ICP alone {t_kiss:.2f} s")
    header = "strategy    t_mean  t_max   r_mean  r_max   rel_t_mm rel_r_mdeg  seconds"
    print(header)
    print("-" * len(header))
    inp = make_input(seq, ego=ego)
    seconds: dict[str, float] = {}
    for name in STRATEGIES:
        if name == "auto":
            inp = make_input(seq, ego=ego)  # fresh: auto pays for everything it needs
        tic = time.perf_counter()
        res = run_strategy(name, inp)
        sec = time.perf_counter() - tic
        seconds[name] = sec
        e = errors(res.track, gt)
        extra = f"  -> {res.extras.get('chosen')}" if name == "auto" else ""
        print(
            f"{name:10s} {e[0]:6.3f} {e[1]:6.3f}  {e[2]:6.4f} {e[3]:6.4f}  {e[4]:8.1f} "
            f"{e[5]:9.1f}  {sec:7.2f}{extra}"
        )
        if name == "auto":
            print(f"whole localization (auto) / KISS-ICP alone: {sec / t_kiss:.2f}")
            print(
                "whole localization (auto) / our KISS-ICP run (reading, ground removal, "
                f"ICP, diagnostics): {sec / seconds['odometry']:.2f}"
            )
            print(f"auto: {res.extras.get('reason')}")
        for w in res.health.warnings:
            print(f"    warning: {w}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="*", type=Path)
    ap.add_argument("--generate", nargs="*", default=[], help="scenes to generate")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--scale", type=float, default=0.05)
    ap.add_argument("--lidar-density", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_localization"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    folders = list(args.folders)
    if args.generate:
        for scene in args.generate:
            out = args.out / scene
            if not out.exists():
                cfg = SynthConfig(
                    scene=scene,
                    frames=args.frames,
                    scale=args.scale,
                    lidar_density=args.lidar_density,
                    seed=args.seed,
                )
                generate(out, cfg)
            folders.append(out)
    for folder in folders:
        bench(folder)


if __name__ == "__main__":
    main()
