"""Scene elements near the track: ground and platform planes, platform edges, poles.

They become the renderer's proxies (plane polygons, pole boxes), so they are simple shapes:

- **planes**: the cloud near the reference centreline is cut into pieces of
  ``segment_length`` metres of track; in each piece open3d's RANSAC (``segment_plane``)
  peels off near-horizontal planes one after the other; the inliers of each plane are
  split into connected components on a grid in track coordinates (arc length s, lateral
  offset), each component refit by least squares (SVD) and outlined per ``outline_step``
  of arc length by its lateral extent. A component whose height above the rail top lies in
  ``platform_height`` and that stays on one side of the track beyond
  ``platform_min_lateral`` is a *platform*, and its near side is its *edge*; below it is
  *ground* (track bed and terrain); above, *other*.
- **poles**: points of tall xy columns (vertical extent >= ``min_column_extent``: this
  drops wires, cantilevers and ground) are clustered by DBSCAN (open3d
  ``cluster_dbscan``); a cluster is a pole when it is thin (radius <= ``max_radius``), tall
  (>= ``min_height``) and covered along its height. Its axis is the points' centroid moved
  away from the track by the half-cylinder bias 2r/pi (the lidar sees the near side only).

Heights are relative to the reference centreline, which runs at the rail top (the base
frame's z = 0): the ego centreline when rails were found, else the trajectory of the base
frame, extended along its end tangents.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from geometry.columns import column_min
from geometry.poses import PoseTrack
from worker.preparation.centreline import Centreline
from worker.preparation.config import PlaneConfig, PoleConfig

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ---------------------------------------------------------------------------- results
@dataclass
class Plane:
    """A planar patch near the track.

    kind : "ground", "platform" or "other".
    normal : (3,) unit normal (z >= 0); offset : d of n . p + d = 0 (world frame, m).
    polygon : (k, 3) outline in the world frame (on the plane), in track order.
    height : median height above the rail top (m); side : "left", "right" or "both".
    lateral : (min, max) lateral offset of the patch from the centreline (m, left +).
    s_range : (start, end) arc length on the reference centreline (m).
    edge : (m, 3) the platform's near edge in the world frame (platforms only, else None).
    edge_offset : median |lateral| of the edge (m; platforms only, else None).
    points : inlier count; rms : RMS inlier distance to the plane (m).
    """

    kind: str
    normal: F64
    offset: float
    polygon: F64
    height: float
    side: str
    lateral: tuple[float, float]
    s_range: tuple[float, float]
    points: int
    rms: float
    edge: F64 | None = None
    edge_offset: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "normal": self.normal.tolist(),
            "offset": float(self.offset),
            "polygon": self.polygon.tolist(),
            "height": float(self.height),
            "side": self.side,
            "lateral": [float(v) for v in self.lateral],
            "s_range": [float(v) for v in self.s_range],
            "points": int(self.points),
            "rms": float(self.rms),
            "edge": None if self.edge is None else self.edge.tolist(),
            "edge_offset": None if self.edge_offset is None else float(self.edge_offset),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Plane:
        edge = d.get("edge")
        return cls(
            kind=d["kind"],
            normal=np.asarray(d["normal"], dtype=np.float64),
            offset=float(d["offset"]),
            polygon=np.asarray(d["polygon"], dtype=np.float64).reshape(-1, 3),
            height=float(d["height"]),
            side=d["side"],
            lateral=(float(d["lateral"][0]), float(d["lateral"][1])),
            s_range=(float(d["s_range"][0]), float(d["s_range"][1])),
            points=int(d["points"]),
            rms=float(d["rms"]),
            edge=None if edge is None else np.asarray(edge, dtype=np.float64).reshape(-1, 3),
            edge_offset=None if d.get("edge_offset") is None else float(d["edge_offset"]),
        )


@dataclass
class Pole:
    """A vertical pole as a box for the renderer.

    center : (3,) box centre (world, m); size : (3,) [2r, 2r, height] (axis-aligned with the
    world frame: a pole is vertical); base_z, top_z : its lowest and highest point (m);
    radius : m; top_point : (3,) the cluster's highest measured point (a landmark
    candidate); axis_xy : (2,) the estimated pole axis; points : cluster size;
    s, lateral : position along the reference centreline (m).
    """

    id: str
    axis_xy: F64
    base_z: float
    top_z: float
    radius: float
    top_point: F64
    points: int
    s: float
    lateral: float

    @property
    def height(self) -> float:
        return self.top_z - self.base_z

    @property
    def center(self) -> F64:
        return np.array([self.axis_xy[0], self.axis_xy[1], 0.5 * (self.base_z + self.top_z)])

    @property
    def size(self) -> F64:
        return np.array([2.0 * self.radius, 2.0 * self.radius, self.height])

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "center": self.center.tolist(),
            "size": self.size.tolist(),
            "quaternion": [0.0, 0.0, 0.0, 1.0],
            "axis_xy": self.axis_xy.tolist(),
            "base_z": float(self.base_z),
            "top_z": float(self.top_z),
            "radius": float(self.radius),
            "top_point": self.top_point.tolist(),
            "points": int(self.points),
            "s": float(self.s),
            "lateral": float(self.lateral),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Pole:
        return cls(
            id=str(d["id"]),
            axis_xy=np.asarray(d["axis_xy"], dtype=np.float64),
            base_z=float(d["base_z"]),
            top_z=float(d["top_z"]),
            radius=float(d["radius"]),
            top_point=np.asarray(d["top_point"], dtype=np.float64),
            points=int(d["points"]),
            s=float(d["s"]),
            lateral=float(d["lateral"]),
        )


@dataclass
class SceneElements:
    """Planes and poles found, with what went wrong (``warnings``) and counts."""

    planes: list[Plane] = field(default_factory=list)
    poles: list[Pole] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)

    @property
    def platforms(self) -> list[Plane]:
        return [p for p in self.planes if p.kind == "platform"]

    @property
    def ground(self) -> list[Plane]:
        return [p for p in self.planes if p.kind == "ground"]


# ---------------------------------------------------------------------------- reference
def reference_centreline(
    ego: Centreline | None, trajectory: PoseTrack, extend: float = 80.0
) -> Centreline:
    """The line heights and lateral offsets are measured from.

    The ego centreline if given; else the base-frame trajectory (its origin is at rail-top
    height) extended by ``extend`` metres along its end tangents (the base x axis when the
    train stands still).
    """
    if ego is not None:
        return ego
    p = trajectory.positions
    step = np.linalg.norm(np.diff(p, axis=0), axis=1) if len(p) > 1 else np.zeros(0)
    if len(p) < 2 or float(step.sum()) < 1.0:
        x = trajectory.T[0, :3, 0]
        c = p.mean(axis=0)
        pts = np.array([c - extend * x, c, c + extend * x])
        return Centreline(pts, track_id="trajectory")
    keep = np.concatenate([[True], step > 0.05])
    p = p[keep]
    t0 = p[min(1, len(p) - 1)] - p[0]
    t1 = p[-1] - p[max(0, len(p) - 2)]
    t0 /= max(np.linalg.norm(t0), 1e-9)
    t1 /= max(np.linalg.norm(t1), 1e-9)
    pts = np.vstack([p[0] - extend * t0, p, p[-1] + extend * t1])
    return Centreline(pts, track_id="trajectory")


@dataclass
class TrackCoords:
    """Track coordinates of the cloud points within ``corridor`` of the reference.

    index : (m,) indices into the cloud; s, lateral, vertical : (m,) m.
    """

    index: I64
    s: F64
    lateral: F64
    vertical: F64


def track_coords(xyz_world: F64, reference: Centreline, corridor: float) -> TrackCoords:
    """Arc length, lateral offset and height of the points within ``corridor`` (horizontal).

    Every point is projected with :meth:`Centreline.project_many` (no KD query per point:
    the registered cloud has millions).
    """
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    pr = reference.project_many(xyz)
    # points beyond the ends project onto the clamped end: keep only those beside the line
    idx = np.flatnonzero((np.abs(pr.lateral) <= corridor) & (pr.distance <= corridor))
    return TrackCoords(idx, pr.s[idx], pr.lateral[idx], pr.vertical[idx])


def _left_normals(reference: Centreline, s: F64) -> F64:
    t = reference.tangent(s)
    left = np.stack([-t[:, 1], t[:, 0], np.zeros(len(s))], axis=1)
    return left / np.maximum(np.linalg.norm(left, axis=1, keepdims=True), 1e-12)


# ---------------------------------------------------------------------------- planes
def fit_plane_svd(p: F64) -> tuple[F64, float, float]:
    """Least-squares plane of (n, 3) points: unit normal (z >= 0), offset d, RMS distance."""
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[-1]
    if n[2] < 0:
        n = -n
    d = -float(n @ c)
    rms = float(np.sqrt(np.mean(((p - c) @ n) ** 2)))
    return n, d, rms


def _components(s: F64, lat: F64, cell: float) -> I64:
    """Connected-component label (0..k-1) of each point on an (s, lateral) grid."""
    i = np.floor((s - s.min()) / cell).astype(np.int64)
    j = np.floor((lat - lat.min()) / cell).astype(np.int64)
    grid = np.zeros((i.max() + 1, j.max() + 1), dtype=bool)
    grid[i, j] = True
    # a one-cell closing bridges the gaps between scan lines
    labels, _ = ndimage.label(ndimage.binary_dilation(grid, iterations=1), np.ones((3, 3)))
    return labels[i, j] - 1


def _plane_z(n: F64, d: float, xy: F64) -> F64:
    return -(d + xy[:, 0] * n[0] + xy[:, 1] * n[1]) / max(n[2], 1e-9)


def _outline(
    reference: Centreline, s: F64, lat: F64, n: F64, d: float, step: float
) -> tuple[F64, F64, F64]:
    """(polygon (k, 3), per-bin min lateral, per-bin max lateral) of a patch, on its plane."""
    edges = np.arange(s.min(), s.max() + step, step)
    b = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, max(len(edges) - 2, 0))
    order = np.argsort(b, kind="stable")
    bs = b[order]
    starts = np.flatnonzero(np.concatenate([[True], bs[1:] != bs[:-1]]))
    counts = np.diff(np.append(starts, len(bs)))
    lo = np.minimum.reduceat(lat[order], starts)
    hi = np.maximum.reduceat(lat[order], starts)
    sc = np.add.reduceat(s[order], starts) / counts
    if len(sc) == 1:  # a patch shorter than one step: two vertices along s
        sc = np.array([s.min(), s.max()])
        lo, hi = np.repeat(lo, 2), np.repeat(hi, 2)
    c = reference.point(sc)
    left = _left_normals(reference, sc)
    near = c + lo[:, None] * left
    far = c + hi[:, None] * left
    poly = np.vstack([near, far[::-1]])
    poly[:, 2] = _plane_z(n, d, poly[:, :2])
    return poly, lo, hi


def find_planes(
    xyz_world: F64, coords: TrackCoords, reference: Centreline, cfg: PlaneConfig, seed: int = 0
) -> tuple[list[Plane], list[str]]:
    """Near-horizontal planes per track segment (see the module docstring)."""

    o3d.utility.random.seed(seed)
    rng = np.random.default_rng(seed)
    warnings: list[str] = []
    h0, h1 = cfg.height_band
    sel = (np.abs(coords.lateral) <= cfg.corridor) & (coords.vertical >= h0)
    sel &= coords.vertical <= h1
    idx, s_all = coords.index[sel], coords.s[sel]
    lat_all, v_all = coords.lateral[sel], coords.vertical[sel]
    planes: list[Plane] = []
    if len(idx) < cfg.min_points:
        warnings.append(f"planes: only {len(idx)} points near the track")
        return planes, warnings
    cos_tilt = np.cos(np.radians(cfg.max_tilt_deg))
    starts = np.arange(s_all.min(), s_all.max(), cfg.segment_length)
    for s0 in starts:
        m = np.flatnonzero((s_all >= s0) & (s_all < s0 + cfg.segment_length))
        if len(m) < cfg.min_points:
            continue
        if len(m) > cfg.max_points:
            m = np.sort(rng.choice(m, cfg.max_points, replace=False))
        p = xyz_world[idx[m]]
        origin = p.mean(axis=0)  # RANSAC on small local coordinates
        remaining = np.arange(len(m))
        for _ in range(cfg.max_planes):
            if len(remaining) < cfg.min_points:
                break
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[remaining] - origin))
            model, inl = pc.segment_plane(
                cfg.distance_threshold, 3, cfg.ransac_iterations, cfg.ransac_probability
            )
            inl = np.asarray(inl, dtype=np.int64)
            if len(inl) < cfg.min_points:
                break
            hit = remaining[inl]
            remaining = np.setdiff1d(remaining, hit, assume_unique=True)
            if abs(model[2]) / max(np.linalg.norm(model[:3]), 1e-12) < cos_tilt:
                continue  # a wall or a slope: not a proxy surface
            comp = _components(s_all[m][hit], lat_all[m][hit], cfg.cell_size)
            for k in range(comp.max() + 1):
                h = hit[comp == k]
                if len(h) < cfg.min_points:
                    continue
                planes.append(
                    _make_plane(p[h], s_all[m][h], lat_all[m][h], v_all[m][h], reference, cfg)
                )
    planes.sort(key=lambda pl: (pl.kind, pl.s_range[0], pl.lateral[0]))
    if not any(pl.kind == "ground" for pl in planes):
        warnings.append("planes: no ground plane found near the track")
    return planes, warnings


def _make_plane(
    p: F64, s: F64, lat: F64, vert: F64, reference: Centreline, cfg: PlaneConfig
) -> Plane:
    n, d, rms = fit_plane_svd(p)
    height = float(np.median(vert))
    lo, hi = float(lat.min()), float(lat.max())
    side = "left" if lo > 0 else "right" if hi < 0 else "both"
    one_side = min(abs(lo), abs(hi)) >= cfg.platform_min_lateral and side != "both"
    if cfg.platform_height[0] <= height <= cfg.platform_height[1] and one_side:
        kind = "platform"
    elif height < cfg.platform_height[0]:
        kind = "ground"
    else:
        kind = "other"
    poly, blo, bhi = _outline(reference, s, lat, n, d, cfg.outline_step)
    edge = edge_offset = None
    if kind == "platform":
        near_lat = blo if side == "left" else bhi
        k = len(near_lat)
        edge = poly[:k] if side == "left" else poly[k:][::-1]
        edge_offset = float(np.median(np.abs(near_lat)))
    return Plane(
        kind=kind,
        normal=n,
        offset=d,
        polygon=poly,
        height=height,
        side=side,
        lateral=(lo, hi),
        s_range=(float(s.min()), float(s.max())),
        points=len(p),
        rms=rms,
        edge=edge,
        edge_offset=edge_offset,
    )


# ---------------------------------------------------------------------------- poles
def _tall_columns(xy: F64, z: F64, cell: float, min_extent: float) -> NDArray[np.bool_]:
    """(n,) mask of points in xy cells whose z extent is at least ``min_extent``."""
    key = np.floor(xy / cell).astype(np.int64)
    key -= column_min(key)
    _, inv = np.unique(key[:, 0] * (int(key[:, 1].max()) + 1) + key[:, 1], return_inverse=True)
    inv = inv.reshape(-1)
    k = inv.max() + 1
    zmin = np.full(k, np.inf)
    zmax = np.full(k, -np.inf)
    np.minimum.at(zmin, inv, z)
    np.maximum.at(zmax, inv, z)
    return (zmax - zmin)[inv] >= min_extent


def find_poles(
    xyz_world: F64,
    coords: TrackCoords,
    reference: Centreline,
    cfg: PoleConfig,
    view_xyz: F64 | None = None,
) -> tuple[list[Pole], list[str]]:
    """Poles by DBSCAN over the points of tall thin columns (see the module docstring).

    ``view_xyz`` (n, 3): where each cloud point was seen from (the sensor position of its
    frame); it sets the direction of the half-cylinder bias (default: from the centreline).
    """

    warnings: list[str] = []
    h0, h1 = cfg.height_band
    sel = (np.abs(coords.lateral) <= cfg.corridor) & (coords.vertical >= h0)
    sel &= coords.vertical <= h1
    idx = coords.index[sel]
    if len(idx) < cfg.min_points:
        return [], [f"poles: only {len(idx)} points above the ground near the track"]
    p = xyz_world[idx]
    tall = _tall_columns(p[:, :2], p[:, 2], cfg.column_cell, cfg.min_column_extent)
    idx, p = idx[tall], p[tall]
    views = None if view_xyz is None else np.asarray(view_xyz, dtype=np.float64)[idx]
    if len(idx) < cfg.min_points:
        return [], ["poles: no tall thin structures near the track"]
    origin = p.mean(axis=0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p - origin))
    labels = np.asarray(pc.cluster_dbscan(cfg.eps, cfg.min_cluster_points, print_progress=False))
    poles: list[Pole] = []
    for k in range(labels.max() + 1 if len(labels) else 0):
        mk = labels == k
        if np.count_nonzero(mk) < cfg.min_points:
            continue
        pole = _pole_from_cluster(p[mk], None if views is None else views[mk], reference, cfg)
        if pole is not None:
            poles.append(pole)
    if poles:  # the boxes reach down to the lowest point under each pole (its foot)
        near = coords.index[np.abs(coords.lateral) <= cfg.corridor]
        # only the points in the 2 m cells the poles' footprints touch go into the KD-tree
        cell = 2.0
        foot = np.array([pl.axis_xy for pl in poles])
        reach = np.array([pl.radius + 0.1 for pl in poles])
        cells = np.unique(
            np.concatenate(
                [
                    np.floor((foot + d * reach[:, None]) / cell)
                    for d in ((-1, -1), (-1, 1), (1, -1), (1, 1))
                ]
            ),
            axis=0,
        ).astype(np.int64)
        key = np.floor(xyz_world[near, :2] / cell).astype(np.int64)
        near = near[
            np.isin(key[:, 0] * 1_000_003 + key[:, 1], cells[:, 0] * 1_000_003 + cells[:, 1])
        ]
        tree = cKDTree(xyz_world[near, :2])
        for pl in poles:
            hits = tree.query_ball_point(pl.axis_xy, pl.radius + 0.1)
            if hits:
                pl.base_z = min(pl.base_z, float(xyz_world[near[hits], 2].min()))
    poles.sort(key=lambda pl: (pl.s, pl.lateral))
    for i, pl in enumerate(poles):
        pl.id = f"pole_{i:03d}"
    if not poles:
        warnings.append("poles: none found near the track")
    return poles, warnings


def _pole_from_cluster(
    q: F64, views: F64 | None, reference: Centreline, cfg: PoleConfig
) -> Pole | None:
    z0, z1 = float(q[:, 2].min()), float(q[:, 2].max())
    if z1 - z0 < cfg.min_height:
        return None
    # covered along its height: at least half of the 0.5 m slices hold points
    nb = max(1, int(np.ceil((z1 - z0) / 0.5)))
    filled = np.unique(np.minimum(((q[:, 2] - z0) / 0.5).astype(np.int64), nb - 1))
    if len(filled) < 0.5 * nb:
        return None
    c = q[:, :2].mean(axis=0)
    r_max = float(np.max(np.linalg.norm(q[:, :2] - c, axis=1)))
    if r_max > cfg.max_radius:
        return None
    pr = reference.project(np.array([[c[0], c[1], z0]]))
    if views is None:
        u = (c - reference.point(pr.s)[0, :2])[None]
    else:
        u = q[:, :2] - views[:, :2]
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
    mean_u = u.mean(axis=0)
    spread = float(np.linalg.norm(mean_u))  # 1: seen from one direction only
    away = mean_u / max(spread, 1e-9)
    across = np.array([-away[1], away[0]])
    w = (q[:, :2] - c) @ across
    radius = float(np.clip(0.5 * (w.max() - w.min()), 0.03, cfg.max_radius))
    # the lidar sees the near side: the centroid of a half cylinder is 2r/pi in front of
    # its axis, less when the views spread around it
    axis = c + (2.0 / np.pi) * radius * spread * away
    top = q[int(np.argmax(q[:, 2]))].copy()
    return Pole(
        id="",
        axis_xy=axis,
        base_z=z0,
        top_z=z1,
        radius=radius,
        top_point=top,
        points=len(q),
        s=float(pr.s[0]),
        lateral=float(pr.lateral[0]),
    )


# ---------------------------------------------------------------------------- entry
def find_scene_elements(
    xyz_world: F64,
    reference: Centreline,
    planes: PlaneConfig,
    poles: PoleConfig,
    seed: int = 0,
    view_xyz: F64 | None = None,
) -> SceneElements:
    """Planes and poles of a registered cloud (``xyz_world`` (n, 3) float64).

    Parameters
    ----------
    xyz_world : (n, 3) world points (the registered cloud).
    reference : the line heights are measured from (:func:`reference_centreline`).
    planes, poles : the parameters (config sections).
    seed : RANSAC / subsampling seed (results are deterministic for a seed).
    view_xyz : (n, 3) sensor position each point was seen from (optional, see find_poles).
    """
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(xyz)):
        raise ValueError("scene elements: the cloud must be finite")
    out = SceneElements()
    coords = track_coords(xyz, reference, max(planes.corridor, poles.corridor))
    out.planes, w1 = find_planes(xyz, coords, reference, planes, seed)
    out.poles, w2 = find_poles(xyz, coords, reference, poles, view_xyz)
    for w in (*w1, *w2):
        log.warning(w)
        out.warnings.append(w)
    out.metrics = {
        "points_near_track": float(len(coords.index)),
        "planes": float(len(out.planes)),
        "ground_planes": float(len(out.ground)),
        "platform_planes": float(len(out.platforms)),
        "poles": float(len(out.poles)),
    }
    return out
