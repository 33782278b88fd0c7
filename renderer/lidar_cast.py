"""Lidar augmentation: a virtual object cast into a real point cloud (pipeline step 6).

For every point of the cloud, the ray from its sensor's origin through the point is
cast against the object (open3d ``RaycastingScene``, Embree). Where the object is hit
before the point's range, the point moves onto the object's surface: x, y, z replaced,
intensity from the object's reflectivity times ``|cos(incidence)|`` in the sensor's
intensity scale; every other field (timestamp, sensor_index, ...) is kept. Points whose
ray misses the object, or meets it only behind the point (the real scene occludes it),
are returned bit-identical.

What this does not do (and why)
-------------------------------
- The point count is kept: no point is added for rays that returned nothing (sky, out of
  range) but would have hit the object, because the real cloud does not say which rays
  the sensor fired. An object seen against the sky gets returns only where something
  was behind it. No point is dropped either.
- Origins are fixed points in the base frame: a per-``sensor_index`` dict (the mounting
  positions, known on synthetic data from ``ground_truth/lidar_origins.json``, or
  estimated) or one (3,) point, the OSDaR-AR paper's single origin, as the fallback. The
  OSDaR23 clouds are motion-compensated, so while the train moves the true origin of a
  point drifts along the track by up to speed x 50 ms within a sweep; that residual is
  not modelled.

Sensor noise (``range_sigma`` and ``dropout`` of :func:`cast_object`): object points
get the range noise and the dropout rate of their own sensor, measured on the real
points of the same ``sensor_index`` around the object
(:func:`renderer.lidar_noise.measure_lidar_noise`).

A dropped object point is a ray that returned nothing: :func:`cast_object` removes it
from the cloud (``LidarCastResult.kept``); with ``dropout = 0`` (the default) the point
count is kept as described above.

Numerics: the mesh, ray origins and directions are expressed in the object frame in
float64 and only then cast to float32 for Embree (magnitudes of tens of metres: ~2 um);
the new points are computed in float64 and stored in the field's dtype.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from geometry.transforms import invert_T, pose_to_T
from renderer.mesh import ObjectMesh

F64 = NDArray[np.float64]
logger = logging.getLogger(__name__)

_MIN_RANGE_M = 1e-3
"""Points closer to their origin than this are never cast (no direction)."""
_NOISE_TRUNCATION = 3.0


@dataclass
class LidarCastResult:
    """Output of :func:`cast_object`.

    Attributes
    ----------
    fields : the new cloud, a new dict of new arrays (same keys, dtypes, order, length).
    object_indices : (k,) int64 sorted indices of the points now on the object (the
        annotation's ``vec``).
    moved : k.
    cos_incidence : (k,) float64 |cos| of the incidence angle at those points.
    kept : None when no point was dropped (``fields`` has the input's length), else the
        (n_out,) input index of every output point; ``object_indices`` then index the
        output. dropped : input indices of the object rays that returned nothing.
    """

    fields: dict[str, np.ndarray]
    object_indices: NDArray[np.int64]
    moved: int
    cos_incidence: F64
    kept: NDArray[np.int64] | None = None
    dropped: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))


def origins_from_json(entries: Sequence[Mapping]) -> dict[int, F64]:
    """``ground_truth/lidar_origins.json`` (or the same layout from an estimate) ->
    {sensor_index: (3,) origin in the base frame}."""
    out: dict[int, F64] = {}
    for e in entries:
        T = pose_to_T(e["translation"], e.get("quaternion", [0.0, 0.0, 0.0, 1.0]))
        out[int(e["sensor_index"])] = T[:3, 3].copy()
    return out


def point_origins(
    fields: Mapping[str, np.ndarray], origins_base: Mapping[int, ArrayLike] | ArrayLike
) -> F64:
    """(n, 3) float64 ray origin of every point: by ``sensor_index`` or one for all.

    Raises
    ------
    ValueError : a dict without an entry for some sensor_index of the cloud, or no
        ``sensor_index`` field.
    """
    n = len(fields["x"])
    if isinstance(origins_base, Mapping):
        if "sensor_index" not in fields:
            raise ValueError("per-sensor origins need a sensor_index field in the cloud")
        sidx = np.asarray(fields["sensor_index"]).astype(np.int64)
        present = np.unique(sidx)
        missing = sorted(set(present.tolist()) - {int(k) for k in origins_base})
        if missing:
            raise ValueError(f"no origin for sensor_index {missing}; known: {sorted(origins_base)}")
        out = np.empty((n, 3))
        for k in present:
            out[sidx == k] = np.asarray(origins_base[int(k)], dtype=np.float64).reshape(3)
        return out
    o = np.asarray(origins_base, dtype=np.float64).reshape(3)
    return np.broadcast_to(o, (n, 3)).copy()


def _object_scene(mesh: ObjectMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene(nthreads=0)
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene


def _candidates(mesh: ObjectMesh, o_obj: F64, p_obj: F64) -> NDArray[np.int64]:
    """Indices of points whose segment origin -> point passes the object's bounding
    sphere (everything else cannot meet the object)."""
    b = mesh.bounds
    c = 0.5 * (b[0] + b[1])
    rad = 0.5 * float(np.linalg.norm(b[1] - b[0])) + 1e-3
    seg = p_obj - o_obj
    L2 = np.einsum("ij,ij->i", seg, seg)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.clip(np.einsum("ij,ij->i", c - o_obj, seg) / L2, 0.0, 1.0)
    closest = o_obj + t[:, None] * seg
    d = np.linalg.norm(closest - c, axis=1)
    ok = np.isfinite(d) & (d <= rad) & (L2 > _MIN_RANGE_M**2)
    return np.flatnonzero(ok)


def _to_obj(T_obj_base: F64, p: F64) -> F64:
    return p @ T_obj_base[:3, :3].T + T_obj_base[:3, 3]


def cast_object(
    fields: Mapping[str, np.ndarray],
    mesh: ObjectMesh,
    T_base_obj: ArrayLike,
    origins_base: Mapping[int, ArrayLike] | ArrayLike,
    *,
    intensity_scale: Mapping[int, float] | float = 255.0,
    seed: int = 0,
    range_sigma: Mapping[int, float] | float = 0.0,
    intensity_noise: float = 0.0,
    dropout: Mapping[int, float] | float = 0.0,
) -> LidarCastResult:
    """Cast ``mesh`` placed at ``T_base_obj`` into one lidar frame.

    Parameters
    ----------
    fields : the PCD's columns, base frame: x, y, z (n,), intensity (n,), sensor_index
        (n,) when ``origins_base`` is a dict, any others (kept).
    mesh : the object, object frame.
    T_base_obj : (4, 4) pose of the object in the base frame of this frame.
    origins_base : {sensor_index: (3,)} ray origins in the base frame, or one (3,)
        origin for every point (the paper's single-origin fallback).
    intensity_scale : full-scale intensity per sensor_index (dict) or for all: the
        intensity of an object point is ``scale * reflectivity * |cos(incidence)|``,
        rounded when the input's intensities of that sensor are all integers.
    seed : seeds the optional noises below.
    range_sigma : Gaussian range noise (m, truncated at 3 sigma) added along the ray to
        object points, per sensor_index (dict, e.g. from
        :func:`renderer.lidar_noise.measure_lidar_noise`) or for all; 0 = exactly on the
        surface.
    intensity_noise : relative Gaussian intensity noise on object points.
    dropout : probability that an object ray returns nothing (per sensor_index or for
        all): such points are removed (``LidarCastResult.kept``).

    Returns
    -------
    LidarCastResult (the input arrays are not modified).
    """
    n = _check_cloud(fields)
    T_base_obj = np.asarray(T_base_obj, dtype=np.float64).reshape(4, 4)
    out = {k: np.array(v, copy=True) for k, v in fields.items()}
    empty = LidarCastResult(out, np.zeros(0, np.int64), 0, np.zeros(0))
    if n == 0 or len(mesh.faces) == 0:
        return empty
    hits = _cast_rays(fields, mesh, invert_T(T_base_obj), origins_base)
    if hits is None:
        return empty
    rng = np.random.default_rng([int(seed) & (2**63 - 1), 0x11DA2])
    _move_points(out, fields, hits, T_base_obj, range_sigma, rng)
    cos_inc = _hit_intensity(out, fields, mesh, hits, intensity_scale, intensity_noise, rng)
    logger.debug("lidar cast %s: %d candidates, %d points moved", mesh.name, hits.candidates,
                 len(hits.idx))  # fmt: skip
    order = np.argsort(hits.idx)
    idx, cos_inc = hits.idx[order].astype(np.int64), cos_inc[order]
    return _drop_returns(out, fields, idx, cos_inc, dropout, rng)


def _check_cloud(fields: Mapping[str, np.ndarray]) -> int:
    """The cloud's point count; ValueError without x, y, z or with ragged fields."""
    for k in ("x", "y", "z"):
        if k not in fields:
            raise ValueError(f"cloud has no {k!r} field")
    n = len(fields["x"])
    if any(len(np.asarray(v)) != n for v in fields.values()):
        raise ValueError("cloud fields have different lengths")
    return n


@dataclass
class _Hits:
    """The rays that meet the object before their point (object frame).

    idx : (k,) input indices of those points; t : (k,) float64 range of the hit (m);
    d : (k, 3) unit ray directions; o_obj : (k, 3) ray origins; rng_m : (k,) the points'
    own ranges; prim, uv, nrm : (k,), (k, 2), (k, 3) the hit triangle, barycentrics and
    normal (open3d's); candidates : rays cast.
    """

    idx: NDArray[np.int64]
    t: F64
    d: F64
    o_obj: F64
    rng_m: F64
    prim: NDArray[np.int64]
    uv: F64
    nrm: F64
    candidates: int


def _cast_rays(
    fields: Mapping[str, np.ndarray],
    mesh: ObjectMesh,
    T_obj_base: F64,
    origins_base: Mapping[int, ArrayLike] | ArrayLike,
) -> _Hits | None:
    """Cast the rays that can meet the object (its bounding sphere); None: no hit."""
    p_base = np.stack([np.asarray(fields[k], dtype=np.float64) for k in "xyz"], axis=1)
    o_base = point_origins(fields, origins_base)
    p_obj = _to_obj(T_obj_base, p_base)
    o_obj = _to_obj(T_obj_base, o_base)
    cand = _candidates(mesh, o_obj, p_obj)
    if len(cand) == 0:
        return None
    seg = p_obj[cand] - o_obj[cand]
    rng_m = np.linalg.norm(seg, axis=1)
    d = seg / rng_m[:, None]
    rays = np.empty((len(cand), 6), dtype=np.float32)
    rays[:, :3] = o_obj[cand]
    rays[:, 3:] = d
    ans = _object_scene(mesh).cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t_hit) & (t_hit < rng_m)
    sel = np.flatnonzero(hit)
    idx = cand[sel]
    if len(idx) == 0:
        return None
    return _Hits(
        idx, t_hit[sel], d[sel], o_obj[idx], rng_m[sel],
        ans["primitive_ids"].numpy()[sel].astype(np.int64),
        ans["primitive_uvs"].numpy()[sel].astype(np.float64),
        ans["primitive_normals"].numpy()[sel].astype(np.float64),
        len(cand),
    )  # fmt: skip


def _move_points(
    out: dict[str, np.ndarray],
    fields: Mapping[str, np.ndarray],
    hits: _Hits,
    T_base_obj: F64,
    range_sigma: Mapping[int, float] | float,
    rng: np.random.Generator,
) -> None:
    """x, y, z of the hit points (in ``out``) onto the object, with the range noise."""
    t = hits.t
    sig = _per_point(fields, hits.idx, range_sigma)
    if np.any(sig > 0.0):
        noise = np.clip(rng.standard_normal(len(t)), -_NOISE_TRUNCATION, _NOISE_TRUNCATION)
        t = np.minimum(t + sig * noise, hits.rng_m)
    q_obj = hits.o_obj + t[:, None] * hits.d
    q_base = q_obj @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
    for j, k in enumerate("xyz"):
        out[k][hits.idx] = q_base[:, j].astype(out[k].dtype)


def _hit_intensity(
    out: dict[str, np.ndarray],
    fields: Mapping[str, np.ndarray],
    mesh: ObjectMesh,
    hits: _Hits,
    intensity_scale: Mapping[int, float] | float,
    intensity_noise: float,
    rng: np.random.Generator,
) -> F64:
    """Intensity of the hit points (in ``out``): reflectivity interpolated at the hit,
    times |cos(incidence)|; returns (k,) |cos(incidence)|."""
    nrm = hits.nrm / np.maximum(np.linalg.norm(hits.nrm, axis=1, keepdims=True), 1e-12)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, hits.d))
    if "intensity" in out:
        tri_r = mesh.reflectivity[mesh.faces[hits.prim]].astype(np.float64)  # (k, 3)
        uv = hits.uv
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        refl = np.einsum("ij,ij->i", tri_r, w)
        value = np.clip(refl * cos_inc, 0.0, 1.0)
        if intensity_noise > 0.0:
            noise = rng.standard_normal(len(hits.idx))
            value = np.clip(value * (1.0 + intensity_noise * noise), 0, 1)
        out["intensity"][hits.idx] = _intensity_values(fields, hits.idx, value, intensity_scale)
    return cos_inc


