"""Pipeline step 2, preparation: one sequence -> poses, registered cloud, tracks, scene.

The recipe (:func:`run_preparation`), one line per stage:

1. open the sequence, check the clicks against its cameras;
2. INS poses (world frame = ENU at the first INS record, nominal INS-to-lidar assumption);
   then the per-lidar corrections of the merged clouds (:mod:`.lidar_alignment`), applied
   to every cloud the stages below read;
3. lidar odometry: ONE KISS-ICP run, memoised for every strategy that needs it;
4. pre-registration: every ``pre_frame_step``-th cloud with the odometry poses anchored on
   all INS positions (or the INS poses), coarse voxels - enough to find the rails;
5. tracks on it: the ego centreline the rail-based strategies need;
6. the localization strategy -> T_world_base at every frame's lidar timestamp;
7. final registration with the strategy's poses (every ``frame_step``-th cloud: at 10 Hz
   consecutive clouds overlap almost entirely);
8. tracks again on the final cloud (the centrelines of the artifact);
9. scene elements: ground / platform planes, platform edges, poles;
10. the calibration point from the clicks (or proposed pole tops);
11. the artifact (written by :func:`prepare` when it is given a cache folder).

:func:`prepare` adds the cache: the artifact is keyed by the sequence's content, the
config and the clicks (:func:`~worker.preparation.artifact.cache_key`), and a per-key lock
makes concurrent preparations of the same key wait and reuse one result.
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geometry.camera import load_cameras
from geometry.poses import PoseTrack
from worker.json_values import jsonable
from worker.orchestration.malloc_tuning import tune_malloc
from worker.osdar.sequence import Sequence
from worker.preparation.artifact import (
    ARTIFACT_VERSION,
    PreparedSequence,
    artifact_key,
    cache_key,
    cached_folder,
    key_lock,
    read_artifact,
    write_artifact,
)
from worker.preparation.calibration_point import (
    CalibrationPoint,
    Clicks,
    ClicksError,
    calibration_point_from_clicks,
    propose_pole_tops,
)
from worker.preparation.config import PrepareConfig
from worker.preparation.frame_clouds import FrameClouds
from worker.preparation.lidar_alignment import LidarAlignment, estimate_alignment
from worker.preparation.localization import odometry_track, run_strategy
from worker.preparation.localization.anchor import anchored_to_ins
from worker.preparation.localization.auto import crispness, judge
from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult
from worker.preparation.localization.common import ins_at_frames, make_input
from worker.preparation.localization.odometry import odometry_run
from worker.preparation.registration import RegisteredCloud, dense_points, register_clouds
from worker.preparation.scene_elements import find_scene_elements, reference_centreline
from worker.preparation.tracks import find_tracks

log = logging.getLogger(__name__)

#: ``progress(stage, done, total)``: called when a stage starts (done = stages finished).
Progress = Callable[[str, int, int], None]

STAGES = (
    "open",
    "ins",
    "lidar_alignment",
    "odometry",
    "pre_registration",
    "pre_tracks",
    "strategy",
    "registration",
    "tracks",
    "scene_elements",
    "calibration_point",
)


# The shared per-frame clouds: range kept for odometry (m); no thinning (0: every
# consumer sees the points as recorded, and a per-frame filter would cost more than it saves).
FRAME_CLOUD_RANGE_M = 100.0
FRAME_CLOUD_VOXEL_M = 0.0
#: Arrays in the preparation summary longer than this are noted by their shape only.
SUMMARY_MAX_ARRAY = 64


class PreparationError(Exception):
    """A sequence or setting preparation cannot use (the message says which and why)."""


class _Stages:
    """Times the stages and reports progress."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self.progress is not None:
            self.progress(name, len(self.seconds), len(STAGES))
        log.info("preparation: %s", name)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = time.perf_counter() - t0


def _load_clicks(clicks: Clicks | str | Path | None) -> Clicks | None:
    if clicks is None or isinstance(clicks, Clicks):
        return clicks
    return Clicks.load(clicks)


