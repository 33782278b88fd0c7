"""``osdar-ar synth``: a synthetic OSDaR23-layout sequence with ground truth."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Any

from worker.cli.errors import CliError
from worker.cli.progress import progress_bar
from worker.synth.generator import SynthConfig, generate
from worker.synth.scenes import SCENE_NAMES


def _parse_overrides(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise CliError(f"--ins {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return out


def run(args: argparse.Namespace) -> int:
    if args.list_scenes:
        for name in SCENE_NAMES:
            print(name)  # noqa: T201 - CLI output
        return 0
    out: Path = args.out
    if out.exists():
        if not args.force:
            raise CliError(f"{out} exists: choose another folder or pass --force")
        shutil.rmtree(out)
    drops = tuple(int(x) for x in args.drop_frames.split(",") if x.strip())
    try:
        cfg = SynthConfig(
            scene=args.scene,
            frames=args.frames,
            scale=args.scale,
            seed=args.seed,
            cameras=tuple(c.strip() for c in args.cameras.split(",") if c.strip()),
            lidar_density=args.lidar_density,
            ins_profile=args.ins_profile,
            ins_overrides=_parse_overrides(args.ins),
            speed_mps=args.speed,
            stationary=args.stationary,
            far_origin=args.far_origin,
            first_counter=args.first_counter,
            dropped_frames=drops,
            pcd_data=args.pcd_data,
            calibration=args.calibration,
            bogies=_pair(args.bogies, "--bogies"),
            lidar_blind_ahead_m=args.lidar_blind_ahead,
            lidar_merge_error=_pair(args.merge_error, "--merge-error"),
        )
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    bar = progress_bar(args.frames - len(drops), f"synth {args.scene}")

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    try:
        res = generate(out, cfg, progress=progress)
    finally:
        bar.close()
    print(  # noqa: T201 - CLI output
        f"wrote {res.folder} ({res.frames} frames) in {res.seconds:.1f} s: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in res.stage_seconds.items())
    )
    return 0


def _pair(text: str | None, flag: str) -> tuple[float, float] | None:
    """ "A,B" -> (A, B); None stays None."""
    if text is None:
        return None
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise CliError(f"{flag} wants two numbers separated by a comma, got {text!r}") from None
    return a, b
