"""Vehicle poses from the NovAtel INS, and pose tracks over time.

NovAtel attitude convention (SPAN / OEM7, INSPVA)
-------------------------------------------------
The INS body frame (SPAN computation frame) is X right, Y forward, Z up. INSPVA reports

- ``roll``: right-handed rotation about the body Y (forward) axis: positive roll lowers the
  right side (body X tilts down);
- ``pitch``: right-handed rotation about the body X (right) axis: positive pitch raises the
  nose (body Y tilts up);
- ``azimuth``: rotation about Z measured *clockwise* from north to the body Y axis (left
  handed about up), in [0, 360): 90 deg points the nose east.

NovAtel's Euler sequence (SPAN manual, "Definition of Reference Frames", and the
VEHICLEBODYROTATION / APN-037 notes: rotate about Z, then about the new X, then about the new
Y) is intrinsic Z-X'-Y'' from the local level frame to the body frame. As a rotation of
vectors from the body frame to the local level East-North-Up frame this is::

    R_enu_ins = Rz(-azimuth) @ Rx(pitch) @ Ry(roll)

with Rz, Rx, Ry the usual right-handed elementary rotations. Consequences used as checks in
the tests: the body Y axis in ENU is ``(cos p sin a, cos p cos a, sin p)`` and the third row
of ``R_enu_ins`` is ``(-cos p sin r, sin p, cos p cos r)``, which gives the inverse
:func:`novatel_attitude_from_R`.

Latency convention
------------------
``InsToLidar.latency_s`` = L means: the INS record *stamped* t describes the vehicle at the
true time ``t - L`` (the solution is stamped late by L). Correcting it moves each record to
``t - L``; equivalently the pose at a sensor time t is read from the INS at stamp ``t + L``.
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from geometry.geodesy import WorldFrame
from geometry.transforms import make_T, matrix_to_quat, normalize_quat, quat_to_matrix

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

logger = logging.getLogger(__name__)

#: Default extrapolation limit of :meth:`PoseTrack.interpolate` (s).
MAX_EXTRAPOLATION_S = 0.2

POSES_CSV_COLUMNS = ("frame_idx", "timestamp", "x", "y", "z", "qx", "qy", "qz", "qw")


# --------------------------------------------------------------------------------------------
# NovAtel attitude
# --------------------------------------------------------------------------------------------


def _rx(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _ry(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def _rz(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def R_enu_ins_from_novatel(
    roll_deg: ArrayLike, pitch_deg: ArrayLike, azimuth_deg: ArrayLike
) -> F64:
    """NovAtel roll, pitch, azimuth (deg) -> rotation from the INS body frame to local ENU.

    ``R_enu_ins = Rz(-azimuth) @ Rx(pitch) @ Ry(roll)`` (see the module docstring).

    Parameters
    ----------
    roll_deg, pitch_deg, azimuth_deg : scalars or (n,) arrays (broadcast together).

    Returns
    -------
    (n, 3, 3) float64; ``v_enu = R @ v_ins``.
    """
    r, p, a = np.broadcast_arrays(
        np.atleast_1d(np.radians(np.asarray(roll_deg, dtype=np.float64))),
        np.atleast_1d(np.radians(np.asarray(pitch_deg, dtype=np.float64))),
        np.atleast_1d(np.radians(np.asarray(azimuth_deg, dtype=np.float64))),
    )
    return _rz(-a) @ _rx(p) @ _ry(r)


def novatel_attitude_from_R(R_enu_ins: ArrayLike) -> tuple[F64, F64, F64]:
    """Inverse of :func:`R_enu_ins_from_novatel`.

    Parameters
    ----------
    R_enu_ins : (3, 3) or (n, 3, 3) rotation from the INS body frame to local ENU.

    Returns
    -------
    roll (n,) in (-180, 180], pitch (n,) in [-90, 90], azimuth (n,) in [0, 360), degrees.
    At pitch = +-90 deg (gimbal lock) roll is set to 0 and azimuth takes the whole heading.
    """
    R = np.asarray(R_enu_ins, dtype=np.float64).reshape(-1, 3, 3)
    pitch = np.arcsin(np.clip(R[:, 2, 1], -1.0, 1.0))
    roll = np.arctan2(-R[:, 2, 0], R[:, 2, 2])
    azimuth = np.arctan2(R[:, 0, 1], R[:, 1, 1])
    # Gimbal lock: the body Y axis is vertical; use the body X axis (right) for the heading.
    lock = np.cos(pitch) < 1e-9
    if np.any(lock):
        roll = np.where(lock, 0.0, roll)
        # With r = 0: body X in ENU = Rz(-a) e_x = (cos a, -sin a, 0).
        azimuth = np.where(lock, np.arctan2(-R[:, 1, 0], R[:, 0, 0]), azimuth)
    az_deg = np.mod(np.degrees(azimuth), 360.0)
    az_deg = np.where(az_deg >= 360.0, 0.0, az_deg)  # mod can round up to 360.0
    return np.degrees(roll), np.degrees(pitch), az_deg


# --------------------------------------------------------------------------------------------
# INS -> lidar (base) transform
# --------------------------------------------------------------------------------------------

#: Nominal rotation of the base axes (x forward, y left, z up) in the INS body frame
#: (X right, Y forward, Z up): columns are base x = INS Y, base y = -INS X, base z = INS Z.
R_INS_BASE_NOMINAL: F64 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _nominal_quat() -> F64:
    return matrix_to_quat(R_INS_BASE_NOMINAL)


@dataclass(eq=False)
class InsToLidar:
    """Lever arm, boresight and time latency between the INS and the lidar/base frame.

    ``translation`` (3,) m and ``quaternion`` (4,) [x, y, z, w] are the pose ``T_ins_base`` of
    the base frame (merged lidar: x forward, y left, z up) in the INS body frame (X right,
    Y forward, Z up): ``p_ins = T_ins_base @ p_base``. ``latency_s``: the INS record stamped
    t describes the true time ``t - latency_s`` (see the module docstring).

    The default (:meth:`nominal`) is an ASSUMPTION, not a calibration: axes aligned (base x =
    INS Y, base y = -INS X, base z = INS Z), zero lever arm, zero latency. OSDaR23 does not
    publish the real INS-to-lidar transform; strategies that need it must estimate it (or say
    that they use this assumption).
    """

    translation: F64 = field(default_factory=lambda: np.zeros(3))
    quaternion: F64 = field(default_factory=_nominal_quat)
    latency_s: float = 0.0

    def __post_init__(self) -> None:
        t = np.asarray(self.translation, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"translation must be 3 finite values, got {self.translation!r}")
        self.translation = t
        self.quaternion = normalize_quat(np.asarray(self.quaternion, dtype=np.float64).reshape(4))
        if not np.isfinite(self.latency_s):
            raise ValueError(f"latency_s must be finite, got {self.latency_s}")
        self.latency_s = float(self.latency_s)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, InsToLidar):
            return NotImplemented
        return (
            np.array_equal(self.translation, other.translation)
            and np.array_equal(self.quaternion, other.quaternion)
            and self.latency_s == other.latency_s
        )

    __hash__ = None  # type: ignore[assignment]  # mutable

    @classmethod
    def nominal(cls) -> InsToLidar:
        """The documented assumption: axes aligned, zero lever arm, zero latency."""
        return cls()

    @classmethod
    def from_T(cls, T_ins_base: ArrayLike, latency_s: float = 0.0) -> InsToLidar:
        """From a (4, 4) pose of the base frame in the INS frame."""
        T = np.asarray(T_ins_base, dtype=np.float64)
        return cls(
            translation=T[:3, 3].copy(), quaternion=matrix_to_quat(T[:3, :3]), latency_s=latency_s
        )

    @property
    def T_ins_base(self) -> F64:
        """(4, 4) pose of the base frame in the INS body frame."""
        return make_T(quat_to_matrix(self.quaternion), self.translation)

    def to_json(self) -> dict[str, Any]:
        """``{"translation": [x,y,z], "quaternion": [x,y,z,w], "latency_s": s}``."""
        return {
            "translation": [float(v) for v in self.translation],
            "quaternion": [float(v) for v in self.quaternion],
            "latency_s": self.latency_s,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> InsToLidar:
        """Inverse of :meth:`to_json`; missing keys take the nominal values."""
        nominal = cls()
        return cls(
            translation=np.asarray(data.get("translation", nominal.translation), dtype=np.float64),
            quaternion=np.asarray(data.get("quaternion", nominal.quaternion), dtype=np.float64),
            latency_s=float(data.get("latency_s", 0.0)),
        )


def format_timestamp(t: float) -> str:
    """UNIX seconds with 9 decimals, e.g. ``1631441453.300000000``.

    The digits are the shortest decimal that reads back as the same float64 (a float64 near
    1.6e9 s resolves ~0.24 us), zero-padded: ``1631441453.3`` gives ``.300000000``, not the
    binary noise ``.299999952`` that ``f"{t:.9f}"`` prints.
    """
    s = np.format_float_positional(float(t), precision=9, unique=True, trim=".")
    whole, _, frac = s.partition(".")
    return f"{whole}.{frac:0<9}"


# --------------------------------------------------------------------------------------------
# Pose tracks
# --------------------------------------------------------------------------------------------


class PoseTrack:
    """Poses over time: ``T`` (n, 4, 4) float64 at ``timestamps`` (n,) UNIX seconds.

    On construction the samples are sorted by time and duplicate timestamps are dropped (the
    first one is kept, with a logged warning). Rotations are re-orthonormalised. An optional
    ``frame_idx`` (n,) int64 travels with the samples (it is what the CSV carries).
    """

    def __init__(
        self, timestamps: ArrayLike, T: ArrayLike, frame_idx: ArrayLike | None = None
    ) -> None:
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        Ts = np.asarray(T, dtype=np.float64)
        if Ts.ndim == 2:
            Ts = Ts[None]
        if Ts.shape != (len(ts), 4, 4):
            raise ValueError(
                f"T must be ({len(ts)}, 4, 4) for {len(ts)} timestamps, got {Ts.shape}"
            )
        if len(ts) == 0:
            raise ValueError("a pose track needs at least one pose")
        if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(Ts))):
            raise ValueError("pose track timestamps and poses must be finite")
        fi = None if frame_idx is None else np.asarray(frame_idx, dtype=np.int64).reshape(-1)
        if fi is not None and fi.shape != ts.shape:
            raise ValueError(f"frame_idx must have {len(ts)} entries, got {fi.shape}")

        order = np.argsort(ts, kind="stable")
        if np.any(order != np.arange(len(ts))):
            logger.warning("pose track timestamps were not sorted; sorting %d samples", len(ts))
        ts, Ts = ts[order], Ts[order]
        fi = None if fi is None else fi[order]
        keep = np.ones(len(ts), dtype=bool)
        keep[1:] = np.diff(ts) > 0.0
        if not np.all(keep):
            dups = np.unique(ts[~keep])
            logger.warning(
                "pose track: dropping %d samples with duplicate timestamps (first kept): %s",
                int(np.sum(~keep)),
                ", ".join(f"{t:.9f}" for t in dups[:5]) + (" ..." if len(dups) > 5 else ""),
            )
            ts, Ts = ts[keep], Ts[keep]
            fi = None if fi is None else fi[keep]

        rot = Rotation.from_matrix(Ts[:, :3, :3])  # projects onto the nearest rotation
        Ts = Ts.copy()
        Ts[:, :3, :3] = rot.as_matrix()
        Ts[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
        self.timestamps: F64 = ts
        self.T: F64 = Ts
        self.frame_idx: I64 | None = fi
        self._rotations = rot
        self._slerp: Slerp | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def __repr__(self) -> str:
        return f"PoseTrack(n={len(self)}, t=[{self.timestamps[0]:.3f}, {self.timestamps[-1]:.3f}])"

    # -- accessors --------------------------------------------------------------------------

    @property
    def positions(self) -> F64:
        """(n, 3) translations."""
        return self.T[:, :3, 3].copy()

    @property
    def quaternions(self) -> F64:
        """(n, 4) rotations as [x, y, z, w] with w >= 0."""
        return matrix_to_quat(self.T[:, :3, :3])

    @property
    def rotations(self) -> Rotation:
        """The n rotations as one scipy ``Rotation``."""
        return self._rotations

    @classmethod
    def from_positions_quaternions(
        cls,
        timestamps: ArrayLike,
        positions: ArrayLike,
        quaternions: ArrayLike,
        frame_idx: ArrayLike | None = None,
    ) -> PoseTrack:
        """From (n,) timestamps, (n, 3) positions and (n, 4) quaternions [x, y, z, w]."""
        p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        R = quat_to_matrix(np.asarray(quaternions, dtype=np.float64).reshape(-1, 4))
        T = np.tile(np.eye(4), (len(p), 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        return cls(timestamps, T, frame_idx)

    def transformed(self, T_new_old: ArrayLike) -> PoseTrack:
        """The same track expressed in another frame: ``T_new_x = T_new_old @ T_old_x``."""
        T = np.asarray(T_new_old, dtype=np.float64)
        return PoseTrack(self.timestamps, T @ self.T, self.frame_idx)

    # -- interpolation ----------------------------------------------------------------------

    def interpolate(self, t: ArrayLike, max_extrapolation_s: float = MAX_EXTRAPOLATION_S) -> F64:
        """Poses at times t: linear translation, SLERP rotation.

        Outside [t_first, t_last] the motion is extrapolated at the constant velocity (linear
        and angular, body frame) of the first / last interval, up to ``max_extrapolation_s``;
        further away raises ``ValueError``. A single-pose track only answers at its own time.

        Parameters
        ----------
        t : scalar or (m,) UNIX seconds.

        Returns
        -------
        (m, 4, 4) float64 ``T`` at those times.
        """
        tq = np.atleast_1d(np.asarray(t, dtype=np.float64)).reshape(-1)
        if not np.all(np.isfinite(tq)):
            raise ValueError("interpolation times must be finite")
        t0, t1 = self.timestamps[0], self.timestamps[-1]
        lo, hi = tq < t0, tq > t1
        limit = float(max_extrapolation_s)
        if len(self) == 1:
            limit = 0.0
        bad = (tq < t0 - limit) | (tq > t1 + limit)
        if np.any(bad):
            tb = float(tq[bad][0])
            raise ValueError(
                f"time {tb:.9f} is outside the pose track [{t0:.9f}, {t1:.9f}] by more than "
                f"the extrapolation limit {limit} s ({int(np.sum(bad))} of {len(tq)} times)"
            )
        out = np.tile(np.eye(4), (len(tq), 1, 1))
        if len(self) == 1:
            out[:] = self.T[0]
            return out

        inside = ~(lo | hi)
        if np.any(inside):
            ti = tq[inside]
            k = np.clip(np.searchsorted(self.timestamps, ti, side="right") - 1, 0, len(self) - 2)
            ta, tb_ = self.timestamps[k], self.timestamps[k + 1]
            w = ((ti - ta) / (tb_ - ta))[:, None]
            p = (1.0 - w) * self.T[k, :3, 3] + w * self.T[k + 1, :3, 3]
            if self._slerp is None:
                self._slerp = Slerp(self.timestamps, self._rotations)
            out[inside, :3, :3] = self._slerp(ti).as_matrix()
            out[inside, :3, 3] = p
        for mask, ia, ib in ((lo, 0, 1), (hi, -1, -2)):
            if not np.any(mask):
                continue
            # Constant velocity from the end sample ia, using the neighbouring sample ib.
            dt_ab = self.timestamps[ib] - self.timestamps[ia]
            s = (tq[mask] - self.timestamps[ia]) / dt_ab  # fraction of the end interval
            p_a, p_b = self.T[ia, :3, 3], self.T[ib, :3, 3]
            out[mask, :3, 3] = p_a + s[:, None] * (p_b - p_a)
            R_a = self._rotations[ia]
            rotvec_ab = (R_a.inv() * self._rotations[ib]).as_rotvec()  # body frame of a
            out[mask, :3, :3] = (R_a * Rotation.from_rotvec(s[:, None] * rotvec_ab)).as_matrix()
        return out

    # -- comparison -------------------------------------------------------------------------

    def relative_errors(
        self, other: PoseTrack, max_extrapolation_s: float = 0.0
    ) -> tuple[F64, F64]:
        """Per-sample errors of this track against ``other`` at this track's timestamps.

        ``other`` is evaluated at ``self.timestamps`` (exactly when the timestamps coincide,
        else interpolated, extrapolating at most ``max_extrapolation_s``).

        Returns
        -------
        translation error (n,) m = ||p_self - p_other||, rotation error (n,) deg = angle of
        ``R_other^T R_self``.
        """
        if len(other) == len(self) and np.array_equal(other.timestamps, self.timestamps):
            T_other = other.T
        else:
            T_other = other.interpolate(self.timestamps, max_extrapolation_s=max_extrapolation_s)
        dt = np.linalg.norm(self.T[:, :3, 3] - T_other[:, :3, 3], axis=1)
        R_err = np.swapaxes(T_other[:, :3, :3], -1, -2) @ self.T[:, :3, :3]
        dr = np.degrees(Rotation.from_matrix(R_err).magnitude())
        return dt, dr

    # -- CSV --------------------------------------------------------------------------------

    def to_csv(
        self,
        path: str | Path,
        frame_idx: ArrayLike | None = None,
        timestamp_text: dict[int, str] | None = None,
    ) -> None:
        """Write ``frame_idx,timestamp,x,y,z,qx,qy,qz,qw`` (ground_truth/poses.csv format).

        Timestamps with 9 decimals (:func:`format_timestamp`), or, for the frames that
        ``timestamp_text`` ({frame_idx: text}) has, that text exactly as the input wrote it
        (a float64 near 1.6e9 s keeps only ~0.24 us); positions and quaternions with full
        ``repr`` precision. ``frame_idx`` (n,) defaults to the track's own ``frame_idx``,
        else -1 for every row (a dense track whose samples are not frames).
        """
        fi = self.frame_idx if frame_idx is None else np.asarray(frame_idx, dtype=np.int64)
        if fi is None:
            fi = np.full(len(self), -1, dtype=np.int64)  # samples that are not frames
        fi = np.asarray(fi, dtype=np.int64).reshape(-1)
        if fi.shape != self.timestamps.shape:
            raise ValueError(f"frame_idx must have {len(self)} entries, got {fi.shape}")
        p, q = self.T[:, :3, 3], self.quaternions
        path = Path(path)
        with path.open("w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(POSES_CSV_COLUMNS)
            for i in range(len(self)):
                text = (timestamp_text or {}).get(int(fi[i]))
                if text is None or abs(float(text) - self.timestamps[i]) > 1e-6:
                    text = format_timestamp(self.timestamps[i])
                w.writerow(
                    [int(fi[i]), text]
                    + [repr(float(v)) for v in p[i]]
                    + [repr(float(v)) for v in q[i]]
                )

    @classmethod
    def from_csv(cls, path: str | Path) -> PoseTrack:
        """Read a file written by :meth:`to_csv` (``frame_idx`` is kept on the track)."""
        path = Path(path)
        with path.open(newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or tuple(h.strip() for h in header) != POSES_CSV_COLUMNS:
                raise ValueError(
                    f"{path}: expected header {','.join(POSES_CSV_COLUMNS)}, got {header}"
                )
            rows = [r for r in reader if r]
        if not rows:
            raise ValueError(f"{path}: no poses")
        try:
            fi = np.array([int(r[0]) for r in rows], dtype=np.int64)
            vals = np.array([[float(v) for v in r[1:]] for r in rows], dtype=np.float64)
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}: malformed poses row: {exc}") from exc
        if vals.shape[1] != 8:
            raise ValueError(f"{path}: expected 9 columns per row")
        return cls.from_positions_quaternions(vals[:, 0], vals[:, 1:4], vals[:, 4:8], fi)


def reexpress(track: PoseTrack, from_world: WorldFrame, to_world: WorldFrame) -> PoseTrack:
    """Re-express poses given in the world frame ``from_world`` in ``to_world`` (exact)."""
    return track.transformed(to_world.T_world_other(from_world))


# --------------------------------------------------------------------------------------------
# INS -> poses
# --------------------------------------------------------------------------------------------