def _open(sequence: Sequence | str | Path) -> Sequence:
    return sequence if isinstance(sequence, Sequence) else Sequence.open(sequence)


# ---------------------------------------------------------------------------- the cache
def prepare(
    sequence: Sequence | str | Path,
    config: PrepareConfig | None = None,
    *,
    clicks: Clicks | str | Path | None = None,
    cache_dir: str | Path | None = None,
    progress: Progress | None = None,
) -> PreparedSequence:
    """Prepare a sequence, reusing the cached artifact when there is one.

    Parameters
    ----------
    sequence : the sequence folder (or an opened Sequence).
    config : the preparation config (defaults: :class:`PrepareConfig`).
    clicks : a clicks file (CSV / JSON, see :mod:`.calibration_point`) or Clicks.
    cache_dir : folder of cached artifacts (``<cache_dir>/<key>/``); None computes without
        writing anything.
    progress : ``progress(stage, done, total)``.

    Returns
    -------
    PreparedSequence; ``summary["reused"]`` tells whether it came from the cache.

    Raises
    ------
    SequenceError, PreparationError, ClicksError
        A broken sequence, unusable settings, a bad clicks file.
    """
    config = config or PrepareConfig()
    seq = _open(sequence)
    cl = _load_clicks(clicks)
    key = cache_key(seq.content_key(), config.config_hash(), None if cl is None else cl.digest())
    if cache_dir is None:
        return run_preparation(seq, config, clicks=cl, progress=progress, key=key)
    folder = cached_folder(cache_dir, key)
    if artifact_key(folder) == key:
        return _reused(folder)
    with key_lock(cache_dir, key):
        if artifact_key(folder) == key:  # prepared by another process while we waited
            return _reused(folder)
        prepared = run_preparation(seq, config, clicks=cl, progress=progress, key=key)
        t0 = time.perf_counter()
        write_artifact(prepared, folder)
        prepared.summary["timings"]["artifact"] = time.perf_counter() - t0
        log.info("preparation %s written to %s", key[:12], folder)
    return prepared


def _reused(folder: Path) -> PreparedSequence:
    prepared = read_artifact(folder)
    prepared.summary["reused"] = True
    log.info("preparation %s reused from %s", prepared.key[:12], folder)
    return prepared


# ---------------------------------------------------------------------------- the recipe
@dataclass
class LocalizationSetup:
    """What the strategies run on: their input (with the ego centreline found on the
    pre-registered cloud), the shared frame clouds, the odometry and the pre-map."""

    inp: LocalizationInput
    clouds: FrameClouds
    odo_track: PoseTrack
    odo_health: Health
    pre_cloud: RegisteredCloud
    pre_tracks: Any
    alignment: LidarAlignment | None = None  # None: lidar alignment off