def _drop_returns(
    out: dict[str, np.ndarray],
    fields: Mapping[str, np.ndarray],
    idx: NDArray[np.int64],
    cos_inc: F64,
    dropout: Mapping[int, float] | float,
    rng: np.random.Generator,
) -> LidarCastResult:
    """The result, each object point (sorted ``idx``) dropped with its sensor's
    ``dropout`` probability (the cloud then shrinks: ``LidarCastResult.kept``)."""
    p_drop = _per_point(fields, idx, dropout)
    if not np.any(p_drop > 0.0):
        return LidarCastResult(out, idx, len(idx), cos_inc)
    drop = rng.random(len(idx)) < p_drop
    keep = np.ones(len(fields["x"]), bool)
    keep[idx[drop]] = False
    kept = np.flatnonzero(keep)
    new_pos = np.cumsum(keep) - 1
    thinned = {k: v[keep] for k, v in out.items()}
    stay = idx[~drop]
    return LidarCastResult(thinned, new_pos[stay].astype(np.int64), len(stay), cos_inc[~drop],
                           kept=kept, dropped=idx[drop])  # fmt: skip


def _per_point(
    fields: Mapping[str, np.ndarray], idx: NDArray[np.int64], value: Mapping[int, float] | float
) -> F64:
    """A per-sensor (dict) or global value at the points ``idx``; sensors missing in the
    dict get 0."""
    if not isinstance(value, Mapping):
        return np.full(len(idx), float(value))
    if "sensor_index" not in fields:
        raise ValueError("per-sensor noise values need a sensor_index field in the cloud")
    sidx = np.asarray(fields["sensor_index"]).astype(np.int64)[idx]
    return np.array([float(value.get(int(s), 0.0)) for s in sidx], dtype=np.float64)


