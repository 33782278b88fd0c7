"""Strategy ``rails``: the OSDaR-AR paper's rail refinement of the INS.

Each frame's INS position (nominal misalignment, ASSUMED) is projected onto the ego
centreline; the pose is the centreline frame there (:meth:`Centreline.frame_at`): position
on the centreline, heading from its tangent, pitch from its slope and roll from its cant.
Beyond the centreline's ends the end frame is moved along its tangent.

Without an ego centreline (``inp.ego`` is None) it falls back to the raw INS and says so
("no rails found"). INS positions far from the centreline are reported.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray
from scipy.stats import median_abs_deviation

from worker.preparation.centreline import Centreline
from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult
from worker.preparation.localization.common import ins_at_frames, make_result

F64 = NDArray[np.float64]

#: An INS position farther than this (m, horizontal) from the ego centreline is suspicious.
FAR_FROM_RAILS_M = 2.0


def rail_frames(ego: Centreline, p_world: F64) -> tuple[F64, F64, F64]:
    """Project (n, 3) world points onto the centreline.

    Returns
    -------
    T_world_base (n, 4, 4) centreline frames at the projections (extended along the end
    tangents beyond the ends), arc lengths s (n,) (unclamped), horizontal distances (n,)
    to the centreline or, beyond its ends, to its extension.
    """
    proj = ego.project(p_world)
    s = np.asarray(proj.s, dtype=np.float64).copy()
    dist = np.asarray(proj.distance, dtype=np.float64).copy()
    T = ego.frame_at(s)
    # Beyond an end: move along the end tangent by the along-tangent excess; the distance
    # is then across the extended line (a train on the first, never seen metres of its
    # track is on the line ahead, not metres from its track).
    for end in (0.0, ego.length):
        at_end = np.abs(s - end) < 1e-9
        if not np.any(at_end):
            continue
        tangent = ego.tangent(np.array([end]))[0]
        excess = (p_world[at_end] - ego.point(np.array([end]))[0]) @ tangent
        excess = np.minimum(excess, 0.0) if end == 0.0 else np.maximum(excess, 0.0)
        T[at_end, :3, 3] += excess[:, None] * tangent
        s[at_end] += excess
        dist[at_end] = np.linalg.norm((p_world[at_end] - T[at_end, :3, 3])[:, :2], axis=1)
    return T, s, dist


#: Spacing (m) at which :func:`orientation_noise` samples the centreline: twice the
#: fit's knot spacing (tracks.FitOptions.station_step), where the knots' noise shows.
NOISE_STEP_M = 4.0


def orientation_noise(ego: Centreline, s_lo: float, s_hi: float) -> F64:
    """Noise (rad) of the centreline frame's roll, pitch and heading over ``[s_lo, s_hi]``.

    A railway alignment is smooth (straights, arcs, clothoids, linear cant ramps): sampled
    every :data:`NOISE_STEP_M` its roll, pitch and heading have second differences near
    zero, while a fitted centreline's knot noise shows in them. Robust std of the second
    differences / sqrt(6) (white noise). Returns (3,) [roll, pitch, heading]; zeros for
    fewer than 5 samples.
    """
    lo, hi = max(0.0, float(s_lo)), min(ego.length, float(s_hi))
    s = np.arange(lo, hi + 1e-9, NOISE_STEP_M)
    if len(s) < 5:
        return np.zeros(3)
    t = ego.tangent(s)
    heading = np.unwrap(np.arctan2(t[:, 1], t[:, 0]))
    pitch = np.arcsin(np.clip(t[:, 2], -1.0, 1.0))
    out = np.zeros(3)
    for i, a in enumerate((ego.roll(s), pitch, heading)):
        d2 = a[:-2] - 2.0 * a[1:-1] + a[2:]
        out[i] = median_abs_deviation(d2, scale="normal") / np.sqrt(6.0)
    return out


class RailsStrategy:
    """INS projected onto the ego centreline (the paper's refinement)."""

    name = "rails"

    def run(self, inp: LocalizationInput) -> LocalizationResult:
        started = time.perf_counter()
        health = Health()
        ins = ins_at_frames(inp, health)
        if inp.ego is None:
            health.degrade("no rails found: no ego centreline; falling back to the raw INS")
            health.fallback = "ins"
            return make_result(self.name, inp, ins.T_world_base, health, started)
        try:
            T, s, dist = rail_frames(inp.ego, ins.T_world_base[:, :3, 3])
        except Exception as exc:
            health.degrade(f"rails: projection onto the centreline failed ({exc}); raw INS used")
            health.fallback = "ins"
            return make_result(self.name, inp, ins.T_world_base, health, started)
        self._check(inp, ins.T_world_base, T, s, dist, health)
        return make_result(
            self.name,
            inp,
            T,
            health,
            started,
            extras={"assumption": "nominal INS-to-lidar misalignment for the along-track s"},
            fallback_T=ins.T_world_base,
        )

    @staticmethod
    def _check(
        inp: LocalizationInput, T_ins: F64, T: F64, s: F64, dist: F64, health: Health
    ) -> None:
        ego = inp.ego
        assert ego is not None
        health.metrics["rails_ins_distance_mean_m"] = float(np.mean(dist))
        health.metrics["rails_ins_distance_max_m"] = float(np.max(dist))
        outside = (s < 0.0) | (s > ego.length)
        if np.any(outside):
            frames = [inp.frames[k] for k in np.flatnonzero(outside)]
            health.warn(f"rails: frame(s) {frames} beyond the centreline's ends; extrapolated")
        if np.max(dist) > FAR_FROM_RAILS_M:
            health.warn(
                f"rails: INS up to {np.max(dist):.2f} m from the ego centreline "
                f"(> {FAR_FROM_RAILS_M} m): wrong track or bad INS?"
            )
        # Heading of the INS against the centreline tangent (driving direction check).
        cos = np.einsum("ni,ni->n", T_ins[:, :3, 0], T[:, :3, 0])
        if np.median(cos) < 0.0:
            health.warn("rails: the train faces against the centreline's direction; flipped")
            flip = np.diag([-1.0, -1.0, 1.0])
            T[:, :3, :3] = T[:, :3, :3] @ flip
