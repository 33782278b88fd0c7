"""``osdar-ar augment``: a virtual obstacle added to a sequence (cameras, lidar,
annotations), the result written in the OSDaR23 layout."""

from __future__ import annotations

import argparse

from pydantic import ValidationError

from osdar_platform.catalog import STRATEGY_NAMES
from osdar_platform.settings import get_settings
from worker.augmentation.augment import augment
from worker.augmentation.placement import PlacementError
from worker.augmentation.plan import AugmentError
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
from worker.cli.errors import CliError
from worker.cli.progress import progress_bar
from worker.preparation.calibration_point import Clicks, ClicksError
from worker.preparation.prepare import PreparationError


def _augment_spec(args: argparse.Namespace) -> AugmentSpec:
    try:
        placement = PlacementModel.parse(args.place)
    except PlacementError as exc:
        raise CliError(str(exc)) from exc
    frame_range = None
    if args.frames:
        try:
            a, b = (int(x) for x in args.frames.split(":"))
        except ValueError as exc:
            raise CliError(f"--frames {args.frames!r}: expected FIRST:LAST") from exc
        frame_range = (a, b)
    clicks = None
    if args.clicks is not None:
        try:
            clicks = Clicks.load(args.clicks).to_json()
        except (ClicksError, OSError) as exc:
            raise CliError(f"--clicks {args.clicks}: {exc}") from exc
    try:
        return AugmentSpec(
            object=ObjectSource.from_cli(
                args.object, scale=args.object_scale, seed=args.seed, mesh_scale=args.mesh_units
            ),
            placement=placement,
            cameras=None
            if args.cameras is None
            else tuple(c.strip() for c in args.cameras.split(",") if c.strip()),
            lidar=not args.no_lidar,
            frame_range=frame_range,
            strategy=args.strategy,
            lidar_origins=args.lidar_origins,
            clicks=clicks,
            render=RenderSpec(
                png_compression=args.png_compression,
                blur=not args.no_blur,
                lab_match=not args.no_lab_match,
                shadow_strength=args.shadow,
                pixel_offset=args.pixel_offset,
                **{
                    k: getattr(args, k)
                    for k in ("exposure_ms", "aperture_mm")
                    if getattr(args, k) is not None
                },
            ),
        )
    except ValidationError as exc:
        msgs = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'spec'}: {e['msg']}" for e in exc.errors()
        )
        raise CliError(msgs) from exc


def run(args: argparse.Namespace) -> int:
    spec = _augment_spec(args)
    if args.strategy not in STRATEGY_NAMES:
        raise CliError(f"--strategy {args.strategy!r}: known {', '.join(STRATEGY_NAMES)}")
    if args.out.exists() and not args.force:
        raise CliError(f"{args.out} exists: choose another folder or pass --force")
    if args.out.resolve() == args.sequence.resolve():
        raise CliError("--out must not be the input sequence")
    cache_dir = args.cache_dir or get_settings().prepared_cache_dir
    bar = progress_bar(0, f"augment {args.sequence.name}")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        metrics = augment(
            args.sequence,
            spec,
            args.out,
            cache_dir=cache_dir,
            workers=max(1, args.workers),
            progress=progress,
            overwrite=args.force,
            evaluate=not args.no_evaluate,
        )
    except PlacementError as exc:
        raise CliError(f"--place {args.place!r}: {exc}") from exc
    except (AugmentError, PreparationError, ClicksError) as exc:
        raise CliError(str(exc)) from exc
    finally:
        bar.close()
    t = metrics["timings_s"]
    cams = ", ".join(
        f"{c} visible in {v['visible_frames']} frames" for c, v in metrics["cameras"].items()
    )
    print(  # noqa: T201 - CLI output
        f"wrote {args.out}: {metrics['object']['class']} annotated in "
        f"{metrics['frames']['annotated']}/{metrics['frames']['total']} frames ({cams}) "
        f"in {t['total']:.1f} s"
    )
    stages = {k: v for k, v in t.items() if isinstance(v, float) and k != "total"}
    print("  stages: " + ", ".join(f"{k} {v:.2f} s" for k, v in stages.items()))  # noqa: T201
    if metrics.get("lidar"):
        li = metrics["lidar"]
        print(  # noqa: T201 - CLI output
            f"  lidar ({li['origins']} origin): {li['object_points_total']} object points "
            f"in {li['frames_with_points']} frames"
        )
    for name, e in (metrics.get("object_errors") or {}).get("cameras", {}).items():
        if e.get("anchor_px_mean") is None:
            continue
        print(  # noqa: T201 - CLI output
            f"  {name}: anchor error {e['anchor_px_mean']:.2f} px mean, "
            f"{e['anchor_px_max']:.2f} max; mask IoU {e['mask_iou_mean'] or 0:.3f} mean "
            f"({e['frames']} frames, vs the true poses)"
        )
    for w in metrics.get("warnings", []):
        print(f"  warning: {w}")  # noqa: T201 - CLI output
    return 0