@dataclass(frozen=True)
class LidarNoise:
    """One sensor's noise near the object (module docstring).

    range_sigma_m : range noise std (m), NaN when not measurable; dropout : fraction of
    rays without a return on the surfaces, 0 when not measurable; points : real points
    used; rings : scan rings found (0: no ring structure).
    """

    range_sigma_m: float
    dropout: float
    points: int
    rings: int


def _intensity_values(
    fields: Mapping[str, np.ndarray],
    idx: NDArray[np.int64],
    value: F64,
    intensity_scale: Mapping[int, float] | float,
) -> NDArray:
    """Object intensities in the input's units and quantisation."""
    src = np.asarray(fields["intensity"])
    if isinstance(intensity_scale, Mapping):
        sidx = np.asarray(fields["sensor_index"]).astype(np.int64)
        missing = sorted(set(np.unique(sidx[idx]).tolist()) - {int(k) for k in intensity_scale})
        if missing:
            raise ValueError(f"no intensity_scale for sensor_index {missing}")
        scale = np.array([float(intensity_scale[int(s)]) for s in sidx[idx]])
        group = sidx
    else:
        scale = np.full(len(idx), float(intensity_scale))
        group = np.zeros(len(src), dtype=np.int64)
    out = scale * value
    for g in np.unique(group[idx]):  # round where the sensor's input is integral
        vals = src[group == g].astype(np.float64)
        finite = vals[np.isfinite(vals)]
        if src.dtype.kind in "iu" or (len(finite) and np.all(finite == np.round(finite))):
            m = group[idx] == g
            out[m] = np.round(out[m])
    if src.dtype.kind in "iu":
        info = np.iinfo(src.dtype)
        out = np.clip(out, info.min, info.max)
    return out.astype(src.dtype)


