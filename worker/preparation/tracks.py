"""Rails and tracks: the one interface over the two rail backends.

``find_tracks(cloud, trajectory, backend)`` returns a :class:`TrackResult`: a smooth
:class:`Centreline` (arc length, tangent, roll from the two rail-head heights) for every
track seen, the ego track chosen and followed.

Backends only decide *which points are rail-head tops*:

- ``"geometric"`` (:mod:`.rails_geometric`): narrow ridges ~0.15-0.2 m above the track bed;
- ``"image"`` (:mod:`.rails_image`): an ONNX segmentation model on the camera frames, the
  per-frame clouds projected into its label images.

The fitting is shared and works in the frame of a reference curve (``s`` along it,
``lateral`` left of it):

1. **Ego track.** The reference is the trajectory itself (the base origin runs on the ego
   centreline at top-of-rail height). Rail-head points within a tolerance of +-0.75 m
   (rail-head centres 1.500 m apart for the 1.435 m gauge) are binned along ``s`` (1 m);
   per bin and side the medians give the lateral offset of each rail and its height; a
   robust local-linear smoother turns them into a centreline offset, a height and a roll
   (``asin((z_left - z_right) / 1.5)``). Tolerances shrink over the passes. Because every
   pass searches only around the previous estimate, which starts on the trajectory, the
   ego track cannot jump to a neighbour or into a diverging branch where the train did
   not go.
2. **Following** beyond the driven stretch: from each end, the curve is extrapolated
   (constant curvature and grade) by a few metres, the rails measured there, the measured
   centre appended; gaps are coasted up to ``max_gap`` m; a track stops where it runs into
   an already found track (a switch) or leaves the corridor.
3. **Other tracks**: lateral histograms of the remaining rail points in 2 m slabs along the
   ego track; peaks 1.50 m apart are rail pairs; chains of pairs seed a reference that is
   refined and followed the same way. Ids: ``"0"`` ego, then ``"1"``, ``"2"``... by
   increasing distance from the ego track (left first on ties).

Units: metres, radians; world frame throughout (``p_world``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.stats import median_abs_deviation

from geometry.columns import finite_rows, zero_centre
from geometry.poses import PoseTrack
from worker.preparation.centreline import RAIL_HEAD_SPACING, Centreline
from worker.preparation.rails_geometric import (
    RidgeParams,
    corridor_mask,
    densify_polyline,
    rail_head_candidates,
)
from worker.preparation.rails_image import image_rail_candidates
from worker.preparation.registration import RegisteredCloud

if TYPE_CHECKING:
    from worker.osdar.sequence import Sequence

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
HALF = 0.5 * RAIL_HEAD_SPACING
BACKENDS = ("geometric", "image")


@dataclass
class TrackResult:
    """Tracks found in a registered cloud.

    centrelines : every track seen, ego first (track_id "0"), then "1", "2"...
    ego : the ego track's centreline (also ``centrelines[0]``), or None if no rails found.
    rail_points : (n, 3) float64 world points assigned to the rails of some track.
    warnings : human-readable warnings (degraded cases, fall-backs).
    metrics : timings and quality figures (seconds, metres, counts, fractions).
    backend : the backend used.
    """

    centrelines: list[Centreline]
    ego: Centreline | None
    rail_points: F64
    warnings: list[str] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    backend: str = "geometric"


@dataclass(frozen=True)
class FitOptions:
    """Fitting options (metres unless stated)."""

    corridor_half_width: float = 20.0
    lookahead: float = 80.0
    bin_len: float = 1.0
    station_step: float = 2.0
    sigma_offset: float = 3.0
    sigma_height: float = 3.0
    sigma_roll: float = 10.0
    tolerances: tuple[float, ...] = (0.25, 0.10, 0.05)
    follow_step: float = 5.0
    follow_tol: float = 0.12
    max_gap: float = 12.0
    merge_distance: float = 0.35
    min_track_length: float = 6.0
    min_candidates: int = 30
    other_tracks: bool = True
    max_tracks: int = 12

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> FitOptions:
        d = d or {}
        names = cls.__dataclass_fields__.keys()
        return cls(
            **{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in names}
        )


# --------------------------------------------------------------------------------------------
# small numerical helpers
# --------------------------------------------------------------------------------------------


def _group_median(key: NDArray[np.int64], val: F64) -> tuple[NDArray[np.int64], F64, NDArray]:
    """Median of ``val`` per distinct ``key``: (keys (g,), medians (g,), counts (g,))."""
    if len(key) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
    order = np.lexsort((val, key))
    k, v = key[order], val[order]
    uk, start, cnt = np.unique(k, return_index=True, return_counts=True)
    med = 0.5 * (v[start + (cnt - 1) // 2] + v[start + cnt // 2])
    return uk, med, cnt


def _local_linear(x: F64, y: F64, w: F64, xq: F64, sigma: float) -> tuple[F64, F64]:
    """Gaussian-weighted local-linear regression of y(x) at xq: (values (m,), weight sums (m,))."""
    if len(x) == 0:
        return np.full(len(xq), np.nan), np.zeros(len(xq))
    d = x[None, :] - xq[:, None]
    K = w[None, :] * np.exp(-0.5 * (d / sigma) ** 2)
    S0, S1, S2 = K.sum(1), (K * d).sum(1), (K * d * d).sum(1)
    T0, T1 = (K @ y), ((K * d) @ y)
    det = S0 * S2 - S1 * S1
    with np.errstate(invalid="ignore", divide="ignore"):
        lin = (S2 * T0 - S1 * T1) / det
        const = T0 / S0
    ok_lin = det > 1e-6 * np.maximum(S0, 1e-12) ** 2 * sigma**2
    return np.where(ok_lin, lin, const), S0


def _robust_smooth(x: F64, y: F64, w: F64, xq: F64, sigma: float, floor: float) -> tuple[F64, F64]:
    """Local-linear smoothing with one pass of outlier rejection (3 robust sigmas)."""
    yq, s0 = _local_linear(x, y, w, xq, sigma)
    if len(x) >= 4:
        fit = np.interp(x, xq, yq) if len(xq) > 1 else np.full(len(x), yq[0])
        r = y - fit
        mad = (
            float(median_abs_deviation(r[w > 0], center=zero_centre, scale="normal"))
            if np.any(w > 0)
            else floor
        )
        w2 = np.where(np.abs(r) <= 3.0 * max(mad, floor), w, 0.0)
        if w2.sum() > 0:
            yq, s0 = _local_linear(x, y, w2, xq, sigma)
    return yq, s0


def _left_normal(t: F64) -> F64:
    """(m, 3) tangents -> (m, 3) horizontal unit normals to the left."""
    n = np.stack([-t[:, 1], t[:, 0], np.zeros(len(t))], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


# --------------------------------------------------------------------------------------------
# measuring rails along a reference curve
# --------------------------------------------------------------------------------------------


@dataclass
class _Bins:
    """Per-bin rail measurements along a reference curve (all (b,))."""

    s: F64
    d_left: F64  # lateral offset of the left rail from its nominal place (NaN: none)
    d_right: F64
    v_left: F64  # rail-head height above the reference centre point (NaN: none)
    v_right: F64
    n_left: F64
    n_right: F64
    inliers: NDArray[np.int64]  # indices into the rail points used


class _RailPoints:
    """Rail-head candidate points with a 2D KD-tree."""

    def __init__(self, p_world: F64) -> None:
        self.p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        self.tree = cKDTree(self.p[:, :2]) if len(self.p) else None

    def near(self, samples: F64, radius: float) -> NDArray[np.int64]:
        if self.tree is None or len(samples) == 0:
            return np.zeros(0, np.int64)
        lists = self.tree.query_ball_point(samples[:, :2], r=radius)
        if not len(lists):
            return np.zeros(0, np.int64)
        idx = np.unique(np.concatenate([np.asarray(i, np.int64) for i in lists]))
        return idx


def _measure(
    rails: _RailPoints,
    ref: Centreline,
    s_lo: float,
    s_hi: float,
    tol: float,
    bin_len: float,
    offset: F64 | None = None,
) -> _Bins:
    """Rails around ``ref`` between s_lo and s_hi: per-bin medians of both rails.

    ``offset`` (optional, (2,) arrays s, lateral) is the expected centre offset from ``ref``.
    """
    s_lo, s_hi = max(0.0, s_lo), min(ref.length, s_hi)
    empty = _Bins(*(np.zeros(0) for _ in range(7)), inliers=np.zeros(0, np.int64))
    if s_hi - s_lo < 1e-3:
        return empty
    ss = np.arange(s_lo, s_hi + 1.0, 1.0)
    idx = rails.near(ref.point(ss), HALF + tol + 0.8)
    if len(idx) == 0:
        return empty
    pr = ref.project(rails.p[idx])
    inside = (pr.s >= s_lo) & (pr.s <= s_hi) & (pr.s > 1e-6) & (pr.s < ref.length - 1e-6)
    exp = np.zeros(len(idx)) if offset is None else np.interp(pr.s, offset[0], offset[1])
    lat = pr.lateral - exp
    half = HALF * np.cos(ref.roll(pr.s))
    side = np.where(lat >= 0, 0, 1)  # 0 left, 1 right
    d = lat - np.where(side == 0, half, -half)
    keep = inside & (np.abs(d) < tol)
    if not np.any(keep):
        return empty
    b_all = np.floor((pr.s - s_lo) / bin_len).astype(np.int64)
    key_all = np.where(keep, b_all * 2 + side, -1)
    # mode seeking per bin and side (shrinking bandwidth, starting at the expected place):
    # near a switch the other branch's rail lies within the tolerance too, and the rail
    # nearest the expectation must win, not the median between the two
    kk = np.flatnonzero(keep)
    ukey, inv = np.unique(key_all[kk], return_inverse=True)
    m = np.zeros(len(ukey))
    dk = d[kk]
    sigmas = (0.5 * tol, 0.05, 0.03, 0.02, 0.02) if tol > 0.15 else (0.03, 0.02, 0.02, 0.02)
    for sig in sigmas:
        w = np.exp(-0.5 * ((dk - m[inv]) / sig) ** 2)
        sw = np.bincount(inv, w, len(ukey))
        m = np.where(sw > 1e-9, np.bincount(inv, w * dk, len(ukey)) / np.maximum(sw, 1e-12), m)
    close = np.abs(dk - m[inv]) < min(tol, 0.04)
    keep = np.zeros(len(idx), bool)
    keep[kk[close]] = True
    if not np.any(keep):
        return empty
    b = b_all[keep]
    key = b * 2 + side[keep]
    uk, d_med, cnt = _group_median(key, d[keep] + exp[keep])
    _, v_med, _ = _group_median(key, pr.vertical[keep])
    nb = int(b.max()) + 1
    out = {k: np.full(nb, np.nan) for k in ("dl", "dr", "vl", "vr")}
    nl, nr = np.zeros(nb), np.zeros(nb)
    left = uk % 2 == 0
    bi = uk // 2
    out["dl"][bi[left]], out["vl"][bi[left]], nl[bi[left]] = d_med[left], v_med[left], cnt[left]
    out["dr"][bi[~left]], out["vr"][bi[~left]], nr[bi[~left]] = (
        d_med[~left],
        v_med[~left],
        cnt[~left],
    )
    s_mid = s_lo + (np.arange(nb) + 0.5) * bin_len
    has = (nl > 0) | (nr > 0)
    return _Bins(
        s_mid[has],
        out["dl"][has],
        out["dr"][has],
        out["vl"][has],
        out["vr"][has],
        nl[has],
        nr[has],
        idx[keep],
    )


@dataclass
class _Fit:
    """A fitted track: centre knots with roll and support flags."""

    points: F64  # (k, 3)
    roll: F64  # (k,)
    supported: NDArray[np.bool_]  # (k,) rails seen near the knot
    inliers: NDArray[np.int64]

    def centreline(self, track_id: str = "0", ego: bool = False) -> Centreline:
        return Centreline(self.points, self.roll, track_id=track_id, ego=ego)

    @property
    def length(self) -> float:
        if len(self.points) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.points[:, :2], axis=0), axis=1).sum())


def _fit_from_bins(
    ref: Centreline, bins: _Bins, s_lo: float, s_hi: float, opt: FitOptions, clip: float | None
) -> _Fit | None:
    """Smooth per-bin rail measurements into centre knots along ``ref``."""
    if len(bins.s) == 0:
        return None
    both = np.isfinite(bins.d_left) & np.isfinite(bins.d_right)
    n_eff = np.minimum(bins.n_left, bins.n_right)
    # roll from bins with both rails
    roll_meas = np.arcsin(np.clip((bins.v_left - bins.v_right) / RAIL_HEAD_SPACING, -0.2, 0.2))
    st = np.arange(s_lo, s_hi + 1e-9, opt.station_step)
    if len(st) < 2 or st[-1] < s_hi - 1e-6:
        st = np.append(st, s_hi)
    if np.any(both):
        roll_st, _ = _robust_smooth(
            bins.s[both], roll_meas[both], np.sqrt(n_eff[both]), st, opt.sigma_roll, 0.002
        )
        roll_st = np.where(np.isfinite(roll_st), roll_st, 0.0)
    else:
        roll_st = ref.roll(st)
    roll_b = np.interp(bins.s, st, roll_st)
    sr = np.sin(roll_b)
    # centre lateral offset and height from each bin (both rails, or one and the roll)
    off = np.where(
        both,
        0.5 * (bins.d_left + bins.d_right),
        np.where(np.isfinite(bins.d_left), bins.d_left, bins.d_right),
    )
    v = np.where(
        both,
        0.5 * (bins.v_left + bins.v_right),
        np.where(np.isfinite(bins.v_left), bins.v_left - HALF * sr, bins.v_right + HALF * sr),
    )
    w = np.sqrt(bins.n_left + bins.n_right) * np.where(both, 1.0, 0.5)
    if clip is not None:
        w = np.where(np.abs(off) <= clip, w, 0.0)
    off_st, s0 = _robust_smooth(bins.s, off, w, st, opt.sigma_offset, 0.01)
    v_st, _ = _robust_smooth(bins.s, v, w, st, opt.sigma_height, 0.01)
    # support: enough weight near the station
    sup = s0 >= 0.5
    if not np.any(sup):
        return None
    lo, hi = np.flatnonzero(sup)[[0, -1]]
    st, off_st, v_st, roll_st, sup = (a[lo : hi + 1] for a in (st, off_st, v_st, roll_st, sup))
    ok = np.isfinite(off_st) & np.isfinite(v_st)
    st, off_st, v_st, roll_st, sup = (a[ok] for a in (st, off_st, v_st, roll_st, sup))
    if len(st) < 2:
        return None
    c = ref.point(st)
    p = c + off_st[:, None] * _left_normal(ref.tangent(st))
    p[:, 2] = c[:, 2] + v_st
    return _Fit(p, roll_st, sup, bins.inliers)


def _refine(
    rails: _RailPoints,
    ref: Centreline,
    opt: FitOptions,
    tolerances: tuple[float, ...],
    clip_first: float | None = None,
) -> tuple[_Fit | None, Centreline]:
    """Refine a reference curve onto the rails with shrinking tolerances."""
    fit = None
    for k, tol in enumerate(tolerances):
        bins = _measure(rails, ref, 0.0, ref.length, tol, opt.bin_len)
        new = _fit_from_bins(ref, bins, 0.0, ref.length, opt, clip_first if k == 0 else tol)
        if new is None:
            break
        try:
            ref = new.centreline()
        except ValueError:
            break
        fit = new
    return fit, ref


# --------------------------------------------------------------------------------------------
# following a track beyond its known part
# --------------------------------------------------------------------------------------------


def _end_state(pts: F64, tail: float) -> tuple[float, float, float]:
    """Heading (rad), curvature (1/m) and grade at the last knot of (k, 3) ``pts``.

    Least-squares fit over the last ``tail`` metres in a frame at the end: a parabola
    (a line when the tail is shorter than 10 m, so the curvature is then 0).
    """
    seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    sel = s >= s[-1] - tail
    q = pts[sel]
    if len(q) < 3:
        d = pts[-1, :2] - pts[max(0, len(pts) - 2), :2]
        return float(np.arctan2(d[1], d[0])), 0.0, 0.0
    chord = q[-1, :2] - q[0, :2]
    a = np.arctan2(chord[1], chord[0])
    ca, sa = np.cos(a), np.sin(a)
    rel = q[:, :2] - q[-1, :2]
    x = rel[:, 0] * ca + rel[:, 1] * sa
    y = -rel[:, 0] * sa + rel[:, 1] * ca
    if np.ptp(x) >= 10.0:
        c2, c1, _ = np.polyfit(x, y, 2)
    else:
        c2, (c1, _) = 0.0, np.polyfit(x, y, 1)
    heading = a + np.arctan(c1)
    kappa = float(np.clip(2.0 * c2 / (1.0 + c1 * c1) ** 1.5, -1 / 120.0, 1 / 120.0))
    sz = s[sel] - s[-1]
    grade = float(np.clip(np.polyfit(sz, q[:, 2], 1)[0], -0.05, 0.05)) if np.ptp(sz) > 1 else 0.0
    return float(heading), kappa, grade


#: The stretch at a track's end the follower fits its next step to (m).
TAIL_SPAN_M = 40.0


def _last_stretch(pts: F64, roll: F64, span: float) -> tuple[F64, F64]:
    """The knots (k, 3) and roll (k,) of the last ``span`` metres of a polyline (and one
    knot before them)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    back = np.cumsum(seg[::-1])  # distance from the last knot back to each earlier one
    keep = int(np.searchsorted(back, span)) + 2
    return pts[-keep:], roll[-keep:]


