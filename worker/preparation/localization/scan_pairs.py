"""Fine scan-to-scan registration of frame pairs, for the ``fused`` smoothing.

KISS-ICP registers each scan against a map of 0.5 m voxels with point-to-point ICP; its
lateral error over 10 frames reached 1.5-2 cm on sparse clouds (robustness matrix), and
that drift is what moves a placed object against the scene from frame to frame (0.3 px a
frame at 50 m on rgb_highres_center). Point-to-plane ICP between the two scans themselves
(open3d, Tukey loss, started from KISS-ICP's relative pose) uses every point of both and
the surfaces' normals: over 10 frames its lateral error was 2-5 mm on the same pairs
(fire_site 20 frames sparse: 21 -> 2.3 mm RMS; klein_flottbek 35 sparse: 15 -> 5 mm).

Each pair's uncertainty comes from its own normal equations: the point-to-plane
information ``H = sum w J^T J`` (``J = [p x n, n]``) at the solution, scaled by the
residuals' robust variance and by :attr:`ScanPairSettings.inflate` (neighbouring points
share their surface's errors, so the formal covariance is optimistic: the true lateral
errors were 1.3-2.6x the formal ones). Where the scene does not fix a direction (a
straight track with only vegetation beside it: along-track information ~0) the
covariance says so.

The ground is left out (:func:`~.odometry.remove_ground`): it is sampled in the same
pattern every frame and pulls the registration towards zero motion; the ground pairs
(:mod:`.ground_pairs`) measure what the ground fixes (height, roll, pitch). No voxel
filter either: a grid fixed in the base frame is such a pattern too (it turned the
heading of consecutive scans by 8 mdeg a step in a curve). Consecutive scans keep a
bias of their own (lateral -1.9 mm, heading and pitch -5 mdeg a step on fire_site, 20
frames), which 20 or 100 steps would add up; over 10 frames and more the same bias is a
fraction of the motion, so ``fused`` takes these pairs' lateral component only, at lags
of 10 and 30 frames.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from worker.orchestration.threads import thread_budget
from worker.preparation.localization.base import LocalizationInput
from worker.preparation.localization.odometry import read_points, remove_ground

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScanPairSettings:
    """Settings of the fine registration (m, rad)."""

    #: Points nearer or farther than these from the base origin are left out: the train's
    #: own body and the far field's few, noisy returns.
    min_range_m: float = 2.0
    max_range_m: float = 80.0
    #: Points kept of each scan (the fixed one's surfaces and normals), and of the moving
    #: one per registration, drawn at random (seeded; a random draw is no pattern fixed to
    #: the base). With 20k points a scan and 6000 a registration, the pairs of 100 frames
    #: cost 20 s of CPU (9 s of it normals) on fire_site (d1, 100 frames).
    scan_points: int = 12000
    source_points: int = 3000
    #: Normal estimation: radius (m) and most neighbours.
    normal_radius_m: float = 0.5
    normal_nn: int = 12
    #: ICP: largest correspondence distance (m), Tukey loss width (m), iterations.
    max_correspondence_m: float = 0.3
    tukey_m: float = 0.1
    max_iterations: int = 30
    #: Share of the source's points that must find a correspondence.
    min_fitness: float = 0.5
    #: Gate against KISS-ICP's relative pose (m, rad): a registration that moved further
    #: from it fell into another minimum.
    max_shift_m: float = 0.3
    max_turn_rad: float = float(np.radians(0.5))
    #: Formal standard deviations are multiplied by this.
    inflate: float = 3.0
    #: Fewest correspondences for a registration.
    min_points: int = 200


@dataclass
class ScanPairs:
    """Registered pairs: frame j's base pose in frame k's base.

    k, j : (Q,) positions of the frames in the input's frame list.
    T_k_j : (Q, 4, 4) relative poses (KISS-ICP's where ``ok`` is False).
    sd_t : (Q, 3) standard deviations of T_k_j's translation, frame k's axes (m).
    sd_r : (Q, 3) standard deviations of its rotation, small angles about frame k's axes
        (rad).
    ok : (Q,) the registration converged within the gates.
    """

    k: NDArray[np.int64]
    j: NDArray[np.int64]
    T_k_j: F64
    sd_t: F64
    sd_r: F64
    ok: NDArray[np.bool_]


class ScanClouds:
    """Each frame's scan for the fine registration: its ground removed, thinned, with
    normals; built on first use and kept."""

    def __init__(self, inp: LocalizationInput, settings: ScanPairSettings) -> None:
        self.inp = inp
        self.settings = settings
        self._cache: dict[int, o3d.geometry.PointCloud] = {}

    def get(self, pos: int) -> o3d.geometry.PointCloud:
        """The scan of the frame at position ``pos`` of the input's frame list."""
        hit = self._cache.get(pos)
        if hit is not None:
            return hit
        cloud = scan_cloud(read_points(self.inp, self.inp.frames[pos]), self.settings)
        self._cache[pos] = cloud
        return cloud


def scan_cloud(p_base: F64, s: ScanPairSettings) -> o3d.geometry.PointCloud:
    """One frame's scan for :func:`register_scans` from its (m, 3) base points: within
    the range limits, its ground removed, thinned, with normals."""
    r = np.linalg.norm(p_base, axis=1)
    p = remove_ground(p_base[(r > s.min_range_m) & (r < s.max_range_m)])
    if len(p) > s.scan_points:
        rng = np.random.default_rng(len(p))
        p = p[np.sort(rng.choice(len(p), s.scan_points, replace=False))]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, dtype=np.float64)))
    if len(cloud.points) >= s.min_points:
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=s.normal_radius_m, max_nn=s.normal_nn)
        )
    return cloud


