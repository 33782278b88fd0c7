"""The ``osdar-ar`` command line.

Sub-commands are small functions over the library; heavy imports happen inside them so
that ``osdar-ar --help`` is instant.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
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
    p.add_argument(
        "--ins-profile",
        default="paper",
        help="INS error profile: paper, good, perfect, hard, osdar23",
    )
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
    from worker.osdar.summary import summarize

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
        help="run the job service embedded and one job end to end on a synthetic sequence",
        description="Start the API and a worker (SQLite, local store, a SQLite broker: no "
        "server), make a synthetic sequence, submit a job over HTTP and poll it, download "
        "and check the archive, print the metrics and the dashboard's address. Everything "
        "is kept under --workdir.",
    )
    p.add_argument("--workdir", type=Path, default=Path("demo_out"))
    p.add_argument("--scene", default="fire_site")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--lidar-density", type=float, default=0.25)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="API port (0: any free port)")
    p.add_argument(
        "--serve", action="store_true", help="keep the API and worker running until Ctrl-C"
    )
    p.set_defaults(func=cmd_demo)


def _fmt(stats: dict[str, Any] | None) -> str:
    if not stats or stats.get("mean") is None:
        return "-"
    return f"{stats['mean']:.2f} ± {stats['std']:.2f}"


def rpe_tables(ev: dict[str, Any], gt: dict[str, Any]) -> list[str]:
    """Two tables, named for what they measure: the paper's RPE / jitter (the calibration
    point picked from the clicked landmark, projected with the poses, against the clicks:
    comparable with the paper's table) and, on synthetic data, the true error (the true 3D
    landmarks projected with the estimated poses against their true pixels)."""
    lines = ["  paper RPE / jitter (calibration point from the clicks, as the paper):"]
    lines.append(f"  {'camera':<20} {'RPE px':>16} {'jitter px':>16}")
    for cam, m in (ev.get("rpe") or {}).items():
        lines.append(f"  {cam:<20} {_fmt(m.get('rpe_px')):>16} {_fmt(m.get('jitter_px')):>16}")
    landmark = gt.get("landmark_rpe") or {}
    if landmark:
        lines.append("  true error of the ground-truth landmarks (synthetic data only):")
        lines.append(f"  {'camera':<20} {'track':<10} {'error px':>16} {'change px':>16}")
        for cam, tracks in landmark.items():
            for name, m in tracks.items():
                err, jit = _fmt(m.get("rpe_px")), _fmt(m.get("jitter_px"))
                lines.append(f"  {cam:<20} {name:<10} {err:>16} {jit:>16}")
    return lines


def _print_demo(result: dict[str, Any], workdir: Path, serving: bool = False) -> None:
    job = result["job"]
    out = print
    out(f"job {job['id']}: {job['state']}" + (f" ({job['error']})" if job.get("error") else ""))
    if job.get("timings"):
        out("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in job["timings"].items()))
    metrics = dict(result.get("metrics") or {})
    if metrics:
        path = workdir / "metrics.json"
        path.write_text(json.dumps(metrics, indent=1))
        ev = metrics.get("evaluation") or {}
        chosen = ev.get("strategy")
        out(f"  strategy: {chosen} (requested {ev.get('requested_strategy')})")
        gt = ev.get("ground_truth") or {}
        pose = (gt.get("pose_error") or {}).get(chosen) or {}
        if "translation_m_mean" in pose:
            out(
                f"  true pose error: {pose['translation_m_mean']:.3f} m "
                f"(max {pose['translation_m_max']:.3f}), {pose['rotation_deg_mean']:.3f} deg"
            )
        for line in rpe_tables(ev, gt):
            out(line)
        aug = metrics.get("augmentation") or {}
        if aug:
            fr = aug.get("frames") or {}
            out(
                f"  augmentation: {aug.get('object', {}).get('class')} annotated in "
                f"{fr.get('annotated')} of {fr.get('augmented_range')} frames"
            )
        out(f"  all metrics: {path}")
    if "archive" in result:
        c = result["archive_check"]
        out(
            f"archive: {result['archive']} ({c['bytes'] / 1e6:.1f} MB, {c['files']} files: "
            f"{c['images']} images, {c['clouds']} clouds, {c['previews']} previews) - checked"
        )
    out(f"dashboard: {result['api']}/dashboard (log in with an API key); docs: {result['docs']}")
    if not serving:
        out("  (the service has stopped: `osdar-ar demo --serve` keeps it up)")


def cmd_demo(args: argparse.Namespace) -> int:
    from worker.demo import run_service_demo

    synth_bar = _progress_bar(args.frames, "synthetic sequence")
    job_bar: Any = None

    def on_synth(done: int, total: int) -> None:
        synth_bar.total = total
        synth_bar.update(done - synth_bar.n)

    def on_job(job: dict[str, Any]) -> None:
        nonlocal job_bar
        if job_bar is None:
            synth_bar.close()
            job_bar = _progress_bar(max(1, job["progress"]["total"]), f"job {job['id'][:8]}")
        job_bar.total = max(1, job["progress"]["total"])
        job_bar.set_postfix_str(f"{job['state'].lower()}: {job['stage'] or '-'}")
        job_bar.update(job["progress"]["done"] - job_bar.n)

    def keep_running(url: str) -> None:
        if not args.serve:
            return
        print(f"serving on {url} (Ctrl-C stops)", file=sys.stderr)  # noqa: T201
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass

    import time

    try:
        result = run_service_demo(
            args.workdir,
            scene=args.scene,
            frames=args.frames,
            scale=args.scale,
            lidar_density=args.lidar_density,
            host=args.host,
            port=args.port,
            on_synth=on_synth,
            on_job=on_job,
            keep_running=keep_running,
        )
    finally:
        synth_bar.close()
        if job_bar is not None:
            job_bar.close()
    _print_demo(result, args.workdir, serving=args.serve)
    return 0 if result["job"]["state"] == "SUCCEEDED" else 1


# ---------------------------------------------------------------------------- serve, worker
def _add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the API (uvicorn); migrates the database first unless --no-migrate",
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1, help="uvicorn worker processes")
    p.add_argument("--no-migrate", action="store_true", help="skip alembic upgrade head")
    p.set_defaults(func=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from osdar_platform.settings import get_settings

    if not args.no_migrate:
        from osdar_platform.migrate import upgrade

        upgrade(database_url=str(get_settings().database_url))
    uvicorn.run("service.app:app", host=args.host, port=args.port, workers=args.workers)
    return 0


def _add_worker(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "worker",
        help="run a Celery worker for the configured broker (BROKER_URL)",
        description="A Celery worker on the osdar_ar queue. Start as many as you like, on "
        "as many machines (they share DATABASE_URL, BROKER_URL and STORE_URL).",
    )
    p.add_argument("--concurrency", type=int, default=None, help="default: number of CPUs")
    p.add_argument("--pool", choices=["prefork", "solo", "threads"], default="prefork")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--hostname", default=None, help="worker node name (default celery@host)")
    p.set_defaults(func=cmd_worker)


def cmd_worker(args: argparse.Namespace) -> int:
    from worker.orchestration.threads import thread_caps

    # Before anything imports numpy: the prefork children inherit the caps.
    os.environ.update(thread_caps(args.concurrency))
    from worker.orchestration.celery_app import QUEUE, celery_app

    argv = ["worker", "--pool", args.pool, "--queues", QUEUE, "--loglevel", args.loglevel]
    if args.concurrency is not None:
        argv += ["--concurrency", str(args.concurrency)]
    if args.hostname:
        argv += ["--hostname", args.hostname]
    celery_app.worker_main(argv)
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

    from geometry.geodesy import WorldFrame
    from geometry.poses import PoseTrack, reexpress

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


# ---------------------------------------------------------------------------- augment
def _add_augment(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "augment",
        help="add a virtual obstacle to a sequence (cameras, lidar, annotations)",
        description="Augment SEQ with a virtual object and write the result to OUT in the "
        "OSDaR23 layout (every input file present: augmented where the object shows, "
        "byte-identical elsewhere) plus OUT/metrics.json (per-stage timings; the object's "
        "errors where SEQ has ground_truth/). The preparation is cached and reused.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument(
        "--object",
        required=True,
        help="built-in obstacle (person, rock, fallen_tree, cow, horse, elephant) or a "
        "mesh file (.glb, .gltf, .obj, .ply)",
    )
    p.add_argument("--object-scale", type=float, default=1.0, help="uniform size factor")
    p.add_argument("--mesh-units", type=float, default=None, help="metres per mesh file unit")
    p.add_argument("--seed", type=int, default=0, help="seed of the built-in obstacle")
    p.add_argument(
        "--place",
        default="s=40,offset=0,yaw=90",
        help='track "s=40,offset=0,yaw=90" (m along the ego track from the first frame, '
        'm left, deg from the track direction), world "mode=world,x=..,y=..,yaw=..", or '
        'lidar frame "frame=12,x=..,y=..,yaw=.."',
    )
    p.add_argument("--cameras", default=None, help="comma-separated (default: the front ones)")
    p.add_argument("--no-lidar", action="store_true", help="leave the point clouds unchanged")
    p.add_argument("--frames", default=None, metavar="FIRST:LAST", help="frame range, inclusive")
    p.add_argument("--strategy", default="auto", help="ins, odometry, rails, fused or auto")
    p.add_argument(
        "--lidar-origins",
        default="single",
        help="'single' (the base frame origin, the paper's fallback), 'x,y,z', or a "
        "lidar_origins.json file of per-sensor origins",
    )
    p.add_argument("--clicks", type=Path, default=None, help="clicked landmark pixels file")
    p.add_argument("--png-compression", type=int, default=1, help="zlib level 0-9")
    p.add_argument("--no-blur", action="store_true")
    p.add_argument("--no-lab-match", action="store_true")
    p.add_argument("--shadow", type=float, default=0.6, help="shadow strength 0-1")
    p.add_argument(
        "--pixel-offset", action="store_true", help="compensate the calibration point's offset"
    )
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--out", type=Path, required=True, help="output sequence folder")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.add_argument("--no-evaluate", action="store_true", help="skip the ground-truth errors")
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default $OSDAR_AR_CACHE_DIR or "
        "~/.cache/osdar-ar/prepared)",
    )
    p.set_defaults(func=cmd_augment)


def _augment_spec(args: argparse.Namespace) -> Any:
    from pydantic import ValidationError

    from worker.augmentation.placement import PlacementError
    from worker.augmentation.spec import (
        AugmentSpec,
        ObjectSource,
        PlacementModel,
        RenderSpec,
    )

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
        from worker.preparation.calibration_point import Clicks, ClicksError

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
            ),
        )
    except ValidationError as exc:
        msgs = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'spec'}: {e['msg']}" for e in exc.errors()
        )
        raise CliError(msgs) from exc


def cmd_augment(args: argparse.Namespace) -> int:
    from worker.augmentation.augment import augment
    from worker.augmentation.placement import PlacementError
    from worker.augmentation.plan import AugmentError
    from worker.preparation.calibration_point import ClicksError
    from worker.preparation.config import STRATEGY_NAMES
    from worker.preparation.prepare import PreparationError

    spec = _augment_spec(args)
    if args.strategy not in STRATEGY_NAMES:
        raise CliError(f"--strategy {args.strategy!r}: known {', '.join(STRATEGY_NAMES)}")
    if args.out.exists() and not args.force:
        raise CliError(f"{args.out} exists: choose another folder or pass --force")
    if args.out.resolve() == args.sequence.resolve():
        raise CliError("--out must not be the input sequence")
    cache_dir = args.cache_dir or Path(
        os.environ.get("OSDAR_AR_CACHE_DIR", Path.home() / ".cache/osdar-ar/prepared")
    )
    bar = _progress_bar(0, f"augment {args.sequence.name}")

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


def _database_ready() -> Any:
    """The settings, with the database migrated to head first (idempotent): a command that
    needs the tables works on a fresh database, or says in one line why it cannot."""
    from sqlalchemy.exc import SQLAlchemyError

    from osdar_platform.migrate import upgrade
    from osdar_platform.settings import get_settings

    settings = get_settings()
    try:
        upgrade(database_url=str(settings.database_url))
    except (SQLAlchemyError, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CliError(
            f"database {settings.database_url} is not usable ({first}); check DATABASE_URL "
            "and run `osdar-ar migrate`"
        ) from exc
    return settings


def cmd_keys_create(args: argparse.Namespace) -> int:
    from osdar_platform.db import session_scope
    from osdar_platform.keys import create_api_key

    settings = _database_ready()
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

    from osdar_platform.db import session_scope
    from osdar_platform.models import ApiKey

    with session_scope(_database_ready()) as session:
        for k in session.scalars(select(ApiKey).order_by(ApiKey.id)):
            state = "revoked" if k.revoked else "active"
            print(f"{k.id:>5}  {k.prefix}...  {state:<8} {k.name}")  # noqa: T201 - CLI output
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from osdar_platform.db import session_scope
    from osdar_platform.keys import revoke_api_key

    with session_scope(_database_ready()) as session:
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
    from osdar_platform.migrate import upgrade
    from osdar_platform.settings import get_settings

    url = str(get_settings().database_url)
    upgrade(database_url=url, revision=args.revision)
    log.info("database at revision %s", args.revision)
    return 0


# ---------------------------------------------------------------------------- evaluate
def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="RPE and jitter per camera and strategy (the paper's definition), true errors",
        description="Prepare SEQ with every strategy (cached), then for every camera, "
        "strategy and landmark: the calibration point (the cloud point registered with that "
        "strategy's poses nearest to the clicks), RPE_i and jitter J_i per frame, mean and "
        "std. Clicks come from --clicks files (CSV / JSON, see the README) or, on synthetic "
        "sequences, from ground_truth/landmarks.json (landmarks --near..--far m ahead). "
        "Writes OUT/metrics.json, OUT/per_frame.csv, OUT/rpe.png and OUT/overlays/*.png.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--strategies", default="ins,odometry,rails,fused", help="comma-separated")
    p.add_argument(
        "--clicks", type=Path, action="append", default=[],
        help="clicks file of one landmark (repeatable); default: ground truth (synthetic)",
    )  # fmt: skip
    p.add_argument("--cameras", default=None, help="comma-separated (default: clicked ones)")
    p.add_argument("--near", type=float, default=30.0, help="m, synthetic landmarks from")
    p.add_argument("--far", type=float, default=80.0, help="m, synthetic landmarks to")
    p.add_argument("--click-noise", type=float, default=0.0, help="px, synthetic click noise")
    p.add_argument("--max-landmarks", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--voxel-size", type=float, default=None, help="m, registered cloud voxel")
    p.add_argument(
        "--dense-radius", type=float, default=None,
        help="m: refine each calibration point among every frame's full-density points this "
        "close (default 0.5; 0: the registered cloud's point only, as in the paper)",
    )  # fmt: skip
    p.add_argument(
        "--overlay-frames", default=None, help="comma-separated frames (default: 3 per camera)"
    )
    p.add_argument("--no-overlay", action="store_true")
    p.add_argument("--cache-dir", type=Path, default=None, help="prepared artifacts cache")
    p.set_defaults(func=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    import time

    from worker.evaluation.evaluate import (
        evaluate_strategies,
        plot_rpe_by_strategy,
        render_overlays,
        write_rows_csv,
    )
    from worker.preparation.calibration_point import Clicks, ClicksError
    from worker.preparation.config import PrepareConfig
    from worker.preparation.prepare import prepare

    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    try:
        clicks = [Clicks.load(c) for c in args.clicks] or None
        configs = {
            s: PrepareConfig(strategy=s).with_overrides(
                registration={} if args.voxel_size is None else {"voxel_size": args.voxel_size}
            )
            for s in strategies
        }
    except (ClicksError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    cache = args.cache_dir or Path(
        os.environ.get("OSDAR_AR_CACHE_DIR", Path.home() / ".cache/osdar-ar/prepared")
    )
    tracks, prep, world = {}, {}, None
    for s, cfg in configs.items():
        t0 = time.perf_counter()
        prepared = prepare(args.sequence, cfg, cache_dir=cache)
        tracks[s] = (prepared.track, prepared.cloud.xyz)
        world = prepared.world
        prep[s] = {
            "seconds": time.perf_counter() - t0,
            "reused": bool(prepared.summary.get("reused")),
            "preparation_seconds": prepared.summary.get("total_seconds"),
            "chosen": prepared.strategy,
            "warnings": prepared.summary.get("warnings", []),
        }
    cameras = None if args.cameras is None else [c.strip() for c in args.cameras.split(",")]
    if args.dense_radius is not None and args.dense_radius < 0:
        raise CliError(f"--dense-radius must be >= 0 m (got {args.dense_radius})")
    dense_kw = {} if args.dense_radius is None else {"dense_radius_m": args.dense_radius}
    try:
        metrics, rows = evaluate_strategies(
            args.sequence, tracks, world=world, cameras=cameras, clicks=clicks,
            near=args.near, far=args.far, click_noise_px=args.click_noise, seed=args.seed,
            max_landmarks=args.max_landmarks, preparation=prep, **dense_kw,
        )  # fmt: skip
    except (ClicksError, ValueError) as exc:
        raise CliError(str(exc)) from exc
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    files = {"per_frame_csv": str(write_rows_csv(rows, out / "per_frame.csv"))}
    plot = plot_rpe_by_strategy(rows, out / "rpe.png", f"RPE over frames, {metrics['sequence']}")
    files["rpe_png"] = None if plot is None else str(plot)
    if not args.no_overlay:
        frames = None
        if args.overlay_frames:
            frames = [int(f) for f in args.overlay_frames.split(",") if f.strip()]
        paths = render_overlays(args.sequence, rows, metrics, tracks, out / "overlays", frames)
        files["overlays"] = [str(p) for p in paths]
    metrics["files"] = files
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, allow_nan=False))
    print(f"{metrics['sequence']}: clicks from {metrics['clicks_source']}, landmarks "  # noqa: T201
          f"{', '.join(metrics['landmarks_clicked']) or 'none'}")  # fmt: skip
    print("paper RPE / jitter (calibration point from the clicks, as the paper):")  # noqa: T201
    print("camera              strategy   RPE mean±std px    jitter mean±std px   n")  # noqa: T201
    for cam, per in metrics["rpe"].items():
        for s, st in per.items():
            rpe = "-" if st["rpe_mean"] is None else f"{st['rpe_mean']:.2f}±{st['rpe_std']:.2f}"
            jit = (
                "-"
                if st["jitter_mean"] is None
                else (f"{st['jitter_mean']:.2f}±{st['jitter_std']:.2f}")
            )
            print(f"{cam:<19} {s:<10} {rpe:<18} {jit:<20} {st['n']}")  # noqa: T201
    for s, te in (metrics.get("true_errors") or {}).items():
        if "translation_m_mean" in te:
            print(  # noqa: T201
                f"true pose error {s}: {te['translation_m_mean']:.3f} m, "
                f"{te['rotation_deg_mean']:.3f} deg (mean)"
            )
    print(f"wrote {out}/metrics.json, per_frame.csv, rpe.png, overlays/")  # noqa: T201
    return 0


# ---------------------------------------------------------------------------- bench
def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="speed against error: the paper's table, knobs / Pareto front, I/O floor",
        description="Run the synthetic counterparts of the paper's three sequences with "
        "every strategy and print the paper's table with its numbers beside ours, the time "
        "per strategy, the speed-against-error table with its Pareto front and the I/O "
        "floor ratio; --hard runs the hard-case suite instead.",
    )
    p.add_argument("--quick", action="store_true", help="reduced run (CI): 20 frames, 2 strategies")
    p.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    p.add_argument("--hard", action="store_true", help="the 12 hard cases with their bounds")
    p.add_argument(
        "--matrix", action="store_true",
        help="the robustness matrix (scenes x lengths x densities x INS profiles x seeds, "
        "slow and standing trains; --quick: the 8 CI cells): per-strategy distributions, "
        "goals (ok / MISS), heatmap PNG",
    )  # fmt: skip
    p.add_argument(
        "--markdown", type=Path, default=None, help="with --matrix: write the report as markdown"
    )
    p.add_argument("--no-floor", action="store_true", help="skip the I/O floor measurement")
    p.add_argument(
        "--ins-profile", default="osdar23",
        help="synthetic INS of the sequences: osdar23 (default: wanders like the real INS), "
        "paper, good, perfect, hard",
    )  # fmt: skip
    p.add_argument(
        "--workdir", type=Path, default=Path("/tmp/osdar_bench"),
        help="generated sequences, per-frame CSVs, pareto.png (reused between runs)",
    )  # fmt: skip
    p.set_defaults(func=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from worker.bench.run import FULL, QUICK, run_bench

    if args.matrix:
        return _bench_matrix(args)
    settings = replace(QUICK if args.quick else FULL, ins_profile=args.ins_profile)
    result = run_bench(
        quick=args.quick, workdir=args.workdir, json_path=args.json, hard=args.hard,
        floor=not args.no_floor, settings=settings,
    )  # fmt: skip
    if args.hard:
        return 0 if all(c["ok"] for c in result["hard_cases"]) else 1
    return 0


def _bench_matrix(args: argparse.Namespace) -> int:
    from worker.bench.matrix import design, format_summary, run_and_report

    bar = _progress_bar(len(design(args.quick)), "robustness matrix")
    bar.unit = "cell"

    def progress(done: int, total: int, name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(done - bar.n)

    try:
        result = run_and_report(
            args.workdir / "matrix", quick=args.quick, json_path=args.json,
            markdown_path=args.markdown, progress=progress,
        )  # fmt: skip
        bar.update(bar.total - bar.n)
    finally:
        bar.close()
    print(format_summary(result))  # noqa: T201 - CLI output
    for kind, path in result["outputs"].items():
        print(f"{kind}: {path}")  # noqa: T201 - CLI output
    return 1 if result["failed_cells"] else 0


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
    _add_serve(sub)
    _add_worker(sub)
    _add_prepare(sub)
    _add_augment(sub)
    _add_evaluate(sub)
    _add_bench(sub)
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
