"""Placement of the virtual object: track coordinates or absolute, snapped to the surface.

Spec forms (the CLI's ``--place`` string or the job spec's ``placement`` object):

- track: ``s=40,offset=0,yaw=90`` — arc length (m) along the ego track measured from the
  first frame's position, lateral offset (m, left of the direction of travel positive) from
  the centreline, yaw (deg) relative to the track's direction (0: the object faces along
  the direction of travel, 90: it faces left, i.e. it stands across the track);
- world: ``x=..,y=..,z=..,yaw=..`` (``mode=world``) in the sequence's world frame (ENU at
  the first INS record), yaw from East counter-clockwise; ``z`` optional (snapped);
- lidar frame: ``frame=12,x=..,y=..,yaw=..`` (``mode=lidar``): a point in that frame's
  lidar/base frame, yaw relative to that frame's x axis.

The object is set upright (its z axis along world up) on the highest proxy surface below
its footprint centre (track bed, platform, ground). A spec whose point lies off the
prepared track's extent, or whose footprint cuts a pole, is refused with a
``PlacementError`` saying why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from geometry.transforms import make_T, transform_points
from renderer.mesh import ObjectMesh, ProxyMesh

F64 = NDArray[np.float64]

# The ego centreline is at top-of-rail height; on the track the object stands on the
# sleepers / ballast this far below it (UIC60 rail 172 mm + pad).
RAIL_HEIGHT_ABOVE_BED = 0.18
# Footprint clearance to a pole's surface (m).
POLE_CLEARANCE = 0.05
# Snapping casts down from this far above the nominal height (m).
SNAP_FROM_ABOVE = 6.0


class PlacementError(ValueError):
    """A placement that cannot be honoured (off the track, inside a pole, bad spec)."""


@dataclass(frozen=True)
class PlacementSpec:
    """A parsed placement. ``mode`` is "track", "world" or "lidar"."""

    mode: str = "track"
    s: float = 40.0
    offset: float = 0.0
    yaw_deg: float = 90.0
    xyz: tuple[float, float, float | None] | None = None
    frame_idx: int | None = None

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass
class ResolvedPlacement:
    """T_world_obj (4, 4) and how it was obtained (surface, track coordinates)."""

    T_world_obj: F64
    surface: str
    s: float | None = None
    lateral: float | None = None
    info: dict[str, Any] = field(default_factory=dict)


def parse_place(text: str) -> PlacementSpec:
    """``"s=40,offset=0,yaw=90"`` or ``"mode=world,x=..,y=..,yaw=.."`` -> PlacementSpec."""
    items: dict[str, str] = {}
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise PlacementError(f"--place {text!r}: {part!r} is not KEY=VALUE")
        k, v = part.split("=", 1)
        items[k.strip().lower()] = v.strip()
    mode = items.pop("mode", None)
    if mode is None:
        mode = "lidar" if "frame" in items else "world" if "x" in items else "track"
    try:
        num = {k: float(v) for k, v in items.items()}
    except ValueError as exc:
        raise PlacementError(f"--place {text!r}: {exc}") from exc
    allowed = {
        "track": {"s", "offset", "yaw"},
        "world": {"x", "y", "z", "yaw"},
        "lidar": {"frame", "x", "y", "z", "yaw"},
    }
    if mode not in allowed:
        raise PlacementError(f"--place: mode must be track, world or lidar, got {mode!r}")
    unknown = set(num) - allowed[mode]
    if unknown:
        raise PlacementError(
            f"--place {text!r}: unknown key(s) {sorted(unknown)} for mode {mode} "
            f"(allowed: {sorted(allowed[mode])})"
        )
    yaw = num.get("yaw", 90.0 if mode == "track" else 0.0)
    if mode == "track":
        return PlacementSpec(
            "track", s=num.get("s", 40.0), offset=num.get("offset", 0.0), yaw_deg=yaw
        )
    if "x" not in num or "y" not in num:
        raise PlacementError(f"--place {text!r}: mode {mode} needs x and y")
    xyz = (num["x"], num["y"], num.get("z"))
    frame = int(num["frame"]) if mode == "lidar" else None
    if mode == "lidar" and "frame" not in num:
        raise PlacementError(f"--place {text!r}: mode lidar needs frame=N")
    return PlacementSpec(mode, yaw_deg=yaw, xyz=xyz, frame_idx=frame)


def placement_from_json(d: dict[str, Any]) -> PlacementSpec:
    """The job spec's placement object -> PlacementSpec (same fields as ``to_json``)."""
    mode = d.get("mode", "track")
    xyz = d.get("xyz")
    return PlacementSpec(
        mode=mode,
        s=float(d.get("s", 40.0)),
        offset=float(d.get("offset", 0.0)),
        yaw_deg=float(d.get("yaw_deg", 90.0 if mode == "track" else 0.0)),
        xyz=None
        if xyz is None
        else (
            float(xyz[0]),
            float(xyz[1]),
            None if len(xyz) < 3 or xyz[2] is None else float(xyz[2]),
        ),
        frame_idx=None if d.get("frame_idx") is None else int(d["frame_idx"]),
    )