def scan_clouds(inp: LocalizationInput, settings: ScanPairSettings | None = None) -> ScanClouds:
    """The input's memoised :class:`ScanClouds` (``inp.options["_scan_clouds"]``)."""
    shared = inp.options.get("_scan_clouds")
    if not isinstance(shared, ScanClouds):
        shared = ScanClouds(inp, settings or ScanPairSettings())
        inp.options["_scan_clouds"] = shared
    return shared


def _subsample(cloud: o3d.geometry.PointCloud, n: int, seed: int) -> o3d.geometry.PointCloud:
    if len(cloud.points) <= n:
        return cloud
    rng = np.random.default_rng(seed)
    return cloud.select_by_index(np.sort(rng.choice(len(cloud.points), n, replace=False)))


def _skew(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pair_covariance(
    p_src_k: F64, q: F64, n: F64, tukey_m: float, t_k_j: F64
) -> tuple[F64, F64] | None:
    """Formal standard deviations of a point-to-plane registration at its solution.

    p_src_k : (m, 3) source points moved into frame k; q : (m, 3) their target points;
    n : (m, 3) the target normals; t_k_j : (3,) the solution's translation.
    Returns (sd_t (3,), sd_r (3,)) of T_k_j's translation and rotation, or None when the
    normal equations are singular. The perturbation ``T -> Exp(d) T`` (d = rotation,
    translation in frame k) moves the translation by ``d_r x t + d_t``.
    """
    r = np.einsum("ij,ij->i", n, p_src_k - q)
    w = np.where(np.abs(r) < tukey_m, (1.0 - (r / tukey_m) ** 2) ** 2, 0.0)
    if np.sum(w > 0) < 12:
        return None
    J = np.hstack([np.cross(p_src_k, n), n])
    H = (J * w[:, None]).T @ J
    s2 = float(np.sum(w * r * r) / max(np.sum(w) - 6.0, 1.0))
    try:
        C = s2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    A = np.hstack([-_skew(t_k_j), np.eye(3)])
    C_t = A @ C @ A.T
    sd_t, sd_r = np.sqrt(np.abs(np.diag(C_t))), np.sqrt(np.abs(np.diag(C)[:3]))
    if not (np.all(np.isfinite(sd_t)) and np.all(np.isfinite(sd_r))):
        return None
    return sd_t, sd_r


def register_scans(
    src: o3d.geometry.PointCloud,
    dst: o3d.geometry.PointCloud,
    T_init: F64,
    s: ScanPairSettings,
    seed: int = 0,
) -> tuple[F64, F64, F64] | None:
    """Scan ``src`` (frame j) registered onto ``dst`` (frame k, with normals) from
    ``T_init`` (4, 4): (T_k_j (4, 4), sd_t (3,), sd_r (3,)) (m, rad, inflated), or None
    when it failed a gate (too few points or correspondences, moved too far from
    ``T_init``, singular)."""
    if len(src.points) < s.min_points or not dst.has_normals():
        return None
    src = _subsample(src, s.source_points, seed)
    reg = o3d.pipelines.registration
    res = reg.registration_icp(
        src, dst, s.max_correspondence_m, T_init,
        reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=s.tukey_m)),
        reg.ICPConvergenceCriteria(max_iteration=s.max_iterations),
    )  # fmt: skip
    T = np.asarray(res.transformation, dtype=np.float64)
    cor = np.asarray(res.correspondence_set)
    if res.fitness < s.min_fitness or len(cor) < s.min_points or not np.all(np.isfinite(T)):
        return None
    D = np.linalg.inv(T_init) @ T
    turn = np.arccos(np.clip(0.5 * (np.trace(D[:3, :3]) - 1.0), -1.0, 1.0))
    if np.linalg.norm(D[:3, 3]) > s.max_shift_m or turn > s.max_turn_rad:
        return None
    p = np.asarray(src.points)[cor[:, 0]] @ T[:3, :3].T + T[:3, 3]
    q = np.asarray(dst.points)[cor[:, 1]]
    n = np.asarray(dst.normals)[cor[:, 1]]
    sd = pair_covariance(p, q, n, s.tukey_m, T[:3, 3])
    if sd is None:
        return None
    return T, sd[0] * s.inflate, sd[1] * s.inflate


