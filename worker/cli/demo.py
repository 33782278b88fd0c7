"""``osdar-ar demo``: the job service embedded, one job end to end on a synthetic
sequence."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from worker.cli.progress import progress_bar
from worker.demo import run_service_demo
from worker.evaluation.tables import rpe_tables


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


def run(args: argparse.Namespace) -> int:
    synth_bar = progress_bar(args.frames, "synthetic sequence")
    job_bar: Any = None

    def on_synth(done: int, total: int) -> None:
        synth_bar.total = total
        synth_bar.update(done - synth_bar.n)

    def on_job(job: dict[str, Any]) -> None:
        nonlocal job_bar
        if job_bar is None:
            synth_bar.close()
            job_bar = progress_bar(max(1, job["progress"]["total"]), f"job {job['id'][:8]}")
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