def _yaw_T(p: F64, heading: float) -> F64:
    c, s = math.cos(heading), math.sin(heading)
    return make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), p)


def resolve_placement(
    spec: PlacementSpec,
    *,
    ego: Any,
    track: Any,
    frame_times: dict[int, float],
    proxies: ProxyMesh | None,
    poles: list[Any],
    obj: ObjectMesh,
) -> ResolvedPlacement:
    """T_world_obj for a spec.

    Parameters
    ----------
    ego : the ego Centreline (None: only world/lidar modes work).
    track : PoseTrack T_world_base of the sequence.
    frame_times : frame counter -> lidar timestamp.
    proxies : the scene proxies to snap onto (None: keep the nominal height).
    poles : prepared poles (axis_xy, radius) to keep the footprint clear of.
    obj : the object (its footprint radius is used for the pole test).
    """
    first = min(frame_times)
    T_first = track.interpolate(np.array([frame_times[first]]))[0]
    if spec.mode == "track":
        if ego is None:
            raise PlacementError(
                "track placement needs the ego track, and preparation found no rails: "
                "place the object with mode=world or mode=lidar"
            )
        s0 = float(ego.project(T_first[None, :3, 3]).s[0])
        s_abs = s0 + spec.s
        if not (0.0 <= s_abs <= ego.length):
            raise PlacementError(
                f"s={spec.s:g} m is off the prepared track: the ego track extends from "
                f"{-s0:.1f} m to {ego.length - s0:.1f} m relative to the first frame"
            )
        c = ego.point([s_abs])[0]
        t = ego.tangent([s_abs])[0]
        left = np.array([-t[1], t[0], 0.0])
        left /= np.linalg.norm(left)
        p = c + spec.offset * left
        on_track = abs(spec.offset) < 1.0
        p[2] = c[2] - (RAIL_HEIGHT_ABOVE_BED if on_track else 0.0)
        heading = math.atan2(t[1], t[0]) + math.radians(spec.yaw_deg)
        s_out, lat_out = s_abs, spec.offset
    elif spec.mode == "world":
        assert spec.xyz is not None
        z = spec.xyz[2] if spec.xyz[2] is not None else T_first[2, 3]
        p = np.array([spec.xyz[0], spec.xyz[1], z], dtype=np.float64)
        heading = math.radians(spec.yaw_deg)
        s_out = lat_out = None
    else:
        assert spec.xyz is not None and spec.frame_idx is not None
        if spec.frame_idx not in frame_times:
            raise PlacementError(
                f"frame={spec.frame_idx} is not a frame of the sequence "
                f"({min(frame_times)}..{max(frame_times)})"
            )
        T = track.interpolate(np.array([frame_times[spec.frame_idx]]))[0]
        z = spec.xyz[2] if spec.xyz[2] is not None else 0.0
        p = transform_points(T, np.array([[spec.xyz[0], spec.xyz[1], z]]))[0]
        x_axis = T[:3, 0]
        heading = math.atan2(x_axis[1], x_axis[0]) + math.radians(spec.yaw_deg)
        s_out = lat_out = None
    surface = "nominal"
    if proxies is not None and len(proxies.faces):
        z_snap = snap_height(proxies, p)
        if z_snap is not None:
            p[2], surface = z_snap, "proxy"
    check_poles(p, obj, heading, poles)
    return ResolvedPlacement(
        _yaw_T(p, heading),
        surface,
        s_out,
        lat_out,
        info={"heading_deg": math.degrees(heading), "xyz": p.tolist()},
    )


def snap_height(proxies: ProxyMesh, p_world: F64) -> float | None:
    """Height of the highest proxy surface below (or at most 6 m above) a point, or None."""

    origin = p_world.copy()
    v = (proxies.vertices - origin).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(proxies.faces.astype(np.uint32)))
    ray = np.array([[0.0, 0.0, SNAP_FROM_ABOVE, 0.0, 0.0, -1.0]], dtype=np.float32)
    t = float(scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
    if not np.isfinite(t):
        return None
    return float(origin[2] + SNAP_FROM_ABOVE - t)


def check_poles(p: F64, obj: ObjectMesh, heading: float, poles: list[Any]) -> None:
    """Refuse a footprint (the object's xy bounding box, rotated) that cuts a pole."""
    if not poles:
        return
    b = obj.bounds
    c, s = math.cos(heading), math.sin(heading)
    R = np.array([[c, -s], [s, c]])
    for pole in poles:
        axis = np.asarray(pole.axis_xy, dtype=np.float64)[:2]
        q = R.T @ (axis - p[:2])  # pole axis in the object's footprint frame
        dx = max(b[0, 0] - q[0], 0.0, q[0] - b[1, 0])
        dy = max(b[0, 1] - q[1], 0.0, q[1] - b[1, 1])
        if math.hypot(dx, dy) < float(pole.radius) + POLE_CLEARANCE:
            raise PlacementError(
                f"the object's footprint at ({p[0]:.2f}, {p[1]:.2f}) cuts pole {pole.id} "
                f"at ({axis[0]:.2f}, {axis[1]:.2f}): move it along the track or sideways"
            )