def localization_setup(
    seq: Sequence, config: PrepareConfig, stage: Callable[[str], Any] | None = None
) -> LocalizationSetup:
    """Stages 2-5 of the recipe: INS poses, odometry, pre-registration, the ego track.

    ``stage(name)`` is a context manager timing each stage (none: untimed). Any strategy
    then runs on ``setup.inp`` (:func:`~worker.preparation.localization.run_strategy`).
    """
    stage = stage or _Stages(None)
    reg = config.registration
    with stage("ins"):
        try:
            inp = make_input(seq, options=dict(config.localization.options))
        except (ValueError, OSError) as exc:
            raise PreparationError(f"{seq.folder}: no usable INS poses ({exc})") from exc
        if not inp.frame_times:
            raise PreparationError(f"{seq.folder}: no frame has a lidar timestamp")
        # Every consumer below (odometry, both registrations) shares one read of each PCD.
        clouds = FrameClouds(
            seq, max_range=max(FRAME_CLOUD_RANGE_M, reg.max_range), voxel_size=FRAME_CLOUD_VOXEL_M
        )
        inp.options["_frame_clouds"] = clouds

    alignment = None
    with stage("lidar_alignment"):  # timed (0 s) when off, as every stage is
        if config.lidar_alignment.enabled:
            p_ins = _at_frames(inp.ins_track, inp).T[:, :3, 3]
            span = float(np.max(np.linalg.norm(p_ins - p_ins[0], axis=1))) if len(p_ins) else 0.0
            alignment = estimate_alignment(
                clouds, inp.frames, config.lidar_alignment.frames, span_m=span
            )
            clouds.set_corrections(alignment.corrections())

    with stage("odometry"):
        odo_track, odo_health = odometry_track(inp)

    with stage("pre_registration"):
        use_odo = reg.pre_poses == "odometry" and odo_health.fallback is None
        if use_odo:
            # Anchored on every INS record, not the first: the rails found on this cloud
            # carry its heading into the rail-based strategies (localization/anchor.py).
            v_world = ins_at_frames(inp, Health()).v_world
            pre_track, anchor_info = anchored_to_ins(odo_track, inp.ins_track, v_world)
            odo_health.metrics.update({f"anchor_{k}": v for k, v in anchor_info.items()})
        else:
            pre_track = _at_frames(inp.ins_track, inp)
        pre_cloud = register_clouds(
            seq,
            pre_track,
            frames=inp.frames[:: reg.pre_frame_step],
            clouds=clouds,
            **config.registration_kwargs(False),
        )

    with stage("pre_tracks"):
        # the strategies need the ego track only; the neighbours come from the final cloud
        pre_tracks = _find_tracks(find_tracks, pre_cloud, pre_track, seq, config, ego_only=True)
        inp.ego = pre_tracks.ego
    return LocalizationSetup(inp, clouds, odo_track, odo_health, pre_cloud, pre_tracks, alignment)


def run_preparation(
    sequence: Sequence | str | Path,
    config: PrepareConfig | None = None,
    *,
    clicks: Clicks | str | Path | None = None,
    progress: Progress | None = None,
    key: str = "",
) -> PreparedSequence:
    """Run the preparation recipe (module docstring) in memory; writes nothing."""

    config = config or PrepareConfig()
    tune_malloc()  # big arrays reuse freed pages (worker/orchestration/malloc_tuning.py)
    stage = _Stages(progress)
    t_start = time.perf_counter()

    with stage("open"):
        seq = _open(sequence)
        cl = _load_clicks(clicks)
        cameras = load_cameras(seq.labels.raw, seq.cameras)
        if cl is not None:
            _check_clicks(cl, cameras)
        if seq.lidar_stream is None:
            raise PreparationError(f"{seq.folder}: sequence has no lidar files")
    setup = localization_setup(seq, config, stage)
    with stage("strategy"):
        result = run_strategy(config.strategy, setup.inp)
        if config.strategy != "auto":  # auto judged its candidates against each other
            _cross_check(setup, result)
    final = _final_map(seq, config, setup, result.track, stage)
    with stage("calibration_point"):
        cal = _calibration(seq, config, cl, cameras, final, result.track, setup.clouds)

    references = {"odometry": setup.odo_track}
    warnings = list(final.warnings)
    try:
        references["ins"] = _at_frames(setup.inp.ins_track, setup.inp)
    except ValueError as exc:
        warnings.append(f"no INS reference poses at the frames ({exc})")
    warnings += _collect_warnings(setup, result, final, cal)
    summary = _summary(seq, config, cl, key, result, setup, final, cal)
    summary["warnings"] = warnings
    summary["timings"] = dict(stage.seconds)
    summary["total_seconds"] = time.perf_counter() - t_start
    prepared = PreparedSequence(
        key=key,
        world=setup.inp.world,
        track=result.track,
        centrelines=list(final.tracks.centrelines),
        planes=final.scene.planes,
        poles=final.scene.poles,
        calibration=cal,
        summary=summary,
        references=references,
        information=result.information,
        timestamp_text=seq.timestamp_text(seq.lidar_stream) if seq.lidar_stream else {},
        _cloud=final.cloud,
        _rail_points=np.asarray(final.tracks.rail_points, dtype=np.float64).reshape(-1, 3),
    )
    log.info("preparation of %s done in %.1f s", seq.name, summary["total_seconds"])
    return prepared


