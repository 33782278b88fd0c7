"""Hand-made prepared sequences with known geometry (no generation, no preparation)."""

from __future__ import annotations

import numpy as np

from geometry.geodesy import WorldFrame
from geometry.poses import PoseTrack
from worker.preparation.artifact import PreparedSequence
from worker.preparation.centreline import Centreline
from worker.preparation.scene_elements import Plane, Pole

#: The straight scene: an ego track along world x from x = 0 to LENGTH; the train's base
#: origin on it from x = FIRST_X, 1 m per frame (10 m/s) for FRAMES frames.
LENGTH = 300.0
FIRST_X = 20.0
FRAMES = 50


def platform(s0: float, s1: float, lat0: float, lat1: float) -> Plane:
    """A platform plane beside the straight track, 0.76 m above the rail top."""
    poly = np.array([[s0, lat0, 0.76], [s1, lat0, 0.76], [s1, lat1, 0.76], [s0, lat1, 0.76]])
    side = "left" if lat0 > 0 else "right"
    return Plane(
        kind="platform",
        normal=np.array([0.0, 0.0, 1.0]),
        offset=-0.76,
        polygon=poly,
        height=0.76,
        side=side,
        lateral=(min(lat0, lat1), max(lat0, lat1)),
        s_range=(s0, s1),
        points=1000,
        rms=0.01,
        edge=poly[:2],
        edge_offset=min(abs(lat0), abs(lat1)),
    )


def pole(pid: str, x: float, y: float, radius: float = 0.15) -> Pole:
    return Pole(
        id=pid,
        axis_xy=np.array([x, y]),
        base_z=-0.5,
        top_z=7.0,
        radius=radius,
        top_point=np.array([x, y, 7.0]),
        points=500,
        s=x,
        lateral=y,
    )


def straight_prepared(
    planes: list[Plane] | None = None, poles: list[Pole] | None = None, ego: bool = True
) -> PreparedSequence:
    """A straight, level ego track with the train driving along it (module constants)."""
    xs = np.linspace(0.0, LENGTH, 31)
    centre = Centreline(np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)]), ego=ego)
    t = 1_700_000_000.0 + 0.1 * np.arange(FRAMES)
    T = np.repeat(np.eye(4)[None], FRAMES, axis=0)
    T[:, 0, 3] = FIRST_X + np.arange(FRAMES, dtype=np.float64)
    return PreparedSequence(
        key="hand-made",
        world=WorldFrame(53.55, 9.99, 40.0),
        track=PoseTrack(t, T, frame_idx=np.arange(FRAMES)),
        centrelines=[centre] if ego else [],
        planes=planes or [],
        poles=poles or [],
        calibration=None,
        summary={"strategy": "hand-made"},
    )
