"""Minimal scene proxies: only what the object needs to be hidden and to cast a shadow.

From the prepared sequence: track boxes along the centrelines (ballast bed up to sleeper
level, and the two rails on top, so a rail in front of a small far object hides its feet),
platform boxes from the platform planes, the ground planes, and pole boxes. Only proxies
near the object or between it and the cameras' path are built. Proxies are written to
depth only: they never show in the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from renderer.mesh import ProxyMesh

F64 = NDArray[np.float64]

RAIL_HEAD_SPACING = 1.500
RAIL_HEAD_WIDTH = 0.072
RAIL_HEIGHT = 0.18  # rail top above the sleepers / ballast crown
BED_HALF_WIDTH = 1.6  # ballast crown half width (m)
BED_DEPTH = 0.6  # box depth below the crown (m)


@dataclass(frozen=True)
class ProxyOptions:
    """How much scene to model around the object (metres)."""

    margin_along: float = 15.0  # beyond the object and before the first camera position
    corridor_half_width: float = 30.0  # lateral extent kept around the ego track
    step: float = 2.0  # segment length of track boxes
    ground_half_width: float = 40.0


def _box(center: F64, axes: F64, half: F64) -> ProxyMesh:
    """An oriented box: centre (3,), axes (3, 3) columns x, y, z, half extents (3,)."""
    signs = np.array(
        [
            [-1, -1, -1],
            [1, -1, -1],
            [1, 1, -1],
            [-1, 1, -1],
            [-1, -1, 1],
            [1, -1, 1],
            [1, 1, 1],
            [-1, 1, 1],
        ],
        dtype=np.float64,
    )
    v = center + (signs * half) @ axes.T
    f = np.array(
        [
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ],
        dtype=np.int64,
    )
    return ProxyMesh(v, f)


def _sweep(
    ego: Any, s: F64, lateral: float, half_w: float, z_top: float, depth: float
) -> ProxyMesh:
    """A box-like strip along a centreline: between lateral +- half_w, from the centreline
    height + z_top down ``depth``; quads between consecutive stations (closed sides)."""
    T = ego.frame_at(s)
    p, y, z = T[:, :3, 3], T[:, :3, 1], T[:, :3, 2]
    c = p + lateral * y
    corners = [
        c - half_w * y + z_top * z,
        c + half_w * y + z_top * z,
        c + half_w * y + (z_top - depth) * z,
        c - half_w * y + (z_top - depth) * z,
    ]
    n = len(s)
    V = np.stack(corners, axis=1).reshape(-1, 3)  # station i, corner k -> 4 i + k
    faces = []
    for i in range(n - 1):
        a, b = 4 * i, 4 * (i + 1)
        for k in range(4):
            k2 = (k + 1) % 4
            faces += [[a + k, b + k, b + k2], [a + k, b + k2, a + k2]]
    caps = [[0, 1, 2], [0, 2, 3]]
    faces += caps + [[4 * (n - 1) + q for q in reversed(c)] for c in caps]
    return ProxyMesh(V, np.asarray(faces, dtype=np.int64))


def build_proxies(
    prepared: Any,
    object_xyz: F64,
    camera_xyz: F64,
    options: ProxyOptions | None = None,
    ground_z: float | None = None,
) -> ProxyMesh:
    """Proxies near the object or between it and the camera positions.

    Parameters
    ----------
    prepared : PreparedSequence (centrelines, planes, poles).
    object_xyz : (3,) world position of the object.
    camera_xyz : (k, 3) world positions of the cameras over the frames.
    ground_z : if given and preparation found no ground plane, a horizontal ground quad at
        this height around the object (so that it still catches a shadow).
    """
    o = options or ProxyOptions()
    pts = np.vstack([object_xyz[None], camera_xyz])
    lo, hi = pts[:, :2].min(0) - o.margin_along, pts[:, :2].max(0) + o.margin_along
    parts: list[ProxyMesh] = []
    for cl in prepared.centrelines:
        s_all = np.arange(0.0, cl.length, o.step)
        s_all = np.append(s_all, cl.length)
        xy = cl.point(s_all)[:, :2]
        near = np.all((xy >= lo - o.corridor_half_width) & (xy <= hi + o.corridor_half_width), 1)
        if near.sum() < 2:
            continue
        idx = np.flatnonzero(near)
        s = s_all[idx[0] : idx[-1] + 1]
        parts.append(_sweep(cl, s, 0.0, BED_HALF_WIDTH, -RAIL_HEIGHT, BED_DEPTH))
        for side in (-1.0, 1.0):
            parts.append(
                _sweep(cl, s, side * RAIL_HEAD_SPACING / 2, RAIL_HEAD_WIDTH / 2, 0.0, RAIL_HEIGHT)
            )
    for plane in prepared.planes:
        poly = np.asarray(plane.polygon, dtype=np.float64)
        if len(poly) < 3:
            continue
        if np.any(poly[:, :2].max(0) < lo - o.corridor_half_width) or np.any(
            poly[:, :2].min(0) > hi + o.corridor_half_width
        ):
            continue
        parts.append(_plane_slab(poly, thickness=1.0 if plane.kind == "platform" else 0.05))
    if ground_z is not None and not any(p.kind == "ground" for p in prepared.planes):
        g = o.ground_half_width
        quad = np.array(
            [
                [lo[0] - g, lo[1] - g, ground_z],
                [hi[0] + g, lo[1] - g, ground_z],
                [hi[0] + g, hi[1] + g, ground_z],
                [lo[0] - g, hi[1] + g, ground_z],
            ]
        )
        parts.append(ProxyMesh(quad, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)))
    for pole in prepared.poles:
        axis = np.asarray(pole.axis_xy, dtype=np.float64)[:2]
        if np.any(axis < lo - 5) or np.any(axis > hi + 5):
            continue
        h = float(pole.top_z - pole.base_z)
        c = np.array([axis[0], axis[1], pole.base_z + h / 2])
        r = float(pole.radius)
        parts.append(_box(c, np.eye(3), np.array([r, r, h / 2])))
    return ProxyMesh.concatenate(parts)


def _plane_slab(poly: F64, thickness: float) -> ProxyMesh:
    """A polygon (k, 3) extruded down by ``thickness``: a fan top, a bottom and the sides
    (platforms are solid: their front face hides what is behind them)."""
    k = len(poly)
    top = poly
    bottom = poly - np.array([0.0, 0.0, thickness])
    V = np.vstack([top, bottom, top.mean(0, keepdims=True), bottom.mean(0, keepdims=True)])
    ct, cb = 2 * k, 2 * k + 1
    faces = []
    for i in range(k):
        j = (i + 1) % k
        faces += [[ct, i, j], [cb, k + j, k + i], [i, k + i, k + j], [i, k + j, j]]
    return ProxyMesh(V, np.asarray(faces, dtype=np.int64))