def _cross_check(setup: LocalizationSetup, result: LocalizationResult) -> None:
    """Judge a strategy's result against the odometry's and the INS's maps (crispness of
    the clouds KISS-ICP kept, :func:`~.localization.auto.judge`): flags it degraded when it
    is much less crisp than either."""
    inp = setup.inp
    try:
        clouds = odometry_run(inp).clouds
        T_ins = _at_frames(inp.ins_track, inp).T
    except (ValueError, RuntimeError) as exc:
        log.warning("no cross-check of %s: %s", result.strategy, exc)
        return
    tracks = {result.strategy: result.track.T, "odometry": setup.odo_track.T, "ins": T_ins}
    crisp = {name: crispness(clouds, T) for name, T in tracks.items()}
    for name, c in crisp.items():
        result.health.metrics[f"cross_check_crispness_{name}_m"] = c
    judge({result.strategy: result}, crisp)


@dataclass
class _FinalMap:
    """Stages 7-9: the cloud registered with the strategy's poses, its tracks, the scene."""

    cloud: RegisteredCloud
    tracks: Any
    scene: Any
    warnings: list[str]


def _final_map(
    seq: Sequence,
    config: PrepareConfig,
    setup: LocalizationSetup,
    track: PoseTrack,
    stage: _Stages,
) -> _FinalMap:
    reg = config.registration
    warnings = []
    with stage("registration"):
        frames = setup.inp.frames
        final_frames = sorted(set(frames[:: reg.frame_step]) | {frames[-1]})
        cloud = register_clouds(
            seq, track, frames=final_frames, clouds=setup.clouds,
            **config.registration_kwargs(True),
        )  # fmt: skip
        if len(cloud) == 0:
            warnings.append("the registered cloud is empty")
    with stage("tracks"):
        tracks = _find_tracks(find_tracks, cloud, track, seq, config)
    with stage("scene_elements"):
        reference = reference_centreline(tracks.ego, track, extend=reg.max_range)
        scene = find_scene_elements(
            cloud.xyz, reference, config.planes, config.poles, view_xyz=_view_points(cloud, track)
        )
    return _FinalMap(cloud, tracks, scene, warnings)


def _calibration(
    seq: Sequence,
    config: PrepareConfig,
    cl: Clicks | None,
    cameras: dict[str, Any],
    final: _FinalMap,
    track: PoseTrack,
    clouds: FrameClouds,
) -> CalibrationPoint | None:
    """Stage 10: the calibration point from the clicks, or proposed pole tops, or none."""
    times = {c: _camera_times(seq, c) for c in cameras}
    if cl is not None:
        return calibration_point_from_clicks(
            final.cloud.xyz, track, cameras, times, cl, config.calibration,
            dense=dense_points(seq, track, clouds),
        )  # fmt: skip
    if config.calibration.auto:
        return propose_pole_tops(final.scene.poles, track, cameras, times, config.calibration)
    return None


def _collect_warnings(
    setup: LocalizationSetup, result: Any, final: _FinalMap, cal: CalibrationPoint | None
) -> list[str]:
    odo_ws = setup.odo_health.warnings
    out = []
    for source, ws in (
        ("lidar_alignment", [] if setup.alignment is None else setup.alignment.warnings),
        ("odometry", odo_ws),
        ("strategy", [w for w in result.health.warnings if w not in odo_ws]),
        ("tracks", final.tracks.warnings),
        ("scene", final.scene.warnings),
        ("calibration", [] if cal is None else cal.warnings),
    ):
        out += [f"{source}: {w}" for w in ws]
    return out


# ---------------------------------------------------------------------------- helpers
def _check_clicks(clicks: Clicks, cameras: dict[str, Any]) -> None:
    missing = sorted(set(clicks.uv) - set(cameras))
    if missing:
        raise ClicksError(
            f"clicks of landmark {clicks.landmark!r} name camera(s) {', '.join(missing)} "
            f"that the sequence lacks (it has: {', '.join(sorted(cameras)) or 'none'})"
        )


