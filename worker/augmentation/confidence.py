"""Per-frame AR confidence: a bound (px) on the placed object's error in each camera.

The object is placed in the map; the map near it was made from the frame that first
covered it (the registered cloud keeps each voxel's first point, and the ego track is
fitted to it), so the object's pixel in frame i is off by what the relative pose of that
reference frame and frame i is off. The preparation's pose information
(:class:`~geometry.pose_uncertainty.PoseInformation`: fused's own J^T W J scaled by its
residuals, or a strategy's default model) gives that uncertainty; the bound is its 90 %
radius at the object's anchor (:func:`~geometry.pose_uncertainty.anchor_bound_px`), in
the image's pixels. The robustness matrix (``osdar-ar bench --matrix``) measures how often
the true error lies within it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel
from geometry.pose_uncertainty import PoseInformation, anchor_bound_px, anchor_pixel_jacobian
from geometry.poses import PoseTrack

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: The reference frame is the first whose base lies within this distance (m) of the object
#: (the registration keeps points up to about this range).
REFERENCE_RANGE_M = 100.0
#: Probability the bound is meant to hold with.
COVERAGE = 0.9


def reference_row(track: PoseTrack, p_obj: F64) -> int:
    """The track row whose map holds the object (module docstring)."""
    d = np.linalg.norm(track.T[:, :3, 3] - p_obj[None, :], axis=1)
    within = np.flatnonzero(d <= REFERENCE_RANGE_M)
    return int(within[0]) if len(within) else int(np.argmin(d))


def placement_bounds(
    track: PoseTrack,
    information: PoseInformation | None,
    cameras: dict[str, CameraModel],
    T_world_base: dict[str, dict[int, F64]],
    T_world_obj: F64,
    frames: list[int],
) -> dict[int, dict[str, float]]:
    """{frame: {camera: bound px}} where the object's anchor projects into the image.

    track : the prepared poses (its rows are the information's frames);
    T_world_base : per camera, frame -> pose at that camera's timestamp.
    Empty without information, or when it does not match the track.
    """
    if information is None or track.frame_idx is None:
        return {}
    if information.n_frames != len(track):
        log.warning(
            "pose information has %d frames, the track %d: no placement bounds",
            information.n_frames, len(track),
        )  # fmt: skip
        return {}
    rows = {int(f): k for k, f in enumerate(track.frame_idx)}
    p_obj = np.asarray(T_world_obj, dtype=np.float64)[:3, 3]
    r = reference_row(track, p_obj)
    T_r = track.T[r]
    out: dict[int, dict[str, float]] = {}
    for f in frames:
        k = rows.get(int(f))
        if k is None:
            continue
        cov = information.covariance(r, k)
        per: dict[str, float] = {}
        for name, cam in cameras.items():
            T_i = T_world_base.get(name, {}).get(int(f))
            if T_i is None:
                continue

            def project(p: F64, T: F64, cam: CameraModel = cam) -> F64:
                uv, _ = cam.project_world(p[None], T)
                return uv[0]

            def project_many(p: F64, T: F64, cam: CameraModel = cam) -> F64:
                return cam.project_world(p, T)[0]

            uv = project(p_obj, T_i)
            if not (np.all(np.isfinite(uv)) and cam.in_image(uv[None])[0]):
                continue
            J = anchor_pixel_jacobian(project, T_r, T_i, p_obj, project_many)
            per[name] = anchor_bound_px(J, cov, COVERAGE)
        if per:
            out[int(f)] = per
    return out