def _predicted_reference(pts: F64, roll: F64, step: float) -> tuple[Centreline, float] | None:
    """A reference curve (the last metres of the track, continued ``step`` m with the end's
    heading, curvature and grade) and the arc length of the last knot along it; None where
    no curve fits the knots."""
    # Only the end of the track matters here: a spline through its last TAIL_SPAN_M
    # (knots further back move its end by less than 1e-6 of their change).
    tp, tr = _last_stretch(pts, roll, TAIL_SPAN_M)
    try:
        cl = Centreline(tp, tr)
    except ValueError:
        return None
    L = cl.length
    tail = min(L, 20.0)
    h0, kappa, grade = _end_state(tp, tail)
    u = np.arange(0.5, step + 1e-9, 0.5)
    # integrate heading (midpoint rule) for the horizontal arc
    du = np.diff(np.concatenate([[0.0], u]))
    hm = h0 + kappa * (u - 0.5 * du)
    xy = pts[-1, :2] + np.cumsum(np.stack([np.cos(hm), np.sin(hm)], 1) * du[:, None], axis=0)
    z = pts[-1, 2] + grade * u
    pred = np.column_stack([xy, z])
    keep_tail = cl.point(np.linspace(max(0.0, L - tail), L, 5))[:-1]
    ref_pts = np.vstack([keep_tail, pts[-1:], pred])
    ref_roll = np.full(len(ref_pts), roll[-1])
    try:
        ref = Centreline(ref_pts, ref_roll)
    except ValueError:
        return None
    return ref, float(ref.project(pts[-1:]).s[0])


