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
report plot (:func:`plot_rpe_jitter`); the job runner calls it and :func:`plot_rpe_jitter`.

The paper's RPE per strategy (:func:`evaluate_strategies`, ``osdar-ar evaluate``)
---------------------------------------------------------------------------------
For every strategy, camera and landmark: the 3D calibration point is the point of the cloud
registered with THAT strategy's poses whose projections are nearest to the clicks
(:func:`~worker.preparation.calibration_point.calibration_point_from_clicks`, the paper's
rule made robust over frames; the cloud is every frame's points, searched at full density
near the click rays and around the point found, not only the voxel-filtered registered
cloud of every ``frame_step``-th frame); RPE_i is the distance between the click of
frame i and that point projected with frame i's pose at the camera's own timestamp;
J_i = |RPE_{i+1} - RPE_i| between consecutive frame counters. Clicks come from a file
(real data, formats in ``calibration_point.py`` / the README) or, on synthetic sequences,
from the ground truth: every landmark the lidar measured (a return within 0.25 m, true
poses), the true full-resolution pixel of that nearest return where its beam truly hit,
the point seen in both the image and the cloud (the merged cloud's calibration error
undone: the calibration point carries it, as on real data;
``click_target="return_recorded"`` clicks the return where the cloud puts it,
``"landmark"`` the landmark itself; optionally with Gaussian click noise) in the frames
where the landmark is in view and the point
``near``-``far`` m in front of the camera (default 30-80 m). Pixels are
at the camera's full resolution. Means and standard deviations pool every observation of
every landmark; ``landmark_mean`` is the mean over landmarks of their RPE means.

metrics.json keys (:func:`evaluate_strategies`):

