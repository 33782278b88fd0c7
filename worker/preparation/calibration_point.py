"""The calibration point: the 3D point of the cloud whose projection is nearest to the clicks.

OSDaR-AR defines it as "the point of the cloud whose projection is nearest to the clicked
position" of a landmark (RPE and jitter are then measured against the clicks, see
OSDAR23.md). Here the same definition is made robust over frames: every cloud point near a
click is projected into every clicked view (camera pose = T_world_base interpolated at the
camera's own timestamp @ T_base_opt) and the point minimising the truncated sum

    cost(p) = sum over clicked views k of min(||uv_k(p) - click_k||^2, r^2)

(r = ``search_radius_px``) wins; with one click it is exactly the paper's definition.
Candidates are the points whose rays lie within about r of a click in a few seed views
spread over the sequence. Per-view residuals are reported.

The registered cloud is voxel-filtered and uses every other frame: its nearest point to a
pole top can be a voxel or a lidar beam gap away from the top, which costs 3-4 px at
4112 px even with perfect poses. So the point found there is then refined among all the
points of all the frames within ``dense_radius_m`` of it, at full density (the same cost;
still a point of the lidar cloud, as in the paper). On the synthetic fire_site this takes
the RPE with true poses from 4.0 to 0.9 px on rgb_highres_center.

A small landmark far away (a pole top at 60-75 m in a 0.3-density cloud) may be hit by a
beam in only a few frames, none of them in the registered cloud: its nearest point there is
on another surface metres away, and refining around that one cannot reach the landmark
(station, 60 frames: a point 13 m off, 50 px with the true poses). With ``dense_rays``
every frame's full-density points near the click rays of the two outermost seed views
compete from the start (:func:`points_near_rays`; the same cloud, read at full density):
there 50 -> 14 px with the true poses; what is left is where the beams hit the pole.

Without clicks, an automatic mode proposes pole tops (the highest point of each pole
cluster, :mod:`scene_elements`) ranked by the number of (camera, frame) views they are in.

Clicks file formats
-------------------
Pixels follow OpenCV (integer coordinates at pixel centres), at the camera's FULL
resolution (OSDaR23: rgb_* 2464 x 1600, rgb_highres_* 4112 x 2504, ir_* 640 x 480) unless
a resolution is given. Frames without a click are simply absent (or have empty / NaN u, v).

CSV (one landmark per file, its name is the file stem unless a ``landmark`` column says
otherwise)::

    camera,frame_idx,u,v
    rgb_center,0,1283.5,402.0
    rgb_highres_center,0,2050.25,610.0

optional columns ``width,height`` give the resolution the row's pixels are in.

JSON::

    {"landmark": "pole_top_17",
     "clicks": {"rgb_center": {"0": [1283.5, 402.0], "1": [1290.0, 401.0]},
                "rgb_highres_center": {"0": [2050.25, 610.0]}},
     "resolution": {"rgb_center": [2464, 1600]}}

``resolution`` is optional (per camera, [width, height]). A camera the sequence lacks is an
error; a frame the sequence lacks is skipped with a warning.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry.camera import CameraModel
from geometry.poses import PoseTrack
from worker.preparation.config import CalibrationConfig
from worker.preparation.scene_elements import Pole

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Full (real) resolution of the OSDaR23 cameras, (width, height) px.
OSDAR23_FULL_RESOLUTION: dict[str, tuple[int, int]] = {
    **{f"rgb_{s}": (2464, 1600) for s in ("center", "left", "right")},
    **{f"rgb_highres_{s}": (4112, 2504) for s in ("center", "left", "right")},
    **{f"ir_{s}": (640, 480) for s in ("center", "left", "right")},
}


class ClicksError(ValueError):
    """A clicks file that cannot be used (format, or a camera the sequence lacks)."""


# ---------------------------------------------------------------------------- clicks
@dataclass
class Clicks:
    """Hand-clicked pixels of one landmark.

    landmark : its name; uv : {camera: {frame_idx: (2,) pixel}};
    resolution : {camera: (width, height)} the pixels are in (missing: full resolution).
    """

    landmark: str
    uv: dict[str, dict[int, F64]]
    resolution: dict[str, tuple[int, int]] = field(default_factory=dict)

    def __len__(self) -> int:
        return sum(len(v) for v in self.uv.values())

    def to_json(self) -> dict[str, Any]:
        return {
            "landmark": self.landmark,
            "clicks": {
                c: {str(f): [float(x) for x in uv] for f, uv in sorted(fr.items())}
                for c, fr in sorted(self.uv.items())
            },
            "resolution": {c: list(wh) for c, wh in sorted(self.resolution.items())},
        }

    def digest(self) -> str:
        """sha256 hex of the canonical JSON (part of the artifact's cache key)."""
        text = json.dumps(self.to_json(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()

    @classmethod
    def from_json(cls, d: Any, where: str = "clicks") -> Clicks:
        if not isinstance(d, dict) or not isinstance(d.get("clicks"), dict):
            raise ClicksError(f"{where}: expected {{'landmark': ..., 'clicks': {{camera: ...}}}}")
        uv: dict[str, dict[int, F64]] = {}
        for cam, frames in d["clicks"].items():
            if not isinstance(frames, dict):
                raise ClicksError(f"{where}: clicks of {cam!r} must map frame_idx -> [u, v]")
            for f, val in frames.items():
                p = _pixel(val, f"{where}: {cam} frame {f}")
                if p is not None:
                    uv.setdefault(str(cam), {})[_frame(f, where)] = p
        res = {}
        for cam, wh in (d.get("resolution") or {}).items():
            res[str(cam)] = _resolution(wh, f"{where}: resolution of {cam}")
        return cls(str(d.get("landmark") or "landmark"), uv, res)

    @classmethod
    def load(cls, path: str | Path) -> Clicks:
        """Read a ``.json`` or ``.csv`` clicks file (formats in the module docstring)."""
        path = Path(path)
        if not path.is_file():
            raise ClicksError(f"{path}: clicks file not found")
        if path.suffix.lower() == ".json":
            try:
                data = json.loads(path.read_text())
            except json.JSONDecodeError as exc:
                raise ClicksError(f"{path}: not valid JSON ({exc})") from exc
            return cls.from_json(data, str(path))
        return cls._load_csv(path)

    @classmethod
    def _load_csv(cls, path: Path) -> Clicks:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        need = {"camera", "frame_idx", "u", "v"}
        if not rows or not need <= set(rows[0]):
            raise ClicksError(f"{path}: expected a CSV with header camera,frame_idx,u,v")
        uv: dict[str, dict[int, F64]] = {}
        res: dict[str, tuple[int, int]] = {}
        landmark = path.stem
        for k, r in enumerate(rows, start=2):
            where = f"{path}:{k}"
            cam = (r["camera"] or "").strip()
            if not cam:
                raise ClicksError(f"{where}: empty camera")
            if (r.get("landmark") or "").strip():
                landmark = r["landmark"].strip()
            if (r.get("width") or "").strip():
                res[cam] = _resolution([r["width"], r.get("height")], where)
            u, v = (r["u"] or "").strip(), (r["v"] or "").strip()
            p = None if not u or not v else _pixel([u, v], where)
            if p is not None:
                uv.setdefault(cam, {})[_frame(r["frame_idx"], where)] = p
        return cls(landmark, uv, res)


def _frame(f: Any, where: str) -> int:
    try:
        return int(str(f).strip())
    except ValueError as exc:
        raise ClicksError(f"{where}: frame_idx {f!r} is not an integer") from exc


def _pixel(val: Any, where: str) -> F64 | None:
    if val is None:
        return None
    try:
        p = np.asarray([float(x) for x in val], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ClicksError(f"{where}: pixel must be [u, v], got {val!r}") from exc
    if p.shape != (2,):
        raise ClicksError(f"{where}: pixel must be [u, v], got {val!r}")
    return p if np.all(np.isfinite(p)) else None


def _resolution(wh: Any, where: str) -> tuple[int, int]:
    try:
        w, h = int(wh[0]), int(wh[1])
    except (TypeError, ValueError, IndexError) as exc:
        raise ClicksError(f"{where}: resolution must be [width, height]") from exc
    if w <= 0 or h <= 0:
        raise ClicksError(f"{where}: resolution must be positive")
    return w, h


# ---------------------------------------------------------------------------- cameras
def camera_at_resolution(cam: CameraModel, width: int, height: int) -> CameraModel:
    """The same camera for its image resized to exactly ``width`` x ``height``.

    Kept for its callers; the mapping is :meth:`CameraModel.resized`.
    """
    return cam.resized(width, height)


def click_resolution(cam: CameraModel, clicks: Clicks | None = None) -> tuple[int, int]:
    """(width, height) the clicks of ``cam`` are in: explicit, else the OSDaR23 full size."""
    if clicks is not None and cam.name in clicks.resolution:
        return clicks.resolution[cam.name]
    if cam.name in OSDAR23_FULL_RESOLUTION:
        return OSDAR23_FULL_RESOLUTION[cam.name]
    log.warning(
        "%s: full resolution unknown, taking the labels' %dx%d", cam.name, cam.width, cam.height
    )
    return cam.width, cam.height


# ---------------------------------------------------------------------------- result
@dataclass
class CalibrationPoint:
    """The calibration point and how well it fits the clicks.

    mode : "clicks" or "auto"; xyz : (3,) world point (None if none was found);
    point_index : its index in the registered cloud (None in auto mode / none found);
    observations : per used view {camera, frame_idx, click [u, v], projected [u, v] or
    None, residual_px, inlier} at the clicks' resolution; skipped : {camera, frame_idx,
    reason}; proposals : auto mode's pole tops {pole, xyz, views, pixels}.
    """

    landmark: str
    mode: str
    xyz: F64 | None
    point_index: int | None = None
    observations: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, Any]] = field(default_factory=list)
    proposals: list[dict[str, Any]] = field(default_factory=list)
    resolution: dict[str, tuple[int, int]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    refined: bool = False

    @property
    def residuals(self) -> F64:
        r = [o["residual_px"] for o in self.observations if o["residual_px"] is not None]
        return np.asarray(r, dtype=np.float64)

    def summary(self) -> dict[str, Any]:
        r = self.residuals
        return {
            "landmark": self.landmark,
            "mode": self.mode,
            "found": self.xyz is not None,
            "views": len(self.observations),
            "inliers": sum(bool(o["inlier"]) for o in self.observations),
            "skipped": len(self.skipped),
            "residual_mean_px": float(r.mean()) if len(r) else None,
            "residual_max_px": float(r.max()) if len(r) else None,
            "residual_rms_px": float(np.sqrt(np.mean(r**2))) if len(r) else None,
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "landmark": self.landmark,
            "mode": self.mode,
            "xyz": None if self.xyz is None else [float(v) for v in self.xyz],
            "point_index": self.point_index,
            "summary": self.summary(),
            "resolution": {c: list(wh) for c, wh in self.resolution.items()},
            "observations": self.observations,
            "skipped": self.skipped,
            "proposals": self.proposals,
            "warnings": self.warnings,
            "refined": self.refined,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> CalibrationPoint:
        return cls(
            landmark=d["landmark"],
            mode=d["mode"],
            xyz=None if d.get("xyz") is None else np.asarray(d["xyz"], dtype=np.float64),
            point_index=d.get("point_index"),
            observations=list(d.get("observations", [])),
            skipped=list(d.get("skipped", [])),
            proposals=list(d.get("proposals", [])),
            resolution={c: (int(w), int(h)) for c, (w, h) in d.get("resolution", {}).items()},
            warnings=list(d.get("warnings", [])),
            refined=bool(d.get("refined", False)),
        )


# ---------------------------------------------------------------------------- from clicks
@dataclass
class _View:
    camera: str
    frame_idx: int
    click: F64  # (2,) px at the clicks' resolution
    cam: CameraModel  # at the clicks' resolution
    T_world_base: F64  # (4, 4) at the camera's timestamp


def _views(
    clicks: Clicks,
    cameras: dict[str, CameraModel],
    camera_times: dict[str, dict[int, float]],
    track: PoseTrack,
    skipped: list[dict[str, Any]],
) -> tuple[list[_View], dict[str, tuple[int, int]]]:
    missing = sorted(set(clicks.uv) - set(cameras))
    if missing:
        raise ClicksError(
            f"clicks name camera(s) {', '.join(missing)} that the sequence lacks "
            f"(it has: {', '.join(sorted(cameras)) or 'none'})"
        )
    views: list[_View] = []
    res: dict[str, tuple[int, int]] = {}
    for name, frames in sorted(clicks.uv.items()):
        W, H = click_resolution(cameras[name], clicks)
        res[name] = (W, H)
        cam = camera_at_resolution(cameras[name], W, H)
        times = camera_times.get(name, {})
        for f, uv in sorted(frames.items()):
            t = times.get(f)
            if t is None or not math.isfinite(t):
                skipped.append({"camera": name, "frame_idx": f, "reason": "no such frame"})
                continue
            try:
                T = track.interpolate(np.array([t]))[0]
            except ValueError:
                skipped.append({"camera": name, "frame_idx": f, "reason": "no pose at t"})
                continue
            views.append(_View(name, f, uv, cam, T))
    return views, res


def _cone_candidates(xyz: F64, view: _View, radius_px: float) -> NDArray[np.int64]:
    """Indices of points whose (undistorted) direction is within ~2 r px of the click ray."""
    T_world_opt = view.T_world_base @ view.cam.T_base_opt
    R, c = T_world_opt[:3, :3], T_world_opt[:3, 3]
    p_opt = (xyz - c) @ R
    z = p_opt[:, 2]
    xy_ray, ok = view.cam.undistort(view.cam.pixel_to_normalized(view.click[None]))
    if not ok[0]:
        return np.zeros(0, dtype=np.int64)
    tol = 2.0 * radius_px / min(view.cam.fx, view.cam.fy)  # margin for the lens distortion
    front = z > 0.5
    idx = np.flatnonzero(front)
    d = p_opt[idx, :2] / z[idx, None] - xy_ray[0]
    return idx[np.einsum("ij,ij->i", d, d) <= tol * tol]


def _seed_rays(views: list[_View]) -> tuple[F64, F64]:
    """(k, 3) world origins (camera centres) and (k, 3) unit world directions of the click
    rays of ``views`` (views whose click cannot be undistorted are left out)."""
    origins, dirs = [], []
    for v in views:
        xy, ok = v.cam.undistort(v.cam.pixel_to_normalized(v.click[None]))
        if not ok[0]:
            continue
        T_world_opt = v.T_world_base @ v.cam.T_base_opt
        d = T_world_opt[:3, :3] @ np.array([xy[0, 0], xy[0, 1], 1.0])
        origins.append(T_world_opt[:3, 3])
        dirs.append(d / np.linalg.norm(d))
    return np.asarray(origins, dtype=np.float64).reshape(-1, 3), np.asarray(
        dirs, dtype=np.float64
    ).reshape(-1, 3)


def points_near_rays(
    frame_points: Callable[[], Iterable[tuple[F64, F64]]],
) -> Callable[[F64, F64, float], F64]:
    """``dense_rays`` for :func:`calibration_point_from_clicks`: every frame's points (at
    full density) within an angle of any of the given rays.

    frame_points : yields per frame (T_world_base (4, 4), p_base (n, 3)): the frame's
        points and its pose at its lidar timestamp.
    The returned function takes (k, 3) world origins, (k, 3) unit world directions and a
    half-angle tolerance (rad) and returns the (m, 3) world points within it, at least
    0.5 m in front of a ray's origin.
    """

    def near(origins: F64, dirs: F64, tol: float) -> F64:
        out = []
        for T, p_base in frame_points():
            R, t = T[:3, :3], T[:3, 3]
            p32 = np.asarray(p_base, dtype=np.float32)  # a selection: float32 is enough
            keep = np.zeros(len(p32), dtype=bool)
            for o, d in zip(origins, dirs, strict=True):
                v = p32 - ((o - t) @ R).astype(np.float32)
                along = v @ (d @ R).astype(np.float32)
                perp2 = np.einsum("ij,ij->i", v, v) - along * along
                keep |= (along > 0.5) & (perp2 <= (tol * along) ** 2)
            if np.any(keep):
                out.append(np.asarray(p_base[keep], dtype=np.float64) @ R.T + t)
        return np.concatenate(out) if out else np.zeros((0, 3))

    return near


def _best_point(p: F64, views: list[_View], r: float) -> tuple[int, F64]:
    """Index of the point of ``p`` (m, 3) minimising the truncated squared pixel distance
    summed over the views, and its projections (k views, 2) (NaN where it fails)."""
    d2 = np.full((len(views), len(p)), r * r)
    uv_all = np.full((len(views), len(p), 2), np.nan)
    for k, v in enumerate(views):
        uv, ok = v.cam.project_world(p, v.T_world_base)
        uv_all[k] = uv
        e = np.where(ok, np.sum((uv - v.click) ** 2, axis=1), np.inf)
        d2[k] = np.minimum(e, r * r)
    best = int(np.argmin(d2.sum(axis=0)))
    return best, uv_all[:, best]


def calibration_point_from_clicks(
    xyz_world: F64,
    track: PoseTrack,
    cameras: dict[str, CameraModel],
    camera_times: dict[str, dict[int, float]],
    clicks: Clicks,
    cfg: CalibrationConfig,
    dense: Callable[[F64, float], F64] | None = None,
    dense_rays: Callable[[F64, F64, float], F64] | None = None,
) -> CalibrationPoint:
    """The cloud point whose projections are nearest to the clicks (module docstring).

    Parameters
    ----------
    xyz_world : (n, 3) registered cloud, world frame.
    track : T_world_base over time (interpolated to each camera's timestamp).
    cameras : camera models of the sequence (any resolution: clicks are rescaled to theirs).
    camera_times : {camera: {frame_idx: timestamp (s)}}.
    clicks : the landmark's clicks.
    cfg : search radius and seeding; ``dense_radius_m`` for the refinement.
    dense : ``dense(centre (3,), radius) -> (m, 3)`` world points of every frame at full
        density near ``centre`` (:func:`~worker.preparation.registration.points_near`).
        When given, the point chosen in ``xyz_world`` is refined among them: the same
        truncated cost, over a cloud dense enough that a point lies near the landmark
        itself (``point_index`` then stays the coarse one, ``refined`` is set).
    dense_rays : ``dense_rays(origins (k, 3), directions (k, 3), tol rad) -> (m, 3)``
        world points of every frame at full density near the seed views' click rays
        (:func:`points_near_rays`). When given they compete with the registered cloud's
        points from the start: a small landmark that only a few frames' beams hit, none
        of them kept in the registered cloud (every ``frame_step``-th frame, one point per
        voxel), is still found, rather than a point of another surface near the ray.

    Raises
    ------
    ClicksError
        The clicks name a camera the sequence lacks.
    """
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    out = CalibrationPoint(clicks.landmark, "clicks", None)
    views, out.resolution = _views(clicks, cameras, camera_times, track, out.skipped)
    for s in out.skipped:
        out.warnings.append(f"click of {s['camera']} frame {s['frame_idx']} skipped: {s['reason']}")
    if not views:
        out.warnings.append("no usable click")
        return out
    r = float(cfg.search_radius_px)
    seeds = np.unique(np.linspace(0, len(views) - 1, min(cfg.seed_frames, len(views))).round())
    seed_views = [views[int(k)] for k in seeds.astype(int)]
    cand = np.unique(np.concatenate([_cone_candidates(xyz, v, r) for v in seed_views]))
    extra = np.zeros((0, 3))
    if dense_rays is not None:  # the two seed views farthest apart: each ray's cone holds it
        origins, dirs = _seed_rays(
            [seed_views[0], seed_views[-1]] if len(seed_views) > 1 else seed_views
        )
        tol = 2.0 * r / min(min(v.cam.fx, v.cam.fy) for v in seed_views)
        if len(origins):
            extra = np.asarray(dense_rays(origins, dirs, tol), dtype=np.float64).reshape(-1, 3)
    if len(cand) == 0 and len(extra) == 0:
        out.warnings.append(f"no cloud point projects within {r:.0f} px of the seed clicks")
        return out
    best, uv_best = _best_point(np.concatenate([xyz[cand], extra]), views, r)
    if best < len(cand):
        out.point_index = int(cand[best])
        out.xyz = xyz[cand[best]].copy()
    else:
        out.xyz, out.refined = extra[best - len(cand)].copy(), True
    if dense is not None and cfg.dense_radius_m > 0:
        near = np.asarray(dense(out.xyz, float(cfg.dense_radius_m)), dtype=np.float64)
        if len(near):
            pts = np.concatenate([out.xyz[None], near.reshape(-1, 3)])
            k_best, uv_dense = _best_point(pts, views, r)
            out.xyz, uv_best, out.refined = pts[k_best].copy(), uv_dense, True
    for k, v in enumerate(views):
        uv = uv_best[k]
        res = float(np.linalg.norm(uv - v.click)) if np.all(np.isfinite(uv)) else None
        out.observations.append(
            {
                "camera": v.camera,
                "frame_idx": v.frame_idx,
                "click": [float(x) for x in v.click],
                "projected": None if res is None else [float(x) for x in uv],
                "residual_px": res,
                "inlier": res is not None and res <= r,
            }
        )
    n_in = sum(o["inlier"] for o in out.observations)
    if n_in < len(views):
        out.warnings.append(f"{len(views) - n_in} of {len(views)} views farther than {r:.0f} px")
    log.info(
        "calibration point %s: %s from %d views (%d candidates), %d inliers",
        clicks.landmark, np.round(out.xyz, 3), len(views), len(cand), n_in,
    )  # fmt: skip
    return out


# ---------------------------------------------------------------------------- automatic
def propose_pole_tops(
    poles: list[Pole],
    track: PoseTrack,
    cameras: dict[str, CameraModel],
    camera_times: dict[str, dict[int, float]],
    cfg: CalibrationConfig,
) -> CalibrationPoint:
    """Automatic mode: the pole tops in view of the cameras over most frames.

    Each pole's highest point is projected into every camera and frame (full resolution);
    a view counts when it is inside the image by ``auto_margin_px`` and between
    ``auto_min_depth`` and ``auto_max_depth`` in front of the camera (occlusion is not
    tested). The best is the calibration point; ``auto_proposals`` are listed with their
    predicted pixels so that a person can click them.
    """
    out = CalibrationPoint("auto_pole_top", "auto", None)
    if not poles:
        out.warnings.append("automatic calibration point: no poles to propose")
        return out
    tops = np.array([p.top_point for p in poles], dtype=np.float64)
    views = np.zeros(len(poles), dtype=np.int64)
    pixels: list[dict[str, dict[str, list[float]]]] = [{} for _ in poles]
    for name, cam0 in sorted(cameras.items()):
        W, H = click_resolution(cam0)
        out.resolution[name] = (W, H)
        cam = camera_at_resolution(cam0, W, H)
        times = {f: t for f, t in camera_times.get(name, {}).items() if math.isfinite(t)}
        if not times:
            continue
        frames = sorted(times)
        try:
            Ts = track.interpolate(np.array([times[f] for f in frames]))
        except ValueError:
            continue
        for f, T in zip(frames, Ts, strict=True):
            T_opt_world = np.linalg.inv(T @ cam.T_base_opt)
            z = tops @ T_opt_world[2, :3] + T_opt_world[2, 3]
            uv, ok = cam.project_world(tops, T)
            ok &= cam.in_image(uv, cfg.auto_margin_px)
            ok &= (z >= cfg.auto_min_depth) & (z <= cfg.auto_max_depth)
            views += ok
            for i in np.flatnonzero(ok):
                pixels[i].setdefault(name, {})[str(f)] = [float(uv[i, 0]), float(uv[i, 1])]
    order = np.argsort(-views, kind="stable")[: cfg.auto_proposals]
    for i in order:
        out.proposals.append(
            {
                "pole": poles[i].id,
                "xyz": [float(v) for v in tops[i]],
                "views": int(views[i]),
                "pixels": pixels[i],
            }
        )
    if views[order[0]] == 0:
        out.warnings.append("automatic calibration point: no pole top is in view")
        return out
    out.landmark = f"{poles[order[0]].id}_top"
    out.xyz = tops[order[0]].copy()
    return out