def _measured_step(bins: _Bins, ref: Centreline, s_end: float) -> F64 | None:
    """The knots (k, 3) of the step past ``s_end`` placed on the measured rails, or None when
    no bin saw both rails (one rail alone can be taken for the other: a half-gauge slip).

    The lateral offset and its slope over the step are a robust weighted line through the
    bins' rail-pair centres (the smoother refines them later); the height is their median.
    """
    if not len(bins.s):
        return None
    both = np.isfinite(bins.d_left) & np.isfinite(bins.d_right)
    if int(np.sum(both)) < 1:
        return None
    off = np.where(
        both,
        0.5 * (bins.d_left + bins.d_right),
        np.where(np.isfinite(bins.d_left), bins.d_left, bins.d_right),
    )
    v = np.where(
        both,
        0.5 * (bins.v_left + bins.v_right),
        np.where(np.isfinite(bins.v_left), bins.v_left, bins.v_right),
    )
    s_new = np.arange(s_end + 1.0, ref.length + 1e-9, 1.0)
    ww = np.sqrt(bins.n_left + bins.n_right)
    a, slope = 0.0, 0.0
    x = bins.s - s_end
    fit_line = len(bins.s) >= 3 and np.ptp(bins.s) >= 2.0
    for sig in (0.03, 0.02, 0.02):
        r = off - (a + slope * x)
        wr = ww * np.exp(-0.5 * (r / sig) ** 2)
        if wr.sum() < 1e-9:
            break
        if fit_line:
            slope, a = np.polyfit(x, off, 1, w=np.sqrt(wr) + 1e-12)
            slope = float(np.clip(slope, -0.02, 0.02))
        else:
            a = float(np.sum(wr * off) / wr.sum())
    o_new = a + slope * (s_new - s_end)
    vv = float(np.median(v))
    c = ref.point(s_new)
    new_pts: F64 = c + o_new[:, None] * _left_normal(ref.tangent(s_new))
    new_pts[:, 2] = c[:, 2] + vv
    return new_pts


