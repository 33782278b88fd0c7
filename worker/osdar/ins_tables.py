"""In-memory tables of the three NovAtel OEM7 CSV streams of an OSDaR23 sequence.

One row per record, columns as (n,) arrays, units exactly as in the CSV files
(degrees for angles, metres, m/s); see ../shared/design/OSDAR23.md. Conversion to
radians and to poses happens in ``geometry.poses``, never here.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class _Table:
    """Column table: every field is an (n,) array of the same length."""

    def __len__(self) -> int:
        return len(getattr(self, fields(self)[0].name))

    def take(self, index: NDArray) -> _Table:
        """Rows selected by an index or boolean mask, as a new table of the same type."""
        return type(self)(
            **{f.name: np.asarray(getattr(self, f.name))[index] for f in fields(self)}
        )

    @classmethod
    def columns(cls) -> list[str]:
        """CSV column names in file order."""
        return [f.name for f in fields(cls)]


@dataclass
class InsPva(_Table):
    """``novatel_oem7_inspva``: INS position, velocity, attitude.

    roll: deg, right-handed about the INS Y (forward) axis; pitch: deg, right-handed about
    the INS X (right) axis; azimuth: deg, clockwise from north (left-handed about Z).
    """

    frame_idx: I64
    timestamp: F64
    latitude: F64
    longitude: F64
    height: F64
    north_velocity: F64
    east_velocity: F64
    up_velocity: F64
    roll: F64
    pitch: F64
    azimuth: F64


@dataclass
class InsStdDev(_Table):
    """``novatel_oem7_insstdev``: standard deviations of the INS solution (m, m/s, deg)."""

    frame_idx: I64
    timestamp: F64
    latitude_stdev: F64
    longitude_stdev: F64
    height_stdev: F64
    north_velocity_stdev: F64
    east_velocity_stdev: F64
    up_velocity_stdev: F64
    roll_stdev: F64
    pitch_stdev: F64
    azimuth_stdev: F64


@dataclass
class CorrImu(_Table):
    """``novatel_oem7_corrimu``: corrected IMU increments (rad/sample, m/s/sample)."""

    frame_idx: I64
    timestamp: F64
    gps_week_number: I64
    gps_week_milliseconds: F64
    pitch_rate: F64
    roll_rate: F64
    yaw_rate: F64
    lateral_acc: F64
    longitudinal_acc: F64
    vertical_acc: F64
