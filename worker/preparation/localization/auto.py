"""Strategy ``auto``: picks a strategy per sequence from internal consistency measures.

Never reads ground truth. Candidates: ``fused``, ``rails``, ``odometry``, ``ins`` (in that
order of preference). For each it measures, on the clouds KISS-ICP already read (kept by the
shared odometry run, so no PCD is read again):

- **map crispness**: the median point-to-plane distance between points of a frame and the
  surfaces of an earlier frame (1 and ``STRIDE`` frames back) once both are placed with the
  candidate's poses (mm; lower is crisper);
- **rail residual**: RMS horizontal/vertical distance of the poses from the ego centreline
  (when one is known);
- **INS agreement**: RMS difference of the frame-to-frame motion against the INS.

A candidate that fell back, or odometry flagged degenerate along the track (where the map
stays crisp although the poses slip along it), is excluded. Among the rest the crispest
wins; a more preferred candidate within ``TIE_TOLERANCE`` of the best is kept instead. The
choice and its reasons are in ``extras["chosen"]``, ``extras["reason"]`` and the
``auto_*`` metrics.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from worker.preparation.localization.base import (
    Health,
    LocalizationInput,
    LocalizationResult,
    Strategy,
)
from worker.preparation.localization.common import make_result, relative_motions
from worker.preparation.localization.fused import FusedStrategy
from worker.preparation.localization.ins import InsStrategy
from worker.preparation.localization.odometry import (
    OdometryStrategy,
    is_degenerate,
    odometry_run,
)
from worker.preparation.localization.rails import RailsStrategy

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

PREFERENCE = ("fused", "rails", "odometry", "ins")
_CANDIDATES: dict[str, type[Strategy]] = {
    "fused": FusedStrategy,
    "rails": RailsStrategy,
    "odometry": OdometryStrategy,
    "ins": InsStrategy,
}
#: A more preferred candidate is kept if its crispness is within this factor of the best.
TIE_TOLERANCE = 1.10
#: Frame pairs (k - STRIDE, k) are checked as well as consecutive ones.
STRIDE = 5
#: At most this many frames anchor the crispness check.
MAX_PAIRS = 12
#: Correspondences farther than this (m) are not the same surface.
MAX_CORRESPONDENCE_M = 0.5


def _normals(points: F64) -> F64:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(1.5, 12))
    return np.asarray(pcd.normals)


def _pairs(n: int) -> list[tuple[int, int]]:
    pairs = [(k - 1, k) for k in range(1, n)] + [(k - STRIDE, k) for k in range(STRIDE, n)]
    if len(pairs) > MAX_PAIRS:
        idx = np.linspace(0, len(pairs) - 1, MAX_PAIRS).round().astype(int)
        pairs = [pairs[i] for i in idx]
    return pairs


def crispness(clouds: list[F64], T_world_base: F64) -> float:
    """Median point-to-plane distance (m) between frame pairs placed with these poses.

    Parameters
    ----------
    clouds : per frame (m_k, 3) base points; T_world_base : (n, 4, 4).

    Returns NaN when no pair has enough points.
    """
    dists = []
    normals_cache: dict[int, F64] = {}
    trees: dict[int, cKDTree] = {}
    for a, b in _pairs(len(clouds)):
        pa, pb = clouds[a], clouds[b]
        if len(pa) < 50 or len(pb) < 50:
            continue
        if a not in trees:
            trees[a] = cKDTree(pa)
            normals_cache[a] = _normals(pa)
        T_a_b = np.linalg.inv(T_world_base[a]) @ T_world_base[b]
        q = pb @ T_a_b[:3, :3].T + T_a_b[:3, 3]
        d, i = trees[a].query(q, distance_upper_bound=MAX_CORRESPONDENCE_M)
        ok = np.isfinite(d)
        if np.sum(ok) < 20:
            continue
        n = normals_cache[a][i[ok]]
        dists.append(np.abs(np.einsum("ni,ni->n", q[ok] - pa[i[ok]], n)))
    if not dists:
        return float("nan")
    return float(np.median(np.concatenate(dists)))


#: A result whose map is this much less crisp than the crispest candidate's is taken as more
#: than 2x worse than the best available (crispness grows slower than the pose error:
#: 37 against 70 mm for a 7x worse lag-1 translation; the robustness matrix reports how
#: often this judgement is right).
CRISP_DEGRADED = 1.5


def judge(results: dict[str, LocalizationResult], crisp: dict[str, float]) -> None:
    """Flag (in their health) the results whose map is CRISP_DEGRADED times less crisp
    than the crispest of ``crisp`` ({name: m}, NaN: not measured)."""
    finite = {k: v for k, v in crisp.items() if np.isfinite(v) and v > 0}
    if not finite:
        return
    best_name = min(finite, key=finite.__getitem__)
    best = finite[best_name]
    for name, res in results.items():
        c = finite.get(name)
        if c is not None and c > CRISP_DEGRADED * best:
            res.health.degrade(
                f"{name}: map {c / best:.1f}x less crisp than {best_name}'s "
                f"({c * 1000:.1f} against {best * 1000:.1f} mm): likely more than 2x worse"
            )


def rail_residual(inp: LocalizationInput, T: F64) -> float:
    """RMS (m) of the poses' horizontal and vertical offsets from the ego centreline."""
    if inp.ego is None:
        return float("nan")
    proj = inp.ego.project(T[:, :3, 3])
    return float(np.sqrt(np.mean(proj.lateral**2 + proj.vertical**2)))


