"""The demo: synthetic sequence in, archive and metrics out.

:func:`run_service_demo` (``osdar-ar demo``, ``make demo``) runs the job service embedded -
the API and a worker on SQLite, the local store and a broker that needs no server - and
submits the job over HTTP. :func:`evaluate_raw_ins` measures the raw INS of a synthetic
sequence against its ground truth (how close the INS error profile is to the paper's).
"""

from __future__ import annotations

import json
import logging
import shutil
import tarfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from geometry.camera import CameraModel
from geometry.poses import PoseTrack
from osdar_platform.db import session_scope
from osdar_platform.keys import create_api_key
from worker.evaluation.landmark_error import landmark_errors
from worker.orchestration.embedded import Embedded, embedded_settings
from worker.osdar.ins_poses import ins_to_base_poses, world_frame_from_ins
from worker.osdar.sequence import Sequence
from worker.synth.generator import SynthConfig, generate

log = logging.getLogger(__name__)


def evaluate_raw_ins(seq_dir: Path) -> dict[str, Any]:
    """Raw-INS poses of a synthetic sequence against its ground truth.

    True pose errors (m, deg) at the lidar timestamps and landmark reprojection error and
    jitter per camera at full resolution (px).
    """
    seq_dir = Path(seq_dir)
    seq = Sequence.open(seq_dir)
    ins = seq.ins()
    world = world_frame_from_ins(ins)
    est = ins_to_base_poses(ins, world)
    gt_dir = seq_dir / "ground_truth"
    truth = PoseTrack.from_csv(gt_dir / "poses.csv")
    d_t, d_r = truth.relative_errors(est, max_extrapolation_s=0.2)
    meta = json.loads((gt_dir / "meta.json").read_text())
    landmarks = json.loads((gt_dir / "landmarks.json").read_text())
    xyz = np.array([lm["xyz"] for lm in landmarks]).reshape(-1, 3)
    per_camera = {}
    for cam_name, cam_json in meta["cameras_full_resolution"].items():
        cam = CameraModel.from_json(cam_json)
        times = dict(zip(seq.frame_indices, seq.timestamps(cam_name), strict=True))
        obs = [{int(f): uv for f, uv in lm["pixels"].get(cam_name, {}).items()} for lm in landmarks]
        errs = landmark_errors(cam, est, xyz, obs, times)
        per_camera[cam_name] = errs.summary()
    return {
        "sequence": seq.name,
        "frames": len(seq.frame_indices),
        "strategy": "ins",
        "pose_error": {
            "translation_m_mean": float(d_t.mean()),
            "translation_m_max": float(d_t.max()),
            "rotation_deg_mean": float(d_r.mean()),
            "rotation_deg_max": float(d_r.max()),
        },
        "landmark_reprojection_px": per_camera,
    }


DEMO_OBJECT = {"builtin": "person", "scale": 1.0}
DEMO_PLACEMENT = {"mode": "track", "s": 25.0, "offset": 0.0, "yaw_deg": 90.0}
POLL_INTERVAL_S = 0.5


def check_archive(archive: Path, sequence_name: str) -> dict[str, Any]:
    """What the downloaded archive holds; ValueError when it is not a complete result."""
    counts = {"files": 0, "images": 0, "clouds": 0, "previews": 0}
    names: set[str] = set()
    with tarfile.open(archive, "r:gz") as tar:
        for m in tar:
            if not m.isfile():
                continue
            names.add(m.name)
            counts["files"] += 1
            counts["images"] += m.name.endswith(".png") and "/report/" not in m.name
            counts["clouds"] += m.name.endswith(".pcd")
            counts["previews"] += m.name.startswith(f"{sequence_name}/report/previews/")
    need = [f"{sequence_name}/metrics.json", f"{sequence_name}/{sequence_name}_labels.json"]
    missing = [n for n in need if n not in names]
    if missing:
        raise ValueError(f"{archive}: missing {', '.join(missing)}")
    return {**counts, "bytes": archive.stat().st_size}