def _find_tracks(
    find_tracks: Callable,
    cloud: RegisteredCloud,
    track: PoseTrack,
    seq: Sequence,
    config: PrepareConfig,
    ego_only: bool = False,
) -> Any:
    options = dict(config.rails.options)
    if ego_only:
        options["other_tracks"] = False
    try:
        return find_tracks(cloud, track, backend=config.rails.backend, seq=seq, options=options)
    except ValueError as exc:
        raise PreparationError(f"rail extraction ({config.rails.backend}): {exc}") from exc


def _at_frames(track: PoseTrack, inp: Any) -> PoseTrack:
    """``track`` evaluated at the frames' lidar timestamps (frame_idx set)."""
    T = track.interpolate(inp.times, max_extrapolation_s=2.0)
    return PoseTrack(inp.times, T, np.asarray(inp.frames, dtype=np.int64))


def _camera_times(seq: Sequence, camera: str) -> dict[int, float]:
    ts = seq.timestamps(camera)
    return {int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)}


def _view_points(cloud: RegisteredCloud, track: PoseTrack) -> np.ndarray:
    """(n, 3) base origin of the frame each point was measured in (the lidar position)."""
    if track.frame_idx is None or len(cloud) == 0:
        return np.zeros((len(cloud), 3))
    order = np.argsort(track.frame_idx)
    fi = track.frame_idx[order]
    k = np.clip(np.searchsorted(fi, cloud.frame_idx), 0, len(fi) - 1)
    return track.positions[order][k]


def _tracks_summary(tr: Any) -> dict[str, Any]:
    return {
        "backend": tr.backend,
        "ego_found": tr.ego is not None,
        "count": len(tr.centrelines),
        "ego_length_m": None if tr.ego is None else tr.ego.length,
        "rail_points": len(tr.rail_points),
        "warnings": list(tr.warnings),
        "metrics": jsonable(tr.metrics, SUMMARY_MAX_ARRAY),
    }


def _summary(
    seq: Sequence,
    config: PrepareConfig,
    clicks: Clicks | None,
    key: str,
    result: Any,
    setup: LocalizationSetup,
    final: _FinalMap,
    cal: CalibrationPoint | None,
) -> dict[str, Any]:
    frames = seq.frame_indices
    odo_health, pre_tracks, pre_cloud = setup.odo_health, setup.pre_tracks, setup.pre_cloud
    tracks, cloud, scene = final.tracks, final.cloud, final.scene
    return jsonable(
        {
            "artifact_version": ARTIFACT_VERSION,
            "key": key,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "reused": False,
            "sequence": {
                "name": seq.name,
                "folder": str(seq.folder.resolve()),
                "content_key": seq.content_key(),
                "frames": len(frames),
                "first_frame": frames[0],
                "last_frame": frames[-1],
                "cameras": seq.cameras,
            },
            "config": config.model_dump(mode="json"),
            "config_hash": config.config_hash(),
            "clicks": None
            if clicks is None
            else {"landmark": clicks.landmark, "count": len(clicks), "digest": clicks.digest()},
            "requested_strategy": config.strategy,
            "strategy": result.strategy,
            "health": result.health.to_json(),
            "strategy_seconds": result.seconds,
            "strategy_extras": result.extras,
            "odometry_health": odo_health.to_json(),
            "lidar_alignment": None if setup.alignment is None else setup.alignment.summary(),
            "pre_tracks": _tracks_summary(pre_tracks),
            "tracks": _tracks_summary(tracks),
            "cloud": {
                "points": len(cloud),
                "voxel_size": config.registration.voxel_size,
                "pre_points": len(pre_cloud),
                "pre_voxel_size": config.registration.pre_voxel_size,
            },
            "scene": {
                "planes": len(scene.planes),
                "platforms": len(scene.platforms),
                "poles": len(scene.poles),
                "metrics": scene.metrics,
                "warnings": scene.warnings,
            },
            "calibration": None if cal is None else cal.summary(),
        },
        SUMMARY_MAX_ARRAY,
    )