def ins_agreement(T: F64, T_ins: F64) -> float:
    """RMS (m) difference of frame-to-frame translations against the INS."""
    if len(T) < 2:
        return 0.0
    a, b = relative_motions(T), relative_motions(T_ins)
    return float(np.sqrt(np.mean(np.sum((a[:, :3, 3] - b[:, :3, 3]) ** 2, axis=1))))


class AutoStrategy:
    """Chooses among fused, rails, odometry and ins by internal consistency."""

    name = "auto"

    def run(self, inp: LocalizationInput) -> LocalizationResult:

        started = time.perf_counter()
        health = Health()
        results: dict[str, LocalizationResult] = {}
        for name in PREFERENCE:
            try:
                results[name] = _CANDIDATES[name]().run(inp)
            except Exception as exc:
                health.warn(f"auto: candidate {name} failed ({exc})")
        if "ins" not in results:
            raise RuntimeError("auto: even the raw INS failed")
        try:
            clouds = odometry_run(inp).clouds
        except Exception as exc:
            health.warn(f"auto: no clouds for the consistency check ({exc})")
            clouds = []
        T_ins = results["ins"].track.T
        scores: dict[str, float] = {}
        reasons: list[str] = []
        crisp_all = {
            name: crispness(clouds, res.track.T) if clouds else float("nan")
            for name, res in results.items()
        }
        judge(results, crisp_all)
        for name, res in results.items():
            T = res.track.T
            crisp = crisp_all[name]
            health.metrics[f"auto_crispness_{name}_m"] = crisp
            health.metrics[f"auto_rail_residual_{name}_m"] = rail_residual(inp, T)
            health.metrics[f"auto_ins_agreement_{name}_m"] = ins_agreement(T, T_ins)
            health.metrics[f"auto_seconds_{name}"] = res.seconds
            if res.health.fallback is not None:
                reasons.append(f"{name} excluded: fell back to {res.health.fallback}")
                continue
            if name == "odometry" and is_degenerate(res.health):
                reasons.append("odometry excluded: degenerate along the track")
                continue
            scores[name] = crisp if np.isfinite(crisp) else np.inf
        chosen = self._choose(scores, reasons)
        for w in results[chosen].health.warnings:
            health.warnings.append(w if w.startswith(f"{chosen}:") else f"{chosen}: {w}")
        if chosen != PREFERENCE[0]:
            health.fallback = chosen
        for why in results[chosen].health.degraded:
            health.degraded.append(f"auto chose {chosen}, itself degraded: {why}")
        health.metrics["auto_chosen_index"] = float(PREFERENCE.index(chosen))
        reason = "; ".join(reasons)
        log.info("auto chose %s: %s", chosen, reason)
        extras = dict(results[chosen].extras)
        extras.update({"chosen": chosen, "reason": reason})
        return make_result(
            self.name, inp, results[chosen].track.T, health, started, extras,
            information=results[chosen].information,
        )  # fmt: skip

    @staticmethod
    def _choose(scores: dict[str, float], reasons: list[str]) -> str:
        if not scores:
            reasons.append("no candidate usable; raw INS")
            return "ins"
        best = min(scores.values())
        for name in PREFERENCE:
            if name in scores and scores[name] <= best * TIE_TOLERANCE + 1e-6:
                reasons.append(
                    f"chose {name}: crispness {scores[name] * 1000:.1f} mm (best "
                    f"{best * 1000:.1f} mm; "
                    + ", ".join(f"{k} {v * 1000:.1f}" for k, v in scores.items())
                    + ")"
                )
                return name
        return min(scores, key=scores.__getitem__)