def _icp_threads() -> int:
    """Threads for the pairs' registrations: open3d's ICP releases the GIL, and on clouds
    this small its own OpenMP team gains little (3000 points onto 12000, 40 registrations:
    0.205 s wall with 2 OpenMP threads, 0.180 s with one, 0.13 s as two registrations at
    a time). :func:`~worker.orchestration.threads.thread_budget`, at most 4."""
    return thread_budget(4)


def register_pairs(
    inp: LocalizationInput,
    k: NDArray[np.int64],
    j: NDArray[np.int64],
    T_init: F64,
    settings: ScanPairSettings | None = None,
) -> ScanPairs:
    """Register frame j's scan onto frame k's for each pair, from ``T_init`` (Q, 4, 4):
    KISS-ICP's relative poses. Pairs that fail keep ``T_init`` with ``ok`` False."""
    clouds = scan_clouds(inp, settings)
    s = clouds.settings
    q = len(k)
    T_out = np.array(T_init, dtype=np.float64, copy=True)
    sd_t, sd_r = np.full((q, 3), np.inf), np.full((q, 3), np.inf)
    ok = np.zeros(q, dtype=bool)
    for pos in sorted({int(x) for x in (*k, *j)}):
        clouds.get(pos)  # the scans first, in this thread: their normals hold the GIL

    def one(i: int) -> tuple[F64, F64, F64] | None:
        try:
            seed = int(k[i]) * 100_003 + int(j[i])
            return register_scans(clouds.get(int(j[i])), clouds.get(int(k[i])), T_init[i], s, seed)
        except RuntimeError as exc:  # open3d's own failures: the pair stays KISS-ICP's
            log.debug("scan pair %d-%d: %s", k[i], j[i], exc)
            return None

    with ThreadPoolExecutor(max_workers=_icp_threads(), thread_name_prefix="scan-pairs") as ex:
        results = list(ex.map(one, range(q)))
    for i, got in enumerate(results):
        if got is not None:
            T_out[i], sd_t[i], sd_r[i] = got
            ok[i] = True
    return ScanPairs(
        np.asarray(k, dtype=np.int64), np.asarray(j, dtype=np.int64), T_out, sd_t, sd_r, ok
    )


def register_to_map(
    inp: LocalizationInput,
    k: int,
    map_frames: NDArray[np.int64],
    T_odom: F64,
    settings: ScanPairSettings | None = None,
) -> F64 | None:
    """Frame ``k``'s scan registered onto the scans of ``map_frames`` merged with their
    poses ``T_odom`` (n, 4, 4): its refined pose in that frame (4, 4), from ``T_odom[k]``,
    or None where it failed a gate."""
    clouds = scan_clouds(inp, settings)
    s = clouds.settings
    target = o3d.geometry.PointCloud()
    for j in map_frames:
        c = clouds.get(int(j))
        if c.has_normals():
            target += o3d.geometry.PointCloud(c).transform(T_odom[int(j)])
    if not target.has_normals() or len(target.points) < s.min_points:
        return None
    got = register_scans(clouds.get(int(k)), target, T_odom[int(k)], s, seed=int(k))
    return None if got is None else got[0]


#: Median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = 0.454936


def closure_factor(pairs: ScanPairs, short: int, long: int) -> tuple[float, int]:
    """How far the registrations' lateral positions disagree with each other beyond their
    sigmas: for every k with the ``long`` pair (k, k + long) and the ``long // short``
    chained ``short`` pairs all converged, the chain's lateral position of frame k + long
    in frame k against the direct pair's, normalised by the sigma both imply (the
    lateral sigmas and each link's heading sigma times the distance still to go). Returns
    the robust scale ``sqrt(median(c^2) / 0.455)`` of those closures (1: as the sigmas
    say) and how many there were; (1.0, 0) without any."""
    if long % short:
        return 1.0, 0
    at = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(pairs.k, pairs.j, strict=True))}
    z = []
    for i, (a, b) in enumerate(zip(pairs.k, pairs.j, strict=True)):
        if b - a != long or not pairs.ok[i]:
            continue
        links = [
            at.get((int(a) + m * short, int(a) + (m + 1) * short)) for m in range(long // short)
        ]
        if any(x is None or not pairs.ok[x] for x in links):
            continue
        T = np.eye(4)
        var = float(pairs.sd_t[i, 1] ** 2)
        for x in links:
            T = T @ pairs.T_k_j[x]
            var += float(pairs.sd_t[x, 1] ** 2)
        # each link's heading error swings the rest of the chain sideways
        rest = pairs.T_k_j[i, 0, 3]
        for x in links:
            rest -= pairs.T_k_j[x, 0, 3]
            var += float((pairs.sd_r[x, 2] * rest) ** 2)
        z.append((T[1, 3] - pairs.T_k_j[i, 1, 3]) / np.sqrt(var))
    if not z:
        return 1.0, 0
    return float(np.sqrt(np.median(np.square(z)) / _CHI2_1_MEDIAN)), len(z)
