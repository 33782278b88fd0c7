"""Height, roll and pitch between frame pairs from the ground both frames see.

KISS-ICP runs on the clouds without their ground (the ground is sampled in the same
pattern every frame and pins point-to-point ICP at zero motion; see
:func:`~worker.preparation.localization.odometry.remove_ground`), so its vertical motion,
roll and pitch come from the structures above the ground only and drift: on the synthetic
scenes by 0.04 deg of pitch over 10 frames, which is 5 px at 50 m on rgb_highres_center.

The ground is the best reference for exactly those three. For a pair of frames (k, j) the
ground points of frame j, moved into frame k by the odometry's relative pose, must lie on
the ground surface frame k saw; the height residuals against frame k's height grid give the
vertical offset, roll and pitch of frame j in frame k (three unknowns of a small-angle
linear least squares, iteratively trimmed). The along-track and lateral motion and the
heading stay the odometry's: a height grid says nothing about them.

Measured on the synthetic klein_flottbek (100 frames; relative errors against the truth,
rms): pitch over 1 / 10 / 30 frames 0.009 / 0.039 / 0.080 deg (KISS-ICP) ->
0.001 / 0.004 / 0.014 deg; height 3.5 / 11 / 7.5 mm -> 1.3 / 4.1 / 10 mm; roll halved.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

#: The part of each frame's cloud used (base frame, m): behind, ahead, either side.
BOX_X = (-30.0, 80.0)
BOX_Y = (-20.0, 20.0)
#: Ground: points within this height (m) of their column's lowest point, columns this
#: wide (m).
COLUMN_M = 1.0
GROUND_BAND_M = 0.08
#: Height grid cell (m) and ground points kept per frame (evenly strided).
CELL_M = 0.5
MAX_POINTS = 4000
#: Input points used (every STRIDE-th).
STRIDE = 2
#: Fewer matched ground points than this: the pair says nothing.
MIN_MATCHED = 300
#: Frame offsets of the pairs the odometry computes as it goes (``fused``'s default lags).
LAGS = (1, 10)
#: Trim residuals beyond this many robust sigmas (floor in m).
TRIM_SIGMAS = 3.0
TRIM_FLOOR_M = 0.005
#: The normal distribution's median absolute deviation in sigmas (``special.ndtri(0.75)``,
#: the constant of ``scipy.stats.median_abs_deviation(..., scale="normal")``).
MAD_PER_SIGMA = 0.6744897501960817


@dataclass(frozen=True)
class FrameGround:
    """One frame's ground: points (m, 3) in its base frame and its height grid."""

    points: F64
    grid: F64  # (nx, ny) mean ground height per CELL_M cell, NaN where empty


@dataclass(frozen=True)
class GroundPair:
    """Correction of the relative pose of frame ``j`` in frame ``k``.

    ``C @ T_k_j`` is the corrected relative pose, ``C`` a rotation by (roll, pitch) about
    frame k's origin and a vertical shift ``dz``. ``matched`` ground points were used,
    ``rms_m`` their height residual.
    """

    k: int
    j: int
    T_k_j: F64  # (4, 4) the corrected relative pose
    matched: int
    rms_m: float


def frame_ground(points_base: NDArray[np.floating], floor: F64 | None = None) -> FrameGround:
    """Ground points and height grid of one frame.

    points_base : (n, 3) the frame's cloud in its base frame (float32 clouds used as stored).
    floor : (n,) ``column_floor(points_base, COLUMN_M)`` (the lowest point of each point's
        column) when the caller has it already: the odometry's ground removal computes it
        for every frame. Computed here otherwise.
    """
    if floor is None:
        floor = column_floor(points_base, COLUMN_M)
    # Every STRIDE-th point: the ground is sampled far more densely than a 0.5 m grid needs.
    # One selection (in the box, near the floor), then float64 for the kept points only.
    p = points_base[::STRIDE]
    x, y = p[:, 0], p[:, 1]
    keep = (x > BOX_X[0]) & (x < BOX_X[1]) & (y > BOX_Y[0]) & (y < BOX_Y[1])
    keep &= p[:, 2] < floor[::STRIDE] + GROUND_BAND_M
    g = np.asarray(p[keep], dtype=np.float64)
    grid = _height_grid(g)
    if len(g) > MAX_POINTS:
        g = g[:: int(np.ceil(len(g) / MAX_POINTS))]
    return FrameGround(g, grid)


