"""Localization strategies: T_world_base at every frame's lidar timestamp.

``STRATEGIES`` names them; :func:`run_strategy` runs one on a :class:`LocalizationInput`
(:func:`make_input` builds one from a sequence). :func:`odometry_track` is the shared,
memoised KISS-ICP run (the orchestrator calls it first to register a cloud for rail
extraction). Every strategy is in its own module: ``ins``, ``odometry``, ``rails``,
``fused``, ``auto``.
"""

from __future__ import annotations

from osdar_platform.catalog import STRATEGY_NAMES as STRATEGIES
from worker.preparation.localization.auto import AutoStrategy
from worker.preparation.localization.base import (
    Health,
    LocalizationInput,
    LocalizationResult,
    Strategy,
)
from worker.preparation.localization.common import make_input
from worker.preparation.localization.fused import FusedStrategy
from worker.preparation.localization.ins import InsStrategy
from worker.preparation.localization.odometry import OdometryStrategy, odometry_track
from worker.preparation.localization.rails import RailsStrategy

__all__ = [
    "STRATEGIES",
    "Health",
    "LocalizationInput",
    "LocalizationResult",
    "Strategy",
    "get_strategy",
    "make_input",
    "odometry_track",
    "run_strategy",
]


def get_strategy(name: str) -> Strategy:
    """The strategy called ``name`` (one of ``STRATEGIES``); ValueError otherwise."""
    if name == "ins":
        return InsStrategy()
    if name == "odometry":
        return OdometryStrategy()
    if name == "rails":
        return RailsStrategy()
    if name == "fused":
        return FusedStrategy()
    if name == "auto":
        return AutoStrategy()
    raise ValueError(f"unknown localization strategy {name!r}; valid: {', '.join(STRATEGIES)}")


def run_strategy(name: str, inp: LocalizationInput) -> LocalizationResult:
    """Run strategy ``name`` on ``inp`` (poses at every frame's lidar time, finite)."""
    return get_strategy(name).run(inp)
