"""The ``osdar-ar`` command line.

Sub-commands are small functions over the library; heavy imports happen inside them so
that ``osdar-ar --help`` is instant.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger("osdar_ar")


class CliError(Exception):
    """An error the user can act on: printed without a traceback, exit code 2."""


def _progress_bar(total: int, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True)


# ---------------------------------------------------------------------------- synth
def _add_synth(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="generate a synthetic OSDaR23-layout sequence with ground truth",
        description="Generate a synthetic OSDaR23 sequence (cameras, lidar, INS) from a "
        "procedural railway scene with the real OSDaR23 calibration; ground truth goes to "
        "OUT/ground_truth/.",
    )
    p.add_argument("out", type=Path, help="output folder; its name is the sequence name")
    p.add_argument("--scene", default="fire_site", help="scene preset (see --list-scenes)")
    p.add_argument("--list-scenes", action="store_true", help="list scene presets and exit")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument(
        "--scale",
        type=float,
        default=0.25,
        help="image size relative to the real resolution (1.0 = 2464x1600, 4112x2504)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cameras", default="rgb_center,rgb_highres_center")
    p.add_argument(
        "--lidar-density",
        type=float,
        default=1.0,
        help="fraction of the real lidars' rays (1.0 = OSDaR23 point counts)",
    )
    p.add_argument("--ins-profile", default="paper", help="INS error profile: paper, good, perfect")
    p.add_argument(
        "--ins",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an INS error-model field, e.g. --ins latency_s=0.05 "
        "(JSON values: --ins 'jumps=[[40,[3,0,0]]]')",
    )
    p.add_argument("--speed", type=float, default=None, help="train speed m/s (scene default)")
    p.add_argument("--stationary", action="store_true", help="train stands still")
    p.add_argument(
        "--far-origin",
        action="store_true",
        help="build and render the scene at UTM magnitudes (hard case 1)",
    )
    p.add_argument("--first-counter", type=int, default=0)
    p.add_argument("--drop-frames", default="", help="comma-separated frame counters to drop")
    p.add_argument("--pcd-data", default="binary", choices=["ascii", "binary", "binary_compressed"])
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        help="OSDaR23 labels file with the real calibration "
        "(default: ../shared/data/osdar23/1_calibration_1.1_labels.json)",
    )
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_synth)


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


def cmd_synth(args: argparse.Namespace) -> int:
    from worker.synth.generator import SynthConfig, generate

    if args.list_scenes:
        from worker.synth.scenes import SCENE_NAMES as SCENES

        for name in SCENES:
            print(name)  # noqa: T201 - CLI output
        return 0
    out: Path = args.out
    if out.exists():
        if not args.force:
            raise CliError(f"{out} exists: choose another folder or pass --force")
        import shutil

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
        )
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    bar = _progress_bar(args.frames - len(drops), f"synth {args.scene}")

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


# ---------------------------------------------------------------------------- info
def _add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="validate an OSDaR23 sequence folder and summarise it")
    p.add_argument("sequence", type=Path)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)


def cmd_info(args: argparse.Namespace) -> int:
    from worker.sequence_summary import summarize

    summary = summarize(args.sequence)
    if args.json:
        print(json.dumps(summary, indent=1))  # noqa: T201 - CLI output
    else:
        for k, v in summary.items():
            print(f"{k:>16}: {v}")  # noqa: T201 - CLI output
    return 0


# ---------------------------------------------------------------------------- demo
def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job end to end on a synthetic sequence",
        description="Make a synthetic sequence, run the pipeline that exists on it, "
        "package the result as an archive and print the metrics.",
    )
    p.add_argument("--workdir", type=Path, default=Path("demo_out"))
    p.add_argument("--scene", default="fire_site")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--lidar-density", type=float, default=0.25)
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from worker.demo import run_demo

    bar = _progress_bar(args.frames, "demo")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        result = run_demo(
            args.workdir,
            scene=args.scene,
            frames=args.frames,
            scale=args.scale,
            lidar_density=args.lidar_density,
            progress=progress,
        )
    finally:
        bar.close()
    print(json.dumps(result["metrics"], indent=1))  # noqa: T201 - CLI output
    print(f"archive: {result['archive']}")  # noqa: T201 - CLI output
    return 0


# ---------------------------------------------------------------------------- prepare
def _add_prepare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "prepare",
        help="prepare a sequence: poses, registered cloud, tracks, scene elements",
        description="Run pipeline step 2 on a sequence and write the artifact to OUT: "
        "poses.csv, world.json, centrelines.json, planes.json, poles.json, "
        "calibration_point.json, summary.json, cloud.npz. The artifact is cached by the "
        "sequence's content, the config and the clicks, and reused. When SEQ/ground_truth "
        "exists, the true pose errors are printed too.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument("--strategy", default="auto", help="ins, odometry, rails, fused or auto")
    p.add_argument("--out", type=Path, required=True, help="artifact folder (replaced)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--voxel-size", type=float, default=None, help="m, registered cloud voxel")
    p.add_argument(
        "--clicks", type=Path, default=None, help="clicked landmark pixels (CSV or JSON)"
    )
    p.add_argument(
        "--config", type=Path, default=None, help="JSON file with PrepareConfig sections"
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default $OSDAR_AR_CACHE_DIR or "
        "~/.cache/osdar-ar/prepared)",
    )
    p.set_defaults(func=cmd_prepare)


def _prepare_config(args: argparse.Namespace) -> Any:
    from pydantic import ValidationError

    from worker.preparation.config import PrepareConfig

    data: dict[str, Any] = {}
    if args.config is not None:
        try:
            data = json.loads(args.config.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CliError(f"--config {args.config}: {exc}") from exc
    data["strategy"] = args.strategy
    if args.voxel_size is not None:
        data["registration"] = {**data.get("registration", {}), "voxel_size": args.voxel_size}
    try:
        return PrepareConfig.model_validate(data)
    except ValidationError as exc:
        msgs = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'config'}: {e['msg']}" for e in exc.errors()
        )
        raise CliError(msgs) from exc


def _pose_error_rows(prepared: Any, seq_folder: Path) -> list[dict[str, Any]]:
    """True pose errors (m, deg) per track against SEQ/ground_truth/poses.csv."""
    import numpy as np

    from worker.geodesy import WorldFrame
    from worker.poses import PoseTrack, reexpress

    gt_dir = seq_folder / "ground_truth"
    gt = PoseTrack.from_csv(gt_dir / "poses.csv")
    world_file = gt_dir / "world.json"
    if world_file.is_file():
        gt = reexpress(gt, WorldFrame.from_json(json.loads(world_file.read_text())), prepared.world)
    rows = []
    tracks = {f"{prepared.strategy} (chosen)": prepared.track, **prepared.references}
    for name, track in tracks.items():
        try:
            dt, dr = track.relative_errors(gt, max_extrapolation_s=0.05)
        except ValueError as exc:
            log.warning("pose errors of %s: %s", name, exc)
            continue
        rows.append(
            {
                "track": name,
                "frames": len(dt),
                "translation_mean_m": float(np.mean(dt)),
                "translation_max_m": float(np.max(dt)),
                "rotation_mean_deg": float(np.mean(dr)),
                "rotation_max_deg": float(np.max(dr)),
            }
        )
    return rows


def cmd_prepare(args: argparse.Namespace) -> int:
    import os

    from worker.preparation.artifact import copy_artifact, write_artifact
    from worker.preparation.calibration_point import ClicksError
    from worker.preparation.prepare import STAGES, PreparationError, prepare

    config = _prepare_config(args)
    cache_dir = args.cache_dir or Path(
        os.environ.get("OSDAR_AR_CACHE_DIR", Path.home() / ".cache/osdar-ar/prepared")
    )
    bar = _progress_bar(len(STAGES), f"prepare {args.sequence.name}")
    bar.unit = "stage"

    def progress(stage: str, done: int, total: int) -> None:
        bar.set_postfix_str(stage)
        bar.update(done - bar.n)

    try:
        prepared = prepare(
            args.sequence, config, clicks=args.clicks, cache_dir=cache_dir, progress=progress
        )
        bar.update(bar.total - bar.n)
    except (PreparationError, ClicksError) as exc:
        raise CliError(str(exc)) from exc
    finally:
        bar.close()
    if prepared.folder is not None:
        copy_artifact(prepared.folder, args.out)
    else:  # pragma: no cover - prepare() always writes under a cache folder
        write_artifact(prepared, args.out)
    s = prepared.summary
    errors = []
    if (args.sequence / "ground_truth" / "poses.csv").is_file():
        errors = _pose_error_rows(prepared, args.sequence)
    if args.json:
        out = {**s, "out": str(args.out), "true_pose_errors": errors or None}
        print(json.dumps(out, indent=1))  # noqa: T201 - CLI output
        return 0
    how = "reused" if s.get("reused") else f"prepared in {s.get('total_seconds', 0.0):.1f} s"
    print(  # noqa: T201 - CLI output
        f"{s['sequence']['name']}: {how}, strategy {s['strategy']} "
        f"(requested {s['requested_strategy']}), key {prepared.key[:16]} -> {args.out}"
    )
    timings = s.get("timings", {})
    if timings and not s.get("reused"):
        print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()))  # noqa: T201
    health = s.get("health", {})
    print(  # noqa: T201 - CLI output
        f"  health: {'ok' if health.get('ok') else 'degraded'}"
        + (f", fallback {health['fallback']}" if health.get("fallback") else "")
    )
    for w in s.get("warnings", []):
        print(f"  warning: {w}")  # noqa: T201 - CLI output
    sc, cal = s.get("scene", {}), s.get("calibration") or {}
    print(  # noqa: T201 - CLI output
        f"  cloud {s['cloud']['points']} points, {s['tracks']['count']} track(s) "
        f"(ego {'found' if s['tracks']['ego_found'] else 'NOT found'}), "
        f"{sc.get('planes', 0)} planes ({sc.get('platforms', 0)} platforms), "
        f"{sc.get('poles', 0)} poles"
    )
    if cal:
        res = cal.get("residual_mean_px")
        print(  # noqa: T201 - CLI output
            f"  calibration point ({cal['mode']}): {cal['landmark']}, "
            + ("not found" if not cal["found"] else "found")
            + ("" if res is None else f", mean residual {res:.2f} px over {cal['views']} views")
        )
    if errors:
        print("  true pose errors (ground_truth/poses.csv):")  # noqa: T201 - CLI output
        print(  # noqa: T201 - CLI output
            f"  {'track':<22} {'frames':>6} {'t mean m':>9} {'t max m':>9} "
            f"{'r mean deg':>10} {'r max deg':>10}"
        )
        for r in errors:
            print(  # noqa: T201 - CLI output
                f"  {r['track']:<22} {r['frames']:>6d} {r['translation_mean_m']:>9.3f} "
                f"{r['translation_max_m']:>9.3f} {r['rotation_mean_deg']:>10.3f} "
                f"{r['rotation_max_deg']:>10.3f}"
            )
    return 0


# ---------------------------------------------------------------------------- keys
def _add_keys(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("keys", help="manage API keys of the job service")
    keys = p.add_subparsers(dest="keys_command", required=True)
    c = keys.add_parser("create", help="create a key and print its secret (shown once)")
    c.add_argument("name", help="who or what the key is for")
    c.set_defaults(func=cmd_keys_create)
    ls = keys.add_parser("list", help="list keys (id, prefix, name, revoked)")
    ls.set_defaults(func=cmd_keys_list)
    r = keys.add_parser("revoke", help="revoke a key by id")
    r.add_argument("key_id", type=int)
    r.set_defaults(func=cmd_keys_revoke)


def cmd_keys_create(args: argparse.Namespace) -> int:
    from worker.jobs.db import session_scope
    from worker.jobs.keys import create_api_key
    from worker.jobs.settings import get_settings

    settings = get_settings()
    try:
        with session_scope(settings) as session:
            row, secret = create_api_key(
                session=session,
                name=args.name,
                pepper=settings.api_key_pepper.get_secret_value(),
            )
            key_id = row.id
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    print(f"key {key_id} ({args.name}); the secret is shown only now:", file=sys.stderr)  # noqa: T201
    print(secret)  # noqa: T201 - CLI output
    return 0


def cmd_keys_list(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from worker.jobs.db import session_scope
    from worker.jobs.models import ApiKey
    from worker.jobs.settings import get_settings

    with session_scope(get_settings()) as session:
        for k in session.scalars(select(ApiKey).order_by(ApiKey.id)):
            state = "revoked" if k.revoked else "active"
            print(f"{k.id:>5}  {k.prefix}...  {state:<8} {k.name}")  # noqa: T201 - CLI output
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from worker.jobs.db import session_scope
    from worker.jobs.keys import revoke_api_key
    from worker.jobs.settings import get_settings

    with session_scope(get_settings()) as session:
        if not revoke_api_key(session=session, key_id=args.key_id):
            raise CliError(f"no key with id {args.key_id}")
    return 0


# ---------------------------------------------------------------------------- migrate
def _add_migrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "migrate",
        help="apply the database migrations (alembic upgrade head): the prestart step",
    )
    p.add_argument("--revision", default="head")
    p.set_defaults(func=cmd_migrate)


def cmd_migrate(args: argparse.Namespace) -> int:
    from worker.jobs.migrate import upgrade
    from worker.jobs.settings import get_settings

    url = str(get_settings().database_url)
    upgrade(database_url=url, revision=args.revision)
    log.info("database at revision %s", args.revision)
    return 0


# ---------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="osdar-ar",
        description="Augmented railway perception data in the OSDaR23 layout.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True)
    _add_synth(sub)
    _add_info(sub)
    _add_demo(sub)
    _add_prepare(sub)
    _add_keys(sub)
    _add_migrate(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG
        if args.verbose > 1
        else logging.INFO
        if args.verbose
        else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    from worker.osdar.errors import SequenceError

    try:
        return int(args.func(args) or 0)
    except (CliError, SequenceError, FileNotFoundError) as exc:
        print(f"osdar-ar {args.command}: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
