"""What every localization strategy takes and gives.

A strategy maps a sequence (and what earlier preparation found) to T_world_base at every
frame's lidar timestamp, in the sequence's world frame (ENU at the first INS record), plus
a health report. It never fails on degraded input and never returns NaN: it falls back
and says so in ``Health``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from geometry.geodesy import WorldFrame
from geometry.pose_uncertainty import PoseInformation
from geometry.poses import PoseTrack
from worker.osdar.ins_tables import InsPva
from worker.osdar.sequence import Sequence
from worker.preparation.centreline import Centreline


@dataclass
class Health:
    """A strategy's own report: what it saw (GNSS jumps, standstill, dropouts, ...), the
    consistency measures it computed (used by ``auto``), which fallback it took, if any,
    and why the result is believed degraded - more than 2x worse than the best available
    (a degenerate or slipping ICP, no rails for the rail strategy, a failed smoothing, a
    map much less crisp than another strategy's: :func:`~.auto.judge`). A warning alone is
    information; ``ok`` is False only with a reason in ``degraded``."""

    warnings: list[str] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    fallback: str | None = None
    degraded: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.degraded

    def degrade(self, reason: str) -> None:
        """Flag the result as degraded (also a warning)."""
        self.warn(reason)
        self.degraded.append(reason)

    def warn(self, message: str) -> None:

        logging.getLogger("worker.preparation.localization").warning(message)
        self.warnings.append(message)

    def to_json(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "degraded": list(self.degraded),
            "warnings": list(self.warnings),
            "metrics": {k: float(v) for k, v in self.metrics.items()},
            "fallback": self.fallback,
        }


@dataclass
class LocalizationInput:
    """Everything a strategy may use. ``ego`` is the ego centreline when rails were found
    (None otherwise); ``frame_times`` maps frame counter -> lidar timestamp (s)."""

    sequence: Sequence
    world: WorldFrame
    ins: InsPva
    ins_track: PoseTrack
    frame_times: dict[int, float]
    ego: Centreline | None = None
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> list[int]:
        return sorted(self.frame_times)

    @property
    def times(self) -> np.ndarray:
        return np.array([self.frame_times[f] for f in self.frames])


@dataclass
class LocalizationResult:
    """Poses T_world_base at each frame's lidar timestamp (``track.frame_idx`` set)."""

    strategy: str
    track: PoseTrack
    health: Health
    seconds: float
    extras: dict[str, Any] = field(default_factory=dict)
    #: Uncertainty of the poses (None: the strategy gives none; see
    #: :func:`~worker.preparation.localization.common.default_information`)
    information: PoseInformation | None = None


class Strategy(Protocol):
    """A localization strategy: ``name`` and ``run(inp) -> LocalizationResult``."""

    name: str

    def run(self, inp: LocalizationInput) -> LocalizationResult: ...
