"""A lidar's range noise and dropout, measured on the real points near an object.

Object points cast into a real cloud (:func:`renderer.lidar_cast.cast_object`) get the
range noise and the dropout rate of their own sensor; :func:`measure_lidar_noise` measures
both per ``sensor_index`` on the real points in a shell around the object.

Scan lines from the timestamps
    A sensor's points sorted by ``timestamp`` fall into *columns*: runs of equal times
    (a spinning lidar fires a column of beams at once; a rosette fires one point at a
    time, a column of one). Two times more than half the median time step apart start a
    new column. A point's scan-line neighbours are, in the columns ``SCAN_OFFSETS`` away,
    the point of the nearest elevation (within half the column's median elevation step:
    the same beam), or for one-point columns simply the points fired just before and
    after. Along a scan line neighbours are a fraction of a degree apart and, on a track
    bed, run across the track (along a sleeper, not over the sleeper/crib steps).

Range noise: inverse range is linear on a plane
    For a plane ``n . x = d`` seen from an origin ``o`` along the unit direction ``u``,
    the range is ``r = (d - n . o) / (n . u)``, so ``q = 1 / r = g . u`` with
    ``g = n / (d - n . o)``: the inverse range is a *linear* function of the direction,
    whatever the origin and the incidence. Per point ``p``:

    1. ``g`` by weighted least squares on its four scan-line neighbours (the point itself
       left out; weights ``r^4``: a range error of std sigma is an error of std
       ``sigma / r^2`` in ``q``; the pseudo-inverse where the directions span only a
       plane), and the prediction ``g . u_p``;
    2. the standardised residual ``z = (q_p - g . u_p) r_p^2 / sqrt(1 + h)``, ``h =
       r_p^4 u_p^T A^+ u_p`` (``A = sum w u u^T``): ``h`` is the fit's own prediction
       variance (its leverage: the three parameters fitted), so on a plane with range
       noise sigma, ``z`` has std sigma, in metres along the ray. Points with ``h >
       MAX_LEVERAGE`` are left out (a choice from the geometry alone: no bias);
    3. only points whose neighbours are a plane among themselves: the spread of the
       neighbours' own residuals against the fit, ``s_nb = sqrt(k / (k - 3) sum w e^2 /
       sum w)`` with ``e = (q - g . u) r^2`` in metres (``k`` neighbours, three
       parameters fitted; std sigma on a plane), below ``PLANAR_SPREAD`` times the
       current estimate. A kink or a step in the
       neighbourhood (a sleeper's end, a ballast shoulder's break, a rail's foot)
       shifts ``z`` by a few centimetres, the noise's own scale: half the track bed's
       points, and the core below read 1.15-1.6x the noise with them. On a plane the
       neighbours' residuals are independent of the fitted value (least squares), so the
       choice does not bias ``z``; it is iterated with the estimate (``PLANAR_ROUNDS``).
       A spinning lidar's point takes the largest spread of itself and the points of
       the beams above and below in its column (:func:`beam_neighbour_max`);
    4. the scale of ``z``: a two-component zero-mean Gaussian scale mixture fitted by EM
       (Dempster, Laird & Rubin 1977): a core of std sigma (the noise) and a wide
       component (at least ``2 sigma``: neighbours across an edge, a rail, a corner,
       vegetation). Its start is ``1.4826 median |z|``. The core's sigma is the estimate.

    Six neighbours (``SCAN_OFFSETS``), three more than the plane's parameters: with four,
    the fit's third direction (the scan line's curvature) takes up a kink between
    symmetric neighbours exactly, and step 3 would not see it.

Dropout: missing times on a scan line
    Along a scan line the columns are fired at a regular time step (the median column
    step); between two returns of one beam ``g`` columns apart, ``g - 1`` rays of that
    beam returned nothing. Counted only within one surface: ``g < MAX_GAP_STEPS`` and the
    two ends' ranges within ``SURFACE_RANGE_STEP`` of their mean (an object's edge against
    a far background, or a sky gap, is not a dropout). ``dropout = missing / (missing +
    returned)`` over the steps that qualify.

Without a ``timestamp`` field the neighbours are the ``NOISE_NEIGHBOURS`` nearest in
direction (a 2-D patch, more often across an edge) and the dropout comes from the gaps
along elevation rings (:func:`ring_dropout`; 0 for a sensor without ring structure).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from renderer.lidar_cast import LidarNoise, point_origins

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

NOISE_SHELL_M = 10.0
WIDE_SHELL_M = 30.0  # when the shell has fewer than MIN_NOISE_POINTS usable residuals
SCAN_OFFSETS = (-3, -2, -1, 1, 2, 3)
NOISE_NEIGHBOURS = 8
NOISE_MAX_POINTS = 8000
MIN_NOISE_POINTS = 60
PLANAR_SPREAD = 1.5
PLANAR_ROUNDS = 5
START_SHARE = 0.25
MAX_LEVERAGE = 10.0
MAX_GAP_STEPS = 6
SURFACE_RANGE_STEP = 0.1
#: Elevation gap (deg) between two rings (:func:`ring_dropout`).
RING_GAP_DEG = 0.12
EM_ITERATIONS = 60
EM_TOLERANCE = 1e-5  # relative change of the core's sigma: converged
SCAN_MARGIN_M = 2.0
_MAD_TO_SIGMA = 1.4826


def measure_lidar_noise(
    fields: Mapping[str, np.ndarray],
    origins_base: Mapping[int, ArrayLike] | ArrayLike,
    centre_base: ArrayLike,
    radius: float,
    *,
    shell_m: float = NOISE_SHELL_M,
) -> dict[int, LidarNoise]:
    """Range noise and dropout per sensor_index (module docstring) from the real points in
    the shell ``radius < |p - centre_base| < radius + shell_m`` (base frame); a sensor
    with too few usable points there is measured in a shell of ``WIDE_SHELL_M``.

    fields : the cloud's columns (x, y, z, optional timestamp and sensor_index);
    origins_base : per sensor_index its origin (3,) in the base frame, or one (3,) for
    all; centre_base : (3,). Returns {sensor_index: LidarNoise} (key 0 for a cloud
    without sensor_index).
    """
    xyz = np.stack([np.asarray(fields[k], dtype=np.float64) for k in "xyz"], axis=1)
    o_all = point_origins(fields, origins_base)
    t_all = np.asarray(fields["timestamp"], np.float64) if "timestamp" in fields else None
    d = np.linalg.norm(xyz - np.asarray(centre_base, np.float64).reshape(1, 3), axis=1)
    sidx = (np.asarray(fields["sensor_index"]).astype(np.int64) if "sensor_index" in fields
            else np.zeros(len(xyz), np.int64))  # fmt: skip
    out: dict[int, LidarNoise] = {}
    ok = np.isfinite(d)
    for s in np.unique(sidx[ok & (d > radius) & (d < radius + shell_m)]):
        mine = np.flatnonzero(ok & (sidx == s))
        for outer in (radius + shell_m, radius + max(shell_m, WIDE_SHELL_M)):
            shell = mine[(d[mine] > radius) & (d[mine] < outer)]
            if len(shell) > NOISE_MAX_POINTS:  # the nearest: a smaller ball
                outer = float(np.sort(d[shell])[NOISE_MAX_POINTS - 1])
            # scan lines over the ball grown by a margin (the object's inside too), so
            # that a line leaving the shell for a moment is not a gap; the shell's own
            # points are measured
            sel = mine[d[mine] < outer + SCAN_MARGIN_M]
            inside = (d[sel] > radius) & (d[sel] <= outer)
            p, o = xyz[sel], o_all[sel]
            t = None if t_all is None else t_all[sel]
            z, spread = residuals_and_spread(p, o, t)
            z, spread = z[inside], spread[inside]
            fin = np.isfinite(z)
            z, spread = z[fin], spread[fin]
            sigma = planar_core_sigma(z, spread)
            if np.isfinite(sigma):
                break
        drop, rings = dropout_rate(p, o, t, inside)
        out[int(s)] = LidarNoise(sigma, drop, int(inside.sum()), rings)
        logger.debug("lidar noise sensor %d: %d points (%d residuals), range sigma %.4f m, "
                     "dropout %.4f (%d rings)", s, inside.sum(), len(z), sigma, drop,
                     rings)  # fmt: skip
    return out


def scan_columns(t: F64) -> NDArray[np.int64] | None:
    """(n,) column number of each point (runs of equal timestamps in time order, module
    docstring); None when all times are equal."""
    order = np.argsort(t, kind="stable")
    gap = np.diff(t[order])
    pos = gap[gap > 0]
    if len(pos) == 0:
        return None
    col_sorted = np.concatenate([[0], np.cumsum(gap > 0.5 * np.median(pos))])
    col = np.empty(len(t), np.int64)
    col[order] = col_sorted
    return col


def scan_neighbours(u: F64, t: F64, offsets: tuple[int, ...] = SCAN_OFFSETS) -> NDArray[np.int64]:
    """(n, len(offsets)) index of each point's neighbour ``offsets`` columns away on its
    scan line (module docstring), -1 where there is none. u : (n, 3) unit directions;
    t : (n,) timestamps."""
    n = len(u)
    out = np.full((n, len(offsets)), -1, np.int64)
    col = scan_columns(t)
    if col is None:
        return out
    if col.max() + 1 > 0.5 * n:  # one point per time: the time order is the scan line
        order = np.lexsort((np.arange(n), col))
        rank = np.empty(n, np.int64)
        rank[order] = np.arange(n)
        for j, step in enumerate(offsets):
            k = rank + step
            ok = (k >= 0) & (k < n)
            out[ok, j] = order[k[ok]]
        return out
    el = np.degrees(np.arcsin(np.clip(u[:, 2], -1.0, 1.0))) + 90.0  # [0, 180]
    key = col * 1000.0 + el
    order = np.argsort(key)
    ks = key[order]
    dk = np.diff(ks)[np.diff(col[order]) == 0]
    tol = 0.5 * float(np.median(dk[dk > 1e-9])) if np.any(dk > 1e-9) else 0.05
    for j, step in enumerate(offsets):
        want = (col + step) * 1000.0 + el
        at = np.searchsorted(ks, want)
        best, gap = np.full(n, -1, np.int64), np.full(n, np.inf)
        for c in (at - 1, at):
            ok = (c >= 0) & (c < n)
            cc = np.where(ok, c, 0)
            dist = np.abs(ks[cc] - want)
            better = ok & (dist < gap) & (col[order[cc]] == col + step)
            best[better], gap[better] = order[cc[better]], dist[better]
        good = gap < tol
        out[good, j] = best[good]
    return out


def standardised_residuals(p: F64, o: F64, t: F64 | None) -> F64:
    """Per point (n, 3) with its origin (n, 3) and timestamp (n,): the standardised
    inverse-range residual ``z`` (m, module docstring) against its scan-line neighbours
    (without times: its nearest neighbours in direction); NaN where it has none."""
    return residuals_and_spread(p, o, t)[0]


def residuals_and_spread(p: F64, o: F64, t: F64 | None) -> tuple[F64, F64]:
    """(z (n,), s_nb (n,)): :func:`standardised_residuals` and the spread of the
    neighbours' own residuals against the same fit (m, module docstring, step 3); NaN
    where a point has no neighbours."""
    n = len(p)
    z = np.full(n, np.nan)
    spread = np.full(n, np.nan)
    if n < len(SCAN_OFFSETS) + 1:
        return z, spread
    v = p - o
    r = np.linalg.norm(v, axis=1)
    if np.any(r <= 1e-6):
        return z, spread
    u = v / r[:, None]
    if t is not None:
        nb = scan_neighbours(u, t)
    else:
        k = min(NOISE_NEIGHBOURS, n - 1)
        found = np.asarray(cKDTree(u).query(u, k=k + 1)[1], np.int64)
        nb = found[:, 1:]
    ok = np.all(nb >= 0, axis=1)
    if not ok.any():
        return z, spread
    un, rn = u[nb[ok]], r[nb[ok]]  # (m, k, 3), (m, k)
    w = rn**4
    scale = w.mean(axis=1)
    A = np.einsum("nk,nki,nkj->nij", w, un, un) / scale[:, None, None]
    b = np.einsum("nk,nki->ni", w / rn, un) / scale[:, None]
    Ainv = np.linalg.pinv(A, rcond=1e-14, hermitian=True)
    g = np.einsum("nij,nj->ni", Ainv, b)
    uo, ro = u[ok], r[ok]
    lev = np.einsum("ni,nij,nj->n", uo, Ainv, uo) / scale * ro**4
    zo = (1.0 / ro - np.einsum("ni,ni->n", g, uo)) * ro**2 / np.sqrt(1.0 + lev)
    zo[lev > MAX_LEVERAGE] = np.nan
    z[ok] = zo
    res_nb = (1.0 / rn - np.einsum("ni,nki->nk", g, un)) * rn**2  # (m, k) metres
    dof = max(un.shape[1] - 3, 1)
    spread[ok] = np.sqrt(np.sum(w * res_nb**2, axis=1) / np.sum(w, axis=1) * un.shape[1] / dof)
    if t is not None:
        spread = beam_neighbour_max(spread, u, t)
    return z, spread


def beam_neighbour_max(spread: F64, u: F64, t: F64) -> F64:
    """(n,) each point's ``spread`` (n,) or that of the points next to it in elevation in
    its column (the beams above and below: u (n, 3) unit directions, t (n,) times),
    whichever is larger (NaN counts as none): a kink running across the scan lines is
    often seen better by the next beam's neighbours. Unchanged for one point per
    column (a rosette)."""
    col = scan_columns(t)
    if col is None or col.max() + 1 > 0.5 * len(t):
        return spread
    el = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    order = np.lexsort((el, col))
    sp, cc = spread[order], col[order]
    out = sp.copy()
    same = cc[1:] == cc[:-1]
    out[1:] = np.where(same, np.fmax(out[1:], sp[:-1]), out[1:])
    out[:-1] = np.where(same, np.fmax(out[:-1], sp[1:]), out[:-1])
    res = np.empty_like(out)
    res[order] = out
    return res


def planar_core_sigma(z: F64, spread: F64) -> float:
    """:func:`core_sigma` of the ``z`` (n,) whose neighbours' ``spread`` (n,) is below
    ``PLANAR_SPREAD`` times the estimate (module docstring, step 3), iterated from the
    points of the flattest ``START_SHARE`` of neighbourhoods (at least the flattest
    ``MIN_NOISE_POINTS``): from above, the kinks a large estimate lets in would hold it
    there. NaN with fewer than ``MIN_NOISE_POINTS`` chosen."""
    n_start = min(max(int(START_SHARE * len(z)), MIN_NOISE_POINTS), len(z))
    chosen = np.zeros(len(z), bool)
    chosen[np.argsort(spread, kind="stable")[:n_start]] = True
    sigma = core_sigma(z[chosen])
    for _ in range(PLANAR_ROUNDS):
        if not np.isfinite(sigma):
            break
        now = spread < PLANAR_SPREAD * sigma
        if np.array_equal(now, chosen):
            break  # the same points: the same estimate
        chosen = now
        sigma = core_sigma(z[chosen])
    return sigma


def core_sigma(z: F64) -> float:
    """Std of the core of a zero-mean two-Gaussian scale mixture fitted to ``z`` by EM
    (module docstring); NaN for fewer than ``MIN_NOISE_POINTS`` values."""
    z = np.asarray(z, np.float64)
    z = z[np.isfinite(z)]
    if len(z) < MIN_NOISE_POINTS:
        return float("nan")
    z2 = z * z
    s1 = max(_MAD_TO_SIGMA * float(np.median(np.abs(z))), 1e-9)
    s2 = max(3.0 * s1, float(np.sqrt(z2.mean())))
    eps = 0.3
    for _ in range(EM_ITERATIONS):
        l1 = (1.0 - eps) / s1 * np.exp(-0.5 * z2 / s1**2)
        l2 = eps / s2 * np.exp(-0.5 * z2 / s2**2)
        w = l1 / np.maximum(l1 + l2, 1e-300)
        last = s1
        s1 = max(float(np.sqrt(np.sum(w * z2) / max(w.sum(), 1e-12))), 1e-9)
        s2 = max(float(np.sqrt(np.sum((1.0 - w) * z2) / max((1.0 - w).sum(), 1e-12))), 2 * s1)
        eps = float(np.clip(1.0 - w.mean(), 1e-6, 1.0 - 1e-6))
        if abs(s1 - last) <= EM_TOLERANCE * s1:
            break
    return s1


def dropout_rate(
    p: F64, o: F64, t: F64 | None, counted: NDArray[np.bool_] | None = None
) -> tuple[float, int]:
    """(dropout fraction, rings) of one sensor's points (n, 3) from their origins (n, 3)
    and timestamps (n,): missing steps along the scan lines within one surface (module
    docstring), over the steps that start at a ``counted`` point (n,) (default all).
    rings: the median points per column (the beams; 0 for one point per
    column, a rosette). Without times: :func:`ring_dropout`."""
    if len(p) < 20:
        return 0.0, 0
    if t is None:
        return ring_dropout(p, o)
    col = scan_columns(t)
    if col is None:
        return 0.0, 0
    counts = np.bincount(col)
    rings = int(np.median(counts)) if np.median(counts) > 1 else 0
    t_col = np.bincount(col, weights=t) / np.maximum(counts, 1)
    step = float(np.median(np.diff(t_col)))
    if not np.isfinite(step) or step <= 0:
        return 0.0, 0
    v = p - o
    r = np.linalg.norm(v, axis=1)
    u = v / np.maximum(r, 1e-12)[:, None]
    # each point's next return on its scan line: the first of the next columns
    nb = scan_neighbours(u, t, tuple(range(1, MAX_GAP_STEPS)))
    has = nb >= 0
    first = np.argmax(has, axis=1)
    nxt = np.where(has.any(axis=1), nb[np.arange(len(p)), first], -1)
    ok = (nxt >= 0) & (np.ones(len(p), bool) if counted is None else counted)
    g = np.round((t[nxt[ok]] - t[ok]) / step)
    same = np.abs(r[nxt[ok]] - r[ok]) < SURFACE_RANGE_STEP * 0.5 * (r[nxt[ok]] + r[ok])
    use = same & (g >= 1) & (g < MAX_GAP_STEPS)
    missing, returned = float(np.sum(g[use] - 1.0)), int(use.sum())
    if returned == 0:
        return 0.0, rings
    return missing / (missing + returned), rings


def ring_dropout(p: F64, o: F64) -> tuple[float, int]:
    """(dropout fraction, rings found) without timestamps: rings as clusters of the
    elevation seen from the origins, a gap of g azimuth steps (the ring's median step,
    g < MAX_GAP_STEPS) holding g - 1 missing returns; (0, 0) without ring structure."""
    v = p - o
    rng_m = np.linalg.norm(v, axis=1)
    el = np.degrees(np.arcsin(np.clip(v[:, 2] / np.maximum(rng_m, 1e-12), -1.0, 1.0)))
    az = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    order = np.argsort(el)
    gaps = np.flatnonzero(np.diff(el[order]) > RING_GAP_DEG)
    rings = np.split(order, gaps + 1)
    missing = returned = 0
    n_rings = 0
    for ring in rings:
        if len(ring) < 20:
            continue
        a = np.sort(az[ring])
        da = np.diff(a)
        da = da[da > 1e-6]
        if len(da) < 10:
            continue
        step = float(np.median(da))
        g = np.round(da / step)
        inside = g < MAX_GAP_STEPS
        missing += int(np.sum(g[inside] - 1.0))
        returned += int(inside.sum()) + 1
        n_rings += 1
    if n_rings < 2 or returned == 0:
        return 0.0, 0
    return missing / (missing + returned), n_rings
