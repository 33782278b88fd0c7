"""Strategy ``odometry``: lidar odometry with KISS-ICP, anchored by the first INS pose.

:func:`odometry_track` runs KISS-ICP ONCE per preparation (memoised in
``inp.options["_odometry"]``) on the frames' clouds. OSDaR23 clouds are already
motion-compensated into the base frame at the lidar timestamp, so KISS-ICP's deskewing is
off; NaN points are dropped. KISS-ICP's poses are relative to the first frame; the first
INS pose (nominal misalignment, an ASSUMPTION) anchors them in the world. Its local map
takes a frame only once the train has moved on (:data:`MAP_LAG_VOXELS`,
:class:`~worker.preparation.kiss_process.LaggedKissICP`): on a slow train a map holding the
frames just before pulled ICP towards their identical lidar pattern, a heading drift of
about 30 mdeg a frame at 30 % density.

Degeneracy (hard case: a long straight with little structure): for every frame the
point-to-plane information matrix ``H = sum J J^T``, ``J = [n, p x n]`` of the cloud used
for registration (normals from its neighbours) is computed; the information left for a
translation along the track (base x) once the other five directions are free (Schur
complement, ``1 / (H^-1)_xx`` per point) measures how well ICP can see motion along the
track. A second check compares the odometry's travelled distance with the INS's.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from geometry.poses import PoseTrack
from worker.preparation.kiss_process import (
    KissProcess,
    KissProcessError,
    kiss_config,
    make_kiss,
    set_prior,
)
from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult
from worker.preparation.localization.common import (
    ins_at_frames,
    interpolate_track,
    make_result,
    relative_motions,
    travelled,
    travelled_robust,
)
from worker.preparation.localization.ground_pairs import (
    COLUMN_M,
    FrameGround,
    GroundPair,
    column_floor,
    frame_ground,
    in_lag_order,
    pairs_ending_at,
)
from worker.preparation.localization.ground_pairs import LAGS as GROUND_LAGS

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

#: KISS-ICP settings (options ``odometry_max_range``, ``odometry_min_range``,
#: ``odometry_voxel_size`` override them).
MAX_RANGE_M = 100.0
MIN_RANGE_M = 1.0
VOXEL_SIZE_M = 0.5
#: A frame enters KISS-ICP's map once the train is this many voxel sizes away from it
#: (:class:`~worker.preparation.kiss_process.LaggedKissICP`; option ``odometry_map_lag_m``
#: in metres overrides it, 0 is KISS-ICP as is): 1.5, KISS-ICP's source voxel (it keeps
#: one point per 1.5 voxel sizes), so a frame registers against samples taken at least one
#: source cell away. Measured (heading error at the end, mdeg; without the lag -577 / -909)
#: on tight_curve (20 frames) / station (35) at 1.5 m/s, density 0.3: lag 0.4 m -37 / -327,
#: 0.55 m -51 / -54, 0.75 m -67 / -73, 1 m -80 / -86. 1 m withheld the previous frame at
#: normal speed too (fire_site 0.9 m, switch 0.8 m a frame), 15-20 % more lag-30 rotation
#: error there; 0.75 m leaves those as they were.
MAP_LAG_VOXELS = 1.5
#: ... but only while the predicted step is shorter than this many voxel sizes (a slow
#: train; option ``odometry_map_fast_step_m`` in metres): at a voxel a frame the previous
#: frame is a voxel away already. Dense station cells at 0.6 m a frame lost with the lag
#: (fused anchor error on rgb_highres_center 1.68 -> 2.31 px over 10 frames, 1.88 -> 2.70
#: over 20).
MAP_FAST_STEP_VOXELS = 1.0
#: Ground removal: grid cell (m) and height above the cell's lowest point (m).
GROUND_CELL_M = COLUMN_M  # 1 m: the ground pairs' columns, one floor serves both
GROUND_HEIGHT_M = 0.2
#: Fewer points than this in a frame: the frame is skipped (constant-velocity prediction).
MIN_POINTS = 100
#: Along-track information per point below this (fraction of a unit normal squared) marks
#: the frame as degenerate along the track.
DEGENERATE_ALONG_INFO = 0.03
#: Share of degenerate frames above which the whole run is flagged degenerate.
DEGENERATE_SHARE = 0.3
#: Odometry / INS travelled distance ratio outside [1 - x, 1 + x] is suspicious.
DISTANCE_RATIO_TOL = 0.05
#: Normal estimation neighbours and radius (m) for the information matrix.
NORMAL_KNN = 12
NORMAL_RADIUS_M = 2.0
#: Points kept per frame for the information matrix and the consistency checks.
INFO_MAX_POINTS = 2000


@dataclass
class OdometryRun:
    """One KISS-ICP run over the frames.

    T_odom_base : (n, 4, 4) KISS-ICP poses (odometry frame = first frame's base).
    along_info : (n,) along-track information per point of each frame (see module doc).
    lateral_info : (n,) the same for base y.
    n_points : (n,) finite points per frame.
    skipped : frame positions that had too few points.
    clouds : per frame the (m, 3) base points used for registration (subsampled), reused
        by ``auto``'s map-consistency check without reading the PCDs again.
    grounds : per frame its ground (:func:`~.ground_pairs.frame_ground`), taken from the
        column floors the ground removal computes anyway, for ``fused``'s ground pairs.
    ground_pairs : the ground pairs of the default lags (``ground_pairs.LAGS``, order
        (lag, k)), computed while KISS-ICP registers the next frames (None: not computed).
    seconds : wall time of the run (reading + KISS-ICP + diagnostics).
    kiss_seconds : time this process spent in KISS-ICP or waiting for its child process
        (the health metric ``kiss_icp_seconds``).
    """

    T_odom_base: F64
    along_info: F64
    lateral_info: F64
    n_points: NDArray[np.int64]
    skipped: list[int] = field(default_factory=list)
    clouds: list[F64] = field(default_factory=list)
    grounds: list[FrameGround] = field(default_factory=list)
    ground_pairs: list[GroundPair] | None = None
    seconds: float = 0.0
    kiss_seconds: float = 0.0


def _kiss_settings(inp: LocalizationInput) -> dict[str, Any]:
    """The KISS-ICP settings of this input's options (:func:`~worker.preparation.
    kiss_process.make_kiss` turns them into a KISS-ICP, here or in the child)."""
    voxel_size = float(inp.options.get("odometry_voxel_size", VOXEL_SIZE_M))
    return {
        "deskew": False,
        "max_range": float(inp.options.get("odometry_max_range", MAX_RANGE_M)),
        "min_range": float(inp.options.get("odometry_min_range", MIN_RANGE_M)),
        "voxel_size": voxel_size,
        "max_num_threads": int(inp.options.get("odometry_threads", 0)),
        "map_lag_m": float(inp.options.get("odometry_map_lag_m", MAP_LAG_VOXELS * voxel_size)),
        "map_fast_step_m": float(
            inp.options.get("odometry_map_fast_step_m", MAP_FAST_STEP_VOXELS * voxel_size)
        ),
    }


def _kiss_config(inp: LocalizationInput) -> Any:
    """The KISSConfig of this input's options."""
    return kiss_config(_kiss_settings(inp))


def read_points(inp: LocalizationInput, frame: int) -> F64:
    """(m, 3) finite float64 base points of one frame (empty on an unreadable cloud).

    Uses the preparation's shared FrameClouds (``inp.options["_frame_clouds"]``) when there
    is one, so each PCD is read once per preparation.
    """
    shared = inp.options.get("_frame_clouds")
    if shared is not None:
        try:
            return shared.get(frame).p_base
        except Exception as exc:
            log.warning("frame %d: cloud unreadable (%s); skipped by odometry", frame, exc)
            return np.zeros((0, 3))
    try:
        cloud = inp.sequence.pcd(frame, allow_nonfinite=True)
    except Exception as exc:
        log.warning("frame %d: cloud unreadable (%s); skipped by odometry", frame, exc)
        return np.zeros((0, 3))
    p = np.asarray(cloud.xyz, dtype=np.float64)
    return p[np.all(np.isfinite(p), axis=1)]


def remove_ground(points_base: F64, floor: F64 | None = None) -> F64:
    """Points more than GROUND_HEIGHT_M above the lowest point of their GROUND_CELL_M column.

    The ground, ballast and rails are sampled by the lidars in the same pattern every frame
    (fixed in the base frame), which pulls point-to-point ICP towards zero motion; only the
    structures above them are kept for odometry.

    Parameters
    ----------
    points_base : (m, 3) base points. Returns (k, 3).
    floor : (m,) ``column_floor(points_base, GROUND_CELL_M)`` if the caller has it.
    """
    if len(points_base) == 0:
        return points_base
    if floor is None:
        floor = column_floor(points_base, GROUND_CELL_M)
    return points_base[points_base[:, 2] > floor + GROUND_HEIGHT_M]


def information(points_base: F64) -> tuple[float, float]:
    """Along-track (x) and lateral (y) translation information per point of a cloud.

    Parameters
    ----------
    points_base : (m, 3) points in the base frame.

    Returns
    -------
    ``1 / (H^-1)_xx / m`` and ``1 / (H^-1)_yy / m`` with the point-to-plane information
    ``H`` (6 x 6) over [translation, rotation]; 0 when the problem is singular.
    """
    m = len(points_base)
    if m < 20:
        return 0.0, 0.0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_base))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(NORMAL_RADIUS_M, NORMAL_KNN))
    n = np.asarray(pcd.normals)
    ok = np.all(np.isfinite(n), axis=1)
    n, p = n[ok], points_base[ok]
    # Rotations about a point near the cloud's centre keep H well conditioned.
    p = p - np.median(p, axis=0)
    scale = max(float(np.median(np.linalg.norm(p, axis=1))), 1.0)
    J = np.concatenate([n, np.cross(p / scale, n)], axis=1)
    H = J.T @ J
    try:
        Hi = np.linalg.inv(H + 1e-9 * np.eye(6))
    except np.linalg.LinAlgError:
        return 0.0, 0.0
    return float(1.0 / Hi[0, 0] / len(n)), float(1.0 / Hi[1, 1] / len(n))


def _subsample(p: F64, k: int, rng: np.random.Generator) -> F64:
    if len(p) <= k:
        return p
    return p[np.sort(rng.choice(len(p), k, replace=False))]


class _InProcess:
    """KISS-ICP in this process, with :class:`~.kiss_process.KissProcess`'s interface."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.kiss = make_kiss(settings)
        self.out: tuple[F64, F64] = (np.eye(4), np.zeros((0, 3)))

    def send(self, points: F64, prior_t: F64 | None = None) -> None:
        set_prior(self.kiss, prior_t)
        if len(points) == 0:
            # Constant-velocity prediction, as KISS-ICP would start from.
            self.kiss.last_pose = self.kiss.last_pose @ self.kiss.last_delta
            source = np.zeros((0, 3))
        else:
            _, source = self.kiss.register_frame(points, np.zeros(len(points)))
        self.out = (np.array(self.kiss.last_pose, dtype=np.float64), source)

    def receive(self) -> tuple[F64, F64]:
        return self.out


def _frame_input(inp: LocalizationInput, frame: int) -> tuple[F64, FrameGround]:
    """One frame's points for KISS-ICP (its ground removed) and its ground.

    One column floor serves both: the ground removal and the ground pairs' ground.
    """
    p = read_points(inp, frame)
    floor = column_floor(p, GROUND_CELL_M)
    return remove_ground(p, floor), frame_ground(p, floor)


def run_kiss_icp(inp: LocalizationInput) -> OdometryRun:
    """KISS-ICP over the frames in time order (no memoisation; see :func:`odometry_track`).

    KISS-ICP runs in a child process (:mod:`worker.preparation.kiss_process`; option
    ``odometry_process``, default True) while this one reads and splits the next cloud;
    in this process when the option is off or the child fails (with a warning; the poses
    are the same).
    """
    started = time.perf_counter()
    settings = _kiss_settings(inp)
    if inp.options.get("odometry_process", True):
        try:
            with KissProcess(settings) as child:
                return _run_frames(inp, child, started)
        except KissProcessError as exc:
            log.warning("odometry: %s; running KISS-ICP in this process", exc)
            started = time.perf_counter()
    return _run_frames(inp, _InProcess(settings), started)


def step_priors(inp: LocalizationInput) -> F64 | None:
    """(n-1, 3) each step's expected translation in the earlier frame's base, from the
    INS velocity (good to cm/s) and attitude; None when the INS has no velocity."""
    try:
        ins = ins_at_frames(inp, Health())
    except ValueError:
        return None
    v = ins.v_world
    if len(v) < 2 or not np.any(np.linalg.norm(v, axis=1) > 0):
        return None
    dt = np.diff(np.asarray(inp.times, dtype=np.float64))
    v_step = 0.5 * (v[1:] + v[:-1]) * dt[:, None]
    R = ins.T_world_base[:-1, :3, :3]
    return np.einsum("nji,nj->ni", R, v_step)


def _run_frames(inp: LocalizationInput, kiss: Any, started: float) -> OdometryRun:
    """The frames through ``kiss`` (send / receive), each frame's input prepared while the
    previous one registers. ``kiss_seconds`` is the time spent waiting for KISS-ICP."""
    rng = np.random.default_rng(0)
    n = len(inp.frames)
    T = np.tile(np.eye(4), (n, 1, 1))
    along, lateral = np.zeros(n), np.zeros(n)
    n_points = np.zeros(n, dtype=np.int64)
    skipped: list[int] = []
    clouds: list[F64] = []
    grounds: list[FrameGround] = []
    pairs: list[GroundPair] = []
    kiss_seconds = 0.0
    priors = step_priors(inp) if inp.options.get("odometry_ins_prior", True) else None
    for k in range(n + 1):
        p = None
        if k < n:
            p, ground = _frame_input(inp, inp.frames[k])  # while KISS-ICP registers k - 1
            grounds.append(ground)
            n_points[k] = len(p)
            if len(p) < MIN_POINTS:
                skipped.append(k)
                p = np.zeros((0, 3))
        source = None
        tic = time.perf_counter()
        if k > 0:
            T[k - 1], source = kiss.receive()
        if p is not None:
            kiss.send(p, None if priors is None or k == 0 else priors[k - 1])
        kiss_seconds += time.perf_counter() - tic
        if source is not None:  # frame k - 1's checks, while KISS-ICP registers k
            sub = _subsample(np.asarray(source, dtype=np.float64), INFO_MAX_POINTS, rng)
            along[k - 1], lateral[k - 1] = information(sub)
            clouds.append(sub)
            pairs += pairs_ending_at(grounds, T, k - 1, GROUND_LAGS)
    finite = bool(np.all(np.isfinite(T)))
    if not finite:
        log.warning("KISS-ICP returned non-finite poses; replaced by identity motion")
        T = _repair_nonfinite(T)
    return OdometryRun(
        T, along, lateral, n_points, skipped, clouds, grounds,
        in_lag_order(pairs, GROUND_LAGS) if finite else None,
        time.perf_counter() - started, kiss_seconds,
    )  # fmt: skip


def _repair_nonfinite(T: F64) -> F64:
    """Non-finite poses -> the previous good pose (zero motion)."""
    out = T.copy()
    last = np.eye(4)
    for k in range(len(out)):
        if np.all(np.isfinite(out[k])):
            last = out[k]
        else:
            out[k] = last
    return out


def _diagnose(run: OdometryRun, inp: LocalizationInput, health: Health) -> None:
    """Degeneracy and consistency diagnostics of a run, into ``health``."""
    frames = inp.frames
    degenerate = run.along_info < DEGENERATE_ALONG_INFO
    share = float(np.mean(degenerate)) if len(degenerate) else 0.0
    health.metrics["odometry_along_info_median"] = float(np.median(run.along_info))
    health.metrics["odometry_lateral_info_median"] = float(np.median(run.lateral_info))
    health.metrics["odometry_degenerate_share"] = share
    health.metrics["odometry_skipped_frames"] = float(len(run.skipped))
    health.metrics["kiss_icp_seconds"] = run.kiss_seconds
    if run.skipped:
        health.warn(
            f"odometry: frame(s) {[frames[k] for k in run.skipped]} have fewer than "
            f"{MIN_POINTS} points; constant-velocity prediction used"
        )
    ins = ins_at_frames(inp, Health())
    d_ins = travelled_robust(ins.T_world_base[:, :3, 3], ins.v_world, inp.times)
    d_odo = travelled(run.T_odom_base[:, :3, 3])
    health.metrics["odometry_travelled_m"] = d_odo
    ratio = d_odo / d_ins if d_ins > 1.0 else 1.0
    health.metrics["odometry_ins_distance_ratio"] = ratio
    if share > DEGENERATE_SHARE:
        health.degrade(
            f"odometry degenerate along the track: {share:.0%} of frames have too little "
            f"along-track structure (median information {np.median(run.along_info):.4f} "
            f"< {DEGENERATE_ALONG_INFO})"
        )
    elif abs(ratio - 1.0) > DISTANCE_RATIO_TOL:
        health.degrade(
            f"odometry travelled {d_odo:.1f} m against {d_ins:.1f} m of the INS "
            f"(ratio {ratio:.3f}): ICP probably slipped along the track"
        )


def degenerate_frames(run: OdometryRun) -> NDArray[np.bool_]:
    """(n,) frames whose along-track ICP constraint is too weak."""
    return run.along_info < DEGENERATE_ALONG_INFO


def is_degenerate(health: Health) -> bool:
    """Whether an odometry health flags the run as unreliable along the track."""
    return any(
        w.startswith("odometry degenerate") or "slipped along the track" in w
        for w in health.warnings
    )


def odometry_run(inp: LocalizationInput) -> OdometryRun:
    """The memoised KISS-ICP run of this input (runs it on the first call)."""
    run = inp.options.get("_odometry_run")
    if not isinstance(run, OdometryRun):
        run = run_kiss_icp(inp)
        inp.options["_odometry_run"] = run
    return run


def odometry_track(inp: LocalizationInput) -> tuple[PoseTrack, Health]:
    """KISS-ICP poses T_world_base at the frames, anchored at the first INS pose.

    Memoised in ``inp.options["_odometry"]``: the orchestrator and every strategy share one
    KISS-ICP run. The returned Health carries the degeneracy diagnostics (warnings and
    ``odometry_*`` metrics).
    """
    memo = inp.options.get("_odometry")
    if memo is not None:
        return memo
    run = odometry_run(inp)
    health = Health()
    ins = ins_at_frames(inp, Health())
    _diagnose(run, inp, health)
    T_world_odom = ins.T_world_base[0] @ np.linalg.inv(run.T_odom_base[0])
    T = T_world_odom @ run.T_odom_base
    track = PoseTrack(inp.times, T, np.asarray(inp.frames, dtype=np.int64))
    inp.options["_odometry"] = (track, health)
    return track, health


def odometry_deltas(inp: LocalizationInput) -> F64:
    """(n-1, 4, 4) KISS-ICP relative motions between consecutive frames."""
    return relative_motions(odometry_run(inp).T_odom_base)


class OdometryStrategy:
    """KISS-ICP lidar odometry anchored at the first INS pose."""

    name = "odometry"

    def run(self, inp: LocalizationInput) -> LocalizationResult:
        started = time.perf_counter()
        try:
            track, odo_health = odometry_track(inp)
        except Exception as exc:
            health = Health(fallback="ins")
            health.degrade(f"odometry failed ({exc}); falling back to the raw INS")
            T = interpolate_track(inp.ins_track, inp.times)
            return make_result(self.name, inp, T, health, started)
        health = Health(
            warnings=list(odo_health.warnings),
            metrics=dict(odo_health.metrics),
            fallback=odo_health.fallback,
            degraded=list(odo_health.degraded),
        )
        return make_result(
            self.name,
            inp,
            track.T,
            health,
            started,
            extras={"anchor": "first INS pose (nominal INS-to-lidar misalignment, ASSUMED)"},
        )
