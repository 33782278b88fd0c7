"""Strategy ``ins``: the raw INS/GNSS poses at the frames' lidar timestamps.

The INS-to-lidar misalignment is the documented ASSUMPTION
(:meth:`geometry.poses.InsToLidar.nominal`: axes aligned, zero lever arm and latency).
Dropouts are interpolated, GNSS jumps and standstill reported (not corrected: this is the
raw baseline).
"""

from __future__ import annotations

import time

from worker.preparation.localization.base import Health, LocalizationInput, LocalizationResult
from worker.preparation.localization.common import ins_at_frames, make_result

ASSUMPTION = "nominal INS-to-lidar misalignment (axes aligned, zero lever arm/latency) ASSUMED"


class InsStrategy:
    """Raw INS poses (nominal misalignment)."""

    name = "ins"

    def run(self, inp: LocalizationInput) -> LocalizationResult:
        started = time.perf_counter()
        health = Health()
        ins = ins_at_frames(inp, health)
        return make_result(
            self.name, inp, ins.T_world_base, health, started, extras={"assumption": ASSUMPTION}
        )