- ``sequence``, ``frames``, ``cameras``, ``strategies``, ``clicks_source``
  ("file" | "ground_truth"), ``near_m``, ``far_m``, ``click_noise_px``, ``click_target``
  ("return" | "return_recorded" | "landmark", synthetic clicks), ``dense_radius_m``
  (the calibration point's full-density refinement radius, 0: the registered cloud only),
  ``lidar_corrections`` (the sensors whose preparation correction those points carry);
- ``rpe[camera][strategy]`` = {``rpe_mean``, ``rpe_std``, ``rpe_max``, ``jitter_mean``,
  ``jitter_std``, ``jitter_max``, ``n``, ``n_jitter``, ``landmark_mean``,
  ``landmarks`` {name: {same statistics, ``calibration_xyz``, ``frames``}}};
- ``true_errors[strategy]`` (synthetic only) = {``translation_m_mean``/``max``,
  ``rotation_deg_mean``/``max``, ``frame_to_frame_mm``, ``anchor_px`` {camera: RPE of
  the TRUE 3D landmarks under the strategy's poses: pixel error of a true anchor point}};
- ``preparation`` {strategy: {``seconds``, ``chosen``, ``warnings``}}; ``files``.

The per-frame CSV has one row per (camera, strategy, landmark, frame):
``camera,strategy,landmark,frame_idx,click_u,click_v,proj_u,proj_v,rpe_px,jitter_px``
(``jitter_px`` = |RPE - RPE of the previous frame counter|, empty for a run's first frame).
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
from typing import Any

import cv2
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial import cKDTree

from geometry.camera import CameraModel, load_cameras
from geometry.geodesy import WorldFrame
from geometry.poses import PoseTrack, reexpress
from worker.evaluation.landmark_error import landmark_errors
from worker.osdar.images import write_png
from worker.osdar.sequence import Sequence
from worker.preparation.artifact import PreparedSequence
from worker.preparation.calibration_point import (
    Clicks,
    ClicksError,
    calibration_point_from_clicks,
    camera_at_resolution,
    click_resolution,
    points_near_rays,
)
from worker.preparation.config import CalibrationConfig
from worker.preparation.frame_clouds import FrameClouds, move_per_sensor
from worker.preparation.lidar_alignment import corrections_from_summary
from worker.preparation.registration import dense_points

log = logging.getLogger(__name__)


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
    clicks = clicks_of(prepared)
    if clicks is not None or (seq_folder / "ground_truth" / "landmarks.json").is_file():
        # the paper's RPE for the chosen strategy and the references (ins, odometry)
        try:
            paper, _ = evaluate_strategies(
                seq_folder, tracks_from_prepared(prepared), world=prepared.world,
                cameras=cameras or None, clicks=clicks,
                lidar_corrections=corrections_from_summary(s.get("lidar_alignment")),
            )  # fmt: skip
            metrics["paper_rpe"] = paper["rpe"]
            metrics["landmarks_clicked"] = paper["landmarks_clicked"]
        except (ValueError, OSError) as exc:
            metrics["warnings"].append(f"evaluation: paper RPE not computed ({exc})")
    return _finite(metrics), series


def plot_rpe_jitter(series: dict[str, Any], out_png: str | Path, title: str = "") -> Path | None:
    """RPE per frame (top) and jitter (bottom) per camera; None when there is nothing."""
    if not series:
        return None

    matplotlib.use("Agg")

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


# ============================================================================ paper RPE
#: Landmarks evaluated at these distances ahead of the camera (m): where objects are placed.
DEFAULT_NEAR_M = 30.0
DEFAULT_FAR_M = 80.0
#: Radius (full-resolution px) of the calibration point's search around the clicks.
EVAL_SEARCH_RADIUS_PX = 60.0
#: A landmark is used when it has at least this many clicked frames in a camera.
MIN_VIEWS = 5
#: Radius (m) around the calibration point where every frame's points, at full density,
#: compete to refine it (calibration_point.py); 0: the registered cloud only (the paper).
DENSE_RADIUS_M = CalibrationConfig().dense_radius_m
#: Frame points farther than this from the base are not read for the refinement (m).
DENSE_MAX_RANGE_M = 120.0
#: Radius (m) of the calibration sphere drawn in the overlays.
SPHERE_RADIUS_M = 0.25
#: Synthetic clicks go to landmarks with a lidar return (true poses) within this distance
#: (m): the calibration sphere's radius, a point on the landmark's own object (a pole top's
#: rim is 0.12 m from its axis).
LIDAR_SUPPORT_M = SPHERE_RADIUS_M
#: How far :func:`nearest_returns` looks for a return (m).
SUPPORT_SEARCH_M = 2.0
#: What the synthetic operator clicks on a measured landmark: "return", the image point of
#: the lidar return nearest the landmark (the point seen in both the image and the cloud
#: that the paper's operator picks) where its beam truly hit: the merged cloud's
#: calibration error (``ground_truth/lidar_merge_errors.json``) undone, as an operator
#: clicking the physical feature sees it, so the RPE carries what is left of that error in
#: the cloud the calibration point is taken from; "return_recorded", the same return where
#: the merged cloud puts it (the click moves with the calibration error, which the measure
#: then does not see); "landmark", the landmark itself (a pole top: the RPE then carries
#: the landmark's distance to its nearest return, 0.1-0.2 m below or beside it on sparse
#: clouds, 5-20 px at 50-70 m on rgb_highres_center with perfect poses).
CLICK_TARGETS = ("return", "return_recorded", "landmark")


def _camera_times(seq: Any, camera: str) -> dict[int, float]:
    ts = seq.timestamps(camera)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


def full_resolution_cameras(seq: Any, cameras: list[str]) -> dict[str, Any]:
    """The sequence's cameras at their full (sensor) resolution: synthetic sequences carry
    them in ``ground_truth/meta.json``; otherwise the labels' intrinsics rescaled to the
    OSDaR23 full size (the identity on real data)."""

    meta_file = Path(seq.folder) / "ground_truth" / "meta.json"
    full = {}
    if meta_file.is_file():
        full = json.loads(meta_file.read_text()).get("cameras_full_resolution", {})
    loaded = load_cameras(seq.labels.raw, seq.cameras)
    out = {}
    for name in cameras:
        if name in full:
            out[name] = CameraModel.from_json(full[name])
        elif name in loaded:
            out[name] = camera_at_resolution(loaded[name], *click_resolution(loaded[name]))
    return out


def cloud_for_track(prepared: PreparedSequence, track: Any) -> np.ndarray:
    """The prepared cloud re-registered with another pose track (same frames).

    Each point was registered with the chosen strategy's pose of its frame; it is moved
    to ``track``'s pose of that frame: p' = T_track(f) T_chosen(f)^-1 p. Frames ``track``
    lacks keep their points where they are.
    """

    cloud = prepared.cloud
    if track is prepared.track:
        return cloud.xyz
    chosen: PoseTrack = prepared.track
    if chosen.frame_idx is None or track.frame_idx is None:
        raise ValueError("re-registering the cloud needs frame indices on both tracks")
    T_c = dict(zip(chosen.frame_idx.tolist(), chosen.T, strict=True))
    T_s = dict(zip(track.frame_idx.tolist(), track.T, strict=True))
    out = cloud.xyz.copy()
    for f in np.unique(cloud.frame_idx):
        f = int(f)
        if f not in T_c or f not in T_s:
            continue
        M = T_s[f] @ np.linalg.inv(T_c[f])
        sel = cloud.frame_idx == f
        out[sel] = cloud.xyz[sel] @ M[:3, :3].T + M[:3, 3]
    return out


def merge_errors_of(seq_folder: str | Path) -> dict[int, np.ndarray]:
    """sensor_index -> (4, 4) merge error E of a synthetic sequence (the generator placed
    sensor s's true base points p at ``E p`` in the merged cloud); ``{}`` when the
    sequence has none (merged without error, or not synthetic)."""
    f = Path(seq_folder) / "ground_truth" / "lidar_merge_errors.json"
    if not f.is_file():
        return {}
    return {
        int(k): np.asarray(v, dtype=np.float64).reshape(4, 4)
        for k, v in json.loads(f.read_text()).items()
    }


def _undo(clouds: Any, merge_errors: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """sensor_index -> (4, 4) taking the points ``clouds`` serves (their corrections
    applied, ``p = C E p_true``) back to the points' true positions: E^-1 C^-1."""
    corr = dict(getattr(clouds, "corrections", {}) or {})
    out = {}
    for s in set(corr) | set(merge_errors):
        M = np.linalg.inv(corr.get(s, np.eye(4)))
        if s in merge_errors:
            M = np.linalg.inv(merge_errors[s]) @ M
        out[int(s)] = M
    return out


def synthetic_clicks(
    seq_folder: str | Path,
    cameras: list[str],
    *,
    near: float = DEFAULT_NEAR_M,
    far: float = DEFAULT_FAR_M,
    click_noise_px: float = 0.0,
    seed: int = 0,
    max_landmarks: int = 8,
    min_views: int = MIN_VIEWS,
    lidar_support_m: float = LIDAR_SUPPORT_M,
    clouds: Any = None,
    click_target: str = "return",
) -> list[Any]:
    """Clicks from the ground truth of a synthetic sequence: one :class:`Clicks` per
    landmark, the true full-resolution pixel of the point clicked (see below) in every
    frame where the landmark is in view and the point ``near``-``far`` m in front of the
    camera (true pose at the camera's timestamp), plus N(0, noise^2).

    Only landmarks the lidar measured are clicked: a return of some frame (true poses, full
    density) within ``lidar_support_m`` of the landmark (0: every landmark, each clicked
    at itself; when none in view is measured, the unmeasured ones are clicked with a
    warning, at their nearest return within :data:`SUPPORT_SEARCH_M` where there is one).
    The paper's operator clicks a landmark seen in both the image and the cloud; a pole top
    no beam ever hit has no calibration point, only points of other surfaces near its rays,
    and its RPE with the true poses is tens of pixels (:func:`nearest_returns`). The point
    clicked is, with ``click_target="return"``, the landmark's nearest return where its
    beam truly hit (the merge's calibration error of its sensor undone with the ground
    truth, :func:`merge_errors_of`; its range noise, millimetres along a ray nearly the
    camera's, stays): a real operator clicks the physical feature, and the calibration
    point, a point of the merged cloud, carries the cloud's calibration error into the
    RPE; with ``"return_recorded"`` the same return as the merged cloud holds it (the
    click moves with the error); with ``"landmark"`` the landmark itself
    (:data:`CLICK_TARGETS`). ``clouds``: the sequence's
    :class:`~worker.preparation.frame_clouds.FrameClouds` if already read (its
    corrections, if any, are undone for the search)."""

    folder = Path(seq_folder)
    gt = folder / "ground_truth"
    seq = Sequence.open(folder)
    dense = gt / "poses_dense.csv"
    truth = PoseTrack.from_csv(dense if dense.is_file() else gt / "poses.csv")
    cams = full_resolution_cameras(seq, cameras)
    landmarks = json.loads((gt / "landmarks.json").read_text())
    if click_target not in CLICK_TARGETS:
        raise ValueError(f"click_target {click_target!r}: one of {', '.join(CLICK_TARGETS)}")
    measured = {lm["id"] for lm in landmarks}
    target: dict[str, np.ndarray] = {}  # landmark -> the 3D point clicked, if not itself
    if lidar_support_m > 0 and landmarks:
        xyz = np.array([lm["xyz"] for lm in landmarks], dtype=np.float64).reshape(-1, 3)
        clouds = clouds if clouds is not None else _frame_clouds(seq)
        errors = merge_errors_of(folder) if click_target != "return_recorded" else {}
        d, p_ret = nearest_returns(clouds, truth, xyz, undo=_undo(clouds, errors))
        measured = {lm["id"] for lm, di in zip(landmarks, d, strict=True) if di <= lidar_support_m}
        if click_target != "landmark":  # the unmeasured ones too, for the fallback below
            target = {lm["id"]: p_ret[i] for i, lm in enumerate(landmarks) if np.isfinite(d[i])}
    rng = np.random.default_rng(seed)
    scored = []
    for lm in landmarks:
        xyz = target.get(lm["id"], np.asarray(lm["xyz"], dtype=np.float64))
        uv: dict[str, dict[int, np.ndarray]] = {}
        for name, cam in cams.items():
            times = _camera_times(seq, name)
            pix = lm.get("pixels", {}).get(name, {})
            for f_txt, p in sorted(pix.items(), key=lambda kv: int(kv[0])):
                f = int(f_txt)
                if p is None or f not in times:  # the landmark out of view or occluded
                    continue
                T = truth.interpolate(np.array([times[f]]), max_extrapolation_s=0.1)[0]
                T_opt_world = np.linalg.inv(T @ cam.T_base_opt)
                depth = float(T_opt_world[2, :3] @ xyz + T_opt_world[2, 3])
                if not near <= depth <= far:
                    continue
                click = np.asarray(p, dtype=np.float64)
                if lm["id"] in target:
                    click, ok = cam.project_world(xyz, T)
                    if not (ok[0] and cam.in_image(click)[0]):
                        continue
                    click = click[0]
                if click_noise_px > 0:
                    click = click + rng.normal(0.0, click_noise_px, 2)
                uv.setdefault(name, {})[f] = click
            if len(uv.get(name, {})) < min_views:
                uv.pop(name, None)
        if uv:
            res = {n: (cams[n].width, cams[n].height) for n in uv}
            scored.append((sum(len(v) for v in uv.values()), Clicks(lm["id"], uv, res)))
    scored.sort(key=lambda x: -x[0])
    kept = [(n, c) for n, c in scored if c.landmark in measured]
    if scored and not kept:  # a few frames of a sparse cloud: say so, click them anyway
        log.warning(
            "%s: no landmark in view has a lidar return within %.2f m; clicking the "
            "unmeasured ones (%s)", seq.name, lidar_support_m,
            f"at their nearest return within {SUPPORT_SEARCH_M:.1f} m, where one is"
            if target else "their RPE includes the distance to the nearest return",
        )  # fmt: skip
        kept = scored
    return [c for _, c in kept[:max_landmarks]]


def nearest_returns(
    clouds: Any, track: Any, xyz_world: np.ndarray, undo: dict[int, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The lidar return of any frame of ``clouds`` (full density as read, registered with
    ``track``) nearest each landmark (m, 3) world: (distance (m,) m, inf where none is
    within :data:`SUPPORT_SEARCH_M`; the return (m, 3) float64 world, NaN there).

    ``undo``: sensor_index -> (4, 4) applied to that sensor's base points first (``p' = R
    p + t``; :func:`_undo` gives the one to the points' true positions)."""
    best = np.full(len(xyz_world), np.inf)
    p_world = np.full((len(xyz_world), 3), np.nan)
    frames = clouds.frames
    if not frames or not len(xyz_world):
        return best, p_world
    T_all = track.interpolate(np.array([clouds.frame_times[f] for f in frames]))
    for f, T in zip(frames, T_all, strict=True):
        lm_base = (xyz_world - T[:3, 3]) @ T[:3, :3]  # the landmarks in the frame's base
        fc = clouds.get(f)
        p_base = fc.p_base32
        if undo:
            p_base = fc.p_base
            move_per_sensor(p_base, fc.sensor_index, undo)
        # the points within reach of some landmark, then each landmark's nearest among them
        d, _ = cKDTree(lm_base).query(p_base, distance_upper_bound=SUPPORT_SEARCH_M)
        near = np.flatnonzero(np.isfinite(d))
        if not len(near):
            continue
        p_near = p_base[near].astype(np.float64)
        dl, j = cKDTree(p_near).query(lm_base, distance_upper_bound=SUPPORT_SEARCH_M)
        better = np.flatnonzero(np.isfinite(dl) & (dl < best))
        best[better] = dl[better]
        p_world[better] = p_near[j[better]] @ T[:3, :3].T + T[:3, 3]
    return best, p_world


def rpe_from_clicks(
    xyz_world: np.ndarray,
    track: Any,
    cameras: dict[str, Any],
    camera_times: dict[str, dict[int, float]],
    clicks: Any,
    search_radius_px: float = EVAL_SEARCH_RADIUS_PX,
    dense: Any = None,
    dense_radius_m: float = 0.0,
    dense_rays: Any = None,
) -> dict[str, dict[str, Any]]:
    """RPE per frame of one landmark in each clicked camera (the paper's definition).

    Per camera the calibration point is chosen from that camera's clicks alone, refined
    among the full-density points ``dense(centre, radius)`` within ``dense_radius_m`` when
    given, and found among every frame's full-density points near the click rays too when
    ``dense_rays`` is given
    (:func:`~worker.preparation.calibration_point.calibration_point_from_clicks`). Returns
    {camera: {"xyz", "frames", "rpe", "click", "projected", "warnings"}} (pixels at the
    clicks' resolution; frames whose projection fails are left out).
    """

    cfg = CalibrationConfig(search_radius_px=search_radius_px, dense_radius_m=dense_radius_m)
    out: dict[str, dict[str, Any]] = {}
    for cam_name, frames in sorted(clicks.uv.items()):
        if cam_name not in cameras:
            continue
        one = Clicks(clicks.landmark, {cam_name: frames}, dict(clicks.resolution))
        cal = calibration_point_from_clicks(
            xyz_world, track, {cam_name: cameras[cam_name]}, camera_times, one, cfg, dense,
            dense_rays,
        )  # fmt: skip
        obs = [o for o in cal.observations if o["residual_px"] is not None]
        out[cam_name] = {
            "xyz": None if cal.xyz is None else [float(v) for v in cal.xyz],
            "frames": [int(o["frame_idx"]) for o in obs],
            "rpe": [float(o["residual_px"]) for o in obs],
            "click": [o["click"] for o in obs],
            "projected": [o["projected"] for o in obs],
            "warnings": list(cal.warnings),
            "refined": cal.refined,
        }
    return out


def _jitter(frames: list[int], rpe: list[float]) -> list[float | None]:
    """|RPE_i - RPE_{i-1}| per frame (None for the first frame of a consecutive run)."""
    out: list[float | None] = [None] * len(frames)
    for k in range(1, len(frames)):
        if frames[k] == frames[k - 1] + 1:
            out[k] = abs(rpe[k] - rpe[k - 1])
    return out


def _rpe_stats(rpe: list[float], jit: list[float]) -> dict[str, Any]:
    r, j = np.asarray(rpe, dtype=np.float64), np.asarray(jit, dtype=np.float64)
    return {
        "rpe_mean": float(r.mean()) if len(r) else None,
        "rpe_std": float(r.std()) if len(r) else None,
        "rpe_max": float(r.max()) if len(r) else None,
        "jitter_mean": float(j.mean()) if len(j) else None,
        "jitter_std": float(j.std()) if len(j) else None,
        "jitter_max": float(j.max()) if len(j) else None,
        "n": len(r),
        "n_jitter": len(j),
    }


def summarize_rpe(per_landmark: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Pooled statistics over landmarks ({landmark: rpe_from_clicks()[camera]})."""
    all_r: list[float] = []
    all_j: list[float] = []
    lms: dict[str, Any] = {}
    for name, s in per_landmark.items():
        jit = [x for x in _jitter(s["frames"], s["rpe"]) if x is not None]
        all_r += s["rpe"]
        all_j += jit
        lms[name] = {
            **_rpe_stats(s["rpe"], jit),
            "calibration_xyz": s["xyz"],
            "frames": [min(s["frames"]), max(s["frames"])] if s["frames"] else None,
        }
    means = [v["rpe_mean"] for v in lms.values() if v["rpe_mean"] is not None]
    return {
        **_rpe_stats(all_r, all_j),
        "landmark_mean": float(np.mean(means)) if means else None,
        "landmarks": lms,
    }


def _true_errors(
    seq: Any, track: Any, world: Any, cams: dict[str, Any], clicks: list[Any]
) -> dict[str, Any]:
    """True pose errors and the pixel error of the true landmarks (synthetic data)."""

    gt_dir = Path(seq.folder) / "ground_truth"
    truth = PoseTrack.from_csv(gt_dir / "poses.csv")
    T_prep_gt = np.eye(4)
    if (gt_dir / "world.json").is_file():
        gt_world = WorldFrame.from_json(json.loads((gt_dir / "world.json").read_text()))
        truth = reexpress(truth, gt_world, world)
        T_prep_gt = world.T_world_other(gt_world)
    out: dict[str, Any] = {}
    try:
        dt, dr = track.relative_errors(truth, max_extrapolation_s=0.05)
        rel = np.linalg.norm(
            np.diff(track.T[:, :3, 3] - _at(truth, track)[:, :3, 3], axis=0), axis=1
        )
        out.update(
            translation_m_mean=float(dt.mean()),
            translation_m_max=float(dt.max()),
            rotation_deg_mean=float(dr.mean()),
            rotation_deg_max=float(dr.max()),
            frame_to_frame_mm=float(rel.mean() * 1e3) if len(rel) else None,
        )
    except ValueError as exc:
        out["error"] = str(exc)
    landmarks = {lm["id"]: lm for lm in json.loads((gt_dir / "landmarks.json").read_text())}
    anchor = {}
    for cam_name, cam in cams.items():
        times = _camera_times(seq, cam_name)
        use = [c for c in clicks if cam_name in c.uv and c.landmark in landmarks]
        if not use:
            continue
        xyz = np.array([landmarks[c.landmark]["xyz"] for c in use], dtype=np.float64)
        xyz = xyz @ T_prep_gt[:3, :3].T + T_prep_gt[:3, 3]
        obs = [
            {
                int(f): uv
                for f, uv in landmarks[c.landmark]["pixels"][cam_name].items()
                if int(f) in c.uv[cam_name]
            }
            for c in use
        ]
        try:
            errs = landmark_errors(cam, track, xyz, obs, times)
        except ValueError:
            continue
        anchor[cam_name] = {k: v for k, v in errs.summary().items()}
    out["anchor_px"] = anchor
    return out


def _frame_clouds(seq: Any) -> Any:
    """The sequence's frame clouds, full density, read once for every strategy."""

    return FrameClouds(seq, max_range=DENSE_MAX_RANGE_M)


def _rays(clouds: Any, track: Any) -> Any:
    """The calibration point's ``dense_rays``: every frame's full-density points near the
    click rays, registered with ``track`` at the frame's lidar timestamp."""
    frames = clouds.frames
    T_all = track.interpolate(np.array([clouds.frame_times[f] for f in frames]))

    def frame_points() -> Any:
        for f, T in zip(frames, T_all, strict=True):
            yield T, clouds.get(f).p_base32

    return points_near_rays(frame_points)


def _at(truth: Any, track: Any) -> np.ndarray:
    return truth.interpolate(track.timestamps, max_extrapolation_s=0.05)


def _clicks(
    folder: Path,
    seq: Any,
    clicks: list[Any] | None,
    cameras: list[str] | None,
    *,
    has_gt: bool,
    near: float,
    far: float,
    click_noise_px: float,
    seed: int,
    max_landmarks: int,
    clouds: Any = None,
    click_target: str = "return",
) -> tuple[list[Any], str]:
    """The clicks (given, or synthetic from the ground truth) and their source; every
    camera they name must be in the sequence."""
    source = "file"
    if clicks is None:
        if not has_gt:
            raise ValueError(f"{folder}: no clicks given and no ground_truth/ to click from")
        source = "ground_truth"
        cams_wanted = cameras or list(seq.cameras)
        clicks = synthetic_clicks(
            folder, cams_wanted, near=near, far=far, click_noise_px=click_noise_px,
            seed=seed, max_landmarks=max_landmarks, clouds=clouds, click_target=click_target,
        )  # fmt: skip
    missing = sorted({c for cl in clicks for c in cl.uv} - set(seq.cameras))
    if missing:
        raise ClicksError(
            f"clicks name camera(s) {', '.join(missing)} that the sequence lacks "
            f"(it has: {', '.join(seq.cameras)})"
        )
    return clicks, source


def _frame_rows(
    strategy: str, cam_name: str, landmark: str, s: dict[str, Any]
) -> list[dict[str, Any]]:
    """The per-frame rows (ROW_FIELDS) of one landmark's RPE series in one camera."""
    jit = _jitter(s["frames"], s["rpe"])
    return [
        {
            "camera": cam_name,
            "strategy": strategy,
            "landmark": landmark,
            "frame_idx": f,
            "click_u": s["click"][k][0],
            "click_v": s["click"][k][1],
            "proj_u": s["projected"][k][0],
            "proj_v": s["projected"][k][1],
            "rpe_px": s["rpe"][k],
            "jitter_px": jit[k],
        }
        for k, f in enumerate(s["frames"])
    ]


def _strategy_rpe(
    strategy: str,
    track: Any,
    xyz: np.ndarray,
    cams: dict[str, Any],
    times: dict[str, Any],
    clicks: list[Any],
    dense: Any,
    dense_radius_m: float,
    dense_rays: Any = None,
) -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    """One strategy's RPE series: {camera: {landmark: series}} and the per-frame rows."""
    per_cam: dict[str, dict[str, Any]] = {c: {} for c in cams}
    rows: list[dict[str, Any]] = []
    for cl in clicks:
        for cam_name, s in rpe_from_clicks(
            xyz, track, cams, times, cl, dense=dense, dense_radius_m=dense_radius_m,
            dense_rays=dense_rays,
        ).items():  # fmt: skip
            per_cam[cam_name][cl.landmark] = s
            rows += _frame_rows(strategy, cam_name, cl.landmark, s)
    return per_cam, rows


def evaluate_strategies(
    seq_folder: str | Path,
    tracks: dict[str, tuple[Any, np.ndarray]],
    *,
    world: Any,
    cameras: list[str] | None = None,
    clicks: list[Any] | None = None,
    near: float = DEFAULT_NEAR_M,
    far: float = DEFAULT_FAR_M,
    click_noise_px: float = 0.0,
    seed: int = 0,
    max_landmarks: int = 8,
    preparation: dict[str, Any] | None = None,
    dense_radius_m: float = DENSE_RADIUS_M,
    click_target: str = "return",
    lidar_corrections: dict[int, np.ndarray] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The paper's RPE and jitter per camera and strategy (module docstring).

    Parameters
    ----------
    seq_folder : the sequence (with ``ground_truth/`` for synthetic clicks / true errors).
    tracks : {strategy: (T_world_base track, its registered cloud (n, 3) world)}.
    world : the world frame the tracks are in (the preparation's).
    cameras : cameras to evaluate (default: the clicked ones, else every camera).
    clicks : landmarks' clicks (None: from the ground truth; then it must exist).
    click_target : what the synthetic clicks hit (:data:`CLICK_TARGETS`).
    preparation : {strategy: {...}} copied into the metrics.
    dense_radius_m : refine each calibration point among the full-density points of every
        frame within this radius (m), registered with the strategy's poses; 0: the paper's
        point of the given cloud only.
    lidar_corrections : sensor_index -> (4, 4), the preparation's per-lidar corrections
        (:func:`~worker.preparation.lidar_alignment.corrections_from_summary`), applied to
        those full-density points as the preparation applied them to the clouds it
        registered (the tracks' clouds); None: the points as recorded.

    Returns
    -------
    (metrics, per-frame rows).
    """

    folder = Path(seq_folder)
    seq = Sequence.open(folder)
    has_gt = (folder / "ground_truth" / "landmarks.json").is_file()
    clouds = _frame_clouds(seq) if dense_radius_m > 0 or (clicks is None and has_gt) else None
    if clouds is not None and lidar_corrections:  # the synthetic clicks undo them
        clouds.set_corrections(lidar_corrections)
    clicks, source = _clicks(
        folder, seq, clicks, cameras, has_gt=has_gt, near=near, far=far,
        click_noise_px=click_noise_px, seed=seed, max_landmarks=max_landmarks, clouds=clouds,
        click_target=click_target,
    )  # fmt: skip
    if cameras is None:
        cameras = sorted({c for cl in clicks for c in cl.uv})
    cams = full_resolution_cameras(seq, cameras)
    times = {c: _camera_times(seq, c) for c in cams}
    metrics: dict[str, Any] = {
        "sequence": seq.name,
        "frames": len(seq.frame_indices),
        "cameras": list(cams),
        "strategies": list(tracks),
        "clicks_source": source,
        "landmarks_clicked": [c.landmark for c in clicks],
        "near_m": near if source == "ground_truth" else None,
        "far_m": far if source == "ground_truth" else None,
        "click_noise_px": click_noise_px if source == "ground_truth" else None,
        "click_target": click_target if source == "ground_truth" else None,
        "dense_radius_m": dense_radius_m,
        "lidar_corrections": sorted(int(k) for k in (lidar_corrections or {})),
        "rpe": {},
    }

    rows: list[dict[str, Any]] = []
    clouds = clouds if dense_radius_m > 0 else None
    for strategy, (track, xyz) in tracks.items():
        dense = rays = None
        if clouds is not None:
            dense, rays = dense_points(seq, track, clouds), _rays(clouds, track)
        per_cam, strategy_rows = _strategy_rpe(
            strategy, track, xyz, cams, times, clicks, dense, dense_radius_m, rays
        )
        rows += strategy_rows
        for cam_name, lms in per_cam.items():
            metrics["rpe"].setdefault(cam_name, {})[strategy] = summarize_rpe(lms)
    if has_gt:
        metrics["true_errors"] = {
            s: _true_errors(seq, tr, world, cams, clicks) for s, (tr, _) in tracks.items()
        }
    if preparation:
        metrics["preparation"] = preparation
    return _finite(metrics), rows


# ---------------------------------------------------------------------------- outputs
ROW_FIELDS = (
    "camera", "strategy", "landmark", "frame_idx", "click_u", "click_v", "proj_u", "proj_v",
    "rpe_px", "jitter_px",
)  # fmt: skip


def write_rows_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=ROW_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r[k]) for k in ROW_FIELDS})
    return path


def plot_rpe_by_strategy(
    rows: list[dict[str, Any]], out_png: str | Path, title: str = ""
) -> Path | None:
    """RPE over frames (mean over landmarks per frame), one line per strategy, one panel
    per camera."""
    if not rows:
        return None

    matplotlib.use("Agg")

    cams = sorted({r["camera"] for r in rows})
    fig, axes = plt.subplots(len(cams), 1, figsize=(8, 3 * len(cams)), sharex=True, squeeze=False)
    for ax, cam in zip(axes[:, 0], cams, strict=True):
        for strat in dict.fromkeys(r["strategy"] for r in rows):
            sel = [r for r in rows if r["camera"] == cam and r["strategy"] == strat]
            if not sel:
                continue
            frames = sorted({r["frame_idx"] for r in sel})
            mean = [np.mean([r["rpe_px"] for r in sel if r["frame_idx"] == f]) for f in frames]
            ax.plot(frames, mean, marker=".", ms=3, label=strat)
        ax.set_ylabel(f"RPE (px)\n{cam}")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[-1, 0].set_xlabel("frame")
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


_COLORS = [(255, 64, 64), (64, 200, 64), (64, 128, 255), (255, 200, 0), (255, 0, 255)]


def render_overlays(
    seq_folder: str | Path,
    rows: list[dict[str, Any]],
    metrics: dict[str, Any],
    tracks: dict[str, tuple[Any, np.ndarray]],
    out_dir: str | Path,
    frames: list[int] | None = None,
    landmark: str | None = None,
    radius_m: float = SPHERE_RADIUS_M,
) -> list[Path]:
    """The calibration sphere drawn into camera frames: per strategy a circle of the
    projected radius of a ``radius_m`` sphere at that strategy's calibration point, and the
    click as a white cross. Default frames: first, middle and last clicked frame of the
    first landmark."""

    seq = Sequence.open(seq_folder)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    strategies = list(tracks)
    for cam_name, per_strat in (metrics.get("rpe") or {}).items():
        lm = landmark or next(
            (n for s in per_strat.values() for n in (s.get("landmarks") or {})), None
        )
        if lm is None:
            continue
        sel = [r for r in rows if r["camera"] == cam_name and r["landmark"] == lm]
        clicked = sorted({r["frame_idx"] for r in sel})
        if not clicked:
            continue
        use = frames or sorted({clicked[0], clicked[len(clicked) // 2], clicked[-1]})
        cam_full = full_resolution_cameras(seq, [cam_name])[cam_name]
        times = _camera_times(seq, cam_name)
        for f in use:
            if f not in times:
                continue
            img = seq.image(f, cam_name)
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            img = np.ascontiguousarray(img[:, :, :3])
            s = img.shape[1] / cam_full.width
            thick = max(1, round(2 * s * 4))
            for k, strat in enumerate(strategies):
                xyz = ((per_strat.get(strat) or {}).get("landmarks") or {}).get(lm, {})
                xyz = xyz.get("calibration_xyz")
                if xyz is None:
                    continue
                track = tracks[strat][0]
                T = track.interpolate(np.array([times[f]]), max_extrapolation_s=0.2)[0]
                p = np.asarray(xyz, dtype=np.float64)[None]
                uv, ok = cam_full.project_world(p, T)
                if not ok[0]:
                    continue
                T_opt_world = np.linalg.inv(T @ cam_full.T_base_opt)
                depth = float(T_opt_world[2, :3] @ p[0] + T_opt_world[2, 3])
                r_px = max(2.0, cam_full.fx * radius_m / max(depth, 1e-3) * s)
                c = (uv[0] + 0.5) * s - 0.5
                cv2.circle(
                    img, (round(c[0] * 16), round(c[1] * 16)), round(r_px * 16),
                    _COLORS[k % len(_COLORS)], thick, cv2.LINE_AA, 4,
                )  # fmt: skip
                cv2.putText(
                    img, strat, (round(c[0] + r_px + 3), round(c[1] + 4 * (k - 1) * thick + 4)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.3 * max(1.0, 4 * s), _COLORS[k % len(_COLORS)],
                    1, cv2.LINE_AA,
                )  # fmt: skip
            click = next((r for r in sel if r["frame_idx"] == f), None)
            if click is not None:
                c = (np.array([click["click_u"], click["click_v"]]) + 0.5) * s - 0.5
                cv2.drawMarker(
                    img, (round(c[0]), round(c[1])), (255, 255, 255), cv2.MARKER_CROSS,
                    max(6, round(24 * s)), 1, cv2.LINE_AA,
                )  # fmt: skip
            path = out_dir / f"overlay_{cam_name}_{f:03d}.png"
            write_png(path, img)
            written.append(path)
    return written


def tracks_from_prepared(
    prepared: PreparedSequence, references: bool = True
) -> dict[str, tuple[Any, np.ndarray]]:
    """{strategy: (track, cloud)}: the chosen strategy with its own registered cloud and,
    with ``references``, the raw INS and odometry tracks with the same cloud re-registered
    with their poses (:func:`cloud_for_track`)."""
    chosen = prepared.strategy or "chosen"
    out = {chosen: (prepared.track, prepared.cloud.xyz)}
    if references:
        for name, track in prepared.references.items():
            if name not in out:
                try:
                    out[name] = (track, cloud_for_track(prepared, track))
                except ValueError as exc:
                    log.warning("reference %s not evaluated: %s", name, exc)
    return out


def clicks_of(prepared: PreparedSequence) -> list[Any] | None:
    """The clicks the preparation used (from its calibration point), or None."""

    cal = prepared.calibration
    if cal is None or cal.mode != "clicks" or not cal.observations:
        return None
    uv: dict[str, dict[int, np.ndarray]] = {}
    for o in cal.observations:
        uv.setdefault(o["camera"], {})[int(o["frame_idx"])] = np.asarray(o["click"], float)
    return [Clicks(cal.landmark, uv, dict(cal.resolution))]