def run_service_demo(
    workdir: Path,
    *,
    scene: str = "fire_site",
    frames: int = 30,
    scale: float = 0.25,
    lidar_density: float = 0.25,
    seed: int = 0,
    host: str = "127.0.0.1",
    port: int = 0,
    on_synth: Callable[[int, int], None] | None = None,
    on_job: Callable[[dict[str, Any]], None] | None = None,
    timeout_s: float = 1800.0,
    keep_running: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The embedded service end to end: API + worker, a synthetic sequence, one job.

    Everything lives under ``workdir``: ``var/`` (SQLite DB and broker, store, caches,
    worker.log), the sequence, and the downloaded archive. ``on_job(job_json)`` is called
    at every poll; ``keep_running(url)`` is called before the service stops (the CLI's
    ``--serve`` blocks there).
    """

    workdir = Path(workdir).resolve()
    data = workdir / "var"
    settings = embedded_settings(data)
    seq_dir = workdir / f"{scene}_demo"
    if not (seq_dir / "ground_truth" / "meta.json").is_file():
        shutil.rmtree(seq_dir, ignore_errors=True)
        cfg = SynthConfig(
            scene=scene, frames=frames, scale=scale, seed=seed, lidar_density=lidar_density
        )
        generate(seq_dir, cfg, progress=on_synth)
    with Embedded(settings, host=host, port=port, log_file=data / "worker.log") as emb:
        with session_scope(settings) as session:
            _, secret = create_api_key(
                session=session, name="demo", pepper=settings.api_key_pepper.get_secret_value()
            )
        headers = {"Authorization": f"Bearer {secret}"}
        with httpx.Client(base_url=emb.url, headers=headers, timeout=60.0) as http:
            r = http.post("/v1/sequences", json={"path": str(seq_dir)})
            r.raise_for_status()
            seq = r.json()
            spec = {
                "sequence_id": seq["id"],
                "cameras": [c for c in seq["cameras"] if c.startswith("rgb")][:2],
                "lidar": True,
                "object": DEMO_OBJECT,
                "placement": DEMO_PLACEMENT,
                "strategy": "auto",
            }
            r = http.post("/v1/jobs", json=spec, headers={"Idempotency-Key": f"demo-{seq['id']}"})
            r.raise_for_status()
            job = r.json()
            deadline = time.monotonic() + timeout_s
            while job["state"] not in ("SUCCEEDED", "FAILED", "CANCELLED"):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"job {job['id']} still {job['state']} after {timeout_s}s")
                if emb.worker is not None and emb.worker.poll() is not None:
                    raise RuntimeError(f"the worker exited (see {data / 'worker.log'})")
                time.sleep(POLL_INTERVAL_S)
                job = http.get(f"/v1/jobs/{job['id']}").json()
                if on_job is not None:
                    on_job(job)
            if on_job is not None:
                on_job(job)
            result: dict[str, Any] = {"job": job, "api": emb.url, "workdir": str(workdir)}
            if job["state"] == "SUCCEEDED":
                archive = workdir / f"{seq_dir.name}.tar.gz"
                with http.stream("GET", f"/v1/jobs/{job['id']}/archive") as resp:
                    resp.raise_for_status()
                    with open(archive, "wb") as f:
                        for chunk in resp.iter_bytes():
                            f.write(chunk)
                result["archive"] = str(archive)
                result["archive_check"] = check_archive(archive, seq_dir.name)
                result["metrics"] = http.get(f"/v1/jobs/{job['id']}/metrics").json()
            paths = {getattr(r, "path", "") for r in emb.app.routes}
            dash = next((p for p in sorted(paths) if p.startswith("/dashboard")), None)
            result["dashboard"] = f"{emb.url}{dash}" if dash else None
            result["docs"] = f"{emb.url}/v1/docs"
            if keep_running is not None:
                keep_running(emb.url)
    return result