def column_floor(points: NDArray[np.floating], cell: float) -> F64:
    """(n,) height of the lowest point in each point's ``cell`` x ``cell`` m column.

    points : (n, 3); columns are cells of the x-y plane (any extent: a dense table of the
    columns when it is small, else the occupied ones only).
    """
    if len(points) == 0:
        return np.zeros(0)
    i = np.floor(points[:, 0] / cell).astype(np.int64)
    j = np.floor(points[:, 1] / cell).astype(np.int64)
    i -= i.min()
    j -= j.min()
    col = i * (int(j.max()) + 1) + j
    if int(col.max()) < max(4 * len(col), 1 << 16):
        size = int(col.max()) + 1
    else:
        _, col = np.unique(col, return_inverse=True)
        col = col.reshape(-1)
        size = int(col.max()) + 1
    z_min = np.full(size, np.inf)
    np.minimum.at(z_min, col, points[:, 2])
    return z_min[col]


def _grid_shape() -> tuple[int, int]:
    return (
        int(np.ceil((BOX_X[1] - BOX_X[0]) / CELL_M)),
        int(np.ceil((BOX_Y[1] - BOX_Y[0]) / CELL_M)),
    )


def _height_grid(g: F64) -> F64:
    """(nx, ny) mean height of the ground points (m, 3) per cell; NaN where empty."""
    nx_grid, ny_grid = _grid_shape()
    i = np.clip(((g[:, 0] - BOX_X[0]) / CELL_M).astype(np.int64), 0, nx_grid - 1)
    j = np.clip(((g[:, 1] - BOX_Y[0]) / CELL_M).astype(np.int64), 0, ny_grid - 1)
    flat = i * ny_grid + j
    s = np.bincount(flat, weights=g[:, 2], minlength=nx_grid * ny_grid)
    c = np.bincount(flat, minlength=nx_grid * ny_grid)
    with np.errstate(invalid="ignore", divide="ignore"):
        h = np.where(c > 0, s / c, np.nan)
    return h.reshape(nx_grid, ny_grid)


def _grid_heights(grid: F64, xy: F64) -> F64:
    """Bilinear heights of the grid at (m, 2) base positions; NaN off the grid or next to
    an empty cell."""
    fi = (xy[:, 0] - BOX_X[0]) / CELL_M - 0.5
    fj = (xy[:, 1] - BOX_Y[0]) / CELL_M - 0.5
    return map_coordinates(grid, [fi, fj], order=1, mode="constant", cval=np.nan)


def ground_pair(
    ground_k: FrameGround, ground_j: FrameGround, T_k_j: F64, k: int = 0, j: int = 0
) -> GroundPair | None:
    """Correct the relative pose ``T_k_j`` (4, 4) (frame j's base in frame k's) in height,
    roll and pitch from frame j's ground on frame k's height grid; None when too few ground
    points match."""
    if len(ground_j.points) < MIN_MATCHED:
        return None
    q = ground_j.points @ T_k_j[:3, :3].T + T_k_j[:3, 3]
    # The correction moves points vertically only: the grid heights under them are fixed.
    r0 = q[:, 2] - _grid_heights(ground_k.grid, q[:, :2])
    finite = np.isfinite(r0)
    if int(np.sum(finite)) < MIN_MATCHED:
        return None
    q, r0 = q[finite], r0[finite]
    A = np.stack([np.ones(len(q)), q[:, 1], -q[:, 0]], axis=1)  # d(residual)/d(dz, roll, pitch)
    x = np.zeros(3)
    ok = np.ones(len(q), dtype=bool)
    r = r0
    for _ in range(4):
        r = r0 + A @ x
        r_ok = r[ok]
        med = float(np.median(r_ok))
        spread = max(_spread_about_zero(r_ok - med), TRIM_FLOOR_M)
        keep = np.abs(r - med) < TRIM_SIGMAS * spread
        if int(np.sum(keep)) < MIN_MATCHED:
            return None
        if np.array_equal(keep, ok) and np.any(x):
            break
        ok = keep
        x = _least_squares(A[ok], -r0[ok])
    r = r0 + A @ x
    if not np.all(np.isfinite(x)):
        return None
    C = np.eye(4)
    C[:3, :3] = _small_rotation(x[1], x[2])
    C[2, 3] = x[0]
    rms = float(np.sqrt(np.mean(r[ok] ** 2))) if np.any(ok) else float("nan")
    return GroundPair(k, j, C @ T_k_j, int(np.sum(ok)), rms)