def _first_merge(new_pts: F64, stop_at: list[Centreline], merge_distance: float) -> int | None:
    """Index of the first knot of ``new_pts`` (k, 3) within ``merge_distance`` of another
    track (inside its ends), or None."""
    if not stop_at:
        return None
    dmin = np.full(len(new_pts), np.inf)
    for other in stop_at:
        pr = other.project(new_pts)
        inside = (pr.s > 1e-6) & (pr.s < other.length - 1e-6)
        dmin = np.minimum(dmin, np.where(inside, pr.distance, np.inf))
    hit = dmin < merge_distance
    return int(np.argmax(hit)) if np.any(hit) else None


def _extend_forward(
    rails: _RailPoints,
    pts: F64,
    roll: F64,
    opt: FitOptions,
    stop_at: list[Centreline],
    region: tuple[F64, float, float],
) -> tuple[F64, F64]:
    """Follow the track past the last knot of ``pts`` (k, 3); returns the extended knots/roll.

    Each step predicts the track ``follow_step`` m on, measures the rails around the
    prediction and keeps the measured knots, or coasts on the prediction (up to
    ``max_gap`` m); the track ends at its last measured knot. ``region`` = (trajectory
    samples (m, 3), corridor half-width, lookahead): the follower stops where the corridor
    ends, or where the track runs into another one (``stop_at``).
    """
    samples, half_width, lookahead = region
    reach = cKDTree(samples[:, :2])
    pts, roll = pts.copy(), roll.copy()
    gap = 0.0
    last_supported = len(pts)
    for _ in range(int(2 * (lookahead + 60.0) / opt.follow_step) + 4):
        predicted = _predicted_reference(pts, roll, opt.follow_step)
        if predicted is None:
            break
        ref, s_end = predicted
        bins = _measure(rails, ref, s_end, ref.length, opt.follow_tol, opt.bin_len)
        measured = _measured_step(bins, ref, s_end)
        supported = measured is not None
        if measured is not None:
            new_pts, gap = measured, 0.0
        else:
            new_pts = ref.point(np.arange(s_end + 1.0, ref.length + 1e-9, 1.0))
            gap += opt.follow_step
        if len(new_pts) == 0:
            break
        first = _first_merge(new_pts, stop_at, opt.merge_distance)
        if first is not None:
            if supported and first > 0:
                pts = np.vstack([pts, new_pts[:first]])
                roll = np.concatenate([roll, np.full(first, roll[-1])])
                last_supported = len(pts)
            break
        d, _ = reach.query(new_pts[-1, :2])
        d_ends = min(
            np.linalg.norm(new_pts[-1, :2] - samples[0, :2]),
            np.linalg.norm(new_pts[-1, :2] - samples[-1, :2]),
        )
        if d > half_width and d_ends > lookahead:
            break
        pts = np.vstack([pts, new_pts])
        roll = np.concatenate([roll, np.full(len(new_pts), roll[-1])])
        if supported:
            last_supported = len(pts)
        if gap > opt.max_gap:
            break
    return pts[:last_supported], roll[:last_supported]


