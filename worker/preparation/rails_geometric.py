"""Rail-head candidates from the lidar alone (no model).

A rail head is a narrow ridge standing ~0.15-0.2 m above the track bed around it (ballast
crib, sleeper tops). On a 2D grid of the world cloud (cells ``cell`` m wide) a cell is a
rail-head cell when

- its highest point lies ``h_range`` above the local ground (the lowest point within
  ``ground_window`` m), and
- it is *narrow*: of the occupied cells on a ring of radius ``ring`` around it, only a few
  (``max_ring_high``) are about as high (within ``ring_dz``). A line crosses a ring twice;
  a platform, a wall, a car or a bush fills it.

The points of such cells near the cell's top (``top_band``) are the candidates. Pairing at
the gauge and following along the track is done by :mod:`worker.preparation.tracks`.
Everything is vectorised; the grid is processed in square tiles so memory stays bounded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt, minimum_filter

from geometry.columns import column_max, column_min, finite_rows

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class RidgeParams:
    """Parameters of the rail-head ridge detector (metres)."""

    cell: float = 0.1
    ground_window: float = 1.3
    h_range: tuple[float, float] = (0.10, 0.40)
    ring: tuple[float, float] = (0.22, 0.36)
    ring_dz: float = 0.08
    max_ring_high: float = 0.34
    min_ring_occupied: int = 4
    top_band: float = 0.035
    tile: float = 80.0


def corridor_mask(
    p_world: F64,
    traj_world: F64,
    half_width: float = 20.0,
    lookahead: float = 80.0,
    z_band: tuple[float, float] = (-2.5, 1.5),
) -> NDArray[np.bool_]:
    """Points near the trajectory: the part of the cloud worth searching for rails.

    Parameters
    ----------
    p_world : (n, 3) world points.
    traj_world : (k, 3) base origins along the trajectory (time order).
    half_width : horizontal distance to the trajectory kept (m).
    lookahead : horizontal distance kept around the first and last pose (m), so the
        track before and after the driven stretch is searched too.
    z_band : kept heights relative to the nearest trajectory sample (m); around the ends
        the band widens by 2 % of the distance (gradients).

    Returns
    -------
    (n,) bool.
    """
    p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
    ok = finite_rows(p)
    if len(traj_world) == 0 or not ok.any():
        return np.zeros(len(p), bool)
    samples = densify_polyline(np.asarray(traj_world, dtype=np.float64), 0.5)
    reach = max(half_width, lookahead)
    pf = p if ok.all() else np.where(ok[:, None], p, 0.0)
    # distance to the trajectory on a 1 m raster (distance transform; ~1 m resolution is
    # plenty for a corridor), with the height of the nearest trajectory sample
    g = 1.0
    lo = samples[:, :2].min(axis=0) - reach - 2 * g
    shape = tuple((np.ceil((samples[:, :2].max(axis=0) + reach + 2 * g - lo) / g)).astype(int) + 1)
    occ = np.ones(shape, bool)
    sij = np.floor((samples[:, :2] - lo) / g).astype(np.int64)
    occ[sij[:, 0], sij[:, 1]] = False
    zgrid = np.full(shape, np.nan)
    zgrid[sij[:, 0], sij[:, 1]] = samples[:, 2]
    dist, (ni, nj) = distance_transform_edt(occ, return_indices=True)
    # the grid cell of every point, column by column (the (n, 3) array is C-ordered)
    pi = np.floor((pf[:, 0] - lo[0]) / g).astype(np.int64)
    pj = np.floor((pf[:, 1] - lo[1]) / g).astype(np.int64)
    inb = ok & (pi >= 0) & (pj >= 0) & (pi < shape[0]) & (pj < shape[1])
    cand = np.flatnonzero(inb)
    cell = pi[cand] * shape[1] + pj[cand]
    d = dist.ravel()[cell] * g
    near = d <= reach
    cand, cell, d = cand[near], cell[near], d[near]
    nearest = ni.ravel()[cell] * shape[1] + nj.ravel()[cell]
    dz = pf[cand, 2] - zgrid.ravel()[nearest]
    in_strip = d <= half_width
    # beyond the strip: only around the first and last pose (lookahead)
    keep = in_strip.copy()
    out_idx = np.flatnonzero(~in_strip)
    qx, qy = pf[cand[out_idx], 0], pf[cand[out_idx], 1]
    d_end = np.minimum(
        np.hypot(qx - samples[0, 0], qy - samples[0, 1]),
        np.hypot(qx - samples[-1, 0], qy - samples[-1, 1]),
    )
    keep[out_idx] = d_end <= lookahead
    slack = 0.02 * np.where(in_strip, 0.0, d)
    z_ok = (dz >= z_band[0] - slack) & (dz <= z_band[1] + slack)
    out = np.zeros(len(p), bool)
    out[cand[keep & z_ok]] = True
    return out


def densify_polyline(p: F64, step: float) -> F64:
    """(k, 3) polyline -> (m, 3) points every <= ``step`` m along it (ends kept)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return p.copy()
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return p[:1].copy()
    keep = np.concatenate([[True], seg > 1e-9])
    s, p = s[keep], p[keep]
    ss = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.stack([np.interp(ss, s, p[:, i]) for i in range(3)], axis=1)