def hidden_from(
    mesh: ObjectMesh,
    T_base_obj: ArrayLike,
    points_base: ArrayLike,
    origins_base: ArrayLike,
    tol: float = 1e-3,
) -> NDArray[np.bool_]:
    """Whether each point is hidden from its origin by the object itself.

    Parameters
    ----------
    points_base, origins_base : (n, 3) points and the origins of their rays, base frame.
    tol : the object may be met at most this far (m) before the point.

    Returns
    -------
    (n,) bool: True where the ray origin -> point enters the object more than ``tol``
    before the point, i.e. a point no sensor at that origin could have measured (a
    surface point facing away, or a point inside). The quality check of the origins:
    with the true origins no object point of :func:`cast_object` is hidden.
    """
    T_obj_base = invert_T(np.asarray(T_base_obj, dtype=np.float64))
    p = _to_obj(T_obj_base, np.asarray(points_base, dtype=np.float64).reshape(-1, 3))
    o = _to_obj(T_obj_base, np.asarray(origins_base, dtype=np.float64).reshape(-1, 3))
    seg = p - o
    r = np.linalg.norm(seg, axis=1)
    out = np.zeros(len(p), dtype=bool)
    ok = np.flatnonzero(r > _MIN_RANGE_M)
    if len(ok) == 0:
        return out
    rays = np.empty((len(ok), 6), dtype=np.float32)
    rays[:, :3] = o[ok]
    rays[:, 3:] = seg[ok] / r[ok, None]
    t = _object_scene(mesh).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    out[ok] = np.isfinite(t) & (t.astype(np.float64) < r[ok] - tol)
    return out