def _follow_both_ways(
    rails: _RailPoints,
    fit: _Fit,
    opt: FitOptions,
    stop_at: list[Centreline],
    region: tuple[F64, float, float],
) -> tuple[F64, F64]:
    pts, roll = _extend_forward(rails, fit.points, fit.roll, opt, stop_at, region)
    pts, roll = _extend_forward(rails, pts[::-1], -roll[::-1], opt, stop_at, region)
    return pts[::-1].copy(), -roll[::-1].copy()


def _complete_track(
    rails: _RailPoints,
    ref: Centreline,
    opt: FitOptions,
    stop_at: list[Centreline],
    region: tuple[F64, float, float],
    clip_first: float | None,
) -> _Fit | None:
    """Refine around ``ref``, follow both ways, refine again (fine tolerances)."""
    fit, ref = _refine(rails, ref, opt, opt.tolerances[:2], clip_first)
    if fit is None:
        return None
    pts, roll = _follow_both_ways(rails, fit, opt, stop_at, region)
    try:
        ref = Centreline(pts, roll)
    except ValueError:
        return fit
    fit2, _ = _refine(rails, ref, opt, opt.tolerances[1:])
    return fit2 if fit2 is not None else fit


def _trim_against(fit: _Fit, others: list[Centreline], opt: FitOptions) -> _Fit | None:
    """Drop the knots of ``fit`` lying on other tracks; keep the longest remaining run."""
    if not others or len(fit.points) == 0:
        return fit
    dmin = np.full(len(fit.points), np.inf)
    for other in others:
        pr = other.project(fit.points)
        inside = (pr.s > 1e-6) & (pr.s < other.length - 1e-6)
        dmin = np.minimum(dmin, np.where(inside, pr.distance, np.inf))
    free = dmin >= opt.merge_distance
    if not np.any(free):
        return None
    # longest run of free knots
    edges = np.diff(np.concatenate([[0], free.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(ends - starts))
    sl = slice(starts[k], ends[k])
    if ends[k] - starts[k] < 2:
        return None
    return _Fit(fit.points[sl], fit.roll[sl], fit.supported[sl], fit.inliers)


# --------------------------------------------------------------------------------------------
# the ego track and the others
# --------------------------------------------------------------------------------------------


def _trajectory_reference(trajectory: PoseTrack) -> tuple[Centreline, F64]:
    """A reference curve along the trajectory (base origins), and its samples (m, 3).

    A trajectory shorter than 2 m (a standing train) becomes a 20 m straight along the
    base x axis of the middle pose.
    """
    T = np.asarray(trajectory.T, dtype=np.float64)
    ok = np.isfinite(T).all(axis=(1, 2))
    T = T[ok]
    if len(T) == 0:
        raise ValueError("trajectory has no finite poses")
    p = T[:, :3, 3]
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
    if length < 2.0:
        mid = T[len(T) // 2]
        x = mid[:3, 0].copy()
        x[2] = 0.0
        x /= max(np.linalg.norm(x), 1e-12)
        u = np.linspace(-10.0, 10.0, 21)
        pts = mid[:3, 3] + u[:, None] * x
        return Centreline(pts), pts
    # order along the base x axis of the first pose (drive direction), thin to >= 0.5 m
    dense = densify_polyline(p, 0.5)
    step = max(1, round(1.0 / 0.5))
    pts = dense[::step]
    if np.linalg.norm(pts[-1] - dense[-1]) > 1e-6:
        pts = np.vstack([pts, dense[-1]])
    return Centreline(pts), dense


#: How far (m) the trajectory may run beside its own track's centre and still have it
#: found: an INS-anchored trajectory carries the INS's lateral error (lever arm, drift:
#: decimetres), which the first pass's tolerance does not cover. Neighbouring tracks' centres
#: lie at least 3.5 m away, so a rail pair centred within this distance is the ego track.
EGO_SEARCH_M = 1.5
#: Lateral window (m) around each expected rail when scoring a shift, and the fewest rail
#: points on each side for a shift to count.
SHIFT_WINDOW_M = 0.05
SHIFT_MIN_POINTS = 4
#: A shift smaller than this (m) is left to the first pass (its tolerance is 0.25 m).
SHIFT_APPLY_M = 0.15


def _lateral_shift(rails: _RailPoints, ref: Centreline) -> tuple[float, int]:
    """The lateral offset (m, left positive) of the rail pair nearest to ``ref`` along it,
    within +-EGO_SEARCH_M, and the rail points on its weaker side (0: no pair).

    Scores every centre offset c on a 1 cm grid by the rail points within SHIFT_WINDOW_M of
    both c + HALF and c - HALF (the weaker side counts: both rails must be there), and
    takes the best, the nearest to 0 among equals.
    """
    idx = rails.near(ref.point(np.arange(0.0, ref.length + 1.0, 1.0)), HALF + EGO_SEARCH_M + 0.3)
    if len(idx) == 0:
        return 0.0, 0
    pr = ref.project(rails.p[idx])
    inside = (pr.s > 1e-6) & (pr.s < ref.length - 1e-6)
    lat = np.sort(pr.lateral[inside])
    if len(lat) == 0:
        return 0.0, 0
    c = np.round(np.arange(-EGO_SEARCH_M, EGO_SEARCH_M + 1e-9, 0.01), 2)

    def count(centre: F64) -> NDArray[np.int64]:
        lo = np.searchsorted(lat, centre - SHIFT_WINDOW_M)
        hi = np.searchsorted(lat, centre + SHIFT_WINDOW_M, side="right")
        return (hi - lo).astype(np.int64)

    score = np.minimum(count(c + HALF), count(c - HALF))
    best = int(score.max())
    if best == 0:
        return 0.0, 0
    ties = np.flatnonzero(score == best)
    k = ties[np.argmin(np.abs(c[ties]))]
    return float(c[k]), best


#: A reference shorter than this (m) is continued straight ahead for the shift search: a
#: slow train's trajectory covers a few metres where the lidars see little of the rails.
SEARCH_MIN_LENGTH_M = 10.0


def _search_reference(ref: Centreline) -> Centreline:
    """``ref`` continued straight along its end tangent to SEARCH_MIN_LENGTH_M (a curve
    of radius 190 m leaves a straight by 0.15 m over 7.5 m: inside the first pass's
    tolerance), knots 1 m apart."""
    if ref.length >= SEARCH_MIN_LENGTH_M:
        return ref
    s = np.arange(0.0, ref.length + 1e-9, 1.0)
    pts = ref.point(s)
    t = ref.tangent(np.array([ref.length]))[0]
    extra = np.arange(1.0, SEARCH_MIN_LENGTH_M - ref.length + 1.0, 1.0)
    ahead = ref.point(np.array([ref.length]))[0] + extra[:, None] * t
    roll = np.concatenate(
        [ref.roll(s), np.full(len(extra), float(ref.roll(np.array([ref.length]))[0]))]
    )
    return Centreline(np.vstack([pts, ahead]), roll)


def _shifted(ref: Centreline, offset: float) -> Centreline:
    """``ref`` moved ``offset`` m to its left (negative: right), knots 1 m apart."""
    s = np.arange(0.0, ref.length + 1e-9, 1.0)
    if s[-1] < ref.length - 1e-6:
        s = np.append(s, ref.length)
    pts = ref.point(s) + offset * _left_normal(ref.tangent(s))
    return Centreline(pts, ref.roll(s))


def _discover_seeds(
    rails: _RailPoints, ego: Centreline, exclude: NDArray[np.bool_], opt: FitOptions
) -> list[F64]:
    """Chains of rail pairs beside the ego track: list of (k, 3) world seed polylines."""
    cand = np.flatnonzero(~exclude)
    if len(cand) < 4:
        return []
    pr = ego.project(rails.p[cand])
    sel = (
        (pr.s > 1e-6) & (pr.s < ego.length - 1e-6) & (np.abs(pr.lateral) <= opt.corridor_half_width)
    )
    s, lat = pr.s[sel], pr.lateral[sel]
    if len(s) < 4:
        return []
    slab, lb = 2.0, 0.04
    n_s = int(np.ceil(ego.length / slab)) + 1
    lat_edges = np.arange(-opt.corridor_half_width - lb, opt.corridor_half_width + 2 * lb, lb)
    H, _, _ = np.histogram2d(s, lat, bins=[np.arange(n_s + 1) * slab, lat_edges])
    Hs = H.copy()
    Hs[:, 1:-1] = H[:, :-2] + 2 * H[:, 1:-1] + H[:, 2:]
    peak = (Hs[:, 1:-1] >= Hs[:, :-2]) & (Hs[:, 1:-1] > Hs[:, 2:]) & (Hs[:, 1:-1] >= 6)
    pk = np.zeros_like(Hs, bool)
    pk[:, 1:-1] = peak
    lat_c = 0.5 * (lat_edges[:-1] + lat_edges[1:])
    seeds = []
    lo_k, hi_k = int(np.floor(1.42 / lb)), int(np.ceil(1.60 / lb))
    for k in range(lo_k, hi_k + 1):
        both = pk[:, :-k] & pk[:, k:]
        i, j = np.nonzero(both)
        for a, b in zip(i, j, strict=True):
            c = 0.5 * (lat_c[b] + lat_c[b + k])
            if abs(c) > 1.1:
                seeds.append(((a + 0.5) * slab, c))
    if not seeds:
        return []
    seeds_a = np.array(sorted(set(seeds)))
    # chain seeds: neighbours within 3 slabs and 0.4 m lateral
    n = len(seeds_a)
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    tree = cKDTree(np.column_stack([seeds_a[:, 0] / (3.0 * slab), seeds_a[:, 1] / 0.4]))
    for i, j in tree.query_pairs(1.0):
        parent[find(i)] = find(j)
    roots = np.array([find(i) for i in range(n)])
    chains = []
    for r in np.unique(roots):
        m = seeds_a[roots == r]
        if len(m) < 2:
            continue
        m = m[np.argsort(m[:, 0])]
        # one lateral per slab (median)
        us, inv = np.unique(m[:, 0], return_inverse=True)
        ul = np.array([np.median(m[inv == q, 1]) for q in range(len(us))])
        c = ego.point(us) + ul[:, None] * _left_normal(ego.tangent(us))
        chains.append(c)
    chains.sort(key=len, reverse=True)
    return chains


def _fit_tracks(
    rail_p_world: F64, trajectory: PoseTrack, opt: FitOptions, warnings: list[str]
) -> tuple[list[Centreline], Centreline | None, F64, dict[str, float]]:
    rails = _RailPoints(rail_p_world)
    metrics: dict[str, float] = {}
    traj_ref, samples = _trajectory_reference(trajectory)
    region = (samples, opt.corridor_half_width, opt.lookahead)
    # the trajectory may run beside its track (an INS-anchored one by the INS's lateral
    # error): the nearest rail pair is the ego track; fit around it when it is clearly off
    search = _search_reference(traj_ref)
    shift, support = _lateral_shift(rails, search)
    ego_fit = None
    if support >= SHIFT_MIN_POINTS and abs(shift) > SHIFT_APPLY_M:
        ego_fit = _complete_track(rails, _shifted(search, shift), opt, [], region, clip_first=0.3)
        metrics["ego_search_shift_m"] = shift
        if ego_fit is not None:
            warnings.append(
                f"the ego track was found {abs(shift):.2f} m to the "
                f"{'left' if shift > 0 else 'right'} of the trajectory (the nearest rail "
                "pair): poses or registration are off laterally"
            )
    if ego_fit is None:
        ego_fit = _complete_track(rails, traj_ref, opt, [], region, clip_first=0.3)
    if ego_fit is None or ego_fit.length < opt.min_track_length:
        return [], None, np.zeros((0, 3)), metrics
    ego = ego_fit.centreline("0", ego=True)
    # how far the trajectory is from the fitted ego centreline (should be ~0)
    pr = ego.project(samples)
    inside = (pr.s > 1e-6) & (pr.s < ego.length - 1e-6)
    if np.any(inside):
        off = float(np.sqrt(np.mean(pr.lateral[inside] ** 2)))
        metrics["trajectory_lateral_rms_m"] = off
        metrics["trajectory_vertical_rms_m"] = float(np.sqrt(np.mean(pr.vertical[inside] ** 2)))
        if off > 0.1:
            warnings.append(
                f"the trajectory runs {off:.2f} m (RMS) beside the fitted ego track: poses or "
                "registration are off"
            )
    metrics["ego_length_m"] = ego.length
    metrics["ego_supported_fraction"] = float(np.mean(ego_fit.supported))
    fits: list[tuple[_Fit, Centreline]] = [(ego_fit, ego)]
    used = np.zeros(len(rails.p), bool)
    used[ego_fit.inliers] = True
    if opt.other_tracks:
        known = [ego]
        for seed in _discover_seeds(rails, ego, used, opt):
            if len(fits) >= opt.max_tracks:
                break
            dmin = np.full(len(seed), np.inf)
            for other in known:
                prs = other.project(seed)
                inside = (prs.s > 1e-6) & (prs.s < other.length - 1e-6)
                dmin = np.minimum(dmin, np.where(inside, prs.distance, np.inf))
            if np.median(dmin) < 0.6:
                continue
            try:
                ref = Centreline(seed) if len(seed) >= 2 else None
            except ValueError:
                ref = None
            if ref is None or ref.length < 1.5:
                continue
            if ref.length < 6.0:  # short chain: a straight along the ego direction
                s0 = ego.project(seed[:1]).s[0]
                t = ego.tangent(np.array([s0]))[0]
                mid = seed.mean(axis=0)
                ref = Centreline(mid + np.linspace(-4, 4, 9)[:, None] * t)
            fit = _complete_track(rails, ref, opt, known, region, clip_first=0.3)
            if fit is None:
                continue
            fit = _trim_against(fit, known, opt)
            if fit is None or fit.length < opt.min_track_length:
                continue
            cl = fit.centreline()
            known.append(cl)
            fits.append((fit, cl))
            used[fit.inliers] = True
    # ids by distance from the ego track (left first on ties)
    others = []
    for fit, cl in fits[1:]:
        pr = ego.project(cl.knots_xyz)
        inside = (pr.s > 1e-6) & (pr.s < ego.length - 1e-6)
        lat = float(np.median(pr.lateral[inside] if np.any(inside) else pr.lateral))
        others.append((abs(lat), -np.sign(lat), fit, cl))
    others.sort(key=lambda o: (o[0], o[1]))
    centrelines = [ego]
    for k, (_, _, fit, _) in enumerate(others, start=1):
        centrelines.append(fit.centreline(str(k), ego=False))
    metrics["n_tracks"] = float(len(centrelines))
    return centrelines, ego, rails.p[used], metrics


# --------------------------------------------------------------------------------------------
# the interface
# --------------------------------------------------------------------------------------------


def _empty(backend: str, warnings: list[str], metrics: dict[str, float]) -> TrackResult:
    return TrackResult([], None, np.zeros((0, 3)), warnings, metrics, backend)


def find_tracks(
    cloud: RegisteredCloud,
    trajectory: PoseTrack,
    backend: str = "geometric",
    seq: Sequence | None = None,
    options: dict | None = None,
) -> TrackResult:
    """Find the tracks in a registered cloud: every centreline, the ego one chosen.

    Parameters
    ----------
    cloud : the registered cloud (world frame, ``frame_idx`` per point).
    trajectory : the poses T_world_base the cloud was registered with (one per frame);
        the base origin runs on the ego centreline at top-of-rail height.
    backend : ``"geometric"`` (lidar only) or ``"image"`` (ONNX segmentation of the camera
        frames; needs ``seq`` and ``options["model"]``, a
        :class:`~worker.preparation.segmentation.SegmentationModel` or its config dict).
    seq : the sequence (image backend only).
    options : fit options (:class:`FitOptions` fields), ``"ridge"`` (a dict of
        :class:`~worker.preparation.rails_geometric.RidgeParams` fields) and, for the image
        backend, ``"model"``, ``"cameras"``, ``"frame_stride"``, ``"max_frames"``,
        ``"range"`` (see :func:`~worker.preparation.rails_image.image_rail_candidates`).

    Returns
    -------
    TrackResult; ``ego`` is None with a warning ``"no rails found ..."`` when no track
    could be fitted (never an exception for that). Raises ValueError for an unknown
    backend, or an image backend without ``seq``/model.
    """
    options = dict(options or {})
    if backend not in BACKENDS:
        raise ValueError(f"unknown rail backend {backend!r}; use one of {BACKENDS}")
    opt = FitOptions.from_dict(options)
    ridge = RidgeParams(**options.get("ridge", {}))
    warnings: list[str] = []
    metrics: dict[str, float] = {}
    t0 = time.perf_counter()
    xyz = np.asarray(cloud.xyz, dtype=np.float64).reshape(-1, 3)
    finite = finite_rows(xyz)
    n_bad = int(len(xyz) - finite.sum())
    if n_bad:
        warnings.append(f"{n_bad} non-finite points ignored")
    T = np.asarray(trajectory.T, dtype=np.float64)
    T_ok = np.isfinite(T).all(axis=(1, 2))
    if not np.any(T_ok):
        warnings.append("no rails found: the trajectory has no finite pose")
        return _empty(backend, warnings, metrics)
    traj_world = T[T_ok, :3, 3]
    corridor = np.zeros(len(xyz), bool)
    corridor[finite] = corridor_mask(
        xyz[finite], traj_world, opt.corridor_half_width, opt.lookahead
    )
    idx = np.flatnonzero(corridor)
    metrics["points"] = float(len(xyz))
    metrics["corridor_points"] = float(len(idx))
    t1 = time.perf_counter()
    metrics["time_corridor_s"] = t1 - t0
    if backend == "geometric":
        flags = rail_head_candidates(xyz[idx], ridge)
    else:
        if seq is None or "model" not in options:
            raise ValueError('the image backend needs seq and options["model"]')
        flags, img_metrics, img_warnings = image_rail_candidates(
            cloud.select(idx), trajectory, seq, options, ridge
        )
        metrics.update(img_metrics)
        warnings.extend(img_warnings)
    cand = xyz[idx[flags]]
    t2 = time.perf_counter()
    metrics["time_candidates_s"] = t2 - t1
    metrics["rail_candidates"] = float(len(cand))
    if len(cand) < opt.min_candidates:
        warnings.append(
            f"no rails found: {len(cand)} rail-head candidates in {len(idx)} corridor points "
            f"({backend} backend); no centreline, use a fallback (e.g. the trajectory)"
        )
        metrics["time_total_s"] = time.perf_counter() - t0
        return _empty(backend, warnings, metrics)
    centrelines, ego, rail_points, fit_metrics = _fit_tracks(cand, trajectory, opt, warnings)
    metrics.update(fit_metrics)
    t3 = time.perf_counter()
    metrics["time_fit_s"] = t3 - t2
    metrics["time_total_s"] = t3 - t0
    if ego is None:
        warnings.append(
            f"no rails found along the trajectory: {len(cand)} rail-head candidates but no "
            f"rail pair at the 1.435 m gauge ({backend} backend); no centreline, use a fallback"
        )
        return _empty(backend, warnings, metrics)
    for w in warnings:
        log.warning("tracks: %s", w)
    log.info(
        "tracks (%s): %d tracks, ego %.0f m, %d rail points in %.2f s",
        backend,
        len(centrelines),
        ego.length,
        len(rail_points),
        metrics["time_total_s"],
    )
    return TrackResult(centrelines, ego, rail_points, warnings, metrics, backend)
