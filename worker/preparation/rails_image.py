"""Rail-head candidates from camera segmentation (the paper's path).

Per processed frame and camera: the ONNX model labels the image; the corridor points
within ``range`` metres ahead of that frame's camera are projected into it with the pose
at the camera's own timestamp (real intrinsics and distortion) and vote rail / not rail.
A point is labelled rail when most of its votes are rail. The labels smear over the
ballast right beside and behind a rail (a pixel is wider than a rail head beyond a few
metres), so the rail-head *tops* are then picked among the labelled points: highest
labelled point of a 0.1 m cell, standing 0.12-0.32 m above the local ground.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from geometry.camera import load_cameras
from geometry.poses import PoseTrack
from geometry.transforms import invert_T, transform_points
from worker.preparation.rails_geometric import RidgeParams
from worker.preparation.registration import RegisteredCloud
from worker.preparation.segmentation import SegmentationModel

if TYPE_CHECKING:
    from worker.osdar.sequence import Sequence

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def _pick_cameras(seq: Sequence, wanted: list[str] | None) -> list[str]:
    cams = seq.cameras
    if wanted:
        missing = [c for c in wanted if c not in cams]
        if missing:
            raise ValueError(f"cameras without images in {seq.name}: {missing}")
        return list(wanted)
    for pref in ("rgb_center", "rgb_highres_center"):
        if pref in cams:
            return [pref]
    return cams[:1]


def _top_of_labelled(
    p_world: F64, labelled: NDArray[np.bool_], params: RidgeParams
) -> NDArray[np.bool_]:
    """Labelled points at the top of their cell and above the local ground (sparse cells)."""
    c = params.cell
    ij = np.floor(p_world[:, :2] / c).astype(np.int64)
    # ground: lowest point of any kind in a coarse neighbourhood (0.5 m cells, 3 x 3)
    g = 0.5
    gij = np.floor(p_world[:, :2] / g).astype(np.int64)
    gkey = gij[:, 0] * 1_000_003 + gij[:, 1]
    uk, inv = np.unique(gkey, return_inverse=True)
    gmin = np.full(len(uk), np.inf)
    np.minimum.at(gmin, inv, p_world[:, 2])
    ground = np.full(len(p_world), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            k = (gij[:, 0] + di) * 1_000_003 + (gij[:, 1] + dj)
            pos = np.clip(np.searchsorted(uk, k), 0, len(uk) - 1)
            hit = uk[pos] == k
            ground = np.where(hit, np.minimum(ground, gmin[pos]), ground)
    idx = np.flatnonzero(labelled)
    out = np.zeros(len(p_world), bool)
    if len(idx) == 0:
        return out
    key = ij[idx, 0] * 1_000_003 + ij[idx, 1]
    uk2, inv2 = np.unique(key, return_inverse=True)
    cmax = np.full(len(uk2), -np.inf)
    np.maximum.at(cmax, inv2, p_world[idx, 2])
    z = p_world[idx, 2]
    h = cmax[inv2] - ground[idx]
    ok = (z >= cmax[inv2] - params.top_band) & (h >= 0.12) & (h <= 0.32)
    out[idx[ok]] = True
    return out


def image_rail_candidates(
    cloud: RegisteredCloud,
    trajectory: PoseTrack,
    seq: Sequence,
    options: dict[str, Any],
    ridge: RidgeParams | None = None,
) -> tuple[NDArray[np.bool_], dict[str, float], list[str]]:
    """Flags of the points of ``cloud`` (a corridor) that are rail-head tops per the images.

    Options: ``model`` (SegmentationModel or its config), ``cameras`` (list, default
    rgb_center), ``frame_stride`` (default: every frame up to ``max_frames`` = 25),
    ``range`` (min, max metres ahead of the camera, default (3, 45)), ``min_rail_vote``
    (fraction of a point's votes, default 0.5).

    Returns
    -------
    (n,) bool flags, metrics, warnings.
    """
    ridge = ridge or RidgeParams()
    model = SegmentationModel.from_config(options["model"])
    cam_names = _pick_cameras(seq, options.get("cameras"))
    cams = load_cameras(seq.labels.raw, cam_names)
    frames = list(seq.frame_indices)
    max_frames = int(options.get("max_frames", 25))
    stride = int(options.get("frame_stride", max(1, int(np.ceil(len(frames) / max_frames)))))
    frames = frames[::stride]
    r_min, r_max = options.get("range", (3.0, 45.0))
    min_vote = float(options.get("min_rail_vote", 0.5))
    p = np.asarray(cloud.xyz, dtype=np.float64)
    votes = np.zeros(len(p), np.int32)
    rail_votes = np.zeros(len(p), np.int32)
    warnings: list[str] = []
    n_img = 0
    tree = cKDTree(p[:, :2])
    rail_px = 0.0
    for name in cam_names:
        ts_all = dict(zip(seq.frame_indices, seq.timestamps(name), strict=True))
        for f in frames:
            t = ts_all.get(f, np.nan)
            if not np.isfinite(t):
                continue
            try:
                T_world_base = trajectory.interpolate(np.array([t]))[0]
            except ValueError:
                continue
            if not np.all(np.isfinite(T_world_base)):
                continue
            img = seq.image(f, name)
            cam = cams[name]
            if img.shape[1] != cam.width:
                cam = cam.scaled(img.shape[1] / cam.width)
            mask = model.rail_mask(img)
            n_img += 1
            rail_px += float(mask.mean())
            idx = np.asarray(tree.query_ball_point(T_world_base[:2, 3], r=r_max), np.int64)
            if len(idx) == 0:
                continue
            p_base = transform_points(invert_T(T_world_base), p[idx])
            near = p_base[:, 0] >= r_min
            idx, p_base = idx[near], p_base[near]
            uv, valid = cam.project(p_base)
            valid &= cam.in_image(uv)
            idx, uv = idx[valid], uv[valid]
            u = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, mask.shape[1] - 1)
            v = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, mask.shape[0] - 1)
            votes[idx] += 1
            rail_votes[idx] += mask[v, u]
    metrics = {
        "image_frames": float(n_img),
        "image_rail_pixel_fraction": rail_px / max(n_img, 1),
    }
    if n_img == 0:
        warnings.append("image backend: no camera frame could be segmented")
        return np.zeros(len(p), bool), metrics, warnings
    with np.errstate(invalid="ignore", divide="ignore"):
        labelled = (votes > 0) & (rail_votes >= min_vote * np.maximum(votes, 1))
    flags = _top_of_labelled(p, labelled, ridge)
    metrics["image_labelled_points"] = float(labelled.sum())
    log.info(
        "image rails: %d frames, %d points labelled rail, %d rail-head tops",
        n_img,
        int(labelled.sum()),
        int(flags.sum()),
    )
    return flags, metrics, warnings