def symmetric_ground_pair(
    ground_k: FrameGround, ground_j: FrameGround, T_k_j: F64, k: int = 0, j: int = 0
) -> GroundPair | None:
    """:func:`ground_pair` both ways, averaged: frame j's ground on frame k's grid and
    frame k's on frame j's (inverted), the mean of the two corrected relative poses.

    Each frame's ground is its points near their column's lowest point, and that selection
    depends on how densely the frame sampled the column: a column seen from nearer has more
    points, a lower minimum and a lower band. One way, the pair carries the difference of
    the two frames' selections as a height, roll and pitch bias (klein_flottbek, 100
    frames, good INS: roll +4.0 mdeg per frame pair, which the chain of lag-1 pairs made
    15 mdeg over 30 frames); the other way the same difference has the opposite sign, and
    the mean cancels most of it (lag 1: roll bias 0.07 mdeg, rms 8.3 -> 5.6; lag 10:
    bias halved). Tried and left: a per-cell plane instead of the cell's mean height and a
    second selection symmetric about the first surface (both noisier at lag 10 on the
    matrix's cells). None when either way is None.
    """
    fwd = ground_pair(ground_k, ground_j, T_k_j, k, j)
    if fwd is None:
        return None
    bwd = ground_pair(ground_j, ground_k, np.linalg.inv(T_k_j), j, k)
    if bwd is None:
        return None
    T_b = np.linalg.inv(bwd.T_k_j)
    R_f = fwd.T_k_j[:3, :3]
    half = 0.5 * Rotation.from_matrix(R_f.T @ T_b[:3, :3]).as_rotvec()
    T = np.eye(4)
    T[:3, :3] = R_f @ Rotation.from_rotvec(half).as_matrix()
    T[:3, 3] = 0.5 * (fwd.T_k_j[:3, 3] + T_b[:3, 3])
    return GroundPair(k, j, T, min(fwd.matched, bwd.matched), 0.5 * (fwd.rms_m + bwd.rms_m))


def _spread_about_zero(r: F64) -> float:
    """Robust sigma of (m,) residuals about zero: their median absolute value over
    :data:`MAD_PER_SIGMA`. The same number, bit for bit, as ``scipy.stats.
    median_abs_deviation(r, center=zero_centre, scale="normal")``, without its argument
    checking and the median it takes only to shape the centre (7.7 against 15 ms a pair).
    """
    return float(np.median(np.abs(r))) / MAD_PER_SIGMA


def _least_squares(A: F64, b: F64) -> F64:
    """argmin |A x - b| for (m, 3) ``A``: the normal equations (a 3 x 3 solve, a tenth of
    ``lstsq``'s time on thousands of rows), ``lstsq`` when they are singular."""
    try:
        return np.linalg.solve(A.T @ A, A.T @ b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(A, b, rcond=None)[0]


def _small_rotation(roll: float, pitch: float) -> F64:

    return Rotation.from_rotvec([roll, pitch, 0.0]).as_matrix()


def pairs_ending_at(
    grounds: list[FrameGround], T_odom_base: F64, j: int, lags: tuple[int, ...]
) -> list[GroundPair]:
    """The ground pairs (j - lag, j) for every lag: what frame j adds once its pose is known.

    grounds : the frames' :func:`frame_ground` (at least up to j); T_odom_base : (>= j + 1,
    4, 4) the odometry's poses (non-finite ones make no pair).
    """
    out = []
    for lag in lags:
        k = j - lag
        if k < 0 or not (
            np.all(np.isfinite(T_odom_base[k])) and np.all(np.isfinite(T_odom_base[j]))
        ):
            continue
        T_k_j = np.linalg.inv(T_odom_base[k]) @ T_odom_base[j]
        pair = symmetric_ground_pair(grounds[k], grounds[j], T_k_j, k, j)
        if pair is not None:
            out.append(pair)
    return out


def ground_pairs(
    grounds: list[FrameGround], T_odom_base: F64, lags: tuple[int, ...]
) -> list[GroundPair]:
    """Ground corrections of the odometry's relative poses for every pair (k, k + lag), in
    the order (lag, k).

    Parameters
    ----------
    grounds : per frame its :func:`frame_ground`.
    T_odom_base : (n, 4, 4) the odometry's poses.
    lags : frame offsets of the pairs.
    """
    pairs = [
        pr for j in range(len(grounds)) for pr in pairs_ending_at(grounds, T_odom_base, j, lags)
    ]
    return in_lag_order(pairs, lags)


def in_lag_order(pairs: list[GroundPair], lags: tuple[int, ...]) -> list[GroundPair]:
    """``pairs`` sorted by (position of their lag in ``lags``, first frame)."""
    rank = {lag: i for i, lag in enumerate(lags)}
    return sorted(pairs, key=lambda pr: (rank[pr.j - pr.k], pr.k))
