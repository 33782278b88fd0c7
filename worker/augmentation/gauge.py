"""The train's clearance envelope along the ego track, and where an object stands against it.

A detector on a train has to decide whether an obstacle fouls the train's path. The
envelope is the space the train sweeps: a rectangle in the cross-section of the ego track
(:class:`GaugeOutline`), swept along the ego centreline ahead of the train.

Frames
------
- world: the sequence's East-North-Up frame (m).
- track frame at arc length s: :meth:`~worker.preparation.centreline.Centreline.frame_at`:
  origin on the centreline at top-of-rail height, x along the tangent, y to the left in
  the canted rail plane, z normal to that plane.

A point's *track coordinates* (s, y, z) are its arc length on the ego centreline (the
centreline's projection, horizontal metric; beyond the centreline's ends extrapolated
along the end tangent) and its y, z in the track frame at that s. Each point is measured
in the frame at its own arc length, so the envelope bends with the curve and tilts with
the cant (a canted track leans the envelope's top towards the low rail).

Labels per object and frame (:class:`GaugeLabel`): whether the object intrudes into the
envelope ahead of the train, its lateral distance to the envelope (m, negative inside), and
its distance along the track from the train (the base frame's origin, the front of the
train in OSDaR23).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


class GaugeOutline(BaseModel):
    """The envelope's cross-section in the track frame (metres).

    half_width_m : half-width of the static vehicle gauge: 1.575 m is half of the 3.15 m
        width of the UIC G1 reference profile.
    margin_m : added on each side for the vehicle's dynamic movements (play in the track,
        sway on the suspension) and a safety allowance.
    floor_m, height_m : the envelope's bottom and top above the top of rail (G1 is 4.65 m
        high). An object lying wholly below the rail top (a flat stone between the rails)
        does not intrude.
    curve_widening_m2 : the overthrow allowance in curves: ``curve_widening_m2 / R`` is
        added to the half-width on both sides in a curve of radius R (measured by
        :func:`smoothed_curvature`; the order of the
        2.5 / R term of the kinematic gauges of EN 15273-2; not a normative calculation).
        0 switches it off.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    half_width_m: float = Field(1.575, gt=0.0, le=5.0)
    margin_m: float = Field(0.2, ge=0.0, le=5.0)
    floor_m: float = Field(0.0, ge=-1.0, le=2.0)
    height_m: float = Field(4.65, gt=0.0, le=10.0)
    curve_widening_m2: float = Field(2.5, ge=0.0, le=50.0)

    @property
    def edge_m(self) -> float:
        """The envelope's half-width on straight track (half-width + margin)."""
        return self.half_width_m + self.margin_m

    def half_width(self, curvature: ArrayLike) -> F64:
        """(n,) horizontal curvature (1/m) -> (n,) half-width (m) of the envelope there."""
        k = np.abs(np.asarray(curvature, dtype=np.float64))
        return self.edge_m + self.curve_widening_m2 * k


@dataclass(frozen=True)
class EnvelopeMeasure:
    """A set of points (one object) against the envelope; independent of the train.

    s_range : (first, last) arc length of the points on the ego centreline (m).
    inside : whether some point lies inside the envelope's cross-section.
    lateral_distance_m : the lateral distance of the points to the envelope's side (m):
        positive outside (the gap), negative inside (how far the innermost point is inside
        the side; an object across the centreline is the envelope's half-width inside).
        Measured over the points within the envelope's height band (all points when none
        is in it).
    """

    s_range: tuple[float, float]
    inside: bool
    lateral_distance_m: float


@dataclass(frozen=True)
class GaugeLabel:
    """One object in one frame: intrusion ahead, lateral distance, distance along the track.

    intrusion : inside the envelope and not wholly behind the train.
    lateral_distance_m : see :class:`EnvelopeMeasure` (negative inside).
    track_distance_m : along the ego track from the train's base origin to the nearest
        part of the object (m): positive ahead, 0 beside the train, negative behind.
    """

    intrusion: bool
    lateral_distance_m: float
    track_distance_m: float


