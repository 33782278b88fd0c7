"""``osdar-ar campaign run``: a campaign embedded (worker/campaign/run.py does the work);
``campaign submit`` and ``campaign download``: on a running service (campaign_client.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from osdar_platform.settings import get_settings
from worker.campaign.run import CampaignRunError, VariantRecord, load_campaign, run_campaign
from worker.campaign.variant import Variant
from worker.cli import campaign_client
from worker.cli.errors import CliError
from worker.cli.progress import progress_bar


def _position(v: Variant) -> str:
    parts = []
    for o in v.objects:
        r = o.resolved
        where = (
            f"s={r.s_job_m:.1f} m offset={r.offset_m:+.2f} m"
            if r.s_job_m is not None and r.offset_m is not None
            else f"xyz=({r.xyz_world[0]:.1f}, {r.xyz_world[1]:.1f}, {r.xyz_world[2]:.1f})"
        )
        seen = (
            ""
            if r.distance_first_view_m is None
            else f", in view at {r.distance_first_view_m:.1f} m (frame {r.first_view_frame})"
        )
        moves = "" if o.motion is None else f", moving at {o.motion['speed_mps']:g} m/s"
        parts.append(
            f"{o.class_name} #{o.variation_seed} {r.zone or 'explicit'} {where} "
            f"yaw={r.yaw_deg:.1f} deg{seen}{moves}"
        )
    return "; ".join(parts)


def run(args: argparse.Namespace) -> int:
    if args.campaign_command in ("submit", "download"):
        return campaign_client.run(args)
    if args.campaign_command != "run":  # pragma: no cover - argparse allows no other
        raise CliError(f"unknown campaign command {args.campaign_command!r}")
    if args.workers < 1:
        raise CliError("--workers must be at least 1")
    try:
        spec = load_campaign(args.spec)
    except CampaignRunError as exc:
        raise CliError(str(exc)) from exc
    out: Path = args.out or Path("campaigns") / spec.name
    cache_dir = args.cache_dir or get_settings().prepared_cache_dir
    bar = None

    def on_prepared(label: str, seconds: float, reused: bool) -> None:
        how = "reused from the cache" if reused else "prepared"
        print(f"{label}: {how} in {seconds:.1f} s")  # noqa: T201 - CLI output

    def on_variants(variants: list[Variant], warnings: list[str]) -> None:
        nonlocal bar  # the warnings are logged by the expansion already
        if args.dry_run:
            for v in variants:
                print(f"{v.id} {v.key} {v.sequence_label}: {_position(v)}")  # noqa: T201
            return
        bar = progress_bar(len(variants), f"campaign {spec.name}")
        bar.unit = "variant"

    def on_variant(v: Variant, rec: VariantRecord, skipped: bool) -> None:
        if bar is not None:
            state = "skipped (complete)" if skipped else rec.state
            bar.set_postfix_str(f"{v.id} {state}")
            bar.update(1)

    try:
        result = run_campaign(
            spec,
            args.spec,
            out,
            cache_dir=cache_dir,
            workers=args.workers,
            dry_run=args.dry_run,
            on_variants=on_variants,
            on_variant=on_variant,
            on_prepared=on_prepared,
        )
    except CampaignRunError as exc:
        raise CliError(str(exc)) from exc
    finally:
        if bar is not None:
            bar.close()
    n = len(result.variants)
    if args.dry_run:
        print(f"{n} variants (dry run, nothing made): {out / 'variants.json'}")  # noqa: T201
        return 0
    done = [r for r in result.records.values() if r is not None and r.state == "done"]
    ran = [r for r in done if r.variant not in result.skipped and r.seconds is not None]
    per = sum(r.seconds or 0.0 for r in ran) / len(ran) if ran else 0.0
    print(  # noqa: T201 - CLI output
        f"campaign {spec.name}: {len(done)}/{n} variants done ({len(result.skipped)} "
        f"complete before, {len(ran)} made, {per:.1f} s each), {len(result.failed)} failed, "
        f"in {result.wall_s:.1f} s"
    )
    print(f"  manifest: {result.manifest_json} and {result.manifest_csv}")  # noqa: T201
    print(f"  contact sheet: {result.contact_sheet}")  # noqa: T201
    for vid in result.failed:
        rec = result.records[vid]
        print(f"  {vid} failed: {rec.error if rec else ''}")  # noqa: T201
    return 1 if result.failed else 0
