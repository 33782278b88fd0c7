"""The demo job: synthetic sequence in, archive and metrics out.

Until the job service exists this runs, in-process, the parts of the pipeline that exist:
generate -> open and validate -> raw-INS poses -> evaluate against the ground truth ->
package (archive + metrics.json).
"""

from __future__ import annotations

import json
import logging
import shutil
import tarfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from renderer.camera import CameraModel
from worker.geodesy import world_frame_from_ins
from worker.landmark_error import landmark_errors
from worker.osdar.sequence import Sequence
from worker.poses import PoseTrack, ins_to_base_poses
from worker.synth.generator import SynthConfig, generate

log = logging.getLogger(__name__)


def run_demo(
    workdir: Path,
    scene: str = "fire_site",
    frames: int = 30,
    scale: float = 0.25,
    lidar_density: float = 0.25,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the demo job; returns {"archive": path, "metrics": dict}."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    seq_dir = workdir / f"{scene}_demo"
    if seq_dir.exists():
        shutil.rmtree(seq_dir)
    cfg = SynthConfig(
        scene=scene, frames=frames, scale=scale, seed=seed, lidar_density=lidar_density
    )
    synth = generate(seq_dir, cfg, progress=progress)
    metrics = evaluate_raw_ins(seq_dir)
    metrics["synth_seconds"] = synth.stage_seconds
    (workdir / "metrics.json").write_text(json.dumps(metrics, indent=1))
    archive = package(seq_dir, workdir / "metrics.json", workdir / f"{seq_dir.name}.tar.gz")
    return {"archive": str(archive), "metrics": metrics}


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


def package(seq_dir: Path, metrics: Path, archive: Path) -> Path:
    """The sequence (without ground truth) and metrics.json as one .tar.gz, atomically."""
    tmp = archive.with_name(archive.name + ".partial")
    with tarfile.open(tmp, "w:gz", compresslevel=1) as tar:
        for path in sorted(seq_dir.rglob("*")):
            rel = path.relative_to(seq_dir)
            if rel.parts[0] == "ground_truth" or not path.is_file():
                continue
            tar.add(path, arcname=f"{seq_dir.name}/{rel.as_posix()}")
        tar.add(metrics, arcname=f"{seq_dir.name}/metrics.json")
    tmp.replace(archive)
    return archive
