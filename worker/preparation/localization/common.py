"""Helpers shared by the localization strategies.

- :func:`make_input`: a :class:`LocalizationInput` from an opened sequence (what the
  orchestrator does, usable by tests and benchmarks);
- :func:`ins_at_frames`: the raw INS base poses at the frames' lidar timestamps, with the
  INS health (dropouts, GNSS jumps, standstill) and per-frame validity;
- :func:`make_result`: a finite, frame-indexed :class:`LocalizationResult` (never NaN);
- small SE(3) helpers on stacks of (4, 4) transforms.

The INS-to-lidar misalignment used here is the documented ASSUMPTION
(:meth:`geometry.poses.InsToLidar.nominal`: axes aligned, zero lever arm and latency);
strategies that estimate it say so.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import median_abs_deviation

from geometry.pose_uncertainty import PoseInformation
from geometry.poses import PoseTrack
from worker.osdar.ins_poses import ins_to_base_poses, world_frame_from_ins
from worker.osdar.sequence import Sequence
from worker.preparation.centreline import Centreline
from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult

F64 = NDArray[np.float64]
log = logging.getLogger("worker.preparation.localization")

#: Below this travelled distance over the whole sequence (m) the train counts as standing.
STANDSTILL_DISTANCE_M = 0.5
#: An INS record farther than this from a frame's lidar time (s) does not cover the frame.
INS_GAP_S = 0.06
#: A GNSS jump: INS position increment off its velocity prediction by more than this (m).
JUMP_THRESHOLD_M = 0.3
#: INS poses at frames outside the INS time range are extrapolated at most this far (s).
MAX_INS_EXTRAPOLATION_S = 2.0


def make_input(
    seq: Sequence,
    ego: Centreline | None = None,
    options: dict[str, Any] | None = None,
) -> LocalizationInput:
    """Build the strategies' input from an opened sequence (nominal INS misalignment).

    Frames without a finite lidar timestamp are left out.
    """
    ins = seq.ins()
    world = world_frame_from_ins(ins)
    ins_track = ins_to_base_poses(ins, world)
    stream = seq.lidar_stream
    if stream is None:
        raise ValueError(f"sequence {seq.name} has no lidar stream")
    ts = seq.timestamps(stream)
    frame_times = {
        int(f): float(t) for f, t in zip(seq.frame_indices, ts, strict=True) if np.isfinite(t)
    }
    return LocalizationInput(
        sequence=seq,
        world=world,
        ins=ins,
        ins_track=ins_track,
        frame_times=frame_times,
        ego=ego,
        options=dict(options or {}),
    )


# --------------------------------------------------------------------------------------------
# SE(3) helpers
# --------------------------------------------------------------------------------------------


def poses_from(R: F64, p: F64) -> F64:
    """(n, 3, 3) rotations and (n, 3) positions -> (n, 4, 4) transforms."""
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    return T


def relative_motions(T: F64) -> F64:
    """(n, 4, 4) -> (n-1, 4, 4) ``T_k^-1 T_{k+1}``."""
    Ti = np.linalg.inv(T[:-1])
    return Ti @ T[1:]


def chain(T0: F64, deltas: F64) -> F64:
    """Poses from a first pose (4, 4) and (n-1, 4, 4) relative motions -> (n, 4, 4)."""
    out = np.empty((len(deltas) + 1, 4, 4))
    out[0] = T0
    for k, d in enumerate(deltas):
        out[k + 1] = out[k] @ d
    return out


def travelled(p: F64) -> float:
    """Path length (m) of (n, 3) positions."""
    if len(p) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def rotation_deg(Ra: F64, Rb: F64) -> F64:
    """(n,) angles (deg) of ``Ra^T Rb`` for (n, 3, 3) stacks."""
    return np.degrees(Rotation.from_matrix(np.swapaxes(Ra, -1, -2) @ Rb).magnitude())


# --------------------------------------------------------------------------------------------
# INS at the frames
# --------------------------------------------------------------------------------------------


@dataclass
class InsFrames:
    """Raw INS (nominal misalignment) at the frames.

    T_world_base : (n, 4, 4) at the frames' lidar times (interpolated, extrapolated at ends).
    covered : (n,) bool, an INS record lies within ``INS_GAP_S`` of the frame.
    jump_frames : frame positions k (0-based) where a GNSS jump starts (between k-1 and k).
    jump_steps : (len(jump_frames), 3) world offsets of those jumps (m).
    v_world : (n, 3) INS velocity at the frames (m/s, from the INSPVA velocities, ENU ~ world).
    standstill : whether the train does not move over the sequence.
    """

    T_world_base: F64
    covered: NDArray[np.bool_]
    jump_frames: list[int]
    jump_steps: F64
    v_world: F64
    standstill: bool


def _ins_velocity_world(inp: LocalizationInput, times: F64) -> F64:
    """(n, 3) INS velocity (east, north, up) at ``times`` (nearest-neighbour-free interp)."""
    ins = inp.ins
    t = np.asarray(ins.timestamp, dtype=np.float64)
    v = np.stack(
        [
            np.asarray(ins.east_velocity, dtype=np.float64),
            np.asarray(ins.north_velocity, dtype=np.float64),
            np.asarray(ins.up_velocity, dtype=np.float64),
        ],
        axis=1,
    )
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    if not np.any(ok):
        return np.zeros((len(times), 3))
    t, v = t[ok], v[ok]
    order = np.argsort(t)
    t, v = t[order], v[order]
    return np.stack([np.interp(times, t, v[:, i]) for i in range(3)], axis=1)


def interpolate_track(track: PoseTrack, times: F64) -> F64:
    """(n, 4, 4) poses of ``track`` at ``times``, extrapolating (constant velocity) up to
    ``MAX_INS_EXTRAPOLATION_S`` and holding the end pose beyond that."""
    t0, t1 = track.timestamps[0], track.timestamps[-1]
    if len(track) == 1:
        return np.repeat(track.T[:1], len(times), axis=0)
    tq = np.clip(times, t0 - MAX_INS_EXTRAPOLATION_S, t1 + MAX_INS_EXTRAPOLATION_S)
    return track.interpolate(tq, max_extrapolation_s=MAX_INS_EXTRAPOLATION_S)


def detect_jumps(p: F64, v: F64, times: F64, covered: NDArray[np.bool_]) -> tuple[list[int], F64]:
    """GNSS jumps: position increments that disagree with the INS velocity.

    Parameters
    ----------
    p : (n, 3) INS positions at the frames; v : (n, 3) velocities; times : (n,) s;
    covered : (n,) frames with their own INS record.

    Returns
    -------
    frame positions k where a jump occurs (between k-1 and k) and their (m, 3) offsets.
    """
    if len(p) < 3:
        return [], np.zeros((0, 3))
    dt = np.diff(times)
    predicted = 0.5 * (v[:-1] + v[1:]) * dt[:, None]
    excess = np.diff(p, axis=0) - predicted
    mag = np.linalg.norm(excess, axis=1)
    noise = float(median_abs_deviation(mag, scale="normal")) + float(np.median(mag))
    thresh = max(JUMP_THRESHOLD_M, 8.0 * noise)
    both = covered[:-1] & covered[1:]
    ks = [int(k) + 1 for k in np.flatnonzero((mag > thresh) & both)]
    return ks, (excess[[k - 1 for k in ks]] if ks else np.zeros((0, 3)))


def ins_at_frames(inp: LocalizationInput, health: Health) -> InsFrames:
    """The raw INS base poses at the frames' lidar times, with their health.

    Warns (into ``health``) about frames without an INS record (dropout: interpolated),
    GNSS jumps and standstill; records ``ins_*`` metrics.
    """
    cache = inp.options.get("_ins_frames")
    if isinstance(cache, InsFrames):
        _report_ins(cache, inp, health)
        return cache
    times = inp.times
    T = interpolate_track(inp.ins_track, times)
    ts_ins = inp.ins_track.timestamps
    k = np.clip(np.searchsorted(ts_ins, times), 1, max(len(ts_ins) - 1, 1))
    lo = ts_ins[np.clip(k - 1, 0, len(ts_ins) - 1)]
    hi = ts_ins[np.clip(k, 0, len(ts_ins) - 1)]
    gap = np.minimum(np.abs(times - lo), np.abs(times - hi))
    covered = gap <= INS_GAP_S
    v = _ins_velocity_world(inp, times)
    p = T[:, :3, 3]
    jumps, steps = detect_jumps(p, v, times, covered)
    standstill = travelled_robust(p, v, times) < STANDSTILL_DISTANCE_M
    out = InsFrames(T, covered, jumps, steps, v, standstill)
    inp.options["_ins_frames"] = out
    _report_ins(out, inp, health)
    return out


def travelled_robust(p: F64, v: F64, times: F64) -> float:
    """Travelled distance (m) from the INS velocity integral, else from the positions.

    The velocity is the INS's best-measured quantity (cm/s); its integral is immune to GNSS
    jumps and to the position solution's wander, which over a few seconds shortens or
    lengthens the position path by decimetres (osdar23 profile, station, 20 frames: true
    11.40 m, velocity integral 11.40 m, positions 10.77 m). Positions only when no record
    has a velocity.
    """
    if len(times) < 2:
        return 0.0
    speed = np.linalg.norm(v, axis=1)
    if not np.any(speed > 0):
        return travelled(p)
    return float(np.sum(0.5 * (speed[:-1] + speed[1:]) * np.diff(times)))


def _report_ins(ins: InsFrames, inp: LocalizationInput, health: Health) -> None:
    frames = inp.frames
    missing = [frames[i] for i in np.flatnonzero(~ins.covered)]
    if missing:
        health.warn(f"INS dropout: no INS record for frame(s) {missing}; poses interpolated")
    for k, step in zip(ins.jump_frames, ins.jump_steps, strict=True):
        health.warn(
            f"GNSS jump at frame {frames[k]}: {np.linalg.norm(step):.2f} m "
            f"(E {step[0]:+.2f}, N {step[1]:+.2f}, U {step[2]:+.2f})"
        )
    if ins.standstill:
        health.warn("standstill: the train does not move; heading from motion unavailable")
    health.metrics["ins_dropout_frames"] = float(len(missing))
    health.metrics["ins_jumps"] = float(len(ins.jump_frames))
    health.metrics["ins_travelled_m"] = travelled_robust(
        ins.T_world_base[:, :3, 3], ins.v_world, inp.times
    )


def remove_jumps(p: F64, jump_frames: list[int], steps: F64) -> F64:
    """INS positions with the jump steps removed, the longest jump-free segment kept as is.

    Parameters
    ----------
    p : (n, 3); jump_frames : positions k of the jumps; steps : (m, 3) their offsets.
    """
    if not jump_frames:
        return p.copy()
    bounds = [0, *jump_frames, len(p)]
    offset = np.zeros((len(p), 3))
    cum = np.zeros(3)
    for j, k in enumerate(jump_frames):
        cum = cum + steps[j]
        offset[k:] = cum
    lengths = np.diff(bounds)
    ref = int(np.argmax(lengths))
    offset -= offset[bounds[ref]]
    return p - offset


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


def make_result(
    name: str,
    inp: LocalizationInput,
    T_world_base: F64,
    health: Health,
    started: float,
    extras: dict[str, Any] | None = None,
    fallback_T: F64 | None = None,
    information: PoseInformation | None = None,
) -> LocalizationResult:
    """A finite result at the frames' lidar times; non-finite poses are replaced by
    ``fallback_T`` (else the raw INS) with a warning."""
    T = np.asarray(T_world_base, dtype=np.float64)
    bad = ~np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    if np.any(bad):
        repl = fallback_T if fallback_T is not None else interpolate_track(inp.ins_track, inp.times)
        health.warn(f"{name}: {int(bad.sum())} non-finite poses replaced by the fallback")
        health.fallback = health.fallback or "ins"
        T = T.copy()
        T[bad] = repl[bad]
    track = PoseTrack(inp.times, T, np.asarray(inp.frames, dtype=np.int64))
    return LocalizationResult(
        strategy=name,
        track=track,
        health=health,
        seconds=time.perf_counter() - started,
        extras=dict(extras or {}),
        information=information or default_information(name, health, len(T)),
    )


#: Uncertainty models of the strategies that give none of their own (rad, m): the raw INS
#: and the rail-refined INS as independent per-frame errors (the osdar23-like INS: 7 cm
#: and 0.04 deg between consecutive frames; a fitted centreline's heading: tenths of a
#: degree), the odometry as a random walk of the fused smoothing's ICP step sigmas.
DEFAULT_UNCERTAINTY = {
    "ins": ("independent", np.radians(0.03), 0.05),
    "rails": ("independent", np.radians(0.3), 0.05),
    "odometry": ("random_walk", np.radians(0.01), 0.006),
}
#: Factor on a degraded strategy's default sigmas.
DEGRADED_FACTOR = 10.0


def default_information(name: str, health: Health, n: int) -> PoseInformation | None:
    """The :data:`DEFAULT_UNCERTAINTY` model of strategy ``name`` (None: unknown)."""
    model = DEFAULT_UNCERTAINTY.get(name)
    if model is None or n == 0:
        return None
    kind, s_rot, s_pos = model
    f = DEGRADED_FACTOR if health.degraded else 1.0
    if kind == "random_walk":
        return PoseInformation.random_walk(f * s_rot, f * s_pos, n)
    return PoseInformation.independent(f * s_rot, f * s_pos, n)