def _points(p: ArrayLike, name: str) -> F64:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        raise ValueError(f"{name} must be (n, 3) with n >= 1, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


#: Half the arc-length window (m) the curvature of the widening is measured over: the
#: heading change across 2 x 10 m, steady against a fitted spline's local wiggles (its
#: second derivative is noisy over a few metres), short against transition curves.
CURVATURE_HALF_WINDOW_M = 10.0


def smoothed_curvature(ego: Any, s: ArrayLike, half_window: float = CURVATURE_HALF_WINDOW_M) -> F64:
    """(n,) arc lengths -> (n,) horizontal curvature (1/m, left +): the heading change
    between s - half_window and s + half_window (clamped to the centreline) over their
    distance."""
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    a = np.clip(s - half_window, 0.0, ego.length)
    b = np.clip(s + half_window, 0.0, ego.length)
    ta, tb = ego.tangent(a), ego.tangent(b)
    dh = np.arctan2(ta[:, 0] * tb[:, 1] - ta[:, 1] * tb[:, 0], (ta[:, :2] * tb[:, :2]).sum(1))
    return np.where(b - a > 1e-6, dh / np.maximum(b - a, 1e-6), 0.0)


def track_coordinates(ego: Any, p_world: ArrayLike) -> F64:
    """Track coordinates (s, y, z) of world points (module docstring).

    Parameters
    ----------
    ego : the ego :class:`~worker.preparation.centreline.Centreline`.
    p_world : (n, 3) world points.

    Returns
    -------
    (n, 3) float64: s (m along the centreline, extrapolated beyond its ends), y (m, left of
    the centreline in the canted rail plane), z (m above the rail plane).
    """
    p = _points(p_world, "p_world")
    s = ego.project(p).s
    T_world_track = ego.frame_at(s)  # (n, 4, 4)
    d = p - T_world_track[:, :3, 3]
    p_track = np.einsum("nij,ni->nj", T_world_track[:, :3, :3], d)  # R^T d per point
    # Inside the curve the projection leaves no offset along the tangent (up to the grade's
    # effect on the horizontal metric); at a clamped end that offset is the extrapolation.
    at_end = (s <= 0.0) | (s >= ego.length)
    s_out = np.where(at_end, s + p_track[:, 0], s)
    return np.column_stack([s_out, p_track[:, 1], p_track[:, 2]])


def measure_against_envelope(
    ego: Any, p_world: ArrayLike, outline: GaugeOutline | None = None
) -> EnvelopeMeasure:
    """Where a set of points (an object's vertices, (n, 3) world) lies against the envelope."""
    o = outline or GaugeOutline()
    syz = track_coordinates(ego, p_world)
    s, y, z = syz[:, 0], syz[:, 1], syz[:, 2]
    w = o.half_width(smoothed_curvature(ego, s))
    band = (z >= o.floor_m) & (z <= o.height_m)
    inside = bool(np.any(band & (np.abs(y) <= w)))
    sel = band if np.any(band) else np.ones(len(s), dtype=bool)
    y_b, w_b = y[sel], w[sel]
    lateral = float(np.min(np.abs(y_b) - w_b))
    if y_b.min() < 0.0 < y_b.max():  # across the centreline: its deepest point is on it
        lateral = min(lateral, -float(w_b.min()))
    return EnvelopeMeasure((float(s.min()), float(s.max())), inside, lateral)


def train_arc_length(ego: Any, T_world_base: ArrayLike) -> F64:
    """(m, 4, 4) base poses -> (m,) arc length of the base origins on the ego centreline."""
    T = np.asarray(T_world_base, dtype=np.float64).reshape(-1, 4, 4)
    return track_coordinates(ego, T[:, :3, 3])[:, 0]


def label_for(measure: EnvelopeMeasure, s_train: float) -> GaugeLabel:
    """The label of a measured object with the train's base origin at arc length s_train."""
    lo, hi = measure.s_range
    if s_train < lo:
        dist = lo - s_train
    elif s_train > hi:
        dist = hi - s_train
    else:
        dist = 0.0
    return GaugeLabel(measure.inside and hi > s_train, measure.lateral_distance_m, float(dist))


def gauge_labels(
    ego: Any,
    p_world_obj: ArrayLike,
    T_world_base: Mapping[int, F64],
    outline: GaugeOutline | None = None,
) -> dict[int, GaugeLabel]:
    """The gauge label of a static object in each frame.

    Parameters
    ----------
    ego : the ego Centreline (None: no labels, {}).
    p_world_obj : (n, 3) the object's points in the world frame (its mesh vertices).
    T_world_base : frame -> (4, 4) the train's base pose at that frame.
    outline : the envelope (default :class:`GaugeOutline`).
    """
    if ego is None or not T_world_base:
        return {}
    measure = measure_against_envelope(ego, p_world_obj, outline)
    frames = sorted(T_world_base)
    s_train = train_arc_length(ego, np.stack([T_world_base[f] for f in frames]))
    return {f: label_for(measure, float(st)) for f, st in zip(frames, s_train, strict=True)}


def gauge_labels_moving(
    ego: Any,
    p_world_by_frame: Mapping[int, F64],
    T_world_base: Mapping[int, F64],
    outline: GaugeOutline | None = None,
) -> dict[int, GaugeLabel]:
    """The gauge label of a moving object in each frame: its points (n, 3) world at that
    frame's timestamp (``p_world_by_frame``) against the envelope, with the train at
    ``T_world_base`` of the same frame. Frames missing from either are skipped."""
    if ego is None:
        return {}
    frames = sorted(set(p_world_by_frame) & set(T_world_base))
    if not frames:
        return {}
    s_train = train_arc_length(ego, np.stack([T_world_base[f] for f in frames]))
    return {
        f: label_for(measure_against_envelope(ego, p_world_by_frame[f], outline), float(st))
        for f, st in zip(frames, s_train, strict=True)
    }


__all__ = [
    "EnvelopeMeasure",
    "GaugeLabel",
    "GaugeOutline",
    "gauge_labels",
    "gauge_labels_moving",
    "label_for",
    "measure_against_envelope",
    "smoothed_curvature",
    "track_coordinates",
    "train_arc_length",
]