def _ring_offsets(params: RidgeParams) -> NDArray[np.int64]:
    r0, r1 = params.ring[0] / params.cell, params.ring[1] / params.cell
    n = int(np.ceil(r1))
    ii, jj = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    r = np.hypot(ii, jj)
    sel = (r >= r0) & (r <= r1)
    return np.stack([ii[sel], jj[sel]], axis=1)


def _ridge_tile(
    p: F64, inner: NDArray[np.bool_], params: RidgeParams, ring: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Candidate flags for the points of one tile (``inner``: the tile proper)."""
    c = params.cell
    # cells on the world grid of multiples of `c`: the candidates near a rail do not
    # depend on how far the cloud reaches (a narrower crop finds the same ones)
    lo = np.floor(column_min(p[:, :2]) / c) * c
    ij = np.floor((p[:, :2] - lo) / c).astype(np.int64)
    nx, ny = column_max(ij) + 1
    lin = ij[:, 0] * ny + ij[:, 1]
    z = p[:, 2]
    zmax = np.full(nx * ny, -np.inf)
    zmin = np.full(nx * ny, np.inf)
    np.maximum.at(zmax, lin, z)
    np.minimum.at(zmin, lin, z)
    w = max(3, round(params.ground_window / c) | 1)
    ground = minimum_filter(zmin.reshape(nx, ny), size=w, mode="constant", cval=np.inf)
    ground = ground.reshape(-1)
    h = zmax - ground
    with np.errstate(invalid="ignore"):
        cand = np.isfinite(h) & (h >= params.h_range[0]) & (h <= params.h_range[1])
    cells = np.flatnonzero(cand)
    if len(cells) == 0:
        return np.zeros(len(p), bool)
    ci, cj = np.divmod(cells, ny)
    top = zmax[cells]
    n_occ = np.zeros(len(cells), np.int32)
    n_high = np.zeros(len(cells), np.int32)
    for di, dj in ring:
        ni, nj = ci + di, cj + dj
        inside = (ni >= 0) & (ni < nx) & (nj >= 0) & (nj < ny)
        nb = np.full(len(cells), -np.inf)
        nb[inside] = zmax[ni[inside] * ny + nj[inside]]
        occ = np.isfinite(nb)
        n_occ += occ
        n_high += occ & (nb > top - params.ring_dz)
    narrow = (n_occ >= params.min_ring_occupied) & (
        n_high <= params.max_ring_high * np.maximum(n_occ, 1)
    )
    good = np.zeros(nx * ny, bool)
    good[cells[narrow]] = True
    return inner & good[lin] & (z >= zmax[lin] - params.top_band)


def rail_head_candidates(p_world: F64, params: RidgeParams | None = None) -> NDArray[np.bool_]:
    """Flags of the points that look like rail-head tops.

    Parameters
    ----------
    p_world : (n, 3) finite world points (a corridor of the registered cloud).
    params : detector parameters.

    Returns
    -------
    (n,) bool.
    """
    params = params or RidgeParams()
    p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(p), bool)
    if len(p) == 0:
        return out
    ring = _ring_offsets(params)
    margin = max(params.ground_window, params.ring[1]) + params.cell
    span = column_max(p[:, :2]) - column_min(p[:, :2])
    if np.prod(span / params.cell + 1) <= 4e7:  # one grid (<= ~320 MB of float64)
        return _ridge_tile(p, np.ones(len(p), bool), params, ring)
    tile = params.tile
    key = np.floor(p[:, :2] / tile).astype(np.int64)
    tiles = np.unique(key, axis=0)
    for tx, ty in tiles:
        x0, y0 = tx * tile, ty * tile
        sel = (
            (p[:, 0] >= x0 - margin)
            & (p[:, 0] < x0 + tile + margin)
            & (p[:, 1] >= y0 - margin)
            & (p[:, 1] < y0 + tile + margin)
        )
        idx = np.flatnonzero(sel)
        inner = (key[idx, 0] == tx) & (key[idx, 1] == ty)
        out[idx] |= _ridge_tile(p[idx], inner, params, ring)
    log.debug("rail-head candidates: %d of %d points", int(out.sum()), len(p))
    return out
