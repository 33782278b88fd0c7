"""Pipeline step 8, evaluation: how well the poses hold a virtual object in place.

The paper's measures (../shared/design/OSDAR23.md), per camera and strategy:
RPE_i = ||GT_i - p_i|| (px) between a landmark's observed pixel and the projection of its
3D point with frame i's pose, and jitter J_i = |RPE_{i+1} - RPE_i|.

- With hand clicks, the landmark is the calibration point of the preparation and GT_i the
  clicks (the paper's setting): its residuals per view are the RPE.
- On synthetic sequences (``ground_truth/``), every true landmark with its true pixels,
  under the chosen strategy's poses and every reference track, plus the true pose errors.
  The pipeline never reads ``ground_truth/`` while it runs; only this step does, to score.

:func:`evaluate_sequence` returns JSON-ready metrics (no NaN) and per-frame series for the
report plot (:func:`plot_rpe_jitter`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from worker.preparation.artifact import PreparedSequence


def _finite(x: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _stats(values: np.ndarray) -> dict[str, Any]:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return {"mean": None, "std": None, "max": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "max": float(v.max()), "n": len(v)}


def _per_frame(frames: np.ndarray, rpe: np.ndarray) -> tuple[list[int], list[float], list[float]]:
    """Mean RPE per frame and the jitter |RPE_{i+1} - RPE_i| between consecutive frames."""
    out_f, out_r = [], []
    for f in sorted(set(int(x) for x in frames)):
        out_f.append(f)
        out_r.append(float(np.mean(rpe[frames == f])))
    jitter = [
        abs(out_r[k + 1] - out_r[k]) for k in range(len(out_f) - 1) if out_f[k + 1] == out_f[k] + 1
    ]
    return out_f, out_r, jitter


def clicks_rpe(prepared: PreparedSequence) -> tuple[dict[str, Any], dict[str, Any]]:
    """RPE / jitter of the clicked calibration point per camera: (metrics, series)."""
    cal = prepared.calibration
    if cal is None or cal.mode != "clicks":
        return {}, {}
    metrics, series = {}, {}
    for cam in sorted({o["camera"] for o in cal.observations}):
        obs = [o for o in cal.observations if o["camera"] == cam and o["residual_px"] is not None]
        frames = np.array([int(o["frame_idx"]) for o in obs], dtype=np.int64)
        rpe = np.array([float(o["residual_px"]) for o in obs], dtype=np.float64)
        f, r, j = _per_frame(frames, rpe)
        metrics[cam] = {"rpe_px": _stats(rpe), "jitter_px": _stats(np.asarray(j))}
        series[cam] = {"frames": f, "rpe": r}
    return metrics, series


def _ground_truth(
    seq_folder: Path, prepared: PreparedSequence, cameras: list[str]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """True pose errors and landmark RPE / jitter per camera and track (synthetic data)."""
    from renderer.camera import CameraModel
    from worker.geodesy import WorldFrame
    from worker.landmark_error import landmark_errors
    from worker.osdar.sequence import Sequence
    from worker.poses import PoseTrack, reexpress

    gt_dir = seq_folder / "ground_truth"
    meta = json.loads((gt_dir / "meta.json").read_text())
    truth = PoseTrack.from_csv(gt_dir / "poses.csv")
    T_prep_gt = np.eye(4)
    if (gt_dir / "world.json").is_file():
        gt_world = WorldFrame.from_json(json.loads((gt_dir / "world.json").read_text()))
        truth = reexpress(truth, gt_world, prepared.world)
        T_prep_gt = prepared.world.T_world_other(gt_world)
    chosen = prepared.strategy or "chosen"
    tracks = {chosen: prepared.track}
    tracks.update({k: v for k, v in prepared.references.items() if k != chosen})
    pose_errors: dict[str, Any] = {}
    for name, track in tracks.items():
        try:
            dt, dr = track.relative_errors(truth, max_extrapolation_s=0.05)
        except ValueError as exc:
            pose_errors[name] = {"error": str(exc)}
            continue
        pose_errors[name] = {
            "translation_m_mean": float(np.mean(dt)),
            "translation_m_max": float(np.max(dt)),
            "rotation_deg_mean": float(np.mean(dr)),
            "rotation_deg_max": float(np.max(dr)),
        }
    landmarks = json.loads((gt_dir / "landmarks.json").read_text())
    xyz_gt = np.array([lm["xyz"] for lm in landmarks], dtype=np.float64).reshape(-1, 3)
    xyz = xyz_gt @ T_prep_gt[:3, :3].T + T_prep_gt[:3, 3]
    seq = Sequence.open(seq_folder)
    full = meta.get("cameras_full_resolution", {})
    rpe: dict[str, Any] = {}
    series: dict[str, Any] = {}
    for cam_name in cameras:
        if cam_name not in full:
            continue
        cam = CameraModel.from_json(full[cam_name])
        times = dict(zip(seq.frame_indices, seq.timestamps(cam_name), strict=True))
        obs = [
            {int(f): uv for f, uv in lm.get("pixels", {}).get(cam_name, {}).items()}
            for lm in landmarks
        ]
        per_track = {}
        for name, track in tracks.items():
            try:
                errs = landmark_errors(cam, track, xyz, obs, times)
            except ValueError as exc:
                per_track[name] = {"error": str(exc)}
                continue
            per_track[name] = {
                "rpe_px": _stats(errs.rpe),
                "jitter_px": _stats(errs.jitter),
            }
            if name == chosen:
                f, r, _ = _per_frame(errs.frame_idx, errs.rpe)
                series[cam_name] = {"frames": f, "rpe": r}
        rpe[cam_name] = per_track
    return {"pose_error": pose_errors, "landmark_rpe": rpe, "landmarks": len(landmarks)}, series


def evaluate_sequence(
    seq_folder: str | Path, prepared: PreparedSequence, cameras: list[str]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Metrics of one job's poses: (metrics JSON, per-frame series per camera for plots)."""
    seq_folder = Path(seq_folder)
    s = prepared.summary
    metrics: dict[str, Any] = {
        "strategy": prepared.strategy,
        "requested_strategy": s.get("requested_strategy"),
        "health": s.get("health"),
        "warnings": list(s.get("warnings", [])),
        "calibration": None if prepared.calibration is None else prepared.calibration.summary(),
    }
    clicked, series = clicks_rpe(prepared)
    if clicked:
        metrics["rpe"] = clicked
    if (seq_folder / "ground_truth" / "poses.csv").is_file():
        gt, gt_series = _ground_truth(seq_folder, prepared, cameras)
        metrics["ground_truth"] = gt
        series = series or gt_series
    return _finite(metrics), series


def plot_rpe_jitter(series: dict[str, Any], out_png: str | Path, title: str = "") -> Path | None:
    """RPE per frame (top) and jitter (bottom) per camera; None when there is nothing."""
    if not series:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_r, ax_j) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for cam, s in sorted(series.items()):
        f, r = np.asarray(s["frames"]), np.asarray(s["rpe"])
        ax_r.plot(f, r, marker=".", label=cam)
        if len(f) > 1:
            ax_j.plot(f[1:], np.abs(np.diff(r)), marker=".", label=cam)
    ax_r.set_ylabel("RPE (px)")
    ax_j.set_ylabel("jitter |ΔRPE| (px)")
    ax_j.set_xlabel("frame")
    ax_r.legend(fontsize=8)
    ax_r.grid(alpha=0.3)
    ax_j.grid(alpha=0.3)
    if title:
        ax_r.set_title(title)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out
